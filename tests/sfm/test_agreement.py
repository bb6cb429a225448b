"""The background's static poses checked against the moving subject (`sfm.subject.agreement`, `sfm.register_check`),
on synthetic rigs with known truth and on the real rigs of ../shared with their own calibrations."""

from __future__ import annotations

import copy
import hashlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

import sfm.subject.agreement
from sfm.frames import Resize
from sfm.options import RegisterOptions
from sfm.plan import FramePose, VideoPlan
from sfm.register_check import TWO_VIEWS_WHY, background_left, check_background, refuse_two_view_focals
from sfm.register_subject import pose_from_subject
from sfm.subject import SubjectVideo
from sfm.subject.agreement import check_agreement
from sfm.subject.observations import VideoObs
from sfm.subject.pairs import PairFit, fit_pair
from sfm.subject.synthetic import Truth, make_rig
from sfm.video import ProbedVideo
from tracking.tracks import Tracks


def _key(*parts: Any) -> str:
    digest = hashlib.sha1()
    for part in parts:
        if isinstance(part, VideoObs):
            arrays = (part.norm, part.times, part.K, part.xy)
            digest.update(repr((part.name, part.period, part.known_K, part.video.width, part.video.height)).encode())
            for array in arrays:
                digest.update(np.ascontiguousarray(array).tobytes())
        else:
            digest.update(repr(part).encode())
    return digest.hexdigest()


@pytest.fixture(scope="module", autouse=True)
def _tracks_fitted_once() -> Iterator[None]:
    """The tracks' own pair geometry does not depend on the poses checked: this module checks many poses against
    the same tracks, so each pair is fitted once (exactly: keyed on every input, the random state included, which
    a hit advances as the fit would have)."""
    memo: dict[str, tuple[PairFit, dict]] = {}

    def fitted(oa: VideoObs, ob: VideoObs, a: int, b: int, max_offset: float, rng: np.random.Generator) -> PairFit:
        key = _key(oa, ob, a, b, max_offset, rng.bit_generator.state)
        if key not in memo:
            memo[key] = (fit_pair(oa, ob, a, b, max_offset, rng), rng.bit_generator.state)
        fit, state = memo[key]
        rng.bit_generator.state = state
        return copy.deepcopy(fit)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(sfm.subject.agreement, "fit_pair", fitted)
        yield


@pytest.fixture(scope="module")
def rig() -> tuple[Tracks, list[SubjectVideo], Truth]:
    return make_rig(kind="skeleton", n_cameras=4, duration=12.0, noise_px=0.7, seed=3)


def _turned(R: np.ndarray, t: np.ndarray, degrees: float, axis: tuple[float, float, float]) -> tuple:
    """The pose turned about its own centre by `degrees` about `axis` (world)."""
    centre = -R.T @ t
    turned = Rotation.from_rotvec(np.radians(degrees) * np.asarray(axis) / np.linalg.norm(axis)).as_matrix() @ R
    return turned, -turned @ centre


def _posed(videos: list[SubjectVideo], truth: Truth, wrong: dict[str, tuple] | None = None) -> list[SubjectVideo]:
    wrong = wrong or {}
    out = []
    for video in videos:
        index = truth.names.index(video.name)
        pose = wrong.get(video.name, (truth.R[index], truth.t[index]))
        out.append(SubjectVideo(**{**vars(video), "cam_from_world": pose}))
    return out


def test_the_true_poses_agree_with_the_subject(rig: tuple[Tracks, list[SubjectVideo], Truth]) -> None:
    tracks, videos, truth = rig
    result = check_agreement(tracks, _posed(videos, truth))
    assert result.refuted == {}
    assert len(result.pairs) == 6 and all(p.checked for p in result.pairs), result.to_json()
    for pair in result.pairs:
        assert pair.poses_px is not None and pair.tracks_px is not None
        assert pair.poses_px < 2 * pair.tracks_px + 0.5, pair  # the truth fits as well as the tracks' own geometry
        index = {n: i for i, n in enumerate(truth.names)}
        true = truth.offsets[index[pair.b]] - truth.offsets[index[pair.a]]
        # the tracks' pair offset, before any chaining or bundle: within a frame of the slower video
        frame = max(truth.periods[index[pair.a]], truth.periods[index[pair.b]])
        assert abs(pair.offset_s - true) < frame, pair  # type: ignore[operator]


