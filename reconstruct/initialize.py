"""Initial 3D shapes from nearly-intersecting ray bundles of other videos (paper, Sec. "Initialization").

For frames f and j of different videos, the depths minimizing ||S_f - S_j||^2 decouple per point: they are the
closest points of the two viewing rays. D(f, j) is the mean squared gap over the points both frames observe; a pair
with a negative depth (diverging rays) gets D = inf. Each frame takes the depths from its best partner.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PARALLEL_EPS = 1e-9
# Below this many shared points a bundle distance says little about the shape; such pairs are skipped when a
# frame has better-supported partners.
MIN_COMMON_POINTS = 3


@dataclass(kw_only=True)
class PairInit:
    """Result of the pairwise initialization."""

    partner: np.ndarray  # (F,) best partner frame, -1 when none
    cost: np.ndarray  # (F,) D(f, partner)
    depth: np.ndarray  # (F, P) depth along the ray, NaN where not initialized


def closest_ray_points(
    center_a: np.ndarray, ray_a: np.ndarray, center_b: np.ndarray, ray_b: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depths (d_a, d_b) of the mutually closest points of rays C_a + d_a r_a and C_b + d_b r_b and their squared
    gap. Broadcasts over leading axes; the last axis is xyz. Unit rays. Parallel rays give NaN."""
    w = center_a - center_b
    b = np.sum(ray_a * ray_b, axis=-1)
    d = np.sum(ray_a * w, axis=-1)
    e = np.sum(ray_b * w, axis=-1)
    denom = 1.0 - b * b
    parallel = denom < PARALLEL_EPS
    denom = np.where(parallel, np.nan, denom)
    depth_a = (b * e - d) / denom
    depth_b = (e - b * d) / denom
    gap = w + depth_a[..., None] * ray_a - depth_b[..., None] * ray_b
    return depth_a, depth_b, np.sum(gap * gap, axis=-1)


def bundle_distances(
    centers: np.ndarray, rays: np.ndarray, rows: np.ndarray, video_index: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """D(f, j) for the frames `rows` against all frames, and the depths of `rows` in each pair.

    centers: (F, 3); rays: (F, P, 3) NaN = unobserved; rows: (B,). Returns D (B, F) and depth (B, F, P).
    The closed form of `closest_ray_points` is evaluated per point with matrix products over frame pairs.
    """
    F, P = rays.shape[:2]
    B = len(rows)
    total = np.zeros((B, F))
    count = np.zeros((B, F), dtype=np.int64)
    diverging = np.zeros((B, F), dtype=bool)
    depth = np.full((B, F, P), np.nan)
    ca = centers[rows]  # (B, 3)
    center_sq = np.einsum("fi,fi->f", centers, centers)
    cross = ca @ centers.T  # (B, F): C_a . C_b
    w_sq = center_sq[rows][:, None] + center_sq[None, :] - 2.0 * cross  # |C_a - C_b|^2
    for p in range(P):
        ra_all, rb = rays[rows, p], rays[:, p]  # (B, 3), (F, 3)
        seen_a, seen_b = ~np.isnan(ra_all[:, 0]), ~np.isnan(rb[:, 0])
        if not seen_a.any():
            continue
        ra, rbz = np.nan_to_num(ra_all), np.nan_to_num(rb)
        b = ra @ rbz.T  # r_a . r_b
        d = np.einsum("bi,bi->b", ra, ca)[:, None] - ra @ centers.T  # r_a . (C_a - C_b)
        e = rbz @ ca.T  # (F, B): r_b . C_a
        e = e.T - np.einsum("fi,fi->f", rbz, centers)[None, :]  # r_b . (C_a - C_b)
        denom = 1.0 - b * b
        usable = seen_a[:, None] & seen_b[None, :] & (denom >= PARALLEL_EPS)
        safe = np.where(usable, denom, 1.0)
        depth_a = (b * e - d) / safe
        depth_b = (e - b * d) / safe
        gap = w_sq + depth_a**2 + depth_b**2 + 2 * depth_a * d - 2 * depth_b * e - 2 * depth_a * depth_b * b
        gap = np.maximum(gap, 0.0)
        total += np.where(usable, gap, 0.0)
        count += usable
        diverging |= usable & ((depth_a < 0) | (depth_b < 0))
        depth[:, :, p] = np.where(usable, depth_a, np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        D = total / count
    # A frame that observes fewer points than MIN_COMMON_POINTS can still pair on all of them.
    observed_in_row = np.sum(~np.isnan(rays[rows, :, 0]), axis=1, keepdims=True)
    enough = count >= np.minimum(MIN_COMMON_POINTS, np.maximum(observed_in_row, 1))
    D[~enough | (count == 0) | diverging] = np.inf
    D[video_index[rows][:, None] == video_index[None, :]] = np.inf
    return D, depth


def initialize_depths(
    centers: np.ndarray, rays: np.ndarray, video_index: np.ndarray, *, memory_elements: int = 8_000_000
) -> PairInit:
    """Pick each frame's best partner of another video and take the depths from that pair. O(F^2 P), in row blocks
    of about `memory_elements` (frame pair x point) entries."""
    F, P = rays.shape[:2]
    block = max(1, memory_elements // max(1, F * P))
    partner = np.full(F, -1, dtype=np.int64)
    cost = np.full(F, np.inf)
    depth = np.full((F, P), np.nan)
    for start in range(0, F, block):
        rows = np.arange(start, min(F, start + block))
        D, depth_rows = bundle_distances(centers, rays, rows, video_index)
        best = np.argmin(D, axis=1)
        best_cost = D[np.arange(len(rows)), best]
        ok = np.isfinite(best_cost)
        partner[rows[ok]] = best[ok]
        cost[rows[ok]] = best_cost[ok]
        depth[rows[ok]] = depth_rows[np.arange(len(rows))[ok], best[ok]]
    return PairInit(partner=partner, cost=cost, depth=depth)


def fill_missing_points(points: np.ndarray, video_index: np.ndarray) -> np.ndarray:
    """Fill NaN 3D points (F, P, 3) for a start value: interpolate within the same video over frame order, else use
    the point's mean over all frames. Only a starting point for the solver, which re-estimates them."""
    filled = points.copy()
    P = points.shape[1]
    for vi in np.unique(video_index):
        members = np.flatnonzero(video_index == vi)
        for p in range(P):
            known = ~np.isnan(filled[members, p, 0])
            if known.all() or not known.any():
                continue
            positions = np.arange(len(members))
            for axis in range(3):
                filled[members[~known], p, axis] = np.interp(positions[~known], positions[known],
                                                             filled[members[known], p, axis])
    for p in range(P):
        missing = np.isnan(filled[:, p, 0])
        if missing.any() and not missing.all():
            filled[missing, p] = np.nanmean(filled[:, p], axis=0)
    return filled
