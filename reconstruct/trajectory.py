"""Temporal refinement: once every frame has a global time, re-estimate each point's trajectory as a smoothing
spline through its viewing rays (trajectory triangulation, in the spirit of Valmadre & Lucey 2012).

Per point p, the unknowns are its positions Y_i at the distinct capture times t_i (frames of different videos at
the same time share one position). The cost, in pixels squared, is

    sum_obs  w_fp s_fp^2 ||(I - r r^T)(Y_node(f) - C_f)||^2  +  lambda s_p^2 sum_i a_i ||D2_i Y||^2

- data: the squared distance of the position to the frame's viewing ray, scaled by s_fp = focal / depth into
  (approximately) a reprojection error in pixels; w_fp are robust IRLS weights (1 without a robust loss);
- prior: D2_i is the second divided difference on the real (non-uniform) time stamps, with time measured in units
  of tau, the median spacing of consecutive capture times, and a_i = (t_{i+1} - t_{i-1}) / (2 tau) its share of
  the time axis, so the sum approximates the integrated squared acceleration (the cubic smoothing spline's energy).
  s_p is point p's mean focal / depth, so one unit of D2 costs as much as one pixel of reprojection error and
  lambda is dimensionless (independent of units, camera distance and frame rate).

lambda is chosen per point by generalized cross-validation (GCV) unless fixed. The system is banded (positions of
the two neighbours in time) and symmetric positive definite: one banded Cholesky solve per point and iteration.
Unobserved frames have no data term: the spline interpolates (or linearly extrapolates) them.

`refine_with_clocks` also polishes the clocks: per-video offset (and rate) corrections that minimize this cost,
found by coordinate descent with the smoothness and robust weights of a first refinement held fixed
(`clocks.model.ClockCorrection`). docs/refinement.md describes the whole.
"""

from __future__ import annotations

import enum
import itertools
import logging
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import LinAlgError, cho_solve_banded, cholesky_banded

from dynrecon.errors import InputError
from reconstruct.block_inverse import BANDS, trace_of_inverse_times
from reconstruct.clocks.model import ClockCorrection
from reconstruct.solver.problem import Problem
from reconstruct.solver.rays import camera_normalization, viewing_rays

log = logging.getLogger(__name__)

PRIOR_DIAGONALS = (0, 3, 6)  # the prior's nonzero bands: it links the same coordinate of nodes i-2..i+2
# Smoothness candidates for GCV, half-decade steps: a wide range, since noise-free frequent captures want little
# smoothing and noisy sparse ones much more.
SMOOTHNESS_GRID = tuple(float(10.0 ** (k / 2)) for k in range(-12, 9))
# Robust scale in pixels of reprojection error: SCALE_SIGMAS x the per-axis noise level that each point's GCV fit
# implies, at least MIN_SCALE_PX.
SCALE_SIGMAS = 2.5
MIN_SCALE_PX = 0.5
RAYLEIGH_MEDIAN = 1.1774  # median norm of a 2D Gaussian residual, in per-axis sigmas: sqrt(2 ln 2)
IRLS_ITERATIONS = 5  # IRLS rounds per GCV pass (weights from the previous round's residuals)
# Smoothness and scale are chosen by GCV, then IRLS runs with them; a second pass chooses again with the robust
# weights (the first pass's weights come from the start points' residuals).
GCV_PASSES = 2
# Beyond this many instants each point's smoothness and scale are chosen on the middle GCV_WINDOW instants only: the
# GCV trace's selected inverse costs a Python step per unknown, and the noise level and the motion's smoothness that
# GCV weighs are properties of the point, not of the capture's length. The fits themselves use every instant.
GCV_WINDOW = 1000
# A point with fewer observations in that window is chosen on all of its own (exactly as below the window).
GCV_WINDOW_MIN_OBSERVATIONS = 50
OUTLIER_FACTOR = 3.0  # residual > factor x scale marks an observation as an outlier in the result
# Capture times closer than this fraction of tau are one instant (one position), so that a pair of nearly
# concurrent frames cannot make the system ill-conditioned.
MERGE_FRACTION = 0.01
# Threads for independent points (their banded solves and selected inverses; bit-identical for any count). One:
# on an idle 2-core machine a second thread gave no wall time back and cost CPU (docs/measurements.md).
WORKERS = 1


class RobustLoss(enum.Enum):
    NONE = "none"  # plain least squares
    HUBER = "huber"  # weight min(1, scale / r): convex, keeps gross errors' influence bounded
    CAUCHY = "cauchy"  # weight 1 / (1 + (r / scale)^2): redescending, ignores gross errors


class SmoothnessRule(enum.Enum):
    GCV = "gcv"  # per point, the grid value of least generalized cross-validation score
    GCV_GLOBAL = "gcv-global"  # one value for all points: least summed GCV score
    FIXED = "fixed"  # `RefineOptions.smoothness` as given


@dataclass(kw_only=True)
class RefineOptions:
    rule: SmoothnessRule = SmoothnessRule.GCV
    smoothness: float = 1.0  # dimensionless lambda for SmoothnessRule.FIXED
    loss: RobustLoss = RobustLoss.HUBER


@dataclass(kw_only=True)
class RefineResult:
    points: np.ndarray  # (F, P, 3) input units; NaN where the input had no point at all (unreconstructable)
    weights: np.ndarray  # (F, P) final robust weights, NaN where unobserved
    outliers: np.ndarray  # (F, P) bool, residual above OUTLIER_FACTOR x scale
    residual_px: np.ndarray  # (F, P) final reprojection error (ray distance x focal / depth), NaN unobserved
    smoothness: np.ndarray  # (P,) lambda used, NaN for points not refined
    scale_px: np.ndarray  # (P,) robust scale used, NaN for points not refined
    cost: list[float] = field(default_factory=list)  # total cost (px^2) after each round


@dataclass(frozen=True)
class TimeNodes:
    node_of_frame: np.ndarray  # (F,) index of the frame's instant
    times: np.ndarray  # (n,) increasing
    tau: float  # median spacing of consecutive distinct instants


