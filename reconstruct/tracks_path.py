"""The path for few points (issue 22): clocks from the tracks and poses alone, then spline trajectories through the
rays on those clocks, without the self-expressive solve (docs/refinement.md, "Few points: the tracks path").

With one to a few points, a W column's Gram matrix has rank at most 3P while its working set holds many more
entries: the seed solve's W-step is singular and stalls (docs/measurements.md). The clocks do not need W there: the
track search finds them from the tracks and poses, and with the clocks a smoothing spline through the rays is the
trajectory. Steps:

1. `estimate_clocks_from_tracks`, checked by `time_checks.clock_checks` (every video clocked, a distinct offset);
2. start points: every observation triangulated at its frame's global time with the nearest observations of the
   other videos (`start_points`);
3. `clock_polish.refine_with_clocks` on those clocks (the polish checked as on the clocks path), then the fit check
   `tracks_fit`: the trajectories meet their rays about as closely as the track search's rays met each other.

Beyond `TemporalOptions.tracks_path_max_points` the path is refereed: its clocks must also agree with those of W's
links from the seed solve on a subsample of the frames (reconstruct/tracks_referee.py). Where a check fails,
`solve_on_tracks` says which, and `reconstruct.stage.solve` falls back to the seed solve.
"""

from __future__ import annotations

import logging
import math
import time
from contextlib import ExitStack
from dataclasses import dataclass
from typing import Any

import numpy as np

from dynrecon.beside import beside
from dynrecon.jsonvalues import finite_or_none
from reconstruct.clocks.estimate import ClockOptions, estimate_clocks_from_tracks
from reconstruct.clocks.model import ClockModel, Clocks, frame_periods
from reconstruct.clocks.ray_gap import ray_gap_px
from reconstruct.free_times import reprojection_px
from reconstruct.solver.alternation import SolveResult, SolverOptions
from reconstruct.solver.blas import one_blas_thread
from reconstruct.solver.initialize import PairInit
from reconstruct.solver.problem import Problem, reconstructable_points
from reconstruct.solver.rays import camera_normalization, viewing_rays
from reconstruct.solver.unseen_frames import take_frames
from reconstruct.solver.wstep import SparseW
from reconstruct.temporal import OnClocks, Temporal, TemporalOptions, refine_on_clocks
from reconstruct.time_checks import MIN_DISTINCTNESS, Check, clock_checks, given_offsets_check
from reconstruct.tracks_referee import compare, referee_times, subsample, subsample_without_clocks
from reconstruct.trajectory import predicted_px

log = logging.getLogger(__name__)

# A partner observation of another video is used for the start when it lies within this many of its frame periods.
PARTNER_PERIODS = 1.0
# The trajectories' median reprojection residual may exceed the track search's robust gap by this factor plus
# TRACKS_FIT_PX: right clocks let a spline meet every ray about as closely as interpolated rays meet each other.
TRACKS_FIT_FACTOR = 1.5
TRACKS_FIT_PX = 1.0
# Beyond a few points the seed solve is affordable and W's links tell the cycles of a periodic motion apart, which
# the track search alone may not: there the tracks' clocks must win their search clearly.
FEW_POINTS = 3
MANY_POINTS_DISTINCTNESS = 3.0
PATH = "tracks"  # report.json temporal.path of this path


@dataclass(kw_only=True)
class TracksAttempt:
    """The tracks path's result: `temporal` and `seed` when every check passed, else None and the report says why."""

    temporal: Temporal | None
    seed: SolveResult | None
    report: dict[str, Any]
    clocks: Clocks | None = None  # the clocks tried (also when a check failed)


def applies(problem: Problem, max_points: int) -> bool:
    """The tracks path is tried when the problem has at most `max_points` reconstructable points (0: never)."""
    count = int(reconstructable_points(problem).sum())
    return 0 < count <= max_points


def refereed(problem: Problem, options: TemporalOptions) -> bool:
    """The tracks path is tried with the referee when the problem has more than `tracks_path_max_points` (> 0)
    reconstructable points and `tracks_path_refereed` is on."""
    max_points = options.tracks_path_max_points
    count = int(reconstructable_points(problem).sum())
    return options.tracks_path_refereed and 0 < max_points < count


