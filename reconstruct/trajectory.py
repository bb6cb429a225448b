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

The banded system's pieces are in reconstruct/spline_system.py, the GCV trace's inverse blocks in
reconstruct/block_inverse.py; reconstruct/clock_polish.py polishes the clocks on this cost (`refine_with_clocks`).
docs/refinement.md describes the whole.
"""

from __future__ import annotations

import enum
import itertools
import logging
import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import LinAlgError, cho_solve_banded, cholesky_banded

from dynrecon.errors import InputError
from reconstruct.block_inverse import BANDS, trace_of_inverse_times
from reconstruct.solver.problem import Problem
from reconstruct.solver.rays import camera_normalization, viewing_rays
from reconstruct.spline_system import TimeNodes, add_blocks, data_blocks, prior_bands, prior_value, time_nodes

log = logging.getLogger(__name__)

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
# GCV trace's recursion costs a Python step per instant, and the noise level and the motion's smoothness that
# GCV weighs are properties of the point, not of the capture's length. The fits themselves use every instant.
GCV_WINDOW = 1000
# A point with fewer observations in that window is chosen on all of its own (exactly as below the window).
GCV_WINDOW_MIN_OBSERVATIONS = 50
OUTLIER_FACTOR = 3.0  # residual > factor x scale marks an observation as an outlier in the result
# Anchors (shares of the system's largest entry) tried in turn where a point's system is numerically singular: a
# double-precision Cholesky holds a condition number up to about 1e15
SINGULAR_ANCHOR = (1e-12, 1e-10, 1e-8)
# Threads for independent points (their banded solves and GCV traces; bit-identical for any count). One:
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
    # (P,) GCV score at the chosen smoothness (px^2 per residual component): the fit's error predicted for a ray it
    # did not see; NaN for points not refined
    gcv_px2: np.ndarray = field(default_factory=lambda: np.zeros(0))


def _fit(
    prior: np.ndarray, scale2: float, smoothness: float, blocks: np.ndarray, rhs: np.ndarray, anchor: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Solve (lambda s^2 P + D + eps I) Y = d + eps Y0 for one point (blocks already carry w s^2); returns the
    positions (n, 3) and the banded Cholesky factor (for the GCV trace)."""
    n = len(blocks)
    eps = _anchor_weight(blocks)
    system = add_blocks(smoothness * scale2 * prior, blocks + eps * np.eye(3)[None])
    b = (rhs + eps * anchor).reshape(-1)
    try:
        factor = cholesky_banded(system, lower=True)
    except LinAlgError:
        # Numerically singular (a point with hardly any rays, or one video's rays alone under a strong prior, whose
        # null space of straight motions they do not pin): a stronger anchor keeps the input position there. It
        # is relative to the system's largest entry, as is the precision the factorization loses.
        for share in SINGULAR_ANCHOR:
            ridge = max(1e-6, share * float(np.abs(system[0]).max()))
            anchored = add_blocks(system, np.broadcast_to(ridge * np.eye(3), (n, 3, 3)))
            try:
                factor = cholesky_banded(anchored, lower=True)
            except LinAlgError:
                continue
            b = (rhs + (eps + ridge) * anchor).reshape(-1)
            break
        else:
            raise
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
    gcv: float = math.nan  # GCV score at the chosen smoothness, px^2 per residual component
    residual: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (m,) px

    def residuals(self, positions: np.ndarray) -> np.ndarray:
        """(m,) reprojection errors in px (ray distance x focal / depth)."""
        offset = positions[self.node] - self.centers
        perpendicular = offset - np.einsum("mi,mi->m", offset, self.rays)[:, None] * self.rays
        return np.sqrt(self.s2 * np.einsum("mi,mi->m", perpendicular, perpendicular))

    def data(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        return data_blocks(self.rays, self.centers, self.weights * self.s2, self.node, n)


def worker_pool() -> AbstractContextManager[ThreadPoolExecutor | None]:
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
    with worker_pool() as pool:
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
    gcv = np.full(P, np.nan)
    for track in tracks:
        p = track.point
        out[:, p] = track.positions[nodes.node_of_frame]
        weights[track.seen, p] = track.weights
        residual_px[track.seen, p] = track.residual
        outliers[track.seen, p] = track.residual > OUTLIER_FACTOR * track.scale
        smoothness[p] = track.smoothness
        scale_px[p] = track.scale
        gcv[p] = track.gcv
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
        gcv_px2=gcv,
    )


def predicted_px(result: RefineResult) -> float:
    """The trajectories' error predicted for a ray they did not see (px): the root of the median over refined points
    of their GCV scores (inf where a point's every smoothness fits its rays exactly). Unlike the residual, it is not
    fooled by a fit that bends through every ray (a wrong clock makes the motion look fast, and a small smoothness
    then fits it)."""
    refined = result.gcv_px2[~np.isnan(result.gcv_px2)]
    return float(np.sqrt(np.median(refined))) if refined.size else math.nan


def predicted_pair(a: RefineResult, b: RefineResult) -> tuple[float, float] | None:
    """`predicted_px` of two refinements of one problem over the points both refined, or None where that does not
    compare them (no such point, or every point's score infinite in both)."""
    both = ~np.isnan(a.gcv_px2) & ~np.isnan(b.gcv_px2)
    if not both.any():
        return None
    first, second = a.gcv_px2[both], b.gcv_px2[both]
    if np.isinf(first).all() and np.isinf(second).all():
        return None
    return float(np.sqrt(np.median(first))), float(np.sqrt(np.median(second)))


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
            total += track.smoothness * track.mean_s2 * float(prior_value(prior, track.positions.reshape(-1)))
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
        track.gcv = float(_gcv_scores(fits.rss[k, g, None, None], fits.trace[k, g, None, None], m[k, None])[0, 0])


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
            tracks[k].smoothness, tracks[k].scale, tracks[k].gcv = views[k].smoothness, views[k].scale, views[k].gcv
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
    GCV traces are most of the refinement's cost, and the GCV choice needs them only near each track's
    least score."""

    COARSE_STEP = 4  # first evaluated grid values: every COARSE_STEP-th and the last
    BATCH_BYTES = 2**26  # banded factors per batch of fits and traces
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
