"""How closely the tracks' rays meet on given clocks: the yardstick for clocks that the track search did not find
itself (registration's or declared offsets), as `SearchResult.residual_px` is for its own.

Each video's observations of a point are paired with every other video's rays of that point interpolated at the
same global time, between that video's consecutive observations of the point when at most MAX_GAP_PERIODS of its
sampling step apart (tracks of every 4th frame interpolate across the untracked frames between them).
"""

from __future__ import annotations

import math

import numpy as np

from reconstruct.clocks.search import MAD_TO_SIGMA, gap_px, sampled_tracks
from reconstruct.solver.problem import Problem
from reconstruct.solver.rays import viewing_rays

MIN_SCALE_PX = 0.1  # as the search's robust scale: rays that meet exactly still get a positive yardstick


def ray_gap_px(problem: Problem, times: np.ndarray) -> float:
    """Robust scale (px, MAD) of the gaps between every observed ray and the other videos' rays of the same point at
    the same global time `times (F,)`; NaN when no two videos' observations overlap in time."""
    rays = viewing_rays(problem)  # once: each point's tracks below take theirs
    gaps: list[np.ndarray] = []
    for p in range(problem.num_points):
        tracks = sampled_tracks(problem, times, np.array([p]), rays)  # the search's rays, on this point's samples
        for u, tu in enumerate(tracks):
            for v, tv in enumerate(tracks):
                if v == u or tv.own.size == 0:
                    continue
                cu, ru, fu = tu.interpolate(tv.own)
                gap = gap_px(tv.centers, tv.rays, tv.focal, cu, ru, fu)[:, 0]
                gaps.append(gap[np.isfinite(gap)])
    values = np.concatenate(gaps) if gaps else np.empty(0)
    if values.size == 0:
        return math.nan
    return max(MAD_TO_SIGMA * float(np.median(values)), MIN_SCALE_PX)
