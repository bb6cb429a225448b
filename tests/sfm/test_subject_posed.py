"""Videos the background posed (a handheld phone) as the subject path's world (`sfm.subject.posed`, and
`pose_from_subject` joining them), against synthetic ground truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest

from sfm.frames import Resize
from sfm.options import RegisterOptions
from sfm.plan import FramePose, VideoPlan
from sfm.register_posed import posed_video
from sfm.register_subject import pose_from_subject
from sfm.subject import SubjectCalibrationError, SubjectResult, calibrate_from_subject
from sfm.subject.posed import align_to_posed
from sfm.subject.synthetic import Handheld, Truth, handheld, make_rig
from sfm.video import ProbedVideo
from tracking.tracks import Tracks, join_tracks

DURATION = 12.0


@pytest.fixture(scope="module")
def rig() -> tuple[Tracks, list, Truth]:
    return make_rig(kind="skeleton", n_cameras=4, duration=DURATION, noise_px=0.7, seed=0)


@pytest.fixture(scope="module")
def solved(rig: tuple[Tracks, list, Truth]) -> SubjectResult:
    tracks, videos, _ = rig
    return calibrate_from_subject(tracks, videos)


def _plan(name: str, times: np.ndarray, static: bool) -> VideoPlan:
    return VideoPlan(
        info=ProbedVideo(path=Path(f"{name}.mp4"), name=name, width=1920, height=1080, times=times, nominal_fps=30.0),
        resize=Resize(scale=1.0, width=1920, height=1080),
        sfm_frames=np.zeros(0, dtype=np.int64),
        wanted=np.arange(len(times)),
        static=static,
    )


def _phone_poses(phone: Handheld) -> dict[int, FramePose]:
    return {
        f: FramePose(
            pose=pycolmap.Rigid3d(pycolmap.Rotation3d(phone.R[f]), phone.t[f]),
            source="sfm",
            intrinsics=(phone.K, None),
        )
        for f in range(len(phone.times))
    }


def _errors(cameras: dict[str, tuple[np.ndarray, np.ndarray]], truth: Truth) -> tuple[float, float]:
    """Largest centre error (% of the camera spread) and rotation error (deg), in the true world: no similarity."""
    centres = truth.centres()
    spread = float(np.linalg.norm(centres - centres.mean(0), axis=1).max())
    centre, rotation = 0.0, 0.0
    for name, (R, t) in cameras.items():
        i = truth.names.index(name)
        centre = max(centre, float(np.linalg.norm(-R.T @ t - centres[i])) / spread * 100)
        cos = np.clip((np.trace(R @ truth.R[i].T) - 1) / 2, -1, 1)
        rotation = max(rotation, float(np.degrees(np.arccos(cos))))
    return centre, rotation


def test_a_handheld_phone_puts_the_static_cameras_in_its_world(
    rig: tuple[Tracks, list, Truth], solved: SubjectResult
) -> None:
    """The background posed a handheld phone walking a 40 deg arc: its tracks fix the similarity (scale included)
    and its clock offset, so the static cameras land in its world without any fitted similarity."""
    _, _, truth = rig
    phone = handheld(duration=DURATION, offset=0.61, arc_deg=40.0)
    # its columns in another order than the trajectory's (a fold's points come in another order): matched by name
    points = list(solved.points)[::-1]
    video = posed_video(_plan("phone", phone.times, False), _phone_poses(phone), phone.tracks, points)
    result = SubjectResult(**{**solved.__dict__, "points": dict(solved.points)})
    result.cameras = [type(c)(**c.__dict__) for c in solved.cameras]

    alignment = align_to_posed(result, [video])
    alignment.apply(result)

    fit = alignment.fits[0]
    assert fit.reason is None and abs(fit.offset - phone.offset) < 0.25 / 30 and fit.runner_up_ratio > 1.5
    assert fit.residual_px < 2.0 and alignment.baseline > 0.2 and alignment.scale_error < 0.005
    centre, rotation = _errors({c.name: (c.R, c.t) for c in result.cameras}, truth)
    assert centre < 2.0 and rotation < 1.0
    assert result.metric


def test_a_phone_that_does_not_move_is_refused(solved: SubjectResult) -> None:
    """One fixed viewpoint sees the trajectory's shape but not its size: refused, and the message says so."""
    phone = handheld(duration=DURATION, arc_deg=0.0, sway_m=0.0)
    video = posed_video(_plan("phone", phone.times, False), _phone_poses(phone), phone.tracks, list(solved.points))
    with pytest.raises(
        SubjectCalibrationError, match=r"do not fix the subject path's scale: their cameras move 0\.0 %"
    ):
        align_to_posed(solved, [video])


