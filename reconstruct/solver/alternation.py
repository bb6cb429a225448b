"""The self-expressive solver: alternate the W-step and the X-step, first with the smoothness term Psi2, then
without it (paper, Sec. "Optimization" and "Sequencing information").

All work happens in normalized world coordinates (average distance between cameras = 1); results come back in the
input's units.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from tqdm import tqdm

from dynrecon.errors import DynreconError, NotEnoughDataError
from reconstruct.solver.anderson import AndersonMixer
from reconstruct.solver.candidates import CandidateOptions, MovingWindows, coarse_to_fine_init
from reconstruct.solver.initialize import PairInit, fill_missing_points, initialize_depths
from reconstruct.solver.problem import Problem, reconstructable_points
from reconstruct.solver.rays import Normalization, camera_normalization, viewing_rays
from reconstruct.solver.wstep import SparseW, WStepOptions, solve_w
from reconstruct.solver.xstep import RayConstraint, XStepOptions, chain_links, solve_x

log = logging.getLogger(__name__)


@dataclass(kw_only=True)
class SolverOptions:
    lambda1: float = 0.05  # structural coherence Psi1
    lambda2: float = 0.1  # smoothness Psi2 in the first stage (the second stage uses 0)
    lambda3: float = 100.0  # soft ray constraint
    constraint: RayConstraint = RayConstraint.SOFT
    max_iterations: int = 200  # alternations per stage
    # Stop a stage when the relative cost decrease falls below this ... and the points have settled (below). With
    # Anderson mixing the tail of alternations buys little: on the paper's tables (5 windows x 14 rows at 2.7 m) 1e-3
    # against 1e-4 moved every row by at most 0.25 points under 10 mm, both ways (noise 1 px 97.05 -> 96.85 %,
    # missing 40 % 94.99 -> 94.76 %, missing 50 % 90.23 -> 91.22 %; mean +0.03), while CMU F = 700 took 6 + 18
    # alternations instead of 6 + 23 (100 % both) and complexknee F = 20,000 9 + 33 instead of 9 + 50 (116 s against
    # 147 s, 99.87 % both; benchmarks/long_capture.py). 1e-5 had been as accurate with 9 + 121 at F = 20,000.
    tolerance: float = 1e-3
    # The smoothing stage only has to pull wrong initial shapes out of their local minima; it need not converge to
    # the Psi2-biased optimum that the final stage leaves anyway.
    smooth_tolerance: float = 1e-3
    point_tolerance: float = 1e-4  # ... and no point moved more than this (normalized units)
    # ... measured on this quantile of the coordinates' movement (1: the max). On long captures a few points drift on
    # while the rest has settled: complexknee F = 5000 stopped after 65 final alternations instead of 82, same
    # 99.90 % < 10 mm; on 6 windows x 4 rows of the paper's tables (F ~ 300) nothing changed at all (the cost test
    # binds there). The cost tests likewise leave out the (1 - quantile) share of frames whose cost changed most
    # (`settled_decrease`; none below 1000 frames): complexknee F = 20,000 then took 8 + 22 alternations instead of
    # 9 + 35 (99.86 against 99.87 % < 10 mm), F = 5000 8 + 21 instead of 11 + 26 and F = 2000 12 + 16 instead of
    # 12 + 17 (same accuracy both).
    point_quantile: float = 0.999
    # Anderson acceleration of the alternation over this many past iterates (0: plain alternation); see
    # reconstruct/solver/anderson.py.
    anderson_memory: int = 5
    w_step: WStepOptions = field(default_factory=WStepOptions)
    # Above this many frames each frame's dictionary is restricted to windows of the other videos around its current
    # matches (solver/candidates.py): linear cost in F instead of quadratic. At or below it, every frame of the
    # other videos is a candidate, as in the paper. Measured (1 BLAS thread): CMU F = 2000 windowed ~16 CPU s,
    # 99.86 % < 10 mm, dense 24.6 s, 99.87 %; complexknee F = 2000 windowed 13.4 s, 99.75 %, dense 22 s, 99.61 %.
    # Short captures stay dense: the flight scenes (P = 1, ~600 frames) give the windows' anchors nothing to match.
    dense_limit: int = 1000
    candidates: CandidateOptions = field(default_factory=CandidateOptions)
    # Threads for the independent parts of large steps (the X-step's points, the W-step's KKT components); small
    # problems stay on one (reconstruct/xstep.PARALLEL_SIZE, reconstruct/working_set.PARALLEL_KKT).
    workers: int = 2
    progress: bool = False
    # Called after every alternation with (stage name, iteration, points (F, P_kept, 3) in input units); for
    # benchmarks that follow accuracy along the iterations.
    monitor: Callable[[str, int, np.ndarray], None] | None = None


@dataclass(kw_only=True)
class StageLog:
    name: str
    lambda2: float
    iterations: int = 0
    converged: bool = False
    cost: list[float] = field(default_factory=list)
    w_iterations: list[int] = field(default_factory=list)
    max_point_change: list[float] = field(default_factory=list)
    rejected_mixes: int = 0  # Anderson mixes that raised the cost and were replaced by the plain step


@dataclass(kw_only=True)
class SolveResult:
    points: np.ndarray  # (F, P, 3) input units; NaN for points that cannot be reconstructed
    W: SparseW
    reconstructable: np.ndarray  # (P,) bool
    init: PairInit
    normalization: Normalization
    stages: list[StageLog]
    timings: dict[str, float]
    residual: np.ndarray  # (F,) self-expression residual per frame, RMS over points, input units
    init_points: np.ndarray  # (F, P, 3) input units, the initialization


def frame_costs(
    points: np.ndarray, W: sp.spmatrix, centers: np.ndarray, rays: np.ndarray, video_index: np.ndarray,
    lambda1: float, lambda2: float, lambda3: float, constraint: RayConstraint,
) -> np.ndarray:
    """(F,) each frame's share of the objective of the paper's Eq. (ourproblem_final) (+ soft ray term), normalized
    units: its self-expression residual, its column's asymmetry, its rays, and the smoothness link to the next frame
    of its video. They sum to `total_cost`."""
    F, P = points.shape[:2]
    shapes = points.reshape(F, -1)
    # trace(S^T Q S) of the X-step's quadratic form, without forming Q = (I - W)(I - W)^T / (FP) + ...: the sparse
    # product cost more than the rest of the alternation's bookkeeping together.
    residual = shapes - W.T @ shapes
    cost = np.einsum("fd,fd->f", residual, residual) / (F * P)
    if lambda2 > 0:
        links = chain_links(video_index)
        if len(links):
            step = shapes[links + 1] - shapes[links]
            cost[links] += lambda2 / (len(links) * P) * np.einsum("fd,fd->f", step, step)
    asym = sp.csc_matrix(W - W.T)
    cost += lambda1 / F * np.asarray(asym.multiply(asym).sum(axis=0)).ravel()
    if constraint is RayConstraint.SOFT:
        offset = points - centers[:, None, :]
        known = np.nan_to_num(rays)
        perpendicular = offset - np.einsum("fpk,fpk->fp", offset, known)[..., None] * known
        perpendicular[np.isnan(rays[..., 0])] = 0.0  # unobserved: no ray term
        cost += lambda3 / (F * P) * np.einsum("fpk,fpk->f", perpendicular, perpendicular)
    return cost


def total_cost(
    points: np.ndarray, W: sp.spmatrix, centers: np.ndarray, rays: np.ndarray, video_index: np.ndarray,
    lambda1: float, lambda2: float, lambda3: float, constraint: RayConstraint,
) -> float:
    """The objective of the paper's Eq. (ourproblem_final) (+ soft ray term), normalized units."""
    return float(np.sum(frame_costs(points, W, centers, rays, video_index, lambda1, lambda2, lambda3, constraint)))