def start_points(problem: Problem, times: np.ndarray) -> np.ndarray:
    """(F, P, 3) every observation triangulated (least squares over rays) with the observation of each other video
    nearest in global time, when within PARTNER_PERIODS of that video's frame periods; NaN elsewhere."""
    F, P = problem.num_frames, problem.num_points
    N = len(problem.video_names)
    rays = viewing_rays(problem)
    centers = problem.centers
    periods = frame_periods(times, problem.video_index, N)
    out = np.full((F, P, 3), np.nan)
    eye = np.eye(3)
    for p in range(P):
        seen = problem.observed[:, p] & np.isfinite(times)
        frames = np.flatnonzero(seen)
        if frames.size == 0:
            continue
        projector = eye - rays[frames, p, :, None] * rays[frames, p, None, :]  # (m, 3, 3)
        A = projector.copy()
        b = np.einsum("mij,mj->mi", projector, centers[frames])
        videos = np.ones(frames.size, dtype=np.int64)
        for u in range(N):
            mine = frames[problem.video_index[frames] == u]
            if mine.size == 0:
                continue
            mine = mine[np.argsort(times[mine], kind="stable")]
            t_u = times[mine]
            k = np.clip(np.searchsorted(t_u, times[frames]), 1, max(len(t_u) - 1, 1))
            before, after = mine[k - 1], mine[np.minimum(k, len(mine) - 1)]
            nearest = np.where(
                np.abs(times[after] - times[frames]) < np.abs(times[before] - times[frames]), after, before
            )
            near = np.abs(times[nearest] - times[frames]) <= PARTNER_PERIODS * periods[u]
            use = near & (problem.video_index[frames] != u)
            partner = nearest[use]
            proj_u = eye - rays[partner, p, :, None] * rays[partner, p, None, :]
            A[use] += proj_u
            b[use] += np.einsum("mij,mj->mi", proj_u, centers[partner])
            videos[use] += 1
        solvable = (videos >= 2) & (np.linalg.cond(A) < 1e8)
        out[frames[solvable], p] = np.linalg.solve(A[solvable], b[solvable, :, None])[..., 0]
    return out


def solve_on_tracks(problem: Problem, options: TemporalOptions, referee: SolverOptions | None = None) -> TracksAttempt:
    """Clocks from the tracks, start points, trajectories on the clocks, each checked (module docstring); with
    `referee`, the clocks must also agree with the seed solve's on a subsample (reconstruct/tracks_referee.py).

    The referee's solve runs beside the rest (`dynrecon/beside.py`: a forked process where safe, else a thread):
    from the start where its subsample does not need the clocks, else from the track search's end; only its
    verdict waits for it. Everything runs with one BLAS thread then, so that neither result depends on when the
    other's BLAS calls happen."""
    with ExitStack() as stack:
        if referee is not None:
            stack.enter_context(one_blas_thread())
        return _attempt(problem, options, referee, stack)


