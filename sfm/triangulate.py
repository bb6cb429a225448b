"""New 3D points from two posed views of the same camera: linear triangulation, then the checks that COLMAP's
mapper applies to a new point (in front of both cameras, small reprojection error in both, wide enough angle)."""

from __future__ import annotations

import cv2
import numpy as np
import pycolmap


def triangulate(
    camera: pycolmap.Camera,
    first: pycolmap.Rigid3d,
    second: pycolmap.Rigid3d,
    xy_first: np.ndarray,
    xy_second: np.ndarray,
    *,
    max_error: float,
    min_angle_deg: float,
) -> tuple[np.ndarray, np.ndarray]:
    """World points (N, 3) of the matches xy_first, xy_second (N, 2) (the camera's COLMAP pixels, seen from the
    poses `first` and `second`, both cam_from_world), and ok (N,) bool: the points that pass every check."""
    count = len(xy_first)
    if count == 0:
        return np.zeros((0, 3)), np.zeros(0, bool)
    rays = [np.asarray(camera.cam_from_img(np.asarray(xy, dtype=float)), dtype=float) for xy in (xy_first, xy_second)]
    homogeneous = cv2.triangulatePoints(first.matrix(), second.matrix(), rays[0].T, rays[1].T)
    w = homogeneous[3]
    ok = np.abs(w) > 1e-12
    xyz = (homogeneous[:3] / np.where(ok, w, 1.0)).T
    centres = []
    for pose, xy in ((first, xy_first), (second, xy_second)):
        in_cam = xyz @ pose.rotation.matrix().T + pose.translation
        ok &= in_cam[:, 2] > 1e-9
        safe = np.where(ok[:, None], in_cam, [0.0, 0.0, 1.0])  # img_from_cam of a point behind: not used
        error = np.linalg.norm(np.asarray(camera.img_from_cam(safe)) - xy, axis=1)
        ok &= error < max_error
        centres.append(-pose.rotation.matrix().T @ pose.translation)
    a, b = xyz - centres[0], xyz - centres[1]
    cosine = (a * b).sum(axis=1) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-12)
    ok &= np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))) >= min_angle_deg
    return xyz, ok