@pytest.mark.parametrize("degrees", [5.0, 15.0, 40.0])
def test_a_turned_camera_is_refuted_and_only_it(rig: tuple[Tracks, list[SubjectVideo], Truth], degrees: float) -> None:
    tracks, videos, truth = rig
    wrong = {"cam2": _turned(truth.R[2], truth.t[2], degrees, (0.3, 1.0, 0.2))}
    result = check_agreement(tracks, _posed(videos, truth, wrong))
    assert list(result.refuted) == ["cam2"], result.to_json()
    assert "contradicts the subject's tracks" in result.refuted["cam2"]
    contradicted = {(p.a, p.b) for p in result.pairs if p.contradicted}
    assert contradicted and all("cam2" in pair for pair in contradicted)


def test_a_moved_camera_centre_is_refuted(rig: tuple[Tracks, list[SubjectVideo], Truth]) -> None:
    tracks, videos, truth = rig
    R, t = truth.R[1], truth.t[1]
    spread = np.ptp(truth.centres(), axis=0).max()
    centre = -R.T @ t + np.array([0.0, 0.5, 0.2]) * spread  # a baseline half the rig off
    result = check_agreement(tracks, _posed(videos, truth, {"cam1": (R, -R @ centre)}))
    assert list(result.refuted) == ["cam1"], result.to_json()


def test_intrinsics_that_are_no_lens_are_refuted(rig: tuple[Tracks, list[SubjectVideo], Truth]) -> None:
    """pycolmap's defaults on the office backgrounds fit focals of 3,000-400,000 px to 1280 px webcams."""
    tracks, videos, truth = rig
    posed = _posed(videos, truth)
    K = posed[1].K.copy()  # type: ignore[union-attr]
    K[0, 0] = K[1, 1] = 100 * max(posed[1].width, posed[1].height)
    posed[1] = SubjectVideo(**{**vars(posed[1]), "K": K})
    result = check_agreement(tracks, posed)
    assert list(result.refuted) == ["cam1"] and "no lens" in result.refuted["cam1"]
    assert all(p.checked != ("cam1" in (p.a, p.b)) for p in result.pairs)  # the others are still checked


def test_a_lone_wrong_pair_refutes_both(rig: tuple[Tracks, list[SubjectVideo], Truth]) -> None:
    """Two cameras: which of them is wrong cannot be told, so neither pose is kept."""
    tracks, videos, truth = rig
    two = _posed(videos[:2], truth, {"cam1": _turned(truth.R[1], truth.t[1], 20.0, (1.0, 0.0, 0.0))})
    result = check_agreement(tracks, two)
    assert sorted(result.refuted) == ["cam0", "cam1"]


def test_a_subject_on_a_line_checks_nothing() -> None:
    """Correspondences on a line determine no epipolar geometry: the pair is not checked, and nothing refuted."""
    tracks, videos, truth = make_rig(kind="line", n_cameras=3, duration=10.0, noise_px=1.0, seed=1)
    wrong = {"cam1": _turned(truth.R[1], truth.t[1], 30.0, (0.0, 1.0, 0.0))}
    result = check_agreement(tracks, _posed(videos, truth, wrong))
    assert result.refuted == {}
    assert not any(p.checked for p in result.pairs) and all(p.why for p in result.pairs)