def time_nodes(times: np.ndarray, merge_fraction: float = MERGE_FRACTION, tau: float | None = None) -> TimeNodes:
    """Distinct instants of `times (F,)`; gaps below merge_fraction x the median gap join one instant. `tau`
    fixes the time unit (else the median gap between instants)."""
    order = np.argsort(times, kind="stable")
    sorted_times = times[order]
    gaps = np.diff(sorted_times)
    positive = gaps[gaps > 0]
    unit = tau if tau is not None else (float(np.median(positive)) if positive.size else 1.0)
    new_node = np.concatenate([[True], gaps > merge_fraction * unit])
    node_sorted = np.cumsum(new_node) - 1
    node_of_frame = np.empty(len(times), dtype=np.int64)
    node_of_frame[order] = node_sorted
    counts = np.bincount(node_sorted)
    node_times = np.bincount(node_sorted, weights=sorted_times) / counts
    node_gaps = np.diff(node_times)
    if tau is None:
        tau = float(np.median(node_gaps)) if node_gaps.size else 1.0
    return TimeNodes(node_of_frame=node_of_frame, times=node_times, tau=tau)


def prior_bands(nodes: TimeNodes) -> np.ndarray:
    """(BANDS, 3n) lower banded form of sum_i a_i D2_i^T D2_i (kron I3), time in units of tau."""
    n = len(nodes.times)
    bands = np.zeros((BANDS, 3 * n))
    if n < 3:
        return bands
    t = nodes.times / nodes.tau
    h = np.diff(t)  # (n-1,)
    h0, h1 = h[:-1], h[1:]  # gaps before and after interior node i = 1..n-2
    span = h0 + h1
    # Second divided difference 2 / (h0 + h1) * ((Y+ - Y) / h1 - (Y - Y-) / h0).
    coef = np.stack([2 / (span * h0), -2 / (h0 * h1), 2 / (span * h1)], axis=1)  # (n-2, 3) for i-1, i, i+1
    area = span / 2
    for a in range(3):
        for b in range(a + 1):
            value = area * coef[:, a] * coef[:, b]  # M[i-1+a, i-1+b], a >= b
            rows = np.arange(n - 2) + b  # the column node (lower form: column index)
            for k in range(3):
                bands[3 * (a - b), 3 * rows + k] += value  # distinct columns: add.at's sums
    return bands


def _data_blocks(
    rays: np.ndarray, centers: np.ndarray, weight: np.ndarray, node: np.ndarray, n: int
) -> tuple[np.ndarray, np.ndarray]:
    """Sum over observations of weight (I - r r^T) per node, (n, 3, 3), and the right-hand sides, (n, 3)."""
    projector = np.eye(3)[None] - rays[:, :, None] * rays[:, None, :]  # (m, 3, 3)
    blocks = weight[:, None, None] * projector
    rhs = np.einsum("mij,mj->mi", blocks, centers)
    return _sum_at(node, blocks, n), _sum_at(node, rhs, n)


def _sum_at(index: np.ndarray, values: np.ndarray, size: int) -> np.ndarray:
    """(size, ...) sums of `values (m, ...)` by `index (m,)`: np.add.at's sums in its order, by np.bincount, which
    is many times faster."""
    flat = values.reshape(len(values), -1)
    width = flat.shape[1]
    slots = (index[:, None] * width + np.arange(width)).ravel()
    return np.bincount(slots, weights=flat.ravel(), minlength=size * width).reshape(size, *values.shape[1:])


def _sum_at_slots(index: np.ndarray, padded: np.ndarray, size: int, alone: np.ndarray) -> np.ndarray:
    """`_sum_at(index, padded[:-1], size)`, bitwise, for values `padded (m + 1, ...)` whose last row is zeros;
    `alone (m,)` marks the values that are the only one of their slot: those are gathered (then + 0.0, bincount's
    first sum), only the others summed by bincount. With unsynchronized cameras nearly every instant holds one
    frame, so nearly every sum has one term, and a gather is several times faster than a scatter or bincount."""
    m = len(padded) - 1
    source = np.full(size, m)  # empty slots take the zero row
    source[index[alone]] = np.flatnonzero(alone)
    out = padded.take(source, axis=0)
    out += 0.0  # 0.0 + x: a gathered -0.0 becomes +0.0 as in bincount
    if not alone.all():
        rest = index[~alone]
        out[rest] = _sum_at(rest, padded[:m][~alone], size)[rest]  # the others' slots hold no gathered value
    return out


def _zero_row(values: np.ndarray) -> np.ndarray:
    """`values (m, ...)` with a row of zeros appended, (m + 1, ...)."""
    return np.concatenate([values, np.zeros((1, *values.shape[1:]))])


# The lower triangle of a symmetric 3x3 block, (row, column) pairs, and the positions of its diagonal among them.
LOWER = ((0, 0), (1, 0), (1, 1), (2, 0), (2, 1), (2, 2))
LOWER_DIAGONAL = (0, 2, 5)


