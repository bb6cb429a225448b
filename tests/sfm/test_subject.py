"""Static cameras calibrated from a moving subject's tracks (`sfm.subject`), against synthetic ground truth."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from sfm.subject import SubjectCalibrationError, SubjectOptions, calibrate_from_subject
from sfm.subject.geometry import bougnoux
from sfm.subject.model import ScalePointsError
from sfm.subject.synthetic import compare, make_rig
from tracking.tracks import Tracks


def test_bougnoux_recovers_focals() -> None:
    rng = np.random.default_rng(1)
    fa, fb = 1500.0, 900.0
    R = np.array([[0.8, 0.0, 0.6], [0.0, 1.0, 0.0], [-0.6, 0.0, 0.8]])
    t = np.array([-1.0, 0.2, 0.3])
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    F = np.diag([1 / fb, 1 / fb, 1]) @ tx @ R @ np.diag([1 / fa, 1 / fa, 1])
    got = bougnoux(F * rng.uniform(0.5, 2))
    assert got == pytest.approx((fa, fb), rel=1e-6)


def test_known_k_wide_baseline_skeleton() -> None:
    tracks, videos, truth = make_rig(kind="skeleton", n_cameras=4, noise_px=0.7, seed=0)
    result = calibrate_from_subject(tracks, videos, SubjectOptions())
    err = compare(result, truth)
    assert err.posed == 4 and not result.failed
    assert err.centre_pct < 2.0 and err.rotation_deg < 1.0 and err.offset_frames < 0.25
    assert not result.metric


def test_flight_single_point_five_cameras() -> None:
    tracks, videos, truth = make_rig(kind="flight", n_cameras=5, noise_px=1.5, false_rate=0.03, seed=0)
    result = calibrate_from_subject(tracks, videos, SubjectOptions())
    err = compare(result, truth)
    assert err.posed == 5
    assert err.centre_pct < 2.0 and err.rotation_deg < 1.0 and err.offset_frames < 0.25
    # every pair's own offset is right, or it says it is ambiguous; the ratio is >= 1 by construction
    true = dict(zip(truth.names, truth.offsets, strict=True))
    for pair in result.pairs:
        assert pair.runner_up_ratio >= 1.0
        wrong = abs(pair.offset - (true[pair.b] - true[pair.a])) > max(truth.periods)
        assert not wrong or pair.ambiguous, pair


def test_unknown_intrinsics_skeleton() -> None:
    tracks, videos, truth = make_rig(
        kind="skeleton", n_cameras=4, duration=12.0, noise_px=0.7, known_K=False, distortion=False, seed=0
    )
    result = calibrate_from_subject(tracks, videos, SubjectOptions())
    err = compare(result, truth)
    assert err.posed == 4 and not result.failed
    assert err.focal_pct < 2.0 and err.centre_pct < 2.0 and err.rotation_deg < 1.0
    for camera, video in zip(result.cameras, videos, strict=True):  # unknown principal points stay at the centre
        assert camera.name == video.name
        assert np.allclose(camera.K[:2, 2], [(video.width - 1) / 2, (video.height - 1) / 2])


def test_few_distinct_positions_are_refused() -> None:
    # someone balancing on the spot: five markers that barely move explain any epipolar geometry
    tracks, videos, _ = make_rig(kind="sway", n_cameras=4, duration=4.0, fps=(60.0,), seed=8)
    with pytest.raises(SubjectCalibrationError, match="distinct positions"):
        calibrate_from_subject(tracks, videos, SubjectOptions(max_offset=1.0))


def test_anchors_fix_frame_and_scale() -> None:
    tracks, videos, truth = make_rig(kind="skeleton", n_cameras=4, duration=10.0, noise_px=0.7, seed=1)
    for i in (0, 2):
        videos[i].cam_from_world = (truth.R[i].copy(), truth.t[i].copy())
    result = calibrate_from_subject(tracks, videos, SubjectOptions())
    assert result.metric and len(result.cameras) == 4
    spread = float(np.linalg.norm(truth.centres() - truth.centres().mean(0), axis=1).max())
    for cam in result.cameras:
        i = truth.names.index(cam.name)
        if i in (0, 2):  # anchors unchanged
            assert np.allclose(cam.R, truth.R[i]) and np.allclose(cam.t, truth.t[i])
            continue
        # the others in the anchors' frame and metric scale: no similarity applied
        assert np.linalg.norm(cam.centre - truth.centres()[i]) / spread < 0.02
        angle = np.degrees(np.arccos(np.clip((np.trace(cam.R @ truth.R[i].T) - 1) / 2, -1, 1)))
        assert angle < 1.0


@pytest.mark.slow
def test_the_tracks_row_order_does_not_change_the_poses() -> None:
    tracks, videos, _ = make_rig(kind="skeleton", n_cameras=3, duration=6.0, noise_px=1.5, false_rate=0.03, seed=2)
    shuffled = tracks.take(np.random.default_rng(1).permutation(len(tracks)))
    a, b = (calibrate_from_subject(t, videos, SubjectOptions()) for t in (tracks, shuffled))
    assert [c.name for c in a.cameras] == [c.name for c in b.cameras]
    for ca, cb in zip(a.cameras, b.cameras, strict=True):
        np.testing.assert_array_equal(ca.R, cb.R)
        assert ca.offset == cb.offset


def test_tracks_of_every_fourth_frame_of_fast_cameras() -> None:
    # a detector run on every 4th frame of 90-120 fps videos: the tracks' samples are 4 frames apart, and the pairs
    # interpolate across them (before: no pair shared observations at any offset)
    tracks, videos, truth = make_rig(kind="skeleton", n_cameras=3, duration=6.0, fps=(120.0, 100.0, 90.0), seed=2)
    sparse = tracks.take(np.flatnonzero(tracks.frame % 4 == 0))
    result = calibrate_from_subject(sparse, videos, SubjectOptions())
    err = compare(result, truth)
    assert err.posed == 3 and err.centre_pct < 2.0 and err.rotation_deg < 1.0 and err.offset_frames < 1.0


def test_scale_from_two_points_gives_metres() -> None:
    tracks, videos, truth = make_rig(kind="skeleton", n_cameras=3, duration=8.0, seed=2)
    from sfm.subject.synthetic import skeleton_motion

    X = skeleton_motion(np.linspace(0, 8, 50))
    metres = float(np.linalg.norm(X[:, 0] - X[:, 11], axis=1).mean())
    result = calibrate_from_subject(tracks, videos, SubjectOptions(scale=("p0", "p11", metres)))
    assert result.metric
    c = np.array([cam.centre for cam in result.cameras])
    true_c = truth.centres()[[truth.names.index(cam.name) for cam in result.cameras]]
    d_est = np.linalg.norm(c[:, None] - c[None], axis=-1)
    d_true = np.linalg.norm(true_c[:, None] - true_c[None], axis=-1)
    assert d_est == pytest.approx(d_true, rel=0.03, abs=0.05)


def test_scale_points_never_seen_at_one_time_are_their_own_error() -> None:
    # p11 is seen by cam0 only in the first half and by cam1 only in the second: never triangulated together with
    # p0, so the scale (not the poses) fails, with an error `register --board` can fall back from.
    tracks, videos, _ = make_rig(kind="skeleton", n_cameras=3, duration=8.0, seed=2)
    point, video, frame = np.asarray(tracks.point), np.asarray(tracks.video), np.asarray(tracks.frame)
    half = np.array([len(next(v for v in videos if v.name == name).times) // 2 for name in video])
    drop = (point == "p11") & (
        (video == "cam2") | ((video == "cam0") & (frame >= half)) | ((video == "cam1") & (frame < half))
    )
    kept = tracks.take(np.flatnonzero(~drop))
    with pytest.raises(ScalePointsError, match="never triangulated together"):
        calibrate_from_subject(kept, videos, SubjectOptions(scale=("p0", "p11", 1.0)))


def test_video_without_time_overlap_fails_alone() -> None:
    tracks, videos, _ = make_rig(kind="skeleton", n_cameras=3, duration=8.0, seed=3)
    # a fourth video whose tracks start 30 s after the others' end
    late = [i for i, v in enumerate(tracks.video) if v == "cam1"]
    shift = int(np.ceil(40.0 * 30))
    rows = [
        (tracks.video[i], int(tracks.frame[i]), tracks.point[i], *map(float, tracks.xy[i])) for i in range(len(tracks))
    ]
    rows += [("late", int(tracks.frame[i]) + shift, tracks.point[i], *map(float, tracks.xy[i])) for i in late]
    from sfm.subject import SubjectVideo

    v1 = videos[1]
    videos.append(
        SubjectVideo(
            name="late",
            width=v1.width,
            height=v1.height,
            times=np.arange(len(v1.times) + shift) / 30.0,
            K=v1.K,
            dist=v1.dist,
        )
    )
    result = calibrate_from_subject(Tracks.from_rows(rows), videos, SubjectOptions(max_offset=5.0))
    assert "late" in result.failed and "overlap" in result.failed["late"]
    assert len(result.cameras) == 3


def test_single_point_too_few_frames() -> None:
    tracks, videos, _ = make_rig(kind="flight", n_cameras=3, duration=0.4, offsets=(0.0, 0.05, -0.05), seed=4)
    with pytest.raises(SubjectCalibrationError, match="shares"):
        calibrate_from_subject(tracks, videos, SubjectOptions(max_offset=1.0))


def test_motion_on_a_line_is_degenerate() -> None:
    tracks, videos, _ = make_rig(kind="line", n_cameras=3, duration=10.0, seed=5)
    with pytest.raises(SubjectCalibrationError, match=r"degenerate motion.*line"):
        calibrate_from_subject(tracks, videos, SubjectOptions(max_offset=3.0))


def test_unknown_scale_point_name() -> None:
    tracks, videos, _ = make_rig(kind="skeleton", n_cameras=2, duration=2.0, seed=6)
    with pytest.raises(SubjectCalibrationError, match="nose"):
        calibrate_from_subject(tracks, videos, SubjectOptions(scale=("nose", "p1", 1.0)))


def test_declared_synchronization_is_tested_per_pair() -> None:
    """A triggered rig's claim (`register --synchronized`: every clock at 0) holds on every pair of a synchronized
    rig; on a rig whose clocks differ by seconds every pair contradicts it, the searched offsets are used, and the
    cameras and clocks come out right."""
    tracks, videos, truth = make_rig(kind="skeleton", n_cameras=3, duration=8.0, offsets=(0.0, 0.0, 0.0), seed=2)
    claim = SubjectOptions(claimed_offsets={v.name: 0.0 for v in videos})
    result = calibrate_from_subject(tracks, videos, claim)
    assert [p.claim for p in result.pairs] == ["held"] * 3
    err = compare(result, truth)
    assert err.posed == 3 and err.rotation_deg < 1.0 and err.offset_frames < 0.25

    tracks, videos, truth = make_rig(kind="skeleton", n_cameras=3, duration=8.0, seed=2)  # clocks 1.4-2.2 s apart
    result = calibrate_from_subject(tracks, videos, claim)
    assert all(p.claim is not None and p.claim.startswith("contradicted") for p in result.pairs), result.pairs
    err = compare(result, truth)
    assert err.posed == 3 and err.rotation_deg < 1.0 and err.offset_frames < 0.25


@pytest.mark.parametrize(
    ("searched", "declared", "claim"),
    [
        ((2.0, 10.0, True, True), (0.0, 3.0, True), "contradicted"),  # far, and clearly better
        ((2.0, 10.0, True, False), (0.0, 3.0, True), "contradicted"),  # far and better, though ambiguous
        ((2.0, 10.0, True, True), (0.0, 9.0, True), "held"),  # far, but not clearly better
        ((0.01, 10.0, True, True), (0.0, 3.0, True), "held"),  # within a frame
        ((2.0, 10.0, True, True), (0.0, 9.0, False), "not used"),  # the declared offset gives nothing usable
        ((10.0, 10.0, True, True), (0.0, 3.0, True), "held"),  # better, but at the end of the search range
    ],
)
def test_the_declared_clock_decision(
    monkeypatch: pytest.MonkeyPatch, searched: tuple, declared: tuple, claim: str
) -> None:
    """`_tested_claim` on a pair's searched fit (shift s, score, has a model, clear) against the fit at the
    declared shift (shift, score, usable): which one the pair keeps, and what its `claim` says."""
    import numpy as np

    from sfm.subject import calibrate
    from sfm.subject.pairs import PairFit

    def fit(shift: float, score: float, usable: bool = True, clear: bool = True) -> PairFit:
        return PairFit(
            a=0,
            b=1,
            shift=-shift,
            inliers=100,
            shared=120,
            runner_up_ratio=2.0 if clear else 1.01,
            degenerate=None if usable else "plane",
            xa=np.zeros((0, 2)),
            xb=np.zeros((0, 2)),
            E=np.eye(3),
            focals=(np.nan, np.nan),
            score=score,
            ambiguous=not clear,
        )

    monkeypatch.setattr(calibrate, "fit_at", lambda *args, **kwargs: fit(*declared))

    class Video:
        period = 1 / 30
        name = "v"
        times = np.arange(0.0, 60.0, 1 / 30)  # a search range of +-10 s (max_offset) inside the overlap

    kept = calibrate._tested_claim([Video(), Video()], fit(*searched), 0.0, 3.0, 10.0)  # type: ignore[list-item]
    assert kept.claim is not None and kept.claim.startswith(claim), kept.claim
    assert kept.shift == (-declared[0] if claim == "held" else -searched[0])


def test_a_pair_logs_only_the_measures_that_apply() -> None:
    """A pair at a known offset has no runner-up: its log line said 'ratio nan, None' (a user's report, 2026-11-30)."""
    from sfm.subject.calibrate import _pair_words
    from sfm.subject.pairs import PairFit

    empty = np.zeros((0, 2))
    known = PairFit(
        a=0,
        b=1,
        shift=-0.25,
        inliers=727,
        shared=735,
        runner_up_ratio=math.nan,
        degenerate=None,
        xa=empty,
        xb=empty,
        E=None,
        focals=(math.nan, math.nan),
    )
    assert _pair_words(known) == "offset 0.250 s, 727/735 inliers"
    searched = dataclasses.replace(known, runner_up_ratio=2.345, degenerate="line", reason="too few inliers")
    assert _pair_words(searched) == (
        "offset 0.250 s, 727/735 inliers, runner-up ratio 2.35, degenerate: line, too few inliers"
    )


def test_two_groups_sharing_no_point_pose_the_larger_and_say_why_not_the_other() -> None:
    """Cameras 0-1 track one half of the skeleton, cameras 2-4 the other half (DeepFly3D's fly rig: each side's
    cameras see their own legs): no pair joins the groups, so the larger group is posed and the other's reason
    says that the groups share no point (not an "inconsistent offset"); the pairs across the groups neither hold
    nor contradict declared clocks, which the pairs within the groups test."""
    tracks, videos, _ = make_rig(kind="skeleton", n_cameras=5, duration=4.0, seed=7)
    points = tracks.point_names()
    half = set(points[: len(points) // 2])
    small = {"cam0", "cam1"}
    keep = [i for i, (v, p) in enumerate(zip(tracks.video, tracks.point, strict=True)) if (v in small) == (p in half)]
    claimed = SubjectOptions(claimed_offsets={v.name: 0.0 for v in videos})
    result = calibrate_from_subject(tracks.take(np.array(keep)), videos, claimed)
    assert sorted(c.name for c in result.cameras) == ["cam2", "cam3", "cam4"]
    for name in small:
        assert "no usable pair joins its group of videos (cam0, cam1)" in result.failed[name]
        assert "shared observations" in result.failed[name].split("their pairs: ")[1]
    across = [p for p in result.pairs if len({p.a, p.b} & small) == 1]
    assert len(across) == 6 and all(p.claim == "untested" for p in across)
    assert all(p.claim not in (None, "untested") for p in result.pairs if len({p.a, p.b} & small) != 1)