def settled_decrease(previous: np.ndarray, current: np.ndarray, quantile: float) -> float:
    """Relative decrease from the frame costs `previous` to `current` (F,), over all frames but the (1 - quantile)
    share whose cost changed most. Noise-free long captures settle everywhere but in a handful of frames: at
    F = 20,000 the last 18 of 35 alternations each lowered the total cost by 0.1-0.3 %, a third of it from the 20
    frames that changed most, while ~10 frames still moved by more than point_tolerance and the share under 10 mm
    stayed at 99.865 +- 0.004 %.
    Below 1 / (1 - quantile) frames nothing is left out: the test is the plain relative decrease."""
    left_out = int(np.floor((1.0 - quantile) * len(current) + 1e-9))
    if left_out > 0:
        kept = np.ones(len(current), dtype=bool)
        kept[np.argpartition(-np.abs(previous - current), left_out - 1)[:left_out]] = False
        previous, current = previous[kept], current[kept]
    after = float(np.sum(current))
    return (float(np.sum(previous)) - after) / max(abs(after), 1e-300)


def frame_residuals(points: np.ndarray, W: sp.spmatrix) -> np.ndarray:
    """(F,) RMS over points of S_f - sum_j W_jf S_j."""
    F, P = points.shape[:2]
    shapes = points.reshape(F, -1)
    residual = shapes - W.T @ shapes
    return np.sqrt(np.sum(residual.reshape(F, P, 3) ** 2, axis=(1, 2)) / P)


