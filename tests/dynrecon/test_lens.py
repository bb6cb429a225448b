"""Pixels to rays through OpenCV's lens model, iterated to the model's precision (dynrecon/lens.py)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dynrecon.lens import undistorted

# caliscope's widest webcam (camera_array.toml cam 0), and a wide 4K lens of OpenCV's rational model (a real drone
# rig's, multiview_calib's examples/drone_rolex)
LENSES = {
    "webcam": (
        np.array([[903.55, 0.0, 618.31], [0.0, 907.88, 394.21], [0.0, 0.0, 1.0]]),
        np.array([-0.3321, 0.04642, -0.004296, 0.004113, 0.06657]),
        (1280, 720),
    ),
    "rational 4K": (
        np.array([[1755.0, 0.0, 1915.0], [0.0, 1755.0, 1085.0], [0.0, 0.0, 1.0]]),
        np.array([2.055, 0.879, 0.0, 0.0, 0.035, 2.339, 1.38, 0.165]),
        (3840, 2160),
    ),
}


@pytest.mark.parametrize("lens", list(LENSES))
def test_rays_reproject_onto_their_pixels_to_the_corners(lens: str) -> None:
    K, dist, (width, height) = LENSES[lens]
    grid = np.array([[x, y] for x in np.linspace(0, width - 1, 9) for y in np.linspace(0, height - 1, 7)])
    rays = undistorted(grid, K, dist)
    back = cv2.projectPoints(np.c_[rays, np.ones(len(rays))], np.zeros(3), np.zeros(3), K, dist)[0].reshape(-1, 2)
    assert np.abs(back - grid).max() < 1e-6
    # OpenCV's default (five iterations) leaves pixels off at the edges: what this module is for
    default = cv2.undistortPoints(grid.reshape(-1, 1, 2), K, dist).reshape(-1, 2)
    off = cv2.projectPoints(np.c_[default, np.ones(len(default))], np.zeros(3), np.zeros(3), K, dist)[0].reshape(-1, 2)
    assert np.abs(off - grid).max() > 0.01


def test_no_distortion_is_the_pinhole() -> None:
    K, _, _ = LENSES["webcam"]
    uv = np.array([[100.0, 200.0], [640.0, 360.0]])
    expected = (uv - K[:2, 2]) / np.diag(K)[:2]
    np.testing.assert_allclose(undistorted(uv, K, None), expected, atol=1e-12)
