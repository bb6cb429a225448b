"""Pixels through OpenCV's lens model back to normalized image coordinates, to the model's precision.

`cv2.undistortPoints` stops after 5 fixed-point iterations unless given criteria: on the caliscope webcams (k1 =
-0.33) that leaves up to 0.3 px at the image's edges, on wide 4K lenses of OpenCV's rational model tens of pixels in
the corners (docs/measurements.md). Iterated to convergence, every reader of a distorted camera gets the same rays.
"""

from __future__ import annotations

import numpy as np

ITERATIONS = 100  # at most; the tolerance below ends it in a few on mild lenses
TOLERANCE = 1e-12


def undistorted(uv: np.ndarray, K: np.ndarray, dist: np.ndarray | None) -> np.ndarray:
    """Pixels `uv (N, 2)` (finite) of a camera `K (3, 3)`, `dist` (OpenCV's 4, 5 or 8 coefficients, or None) ->
    undistorted normalized image coordinates (N, 2)."""
    import cv2  # slow to import: only distorted cameras need it

    points = np.ascontiguousarray(uv, dtype=np.float64).reshape(-1, 1, 2)
    coefficients = None if dist is None else np.asarray(dist, dtype=np.float64)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, ITERATIONS, TOLERANCE)
    return cv2.undistortPoints(points, K, coefficients, None, None, None, criteria).reshape(-1, 2)


__all__ = ["undistorted"]
