"""How closely the tracks' rays meet on given clocks: the yardstick for clocks that the track search did not find
itself (registration's or declared offsets), as `SearchResult.residual_px` is for its own.

Each video's observations of a point are paired with every other video's rays of that point interpolated at the
same global time, between that video's consecutive observations of the point when at most MAX_GAP_PERIODS of its
sampling step apart (tracks of every 4th frame interpolate across the untracked frames between them).
"""

from __future__ import annotations

import math

import numpy as np

from reconstruct.clocks.search import MAD_TO_SIGMA, MAX_GAP_PERIODS, gap_px, median_step
from reconstruct.solver.problem import Problem
from reconstruct.solver.rays import viewing_rays

MIN_SCALE_PX = 0.1  # as the search's robust scale: rays that meet exactly still get a positive yardstick


def ray_gap_px(problem: Problem, times: np.ndarray) -> float:
    """Robust scale (px, MAD) of the gaps between every observed ray and the other videos' rays of the same point at
    the same global time `times (F,)`; NaN when no two videos' observations overlap in time."""
    rays = viewing_rays(problem)  # (F, P, 3)
    centers = problem.centers
    focal = 0.5 * (problem.K[:, 0, 0] + problem.K[:, 1, 1])
    observed = problem.observed & np.isfinite(times)[:, None]
    N = len(problem.video_names)
    gaps: list[np.ndarray] = []
    for p in range(problem.num_points):
        rows = [_sorted_rows(problem, times, observed[:, p], v) for v in range(N)]
        for u in range(N):
            mine = rows[u]
            if mine.size < 2:
                continue
            t_u = times[mine]
            max_gap = MAX_GAP_PERIODS * _sampling_step(problem, times, u, t_u)
            for v in range(N):
                if v == u or rows[v].size == 0:
                    continue
                query = times[rows[v]]
                k = np.clip(np.searchsorted(t_u, query, side="right") - 1, 0, mine.size - 2)
                t0, t1 = t_u[k], t_u[k + 1]
                a = (query - t0) / (t1 - t0)
                ok = (a >= 0) & (a <= 1) & (t1 - t0 <= max_gap)
                if not ok.any():
                    continue
                a, before, after, at = a[ok], mine[k[ok]], mine[k[ok] + 1], rows[v][ok]
                ray = rays[before, p] * (1 - a)[:, None] + rays[after, p] * a[:, None]
                ray /= np.linalg.norm(ray, axis=-1, keepdims=True)
                center = centers[before] * (1 - a)[:, None] + centers[after] * a[:, None]
                gap = gap_px(centers[at], rays[at, p, None], focal[at], center, ray[:, None], focal[before])[:, 0]
                gaps.append(gap[np.isfinite(gap)])
    values = np.concatenate(gaps) if gaps else np.empty(0)
    if values.size == 0:
        return math.nan
    return max(MAD_TO_SIGMA * float(np.median(values)), MIN_SCALE_PX)


def _sorted_rows(problem: Problem, times: np.ndarray, seen: np.ndarray, video: int) -> np.ndarray:
    rows = np.flatnonzero(seen & (problem.video_index == video))
    return rows[np.argsort(times[rows], kind="stable")]


def _sampling_step(problem: Problem, times: np.ndarray, video: int, tracked: np.ndarray) -> float:
    """The video's step between its tracked samples (median), at least its frame period."""
    own = times[(problem.video_index == video) & np.isfinite(times)]
    return max(median_step(own), median_step(tracked))
