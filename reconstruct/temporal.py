"""After the self-expressive solve: recover every video's clock, then refine the 3D trajectories on those clocks.

The seed paper stops at local sequencing (W). dynrecon goes on (docs/clocks.md, docs/refinement.md):
1. `clocks.estimate.estimate_clocks`: a clock per video from W's links, and from the tracks where W is ambiguous;
2. `clock_polish.refine_with_clocks`: a smoothing-spline trajectory per point through its rays on the recovered global
   times (GCV smoothness, Huber IRLS against false detections), which also polishes each video's offset and rate;
   a polish whose cost rose or that moved a rate far is rejected (`_plausible`), and the trajectories are then
   refined on the estimated clocks;
3. the clocks are refitted to the polished times (`Clocks.refit`), so that sequencing.json's clocks and per-frame
   times agree.
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from dynrecon.jsonvalues import finite_or_none
from reconstruct.clock_polish import refine_with_clocks
from reconstruct.clocks.estimate import ClockOptions, estimate_clocks
from reconstruct.clocks.model import ClockModel, Clocks
from reconstruct.solver.alternation import SolveResult
from reconstruct.solver.problem import Problem
from reconstruct.time_checks import Check, RefinementJudge, TimePath, clock_checks, rate_unknown
from reconstruct.trajectory import RefineOptions, RefineResult, predicted_pair, predicted_px, refine

log = logging.getLogger(__name__)

# A polish that moves a rate by more than this (relative) is not believed: short captures legitimately move rates
# by about a per cent, a runaway polish by tens of per cent.
MAX_RATE_CORRECTION = 0.05
POLISH_COST_SLACK = 1.01  # a polish is kept when its trajectory cost never rose above this x its start
LINKS_BETTER = 0.8  # W's links' clocks replace the tracks' where their predicted error is below this x the tracks'


class Refinement(enum.Enum):
    NONE = "none"  # keep the self-expressive solve's points (the paper)
    CLOCKS = "clocks"  # smoothing-spline trajectories on the recovered clocks


@dataclass(kw_only=True)
class TemporalOptions:
    clocks: ClockOptions = field(default_factory=ClockOptions)
    # None: offset-only clocks when every frame has a time (phones' timestamps carry the rate, and a free rate can
    # lock onto a wrong period of a periodic motion), else `clocks.model`; `stage.solve` resolves it first where
    # videos have a given rate (`clocks.rates`).
    clock_model: ClockModel | None = None
    refinement: Refinement = Refinement.CLOCKS
    refine: RefineOptions = field(default_factory=RefineOptions)
    # At most this many reconstructable points: clocks from the tracks and trajectories without the self-expressive
    # solve (reconstruct/tracks_path.py), whose W-step slows down sharply as the points get fewer; 0 never takes
    # that path. Its checks fall back to the seed solve.
    tracks_path_max_points: int = 20
    # Beyond that many points the tracks path is tried too, its clocks refereed by the seed solve on a subsample of
    # the frames (reconstruct/tracks_referee.py), which costs a fraction of the whole seed solve; False: the seed
    # solve. Not with tracks_path_max_points 0.
    tracks_path_refereed: bool = True

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
    trajectories: RefineResult | None = None  # the refinement the points come from (None: not refined)


def recover_and_refine(problem: Problem, result: SolveResult, options: TemporalOptions | None = None) -> Temporal:
    """Clocks, then the trajectories on the first time hypothesis that passes its checks (docs/refinement.md,
    "Never worse"): the clock model's times, else a time per frame without a clock model, else the seed solve."""
    options = options or TemporalOptions()
    clock_options = options.clock_options(problem)
    started = time.perf_counter()
    clocks = estimate_clocks(problem, result, clock_options)
    timings = {"clocks": time.perf_counter() - started}
    report: dict[str, Any] = {"refinement": options.refinement.value, "refined": False, "timings": timings}
    started = time.perf_counter()
    try:
        return _recover_and_refine(problem, result, options, clocks, report)
    finally:
        timings["refinement"] = time.perf_counter() - started


