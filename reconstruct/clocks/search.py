"""Clocks from the 2D tracks and poses alone (in the spirit of Albl et al., unsynchronized camera triangulation).

A clock hypothesis for two videos maps the own time of one into the other's. Under the right hypothesis, the track of
one video, interpolated to the other's frame times (rays: pixel direction in the world and camera centre, linear
between the two bracketing frames, so a moving handheld camera is interpolated too), triangulates with the other's
observations: the two rays nearly meet. The score is a truncated (MSAC) cost of the pixel gap between the rays.

1. Pairs: for every pair of videos, a coarse grid over the offset (and, for videos without a known frame rate, the
   common frame-rate ratios), both directions (each video's frames query the other), on a subsample of frames and
   points; the best hypothesis and how distinct it is from the runner-up (another minimum more than a few steps away).
2. Chain: composition of the pair relations along a maximum spanning tree (most distinct pairs) from the reference.
3. Joint refinement of all clocks (offset, rate, drift per the model) by robust least squares (Cauchy) on the gaps
   of every ordered pair of videos; the covariance comes from the final Jacobian. Started from the chained pairs and,
   when given, from the link clocks of W; the start with the lower robust cost wins.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from reconstruct.clocks.chain import chain_clocks
from reconstruct.clocks.model import (
    DEFAULT_FPS,
    Clock,
    ClockModel,
    ClockSet,
    TimeSource,
    frame_periods,
    video_centers,
)
from reconstruct.solver.problem import Problem
from reconstruct.solver.rays import closest_depths, viewing_rays

log = logging.getLogger(__name__)

# Frame rates a consumer video may have: the rate ratios tried for videos without decoder times or a known fps.
COMMON_FPS = (23.976, 24.0, 25.0, 29.97, 30.0, 48.0, 50.0, 59.94, 60.0, 120.0)
MAD_TO_SIGMA = 1.4826
COARSE_STEP_PERIODS = 0.5  # final grid step in frame periods of the slower video of a pair
MAX_HYPOTHESES = 600  # offsets on the first, coarser grid of a pair (then the fine step around the best) ...
# ... unless the subject's image speed makes a basin narrower than that grid's step: then one step per basin (the
# time the tracks take to move `inlier_px`), up to this many offsets
MAX_DENSE_HYPOTHESES = 20_000
DENSE_RATIOS = 2  # where frame rates are unknown, the rate ratios (of the coarse grid's best) searched densely
MIN_OVERLAP = 12  # interpolated samples a hypothesis needs
MIN_OVERLAP_SHARE = 0.15  # ... and this share of the shorter video's observed samples
MIN_SUPPORT_SHARE = 0.5  # ... and this share of the pair's best support (summed margins under the truncation)
MAX_GAP_PERIODS = 2.5  # no interpolation across a gap longer than this (missing frames)
DISTINCT_STEPS = 4  # the runner-up minimum lies more than this many grid steps away
MIN_DISTINCTNESS = 1.15  # runner-up cost / best cost of a pair usable for the chain
REFINE_ROUNDS = 3
REFINE_THRESHOLDS = (8.0, 5.0, 4.0)  # samples kept per refinement round: gap below this many robust scales
CLUSTER_S = 0.5  # residuals within this time of one video form one cluster of the covariance
# Sparse tracks (every n-th frame tracked) are interpolated across their own step only for this few points: with
# many, per-point gaps between people or joints changed the real multi-person Pose2Sim solve (docs/clocks.md).
SPARSE_MAX_POINTS = 3
SPARSE_STEP_PERIODS = 1.5  # a video whose tracked frames are this many frame periods apart (median) is sparse


@dataclass(kw_only=True)
class SearchOptions:
    max_points: int = 3  # points used by the coarse grid (the most observed ones)
    max_queries: int = 150  # frames per video and direction on the coarse grid
    inlier_px: float = 8.0  # truncation of the pixel gap in the coarse cost and in the comparison of starts
    # Prior std of a rate around 1 for videos with decoder times or a known fps (0: none): phone clocks are quartz,
    # while a far, noisy single point leaves the rate of a short video weakly determined.
    rate_prior: float = 2e-4
    max_residuals: int = 30000  # (frame, point, other video) samples in the joint refinement


@dataclass(kw_only=True)
class PairHypothesis:
    """own_u = alpha + beta * own_v at the best coarse cost."""

    v: int
    u: int
    alpha: float
    beta: float
    cost: float  # px^2, mean truncated squared gap
    runner_up: float  # rival cost (`rival_cost`) of the best hypothesis more than `distinct_steps` away
    samples: int
    support: float = math.inf  # px^2, summed margins of its samples under the truncation (MSAC's)
    count: float = math.inf  # samples at the best offset

    @property
    def distinctness(self) -> float:
        return self.runner_up / max(self.cost, 1e-12)


@dataclass(kw_only=True)
class SearchResult:
    params: ClockSet
    pairs: list[PairHypothesis]
    residual_px: float  # robust RMS gap over all samples at the solution
    video_residual_px: np.ndarray  # (N,)
    timing_spread: np.ndarray  # (N,) s, frames' capture-time spread around their clock (jitter), NaN if unknown
    start: str  # "tracks" or "links": the start the refinement kept
    warnings: list[str]
    reference: int  # the gauge video: the one asked for, unless `search_clocks` could move it


@dataclass
class VideoRays:
    """One video's observations in own-time order."""

    own: np.ndarray  # (n,) increasing
    centers: np.ndarray  # (n, 3)
    rays: np.ndarray  # (n, P, 3) unit, NaN where unobserved
    focal: np.ndarray  # (n,)
    max_gap: float

    def interpolate(self, tq: np.ndarray, clamp: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Centres (m, 3), rays (m, P, 3) and focal (m,) at own times tq (m,): NaN where not interpolable (outside
        the video, across a gap), or with `clamp` held at the nearest interpolable value (continuous in tq, for the
        refinement whose sample set is fixed per round)."""
        n = len(self.own)
        k = np.clip(np.searchsorted(self.own, tq, side="right") - 1, 0, max(n - 2, 0))
        if n < 2:
            nan = np.full((len(tq), *self.rays.shape[1:]), np.nan)
            return np.full((len(tq), 3), np.nan), nan, np.full(len(tq), np.nan)
        t0, t1 = self.own[k], self.own[k + 1]
        a = (tq - t0) / (t1 - t0)
        if clamp:
            a = np.clip(a, 0.0, 1.0)
        else:
            ok = (a >= 0) & (a <= 1) & (t1 - t0 <= self.max_gap)
            a = np.where(ok, a, np.nan)
        centers = self.centers[k] * (1 - a)[:, None] + self.centers[k + 1] * a[:, None]
        rays = self.rays[k] * (1 - a)[:, None, None] + self.rays[k + 1] * a[:, None, None]
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
        return centers, rays, self.focal[k]


def _tracks(
    problem: Problem, own: np.ndarray, points: np.ndarray, sampled: bool = False, rays: np.ndarray | None = None
) -> list[VideoRays]:
    """Each video's rays of `points` at every frame, interpolated across at most MAX_GAP_PERIODS frame periods; or,
    `sampled`, at its frames with an observation of them only, across MAX_GAP_PERIODS of its sampling step (tracks of
    every 4th frame: across the untracked frames between them). `rays`: the problem's `viewing_rays`, when known."""
    seen = problem.observed[:, points].any(axis=1) & np.isfinite(own) if sampled else np.ones(len(own), dtype=bool)
    rays = (viewing_rays(problem) if rays is None else rays)[:, points]
    centers = problem.centers
    focal = 0.5 * (problem.K[:, 0, 0] + problem.K[:, 1, 1])
    periods = frame_periods(own, problem.video_index, len(problem.video_names))
    tracks = []
    for v in range(len(problem.video_names)):
        rows = np.flatnonzero((problem.video_index == v) & seen)
        rows = rows[np.argsort(own[rows], kind="stable")]
        step = float(periods[v])
        if sampled:
            step = max(float(np.nan_to_num(periods[v])), _median_step(own[rows]))
        tracks.append(
            VideoRays(
                own=own[rows],
                centers=centers[rows],
                rays=rays[rows],
                focal=focal[rows],
                max_gap=MAX_GAP_PERIODS * step,
            )
        )
    return tracks


def sampled_tracks(
    problem: Problem, own: np.ndarray, points: np.ndarray, rays: np.ndarray | None = None
) -> list[VideoRays]:
    """`_tracks` on the tracked samples of `points` only."""
    return _tracks(problem, own, points, sampled=True, rays=rays)


def _median_step(times: np.ndarray) -> float:
    """The median positive step between sorted `times` (s); 0 without one."""
    steps = np.diff(np.sort(times))
    steps = steps[steps > 0]
    return float(np.median(steps)) if steps.size else 0.0


def sparse_tracks(problem: Problem, own: np.ndarray) -> bool:
    """Tracks of at most SPARSE_MAX_POINTS points sampled sparser than the frames (a video's median step between
    observed frames over SPARSE_STEP_PERIODS of its frame periods: a detector run on every 4th frame)."""
    observed = problem.observed
    if int(observed.any(axis=0).sum()) > SPARSE_MAX_POINTS:
        return False
    periods = frame_periods(own, problem.video_index, len(problem.video_names))
    tracked = observed.any(axis=1) & np.isfinite(own)
    steps = [_median_step(own[(problem.video_index == v) & tracked]) for v in range(len(problem.video_names))]
    return any(
        step > 0 and np.isfinite(period) and step > SPARSE_STEP_PERIODS * period
        for step, period in zip(steps, periods, strict=True)
    )


def video_tracks(problem: Problem, own: np.ndarray, points: np.ndarray) -> list[VideoRays]:
    """Every frame's rays, or for sparse tracks of few points the tracked samples' (`sparse_tracks`)."""
    return sampled_tracks(problem, own, points) if sparse_tracks(problem, own) else _tracks(problem, own, points)


def gap_px(
    c1: np.ndarray,
    r1: np.ndarray,
    f1: np.ndarray,
    c2: np.ndarray,
    r2: np.ndarray,
    f2: np.ndarray,
    signed_depth: bool = True,
    vector: bool = False,
) -> np.ndarray:
    """(m, P) pixel gap between ray pairs: the distance between the rays, half to each, over each depth, times
    each focal length (RMS of the two). NaN where a ray is missing, the rays are parallel or (with `signed_depth`)
    a depth is negative; without it, depths count by magnitude (continuous, for the refinement). `vector`: the
    (m, P, 3) segment between the rays' closest points at the same pixel scale instead of its length."""
    w = np.broadcast_to((c1 - c2)[:, None, :], r1.shape)
    d1, d2, denom = closest_depths(r1, r2, w)
    with np.errstate(invalid="ignore", divide="ignore"):
        between = w + d1[..., None] * r1 - d2[..., None] * r2
        gap = np.sqrt(np.einsum("mpk,mpk->mp", between, between))
        px = 0.5 * gap * np.sqrt((f1[:, None] / d1) ** 2 + (f2[:, None] / d2) ** 2) / math.sqrt(2.0)
    bad = denom < 1e-10
    if signed_depth:
        bad |= (d1 <= 0) | (d2 <= 0)
    if vector:
        with np.errstate(invalid="ignore", divide="ignore"):
            scale = np.where(gap > 0, px / gap, np.nan)
        return np.where(bad[..., None], np.nan, between * scale[..., None])
    return np.where(bad, np.nan, px)


def _query(
    tracks: list[VideoRays], v: int, u: int, own_u: np.ndarray, rows: np.ndarray, smooth: bool = False
) -> np.ndarray:
    """(m, P) gaps between video v's frames `rows` and video u's track interpolated at own_u (m,); `smooth`:
    continuous in own_u (clamped interpolation, unsigned depths)."""
    tv = tracks[v]
    cu, ru, fu = tracks[u].interpolate(own_u, clamp=smooth)
    return gap_px(tv.centers[rows], tv.rays[rows], tv.focal[rows], cu, ru, fu, signed_depth=not smooth)


def _subsample(n: int, limit: int) -> np.ndarray:
    return np.arange(n) if n <= limit else np.unique(np.linspace(0, n - 1, limit).round().astype(np.int64))


def _rate_scales(source: TimeSource) -> np.ndarray:
    """Factors s with true own time ~ s * own: 1 when the own time is known, 30 / fps candidates otherwise."""
    if source is TimeSource.NOMINAL:
        return DEFAULT_FPS / np.array(COMMON_FPS)
    return np.array([1.0])


def _grid_cost(
    tracks: list[VideoRays],
    v: int,
    u: int,
    qv: np.ndarray,
    qu: np.ndarray,
    alphas: np.ndarray,
    beta: float,
    need: int,
    c2: float,
    chunk_samples: int = 400_000,
) -> tuple[np.ndarray, np.ndarray]:
    """(A,) mean truncated squared gap of each hypothesis alpha (inf with fewer than `need` samples) and (A,) its
    support, the summed margin of its samples under the truncation (c2 - gap^2, 0 for an outlier: MSAC's), vectorized
    over chunks of hypotheses."""
    tv, tu = tracks[v], tracks[u]
    P = tv.rays.shape[1]
    per = max(1, chunk_samples // max(1, (len(qv) + len(qu)) * P))
    cost = np.full(len(alphas), np.inf)
    support = np.zeros(len(alphas))
    for start in range(0, len(alphas), per):
        a = alphas[start : start + per]
        A = len(a)
        g1 = _query(tracks, v, u, (a[:, None] + beta * tv.own[qv][None]).ravel(), np.tile(qv, A))
        g2 = _query(tracks, u, v, ((tu.own[qu][None] - a[:, None]) / beta).ravel(), np.tile(qu, A))
        g1 = g1.reshape(A, -1)
        g2 = g2.reshape(A, -1)
        n = np.isfinite(g1).sum(axis=1) + np.isfinite(g2).sum(axis=1)
        total = np.minimum(np.nan_to_num(g1, nan=0.0) ** 2, c2).sum(axis=1) + np.minimum(
            np.nan_to_num(g2, nan=0.0) ** 2, c2
        ).sum(axis=1)
        cost[start : start + per] = np.where(n >= need, total / np.maximum(n, 1), np.inf)
        support[start : start + per] = np.where(n >= need, n * c2 - total, 0.0)
    return cost, support


def _pair_queries(
    tracks: list[VideoRays], v: int, u: int, options: SearchOptions
) -> tuple[np.ndarray, np.ndarray, int]:
    """The pair's query rows of v and u (subsampled) and the interpolated samples a hypothesis needs."""
    qv = _subsample(len(tracks[v].own), options.max_queries)
    qu = _subsample(len(tracks[u].own), options.max_queries)
    seen_v = np.isfinite(tracks[v].rays[qv, :, 0])
    seen_u = np.isfinite(tracks[u].rays[qu, :, 0])
    return qv, qu, max(MIN_OVERLAP, int(MIN_OVERLAP_SHARE * min(seen_v.sum(), seen_u.sum())))


def pair_cost(
    tracks: list[VideoRays], v: int, u: int, alpha: float, beta: float, options: SearchOptions, count: float = math.inf
) -> float:
    """The pair search's cost (px^2) of one hypothesis own_u = alpha + beta own_v (inf: too little overlap), as a
    rival of a best hypothesis of `count` samples (`rival_cost`; its own mean by default)."""
    qv, qu, need = _pair_queries(tracks, v, u, options)
    c2 = options.inlier_px**2
    cost, support = _grid_cost(tracks, v, u, qv, qu, np.array([alpha]), beta, need, c2)
    return float(rival_cost(cost, support, count, c2)[0])


def _image_speed(*tracks: VideoRays) -> float:
    """The median speed (px/s) of the tracks' points in their images between consecutive observed samples of each
    video (0 without any)."""
    speeds = []
    for track in tracks:
        dt = np.diff(track.own)
        near = (dt > 0) & (dt <= track.max_gap)
        moved = np.linalg.norm(track.rays[1:] - track.rays[:-1], axis=-1)  # (n-1, P) chord ~ angle (rad)
        px = moved * track.focal[1:, None] / np.where(near, dt, np.inf)[:, None]
        speeds.append(px[np.isfinite(px) & near[:, None]])
    values = np.concatenate(speeds) if speeds else np.zeros(0)
    return float(np.median(values)) if values.size else 0.0


def search_pair(
    tracks: list[VideoRays], v: int, u: int, options: SearchOptions, periods: np.ndarray, sources: list[TimeSource]
) -> PairHypothesis | None:
    """Coarse grid over own_u = alpha + beta own_v; cost = mean truncated squared gap over both directions."""
    tv, tu = tracks[v], tracks[u]
    qv, qu, need = _pair_queries(tracks, v, u, options)
    if not np.isfinite(periods[[v, u]]).any():
        return None  # videos of one timed frame each have no frame period to step a search by
    step = COARSE_STEP_PERIODS * float(np.nanmax(periods[[v, u]]))
    c2 = options.inlier_px**2
    basin = options.inlier_px / max(_image_speed(tv, tu), 1e-9)  # s: a fast ball's offsets are sharp
    betas = np.unique(np.round(np.outer(_rate_scales(sources[v]), 1.0 / _rate_scales(sources[u])).ravel(), 9))

    def hypothesis(beta: float, dense: bool) -> PairHypothesis | None:
        # own_u = alpha + beta own_v overlaps when alpha spans [u start - beta v end, u end - beta v start].
        lo = tu.own[0] - beta * tv.own[-1]
        hi = tu.own[-1] - beta * tv.own[0]
        narrow = min((hi - lo) / MAX_HYPOTHESES, basin) if dense else (hi - lo) / MAX_HYPOTHESES
        coarse = max(step, narrow, (hi - lo) / MAX_DENSE_HYPOTHESES)
        alphas = np.arange(lo, hi + coarse, coarse)
        cost, support = _grid_cost(tracks, v, u, qv, qu, alphas, beta, need, c2)
        if not np.isfinite(cost).any():
            return None
        # the lowest mean among the hypotheses with a fair share of the best support: a few samples of a subject at
        # rest, met at an offset that overlaps the videos' ends alone, have a low mean and say nothing
        floor = MIN_SUPPORT_SHARE * float(support.max())
        i = int(np.argmin(np.where(support >= floor, cost, np.inf)))
        alpha, best_cost, best_support = float(alphas[i]), float(cost[i]), float(support[i])
        count = _count(best_cost, best_support, c2)
        far = np.abs(np.arange(len(alphas)) - i) > DISTINCT_STEPS
        runner = float(np.min(rival_cost(cost[far], support[far], count, c2))) if far.any() else np.inf
        if coarse > step:  # the basin is wider than the coarse step: settle the offset on the fine step
            fine = alpha + np.arange(-coarse, coarse + step, step)
            fine_cost, fine_support = _grid_cost(tracks, v, u, qv, qu, fine, beta, need, c2)
            fine_cost = np.where(fine_support >= floor, fine_cost, np.inf)
            j = int(np.argmin(fine_cost))
            if fine_cost[j] < best_cost:
                alpha, best_cost, best_support = float(fine[j]), float(fine_cost[j]), float(fine_support[j])
                count = _count(best_cost, best_support, c2)
        samples = int(np.sum(np.isfinite(cost)))
        return PairHypothesis(
            v=v,
            u=u,
            alpha=alpha,
            beta=float(beta),
            cost=best_cost,
            runner_up=runner,
            samples=samples,
            support=best_support,
            count=count,
        )

    # Unknown frame rates try many ratios: each on the coarse grid, the dense one (fast points) on the likeliest few.
    many = len(betas) > 1
    found = {float(b): h for b in betas if (h := hypothesis(float(b), dense=not many)) is not None}
    if many:
        for beta in sorted(found, key=lambda b: found[b].cost)[:DENSE_RATIOS]:
            dense = hypothesis(beta, dense=True)
            if dense is not None and dense.cost < found[beta].cost:
                found[beta] = dense
    if not found:
        return None
    floor = MIN_SUPPORT_SHARE * max(h.support for h in found.values())  # across the rate ratios too
    best = min((h for h in found.values() if h.support >= floor), key=lambda h: h.cost)
    others = [
        float(rival_cost(np.array([h.cost]), np.array([h.support]), best.count, c2)[0])
        for h in found.values()
        if h is not best
    ]
    best.runner_up = min([best.runner_up, *others])
    return best


def _count(cost: float, support: float, c2: float) -> float:
    """The samples of a hypothesis from its mean truncated cost and support (support = count x (c2 - cost))."""
    return support / (c2 - cost) if c2 - cost > 0 else math.inf


def rival_cost(cost: np.ndarray, support: np.ndarray, count: float, c2: float) -> np.ndarray:
    """A rival hypothesis's cost on the best's `count` samples: its own mean, or higher where it has fewer samples,
    the missing ones counted as outliers (MSAC): a stretch that overlaps the videos' resting ends alone rivals
    nothing, while a rival with as many samples keeps its mean."""
    with np.errstate(invalid="ignore", divide="ignore"):
        on_count = c2 - support / count if math.isfinite(count) and count > 0 else cost
    return np.maximum(cost, np.nan_to_num(on_count, nan=np.inf))


def _chain(
    pairs: list[PairHypothesis], ref: int, num_videos: int, centers: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Clock coefficients (N, 3) by composing pair relations along a maximum spanning tree of distinctness."""
    usable = {(p.v, p.u): p for p in pairs if p.distinctness >= MIN_DISTINCTNESS and np.isfinite(p.cost)}
    strength = np.zeros((num_videos, num_videos))
    for (v, u), p in usable.items():
        strength[v, u] = strength[u, v] = min(p.distinctness, 1e6)

    def relation(v: int, u: int) -> tuple[float, float]:
        p = usable.get((v, u)) or usable[(u, v)]
        return (p.alpha, p.beta) if (p.v, p.u) == (v, u) else (-p.alpha / p.beta, 1.0 / p.beta)

    return chain_clocks(strength, ref, centers, relation)


class _Joint:
    """Robust least squares over the clocks of the free videos, on the gaps of every ordered pair of videos."""

    def __init__(
        self,
        tracks: list[VideoRays],
        centers: np.ndarray,
        ref_coef: np.ndarray,
        ref: int,
        free: list[int],
        model: ClockModel,
        max_residuals: int,
        block_s: float,
        rate_sigma: np.ndarray,
    ):
        self.raw, self.tracks, self.centers, self.ref, self.free = tracks, list(tracks), centers, ref, free
        self.k = model.free_terms
        # Prior rate 1 +- rate_sigma (per video, inf = none) as extra residuals, in units of the gap scale.
        self.rate_sigma = rate_sigma
        self.prior_videos = [i for i, v in enumerate(free) if np.isfinite(rate_sigma[v])] if self.k >= 2 else []
        self.prior_scale = 1.0
        self.ref_coef = ref_coef
        active = [ref, *free]
        samples = sum(len(tracks[v].own) for v in active) * max(len(active) - 1, 1) * tracks[0].rays.shape[1]
        stride = max(1, math.ceil(samples / max_residuals))
        self.rows = {v: np.arange(0, len(tracks[v].own), stride) for v in active}
        self.pairs = [(v, u) for v in active for u in active if u != v]
        self.mask: dict[tuple[int, int], np.ndarray] = {}
        # Residuals of one video's frames within `block_s` are correlated (interpolation error, smooth motion):
        # they form one cluster of the covariance.
        self.block: dict[int, np.ndarray] = {
            v: np.floor((tracks[v].own[self.rows[v]] - tracks[v].own[0]) / block_s).astype(np.int64) + 100_000 * v
            for v in active
        }

    def coefficients(self, theta: np.ndarray) -> np.ndarray:
        coef = np.full((len(self.tracks), 3), np.nan)
        coef[self.ref] = self.ref_coef
        for i, v in enumerate(self.free):
            coef[v] = [0.0, 1.0, 0.0]
            coef[v, : self.k] = theta[i * self.k : (i + 1) * self.k]
        return coef

    def clock(self, coef: np.ndarray, v: int) -> Clock:
        """Video v's clock of coefficients `coef (N, 3)`."""
        return Clock(center=self.centers[v], coef=coef[v])

    def gaps(self, theta: np.ndarray, smooth: bool = False) -> dict[tuple[int, int], np.ndarray]:
        """(rows, P) gaps of every ordered pair (v, u): v's sample rows against u's track at their times; one
        interpolation and one gap computation per video u for all v (the same numbers, fewer array calls)."""
        coef = self.coefficients(theta)
        out = {}
        for u in {u: None for _, u in self.pairs}:
            sources = [v for v, w in self.pairs if w == u]
            own_u = [
                self.clock(coef, u).own_time(self.clock(coef, v).global_time(self.tracks[v].own[self.rows[v]]))
                for v in sources
            ]
            cu, ru, fu = self.tracks[u].interpolate(np.concatenate(own_u), clamp=smooth)
            mine = [(self.tracks[v], self.rows[v]) for v in sources]
            gaps = gap_px(
                np.concatenate([t.centers[rows] for t, rows in mine]),
                np.concatenate([t.rays[rows] for t, rows in mine]),
                np.concatenate([t.focal[rows] for t, rows in mine]),
                cu,
                ru,
                fu,
                signed_depth=not smooth,
            )
            ends = np.cumsum([len(rows) for _, rows in mine])[:-1]
            out.update({(v, u): part for v, part in zip(sources, np.split(gaps, ends), strict=True)})
        return {pair: out[pair] for pair in self.pairs}

    def clean(self, theta: np.ndarray, threshold: float) -> int:
        """Drop observations whose median gap to the other videos exceeds `threshold` px (false detections): they
        would also spoil every interpolation that brackets them. Returns how many were dropped."""
        coef = self.coefficients(theta)
        active = [self.ref, *self.free]
        dropped = 0
        cleaned = list(self.raw)
        for v in active:
            track = self.raw[v]
            rows = np.arange(len(track.own))
            g = self.clock(coef, v).global_time(track.own)
            gaps = np.stack([_query(self.raw, v, u, self.clock(coef, u).own_time(g), rows) for u in active if u != v])
            if not len(gaps):
                continue
            # observations outside every other video's span (all-NaN columns) are kept; not a filtered warning,
            # since warnings.catch_warnings is not thread-safe (a Dask worker's threads)
            spanned = np.isfinite(gaps).any(axis=0)
            median = np.full(gaps.shape[1:], np.nan)
            median[spanned] = np.nanmedian(gaps[:, spanned], axis=0)
            bad = np.isfinite(median) & (median > threshold)
            dropped += int(bad.sum())
            rays = track.rays.copy()
            rays[bad] = np.nan
            cleaned[v] = VideoRays(
                own=track.own, centers=track.centers, rays=rays, focal=track.focal, max_gap=track.max_gap
            )
        self.tracks = cleaned
        return dropped

    def fix_mask(self, theta: np.ndarray, threshold: float) -> int:
        """Samples of this round: interpolable, positive depths, gap below `threshold` px (outlier detections)."""
        gaps = self.gaps(theta)
        self.mask = {
            key: np.isfinite(value) & (np.nan_to_num(value, nan=np.inf) < threshold) for key, value in gaps.items()
        }
        return int(sum(m.sum() for m in self.mask.values()))

    def residuals(self, theta: np.ndarray) -> np.ndarray:
        gaps = self.gaps(theta, smooth=True)
        parts = [np.nan_to_num(value[self.mask[key]], nan=0.0) for key, value in gaps.items()]
        parts.append(
            np.array(
                [
                    (theta[i * self.k + 1] - 1.0) / self.rate_sigma[self.free[i]] * self.prior_scale
                    for i in self.prior_videos
                ]
            )
        )
        return np.concatenate(parts)

    def clusters(self) -> np.ndarray:
        parts = []
        for (v, _), m in self.mask.items():
            parts.append(np.broadcast_to(self.block[v][:, None], m.shape)[m])
        parts.append(-1 - np.arange(len(self.prior_videos)))  # each prior row on its own
        return np.concatenate(parts)

    def timing_spread(self, theta: np.ndarray, periods: np.ndarray, noise_px: float) -> np.ndarray:
        """(N,) s: spread of the frames' capture times around their clock (jitter), which no clock model holds.

        Per frame, the shift of its time that best closes its (signed, pixel-scaled) gap vectors to the other
        videos, linearized: delta = -sum w0.w' / sum |w'|^2, with w' from interpolating the others half a period
        around. Its robust variance minus the part the pixel noise explains (noise^2 / sum |w'|^2) is the jitter.
        """
        coef = self.coefficients(theta)
        active = [self.ref, *self.free]
        spread = np.full(len(self.tracks), np.nan)
        for v in active:
            track = self.tracks[v]
            rows = np.arange(len(track.own))
            g = self.clock(coef, v).global_time(track.own)
            num = np.zeros(len(rows))
            den = np.zeros(len(rows))
            for u in active:
                if u == v:
                    continue
                h = 0.25 * float(periods[u])
                own_u = self.clock(coef, u).own_time(g)
                vectors = []
                for shift in (0.0, -h, h):
                    cu, ru, fu = self.tracks[u].interpolate(own_u + shift)
                    vectors.append(gap_px(track.centers, track.rays, track.focal, cu, ru, fu, vector=True))
                w0, minus, plus = vectors
                slope = (plus - minus) / (2 * h)
                ok = np.isfinite(w0).all(-1) & np.isfinite(slope).all(-1)
                ok &= np.linalg.norm(np.nan_to_num(w0), axis=-1) < 4 * noise_px
                num += np.where(ok, np.einsum("fpk,fpk->fp", np.nan_to_num(w0), np.nan_to_num(slope)), 0).sum(1)
                den += np.where(ok, np.einsum("fpk,fpk->fp", np.nan_to_num(slope), np.nan_to_num(slope)), 0).sum(1)
            usable = den > 0
            if usable.sum() < 5:
                continue
            delta = -num[usable] / den[usable]
            total = MAD_TO_SIGMA * float(np.median(np.abs(delta - np.median(delta))))
            noise_var = float(np.median(noise_px**2 / den[usable]))
            spread[v] = math.sqrt(max(total * total - noise_var, 0.0))
        return spread

    def video_rms(self, theta: np.ndarray, scale: float) -> np.ndarray:
        gaps = self.gaps(theta)
        rms = np.full(len(self.tracks), np.nan)
        for v in [self.ref, *self.free]:
            values = np.concatenate([gaps[key][np.isfinite(gaps[key])] for key in gaps if v in key])
            inl = values[values < 4 * scale]
            if len(inl):
                rms[v] = float(np.sqrt(np.mean(inl**2)))
        return rms


@dataclass
class _Refined:
    theta: np.ndarray
    cov: np.ndarray
    scale: float  # robust gap scale, px
    cost: float  # truncated mean squared gap over the interpolable samples, px^2
    coverage: int  # samples


def _refine(joint: _Joint, theta: np.ndarray, options: SearchOptions, steps: np.ndarray) -> _Refined:
    """Rounds of: robust scale of the gaps, samples below a shrinking multiple of it, soft-L1 least squares."""
    from scipy.optimize import least_squares  # slow to import: only where the search refines

    scale = math.nan
    for round_ in range(REFINE_ROUNDS):
        values = np.concatenate([g[np.isfinite(g)] for g in joint.gaps(theta).values()])
        if len(values) <= len(theta):
            break
        scale = max(MAD_TO_SIGMA * float(np.median(values)), 0.1)
        threshold = max(REFINE_THRESHOLDS[min(round_, 2)] * scale, 1.0)
        joint.prior_scale = scale
        joint.clean(theta, threshold)
        if joint.fix_mask(theta, threshold) <= len(theta):
            break
        fit = least_squares(
            joint.residuals, theta, loss="soft_l1", f_scale=scale, x_scale=steps, diff_step=None, max_nfev=100
        )
        theta = fit.x
    values = np.concatenate([g[np.isfinite(g)] for g in joint.gaps(theta).values()])
    if len(values):
        scale = max(MAD_TO_SIGMA * float(np.median(values)), 0.1)
    cleaned, joint.tracks = joint.tracks, joint.raw  # starts are compared on the same (raw) observations
    raw = np.concatenate([g[np.isfinite(g)] for g in joint.gaps(theta).values()])
    joint.tracks = cleaned
    cost = float(np.mean(np.minimum(raw**2, options.inlier_px**2))) if len(raw) else math.inf
    cov = np.full((len(theta), len(theta)), np.inf)
    if joint.fix_mask(theta, max(4.0 * scale, 1.0)) > len(theta):
        r = joint.residuals(theta)
        J = _central_jacobian(joint.residuals, theta, 0.1 * steps)
        weights = 1.0 / np.sqrt(1.0 + (r / scale) ** 2)  # soft-L1 IRLS weights
        cov = cluster_covariance(J, r, weights, joint.clusters())
    return _Refined(theta=theta, cov=cov, scale=scale, cost=cost, coverage=len(values))


def _weakly_supported(
    identified: np.ndarray, pairs: list[PairHypothesis], ref: int, names: list[str], misfit: float
) -> list[str]:
    """A warning per clocked video none of whose pairs is distinct and brings its rays together at its best offset,
    where other pairs do (every pair at the misfit level is said once by `_pairs_and_chain`): its clock rests on
    pairs that single nothing out, and one point's trajectory bends to meet its rays on a wrong clock too."""
    if not any(p.cost < misfit for p in pairs):
        return []
    out = []
    for v in np.flatnonzero(identified):
        mine = [p for p in pairs if v in (p.v, p.u)]
        if v == ref or not mine or any(p.distinctness >= MIN_DISTINCTNESS and p.cost < misfit for p in mine):
            continue
        closest = min(mine, key=lambda p: p.cost)
        out.append(
            f"video {names[v]!r}: no pair of videos with it brings the rays together at a distinct offset "
            f"(closest: {names[closest.v]}-{names[closest.u]}, {closest.cost:.0f} px^2, of {misfit:.0f} at which "
            f"rays stay apart, runner-up x{closest.distinctness:.2f}): its clock is weakly supported; check its "
            "points, or give its clock offset (`--offsets` of register or import-calibration)"
        )
    return out


def cluster_covariance(J: np.ndarray, r: np.ndarray, weights: np.ndarray, clusters: np.ndarray) -> np.ndarray:
    """Cluster-robust (sandwich) covariance of a weighted least-squares estimate: H^-1 M H^-1 with H = J^T W J and
    M = sum over clusters of (J_c^T W_c r_c)(J_c^T W_c r_c)^T, times n / (n - p).

    Residuals of neighbouring frames share interpolation errors and neighbours, so the plain sigma^2 H^-1 is too
    optimistic; clusters of CLUSTER_S absorb that correlation.
    """
    n, p = J.shape
    cov = np.full((p, p), np.inf)
    if n <= p:
        return cov
    H = J.T @ (weights[:, None] * J)
    scores = J * (weights * r)[:, None]  # (n, p)
    _, cluster_index = np.unique(clusters, return_inverse=True)
    summed = np.zeros((int(cluster_index.max()) + 1, p))
    np.add.at(summed, cluster_index, scores)
    M = summed.T @ summed
    try:
        H_inv = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return cov
    return (H_inv @ M @ H_inv) * n / (n - p)


def _central_jacobian(function: Callable[[np.ndarray], np.ndarray], theta: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """Central differences with steps of a fraction of a frame period: the gaps are piecewise smooth between
    frames, and the slope across a kink is what the clock estimate feels."""
    columns = []
    for i in range(len(theta)):
        delta = np.zeros_like(theta)
        delta[i] = steps[i]
        columns.append((function(theta + delta) - function(theta - delta)) / (2 * steps[i]))
    return np.stack(columns, axis=1)


def _parameter_steps(period: float, own: np.ndarray, k: int) -> np.ndarray:
    """Typical changes of (a, b, c): a tenth of a frame period at the ends of the video."""
    half = max(float(np.ptp(own)) / 2, period)
    return np.array([0.1 * period, 0.1 * period / half, 0.1 * period / half**2])[:k]


# Every pair's best truncated cost at or over this share of its cap (inlier_px^2) says that the cameras do not fit
# the tracks, early, before a slow solve (docs/clocks.md, "Cameras that do not fit")
MISFIT_SHARE = 0.4
_MISFITS_SAID: set[tuple[str | float, ...]] = set()


def search_clocks(
    problem: Problem,
    own: np.ndarray,
    ref: int,
    model: ClockModel = ClockModel.AFFINE,
    sources: list[TimeSource] | None = None,
    options: SearchOptions | None = None,
    start: ClockSet | None = None,
    movable_reference: bool = False,
) -> SearchResult:
    """Clocks of all videos from the tracks (`sources`: each video's own time source, NOMINAL ones search frame
    rates; default DECODER); `start` (link clocks of W) is tried as a second start. `movable_reference`: where no
    distinct pair links `ref` to the largest group of videos that distinct pairs link, that group's first video is
    the reference instead (`SearchResult.reference`), so that a video with a few samples does not leave every other
    clock unidentified."""
    options = options or SearchOptions()
    N = len(problem.video_names)
    sources = sources or [TimeSource.DECODER] * N
    counts = problem.observed.sum(axis=0)
    counts[counts == 0] = -1
    periods = frame_periods(own, problem.video_index, N)
    centers = video_centers(own, problem.video_index, N)
    pairs, coef, reached = _pairs_and_chain(problem, own, ref, sources, options, counts, periods, centers)
    if movable_reference:
        moved = linked_reference(pairs, ref, N, sources)
        if moved != ref:
            log.info(
                "clock search: no distinct pair links %s to the others: %s is the clock reference",
                problem.video_names[ref],
                problem.video_names[moved],
            )
            ref = moved
            coef, reached = _chain(pairs, ref, N, centers)
    full_tracks = video_tracks(problem, own, np.flatnonzero(counts > 0))
    starts: list[tuple[str, np.ndarray, np.ndarray]] = [("tracks", coef, reached)]
    if start is not None and start.identified.sum() > 1:
        starts.append(("links", start.coef.copy(), start.identified.copy()))
    best = _best_start(starts, full_tracks, centers, ref, model, sources, options, periods)
    misfit = MISFIT_SHARE * options.inlier_px**2
    return _search_result(best, pairs, centers, ref, periods, problem.video_names, misfit)


def linked_reference(pairs: list[PairHypothesis], ref: int, num_videos: int, sources: list[TimeSource]) -> int:
    """`ref`, unless the distinct pairs link a larger group of videos without it: then that group's first video with
    decoder times (else its first)."""
    label = np.arange(num_videos)
    for p in pairs:
        if p.distinctness >= MIN_DISTINCTNESS and np.isfinite(p.cost):
            a, b = label[p.v], label[p.u]
            label[label == max(a, b)] = min(a, b)
    sizes = np.bincount(label, minlength=num_videos)
    largest = int(np.argmax(sizes))  # ties: the group of the lowest-numbered video
    if sizes[label[ref]] >= sizes[largest]:
        return ref
    group = np.flatnonzero(label == largest)
    decoder = [int(v) for v in group if sources[v] is TimeSource.DECODER]
    return decoder[0] if decoder else int(group[0])


def _pairs_and_chain(
    problem: Problem,
    own: np.ndarray,
    ref: int,
    sources: list[TimeSource],
    options: SearchOptions,
    counts: np.ndarray,
    periods: np.ndarray,
    centers: np.ndarray,
) -> tuple[list[PairHypothesis], np.ndarray, np.ndarray]:
    """Steps 1 and 2: the coarse pair searches on the most observed points, chained into start clocks."""
    N = len(problem.video_names)
    names = problem.video_names
    coarse_points = np.argsort(-counts, kind="stable")[: options.max_points]
    coarse_points = coarse_points[counts[coarse_points] > 0]
    tracks = video_tracks(problem, own, coarse_points)
    pairs = [
        p
        for v in range(N)
        for u in range(v + 1, N)
        if (p := search_pair(tracks, v, u, options, periods, sources)) is not None
    ]
    misfit = MISFIT_SHARE * options.inlier_px**2  # a pair's cost at which its rays stay apart
    for p in pairs:
        # a best offset no better than the runner-up, or one whose rays stay apart, identifies nothing: said so
        unsure = p.distinctness < 1.05 or p.cost >= misfit
        log.info(
            "clock search %s -> %s: own_u = %.4f + %.6f own_v, cost %.2f px^2, runner-up x%.2f%s",
            names[p.v],
            names[p.u],
            p.alpha,
            p.beta,
            p.cost,
            p.distinctness,
            " (not identified)" if unsure else "",
        )
    said: tuple[str | float, ...] = (*names, *(round(p.cost, 3) for p in pairs))  # searched again later: said once
    if pairs and all(p.cost >= misfit for p in pairs) and said not in _MISFITS_SAID:
        _MISFITS_SAID.add(said)
        best = min(pairs, key=lambda p: p.cost)
        log.warning(
            "clock search: at its best offset no pair of videos brings its rays together (truncated mean squared "
            "gaps %s px^2, of at most %.0f): the cameras may not fit these tracks (another session's calibration, "
            "cameras given to the wrong videos, a mirrored world) or the tracks follow other points (in some videos "
            "another subject: a detector that picked another person); the solve goes on, the slow way where no "
            "clock is found. The pair that fits best, %s and %s (%.0f px^2), can be solved alone with --videos %s,%s",
            ", ".join(f"{p.cost:.0f}" for p in pairs),
            options.inlier_px**2,
            names[best.v],
            names[best.u],
            best.cost,
            names[best.v],
            names[best.u],
        )
    coef, reached = _chain(pairs, ref, N, centers)
    return pairs, coef, reached


def _best_start(
    starts: list[tuple[str, np.ndarray, np.ndarray]],
    full_tracks: list[VideoRays],
    centers: np.ndarray,
    ref: int,
    model: ClockModel,
    sources: list[TimeSource],
    options: SearchOptions,
    periods: np.ndarray,
) -> tuple[tuple[int, float], str, _Refined, _Joint] | None:
    """Step 3 from every start: the refinement that clocks the most videos, then at the lower truncated cost."""
    N = len(centers)
    # Decoder clocks are quartz: rate 1 within a few hundred ppm. Nominal own times carry an unknown frame rate.
    rate_sigma = np.array(
        [options.rate_prior if s is not TimeSource.NOMINAL and options.rate_prior > 0 else np.inf for s in sources]
    )
    best: tuple[tuple[int, float], str, _Refined, _Joint] | None = None
    for label, c, ok in starts:
        free = [v for v in range(N) if ok[v] and v != ref]
        if not free:
            continue
        joint = _Joint(full_tracks, centers, c[ref], ref, free, model, options.max_residuals, CLUSTER_S, rate_sigma)
        k = joint.k
        theta0 = np.concatenate([c[v, :k] for v in free])
        steps = np.concatenate([_parameter_steps(float(periods[v]), full_tracks[v].own, k) for v in free])
        refined = _refine(joint, theta0, options, steps)
        log.info(
            "clock search: start from %s -> truncated cost %.3f px^2 (gap scale %.2f px, %d videos)",
            label,
            refined.cost,
            refined.scale,
            len(free) + 1,
        )
        # More clocked videos first, then the lower truncated cost.
        key = (-len(free), refined.cost)
        if best is None or key < best[0]:
            best = (key, label, refined, joint)
    return best


def _search_result(
    best: tuple[tuple[int, float], str, _Refined, _Joint] | None,
    pairs: list[PairHypothesis],
    centers: np.ndarray,
    ref: int,
    periods: np.ndarray,
    names: list[str],
    misfit: float = math.inf,
) -> SearchResult:
    """The refined clocks (identified with a finite covariance and a positive rate), residuals and jitter."""
    N = len(centers)
    params = ClockSet.reference_only(centers, ref)
    video_rms = np.full(N, np.nan)
    spread = np.full(N, np.nan)
    residual = math.nan
    label = "tracks"
    if best is not None:
        _, label, refined, joint = best
        coef_all = joint.coefficients(refined.theta)
        k = joint.k
        for i, v in enumerate(joint.free):
            block = refined.cov[i * k : (i + 1) * k, i * k : (i + 1) * k]
            params.coef[v] = coef_all[v]
            params.cov[v] = 0.0
            params.cov[v, :k, :k] = block
            params.identified[v] = bool(np.all(np.isfinite(block)) and coef_all[v, 1] > 0)
        video_rms = joint.video_rms(refined.theta, refined.scale)
        residual = refined.scale
        spread = joint.timing_spread(refined.theta, periods, refined.scale)
    warnings = [
        f"video {names[v]!r}: the track search found no distinct offset to the other videos (too little "
        "overlap, or motion that every offset explains), so the search leaves its clock to the solve's later "
        "stages (report.json's clocks say what was used)"
        for v in range(N)
        if not params.identified[v]
    ]
    warnings += _weakly_supported(params.identified, pairs, ref, names, misfit)
    return SearchResult(
        params=params,
        pairs=pairs,
        residual_px=residual,
        video_residual_px=video_rms,
        timing_spread=spread,
        start=label,
        warnings=warnings,
        reference=ref,
    )
