"""The self-expressive solver: alternate the W-step and the X-step, first with the smoothness term Psi2, then
without it (paper, Sec. "Optimization" and "Sequencing information").

All work happens in normalized world coordinates (average distance between cameras = 1); results come back in the
input's units.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from tqdm import tqdm

from dynrecon.errors import DynreconError, NotEnoughDataError
from reconstruct.solver import unseen_frames
from reconstruct.solver.anderson import AndersonMixer
from reconstruct.solver.blas import one_blas_thread, outer_blas_threads
from reconstruct.solver.candidates import CandidateOptions, MovingWindows, coarse_to_fine_init
from reconstruct.solver.initialize import PairInit, fill_missing_points, initialize_depths
from reconstruct.solver.problem import Problem, reconstructable_points
from reconstruct.solver.rays import Normalization, camera_normalization, viewing_rays
from reconstruct.solver.wstep import SparseW, WStepOptions, WStepStats, solve_w
from reconstruct.solver.xstep import RayConstraint, XStepOptions, chain_links, solve_x

log = logging.getLogger(__name__)

# A stage stops when the relative decrease of the cost falls below its tolerance (and, in the final stage, the points
# have settled): with Anderson mixing the tail of alternations buys little accuracy (docs/measurements.md).
COST_TOLERANCE = 1e-3
# The smoothing stage only has to pull wrong initial shapes out of their local minima; it need not converge to the
# Psi2-biased optimum that the final stage leaves anyway.
SMOOTH_TOLERANCE = 1e-3
POINT_TOLERANCE = 1e-4  # ... and no point coordinate moved more than this (normalized units)
# On long captures a few points drift on while the rest has settled: the point test and the cost tests leave out the
# (1 - POINT_QUANTILE) share of coordinates and frames that changed most (`settled_decrease`).
POINT_QUANTILE = 0.999
# ... unless the cost has changed by less than COST_TOLERANCE in this many alternations in a row: the points still
# moving then move along directions the objective hardly sees (a joint seen by two nearly parallel rays), and more
# alternations only drift.
STALL_ALTERNATIONS = 20
# Weights beyond this swamp every other term in double precision: the solve diverges, not the data's fault.
MAX_WEIGHT = 1e6


@dataclass(kw_only=True)
class SolverOptions:
    """Options of the self-expressive solve (`solve`).

    lambda1, lambda2, lambda3: weights of the paper's structural coherence Psi1, of its smoothness Psi2 in the first
    stage (the second stage uses 0; 0 skips the first stage) and of the soft ray constraint.
    constraint: points exactly on their viewing rays (hard) or pulled to them (soft, for noisy tracks).
    max_iterations: alternations per stage.
    anderson_memory: Anderson acceleration over this many past iterates (0: the plain alternation;
    `reconstruct.solver.anderson`).
    dense_limit: above this many frames each frame's dictionary is restricted to windows of the other videos around
    its current matches (`candidates`, set by `reconstruct.solver.candidates.CandidateOptions`): linear cost in the
    frames instead of quadratic. At or below it every frame of the other videos is a candidate, as in the paper.
    w_step: the W-step's settings (`WStepOptions`); its `lambda1` and `workers` are this object's (`w_step_options`).
    workers: threads for the independent parts of large steps (the X-step's points, the W-step's KKT components);
    small problems stay on one.
    progress: show a progress bar per stage.
    """

    lambda1: float = 0.05
    lambda2: float = 0.1
    lambda3: float = 100.0
    constraint: RayConstraint = RayConstraint.SOFT
    max_iterations: int = 200
    anderson_memory: int = 5
    w_step: WStepOptions = field(default_factory=WStepOptions)
    # Short captures stay dense: the flight scenes (one point, few hundred frames) give the windows' anchors nothing
    # to match.
    dense_limit: int = 1000
    candidates: CandidateOptions = field(default_factory=CandidateOptions)
    workers: int = 2
    progress: bool = False

    def __post_init__(self) -> None:
        # Programming errors (`dynrecon solve` checks what users type, naming the flag): fail at construction, not
        # after a diverged solve.
        for name in ("lambda1", "lambda2", "lambda3"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0 <= value <= MAX_WEIGHT):
                raise ValueError(f"{name} {value} must be a number from 0 to {MAX_WEIGHT:g}")
        if self.lambda3 == 0 and self.constraint is RayConstraint.SOFT:
            raise ValueError("lambda3 = 0 with the soft constraint ties the points to no ray: any shape fits")
        if self.max_iterations < 1 or self.workers < 1 or self.anderson_memory < 0:
            raise ValueError("max_iterations and workers must be at least 1, anderson_memory at least 0")

    def w_step_options(self) -> WStepOptions:
        """The W-step's options: `w_step` with this solve's lambda1 and threads."""
        return dataclasses.replace(self.w_step, lambda1=self.lambda1, workers=self.workers)

    def x_step_options(self, lambda2: float) -> XStepOptions:
        """The X-step's options for a stage with smoothness weight `lambda2`."""
        return XStepOptions(lambda2=lambda2, lambda3=self.lambda3, constraint=self.constraint, workers=self.workers)


