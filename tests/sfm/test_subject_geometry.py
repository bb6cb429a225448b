"""The subject path's batched two-view fits: one degenerate sample never fails the batch."""

from __future__ import annotations

import numpy as np

from sfm.subject.geometry import eight_point, sampson


def test_a_singular_sample_scores_nothing_and_the_others_are_fitted() -> None:
    """Eight copies of one far point make the sample's 8x8 system singular even with the ridge (which vanishes
    beside its entries): numpy's batched solve raised for the whole batch, a traceback in `register`, depending on
    which samples the draw made. Now that sample gives no hypothesis and the good one is still fitted."""
    rng = np.random.default_rng(0)
    R = np.array([[np.cos(0.3), 0, np.sin(0.3)], [0, 1, 0], [-np.sin(0.3), 0, np.cos(0.3)]])
    t = np.array([1.0, 0.2, 0.1])
    X = rng.uniform(-1, 1, (8, 3)) + np.array([0.0, 0.0, 5.0])
    xa = X[:, :2] / X[:, 2:]
    Xb = X @ R.T + t
    xb = Xb[:, :2] / Xb[:, 2:]
    bad_a, bad_b = np.full((8, 2), 1e6), np.full((8, 2), 2e6)
    F = eight_point(np.stack([xa, bad_a]), np.stack([xb, bad_b]), essential=True)
    assert np.isfinite(F).all()
    assert float(sampson(F[0][None], xa, xb).max()) < 1e-12  # the good sample's exact geometry


def test_an_opencv_assertion_in_a_pair_fit_is_a_pair_without_geometry(monkeypatch) -> None:
    """OpenCV's USAC asserts (`!model.empty()` in setModelParameters) on some degenerate correspondences (Pose2Sim's
    multi-person lab, 3 points, two nearly still): `register` ended in a traceback without its report. The pair now
    has no geometry, with OpenCV's words as its reason, and the path goes on with the others."""
    import cv2

    from sfm.subject.model import SubjectVideo
    from sfm.subject.observations import build_observations
    from sfm.subject.pairs import fit_at
    from tracking.tracks import Tracks

    rng = np.random.default_rng(1)
    frames = np.arange(60)
    X = np.c_[np.sin(frames / 9.0), np.cos(frames / 7.0), 5.0 + 0.3 * np.sin(frames / 5.0)]
    rows = []
    for name, shift in (("a", 0.0), ("b", 0.8)):
        x = (X[:, 0] + shift) / X[:, 2] * 800 + 640 + rng.normal(0, 0.3, 60)
        y = X[:, 1] / X[:, 2] * 800 + 360 + rng.normal(0, 0.3, 60)
        rows += [(name, int(f), "p", float(u), float(v)) for f, u, v in zip(frames, x, y, strict=True)]
    videos = [SubjectVideo(name=n, width=1280, height=720, times=frames / 30.0) for n in ("a", "b")]
    _, obs = build_observations(Tracks.from_rows(rows), videos)

    def assertion(*args: object, **kwargs: object) -> None:
        raise cv2.error("OpenCV(5.0.0) estimator.cpp:418: error: (-215:Assertion failed) !model.empty()")

    monkeypatch.setattr(cv2, "findFundamentalMat", assertion)
    monkeypatch.setattr(cv2, "findEssentialMat", assertion)
    fit = fit_at(obs[0], obs[1], 0, 1, 0.0)
    assert fit.E is None and fit.reason is not None and "no epipolar geometry found (OpenCV" in fit.reason


def test_self_calibrated_focals_at_the_search_bound_are_refused() -> None:
    """DANNCE's mouse arena, blob tracks of 2 points: self-calibration put every focal at 0.25 or 4 x the long side,
    and the path ran past 9 minutes on those lenses. A focal at the bound is no measurement: refused, named."""
    from types import SimpleNamespace

    import pytest

    from sfm.subject.calibrate import _refuse_bounded
    from sfm.subject.model import SubjectCalibrationError

    def camera(name: str) -> SimpleNamespace:
        return SimpleNamespace(name=name, video=SimpleNamespace(width=1328, height=1048))

    obs = [camera("CameraE"), camera("CameraL"), camera("CameraR")]
    _refuse_bounded(obs, {0: 1100.0, 1: 900.0, 2: 1400.0})  # measured focals pass
    with pytest.raises(SubjectCalibrationError, match=r"focal length of CameraE \(5312 px, 4 x .*CameraR \(332 px"):
        _refuse_bounded(obs, {0: 4.0 * 1328, 1: 900.0, 2: 0.25 * 1328})


def test_an_opencv_assertion_in_pnp_or_the_homography_test_is_no_pose_and_no_plane(monkeypatch) -> None:
    """The same OpenCV assertions in a camera's PnP (no pose: the camera is left to the others) and in the plane
    test (no homography: not called planar), not a traceback."""
    import cv2

    from sfm.subject.chain import Knots, pnp
    from sfm.subject.model import SubjectVideo
    from sfm.subject.observations import build_observations
    from sfm.subject.pairs import _degeneracy
    from tracking.tracks import Tracks

    def assertion(*args: object, **kwargs: object) -> None:
        raise cv2.error("OpenCV(5.0.0) estimator.cpp:418: error: (-215:Assertion failed) !model.empty()")

    rng = np.random.default_rng(0)
    frames = np.arange(30)
    X = np.c_[np.sin(frames / 4.0), np.cos(frames / 3.0), 5.0 + np.sin(frames / 5.0)][:, None, :]  # (30, 1, 3)
    rows = [
        ("a", int(f), "p", float(640 + 800 * x / z), float(360 + 800 * y / z))
        for f, (x, y, z) in zip(frames, X[:, 0], strict=True)
    ]
    video = SubjectVideo(name="a", width=1280, height=720, times=frames / 30.0)
    _, obs = build_observations(Tracks.from_rows(rows), [video])
    knots = Knots(t0=0.0, h=1 / 30.0, X=X)
    monkeypatch.setattr(cv2, "solvePnPRansac", assertion)
    assert pnp(obs[0], 0.0, knots, 2.0) is None
    monkeypatch.setattr(cv2, "findHomography", assertion)
    xa = rng.uniform(-0.5, 0.5, (50, 2))
    assert _degeneracy(xa, xa + rng.normal(0, 0.01, (50, 2)), 0.001) is None