def _add_blocks(bands: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    """Banded matrix + block diagonal (n, 3, 3) (lower form)."""
    out = bands.copy()
    columns = out.reshape(BANDS, len(blocks), 3)  # a view: column 3i + col is [:, i, col]
    for row in range(3):
        for col in range(row + 1):
            columns[row - col, :, col] += blocks[:, row, col]
    return out


def _fit(
    prior: np.ndarray, scale2: float, smoothness: float, blocks: np.ndarray, rhs: np.ndarray, anchor: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Solve (lambda s^2 P + D + eps I) Y = d + eps Y0 for one point (blocks already carry w s^2); returns the
    positions (n, 3) and the banded Cholesky factor (for the GCV trace)."""
    n = len(blocks)
    eps = _anchor_weight(blocks)
    system = _add_blocks(smoothness * scale2 * prior, blocks + eps * np.eye(3)[None])
    b = (rhs + eps * anchor).reshape(-1)
    try:
        factor = cholesky_banded(system, lower=True)
    except LinAlgError:
        # Numerically singular (a point with hardly any rays): a stronger anchor keeps the input position.
        system = _add_blocks(system, np.broadcast_to(1e-6 * np.eye(3), (n, 3, 3)))
        b = (rhs + (eps + 1e-6) * anchor).reshape(-1)
        factor = cholesky_banded(system, lower=True)
    return cho_solve_banded((factor, True), b).reshape(n, 3), factor


def robust_weights(residual: np.ndarray, loss: RobustLoss, scale: float) -> np.ndarray:
    """IRLS weights of residual norms (px)."""
    if loss is RobustLoss.NONE:
        return np.ones_like(residual)
    ratio = residual / scale
    if loss is RobustLoss.HUBER:
        return np.minimum(1.0, 1.0 / np.maximum(ratio, 1e-300))
    return 1.0 / (1.0 + ratio * ratio)


def _check_inputs(problem: Problem, points: np.ndarray, times: np.ndarray) -> None:
    F, P = problem.num_frames, problem.num_points
    if points.shape != (F, P, 3):
        raise InputError(None, f"refine: points have shape {points.shape}, the problem needs ({F}, {P}, 3)")
    if times.shape != (F,):
        raise InputError(
            None,
            f"refine: times have shape {times.shape}, the problem has {F} frames",
            fix="give one global time per frame",
        )
    bad = np.flatnonzero(~np.isfinite(times))
    if bad.size:
        f = int(bad[0])
        raise InputError(
            None,
            f"refine: frame {f} (video {problem.frame_videos[f]!r} frame {int(problem.frames[f])}) has no global time",
            fix="estimate the clocks first, every frame needs a time",
        )


@dataclass(kw_only=True)
class _Track:
    """One point's observations and its refinement state."""

    point: int
    seen: np.ndarray  # (m,) frames that observe it
    node: np.ndarray  # (m,) their instants
    rays: np.ndarray  # (m, 3)
    centers: np.ndarray  # (m, 3) normalized units
    s2: np.ndarray  # (m,) (focal / depth)^2: normalized units^2 -> px^2
    mean_s2: float  # (mean focal / depth)^2, the prior's px scale
    anchor: np.ndarray  # (n, 3) start positions per instant
    positions: np.ndarray  # (n, 3) current estimate
    weights: np.ndarray  # (m,) robust weights
    scale: float = 1.0  # robust scale, px
    smoothness: float = 1.0
    residual: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (m,) px

    def residuals(self, positions: np.ndarray) -> np.ndarray:
        """(m,) reprojection errors in px (ray distance x focal / depth)."""
        offset = positions[self.node] - self.centers
        perpendicular = offset - np.einsum("mi,mi->m", offset, self.rays)[:, None] * self.rays
        return np.sqrt(self.s2 * np.einsum("mi,mi->m", perpendicular, perpendicular))

    def data(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        return _data_blocks(self.rays, self.centers, self.weights * self.s2, self.node, n)


def _threads() -> AbstractContextManager[ThreadPoolExecutor | None]:
    """A pool of WORKERS threads for one refinement or polish round; None with one worker (no thread hop)."""
    return ThreadPoolExecutor(WORKERS) if WORKERS > 1 else nullcontext(None)


def refine(
    problem: Problem, points: np.ndarray, times: np.ndarray, options: RefineOptions | None = None
) -> RefineResult:
    """Smooth trajectories through the rays of `problem`, started from `points (F, P, 3)` (e.g. the seed
    solver's, input units) at global `times (F,)` seconds."""
    options = options or RefineOptions()
    points = np.asarray(points, dtype=float)
    times = np.asarray(times, dtype=float)
    _check_inputs(problem, points, times)
    F, P = problem.num_frames, problem.num_points
    normalization = camera_normalization(problem.centers, problem.video_index)
    centers = normalization.apply(problem.centers)  # (F, 3)
    start = normalization.apply(points)
    rays = viewing_rays(problem)
    focal = np.sqrt(problem.K[:, 0, 0] * problem.K[:, 1, 1])  # (F,) px
    nodes = time_nodes(times)
    n = len(nodes.times)
    prior = prior_bands(nodes)
    grid = [options.smoothness] if options.rule is SmoothnessRule.FIXED else list(SMOOTHNESS_GRID)

    tracks = _make_tracks(problem, start, rays, centers, focal, nodes)
    for track in tracks:
        track.smoothness = grid[0]
        # First weights and scale from the start's residuals: a false detection is already far from its ray.
        residual = track.residuals(track.anchor)
        track.scale = _loss_scale(residual)
        track.weights = robust_weights(residual, options.loss, track.scale)

    cost: list[float] = []
    with _threads() as pool:
        for _ in range(max(GCV_PASSES, 1)):
            if tracks:
                _choose_smoothness_in_window(tracks, prior, grid, nodes, options, pool)
            if _irls(tracks, prior, n, options, cost, pool):
                break

    out = np.full((F, P, 3), np.nan)
    weights = np.full((F, P), np.nan)
    residual_px = np.full((F, P), np.nan)
    outliers = np.zeros((F, P), dtype=bool)
    smoothness = np.full(P, np.nan)
    scale_px = np.full(P, np.nan)
    for track in tracks:
        p = track.point
        out[:, p] = track.positions[nodes.node_of_frame]
        weights[track.seen, p] = track.weights
        residual_px[track.seen, p] = track.residual
        outliers[track.seen, p] = track.residual > OUTLIER_FACTOR * track.scale
        smoothness[p] = track.smoothness
        scale_px[p] = track.scale
    if tracks:
        log.info(
            "refined %d point(s) on %d instants: smoothness median %.3g, %d outlier observation(s)",
            len(tracks),
            n,
            float(np.nanmedian(smoothness)),
            int(outliers.sum()),
        )
    return RefineResult(
        points=normalization.undo(out),
        weights=weights,
        outliers=outliers,
        residual_px=residual_px,
        smoothness=smoothness,
        scale_px=scale_px,
        cost=cost,
    )


def _irls(
    tracks: list[_Track],
    prior: np.ndarray,
    n: int,
    options: RefineOptions,
    cost: list[float],
    pool: ThreadPoolExecutor | None = None,
) -> bool:
    """IRLS rounds at the tracks' smoothness and scale, appending the total cost of each to `cost`; True when the
    loss is plain least squares (one fit is final)."""
    for _ in range(max(IRLS_ITERATIONS, 1)):
        total = 0.0
        for track, fitted in zip(tracks, _fit_tracks(tracks, prior, n, pool), strict=True):
            track.positions = fitted
            track.residual = track.residuals(track.positions)
            total += float(np.sum(_rho(track.residual, options.loss, track.scale)))
            total += track.smoothness * track.mean_s2 * float(_prior_value(prior, track.positions.reshape(-1)))
            track.weights = robust_weights(track.residual, options.loss, track.scale)
        cost.append(total)
        if options.loss is RobustLoss.NONE:
            return True
    return False


def _make_tracks(
    problem: Problem, start: np.ndarray, rays: np.ndarray, centers: np.ndarray, focal: np.ndarray, nodes: TimeNodes
) -> list[_Track]:
    """One _Track per point that has observations and a start position (normalized units)."""
    tracks: list[_Track] = []
    for p in range(problem.num_points):
        seen = np.flatnonzero(problem.observed[:, p])
        if seen.size == 0 or not np.isfinite(start[:, p]).all(axis=1).any():
            continue  # nothing to refine (the solver left the point empty)
        anchor = _start_per_node(start[:, p], nodes)
        node = nodes.node_of_frame[seen]
        depth = np.einsum("mi,mi->m", anchor[node] - centers[seen], rays[seen, p])
        typical = float(np.median(depth[depth > 0])) if np.any(depth > 0) else 1.0
        depth = np.where(depth > 0.05 * typical, depth, typical)  # a start behind the camera: typical depth
        s = focal[seen] / depth
        tracks.append(
            _Track(
                point=p,
                seen=seen,
                node=node,
                rays=rays[seen, p],
                centers=centers[seen],
                s2=s * s,
                mean_s2=float(np.mean(s)) ** 2,
                anchor=anchor,
                positions=anchor,
                weights=np.ones(seen.size),
            )
        )
    return tracks


def _choose_smoothness(
    tracks: list[_Track],
    prior: np.ndarray,
    grid: list[float],
    n: int,
    options: RefineOptions,
    pool: ThreadPoolExecutor | None = None,
) -> None:
    """Smoothness by GCV over `grid` with the tracks' current weights, score = (RSS / m) / (1 - tr(H) / m)^2
    (m = 2 per ray), and the robust scale from the noise level the fit implies, sigma^2 = RSS / (m - tr(H)).

    The residuals' own spread would underestimate sigma by the fitted degrees of freedom; re-estimated every IRLS
    round it also shrinks as observations are down-weighted, until the poorly constrained ends of a track are
    rejected. So the scale is set here, once per GCV pass, and held during IRLS.
    """
    m = np.array([2.0 * track.seen.size for track in tracks])[:, None]  # each ray constrains two coordinates
    fits = _GridFits(tracks, prior, grid, n, pool)
    if options.rule is SmoothnessRule.GCV_GLOBAL:
        fits.compute(np.ones(fits.known.shape, dtype=bool))
        total = float(m.sum())
        scores = _least_gcv(fits.rss.sum(axis=0)[None], fits.trace.sum(axis=0)[None], np.array([[total]]))
        chosen = np.full(len(tracks), int(scores[0]))
    else:
        fits.least_gcv(m)
        chosen = _least_gcv(fits.rss, np.where(fits.known, fits.trace, m), m)
    for k, track in enumerate(tracks):
        g = int(chosen[k])
        track.smoothness = grid[g]
        # Weighted RSS over the weights' effective count of residual components.
        effective = float(np.sum(track.weights)) * 2.0
        sigma = np.sqrt(fits.rss[k, g] / max(effective - fits.trace[k, g], 1.0))
        track.scale = max(SCALE_SIGMAS * sigma, MIN_SCALE_PX)


def _choose_smoothness_in_window(
    tracks: list[_Track],
    prior: np.ndarray,
    grid: list[float],
    nodes: TimeNodes,
    options: RefineOptions,
    pool: ThreadPoolExecutor | None = None,
) -> None:
    """`_choose_smoothness`, on the middle GCV_WINDOW instants where there are more (the module's constants)."""
    n = len(nodes.times)
    if n <= GCV_WINDOW:
        _choose_smoothness(tracks, prior, grid, n, options, pool)
        return
    low = (n - GCV_WINDOW) // 2
    high = low + GCV_WINDOW
    window = TimeNodes(node_of_frame=np.zeros(0, dtype=np.int64), times=nodes.times[low:high], tau=nodes.tau)
    views = [_window_view(track, low, high) for track in tracks]
    inside = [k for k, view in enumerate(views) if view.seen.size >= GCV_WINDOW_MIN_OBSERVATIONS]
    outside = [track for track, view in zip(tracks, views, strict=True) if view.seen.size < GCV_WINDOW_MIN_OBSERVATIONS]
    log.info(
        "smoothness of %d point(s) chosen on the middle %d of %d instants (GCV_WINDOW), %d on all of theirs",
        len(inside),
        GCV_WINDOW,
        n,
        len(tracks) - len(inside),
    )
    if inside:
        _choose_smoothness([views[k] for k in inside], prior_bands(window), grid, GCV_WINDOW, options, pool)
        for k in inside:
            tracks[k].smoothness, tracks[k].scale = views[k].smoothness, views[k].scale
    if outside:
        _choose_smoothness(outside, prior, grid, n, options, pool)


def _window_view(track: _Track, low: int, high: int) -> _Track:
    """The track's observations at instants low..high-1, renumbered from 0 (its start, positions and weights too)."""
    keep = (track.node >= low) & (track.node < high)
    return _Track(
        point=track.point,
        seen=track.seen[keep],
        node=track.node[keep] - low,
        rays=track.rays[keep],
        centers=track.centers[keep],
        s2=track.s2[keep],
        mean_s2=track.mean_s2,
        anchor=track.anchor[low:high],
        positions=track.positions[low:high],
        weights=track.weights[keep],
        scale=track.scale,
        smoothness=track.smoothness,
    )


def _fit_tracks(
    tracks: list[_Track], prior: np.ndarray, n: int, pool: ThreadPoolExecutor | None = None
) -> list[np.ndarray]:
    """`_fit` of every track at its smoothness and weights, (n, 3) each: the systems side by side in one LAPACK
    call per batch and worker (the same numbers, fewer calls)."""
    batch = max(1, _GridFits.BATCH_BYTES // (BANDS * 3 * n * 8))
    if pool is not None:  # a batch per worker at least: a track's fit does not depend on its neighbours
        batch = max(1, min(batch, -(-len(tracks) // WORKERS)))
    chunks = [tracks[start : start + batch] for start in range(0, len(tracks), batch)]
    fitted = (
        pool.map(_fit_chunk, chunks, [prior] * len(chunks), [n] * len(chunks))
        if pool is not None
        else (_fit_chunk(chunk, prior, n) for chunk in chunks)
    )
    return [positions for part in fitted for positions in part]


def _fit_chunk(chunk: list[_Track], prior: np.ndarray, n: int) -> list[np.ndarray]:
    """`_fit` of the tracks of `chunk`, (n, 3) each, in one LAPACK call."""
    data = [track.data(n) for track in chunk]
    systems = [
        _grid_systems(prior, t, np.array([t.smoothness]), blocks)[0] for t, (blocks, _) in zip(chunk, data, strict=True)
    ]
    factor = _stacked_factor(np.stack(systems))
    if factor is None:  # one needs `_fit`'s stronger anchor: each on its own (the same numbers for the others)
        return [_fit(prior, t.mean_s2, t.smoothness, b, r, t.anchor)[0] for t, (b, r) in zip(chunk, data, strict=True)]
    b = np.concatenate(
        [(r + _anchor_weight(blocks) * t.anchor).reshape(-1) for t, (blocks, r) in zip(chunk, data, strict=True)]
    )
    stacked = factor.transpose(1, 0, 2).reshape(BANDS, -1)
    return list(cho_solve_banded((stacked, True), b).reshape(len(chunk), n, 3))


def _grid_systems(prior: np.ndarray, track: _Track, values: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    """(G, BANDS, 3n) the systems of `_fit` for each smoothness value, same arithmetic."""
    n = len(blocks)
    diagonal = blocks + _anchor_weight(blocks) * np.eye(3)[None]
    systems = (np.asarray(values, dtype=float) * track.mean_s2)[:, None, None] * prior[None]
    columns = systems.reshape(len(systems), BANDS, n, 3)  # a view: column 3i + col is [..., i, col]
    for row in range(3):
        for col in range(row + 1):
            columns[:, row - col, :, col] += diagonal[:, row, col]
    return systems


def _anchor_weight(blocks: np.ndarray) -> float:
    """`_fit`'s tiny pull towards the start positions."""
    return 1e-9 * max(float(np.mean(np.trace(blocks, axis1=1, axis2=2))), 1e-300)


def _stacked_factor(systems: np.ndarray) -> np.ndarray | None:
    """(G, BANDS, N) banded Cholesky factors of G systems side by side in one LAPACK call (no band crosses a
    seam, so each factor is the one of its own system); None when one is numerically singular."""
    G, bands, N = systems.shape
    try:
        factor = cholesky_banded(systems.transpose(1, 0, 2).reshape(bands, G * N), lower=True)
    except LinAlgError:
        return None
    return factor.reshape(bands, G, N).transpose(1, 0, 2)


class _GridFits:
    """The tracks' fits at the grid's smoothness values, RSS and tr(H), computed on demand: the fits and the
    selected inverse are most of the refinement's cost, and the GCV choice needs them only near each track's
    least score."""

    COARSE_STEP = 4  # first evaluated grid values: every COARSE_STEP-th and the last
    BATCH_BYTES = 2**26  # factors per batch of the selected inverse (its two work arrays are as large)
    # Relative margin of the lower bounds on the score: the tiny anchor pull of `_fit` and round-off make RSS and
    # tr(H) monotone in the smoothness only to about this.
    BOUND_MARGIN = 1e-3

    def __init__(
        self, tracks: list[_Track], prior: np.ndarray, grid: list[float], n: int, pool: ThreadPoolExecutor | None = None
    ):
        self.pool = pool
        self.tracks, self.prior, self.grid = tracks, prior, np.asarray(grid, dtype=float)
        self.data = [track.data(n) for track in tracks]
        shape = (len(tracks), len(grid))
        self.rss, self.trace = np.zeros(shape), np.full(shape, np.nan)
        self.known = np.zeros(shape, dtype=bool)
        self.batch = max(1, self.BATCH_BYTES // (BANDS * 3 * n * 8))

    def compute(self, wanted: np.ndarray) -> None:
        """Fit, RSS and trace where `wanted (K, G)` and not yet known, in batches of systems."""
        pairs = np.argwhere(wanted & ~self.known)
        for start in range(0, len(pairs), self.batch):
            chunk = pairs[start : start + self.batch]
            tracks = np.unique(chunk[:, 0]).tolist()
            columns = [chunk[chunk[:, 0] == k, 1] for k in tracks]
            factors = np.concatenate(self._map(self._fit_track, tracks, columns))
            data = np.stack([self.data[int(k)][0] for k in chunk[:, 0]])
            # each system's trace is its own (the batch is elementwise on the last axis): halves side by side
            parts = WORKERS if self.pool is not None and len(factors) > 1 else 1
            traces = self._map(trace_of_inverse_times, np.array_split(factors, parts), np.array_split(data, parts))
            self.trace[chunk[:, 0], chunk[:, 1]] = np.concatenate(traces)
        self.known |= wanted

    def _map(self, function: Callable[..., np.ndarray], *arguments: list) -> list[np.ndarray]:
        """[function(*a) for a in zip(*arguments)], on the pool's threads when there is one."""
        if self.pool is None:
            return list(map(function, *arguments))
        return list(self.pool.map(function, *arguments))

    def _fit_track(self, k: int, columns: np.ndarray) -> np.ndarray:
        """Fits of track k at grid values `columns`: sets their RSS, returns their factors (len, BANDS, 3n)."""
        track = self.tracks[k]
        blocks, rhs = self.data[k]
        n = len(blocks)
        factor = _stacked_factor(_grid_systems(self.prior, track, self.grid[columns], blocks))
        if factor is None:  # one value needs `_fit`'s stronger anchor: each on its own
            fits = [_fit(self.prior, track.mean_s2, self.grid[g], blocks, rhs, track.anchor) for g in columns]
            positions = np.stack([f[0] for f in fits])
            factor = np.stack([f[1] for f in fits])
        else:
            b = np.tile((rhs + _anchor_weight(blocks) * track.anchor).reshape(-1), len(columns))
            stacked = factor.transpose(1, 0, 2).reshape(BANDS, -1)
            positions = cho_solve_banded((stacked, True), b).reshape(len(columns), n, 3)
        for g, fitted in zip(columns, positions, strict=True):
            self.rss[k, g] = float(np.sum(track.weights * track.residuals(fitted) ** 2))
        return factor

    def least_gcv(self, m: np.ndarray) -> None:
        """Known at least where `_least_gcv` over the whole grid could choose: every value whose GCV score may be
        below the best known one. RSS rises and tr(H) falls as the smoothness grows, so a value between two known
        ones scores at least the smaller smoothness's RSS over the larger one's denominator."""
        K, G = self.known.shape
        wanted = np.zeros((K, G), dtype=bool)
        wanted[:, :: self.COARSE_STEP] = wanted[:, -1] = True
        if self.batch >= K * G:  # one pass over the columns holds them all: rounds would cost more than they save
            wanted[:] = True
        while wanted.any():
            self.compute(wanted)
            wanted = self._bisections(m)

    def _bisections(self, m: np.ndarray) -> np.ndarray:
        """(K, G) the middle of every gap between known values that holds a value whose lower bound on the score
        is not above the best known score."""
        K, G = self.known.shape
        score = np.where(self.known, _gcv_scores(self.rss, np.where(self.known, self.trace, 0.0), m), np.inf)
        best = score.min(axis=1)
        wanted = np.zeros((K, G), dtype=bool)
        for k in range(K):
            known = np.flatnonzero(self.known[k])
            for a, b in itertools.pairwise(known):
                if b - a < 2:
                    continue
                bound = self.rss[k, a] / m[k, 0] / max(1 - self.trace[k, b] / m[k, 0], 1e-9) ** 2
                if bound * (1 - self.BOUND_MARGIN) <= best[k] or not np.isfinite(best[k]):
                    wanted[k, (a + b) // 2] = True
        return wanted


MIN_RESIDUAL_DOF = 1.0  # GCV candidates must leave at least this many residual degrees of freedom (m - tr(H))


def _least_gcv(rss: np.ndarray, trace: np.ndarray, m: np.ndarray) -> np.ndarray:
    """(T,) index of each row's least GCV score over the grid, rss and trace (T, G), m (T, 1).

    A fit with m - tr(H) near 0 interpolates its rays: RSS and the denominator (1 - tr(H)/m)^2 both vanish and the
    score is round-off. With unsynchronized cameras each instant often has one ray, which any small smoothness
    fits exactly, so these values can be most of the grid, and the choice among them would flip with round-off
    from run to run. Such values are not candidates. When every value interpolates, the data cannot choose, and the
    least smoothing keeps the trajectory on its rays."""
    score = _gcv_scores(rss, trace, m)
    score[np.isinf(score).all(axis=1)] = 0.0
    return np.argmin(score, axis=1)


def _gcv_scores(rss: np.ndarray, trace: np.ndarray, m: np.ndarray) -> np.ndarray:
    """GCV scores (T, G); inf where a value interpolates its rays (fewer than MIN_RESIDUAL_DOF residual dof)."""
    score = rss / m / np.maximum(1 - trace / m, 1e-9) ** 2
    score[m - trace < MIN_RESIDUAL_DOF] = np.inf
    return score


def _start_per_node(start: np.ndarray, nodes: TimeNodes) -> np.ndarray:
    """(n, 3) mean input position per instant; instants without one take the nearest instant's."""
    n = len(nodes.times)
    ok = np.isfinite(start).all(axis=1)
    sums = np.zeros((n, 3))
    counts = np.zeros(n)
    np.add.at(sums, nodes.node_of_frame[ok], start[ok])
    np.add.at(counts, nodes.node_of_frame[ok], 1.0)
    have = counts > 0
    anchor = np.empty((n, 3))
    anchor[have] = sums[have] / counts[have, None]
    if not have.all():
        known = np.flatnonzero(have)
        for axis in range(3):
            anchor[~have, axis] = np.interp(nodes.times[~have], nodes.times[known], anchor[known, axis])
    return anchor


def _loss_scale(residual: np.ndarray) -> float:
    """The first robust scale, from the start's residual norms (px)."""
    sigma = float(np.median(residual)) / RAYLEIGH_MEDIAN if residual.size else 0.0
    return max(SCALE_SIGMAS * sigma, MIN_SCALE_PX)


def _rho(residual: np.ndarray, loss: RobustLoss, scale: float) -> np.ndarray:
    """The robust loss of residual norms (px^2 units; r^2 for small residuals)."""
    if loss is RobustLoss.NONE:
        return residual**2
    if loss is RobustLoss.HUBER:
        return np.where(residual <= scale, residual**2, 2 * scale * residual - scale**2)
    return scale**2 * np.log1p((residual / scale) ** 2)


def _prior_value(bands: np.ndarray, y: np.ndarray) -> np.ndarray:
    """y^T M y for the lower-banded prior M (BANDS, N) of `prior_bands` and y (..., N); its other bands are zero,
    and their terms would add exact zeros."""
    value = np.sum(bands[0] * y * y, axis=-1)
    for d in PRIOR_DIAGONALS[1:]:
        value = value + 2.0 * np.sum(bands[d, :-d] * y[..., :-d] * y[..., d:], axis=-1)
    return value


# ---------------------------------------------------------------------------------------------------------------
# The clock polish: per-video offset and rate corrections that minimize the refinement's own cost

POLISH_ROUNDS = 2  # refine (choosing the smoothness), then search the clocks; repeated
POLISH_SWEEPS = 4  # coordinate-descent sweeps over the videos per round
POLISH_REACH_PERIODS = 1.0  # each sweep searches a video's offset within +- this many of its frame periods
POLISH_TOLERANCE = 0.005  # the golden-section search stops at this share of its reach
POLISH_STOP = 1e-6  # sweeps stop when one lowers the cost by less than this share
# Beyond this many point-frames the polish's cost uses the most observed points up to it (at least
# POLISH_MIN_POINTS): every point sees the same clocks, and each cost evaluation solves every point over every
# instant, dozens of times per polish.
POLISH_SIZE = 200_000
POLISH_MIN_POINTS = 4


@dataclass(kw_only=True)
class ClockRefineResult:
    times: np.ndarray  # (F,) adjusted global times, s
    correction: ClockCorrection  # from the input times to `times` (the reference's is 0)
    cost: list[float]  # trajectory cost after each sweep (px^2)
    result: RefineResult  # the refinement at the adjusted times
    at_input: RefineResult | None = None  # the refinement at the input times (what a rejected polish falls back to)


def refine_with_clocks(
    problem: Problem,
    points: np.ndarray,
    times: np.ndarray,
    options: RefineOptions | None = None,
    *,
    reference: int | None = None,
    rates: bool = True,
) -> ClockRefineResult:
    """`refine`, then per-video time offsets (and, with `rates`, rates) that minimize the refinement's own cost,
    then `refine` again; POLISH_ROUNDS times (each round re-chooses the smoothness: wrong times make GCV smooth
    more, which flattens the cost the clocks are searched on). Video `reference` keeps its clock (default: the one
    with most frames): the cost does not see a global affine change of time."""
    options = options or RefineOptions()
    times = np.asarray(times, dtype=float)
    original = times
    result = _clock_round(problem, points, times, options, reference, rates)
    at_input = result.at_input
    history = list(result.cost)
    for _ in range(POLISH_ROUNDS - 1):
        if np.array_equal(result.times, times):
            break  # no clock moved: another round would repeat this one exactly
        times = result.times
        # the round's own first refinement would repeat the last one (same inputs): start from it
        result = _clock_round(problem, points, result.times, options, reference, rates, result.result)
        history.extend(result.cost)
    # Corrections relative to the input times (the rounds compose affine maps per video).
    correction = ClockCorrection.fit(original, result.times, problem.video_index, len(problem.video_names))
    return ClockRefineResult(
        times=result.times, correction=correction, cost=history, result=result.result, at_input=at_input
    )


def _clock_round(
    problem: Problem,
    points: np.ndarray,
    times: np.ndarray,
    options: RefineOptions,
    reference: int | None,
    rates: bool,
    first: RefineResult | None = None,
) -> ClockRefineResult:
    """One round of refine_with_clocks; `first`: the refinement at `times`, when an earlier round computed it.

    Estimated clocks can be off by a fraction of a frame, which folds the trajectory into a zig-zag the prior pays
    for. With the smoothness and robust weights of a first refinement held fixed, the cost (weighted ray distances
    + smoothness) is a function of the clocks alone; each video's offset (then rate) is found by golden-section
    search in turn (coordinate descent).
    """
    first = first if first is not None else refine(problem, points, times, options)
    N = len(problem.video_names)
    counts = np.bincount(problem.video_index, minlength=N)
    if reference is None:
        reference = int(np.argmax(counts))
    middle = np.array([np.median(times[problem.video_index == v]) if counts[v] else 0.0 for v in range(N)])
    correction = ClockCorrection.none(middle)
    with _threads() as pool:
        cost = _PolishCost(problem, first, times, pool)
        history = _coordinate_descent(cost, times, problem.video_index, correction, rates)
    adjusted, correction = correction.in_gauge_of(reference, times, problem.video_index)
    log.info(
        "clock offsets (ms): %s; rates (ms/s): %s; trajectory cost %.4g -> %.4g",
        ", ".join(f"{1000 * o:+.2f}" for o in correction.offset),
        ", ".join(f"{1000 * r:+.2f}" for r in correction.rate),
        history[0],
        history[-1],
    )
    # a polish that moved no clock leaves the times bitwise as they were: the first refinement is the final one
    final = first if np.array_equal(adjusted, times) else refine(problem, points, adjusted, options)
    return ClockRefineResult(times=adjusted, correction=correction, cost=history, result=final, at_input=first)


class _PolishCost:
    """The refinement's cost (px^2) at candidate frame times, one banded solve for all refined points; held fixed:
    the smoothness and robust weights of a first refinement, and each observation's px scale from its positions
    (time shifts of a fraction of a frame barely move the depths). The points are independent: with a `pool`,
    each worker solves a run of them (`_PolishPart`), and only the final sums are taken over all."""

    def __init__(
        self, problem: Problem, first: RefineResult, times: np.ndarray, pool: ThreadPoolExecutor | None = None
    ):
        self.pool = pool
        normalization = camera_normalization(problem.centers, problem.video_index)
        centers = normalization.apply(problem.centers)
        rays = viewing_rays(problem)
        focal = np.sqrt(problem.K[:, 0, 0] * problem.K[:, 1, 1])
        self.tau = time_nodes(times).tau
        self.span = float(np.ptp(times))
        refined = _polish_points(problem.observed, np.isfinite(first.smoothness))
        observed = problem.observed & refined[None, :]
        frame, point = np.nonzero(observed)  # every observation of a refined point
        keep = np.flatnonzero(refined)
        column = np.searchsorted(keep, point)  # the observation's point among the refined ones
        positions = normalization.apply(first.points)
        depth = np.einsum("mi,mi->m", positions[frame, point] - centers[frame], rays[frame, point])
        s2 = (focal[frame] / np.maximum(depth, 1e-9)) ** 2
        self.weight = np.nan_to_num(first.weights[frame, point]) * s2
        mean_s2 = np.array([np.mean(np.sqrt(s2[column == k])) ** 2 for k in range(len(keep))])
        self.strength = first.smoothness[keep] * mean_s2  # (P',)
        self.num_observations = len(frame)
        bounds = [len(keep) * w // WORKERS for w in range(WORKERS + 1)] if pool is not None else [0, len(keep)]
        self.parts = [
            _PolishPart(
                observations=np.flatnonzero((column >= low) & (column < high)),
                first=low,
                frame=frame,
                column=column,
                rays=rays[frame, point],
                centers=centers[frame],
                weight=self.weight,
                strength=self.strength[low:high],
                known_positions=np.nan_to_num(positions[:, keep[low:high]]),
            )
            for low, high in itertools.pairwise(bounds)
            if high > low
        ]

    def __call__(self, candidate: np.ndarray) -> float:
        # Time unit proportional to the span: the cost is then invariant to a global affine change of time (the
        # gauge), so every video, the reference included, can move alone.
        nodes = time_nodes(candidate, MERGE_FRACTION, self.tau * float(np.ptp(candidate)) / self.span)
        prior = prior_bands(nodes)
        frames_at = np.bincount(nodes.node_of_frame, minlength=len(nodes.times))

        def run(part: _PolishPart) -> tuple[np.ndarray, np.ndarray]:
            return part.evaluate(nodes.node_of_frame, frames_at, prior)

        solved = self.pool.map(run, self.parts) if self.pool is not None else map(run, self.parts)
        squared = np.empty(self.num_observations)
        prior_values = []
        for part, (distance2, value) in zip(self.parts, solved, strict=True):
            squared[part.observations] = distance2
            prior_values.append(value)
        total = float(np.sum(self.weight * squared))
        return total + float(np.sum(self.strength * np.concatenate(prior_values)))


class _PolishPart:
    """A run of the polish cost's points, `first` on: their observations (indices among all, in their order) and
    what their systems need, each observation with a zero row for `_sum_at_slots`."""

    def __init__(
        self,
        *,
        observations: np.ndarray,
        first: int,
        frame: np.ndarray,
        column: np.ndarray,
        rays: np.ndarray,
        centers: np.ndarray,
        weight: np.ndarray,
        strength: np.ndarray,
        known_positions: np.ndarray,
    ):
        self.observations = observations
        self.frame = frame[observations]
        self.column = column[observations] - first  # the observation's point within the part
        self.strength = strength  # (K,)
        self.rays, self.centers = rays[observations], centers[observations]
        projector = np.eye(3)[None] - self.rays[:, :, None] * self.rays[:, None, :]
        blocks = weight[observations, None, None] * projector
        # each block's lower triangle (m + 1, 6), all the systems need, and right-hand side (m + 1, 3)
        self.lower = _zero_row(np.stack([blocks[:, row, col] for row, col in LOWER], axis=1))
        self.rhs = _zero_row(np.einsum("mij,mj->mi", blocks, self.centers))
        self.known_positions = _zero_row(known_positions)  # (F + 1, K, 3)

    def evaluate(
        self, node_of_frame: np.ndarray, frames_at: np.ndarray, prior: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The part's squared ray distances (m,), unweighted, and prior values (K,) at the solved positions, for the
        instants `node_of_frame (F,)` holding `frames_at (n,)` frames each."""
        K, n = len(self.strength), len(frames_at)
        node = node_of_frame[self.frame]
        slot = self.column * n + node
        alone = frames_at[node] == 1  # an instant of one frame holds one observation of each point
        lower = _sum_at_slots(slot, self.lower, K * n, alone).reshape(K, n, 6)
        rhs = _sum_at_slots(slot, self.rhs, K * n, alone).reshape(K, n, 3)
        d0, d1, d2 = LOWER_DIAGONAL
        eps = 1e-9 * np.maximum(np.mean(lower[..., d0] + lower[..., d1] + lower[..., d2], axis=1), 1e-300)
        lower[..., LOWER_DIAGONAL] += eps[:, None, None]  # + eps I (the off-diagonal entries' + 0 changes nothing)
        # mean position per instant (the tiny eps pull's target)
        anchor = _sum_at_slots(node_of_frame, self.known_positions, n, frames_at[node_of_frame] == 1)
        anchor /= np.maximum(frames_at, 1)[:, None, None]
        rhs += eps[:, None, None] * anchor.transpose(1, 0, 2)
        # Points are independent: their systems side by side form one banded matrix (no band crosses a seam, and
        # LAPACK's banded Cholesky, unblocked for so few bands, and solves work column by column: each point's
        # numbers are its own, whichever points share the call).
        system = np.zeros((BANDS, K, 3 * n))  # (BANDS, K, 3n); the prior's other bands are zero
        for d in PRIOR_DIAGONALS:
            np.multiply(self.strength[:, None], prior[d], out=system[d])
        columns = system.reshape(BANDS, K, n, 3)  # a view: column 3i + col of point k is [:, k, i, col]
        for entry, (row, col) in enumerate(LOWER):
            columns[row - col, :, :, col] += lower[:, :, entry]
        # finite by construction: LAPACK's own checks suffice
        factor = cholesky_banded(system.reshape(BANDS, -1), lower=True, check_finite=False)
        solved = cho_solve_banded((factor, True), rhs.reshape(-1), check_finite=False).reshape(K, n, 3)
        offset = solved.reshape(-1, 3).take(slot, axis=0) - self.centers
        along = np.einsum("mi,mi->m", offset, self.rays)
        perpendicular = offset - along[:, None] * self.rays
        return np.einsum("mi,mi->m", perpendicular, perpendicular), _prior_value(prior, solved.reshape(K, -1))


def _polish_points(observed: np.ndarray, refined: np.ndarray) -> np.ndarray:
    """(P,) the refined points whose observations `observed (F, P)` the polish's cost uses: all of them, or the
    most observed ones where they span more than POLISH_SIZE point-frames."""
    count = int(refined.sum())
    allowed = max(POLISH_MIN_POINTS, POLISH_SIZE // max(len(observed), 1))
    if count <= allowed:
        return refined
    seen = np.where(refined, observed.sum(axis=0), -1)
    chosen = np.zeros_like(refined)
    chosen[np.argsort(-seen, kind="stable")[:allowed]] = True
    log.info("clock polish on the %d most observed of %d points (%d frames)", allowed, count, len(observed))
    return chosen


def _coordinate_descent(
    cost: _PolishCost, times: np.ndarray, video_index: np.ndarray, correction: ClockCorrection, rates: bool
) -> list[float]:
    """Sweeps over the videos, each video's offset (then rate) by golden-section search with the others held;
    `correction` is updated in place. Returns the cost before and after each sweep."""
    history = [cost(times)]
    current = history[0]  # the cost at the current correction: every search's value at 0, known without a solve
    # (video, kind) -> the correction its last search could not improve: the same search there finds nothing again
    fruitless: dict[tuple[int, str], bytes] = {}
    for _ in range(max(POLISH_SWEEPS, 0)):
        for v in range(len(correction.offset)):
            own = video_index == v
            if own.sum() < 2:
                continue
            period = float(np.median(np.diff(np.sort(times[own]))))
            video_span = float(np.ptp(times[own]))
            if not (period > 0 and video_span > 0):
                continue
            for kind in ("offset", "rate") if rates else ("offset",):
                state = correction.offset.tobytes() + correction.rate.tobytes()
                if fruitless.get((v, kind)) == state:
                    continue
                values = correction.offset if kind == "offset" else correction.rate
                # The rate's bracket moves the video's ends by as much as the offset's moves its middle.
                reach = POLISH_REACH_PERIODS * period * (1.0 if kind == "offset" else 2.0 / video_span)

                def shifted(delta: float, values: np.ndarray = values, v: int = v) -> float:
                    trial = values.copy()
                    trial[v] += delta
                    if values is correction.offset:
                        moved = ClockCorrection(middle=correction.middle, offset=trial, rate=correction.rate)
                    else:
                        moved = ClockCorrection(middle=correction.middle, offset=correction.offset, rate=trial)
                    return cost(moved.apply(times, video_index))

                best, best_cost = _search_from_zero(shifted, current, reach, POLISH_TOLERANCE * reach)
                if best_cost < current:
                    values[v] += best  # the same sum as the search's trial: `current` is its cost exactly
                    current = best_cost
                else:
                    fruitless[v, kind] = state
        history.append(current)
        if history[-2] - history[-1] <= POLISH_STOP * abs(history[-2]):
            break
    return history


def _search_from_zero(
    f: Callable[[float], float], at_zero: float, reach: float, tolerance: float
) -> tuple[float, float]:
    """Minimum of a unimodal f on [-reach, reach] to `tolerance`, f(0) = `at_zero` known: (argument, value).

    Probes +- tolerance / 2 first. Where neither is lower than f(0) the minimum lies within them, i.e. at 0 to the
    tolerance (two solves: the usual case once the clocks are right); otherwise it lies on the lower side, which
    the golden-section search takes."""
    half = tolerance / 2
    for side in (1.0, -1.0):
        probe = f(side * half)
        if probe < at_zero:
            low, high = (0.0, reach) if side > 0 else (-reach, 0.0)
            best, best_value = _golden_search(f, low, high, tolerance)
            return (best, best_value) if best_value < probe else (side * half, probe)
    return 0.0, at_zero


def _golden_search(f: Callable[[float], float], low: float, high: float, tolerance: float) -> tuple[float, float]:
    """Minimum of a unimodal f on [low, high] to `tolerance`: (argument, value)."""
    golden = (np.sqrt(5.0) - 1) / 2
    a, b = high - golden * (high - low), low + golden * (high - low)
    fa, fb = f(a), f(b)
    while high - low > tolerance:
        if fa < fb:
            high, b, fb = b, a, fa
            a = high - golden * (high - low)
            fa = f(a)
        else:
            low, a, fa = a, b, fb
            b = low + golden * (high - low)
            fb = f(b)
    return (a, fa) if fa < fb else (b, fb)