@dataclass(kw_only=True)
class StageLog:
    name: str
    lambda2: float
    iterations: int = 0
    converged: bool = False
    stalled: bool = False  # final stage: stopped by STALL_ALTERNATIONS flat alternations, points still moving
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
    points: np.ndarray,
    W: sp.spmatrix,
    centers: np.ndarray,
    rays: np.ndarray,
    video_index: np.ndarray,
    lambda1: float,
    lambda2: float,
    lambda3: float,
    constraint: RayConstraint,
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
    points: np.ndarray,
    W: sp.spmatrix,
    centers: np.ndarray,
    rays: np.ndarray,
    video_index: np.ndarray,
    lambda1: float,
    lambda2: float,
    lambda3: float,
    constraint: RayConstraint,
) -> float:
    """The objective of the paper's Eq. (ourproblem_final) (+ soft ray term), normalized units."""
    return float(np.sum(frame_costs(points, W, centers, rays, video_index, lambda1, lambda2, lambda3, constraint)))


def settled_decrease(previous: np.ndarray, current: np.ndarray, quantile: float) -> float:
    """Relative decrease from the frame costs `previous` to `current` (F,), over all frames but the (1 - quantile)
    share whose cost changed most: noise-free long captures settle everywhere but in a handful of frames, which
    would keep the plain relative decrease above the tolerance long after the accuracy stopped changing.
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
    """The paper's alternation on `problem`: initialization, then W-step / X-step alternations with Psi2 (when
    lambda2 > 0) and without. Raises NotEnoughDataError when no point is seen in two videos, DynreconError when the
    solve diverges."""
    options = options or SolverOptions()
    with one_blas_thread():  # reconstruct/solver/blas.py: the solver's threads, not BLAS's
        return _solve(problem, options)


def _solve(problem: Problem, options: SolverOptions) -> SolveResult:
    keep = _reconstructable(problem)
    seen = unseen_frames.seen_frames(problem, keep)
    if seen.all():
        return _solve_seen(problem, keep, options)
    log.info("%d of %d frames observe no point: solved without them, then interpolated", int((~seen).sum()), len(seen))
    part = _solve_seen(unseen_frames.take_frames(problem, seen), keep, options)
    return dataclasses.replace(
        part,
        points=unseen_frames.put_back(part.points, seen, problem.video_index, keep),
        W=unseen_frames.put_back_w(part.W, seen),
        init=unseen_frames.put_back_init(part.init, seen),
        residual=unseen_frames.along(part.residual, seen),
        init_points=unseen_frames.along(part.init_points, seen),
    )


def _solve_seen(problem: Problem, keep: np.ndarray, options: SolverOptions) -> SolveResult:
    """The alternation on `problem`, every frame of which observes one of the `keep` points or more."""
    timings: dict[str, float] = {}
    started = time.perf_counter()
    normalization = camera_normalization(problem.centers, problem.video_index)
    scene = _Scene(
        centers=normalization.apply(problem.centers),
        rays=viewing_rays(problem)[:, keep],
        video_index=problem.video_index,
        observed=problem.observed[:, keep],
    )
    timings["rays"] = time.perf_counter() - started

    t0 = time.perf_counter()
    init = _initialize(problem, scene, options)
    init_points = scene.centers[:, None, :] + init.depth[..., None] * scene.rays
    unmatched = int(np.sum(init.partner < 0))
    if unmatched == scene.num_frames:  # nothing to start from: every start value would be NaN
        raise NotEnoughDataError(
            "no frame's rays meet another video's rays of the same points in front of both cameras: nothing to start "
            "the solve from (check the cameras against the tracks: video and point names, poses as cam_from_world)"
        )
    if unmatched:
        log.info("%d frame(s) found no partner bundle in another video; their start values are interpolated", unmatched)
    points = fill_missing_points(init_points, scene.video_index)
    timings["initialize"] = time.perf_counter() - t0

    stages, points, W = _alternate(points, scene, options, timings)
    timings["total"] = time.perf_counter() - started
    return _result(problem, keep, normalization, init, init_points, points, W, stages, timings)


@dataclass(kw_only=True)
class _Scene:
    """What every alternation of one solve shares, normalized units, reconstructable points only."""

    centers: np.ndarray  # (F, 3)
    rays: np.ndarray  # (F, P, 3) unit viewing rays, NaN where unobserved
    video_index: np.ndarray  # (F,)
    observed: np.ndarray  # (F, P) bool
    windows: MovingWindows | None = None  # candidate windows on long captures; None: dense dictionaries

    @property
    def num_frames(self) -> int:
        return self.rays.shape[0]

    @property
    def num_points(self) -> int:
        return self.rays.shape[1]


def _reconstructable(problem: Problem) -> np.ndarray:
    """(P,) bool, the points seen in at least two videos; warns about the others."""
    keep = reconstructable_points(problem)
    for name in np.asarray(problem.point_names)[~keep].tolist():  # str, not np.str_, in the message
        log.warning("point %r is seen in fewer than two videos: it cannot be reconstructed (left empty)", name)
    if not keep.any():
        raise NotEnoughDataError(
            f"none of the {problem.num_points} point(s) is seen in two different videos: nothing can be "
            "reconstructed (each point needs observations from at least two videos)"
        )
    return keep


def _initialize(problem: Problem, scene: _Scene, options: SolverOptions) -> PairInit:
    """The paper's initialization; on long captures coarse to fine, which also sets `scene.windows`."""
    F = scene.num_frames
    if options.dense_limit >= F:
        return initialize_depths(scene.centers, scene.rays, scene.video_index)
    init, anchor = coarse_to_fine_init(
        scene.centers, scene.rays, scene.video_index, options.candidates, times=problem.times
    )
    scene.windows = MovingWindows(anchor, scene.video_index, options.candidates, times=problem.times)
    log.info(
        "%d frames: dictionaries restricted to +-%d frames of each other video around each frame's matches",
        F,
        options.candidates.half_window,
    )
    return init


