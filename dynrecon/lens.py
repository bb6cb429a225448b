"""Pixels through OpenCV's lens model back to normalized image coordinates, to the model's precision.

`cv2.undistortPoints` stops after 5 fixed-point iterations unless given criteria: on the caliscope webcams (k1 =
-0.33) that leaves up to 0.3 px at the image's edges, on wide 4K lenses of OpenCV's rational model tens of pixels in
the corners (docs/measurements.md). Iterated to convergence, per point unless the default lands nearer its pixel
(beyond a lens model's fold the iteration may not converge).
"""

from __future__ import annotations

import numpy as np

ITERATIONS = 100  # at most; the tolerance below ends it in a few on mild lenses
TOLERANCE = 1e-12
LANDED_PX = 1e-6  # a ray projecting back within this of its pixel is the model's inverse there: nothing to compare


def undistorted(uv: np.ndarray, K: np.ndarray, dist: np.ndarray | None) -> np.ndarray:
    """Pixels `uv (N, 2)` (finite) of a camera `K (3, 3)`, `dist` (OpenCV's 4, 5 or 8 coefficients, or None) ->
    undistorted normalized image coordinates (N, 2)."""
    import cv2  # slow to import: only distorted cameras need it

    points = np.ascontiguousarray(uv, dtype=np.float64).reshape(-1, 1, 2)
    coefficients = None if dist is None else np.asarray(dist, dtype=np.float64)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, ITERATIONS, TOLERANCE)
    rays = cv2.undistortPoints(points, K, coefficients, None, None, None, criteria).reshape(-1, 2)
    pixels = points.reshape(-1, 2)
    # beyond a lens model's fold the iteration may not converge: there, the default where it lands nearer the pixel
    miss = _round_trip(rays, pixels, K, coefficients)
    off = np.flatnonzero(miss > LANDED_PX)
    if off.size:
        default = cv2.undistortPoints(points[off], K, coefficients).reshape(-1, 2)
        nearer = _round_trip(default, pixels[off], K, coefficients) < miss[off]
        rays[off[nearer]] = default[nearer]
    return rays


def _round_trip(rays: np.ndarray, uv: np.ndarray, K: np.ndarray, dist: np.ndarray | None) -> np.ndarray:
    """(N,) pixels between `uv` and its `rays` projected back through the lens (inf where not finite)."""
    import cv2

    finite = np.isfinite(rays).all(axis=1)
    miss = np.full(len(rays), np.inf)
    if finite.any():
        homogeneous = np.c_[rays[finite], np.ones(int(finite.sum()))]
        back = cv2.projectPoints(homogeneous, np.zeros(3), np.zeros(3), K, dist)[0].reshape(-1, 2)
        miss[finite] = np.linalg.norm(back - uv[finite], axis=1)
    return miss


__all__ = ["undistorted"]
