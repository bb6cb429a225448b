"""The cameras given to the wrong videos (a calibration matched by order): found from the tracks, the order that fits
named in one line, before the solve; right cameras, moving cameras and a rig whose swap is a mirror pass."""

from __future__ import annotations

import dataclasses
import importlib.util
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from dynrecon.cli import main
from dynrecon.errors import InputError
from reconstruct import camera_order
from reconstruct.camera_order import CameraOrder, check_camera_order, score_camera_order
from reconstruct.solver.problem import Problem
from sfm.cameras import CameraSet, FrameCamera, VideoCameras, write_cameras
from tracking.tracks import Tracks, write_tracks

_spec = importlib.util.spec_from_file_location("clock_scenes", Path(__file__).parent / "clocks" / "test_clocks.py")
assert _spec is not None and _spec.loader is not None
scenes = importlib.util.module_from_spec(_spec)
sys.modules.setdefault("clock_scenes", scenes)  # dataclasses look their module up there
_spec.loader.exec_module(scenes)

CLOCKS = [
    scenes.ClockTruth(fps=30.0, frames=90),
    scenes.ClockTruth(fps=30.0, frames=90, offset=0.3),
    scenes.ClockTruth(fps=25.0, frames=75, offset=-0.2),
    scenes.ClockTruth(fps=30.0, frames=90, offset=0.5),
]


def _capture(seed: int = 4) -> Problem:
    """Four static cameras at uneven azimuths, heights, distances and focals around six moving points (a ring of
    like cameras at even angles would make some orders a rotation or mirror of the rig: equally right)."""
    problem, _, X = scenes.make_capture(CLOCKS, points=6, distance=8.0, noise_px=0.0, seed=seed)
    rng = np.random.default_rng(seed)
    K, R, t = problem.K.copy(), problem.R.copy(), problem.t.copy()
    setups = zip(
        (0.2, 1.9, 3.3, 4.6), (1.2, 2.4, 0.6, 1.8), (7.0, 9.0, 8.0, 6.0), (1400.0, 1600, 1500, 1700), strict=True
    )
    for v, (azimuth, height, distance, focal) in enumerate(setups):
        rows = problem.video_index == v
        centre = np.array([distance * np.cos(azimuth), distance * np.sin(azimuth), height])
        K[rows, 0, 0] = K[rows, 1, 1] = focal
        R[rows] = scenes.look_at(centre, np.array([0.0, 0.0, 1.0]))
        t[rows] = -R[rows][0] @ centre
    cam = np.einsum("fij,fpj->fpi", R, X) + t[:, None, :]
    uv = np.einsum("fij,fpj->fpi", K, cam)
    uv = uv[..., :2] / uv[..., 2:3] + rng.normal(scale=0.5, size=(*uv.shape[:2], 2))
    return dataclasses.replace(problem, K=K, R=R, t=t, uv=uv)


def _moved(problem: Problem, order: list[int]) -> Problem:
    """Video v given the camera of video order[v]."""
    first = [int(np.flatnonzero(problem.video_index == v)[0]) for v in range(len(problem.video_names))]
    K, R, t = problem.K.copy(), problem.R.copy(), problem.t.copy()
    for v, c in enumerate(order):
        rows = problem.video_index == v
        K[rows], R[rows], t[rows] = problem.K[first[c]], problem.R[first[c]], problem.t[first[c]]
    return dataclasses.replace(problem, K=K, R=R, t=t)


def test_right_cameras_pass_at_the_cost_of_the_pairs() -> None:
    problem = _capture()
    found = check_camera_order(problem, None)
    assert found is not None and not found.swapped
    assert max(found.given_costs) < 2.0 and found.best_costs == found.given_costs


@pytest.mark.parametrize("order", [[1, 0, 2, 3], [3, 0, 1, 2], [0, 2, 3, 1]])
def test_the_order_that_fits_is_named(order: list[int]) -> None:
    """A swap, a cycle of all four and a cycle of three: each video's camera found, and the order to import in."""
    problem = _capture()
    wrong = _moved(problem, order)
    found = score_camera_order(wrong)
    assert found is not None
    assert [order[c] for c in found.order] == [0, 1, 2, 3]  # composing the two gives each video its own camera
    with pytest.raises(InputError) as raised:
        check_camera_order(wrong, Path("ws/cameras.json"))
    message = str(raised.value)
    assert message.startswith("ws/cameras.json: the cameras fit these tracks in another order") and "\n" not in message
    # the k-th camera of the import goes to the video whose own camera it is
    wanted = [problem.video_names[order[k]] for k in range(4)]
    assert f"in the order {' '.join(wanted)})" in message