def _alternate(
    points: np.ndarray, scene: _Scene, options: SolverOptions, timings: dict[str, float]
) -> tuple[list[StageLog], np.ndarray, SparseW]:
    """Both stages from the start `points` (F, P, 3); adds the W-step and X-step times to `timings`."""
    stages: list[StageLog] = []
    plan = [("smooth", options.lambda2), ("final", 0.0)] if options.lambda2 > 0 else [("final", 0.0)]
    W: SparseW | None = None
    w_options = options.w_step_options()
    timings["w_step"] = timings["x_step"] = 0.0
    for name, lambda2 in plan:
        stage = StageLog(name=name, lambda2=lambda2)
        stages.append(stage)
        points, W = _run_stage(stage, points, W, scene, options, w_options, timings)
        log.info(
            "stage %s: %d iterations, cost %.4e, %s",
            name,
            stage.iterations,
            stage.cost[-1] if stage.cost else float("nan"),
            _ending(stage),
        )
    if W is None:
        raise ValueError("max_iterations must be at least 1")
    return stages, points, W


def _ending(stage: StageLog) -> str:
    if stage.stalled:
        return f"stalled: the cost changed by less than {COST_TOLERANCE:g} in each of {STALL_ALTERNATIONS} alternations"
    return "converged" if stage.converged else "not converged"