def test_offsets_the_tracks_do_not_single_out_check_nothing() -> None:
    """One tracked point, or tracks that never overlap at the true offset: the pair's best offset pairs other
    instants, which the tracks' own geometry fits and the true poses do not. Such pairs are not checked."""

    tracks, videos, truth = make_rig(kind="skeleton", n_cameras=3, duration=6.0, noise_px=0.7, seed=3)
    right = _posed(videos, truth)
    one_point = tracks.take(np.flatnonzero(np.array([p == tracks.point_names()[0] for p in tracks.point])))
    apart = np.array(
        [
            not (
                (v == "cam0" and f < len(videos[0].times) // 2 + 30) or (v == "cam1" and f > len(videos[1].times) // 4)
            )
            for v, f in zip(tracks.video, tracks.frame, strict=True)
        ]
    )
    for part in (one_point, tracks.take(np.flatnonzero(apart))):
        result = check_agreement(part, right)
        assert result.refuted == {}, result.to_json()


# ---------------------------------------------------------------------------------------------------------------
# register's wiring: a refuted background pose goes, and the subject path poses that camera


def _plan(video: SubjectVideo) -> VideoPlan:
    info = ProbedVideo(
        path=Path(f"{video.name}.mp4"),
        name=video.name,
        width=video.width,
        height=video.height,
        times=np.asarray(video.times),
        nominal_fps=None,
    )
    return VideoPlan(
        info=info,
        resize=Resize(scale=1.0, width=video.width, height=video.height),
        sfm_frames=np.zeros(0, dtype=np.int64),
        wanted=np.arange(len(video.times)),
        static=True,
    )


def _background(video: SubjectVideo, pose: tuple[np.ndarray, np.ndarray]) -> dict[int, FramePose]:
    frame_pose = FramePose(
        pose=pycolmap.Rigid3d(pycolmap.Rotation3d(pose[0]), np.asarray(pose[1], dtype=float)),
        source="static",
        intrinsics=(video.K, video.dist),
    )
    return dict.fromkeys(range(len(video.times)), frame_pose)


@pytest.mark.slow
def test_register_drops_a_refuted_background_pose_and_poses_it_from_the_subject(
    rig: tuple[Tracks, list[SubjectVideo], Truth],
) -> None:
    tracks, videos, truth = rig
    plans = [_plan(v) for v in videos]
    wrong = _turned(truth.R[3], truth.t[3], 12.0, (0.2, 1.0, 0.0))
    poses = {v.name: (R, t) for v, R, t in zip(videos, truth.R, truth.t, strict=True)} | {"cam3": wrong}
    results = {v.name: _background(v, poses[v.name]) for v in videos}
    warnings: list[str] = []

    section = check_background(plans, results, tracks, warnings)

    assert section is not None and section["checked"] and list(section["refuted"]) == ["cam3"]
    assert all(r.pose is None and "contradicts" in (r.reason or "") for r in results["cam3"].values())
    assert any("cam3: the background's pose is not used" in w for w in warnings)
    assert background_left(plans, results)

    subject = pose_from_subject(plans, results, tracks, {}, RegisterOptions(), warnings)

    assert subject is not None and subject["used"] and sorted(subject["anchors"]) == ["cam0", "cam1", "cam2"]
    pose = next(iter(results["cam3"].values()))
    assert pose.source == "subject" and pose.pose is not None
    R = pose.pose.rotation.matrix()
    angle = np.degrees(np.arccos(np.clip((np.trace(R @ truth.R[3].T) - 1) / 2, -1, 1)))
    centre_error = np.linalg.norm(-R.T @ np.asarray(pose.pose.translation) - truth.centres()[3])
    spread = np.linalg.norm(truth.centres() - truth.centres().mean(0), axis=1).max()
    assert angle < 0.5 and centre_error < 0.01 * spread, (angle, centre_error / spread)


def test_register_keeps_background_poses_that_agree(rig: tuple[Tracks, list[SubjectVideo], Truth]) -> None:
    tracks, videos, truth = rig
    plans = [_plan(v) for v in videos]
    results = {v.name: _background(v, (R, t)) for v, R, t in zip(videos, truth.R, truth.t, strict=True)}
    before = {name: next(iter(frames.values())) for name, frames in results.items()}

    section = check_background(plans, results, tracks, [])

    assert section is not None and section["checked"] and section["refuted"] == {}
    assert {name: next(iter(frames.values())) for name, frames in results.items()} == before


def test_no_check_without_tracks_or_with_one_posed_static_video(rig: tuple[Tracks, list[SubjectVideo], Truth]) -> None:
    tracks, videos, truth = rig
    plans = [_plan(v) for v in videos]
    results = {v.name: _background(v, (R, t)) for v, R, t in zip(videos, truth.R, truth.t, strict=True)}
    section = check_background(plans, results, None, [])
    assert section is not None and not section["checked"] and "no 2D tracks" in section["why"]
    one_tracked = Tracks.from_rows([("cam0", 0, "p0", 1.0, 2.0)])
    section = check_background(plans, results, one_tracked, [])
    assert section is not None and not section["checked"] and "fewer than two" in section["why"]
    one = {v.name: (_background(v, (truth.R[0], truth.t[0])) if v.name == "cam0" else {}) for v in videos}
    assert check_background(plans, one, tracks, []) is None


# ---------------------------------------------------------------------------------------------------------------
# The real rigs: their own calibrations agree with their subjects; a camera turned far does not


def _check_real(tracks: Tracks, videos: list[SubjectVideo], degrees: float) -> None:
    assert check_agreement(tracks, videos).refuted == {}
    for index, axis in enumerate([(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), (1.0, 1.0, 0.0)]):
        video = videos[index % len(videos)]
        assert video.cam_from_world is not None
        turned = _turned(*video.cam_from_world, degrees, axis)
        wrong = [SubjectVideo(**{**vars(v), "cam_from_world": turned}) if v is video else v for v in videos]
        assert list(check_agreement(tracks, wrong).refuted) == [video.name], (video.name, axis)


@pytest.mark.shared
@pytest.mark.slow
def test_pose2sim_lab_calibration_agrees_with_the_openpose_detections(shared_dir: Path) -> None:
    from benchmarks.background_check import rig

    # joint detections sit 5-7 px from their own epipolar geometry: a 10 degree pan of a camera in this ring moves
    # them mostly along the epipolar lines and passes (docs/registration.md); 20 degrees about any axis does not
    _check_real(*rig("pose2sim", shared_dir / "data" / "videos"), 20.0)


@pytest.mark.shared
@pytest.mark.slow
def test_caliscope_calibration_agrees_with_the_board_corners(shared_dir: Path) -> None:
    from benchmarks.background_check import rig

    _check_real(*rig("caliscope", shared_dir / "data" / "videos"), 10.0)


# ---------------------------------------------------------------------------------------------------------------
# `dynrecon run`: the background registered before the tracks existed; its folder is checked once they do


def _folder(tmp_path: Path, videos: list[SubjectVideo], poses: dict[str, tuple], checked: bool) -> Path:
    import json

    from sfm.cameras import CameraSet, FrameCamera, VideoCameras, write_cameras

    cameras = CameraSet()
    for video in videos:
        R, t = poses[video.name]
        frames = [
            FrameCamera(frame=f, K=video.K, R=R, t=t, time=float(time_s), dist=video.dist)  # type: ignore[arg-type]
            for f, time_s in enumerate(video.times)
        ]
        cameras.videos.append(VideoCameras(name=video.name, width=video.width, height=video.height, frames=frames))
    write_cameras(tmp_path / "cameras.json", cameras)
    report = {
        "videos": [{"name": v.name, "camera": "static", "posed_by": "static (background SfM)"} for v in videos],
        "background_check": {"checked": True} if checked else None,
    }
    (tmp_path / "register_report.json").write_text(json.dumps(report))
    return tmp_path


def test_a_registration_folder_is_checked_once_tracks_exist(
    rig: tuple[Tracks, list[SubjectVideo], Truth], tmp_path: Path
) -> None:
    from sfm.register_check import refuted_in_folder

    tracks, videos, truth = rig
    poses = {v.name: (R, t) for v, R, t in zip(videos, truth.R, truth.t, strict=True)}
    paths = [Path(f"{v.name}.mp4") for v in videos]  # not opened: a static video's cameras.json has every frame's time
    assert refuted_in_folder(_folder(tmp_path / "right", videos, poses, False), tracks, paths) == {}
    poses["cam0"] = _turned(truth.R[0], truth.t[0], 15.0, (0.0, 0.0, 1.0))
    wrong = _folder(tmp_path / "wrong", videos, poses, False)
    assert list(refuted_in_folder(wrong, tracks, paths)) == ["cam0"]
    # where register had the tracks, its own check ran: not again
    assert refuted_in_folder(_folder(tmp_path / "done", videos, poses, True), tracks, paths) == {}


def test_a_two_image_model_of_unknown_focals_poses_nothing(rig: tuple[Tracks, list[SubjectVideo], Truth]) -> None:
    """Two views do not fix two unknown focal lengths (sleap-anipose's mouse: a two-image model's focals came out
    1.6 and 2.6 x the lab's, its baseline 28.7 deg off, and the subject too still to refute it): its poses are
    dropped, every frame saying why; with known intrinsics, or a third image, they stay."""
    _, videos, truth = rig

    def fresh() -> dict[str, dict[int, FramePose]]:
        return {v.name: _background(v, (truth.R[i], truth.t[i])) for i, v in enumerate(videos[:2])}

    results = fresh()
    assert refuse_two_view_focals(2, {"cam0"}, results) == ["cam0", "cam1"]  # one camera's K known: not enough
    assert all(r.pose is None and TWO_VIEWS_WHY in (r.reason or "") for f in results.values() for r in f.values())
    for images, known in ((2, {"cam0", "cam1"}), (3, set()), (None, set())):
        kept = fresh()
        assert refuse_two_view_focals(images, known, kept) == []
        assert all(r.pose is not None for f in kept.values() for r in f.values())