def _recover_and_refine(
    problem: Problem, result: SolveResult, options: TemporalOptions, clocks: Clocks, report: dict[str, Any]
) -> Temporal:
    clock_options = options.clock_options(problem)
    times = clocks.global_time.copy()
    if options.refinement is Refinement.NONE:
        report["path"] = TimePath.SEED.value
        return Temporal(clocks=clocks, points=result.points, times=times, refined=False, report=report)
    judge = RefinementJudge(problem, result, options.refine)
    checks = clock_checks(problem, clocks)
    if all(c.passed for c in checks):
        on_clocks = refine_on_clocks(problem, result.points, clocks, clock_options.model, options.refine)
        chosen, on_clocks = _tracks_or_links(problem, judge, clocks, on_clocks, clock_options.model, options, report)
        if chosen is not clocks:  # the links' clocks pass the same checks before they are used
            clocks, checks = chosen, clock_checks(problem, chosen)
        checks.extend(judge.clock_fit(on_clocks.result, rate_unknown(clocks)))
        if all(c.passed for c in checks):
            report.update(on_clocks.report)
            return _finish(problem, result, on_clocks.clocks, on_clocks.result, TimePath.CLOCKS, checks, report)
    failed = next(c for c in checks if not c.passed)
    log.warning("clock model not used: %s; refining without a clock model", failed.sentence())
    free = judge.free()
    free_checks = judge.seed_agreement(free.result, "free_times")
    checks.extend(free_checks)
    if all(c.passed for c in free_checks):
        points, kept = judge.keep_seed_where_far(free.result)
        report.update({"free_times_residual_px": free.residual_px, "seed_points_kept": kept, **judge.free_report()})
        refitted = clocks.refit(problem.video_index, free.times)
        kept_free = dataclasses.replace(free.result, points=points)
        return _finish(problem, result, refitted, kept_free, TimePath.FREE_TIMES, checks, report)
    log.warning(
        "refinement without a clock model not used either: %s; the self-expressive solve is kept",
        free_checks[-1].sentence(),
    )
    _warn_no_clock(clocks)
    report.update({"path": TimePath.SEED.value, "checks": [c.to_json() for c in checks], **judge.free_report()})
    return Temporal(clocks=clocks, points=result.points, times=times, refined=False, report=report)


def _warn_no_clock(clocks: Clocks) -> None:
    """Where no video's clock was recovered against the reference, the seed solve alone placed every video's
    frames: say so, and the usual cause (the videos' tracks follow different subjects)."""
    others = [c.name for c in clocks.videos if c.name != clocks.reference]
    if not others or any(c.identified for c in clocks.videos if c.name != clocks.reference):
        return
    clocks.warnings.append(
        f"no video's clock was recovered against {clocks.reference!r} ({', '.join(others)}): the points rest on the "
        "seed solve alone and may be far off; most often the videos' tracks follow different subjects (a detector's "
        "person numbers are each video's own: `register` with `import-tracks --person all` matches people across "
        "videos), or the subject moves too little"
    )
    log.warning("%s", clocks.warnings[-1])


def _tracks_or_links(
    problem: Problem,
    judge: RefinementJudge,
    clocks: Clocks,
    on_clocks: OnClocks,
    model: ClockModel,
    options: TemporalOptions,
    report: dict[str, Any],
) -> tuple[Clocks, OnClocks]:
    """Where the tracks' clock of some video was kept against W's links (a periodic motion can mislead either), the
    trajectories on the links' clocks too: the hypothesis whose trajectories predict rays they did not see clearly
    better (LINKS_BETTER) is kept, the tracks' otherwise (report.json `temporal.links_clocks`)."""
    alternative = clocks.links_alternative
    if alternative is None:
        return clocks, on_clocks
    on_links = refine_on_clocks(problem, judge.result.points, alternative, model, options.refine)
    residual = judge.residual(on_clocks.result.points), judge.residual(on_links.result.points)
    predicted = predicted_pair(on_clocks.result, on_links.result)
    # the predicted errors where they compare the two, else (no point refined in both) the residuals
    criterion = "predicted_px" if predicted is not None else "residual_px"
    mine, theirs = predicted if predicted is not None else residual
    kept = bool(theirs < LINKS_BETTER * mine)
    videos = [c.name for c, a in zip(clocks.videos, alternative.videos, strict=True) if a.method != c.method]
    report["links_clocks"] = {
        "videos": videos,
        "criterion": criterion,
        "predicted_px": {
            "tracks": finite_or_none(predicted[0] if predicted else None),
            "links": finite_or_none(predicted[1] if predicted else None),
        },
        "residual_px": {"tracks": finite_or_none(residual[0]), "links": finite_or_none(residual[1])},
        "limit": LINKS_BETTER,
        "kept": "links" if kept else "tracks",
    }
    log.warning(
        "clocks of %s: W's links' (%s %.3g px) against the tracks' (%.3g px): the %s' kept",
        ", ".join(videos),
        criterion,
        theirs,
        mine,
        "links" if kept else "tracks",
    )
    return (alternative, on_links) if kept else (clocks, on_clocks)


