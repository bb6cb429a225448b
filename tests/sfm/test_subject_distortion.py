"""Radial distortion in the subject path's self-calibration (issue 16): estimated where it predicts held-out
observations better, the simpler focal-only model kept otherwise."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from sfm.subject import SubjectOptions, calibrate_from_subject
from sfm.subject.focals import division_to_opencv, undistort_division
from sfm.subject.model import Lens
from sfm.subject.synthetic import compare, make_rig


@pytest.mark.parametrize("k1", [-0.115, 0.1])
def test_division_model_converts_to_the_opencv_coefficients_it_stands_for(k1: float) -> None:
    """Over the whole image; a start for the bundle adjustment (stronger lenses, e.g. k1 = -0.33 at f = w / 2,
    fold near the corners, where the two models part: the bundle refines k1, k2 from the observed radii)."""
    width, height, focal = 1920, 1080, 960.0
    half = width / 2
    K = np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1.0]])
    dist = np.array([k1, 0.0, 0.0, 0.0, 0.0])
    ideal = np.random.default_rng(0).uniform([-0.8, -0.45], [0.8, 0.45], (400, 2))  # normalized, undistorted
    pixels, _ = cv2.projectPoints(np.column_stack([ideal, np.ones(len(ideal))]), np.zeros(3), np.zeros(3), K, dist)
    centred = pixels.reshape(-1, 2) - K[:2, 2]
    # the division coefficient that undistorts these pixels best, on a fine grid
    grid = np.linspace(-0.8, 0.8, 801)
    errors = [np.abs(undistort_division(centred, lam, half) / focal - ideal).max() for lam in grid]
    lam = float(grid[int(np.argmin(errors))])
    back = division_to_opencv(lam, focal, half, width, height)
    assert back[2:] == pytest.approx(0.0)
    redistorted, _ = cv2.projectPoints(np.column_stack([ideal, np.ones(len(ideal))]), np.zeros(3), np.zeros(3), K, back)
    displacement = np.linalg.norm(centred - ideal * focal, axis=1).max()
    assert np.linalg.norm(redistorted.reshape(-1, 2) - pixels.reshape(-1, 2), axis=1).max() < 0.05 * displacement


@pytest.mark.slow
def test_wide_angle_identical_webcams_are_posed_with_their_distortion() -> None:
    """Four identical wide-angle cameras (k1 = -0.33), no intrinsics given: focal-only self-calibration is several
    per cent and degrees off; with radial distortion, within 2 % and 1 degree, and the lens is reported."""
    tracks, videos, truth = make_rig(kind="skeleton", n_cameras=4, known_K=False, focal=0.5, k1=-0.33)
    result = calibrate_from_subject(tracks, videos, SubjectOptions())
    errors = compare(result, truth)
    assert result.lens is Lens.RADIAL
    assert result.lens_check["radial"] < result.lens_check["focal"]
    assert errors.posed == 4
    assert errors.centre_pct < 2.0
    assert errors.rotation_deg < 1.0
    assert errors.focal_pct < 3.0
    for camera in result.cameras:
        assert camera.dist is not None
        assert camera.dist[0] == pytest.approx(-0.33, abs=0.06)


@pytest.mark.slow
def test_cameras_without_distortion_keep_the_focal_only_model() -> None:
    """No distortion in the data: the simpler model is kept (no distortion found, or not better on held-out
    observations), and the poses stay as accurate as before."""
    tracks, videos, truth = make_rig(kind="skeleton", n_cameras=4, known_K=False, distortion=False, duration=8.0)
    result = calibrate_from_subject(tracks, videos, SubjectOptions())
    errors = compare(result, truth)
    assert result.lens is Lens.FOCAL
    assert errors.posed == 4
    assert errors.centre_pct < 1.0
    assert errors.rotation_deg < 1.0
