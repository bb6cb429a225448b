"""How well one clock hypothesis predicts each video's rays from the other videos alone (leave one video out).

A wrong clock is a property of one video: its rays are placed at the wrong instants of the motion the others see.
Fitted with every video, the trajectories can bend through those rays, or meet them alone where the wrong clock
moves them out of the others' time span (one ray per instant fixes no depth), so the in-sample residual can favour
the wrong clock. Held out, a video's rays are met only by trajectories the other videos built, at the instants its
clock gives: the reprojection error there measures that clock against the others (docs/refinement.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from reconstruct.free_times import reprojection_px
from reconstruct.solver.problem import Problem, most_observed, reconstructable_points
from reconstruct.tracks_path import start_points
from reconstruct.trajectory import RefineOptions, refine

# A clock error moves every point of its video alike: the most observed points show it, and the cost (one refinement
# per video and hypothesis) grows with points x frames. At most MAX_POINTS points, fewer on long captures (within
# POINT_FRAMES point-frames), never under MIN_POINTS.
MAX_POINTS = 12
MIN_POINTS = 3
POINT_FRAMES = 24_000


@dataclass(kw_only=True)
class HeldOut:
    per_video_px: np.ndarray  # (N,) median held-out reprojection error of each video's rays, NaN where none
    rays_px: np.ndarray  # (R,) every held-out ray's reprojection error

    @property
    def median_px(self) -> float:
        """The median over every held-out ray (inf where no ray could be predicted)."""
        return float(np.median(self.rays_px)) if self.rays_px.size else math.inf


def holds_out(problem: Problem) -> bool:
    """Whether leaving one video out leaves rays to fit: at least three videos observe the points (with two, the one
    left cannot place a point in depth)."""
    return len(np.unique(problem.video_index[problem.observed.any(axis=1)])) >= 3


def heldout_px(problem: Problem, times: np.ndarray, options: RefineOptions) -> HeldOut:
    """For each video, the trajectories refined on the other videos' rays at global `times (F,)`, and its own rays'
    reprojection errors at those trajectories' positions for its frames' times (on the most observed points:
    `point_budget`)."""
    problem = on_most_observed(problem, point_budget(problem.num_frames))
    N = len(problem.video_names)
    per_video = np.full(N, np.nan)
    errors: list[np.ndarray] = []
    for v in range(N):
        own = problem.video_index == v
        if not problem.observed[own].any():
            continue
        uv = problem.uv.copy()
        uv[own] = np.nan
        others = replace(problem, uv=uv)
        if not others.observed.any():
            continue
        fitted = refine(others, start_points(others, times), times, options)
        residual = reprojection_px(problem, fitted.points)[own]
        # a point fewer than two other videos see has no depth from them: no prediction, like one none sees (NaN)
        residual[:, ~reconstructable_points(others)] = np.nan
        residual = residual[np.isfinite(residual)]
        if residual.size:
            per_video[v] = float(np.median(residual))
            errors.append(residual)
    rays = np.concatenate(errors) if errors else np.zeros(0)
    return HeldOut(per_video_px=per_video, rays_px=rays)


def on_most_observed(problem: Problem, count: int) -> Problem:
    """`problem` on its `count` most observed points (ties in point order), or itself when it has no more."""
    if problem.num_points <= count:
        return problem
    keep = np.flatnonzero(most_observed(problem.observed, np.ones(problem.num_points, dtype=bool), count))
    return replace(problem, uv=problem.uv[:, keep], point_names=[problem.point_names[p] for p in keep])


def point_budget(num_frames: int) -> int:
    """How many points the held-out fits use for a capture of `num_frames` frames."""
    return int(np.clip(POINT_FRAMES // max(num_frames, 1), MIN_POINTS, MAX_POINTS))