@dataclass(kw_only=True)
class OnClocks:
    clocks: Clocks
    result: RefineResult
    report: dict[str, Any]


def refine_on_clocks(
    problem: Problem, points: np.ndarray, clocks: Clocks, model: ClockModel, options: RefineOptions
) -> OnClocks:
    """The trajectories on the clocks' times, started from `points (F, P, 3)`, with the clock polish when it is
    plausible."""
    times = clocks.global_time.copy()
    report: dict[str, Any] = {}
    # The polish's cost does not see a global affine change of time: hold the clocks' reference video fixed so
    # that the polished times stay in the clocks' gauge (reference: offset 0, rate 1). Offset-only clocks trust the
    # decoder's rate: a polish fitting rates anyway made short clips unstable.
    polished = refine_with_clocks(
        problem,
        points,
        times,
        options,
        reference=problem.video_names.index(clocks.reference),
        rates=model is not ClockModel.OFFSET,
    )
    correction = polished.correction
    cost = [float(c) for c in polished.cost]
    rejection = _rejection(polished.cost, correction.rate, MAX_RATE_CORRECTION)
    if rejection is None:
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
            "the clock polish of the refinement was rejected (%s): refining on the estimated clocks",
            rejection,
        )
        report["clock_polish_rejected"] = True
        # the polish's own first refinement had these inputs
        refined = polished.at_input if polished.at_input is not None else refine(problem, points, times, options)
        cost.extend(float(c) for c in refined.cost)
    report["cost"] = cost
    return OnClocks(clocks=clocks, result=refined, report=report)


def _finish(
    problem: Problem,
    result: SolveResult,
    clocks: Clocks,
    refined: RefineResult,
    path: TimePath,
    checks: list[Check],
    report: dict[str, Any],
) -> Temporal:
    points = np.where(np.isfinite(refined.points), refined.points, result.points)
    report.update(
        {
            "refined": True,
            "path": path.value,
            "checks": [c.to_json() for c in checks],
            "smoothness_median": finite_or_none(np.nanmedian(refined.smoothness)),
            "predicted_px": finite_or_none(predicted_px(refined)),
            "outlier_observations": int(refined.outliers.sum()),
        }
    )
    return Temporal(
        clocks=clocks, points=points, times=clocks.global_time.copy(), refined=True, report=report, trajectories=refined
    )


def _rejection(cost: list[float], rates: np.ndarray, max_rate_correction: float) -> str | None:
    """Why a clock polish is rejected, in words, or None where it is kept: its trajectory cost never rose above its
    start and no rate moved far."""
    if not cost:
        return "no point was refined at the clocks it started from (every video apart in time?)"
    if not np.all(np.isfinite(cost)):
        return "its cost was not finite"
    # the slack is a share of the start's size: a trajectory cost can be negative (exact data)
    if max(cost) > cost[0] + (POLISH_COST_SLACK - 1.0) * abs(cost[0]):
        return f"its cost rose from {cost[0]:.6g} to {max(cost):.6g}"
    if np.all(np.abs(rates) <= max_rate_correction):
        return None
    return f"a rate moved by {100 * float(np.max(np.abs(rates))):.1f} %, over {100 * max_rate_correction:.0f} %"


def _plausible(cost: list[float], rates: np.ndarray, max_rate_correction: float) -> bool:
    """A clock polish is kept when `_rejection` finds nothing against it."""
    return _rejection(cost, rates, max_rate_correction) is None
