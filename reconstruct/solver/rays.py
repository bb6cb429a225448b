"""Viewing rays and the similarity normalization the solver works in."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dynrecon.lens import undistorted
from reconstruct.solver.problem import Problem


def has_distortion(dist: np.ndarray | None) -> bool:
    """Whether OpenCV distortion coefficients change any pixel (None or all zeros do not)."""
    return dist is not None and bool(np.any(dist != 0))


def normalized_image_points(uv: np.ndarray, K: np.ndarray, dist: np.ndarray | None) -> np.ndarray:
    """Pixels (N, 2) of one camera -> normalized image coordinates (N, 2), undistorted when `dist` is given."""
    if has_distortion(dist):
        return undistorted(uv, K, dist)
    homogeneous = np.column_stack([uv, np.ones(len(uv))])
    return np.linalg.solve(K, homogeneous.T).T[:, :2]


def closest_depths(r1: np.ndarray, r2: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depths d1, d2 along unit rays r1, r2 (..., 3) of their closest points, the rays leaving centres c1 and c2
    with w = c1 - c2 (broadcast to the rays); and 1 - cos^2 of their angle (0: parallel, where d1, d2 are not
    finite). The closest points are c1 + d1 r1 and c2 + d2 r2."""
    b = np.einsum("...k,...k->...", r1, r2)
    d = np.einsum("...k,...k->...", r1, w)
    e = np.einsum("...k,...k->...", r2, w)
    denom = 1.0 - b * b
    with np.errstate(invalid="ignore", divide="ignore"):
        return (b * e - d) / denom, (e - b * d) / denom, denom


def viewing_rays(problem: Problem) -> np.ndarray:
    """Unit ray directions in world coordinates r = normalize(R^T K^-1 [u v 1]^T), (F, P, 3); NaN where unobserved.
    All frames at once (a loop over frames is slow on long captures); frames with lens distortion go through OpenCV,
    one call per lens."""
    F, P = problem.num_frames, problem.num_points
    observed = problem.observed
    pixels = np.concatenate([np.where(observed[..., None], problem.uv, 0.0), np.ones((F, P, 1))], axis=2)
    normalized = np.linalg.solve(problem.K, pixels.transpose(0, 2, 1)).transpose(0, 2, 1)  # (F, P, 3)
    normalized[..., 2] = 1.0
    # one OpenCV call per lens (a static camera's frames share one), not one per frame
    lenses: dict[bytes, list[int]] = {}
    for f, dist in enumerate(problem.dist):
        if has_distortion(dist) and observed[f].any():
            key = np.ascontiguousarray(problem.K[f]).tobytes() + np.asarray(dist, dtype=np.float64).tobytes()
            lenses.setdefault(key, []).append(f)
    for frames in lenses.values():
        seen = np.zeros_like(observed)
        seen[frames] = observed[frames]
        first = frames[0]
        normalized[seen, :2] = normalized_image_points(problem.uv[seen], problem.K[first], problem.dist[first])
    directions = np.matmul(normalized, problem.R)  # rows: R^T d
    rays = directions / np.linalg.norm(directions, axis=2, keepdims=True)
    rays[~observed] = np.nan
    return rays


@dataclass(frozen=True)
class Normalization:
    """x_normalized = (x_world - offset) / scale."""

    offset: np.ndarray  # (3,)
    scale: float

    def apply(self, points: np.ndarray) -> np.ndarray:
        return (points - self.offset) / self.scale

    def undo(self, points: np.ndarray) -> np.ndarray:
        return points * self.scale + self.offset


def camera_normalization(centers: np.ndarray, video_index: np.ndarray) -> Normalization:
    """Average distance between the cameras' centres -> 1, their centroid -> origin (as in the paper).

    Cameras move, so each video is represented by its mean centre; comparing every frame pair would count the zero
    distances of frames of one static camera.
    """
    video_centers = np.stack([centers[video_index == v].mean(axis=0) for v in np.unique(video_index)])
    offset = video_centers.mean(axis=0)
    gaps = np.linalg.norm(video_centers[:, None] - video_centers[None], axis=-1)
    pairs = gaps[np.triu_indices(len(video_centers), k=1)]
    scale = float(pairs.mean()) if len(pairs) and pairs.mean() > 0 else 1.0
    if scale <= 0 or not np.isfinite(scale):
        scale = 1.0
    return Normalization(offset=offset, scale=scale)