def test_tracks_of_another_subject_are_refused(solved: SubjectResult) -> None:
    """The phone's tracks name the same points but follow another motion (a labeling mix-up): nothing agrees."""
    phone = handheld(duration=DURATION, arc_deg=40.0)
    names = sorted(set(phone.tracks.point))
    swapped = {p: names[(i + 3) % len(names)] for i, p in enumerate(names)}
    tracks = Tracks.from_rows(
        [
            (v, int(f), swapped[p], float(x), float(y))
            for v, f, p, (x, y) in zip(
                phone.tracks.video, phone.tracks.frame, phone.tracks.point, phone.tracks.xy, strict=True
            )
        ]
    )
    video = posed_video(_plan("phone", phone.times, False), _phone_poses(phone), tracks, list(solved.points))
    with pytest.raises(SubjectCalibrationError, match="phone"):
        align_to_posed(solved, [video])


@pytest.mark.slow
def test_register_joins_static_cameras_to_a_handheld_phone(rig: tuple[Tracks, list, Truth]) -> None:
    """`pose_from_subject` when the background posed only the handheld phone: the static videos it left out are
    posed in the phone's world (metric), the report says which videos anchored it, and the phone keeps its poses.
    The phone films 6-10 s longer at each end than the static cameras (only the shared span is adjusted), and a
    --scale is said not to be used (the phone's world sets the scale)."""
    tracks, videos, truth = rig
    phone = handheld(duration=DURATION + 16.0, offset=-8.0, arc_deg=40.0)
    plans = [_plan(v.name, v.times, True) for v in videos] + [_plan("phone", phone.times, False)]
    results = {
        v.name: {f: FramePose(pose=None, reason="not in the background model") for f in range(len(v.times))}
        for v in videos
    }
    results["phone"] = _phone_poses(phone)
    intrinsics = {v.name: (v.K, v.dist) for v in videos}
    warnings: list[str] = []

    options = RegisterOptions(scale=("p0", "p11", 5.0))
    section = pose_from_subject(plans, results, join_tracks(tracks, phone.tracks), intrinsics, options, warnings)

    assert section is not None and section["used"] and section["metric"], (section, warnings)
    assert sorted(section["posed"]) == sorted(v.name for v in videos)
    assert section["stability"]["checked"] and not section["stability"]["unstable"]
    assert warnings == ["--scale: not used: the videos the background posed set the scale (the background's own units)"]
    assert section["units"] is None  # the background's units, not metres
    anchor = section["posed_videos"]["videos"][0]
    assert anchor["name"] == "phone" and anchor["reason"] is None and abs(anchor["offset_s"] + 8.0) < 0.01
    assert anchor["residual_px"] < 1.5
    cameras = {}
    for v in videos:
        pose = results[v.name][0].pose
        assert pose is not None and results[v.name][0].source == "subject"
        cameras[v.name] = (pose.rotation.matrix(), np.asarray(pose.translation))
    centre, rotation = _errors(cameras, truth)
    assert centre < 2.0 and rotation < 1.0
    assert results["phone"][5].pose is not None and results["phone"][5].source == "sfm"


@pytest.mark.slow
def test_one_static_anchor_and_a_phone(rig: tuple[Tracks, list, Truth]) -> None:
    """The background posed one static video and the phone: the static anchor keeps the background's pose, the
    phone fixes the scale, and the other static videos land in their world."""
    tracks, videos, truth = rig
    phone = handheld(duration=DURATION, offset=0.61, arc_deg=40.0)
    plans = [_plan(v.name, v.times, True) for v in videos] + [_plan("phone", phone.times, False)]
    results = {
        v.name: {f: FramePose(pose=None, reason="not in the background model") for f in range(len(v.times))}
        for v in videos[1:]
    }
    anchor = pycolmap.Rigid3d(pycolmap.Rotation3d(truth.R[0]), truth.t[0])
    results[videos[0].name] = dict.fromkeys(range(len(videos[0].times)), FramePose(pose=anchor, source="sfm"))
    results["phone"] = _phone_poses(phone)
    intrinsics = {v.name: (v.K, v.dist) for v in videos}
    warnings: list[str] = []

    section = pose_from_subject(
        plans, results, join_tracks(tracks, phone.tracks), intrinsics, RegisterOptions(), warnings
    )

    assert section is not None and section["used"] and section["anchors"] == [videos[0].name], (section, warnings)
    assert sorted(v["name"] for v in section["posed_videos"]["videos"]) == sorted([videos[0].name, "phone"])
    assert results[videos[0].name][0].pose is not None and results[videos[0].name][0].source == "sfm"
    cameras = {}
    for v in videos[1:]:
        pose = results[v.name][0].pose
        assert pose is not None
        cameras[v.name] = (pose.rotation.matrix(), np.asarray(pose.translation))
    centre, rotation = _errors(cameras, truth)
    assert centre < 2.0 and rotation < 1.0
