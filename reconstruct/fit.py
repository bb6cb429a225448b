"""Do the written trajectories fit the tracks at all? A calibration of another session, another image size or a
mirrored world leaves every point tens of pixels off its observations, and the trust flag, whose limits follow the
capture's own medians, cannot see a miss that is everywhere (a two-camera jump with a DLT of its calibration
object: 26 px median, 94 % of the points unflagged).

The measure: the written points' median reprojection error over the observed points; where the self-expressive
solve is the output (its points lie on their rays by construction), its median self-expression residual in pixels
instead. Refined trajectories may bend through every ray (one point seen by one video per instant: a flight with
two cameras of another session fits its rays to a thousandth of a pixel): where their reprojection is a small share
(`BENT_SHARE`) of their error predicted for an unseen ray (GCV, `trajectory.predicted_px`), each video's rays
predicted by the trajectories the other videos alone give (`heldout.heldout_px`) are judged instead, or GCV's
prediction where fewer than three videos see the points (docs/formats.md). GCV's own prediction barely moves with
cameras of another session (the trajectory bends between rays of different videos as it does through noise); rays
held out are met only where the cameras agree. Above `WARN_PX` (or `WARN_DIAGONAL` of the image diagonal, for
large images) the solve warns, and report.json `fit` says which measure and how far.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from reconstruct.solver.problem import Problem
from reconstruct.solver.rays import viewing_rays
from reconstruct.trust import Trust, ray_distances

log = logging.getLogger(__name__)

WARN_PX = 10.0  # real captures with their own cameras fit within 0.3-3.2 px (docs/measurements.md)
WARN_DIAGONAL = 0.005  # ... or this share of the image diagonal, if larger
BENT_SHARE = 0.1  # refined points whose reprojection is under this share of GCV's predicted error sit on their rays


def check_fit(
    problem: Problem,
    points: np.ndarray,
    trust: Trust,
    refined: bool,
    predicted: float | None = None,
    heldout: Callable[[], tuple[float, dict[str, float]] | None] | None = None,
) -> dict[str, Any]:
    """report.json `fit`: the median miss of the written `points (F, P, 3)` against the observations (`refined`;
    where they pass through their rays, `heldout()`: the median error of each video's rays predicted from the
    others', and per video (None where it cannot be measured), else `predicted`, their error predicted for an unseen
    ray), or the seed solve's median self-expression residual (not refined), and whether it exceeds the limit."""
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
    median = reprojection = float(np.median(values))
    # the trajectories pass through their rays (the reprojection a small share of the predicted error, or every
    # smoothness fitting them exactly: inf): the reprojection says nothing there, the prediction does
    bent = refined and predicted is not None and not math.isnan(predicted) and reprojection < BENT_SHARE * predicted
    if bent and predicted is not None and math.isinf(predicted):
        log.info("fit: the trajectories pass through every ray at every smoothness; no measure of fit is left")
        return {
            "measure": "none: the trajectories pass through every ray at every smoothness",
            "median_px": None,
            "reprojection_px": reprojection,
            "predicted_px": None,
            "limit_px": None,
            "fits": None,
        }
    held = heldout() if bent and heldout is not None else None
    if held is not None and not math.isfinite(held[0]):
        held = None
    if held is not None:
        median = held[0]
        measure = (
            "each video's rays predicted by the other videos' trajectories (held out, median over rays): the"
            " trajectories pass through their rays"
        )
    elif bent:
        median = float(predicted)  # type: ignore[arg-type]
        measure = (
            "error the trajectories predict for an unseen ray (GCV, median over points): they pass through their rays"
        )
    per_video = (
        held[1]
        if held is not None
        else {
            name: float(np.median(px[(problem.video_index == v)[:, None] & observed & np.isfinite(px)]))
            for v, name in enumerate(problem.video_names)
            if np.any(observed[problem.video_index == v])
        }
    )
    if median > limit:
        log.warning(
            "the %s miss the tracks by a median of %.1f px (over %.0f px%s): the cameras may not be this "
            "capture's (another session's calibration, another image size, a mirrored world, or given to the wrong "
            "videos: import-calibration matches cameras to videos by order where their names differ) or the tracks "
            "follow another subject; the trust flag, relative to the capture's own medians, does not show this",
            "trajectories predicted for rays held out" if bent else "written points",
            median,
            limit,
            ""
            if bent and held is None
            else "; " + ", ".join(f"{name} {value:.1f} px" for name, value in per_video.items()),
        )
    return {
        "measure": measure,
        "median_px": median,
        "reprojection_px": reprojection if refined else None,
        "predicted_px": float(predicted) if refined and predicted is not None and math.isfinite(predicted) else None,
        "heldout_px": held[0] if held is not None else None,
        "p90_px": None if bent else float(np.percentile(values, 90)),  # GCV gives no distribution over rays
        "per_video_px": per_video,  # of the measure judged: the held-out rays' where those are
        "limit_px": limit,
        "fits": median <= limit,
    }


__all__ = ["BENT_SHARE", "WARN_DIAGONAL", "WARN_PX", "check_fit"]
