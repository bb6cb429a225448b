"""Do the written trajectories fit the tracks at all? A calibration of another session, another image size or a
mirrored world leaves every point tens of pixels off its observations, and the trust flag, whose limits follow the
capture's own medians, cannot see a miss that is everywhere (a two-camera jump with a DLT of its calibration
object: 26 px median, 94 % of the points unflagged).

The measure: the written points' median reprojection error over the observed points; where the self-expressive
solve is the output (its points lie on their rays by construction), its median self-expression residual in pixels
instead. Above `WARN_PX` (or `WARN_DIAGONAL` of the image diagonal, for large images) the solve warns, and
report.json `fit` says which measure and how far.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from reconstruct.solver.problem import Problem
from reconstruct.solver.rays import viewing_rays
from reconstruct.trust import Trust, ray_distances

log = logging.getLogger(__name__)

WARN_PX = 10.0  # real captures with their own cameras fit within 0.3-3.2 px (docs/measurements.md)
WARN_DIAGONAL = 0.005  # ... or this share of the image diagonal, if larger


def check_fit(problem: Problem, points: np.ndarray, trust: Trust, refined: bool) -> dict[str, Any]:
    """report.json `fit`: the median miss of the written `points (F, P, 3)` against the observations (`refined`),
    or the seed solve's median self-expression residual (not refined), and whether it exceeds the limit."""
    observed = problem.observed & np.isfinite(points).all(axis=-1)
    if refined:
        focal = 0.5 * (problem.K[:, 0, 0] + problem.K[:, 1, 1])
        _, px = ray_distances(points - problem.centers[:, None, :], viewing_rays(problem), observed, focal)
        measure = "reprojection of the written points (median over observed points)"
    else:
        px = np.where(observed, trust.residual_px, np.nan)
        measure = "self-expression residual of the seed solve (median over observed points, px)"
    values = px[observed & np.isfinite(px)]
    if not values.size:
        return {"measure": measure, "median_px": None, "limit_px": None, "fits": None}
    diagonal = float(np.median(2.0 * np.hypot(problem.K[:, 0, 2], problem.K[:, 1, 2])))  # principal points ~ centre
    limit = max(WARN_PX, WARN_DIAGONAL * diagonal)
    median = float(np.median(values))
    per_video = {
        name: float(np.median(px[(problem.video_index == v)[:, None] & observed & np.isfinite(px)]))
        for v, name in enumerate(problem.video_names)
        if np.any(observed[problem.video_index == v])
    }
    if median > limit:
        log.warning(
            "the written points miss the tracks by a median of %.1f px (over %.0f px; %s): the cameras may not be this "
            "capture's (another session's calibration, another image size, a mirrored world, or given to the wrong "
            "videos: import-calibration matches cameras to videos by order where their names differ) or the tracks "
            "follow another subject; the trust flag, relative to the capture's own medians, does not show this",
            median,
            limit,
            ", ".join(f"{name} {value:.1f} px" for name, value in per_video.items()),
        )
    return {
        "measure": measure,
        "median_px": median,
        "p90_px": float(np.percentile(values, 90)),
        "per_video_px": per_video,
        "limit_px": limit,
        "fits": median <= limit,
    }


__all__ = ["WARN_DIAGONAL", "WARN_PX", "check_fit"]
