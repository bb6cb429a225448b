"""After the self-expressive solve: recover every video's clock, then refine the 3D trajectories on those clocks.

The seed paper stops at local sequencing (W). dynrecon goes on (docs/solver.md, "Beyond the paper"):
1. `clocks.estimate_clocks`: an affine clock per video from W's links, and from the tracks where W is ambiguous;
2. `refine.refine_with_clocks`: a smoothing-spline trajectory per point through its rays on the recovered global
   times (GCV smoothness, Huber IRLS against false detections), which also polishes each video's offset and rate;
3. the clocks are refitted to the polished times, so that sequencing.json's clocks and per-frame times agree.
"""

from __future__ import annotations

import enum
import logging
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from reconstruct.clocks.estimate import ClockModel, ClockOptions, Clocks, estimate_clocks
from reconstruct.solver.alternation import SolveResult
from reconstruct.solver.problem import Problem
from reconstruct.trajectory import ClockRefineOptions, RefineOptions, refine, refine_with_clocks

log = logging.getLogger(__name__)


class Refinement(enum.Enum):
    NONE = "none"  # keep the self-expressive solve's points (the paper)
    CLOCKS = "clocks"  # smoothing-spline trajectories on the recovered clocks


@dataclass(kw_only=True)
class TemporalOptions:
    clocks: ClockOptions = field(default_factory=ClockOptions)
    # None: offset-only clocks when every frame has a decoder time (phones' timestamps carry the rate; drift of
    # ~100 ppm is ~6 ms per minute), else `clocks.model`. Measured on the periodic treadmill walk of the video sample:
    # affine clocks locked cam1 three steps off with rate 0.73 (4.4 % < 10 mm after refinement); offset-only clocks
    # gave 90.3 %.
    clock_model: ClockModel | None = None
    refinement: Refinement = Refinement.CLOCKS
    refine: RefineOptions = field(default_factory=RefineOptions)
    clock_refine: ClockRefineOptions = field(default_factory=ClockRefineOptions)
    # A polish that moves a rate by more than this (relative) is not believed. Short captures legitimately move
    # rates by ~1 % (the 1 s demo cut: 0.75-0.9 %); the runaway seen on the flight scene was 24 %.
    max_rate_correction: float = 0.05


@dataclass(kw_only=True)
class Temporal:
    clocks: Clocks
    points: np.ndarray  # (F, P, 3) input units: refined, or the solve's when not refined
    times: np.ndarray  # (F,) global seconds, NaN where the clocks could not be recovered
    refined: bool
    report: dict[str, Any]


def recover_and_refine(problem: Problem, result: SolveResult, options: TemporalOptions | None = None) -> Temporal:
    options = options or TemporalOptions()
    model = options.clock_model
    if model is None:
        model = ClockModel.OFFSET if np.all(np.isfinite(problem.times)) else options.clocks.model
    clocks = estimate_clocks(problem, result, replace(options.clocks, model=model))
    times = clocks.global_time.copy()
    report: dict[str, Any] = {"refinement": options.refinement.value, "refined": False}
    if options.refinement is Refinement.NONE:
        return Temporal(clocks=clocks, points=result.points, times=times, refined=False, report=report)
    if not np.all(np.isfinite(times)):
        missing = [c.name for c in clocks.videos if not c.identified]
        log.warning("clocks of %s could not be recovered: the trajectories are not refined (the self-expressive "
                    "solve is kept)", ", ".join(missing) or "some frames")
        report["skipped"] = f"unidentified clocks: {', '.join(missing)}"
        return Temporal(clocks=clocks, points=result.points, times=times, refined=False, report=report)
    # The polish's cost does not see a global affine change of time: hold the clocks' reference video fixed so
    # that the polished times stay in the clocks' gauge (reference: offset 0, rate 1).
    clock_refine = options.clock_refine
    if clock_refine.reference is None:
        clock_refine = replace(clock_refine, reference=problem.video_names.index(clocks.reference))
    if model is ClockModel.OFFSET:
        # Offset-only clocks trust the decoder's rate; letting the polish fit rates anyway made short clips
        # unstable (the 1 s demo cut: a 4.6 % rate correction was accepted and gave 39 % < 10 mm, against 75-90 %
        # on other registrations of the same clip).
        clock_refine = replace(clock_refine, rates=False)
    polished = refine_with_clocks(problem, result.points, times, options.refine, clock_refine)
    cost = [float(c) for c in polished.cost]
    if _plausible(polished.cost, polished.rates, options.max_rate_correction):
        clocks = refit_clocks(clocks, problem.video_index, polished.times)
        refined = polished.result
        report["clock_corrections"] = [{"video": name, "offset_s": float(o), "rate": float(r)} for name, o, r in
                                       zip(problem.video_names, polished.offsets, polished.rates, strict=True)]
    else:
        # Measured on the flight scene (one point, 3 % false detections): started from a seed solve metres off,
        # the polish stretched two clocks by 24 % while its cost rose 1e6-fold. Keep the estimated clocks.
        log.warning("the clock polish of the refinement was rejected (its cost rose or a rate moved by more than "
                    "%.0f %%): refining on the estimated clocks", 100 * options.max_rate_correction)
        report["clock_polish_rejected"] = True
        refined = refine(problem, result.points, times, options.refine)
        cost.extend(float(c) for c in refined.cost)
    points = np.where(np.isfinite(refined.points), refined.points, result.points)
    report.update({
        "refined": True,
        "smoothness_median": _finite(np.nanmedian(refined.smoothness)),
        "outlier_observations": int(refined.outliers.sum()),
        "cost": cost,
    })
    return Temporal(clocks=clocks, points=points, times=clocks.global_time.copy(), refined=True, report=report)


def _plausible(cost: list[float], rates: np.ndarray, max_rate_correction: float) -> bool:
    """A clock polish is kept when its trajectory cost never rose above its start and no rate moved far."""
    finite = np.isfinite(cost)
    return bool(np.all(finite) and max(cost) <= 1.01 * cost[0] and np.all(np.abs(rates) <= max_rate_correction))


def refit_clocks(clocks: Clocks, video_index: np.ndarray, times: np.ndarray) -> Clocks:
    """The clocks with each video's offset/rate(/drift) refitted to `times (F,)` by least squares on its own
    times, and those times as the per-frame global times (the uncertainties are kept). `times` must be in the
    clocks' gauge (the reference video's global time = its own time)."""
    degree = 2 if clocks.model is ClockModel.DRIFT else 1
    for v, clock in enumerate(clocks.videos):
        own = video_index == v
        if own.sum() <= degree or not clock.identified:
            continue
        coefficients = np.polyfit(clocks.own_time[own], times[own], degree)[::-1]
        clock.offset, clock.rate = float(coefficients[0]), float(coefficients[1])
        if degree == 2:
            clock.drift = float(coefficients[2])
    clocks.global_time = np.asarray(times, dtype=float).copy()
    return clocks


def _finite(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None