def solve(problem: Problem, options: SolverOptions | None = None) -> SolveResult:
    options = options or SolverOptions()
    timings: dict[str, float] = {}
    started = time.perf_counter()
    F, P_all = problem.num_frames, problem.num_points
    video_index = problem.video_index
    keep = reconstructable_points(problem)
    for name in np.asarray(problem.point_names)[~keep]:
        log.warning("point %r is seen in fewer than two videos: it cannot be reconstructed (left empty)", name)
    if not keep.any():
        raise NotEnoughDataError(
            f"none of the {problem.num_points} point(s) is seen in two different videos: nothing can be "
            "reconstructed (each point needs observations from at least two videos)")

    rays_all = viewing_rays(problem)
    normalization = camera_normalization(problem.centers, video_index)
    centers = normalization.apply(problem.centers)
    rays = rays_all[:, keep]
    P = int(keep.sum())
    timings["rays"] = time.perf_counter() - started

    t0 = time.perf_counter()
    sparse = options.dense_limit < F
    if sparse:
        init, anchor = coarse_to_fine_init(centers, rays, video_index, options.candidates, times=problem.times)
        windows = MovingWindows(anchor, video_index, options.candidates, times=problem.times)
        log.info("%d frames: dictionaries restricted to +-%d frames of each other video around each frame's "
                 "matches", F, options.candidates.half_window)
    else:
        init = initialize_depths(centers, rays, video_index)
    init_points = centers[:, None, :] + init.depth[..., None] * rays
    unmatched = int(np.sum(init.partner < 0))
    if unmatched:
        log.info("%d frame(s) found no partner bundle in another video; their start values are interpolated",
                 unmatched)
    points = fill_missing_points(init_points, video_index)
    timings["initialize"] = time.perf_counter() - t0

    stages: list[StageLog] = []
    plan = [("smooth", options.lambda2), ("final", 0.0)] if options.lambda2 > 0 else [("final", 0.0)]
    W: SparseW | None = None
    w_options = WStepOptions(**{**options.w_step.__dict__, "lambda1": options.lambda1, "workers": options.workers})
    t_w = t_x = 0.0
    for name, lambda2 in plan:
        stage = StageLog(name=name, lambda2=lambda2)
        stages.append(stage)
        x_options = XStepOptions(lambda2=lambda2, lambda3=options.lambda3, constraint=options.constraint,
                                 workers=options.workers)
        previous_cost = np.inf
        previous_frames: np.ndarray | None = None  # (F,) frame costs of the previous alternation
        mixer = AndersonMixer(options.anderson_memory) if options.anderson_memory > 0 else None
        candidate = points  # where the next W-step starts: the last X-step's points or an Anderson mix of them
        bar = tqdm(range(options.max_iterations), desc=f"solve ({name})", disable=None if options.progress else True,
                   leave=False)
        for _ in bar:
            t0 = time.perf_counter()
            pool = windows.pool() if sparse else None
            W_next, w_stats = solve_w(candidate.reshape(F, -1), video_index, P, w_options, previous=W, pool=pool)
            W_matrix = W_next.to_csc()
            if candidate is not points:
                mixed_cost = total_cost(candidate, W_matrix, centers, rays, video_index, options.lambda1,
                                        lambda2, options.lambda3, options.constraint)
                if mixed_cost > previous_cost:  # the mix lost ground: fall back to the plain alternation
                    stage.rejected_mixes += 1
                    if mixer is not None:
                        mixer.reset()
                    candidate = points
                    W_next, w_stats = solve_w(candidate.reshape(F, -1), video_index, P, w_options, previous=W,
                                              pool=pool)
                    W_matrix = W_next.to_csc()
            W = W_next
            if sparse:
                windows.follow(W_matrix)
            t_w += time.perf_counter() - t0
            t0 = time.perf_counter()
            new_points = solve_x(W_matrix, centers, rays, video_index, x_options, start=candidate)
            t_x += time.perf_counter() - t0
            if not np.all(np.isfinite(new_points)):
                sparse_frames = int(np.sum(problem.observed[:, keep].sum(axis=1) < 2))
                raise DynreconError(
                    f"the solve diverged in stage {name!r} after {stage.iterations} alternation(s); "
                    f"{sparse_frames} of {F} frames observe fewer than 2 points: track more points per frame, or "
                    "drop frames where almost nothing is observed")
            moved = np.abs(new_points - candidate)
            change = float(np.max(moved))
            settled = change if options.point_quantile >= 1.0 else float(np.quantile(moved, options.point_quantile))
            frames_cost = frame_costs(new_points, W_matrix, centers, rays, video_index, options.lambda1, lambda2,
                                      options.lambda3, options.constraint)
            cost = float(np.sum(frames_cost))
            stage.iterations += 1
            stage.cost.append(cost)
            stage.w_iterations.append(w_stats.iterations)
            stage.max_point_change.append(change)
            bar.set_postfix(cost=f"{cost:.3e}", change=f"{change:.1e}")
            if options.monitor is not None:
                options.monitor(name, stage.iterations, normalization.undo(new_points))
            decrease = (np.inf if previous_frames is None
                        else settled_decrease(previous_frames, frames_cost, options.point_quantile))
            if lambda2 > 0:
                converged = decrease < options.smooth_tolerance
            else:
                converged = decrease < options.tolerance and settled < options.point_tolerance
            previous_cost, previous_frames = cost, frames_cost
            if converged:
                points = new_points
                stage.converged = True
                break
            candidate = mixer.mix(candidate, new_points) if mixer is not None else new_points
            points = new_points
        log.info("stage %s: %d iterations, cost %.4e, converged: %s", name, stage.iterations,
                 stage.cost[-1] if stage.cost else float("nan"), stage.converged)
    if W is None:
        raise ValueError("max_iterations must be at least 1")
    timings["w_step"] = t_w
    timings["x_step"] = t_x
    timings["total"] = time.perf_counter() - started

    W_matrix = W.to_csc()
    out = np.full((F, P_all, 3), np.nan)
    out[:, keep] = normalization.undo(points)
    init_out = np.full((F, P_all, 3), np.nan)
    init_out[:, keep] = normalization.undo(init_points)
    return SolveResult(
        points=out, W=W, reconstructable=keep, init=init, normalization=normalization, stages=stages,
        timings=timings, residual=frame_residuals(points, W_matrix) * normalization.scale, init_points=init_out,
    )
