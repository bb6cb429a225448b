"""After the self-expressive solve: recover every video's clock, then refine the 3D trajectories on those clocks.

The seed paper stops at local sequencing (W). dynrecon goes on (docs/clocks.md, docs/refinement.md):
1. `clocks.estimate.estimate_clocks`: a clock per video from W's links, and from the tracks where W is ambiguous;
2. `trajectory.refine_with_clocks`: a smoothing-spline trajectory per point through its rays on the recovered global
   times (GCV smoothness, Huber IRLS against false detections), which also polishes each video's offset and rate;
   a polish whose cost rose or that moved a rate far is rejected (`_plausible`), and the trajectories are then
   refined on the estimated clocks;
3. the clocks are refitted to the polished times (`Clocks.refit`), so that sequencing.json's clocks and per-frame
   times agree.
"""

from __future__ import annotations

import enum
import logging
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from reconstruct.clocks.estimate import ClockOptions, estimate_clocks
from reconstruct.clocks.model import ClockModel, Clocks
from reconstruct.solver.alternation import SolveResult
from reconstruct.solver.problem import Problem
from reconstruct.trajectory import RefineOptions, refine, refine_with_clocks

log = logging.getLogger(__name__)

# A polish that moves a rate by more than this (relative) is not believed: short captures legitimately move rates
# by about a per cent, a runaway polish by tens of per cent.
MAX_RATE_CORRECTION = 0.05
POLISH_COST_SLACK = 1.01  # a polish is kept when its trajectory cost never rose above this x its start


class Refinement(enum.Enum):
    NONE = "none"  # keep the self-expressive solve's points (the paper)
    CLOCKS = "clocks"  # smoothing-spline trajectories on the recovered clocks


@dataclass(kw_only=True)
class TemporalOptions:
    clocks: ClockOptions = field(default_factory=ClockOptions)
    # None: offset-only clocks when every frame has a decoder time (phones' timestamps carry the rate, and a free
    # rate can lock onto a wrong period of a periodic motion), else `clocks.model`.
    clock_model: ClockModel | None = None
    refinement: Refinement = Refinement.CLOCKS
    refine: RefineOptions = field(default_factory=RefineOptions)

    def clock_options(self, problem: Problem) -> ClockOptions:
        """The clock options of this solve: `clocks` with the model `clock_model` resolves to."""
        model = self.clock_model
        if model is None:
            model = ClockModel.OFFSET if np.all(np.isfinite(problem.times)) else self.clocks.model
        return replace(self.clocks, model=model)


@dataclass(kw_only=True)
class Temporal:
    clocks: Clocks
    points: np.ndarray  # (F, P, 3) input units: refined, or the solve's when not refined
    times: np.ndarray  # (F,) global seconds, NaN where the clocks could not be recovered
    refined: bool
    report: dict[str, Any]


def recover_and_refine(problem: Problem, result: SolveResult, options: TemporalOptions | None = None) -> Temporal:
    options = options or TemporalOptions()
    clock_options = options.clock_options(problem)
    clocks = estimate_clocks(problem, result, clock_options)
    times = clocks.global_time.copy()
    report: dict[str, Any] = {"refinement": options.refinement.value, "refined": False}
    if options.refinement is Refinement.NONE:
        return Temporal(clocks=clocks, points=result.points, times=times, refined=False, report=report)
    if not np.all(np.isfinite(times)):
        missing = [c.name for c in clocks.videos if not c.identified]
        log.warning(
            "clocks of %s could not be recovered: the trajectories are not refined (the self-expressive solve is kept)",
            ", ".join(missing) or "some frames",
        )
        report["skipped"] = f"unidentified clocks: {', '.join(missing)}"
        return Temporal(clocks=clocks, points=result.points, times=times, refined=False, report=report)
    # The polish's cost does not see a global affine change of time: hold the clocks' reference video fixed so
    # that the polished times stay in the clocks' gauge (reference: offset 0, rate 1). Offset-only clocks trust the
    # decoder's rate: a polish fitting rates anyway made short clips unstable.
    polished = refine_with_clocks(
        problem,
        result.points,
        times,
        options.refine,
        reference=problem.video_names.index(clocks.reference),
        rates=clock_options.model is not ClockModel.OFFSET,
    )
    correction = polished.correction
    cost = [float(c) for c in polished.cost]
    if _plausible(polished.cost, correction.rate, MAX_RATE_CORRECTION):
        clocks = clocks.refit(problem.video_index, polished.times)
        refined = polished.result
        report["clock_corrections"] = [
            {"video": name, "offset_s": float(o), "rate": float(r)}
            for name, o, r in zip(problem.video_names, correction.offset, correction.rate, strict=True)
        ]
    else:
        # A polish started from a seed solve far off can stretch clocks while its cost rises: keep the estimated
        # clocks.
        log.warning(
            "the clock polish of the refinement was rejected (its cost rose or a rate moved by more than "
            "%.0f %%): refining on the estimated clocks",
            100 * MAX_RATE_CORRECTION,
        )
        report["clock_polish_rejected"] = True
        refined = refine(problem, result.points, times, options.refine)
        cost.extend(float(c) for c in refined.cost)
    points = np.where(np.isfinite(refined.points), refined.points, result.points)
    report.update(
        {
            "refined": True,
            "smoothness_median": _finite(np.nanmedian(refined.smoothness)),
            "outlier_observations": int(refined.outliers.sum()),
            "cost": cost,
        }
    )
    return Temporal(clocks=clocks, points=points, times=clocks.global_time.copy(), refined=True, report=report)


def _plausible(cost: list[float], rates: np.ndarray, max_rate_correction: float) -> bool:
    """A clock polish is kept when its trajectory cost never rose above its start and no rate moved far."""
    finite = np.isfinite(cost)
    return bool(
        np.all(finite) and max(cost) <= POLISH_COST_SLACK * cost[0] and np.all(np.abs(rates) <= max_rate_correction)
    )


def _finite(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None