def _attempt(
    problem: Problem, options: TemporalOptions, referee: SolverOptions | None, stack: ExitStack
) -> TracksAttempt:
    t0 = time.perf_counter()
    what = f"the tracks path on the {len(problem.video_names)} videos was"  # a second try may take fewer
    clock_options = options.clock_options(problem)
    index = subsample_without_clocks(problem) if referee is not None else None
    running, beside_what = None, ""
    if referee is not None and index is not None:
        running = stack.enter_context(beside(_timed_referee, problem, index, referee, clock_options))
        beside_what = "track search and refinement"
    clocks = estimate_clocks_from_tracks(problem, clock_options)
    timings = {"clocks": time.perf_counter() - t0}
    report: dict[str, Any] = {"refinement": options.refinement.value, "refined": False, "timings": timings}
    many = int(reconstructable_points(problem).sum()) > FEW_POINTS
    checks = clock_checks(problem, clocks, MANY_POINTS_DISTINCTNESS if many else MIN_DISTINCTNESS)
    if not all(c.passed for c in checks):
        return _failed(checks, report, clocks, what)  # leaving the stack stops a referee still running
    if referee is not None and running is None:
        index = subsample(problem, clocks.global_time)
        running = stack.enter_context(beside(_timed_referee, problem, index, referee, clock_options))
        beside_what = "refinement"
    t0 = time.perf_counter()
    start = start_points(problem, clocks.global_time)
    timings["start_points"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    on_clocks = _refine(problem, start, clocks, clock_options.model, options, checks)
    if on_clocks is None:
        # clocks that passed the track checks but break the refinement: the seed solve decides, as on a failed check
        return _failed(checks, report, clocks, what)
    timings["refinement"] = time.perf_counter() - t0
    if running is not None and index is not None:
        t0 = time.perf_counter()
        referee_time, seconds = running.result()
        check, report["referee"] = compare(problem, clocks, index, referee_time, seconds)
        # its seconds overlap those of the steps it ran beside; timings.referee_wait is what the solve waited
        ran_in = "caller" if running.redone else "process" if running.forked else "thread"
        report["referee"].update({"beside": beside_what, "ran_in": ran_in})
        timings["referee"] = seconds
        timings["referee_wait"] = time.perf_counter() - t0
        checks.append(check)
        if not check.passed:
            return _failed(checks, report, clocks, what)
    gap = clocks.diagnostics.get("track_residual_px")
    checks.append(_fit_check(problem, on_clocks, gap if isinstance(gap, float) else math.nan, "the tracks' clocks"))
    if not all(c.passed for c in checks):
        return _failed(checks, report, clocks, what)
    placed = int((np.isfinite(start).all(axis=-1).any(axis=0)).sum())
    reason = f"{placed} reconstructable point(s): clocks from the tracks, no self-expressive solve"
    return _accepted(problem, start, on_clocks, checks, report, reason, PATH)


def solve_on_given_clocks(problem: Problem, clocks: Clocks, options: TemporalOptions, path: str) -> TracksAttempt:
    """The tracks path's trajectories and fit check on clocks it did not find itself (registration's or declared
    offsets, for few points whose tracks do not single out their clocks, where the seed solve is singular): the
    fit's yardstick is how closely the tracks' rays meet at those clocks (`clocks/ray_gap.py`). `path` names the
    result in report.json `temporal.path`."""
    t0 = time.perf_counter()
    report: dict[str, Any] = {"refinement": options.refinement.value, "refined": False, "timings": {}}
    check, verdicts = given_offsets_check(problem, clocks, options.clocks.track_search)
    report["given_offsets"] = [v.to_json() for v in verdicts]
    checks = [check]
    if not check.passed:
        return _failed(checks, report, clocks, what="cameras.json's clock offsets were")
    gap = ray_gap_px(problem, clocks.global_time)
    start = start_points(problem, clocks.global_time)
    on_clocks = _refine(problem, start, clocks, clocks.model, options, checks)
    if on_clocks is None:
        return _failed(checks, report, clocks, what="cameras.json's clock offsets were")
    checks.append(_fit_check(problem, on_clocks, gap, "these clocks"))
    report["timings"]["refinement"] = time.perf_counter() - t0
    report["ray_gap_px"] = finite_or_none(gap)
    if not checks[-1].passed:
        return _failed(checks, report, clocks, what="cameras.json's clock offsets were")
    placed = int((np.isfinite(start).all(axis=-1).any(axis=0)).sum())
    reason = f"{placed} reconstructable point(s) on cameras.json's clock offsets, no self-expressive solve"
    return _accepted(problem, start, on_clocks, checks, report, reason, path)


@dataclass(kw_only=True)
class Clocked:
    """`solve_without_unclocked`'s result: the problem on the clocked videos, the path's result on it (as
    `TracksAttempt`'s when it passes), and the videos left out."""

    problem: Problem
    seed: SolveResult
    temporal: Temporal
    left_out: list[str]


def solve_without_unclocked(problem: Problem, attempt: TracksAttempt, options: TemporalOptions) -> Clocked | None:
    """Few points whose tracks clock some videos but not all (the path's `identified` check failed): the path on the
    clocked videos alone, each of the others left out of the solve, instead of the seed solve, which is singular
    for so few points; None where fewer than two videos were clocked or the path fails a check there too (said in
    `attempt.report["without_unclocked"]`)."""
    if attempt.clocks is None or attempt.report.get("failed") != "identified":
        return None
    clocked = np.array([video.identified for video in attempt.clocks.videos])
    if clocked.sum() < 2 or clocked.all():
        return None
    kept = take_frames(problem, clocked[problem.video_index])
    if not reconstructable_points(kept).any():
        return None
    again = solve_on_tracks(kept, options)
    if again.temporal is None or again.seed is None:
        attempt.report["without_unclocked"] = {
            key: again.report[key] for key in ("checks", "failed") if key in again.report
        }
        return None
    left_out = [name for name, ok in zip(problem.video_names, clocked, strict=True) if not ok]
    return Clocked(problem=kept, seed=again.seed, temporal=again.temporal, left_out=left_out)


def _refine(
    problem: Problem,
    start: np.ndarray,
    clocks: Clocks,
    model: ClockModel,
    options: TemporalOptions,
    checks: list[Check],
) -> OnClocks | None:
    """`refine_on_clocks`, or None with a failed `refinement` check appended when it raises a numerical error."""
    try:
        return refine_on_clocks(problem, start, clocks, model, options.refine)
    except (np.linalg.LinAlgError, ValueError, FloatingPointError) as error:
        checks.append(
            Check(
                name="refinement",
                value=1.0,
                limit=0.0,
                passed=False,
                meaning=f"the refinement on the clocks failed ({type(error).__name__}: {error}); failures",
            )
        )
        return None


def _fit_check(problem: Problem, on_clocks: OnClocks, gap: float, clocks_name: str) -> Check:
    """`tracks_fit`: the trajectories meet their rays about as closely as the rays meet each other on the clocks."""
    residual = reprojection_px(problem, on_clocks.result.points)
    finite = residual[np.isfinite(residual)]
    median = float(np.median(finite)) if finite.size else math.nan
    gap = gap if math.isfinite(gap) else 0.0
    limit = TRACKS_FIT_FACTOR * gap + TRACKS_FIT_PX
    return Check(
        name="tracks_fit",
        value=median,
        limit=limit,
        passed=bool(median <= limit),
        meaning=f"median reprojection residual (px) on {clocks_name}, against their {gap:.3g} px ray gap",
    )


def _accepted(
    problem: Problem,
    start: np.ndarray,
    on_clocks: OnClocks,
    checks: list[Check],
    report: dict[str, Any],
    reason: str,
    path: str,
) -> TracksAttempt:
    refined = on_clocks.result
    points = np.where(np.isfinite(refined.points), refined.points, start)
    report.update(on_clocks.report)
    report.update(
        {
            "refined": True,
            "path": path,
            "checks": [c.to_json() for c in checks],
            "smoothness_median": finite_or_none(np.nanmedian(refined.smoothness)),
            "predicted_px": finite_or_none(predicted_px(refined)),
            "outlier_observations": int(refined.outliers.sum()),
            "reason": reason,
        }
    )
    temporal = Temporal(
        clocks=on_clocks.clocks,
        points=points,
        times=on_clocks.clocks.global_time.copy(),
        refined=True,
        report=report,
        trajectories=refined,
    )
    return TracksAttempt(
        temporal=temporal,
        seed=clocks_seed(problem, start, points, on_clocks.clocks.global_time, report["timings"]),
        report=report,
        clocks=on_clocks.clocks,
    )


def _timed_referee(
    problem: Problem, index: np.ndarray, referee: SolverOptions, clock_options: ClockOptions
) -> tuple[np.ndarray, float]:
    started = time.perf_counter()
    return referee_times(problem, index, referee, clock_options), time.perf_counter() - started


def _failed(
    checks: list[Check], report: dict[str, Any], clocks: Clocks, what: str = "the tracks path was"
) -> TracksAttempt:
    failed = next(c for c in checks if not c.passed)
    log.warning("%s not used: %s", what, failed.sentence())
    report.update({"checks": [c.to_json() for c in checks], "failed": failed.name})
    return TracksAttempt(temporal=None, seed=None, report=report, clocks=clocks)


def clocks_seed(
    problem: Problem, start: np.ndarray, points: np.ndarray, times: np.ndarray, timings: dict[str, float]
) -> SolveResult:
    """What `Reconstruction.seed` holds on this path: the start points, W from the clocks (`time_w`) and the
    refined points' residual against it, no initialization pairs and no solver stages."""
    F, P = problem.num_frames, problem.num_points
    W = time_w(problem, times)
    shapes = np.nan_to_num(points).reshape(F, -1)
    residual = np.sqrt(np.mean((shapes - W.to_csc().T @ shapes).reshape(F, P, 3).__pow__(2).sum(axis=-1), axis=1))
    return SolveResult(
        points=start,
        W=W,
        reconstructable=reconstructable_points(problem),
        init=PairInit(partner=np.full(F, -1), cost=np.full(F, np.nan), depth=np.full((F, P), np.nan)),
        normalization=camera_normalization(problem.centers, problem.video_index),
        stages=[],
        timings=dict(timings),
        residual=np.where(W.valid.any(axis=1), residual, np.nan),
        init_points=start,
    )


def time_w(problem: Problem, times: np.ndarray) -> SparseW:
    """W from the clocks: each frame as the linear interpolation, at its global time, between the two bracketing
    frames of every other video that spans it (equal shares per video): the sequencing a time axis implies."""
    F = problem.num_frames
    N = len(problem.video_names)
    periods = frame_periods(times, problem.video_index, N)
    cand = np.zeros((F, 2 * N), dtype=np.int64)
    value = np.zeros((F, 2 * N))
    valid = np.zeros((F, 2 * N), dtype=bool)
    for u in range(N):
        mine = np.flatnonzero((problem.video_index == u) & np.isfinite(times))
        if mine.size < 2:
            continue
        mine = mine[np.argsort(times[mine], kind="stable")]
        k = np.clip(np.searchsorted(times[mine], times, side="right"), 1, len(mine) - 1)
        before, after = mine[k - 1], mine[k]
        span = times[after] - times[before]
        share = (times - times[before]) / np.where(span > 0, span, 1.0)
        spans = (share >= 0) & (share <= 1) & (span > 0) & (span <= 2.5 * periods[u]) & (problem.video_index != u)
        cand[:, 2 * u], cand[:, 2 * u + 1] = before, after
        value[:, 2 * u], value[:, 2 * u + 1] = 1 - share, share
        valid[:, 2 * u] = valid[:, 2 * u + 1] = spans
    count = valid.sum(axis=1) / 2
    value = np.where(valid, value / np.maximum(count, 1)[:, None], 0.0)
    return SparseW(cand=cand, valid=valid, value=value)