def _run_stage(
    stage: StageLog,
    points: np.ndarray,
    W: SparseW | None,
    scene: _Scene,
    options: SolverOptions,
    w_options: WStepOptions,
    timings: dict[str, float],
) -> tuple[np.ndarray, SparseW | None]:
    """Alternations of one stage until it converges or runs out of iterations; returns its points and W."""
    lambda2 = stage.lambda2
    x_options = options.x_step_options(lambda2)
    previous_cost = np.inf
    previous_frames: np.ndarray | None = None  # (F,) frame costs of the previous alternation
    flat = 0  # consecutive alternations whose cost changed by less than COST_TOLERANCE, either way
    mixer = AndersonMixer(options.anderson_memory) if options.anderson_memory > 0 else None
    candidate = points  # where the next W-step starts: the last X-step's points or an Anderson mix of them
    # off a terminal too (the CLI thins redraws to one per 10 s there), and -q's TQDM_DISABLE still applies
    hidden = {} if options.progress else {"disable": True}
    bar = tqdm(range(options.max_iterations), desc=f"solve ({stage.name})", leave=False, **hidden)
    for _ in bar:
        t0 = time.perf_counter()
        W, W_matrix, w_stats, candidate = _w_step(
            stage, candidate, points, W, previous_cost, mixer, scene, options, w_options
        )
        timings["w_step"] += time.perf_counter() - t0
        t0 = time.perf_counter()
        new_points = solve_x(W_matrix, scene.centers, scene.rays, scene.video_index, x_options, start=candidate)
        timings["x_step"] += time.perf_counter() - t0
        _check_finite(new_points, stage, scene)
        moved = np.abs(new_points - candidate)
        change = float(np.max(moved))
        settled = float(np.quantile(moved, POINT_QUANTILE))
        frames_cost = frame_costs(
            new_points,
            W_matrix,
            scene.centers,
            scene.rays,
            scene.video_index,
            options.lambda1,
            lambda2,
            options.lambda3,
            options.constraint,
        )
        cost = float(np.sum(frames_cost))
        stage.iterations += 1
        stage.cost.append(cost)
        stage.w_iterations.append(w_stats.iterations)
        stage.max_point_change.append(change)
        bar.set_postfix(cost=f"{cost:.3e}", change=f"{change:.1e}")
        decrease = np.inf if previous_frames is None else settled_decrease(previous_frames, frames_cost, POINT_QUANTILE)
        flat = flat + 1 if abs(decrease) < COST_TOLERANCE else 0  # a cost rising past it is not flat either
        if lambda2 > 0:
            converged = decrease < SMOOTH_TOLERANCE
        else:
            converged = decrease < COST_TOLERANCE and settled < POINT_TOLERANCE
            stage.stalled = not converged and flat >= STALL_ALTERNATIONS
            converged = converged or stage.stalled
        previous_cost, previous_frames = cost, frames_cost
        if converged:
            stage.converged = True
            return new_points, W
        if mixer is not None:
            with outer_blas_threads():  # its dot products' values depend on the BLAS thread count: the caller's
                candidate = mixer.mix(candidate, new_points)
        else:
            candidate = new_points
        points = new_points
    return points, W


def _w_step(
    stage: StageLog,
    candidate: np.ndarray,
    points: np.ndarray,
    W: SparseW | None,
    previous_cost: float,
    mixer: AndersonMixer | None,
    scene: _Scene,
    options: SolverOptions,
    w_options: WStepOptions,
) -> tuple[SparseW, sp.csc_matrix, WStepStats, np.ndarray]:
    """The W-step from `candidate` (an Anderson mix, or the last X-step's `points`); a mix whose cost exceeds
    `previous_cost` is dropped for the plain step. Returns W, as a matrix, its stats and the start actually used."""
    F, P = scene.num_frames, scene.num_points
    pool = scene.windows.pool() if scene.windows is not None else None
    W_next, w_stats = solve_w(candidate.reshape(F, -1), scene.video_index, P, w_options, previous=W, pool=pool)
    W_matrix = W_next.to_csc()
    if candidate is not points:
        mixed_cost = total_cost(
            candidate,
            W_matrix,
            scene.centers,
            scene.rays,
            scene.video_index,
            options.lambda1,
            stage.lambda2,
            options.lambda3,
            options.constraint,
        )
        if mixed_cost > previous_cost:  # the mix lost ground: fall back to the plain alternation
            stage.rejected_mixes += 1
            if mixer is not None:
                mixer.reset()
            candidate = points
            W_next, w_stats = solve_w(candidate.reshape(F, -1), scene.video_index, P, w_options, previous=W, pool=pool)
            W_matrix = W_next.to_csc()
    if scene.windows is not None:
        scene.windows.follow(W_matrix)
    return W_next, W_matrix, w_stats, candidate


def _check_finite(points: np.ndarray, stage: StageLog, scene: _Scene) -> None:
    if not np.all(np.isfinite(points)):
        sparse_frames = int(np.sum(scene.observed.sum(axis=1) < 2))
        raise DynreconError(
            f"the solve diverged in stage {stage.name!r} after {stage.iterations} alternation(s); "
            f"{sparse_frames} of {scene.num_frames} frames observe fewer than 2 points: track more points per frame, "
            "or drop frames where almost nothing is observed"
        )


def _result(
    problem: Problem,
    keep: np.ndarray,
    normalization: Normalization,
    init: PairInit,
    init_points: np.ndarray,
    points: np.ndarray,
    W: SparseW,
    stages: list[StageLog],
    timings: dict[str, float],
) -> SolveResult:
    """Back to input units, with NaN for the points that could not be reconstructed."""
    F, P_all = problem.num_frames, problem.num_points
    W_matrix = W.to_csc()
    out = np.full((F, P_all, 3), np.nan)
    out[:, keep] = normalization.undo(points)
    init_out = np.full((F, P_all, 3), np.nan)
    init_out[:, keep] = normalization.undo(init_points)
    return SolveResult(
        points=out,
        W=W,
        reconstructable=keep,
        init=init,
        normalization=normalization,
        stages=stages,
        timings=timings,
        residual=frame_residuals(points, W_matrix) * normalization.scale,
        init_points=init_out,
    )