def test_videos_without_tracks_keep_their_cameras() -> None:
    """Two of four videos without tracks: nothing tells their cameras apart, so only the tracked videos' cameras are
    reordered, and their swap is named (not a tie with a swap of the untracked ones); a solve of some of the
    cameras file's videos is not told an order to import in."""
    problem = _moved(_capture(), [1, 0, 2, 3])
    problem.uv[problem.video_index >= 2] = np.nan
    found = score_camera_order(problem)
    assert found is not None and found.order == (1, 0, 2, 3)
    with pytest.raises(InputError) as raised:
        check_camera_order(problem, None, every_video=[*problem.video_names, "cam4"])
    message = str(raised.value)
    assert "cam0 fits cam1's camera, cam1 fits cam0's camera (" in message
    assert "in the order" not in message and "give each video its own camera" in message


def test_two_orders_fitting_alike_are_warned_about_not_refused(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """Where a second order fits about as well as the best (a rig whose swap is nearly a rotation or mirror of it),
    neither is named as the fix: a warning names both and the solve goes on."""
    problem = _capture()
    scored = CameraOrder(
        order=(1, 0, 2, 3),
        given_costs=[40.0] * 6,
        best_costs=[2.0] * 6,
        cap=64.0,
        runner_up=(2, 3, 0, 1),
        runner_up_costs=[2.5] * 6,
    )
    monkeypatch.setattr(camera_order, "score_camera_order", lambda *_: scored)
    assert check_camera_order(problem, Path("cameras.json")) is scored
    assert "two about as well (cam0 fits cam1's camera, cam1 fits cam0's camera; cam0 fits cam2's camera" in caplog.text


def test_moving_cameras_are_not_tested() -> None:
    problem, _, _ = scenes.make_capture(CLOCKS[:3], points=6, distance=8.0, handheld=True, seed=1)
    assert score_camera_order(problem) is None


def _write(problem: Problem, folder: Path) -> None:
    """cameras.json (1920 x 1080 videos, every frame with its decoder time) and tracks.csv of `problem`."""
    videos = []
    for v, name in enumerate(problem.video_names):
        rows = np.flatnonzero(problem.video_index == v)
        frames = [
            FrameCamera(
                frame=int(problem.frames[r]), K=problem.K[r], R=problem.R[r], t=problem.t[r], time=problem.times[r]
            )
            for r in rows
        ]
        videos.append(VideoCameras(name=name, width=1920, height=1080, frames=frames))
    write_cameras(folder / "cameras.json", CameraSet(videos=videos))
    observed = np.argwhere(problem.observed)
    rows = [
        (problem.video_names[problem.video_index[f]], int(problem.frames[f]), problem.point_names[p], *problem.uv[f, p])
        for f, p in observed
    ]
    write_tracks(folder / "tracks.csv", Tracks.from_rows(rows))


def test_solve_refuses_swapped_cameras_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`dynrecon solve` on a cameras.json whose cam0 and cam2 are swapped: exit 2, one line, nothing written."""
    _write(_moved(_capture(), [2, 1, 0, 3]), tmp_path)
    args = ["--cameras", str(tmp_path / "cameras.json"), "--tracks", str(tmp_path / "tracks.csv")]
    assert main(["solve", *args, "--out", str(tmp_path / "out")]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "cam0 fits cam2's camera, cam2 fits cam0's camera" in error, error
    assert "in the order cam2 cam1 cam0 cam3" in error
    assert not (tmp_path / "out").exists()


def test_the_misfit_warning_names_the_pair_that_fits_best(caplog: pytest.LogCaptureFixture) -> None:
    """Where no pair of videos brings its rays together (every camera given to another video here; on a real
    four-camera lab, a detector that picked another person in two videos, 2026-11-30), the clock search's warning
    names the pair that fits best and how to solve it alone."""
    import logging

    from reconstruct.clocks import search
    from reconstruct.clocks.model import own_times

    problem = _moved(_capture(), [1, 2, 3, 0])
    own, _ = own_times(problem)
    search._MISFITS_SAID.clear()  # said once per process and costs
    with caplog.at_level(logging.WARNING):
        search.search_clocks(problem, own, 0)
    costs = re.search(r"truncated mean squared gaps ([\d, ]+) px\^2", caplog.text)
    assert costs is not None, caplog.text
    best = min(int(c) for c in costs.group(1).split(", "))
    named = re.search(
        r"The pair that fits best, (cam\d) and (cam\d) \((\d+) px\^2\), can be solved alone with "
        r"--videos (cam\d),(cam\d)",
        caplog.text,
    )
    assert named is not None and int(named.group(3)) == best and named.group(1, 2) == named.group(4, 5)
