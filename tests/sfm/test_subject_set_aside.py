"""Setting aside the videos whose tracks spoil the others' poses (`sfm.subject.set_aside`)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from sfm.register_subject import _determined
from sfm.subject import SubjectCamera, SubjectOptions, SubjectResult, SubjectVideo
from sfm.subject.set_aside import largest_determined
from sfm.subject.stability import Stability
from sfm.subject.synthetic import make_rig, other_walker
from tracking.tracks import join_tracks


def _video(name: str, known_K: bool = True) -> SubjectVideo:
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]) if known_K else None
    return SubjectVideo(name=name, width=640, height=480, times=np.arange(10) / 30.0, K=K)


def _scripted(
    unstable_by_group: dict[frozenset[str], dict[str, float]], calls: list[list[str]]
) -> Callable[[list[SubjectVideo]], tuple[SubjectResult, Stability, None]]:
    """A trial whose folds move each camera of a group by the scripted centre change (fraction of the spread)."""

    def trial(some: list[SubjectVideo]) -> tuple[SubjectResult, Stability, None]:
        names = [v.name for v in some]
        calls.append(names)
        moves = unstable_by_group[frozenset(names)]
        cameras = [
            SubjectCamera(
                name=n, K=np.eye(3), dist=None, R=np.eye(3), t=np.zeros(3), offset=0.0, inliers=50, residual_px=1.0
            )
            for n in names
        ]
        stability = Stability(
            centre_folds={n: [moves.get(n, 0.01)] for n in names},
            rotation_folds={n: [0.1] for n in names},
            unstable={n: f"moved {moves[n]:.2f}" for n in names if moves.get(n, 0.0) > 0.1},
        )
        return SubjectResult(cameras=cameras, pairs=[], failed={}, metric=False), stability, None

    return trial


def test_a_rig_whose_cameras_are_all_but_one_determined_is_solved_once() -> None:
    videos = [_video(f"cam{i}") for i in range(4)]
    calls: list[list[str]] = []
    trial = _scripted({frozenset(v.name for v in videos): {"cam3": 0.5}}, calls)

    result, stability, _ = largest_determined(trial, videos)

    assert len(calls) == 1 and result.failed == {} and list(stability.unstable) == ["cam3"]


def test_the_least_determined_video_goes_first_until_the_rest_are_determined() -> None:
    videos = [_video(f"cam{i}") for i in range(4)]
    calls: list[list[str]] = []
    trial = _scripted(
        {
            frozenset({"cam0", "cam1", "cam2", "cam3"}): {"cam0": 0.7, "cam1": 0.2, "cam2": 0.3, "cam3": 0.2},
            frozenset({"cam1", "cam2", "cam3"}): {"cam1": 0.2, "cam2": 0.4, "cam3": 0.2},
            frozenset({"cam1", "cam3"}): {},
        },
        calls,
    )

    result, stability, _ = largest_determined(trial, videos)

    assert calls == [["cam0", "cam1", "cam2", "cam3"], ["cam1", "cam2", "cam3"], ["cam1", "cam3"]]
    assert [c.name for c in result.cameras] == ["cam1", "cam3"] and not stability.unstable
    assert sorted(result.failed) == ["cam0", "cam2"] and result.set_aside == ["cam0", "cam2"]
    assert result.failed["cam0"].startswith("set aside: solved with the other videos, its camera was moved 0.70;")
    assert "without cam0, cam2, 2 camera(s) are determined (cam1, cam3)" in result.failed["cam0"]


def test_two_cameras_without_intrinsics_are_not_a_group() -> None:
    """Two cameras' folds compare their relative rotation only, which a wrong self-calibrated focal moves
    consistently: without intrinsics the smallest group is three."""
    videos = [_video(f"cam{i}", known_K=False) for i in range(4)]
    calls: list[list[str]] = []
    trial = _scripted(
        {
            frozenset({"cam0", "cam1", "cam2", "cam3"}): {"cam0": 0.7, "cam1": 0.2, "cam2": 0.3, "cam3": 0.2},
            frozenset({"cam1", "cam2", "cam3"}): {"cam1": 0.2, "cam2": 0.4, "cam3": 0.2},
        },
        calls,
    )

    result, _, _ = largest_determined(trial, videos)

    assert len(calls) == 2 and len(result.cameras) == 4 and result.failed == {} and result.set_aside == []


def test_a_smaller_group_that_determines_no_more_cameras_is_not_kept_and_anchors_stay() -> None:
    videos = [_video(f"cam{i}") for i in range(4)]
    calls: list[list[str]] = []
    trial = _scripted(
        {
            frozenset({"cam0", "cam1", "cam2", "cam3"}): {"cam0": 0.9, "cam1": 0.5, "cam2": 0.2},
            frozenset({"cam0", "cam2", "cam3"}): {"cam0": 0.9, "cam2": 0.2},
            frozenset({"cam0", "cam3"}): {"cam0": 0.9},
        },
        calls,
    )

    result, _, _ = largest_determined(trial, videos, keep=["cam0"])

    # cam0 (an anchor) is never set aside; without cam1, then cam2, one camera is determined, as in the whole
    assert calls[1:] == [["cam0", "cam2", "cam3"], ["cam0", "cam3"]]
    assert [c.name for c in result.cameras] == ["cam0", "cam1", "cam2", "cam3"] and result.failed == {}


@pytest.mark.slow
def test_two_videos_following_another_person_are_set_aside_and_the_others_posed() -> None:
    """A synthetic rig of four cameras: cam2 and cam3's tracks follow another person walking elsewhere. Solved
    together no camera is determined (the path posed nothing before); one consistent pair is posed, right."""
    tracks, videos, truth = make_rig(kind="skeleton", n_cameras=4, duration=8.0, seed=0)
    other, _, _ = make_rig(kind="skeleton", n_cameras=4, duration=8.0, seed=0, motion=other_walker)
    mixed = join_tracks(tracks.of_videos(["cam0", "cam1"]), other.of_videos(["cam2", "cam3"]))

    result, stability = _determined(mixed, videos, [], SubjectOptions())

    posed = sorted(c.name for c in result.cameras if c.name not in stability.unstable)
    assert posed in (["cam0", "cam1"], ["cam2", "cam3"])
    assert sorted(result.failed) == sorted({"cam0", "cam1", "cam2", "cam3"} - set(posed))
    assert all(why.startswith("set aside") for why in result.failed.values()) and sorted(result.set_aside) == sorted(
        result.failed
    )
    a, b = (result.camera(n) for n in posed)
    assert a is not None and b is not None
    i, j = (truth.names.index(n) for n in posed)
    relative = (b.R @ a.R.T) @ (truth.R[j] @ truth.R[i].T).T
    assert np.degrees(np.arccos(np.clip((np.trace(relative) - 1) / 2, -1, 1))) < 1.0
