"""Video clocks from the solve: every video's own time mapped to one global time (the model: `clocks.model`).

The reference video (the first one with decoder times) fixes the gauge: offset 0, rate 1, drift 0. Two sources of
evidence:

* Links of W (this module). Column f of W says S_f ~ sum_j W_jf S_j with every j in another video; locally the
  motion is smooth, so frame f's global time is close to the same combination of its neighbours' times:
  g(f) - sum_j W_jf g(j) ~ 0. That is linear in the clock parameters. A robust start (per pair of videos, a RANSAC
  line through the (own time, neighbours' own time) links, chained along a maximum spanning tree from the reference)
  then IRLS with a Cauchy loss on the link residuals; the covariance comes from the final weighted normal equations.
* The 2D tracks and poses (`reconstruct.clocks.search`): the offsets and rates that make the interpolated tracks of
  different videos triangulate. Needed where W is ambiguous (one point seen from far away: almost any two rays of
  different videos pass close to each other, so the solver's shapes, and W, do not know the time).

`estimate_clocks` fits the links, runs the track search (by default always: it is cheap, and the tracks are the
direct measurement where W's links are W's interpretation of them) and keeps the estimate the evidence supports (see
its docstring). Each frame's time std holds the clock's covariance, the capture-time jitter around the clock (from
the tracks, else the links) and a floor of STD_FLOOR_PERIODS of a frame period. The result goes into
sequencing.json under the key `clocks` (`Clocks.to_json`, docs/formats.md).
"""

from __future__ import annotations

import copy
import enum
import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp

from dynrecon.errors import InputError
from reconstruct.clocks.chain import chain_clocks
from reconstruct.clocks.model import (
    DEFAULT_FPS,
    Clock,
    ClockModel,
    Clocks,
    ClockSet,
    TimeSource,
    VideoClockReport,
    clock_basis,
    frame_periods,
    own_times,
    video_centers,
)
from reconstruct.clocks.search import SearchOptions, SearchResult, search_clocks
from reconstruct.solver.alternation import SolveResult
from reconstruct.solver.problem import Problem

log = logging.getLogger(__name__)

CAUCHY_C = 2.385  # Cauchy loss constant: 95 % efficiency under Gaussian noise
MAD_TO_SIGMA = 1.4826
MIN_WEIGHT = 1e-6  # W entries below this are numerical dust, not links (dropping real ones biases)
MIN_LINKS = 10  # inlier links a video needs (to the already-clocked videos) to be identified by W
RANSAC_ITERATIONS = 300
RANSAC_SEED = 0
RANSAC_THRESHOLD_PERIODS = 1.0  # link inlier threshold in frame periods of the linked video
IRLS_ITERATIONS = 30
# SearchMode.AUTO runs the track search when the problem has at most this many reconstructable points ...
SEARCH_MAX_POINTS = 3
# ... or when fewer than this share of the links are inliers, or a video is not identified by W.
MIN_INLIER_SHARE = 0.6
# Links and tracks agree when their middle times differ by less than this many combined standard deviations (or
# less than AGREE_PERIODS frame periods): then both are fused.
AGREE_SIGMAS = 4.0
AGREE_PERIODS = 0.5
# Links whose robust scale is at most this share of the fastest frame period are precise enough to refine the
# tracks' clocks; noisier ones only clock the videos the tracks cannot.
PRECISE_LINK_PERIODS = 0.25
# Each frame's time std is at least this share of its video's frame period: interpolating a curved track linearly
# between frames (and expressing a shape by neighbours) leaves a sub-frame bias the covariance does not see.
STD_FLOOR_PERIODS = 0.05


class SearchMode(enum.Enum):
    AUTO = "auto"  # run the track search when the links are weak or the problem has few points
    ALWAYS = "always"
    NEVER = "never"


@dataclass(kw_only=True)
class ClockOptions:
    model: ClockModel = ClockModel.AFFINE
    # ALWAYS by default: the search is cheap next to the solve, and on simulated phones W's links alone were
    # several times farther off than the tracks (docs/clocks.md).
    search: SearchMode = SearchMode.ALWAYS
    fps: dict[str, float] = field(default_factory=dict)  # videos whose own time is frame / fps: a rate given
    reference: str | None = None  # gauge video; default: the first video with decoder times
    track_search: SearchOptions = field(default_factory=SearchOptions)


# ---------------------------------------------------------------------------------------------------------------
# Links of W


@dataclass(kw_only=True)
class Links:
    """Sparse link equations: frame[i] is combined from the (neighbour, weight) entries whose row is i."""

    frame: np.ndarray  # (L,) frames with at least one link
    neighbour: np.ndarray  # (E,) frame index of each entry
    weight: np.ndarray  # (E,) normalized per frame to sum to 1
    row: np.ndarray  # (E,) link index of each entry


def w_links(W: sp.spmatrix, video_index: np.ndarray, min_weight: float) -> Links:
    """One link per frame whose column of W has weight >= min_weight on other videos (weights renormalized)."""
    csc = sp.csc_matrix(W)
    csc.eliminate_zeros()
    cols = np.repeat(np.arange(csc.shape[1]), np.diff(csc.indptr))
    rows, vals = csc.indices.astype(np.int64), csc.data
    keep = (vals >= min_weight) & (video_index[rows] != video_index[cols])
    rows, cols, vals = rows[keep], cols[keep], vals[keep]
    totals = np.bincount(cols, weights=vals, minlength=csc.shape[1])
    frames = np.flatnonzero(totals > 0)
    link_of = np.full(csc.shape[1], -1)
    link_of[frames] = np.arange(len(frames))
    return Links(frame=frames, neighbour=rows, weight=vals / totals[cols], row=link_of[cols])


def _pair_relations(
    links: Links, own: np.ndarray, video_index: np.ndarray, periods: np.ndarray, num_videos: int, model: ClockModel
) -> dict[tuple[int, int], tuple[float, float, int]]:
    """Robust affine relation own_u ~ alpha + beta own_v for each pair (v, u) linked by W: (alpha, beta, inliers).

    For each link of a frame f of v, the neighbours in video u give one sample (own_f, weighted mean own time of
    u-neighbours). RANSAC on two-sample lines (or the median difference when the rate is fixed), then least squares
    on the inliers.
    """
    rng = np.random.default_rng(RANSAC_SEED)
    u_entry = video_index[links.neighbour]
    key = (links.row * num_videos + u_entry).astype(np.int64)
    unique, inverse = np.unique(key, return_inverse=True)
    weight_sum = np.bincount(inverse, weights=links.weight)
    mean_own = np.bincount(inverse, weights=links.weight * own[links.neighbour]) / weight_sum
    sample_frame = links.frame[unique // num_videos]
    sample_u = (unique % num_videos).astype(np.int64)
    sample_v = video_index[sample_frame]
    relations: dict[tuple[int, int], tuple[float, float, int]] = {}
    fixed_rate = model is ClockModel.OFFSET
    for v in range(num_videos):
        for u in range(num_videos):
            sel = (sample_v == v) & (sample_u == u)
            n = int(sel.sum())
            if u == v or n < 2:
                continue
            x, y = own[sample_frame[sel]], mean_own[sel]
            threshold = RANSAC_THRESHOLD_PERIODS * float(np.nanmax([periods[u], periods[v]]))
            if fixed_rate:
                alpha, beta = float(np.median(y - x)), 1.0
            else:
                i = rng.integers(0, n, size=(RANSAC_ITERATIONS, 2))
                dx = x[i[:, 1]] - x[i[:, 0]]
                ok = np.abs(dx) > 1e-9
                if not ok.any():
                    continue
                betas = (y[i[ok, 1]] - y[i[ok, 0]]) / dx[ok]
                alphas = y[i[ok, 0]] - betas * x[i[ok, 0]]
                plausible = (betas > 0.2) & (betas < 5.0)  # frame rates differ by at most 5x
                if not plausible.any():
                    continue
                alphas, betas = alphas[plausible], betas[plausible]
                counts = (np.abs(y[None] - alphas[:, None] - betas[:, None] * x[None]) < threshold).sum(axis=1)
                best = int(np.argmax(counts))
                alpha, beta = float(alphas[best]), float(betas[best])
            for _ in range(3):
                inl = np.abs(y - alpha - beta * x) < threshold
                if inl.sum() < 2:
                    break
                if fixed_rate:
                    alpha = float(np.mean(y[inl] - x[inl]))
                elif np.ptp(x[inl]) > 0:
                    beta, alpha = (float(c) for c in np.polyfit(x[inl], y[inl], 1))
            inliers = int((np.abs(y - alpha - beta * x) < threshold).sum())
            relations[(v, u)] = (alpha, beta, inliers)
    return relations


def _chain_start(
    relations: dict[tuple[int, int], tuple[float, float, int]], ref: int, num_videos: int, centers: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Start coefficients by composing pair relations along a maximum spanning tree (most inliers) from `ref`."""
    strength = np.zeros((num_videos, num_videos))
    for (v, u), (_, _, n) in relations.items():
        strength[v, u] += n
        strength[u, v] += n
    strength[strength < MIN_LINKS] = 0

    def relation(v: int, u: int) -> tuple[float, float]:
        # own_u = alpha + beta own_v (from v's links) or own_v = alpha' + beta' own_u (from u's links)
        if (v, u) in relations and (u, v) in relations:
            pick = (v, u) if relations[(v, u)][2] >= relations[(u, v)][2] else (u, v)
        else:
            pick = (v, u) if (v, u) in relations else (u, v)
        alpha, beta, _ = relations[pick]
        return (alpha, beta) if pick == (v, u) else (-alpha / beta, 1.0 / beta)

    return chain_clocks(strength, ref, centers, relation)


@dataclass(kw_only=True)
class LinkFit:
    params: ClockSet
    scale: float  # robust scale of the link residuals, s
    inlier_share: float  # share of links with Cauchy weight > 0.5
    links_per_video: np.ndarray  # (N,) inlier links touching each video
    residuals: np.ndarray  # (L,) s
    frame_scatter: np.ndarray  # (N,) s, per-frame timing spread of each video's inlier links (jitter + W noise)
    warnings: list[str]


@dataclass(kw_only=True)
class _LinkSystem:
    """The link equations A theta ~ y over the free clock terms of the videos the chained start reached."""

    A: sp.csr_matrix  # (L, k * len(free_videos))
    y: np.ndarray  # (L,) the fixed terms' part, moved to the right
    theta: np.ndarray  # (k * len(free_videos),) start: the chained clocks
    use_link: np.ndarray  # (L,) every frame of the link belongs to a reached video
    free_videos: list[int]
    fixed_coef: np.ndarray  # (N, 3) the terms the model does not free (and the reference's clock)
    k: int  # free terms per video


@dataclass(kw_only=True)
class _LinkSolution:
    theta: np.ndarray
    residual: np.ndarray  # (L,) s
    inlier: np.ndarray  # (L,) Cauchy weight > 0.5
    scale: float  # s
    cov: np.ndarray  # (n_free, n_free)


def fit_links(
    W: sp.spmatrix,
    own: np.ndarray,
    video_index: np.ndarray,
    num_videos: int,
    ref: int,
    model: ClockModel,
    names: list[str] | None = None,
) -> LinkFit:
    """Robust affine (or offset / drift) clocks from the links of W; see the module docstring."""
    names = names or [f"video {v}" for v in range(num_videos)]
    periods = frame_periods(own, video_index, num_videos)
    centers = video_centers(own, video_index, num_videos)
    links = w_links(W, video_index, MIN_WEIGHT)
    if len(links.frame) == 0:
        return LinkFit(
            params=ClockSet.reference_only(centers, ref),
            scale=math.nan,
            inlier_share=0.0,
            links_per_video=np.zeros(num_videos, dtype=np.int64),
            residuals=np.zeros(0),
            frame_scatter=np.full(num_videos, np.nan),
            warnings=["W has no links between videos: no clock can be estimated from it"],
        )
    relations = _pair_relations(links, own, video_index, periods, num_videos, model)
    coef, reached = _chain_start(relations, ref, num_videos, centers)
    system = _link_system(links, own, video_index, centers, coef, reached, ref, model)
    solution = _solve_links(system, periods)
    touching = _inliers_per_video(links, video_index, num_videos, solution.inlier)
    params, warnings = _link_clocks(system, solution, touching, centers, coef, ref, names)
    for v in range(num_videos):
        if not reached[v]:
            warnings.append(
                f"video {names[v]!r}: W does not link it to the reference video {names[ref]!r} "
                f"with {MIN_LINKS}+ consistent links: its clock is not identified by the sequencing"
            )
    used = system.use_link.sum()
    share = float(solution.inlier.sum() / used) if used else 0.0
    return LinkFit(
        params=params,
        scale=solution.scale,
        inlier_share=share,
        links_per_video=touching,
        residuals=solution.residual,
        frame_scatter=_link_scatter(links, video_index, num_videos, solution),
        warnings=warnings,
    )


def _link_system(
    links: Links,
    own: np.ndarray,
    video_index: np.ndarray,
    centers: np.ndarray,
    coef: np.ndarray,
    reached: np.ndarray,
    ref: int,
    model: ClockModel,
) -> _LinkSystem:
    """Design: for frame f (row L) coefficient +phi(s_f) on video(f)'s block, -w phi(s_j) on video(j)'s blocks."""
    num_videos = len(centers)
    k = model.free_terms
    free_videos = [v for v in range(num_videos) if reached[v] and v != ref]
    # Links among reached videos only; entries of unreached videos would be unknowns without a start.
    use_entry = reached[video_index[links.neighbour]]
    use_link = np.bincount(links.row, weights=(~use_entry).astype(float), minlength=len(links.frame)) == 0
    use_link &= reached[video_index[links.frame]]
    column_of = np.full((num_videos, 3), -1)
    for i, v in enumerate(free_videos):
        column_of[v, :k] = np.arange(i * k, (i + 1) * k)
    basis = clock_basis(own - centers[video_index])  # (F, 3)
    n_links = len(links.frame)
    rows_l = np.concatenate([np.arange(n_links), links.row])
    frames_l = np.concatenate([links.frame, links.neighbour])
    signs = np.concatenate([np.ones(n_links), -links.weight])
    entry_rows = np.repeat(rows_l, 3)
    entry_terms = np.tile(np.arange(3), len(rows_l))
    entry_frames = np.repeat(frames_l, 3)
    entry_values = np.repeat(signs, 3) * basis[entry_frames, entry_terms]
    entry_cols = column_of[video_index[entry_frames], entry_terms]
    is_free = entry_cols >= 0
    n_free = k * len(free_videos)
    A = sp.csr_matrix((entry_values[is_free], (entry_rows[is_free], entry_cols[is_free])), shape=(n_links, n_free))
    # Fixed parts: the reference video's coefficients and the fixed rate/drift terms of free videos.
    fixed_coef = np.zeros((num_videos, 3))
    fixed_coef[ref] = coef[ref]
    for v in free_videos:
        fixed_coef[v] = [0.0, 1.0, 0.0]  # only the terms the model does not free are read: rate 1, no drift
    fixed_values = entry_values * fixed_coef[video_index[entry_frames], entry_terms]
    fixed_values[is_free] = 0.0
    y = -np.bincount(entry_rows, weights=fixed_values, minlength=n_links)
    theta = np.concatenate([coef[v, :k] for v in free_videos]) if free_videos else np.zeros(0)
    return _LinkSystem(A=A, y=y, theta=theta, use_link=use_link, free_videos=free_videos, fixed_coef=fixed_coef, k=k)


def _solve_links(system: _LinkSystem, periods: np.ndarray) -> _LinkSolution:
    """IRLS with a Cauchy loss from the chained start; the covariance from the final weighted normal equations."""
    A, y, theta, use_link = system.A, system.y, system.theta, system.use_link
    n_free = A.shape[1]
    residual = A @ theta - y
    floor = 1e-3 * float(np.nanmin(periods)) if np.isfinite(periods).any() else 1e-6
    weights = np.where(use_link, 1.0, 0.0)
    scale = floor
    cov_free = np.zeros((n_free, n_free))
    for _ in range(max(1, IRLS_ITERATIONS)):
        r_used = residual[use_link]
        scale = max(MAD_TO_SIGMA * float(np.median(np.abs(r_used))) if len(r_used) else floor, floor)
        weights = np.where(use_link, 1.0 / (1.0 + (residual / (CAUCHY_C * scale)) ** 2), 0.0)
        if n_free == 0:
            break
        Aw = A.multiply(weights[:, None]).tocsr()
        normal = (A.T @ Aw).toarray()
        rhs = Aw.T @ y
        try:
            new_theta = np.linalg.solve(normal + 1e-12 * np.eye(n_free) * np.trace(normal) / n_free, rhs)
        except np.linalg.LinAlgError:
            break
        change = float(np.max(np.abs(new_theta - theta)))
        theta = new_theta
        residual = A @ theta - y
        if change < 1e-4 * floor:
            break
    inlier = weights > 0.5
    if n_free:
        Aw = A.multiply(weights[:, None]).tocsr()
        normal = (A.T @ Aw).toarray()
        dof = max(int(inlier.sum()) - n_free, 1)
        sigma2 = float(np.sum(weights * residual**2)) / dof
        try:
            cov_free = sigma2 * np.linalg.inv(normal)
        except np.linalg.LinAlgError:
            cov_free = np.full((n_free, n_free), np.inf)
    return _LinkSolution(theta=theta, residual=residual, inlier=inlier, scale=scale, cov=cov_free)


def _inliers_per_video(links: Links, video_index: np.ndarray, num_videos: int, inlier: np.ndarray) -> np.ndarray:
    """(N,) inlier links touching each video (as the expressed frame or as a neighbour)."""
    n_links = len(links.frame)
    touching = np.zeros(num_videos, dtype=np.int64)
    for v in range(num_videos):
        involved = video_index[links.frame] == v
        involved |= (
            np.bincount(links.row, weights=(video_index[links.neighbour] == v).astype(float), minlength=n_links) > 0
        )
        touching[v] = int(np.sum(involved & inlier))
    return touching


def _link_clocks(
    system: _LinkSystem,
    solution: _LinkSolution,
    touching: np.ndarray,
    centers: np.ndarray,
    coef: np.ndarray,
    ref: int,
    names: list[str],
) -> tuple[ClockSet, list[str]]:
    """The fitted clocks; a video is identified with MIN_LINKS inlier links, a finite covariance and a positive
    rate."""
    k = system.k
    warnings: list[str] = []
    params = ClockSet(
        center=centers,
        coef=np.full((len(centers), 3), np.nan),
        cov=np.full((len(centers), 3, 3), np.nan),
        identified=np.zeros(len(centers), dtype=bool),
    )
    params.coef[ref] = coef[ref]
    params.cov[ref] = 0.0
    params.identified[ref] = True
    for i, v in enumerate(system.free_videos):
        c = system.fixed_coef[v].copy()
        c[:k] = solution.theta[i * k : (i + 1) * k]
        block = solution.cov[i * k : (i + 1) * k, i * k : (i + 1) * k]
        cv = np.zeros((3, 3))
        cv[:k, :k] = block
        ok = touching[v] >= MIN_LINKS and np.all(np.isfinite(block)) and c[1] > 0
        params.coef[v] = c
        params.cov[v] = cv
        params.identified[v] = bool(ok)
        if not ok:
            warnings.append(
                f"video {names[v]!r}: only {touching[v]} consistent W link(s) to other videos "
                f"(needs {MIN_LINKS}): its clock is not identified by the sequencing"
            )
    return params, warnings


def _link_scatter(links: Links, video_index: np.ndarray, num_videos: int, solution: _LinkSolution) -> np.ndarray:
    """(N,) s: each video's per-frame timing spread from its inlier link residuals."""
    # residual = jitter_f - sum_j w_j jitter_j: variance (1 + sum w^2) times one frame's.
    sum_w2 = np.bincount(links.row, weights=links.weight**2, minlength=len(links.frame))
    scatter = np.full(num_videos, np.nan)
    for v in range(num_videos):
        sel = solution.inlier & (video_index[links.frame] == v)
        if sel.sum() >= 3:
            scatter[v] = (
                MAD_TO_SIGMA
                * float(np.median(np.abs(solution.residual[sel])))
                / math.sqrt(1.0 + float(np.mean(sum_w2[sel])))
            )
    return scatter


# ---------------------------------------------------------------------------------------------------------------
# Entry point


def choose_reference(problem: Problem, sources: list[TimeSource], requested: str | None) -> int:
    if requested is not None:
        if requested not in problem.video_names:
            raise InputError(
                None,
                f"clock reference video {requested!r} is not one of the solved videos",
                fix=f"choose one of: {', '.join(problem.video_names)}",
            )
        return problem.video_names.index(requested)
    # a video without one observation links to nothing: every clock would be "not linked to the reference"
    seen = [bool(problem.observed[problem.video_index == v].any()) for v in range(len(problem.video_names))]
    for v, source in enumerate(sources):
        if source is TimeSource.DECODER and seen[v]:
            return v
    return seen.index(True) if any(seen) else 0


def estimate_clocks(problem: Problem, result: SolveResult, options: ClockOptions | None = None) -> Clocks:
    """Every video's clock from W's links and the tracks (see the module docstring).

    The link fit always runs. The track search runs with SearchMode.ALWAYS (the default), or with AUTO when the
    links are weak (a video unidentified, fewer than MIN_INLIER_SHARE inliers) or the problem has at most
    SEARCH_MAX_POINTS points. Where both clock a video: links whose robust scale is within PRECISE_LINK_PERIODS of
    the fastest frame period are fused with the tracks (inverse covariance) when they agree (middle times within
    AGREE_SIGMAS combined stds or AGREE_PERIODS frame periods), else the tracks win with a warning (the
    triangulation residual is a direct measurement, W is the solver's interpretation of it); noisier links only
    clock the videos the tracks cannot. A video neither source clocks is `identified = False` with NaN times and a
    warning.
    """
    options = options or ClockOptions()
    own, sources = own_times(problem, options.fps)
    N = len(problem.video_names)
    ref = choose_reference(problem, sources, options.reference)
    model = _usable_model(options.model, sources, problem.video_names)
    link_fit = fit_links(result.W.to_csc(), own, problem.video_index, N, ref, model, problem.video_names)
    periods = frame_periods(own, problem.video_index, N)
    run_search = _run_search(options.search, link_fit, int(np.sum(result.reconstructable)))
    warnings = list(link_fit.warnings)
    diagnostics: dict[str, Any] = {
        "link_scale_s": link_fit.scale,
        "link_inlier_share": link_fit.inlier_share,
        "links": len(link_fit.residuals),
        "search": run_search,
    }
    params = link_fit.params
    swapped: tuple[ClockSet, list[str], np.ndarray] | None = None  # the links' clock where the tracks' was kept
    methods = ["links" if params.identified[v] else "unidentified" for v in range(N)]
    methods[ref] = "reference"
    track_rms = np.full(N, np.nan)
    scatter = link_fit.frame_scatter.copy()
    if run_search:
        search = search_clocks(problem, own, ref, model, sources, options.track_search, start=link_fit.params)
        warnings.extend(search.warnings)
        diagnostics["track_residual_px"] = search.residual_px
        distinct = [p.distinctness for p in search.pairs if np.isfinite(p.distinctness)]
        diagnostics["track_distinctness"] = float(np.median(distinct)) if distinct else None
        track_rms = search.video_residual_px
        shortest = float(np.nanmin(periods)) if np.isfinite(periods).any() else np.nan  # NaN: one frame per video
        precise = bool(link_fit.scale <= PRECISE_LINK_PERIODS * shortest)
        params, methods, fuse_notes, disagree = _combine(
            link_fit.params, search.params, periods, ref, problem.video_names, precise
        )
        diagnostics["links_precise"] = precise
        warnings.extend(fuse_notes)
        _take_track_scatter(scatter, search, methods)
        if disagree:  # the tracks' clock was kept against W's links: the refinement measures both
            swapped = (copy.deepcopy(params), list(methods), scatter.copy())
            for v in disagree:
                swapped[0].coef[v], swapped[0].cov[v] = link_fit.params.coef[v], link_fit.params.cov[v]
                swapped[1][v], swapped[2][v] = "links", link_fit.frame_scatter[v]
    for w in warnings:
        log.warning("clocks: %s", w)

    def clocks_of(chosen: ClockSet, chosen_methods: list[str], chosen_scatter: np.ndarray) -> Clocks:
        # both hypotheses carry the same notes: they describe the evidence, not the choice
        return _report(
            problem,
            own,
            sources,
            ref,
            model,
            chosen,
            chosen_methods,
            periods,
            chosen_scatter,
            link_fit,
            track_rms,
            list(warnings),
            dict(diagnostics),
        )

    clocks = clocks_of(params, methods, scatter)
    clocks.links_alternative = clocks_of(*swapped) if swapped is not None else None
    return clocks


def estimate_clocks_from_tracks(problem: Problem, options: ClockOptions | None = None) -> Clocks:
    """Every video's clock from the tracks and poses alone (no self-expressive solve, no W): the track search
    started from its own chained pair searches. The path for few points (reconstruct/tracks_path.py), where W's
    links would only repeat what the tracks say."""
    options = options or ClockOptions()
    own, sources = own_times(problem, options.fps)
    N = len(problem.video_names)
    ref = choose_reference(problem, sources, options.reference)
    model = _usable_model(options.model, sources, problem.video_names)
    periods = frame_periods(own, problem.video_index, N)
    centers = video_centers(own, problem.video_index, N)
    search = search_clocks(
        problem, own, ref, model, sources, options.track_search, movable_reference=options.reference is None
    )
    ref = search.reference
    no_links = LinkFit(
        params=ClockSet.reference_only(centers, ref),
        scale=math.nan,
        inlier_share=0.0,
        links_per_video=np.zeros(N, dtype=np.int64),
        residuals=np.zeros(0),
        frame_scatter=np.full(N, np.nan),
        warnings=[],
    )
    distinct = [p.distinctness for p in search.pairs if np.isfinite(p.distinctness)]
    diagnostics: dict[str, Any] = {
        "link_scale_s": math.nan,
        "link_inlier_share": 0.0,
        "links": 0,
        "search": True,
        "track_residual_px": search.residual_px,
        "track_distinctness": float(np.median(distinct)) if distinct else None,
        "links_precise": False,
    }
    params, methods, _, _ = _combine(no_links.params, search.params, periods, ref, problem.video_names)
    scatter = np.full(N, np.nan)
    _take_track_scatter(scatter, search, methods)
    for w in search.warnings:
        log.warning("clocks: %s", w)
    return _report(
        problem,
        own,
        sources,
        ref,
        model,
        params,
        methods,
        periods,
        scatter,
        no_links,
        search.video_residual_px,
        list(search.warnings),
        diagnostics,
    )


def _usable_model(model: ClockModel, sources: list[TimeSource], names: list[str]) -> ClockModel:
    """The requested model, or AFFINE where an offset-only clock cannot hold (a video with neither decoder times
    nor a given frame rate)."""
    for name, source in zip(names, sources, strict=True):
        if source is TimeSource.NOMINAL:
            log.warning(
                "video %r has neither decoder times nor a known frame rate: own time = frame / %g s, its "
                "rate absorbs the true frame rate",
                name,
                DEFAULT_FPS,
            )
    if model is ClockModel.OFFSET and TimeSource.NOMINAL in sources:
        log.warning("clock model 'offset' needs decoder times or a frame rate for every video; using 'affine'")
        return ClockModel.AFFINE
    return model


def _run_search(mode: SearchMode, link_fit: LinkFit, points: int) -> bool:
    """ALWAYS, or AUTO with weak links (a video unidentified, few inliers) or few reconstructable points."""
    weak = (not link_fit.params.identified.all()) or link_fit.inlier_share < MIN_INLIER_SHARE
    return mode is SearchMode.ALWAYS or (mode is SearchMode.AUTO and (weak or points <= SEARCH_MAX_POINTS))


def _take_track_scatter(scatter: np.ndarray, search: SearchResult, methods: list[str]) -> None:
    """Per-frame timing spread (in place): the tracks' pooled jitter estimate wherever they clock the video."""
    # Per-video jitter estimates of the tracks are noisy (a few hundred frames, noise removed by subtraction):
    # pool them over the videos.
    spreads = search.timing_spread[np.isfinite(search.timing_spread)]
    pooled = float(np.median(spreads)) if len(spreads) else math.nan
    for v in range(len(scatter)):
        # The links' spread holds W's own noise too: the tracks' estimate is the direct one wherever they clock
        # the video.
        if methods[v] != "links" and math.isfinite(pooled):
            scatter[v] = pooled


def _report(
    problem: Problem,
    own: np.ndarray,
    sources: list[TimeSource],
    ref: int,
    model: ClockModel,
    params: ClockSet,
    methods: list[str],
    periods: np.ndarray,
    scatter: np.ndarray,
    link_fit: LinkFit,
    track_rms: np.ndarray,
    warnings: list[str],
    diagnostics: dict[str, Any],
) -> Clocks:
    """Per-frame times and stds, and every video's clock at own time 0 (NaN for unidentified videos)."""
    global_time = params.global_time(own, problem.video_index)
    # Per frame: the clock's own uncertainty, the frames' timing spread around it (jitter) and a floor for the
    # sub-frame bias of interpolating tracks / combining neighbours linearly.
    floor = STD_FLOOR_PERIODS * periods
    frame_sd = np.fmax(np.nan_to_num(scatter, nan=0.0), floor)
    global_std = np.hypot(params.global_std(own, problem.video_index), frame_sd[problem.video_index])
    videos: list[VideoClockReport] = []
    for v, name in enumerate(problem.video_names):
        values, stds = params.offset_rate_drift(v)
        identified = bool(params.identified[v])
        if not identified:
            global_time[problem.video_index == v] = np.nan
            global_std[problem.video_index == v] = np.nan
            values = stds = np.full(3, math.nan)
        videos.append(
            VideoClockReport(
                name=name,
                time_source=sources[v],
                method=methods[v] if identified else "unidentified",
                identified=identified,
                offset=float(values[0]),
                rate=float(values[1]),
                drift=float(values[2]),
                offset_std=float(stds[0]),
                rate_std=float(stds[1]),
                drift_std=float(stds[2]),
                links=int(link_fit.links_per_video[v]),
                track_residual_px=float(track_rms[v]),
                frame_scatter=float(frame_sd[v]),
            )
        )
    return Clocks(
        model=model,
        reference=problem.video_names[ref],
        videos=videos,
        frame_videos=problem.frame_videos,
        frames=problem.frames.copy(),
        own_time=own,
        global_time=global_time,
        global_std=global_std,
        warnings=warnings,
        diagnostics=diagnostics,
    )


def _combine(
    links: ClockSet, tracks: ClockSet, periods: np.ndarray, ref: int, names: list[str], links_precise: bool = True
) -> tuple[ClockSet, list[str], list[str], list[int]]:
    """Per video: the tracks' clock, the links' clock, or both fused (see estimate_clocks); methods, notes and the
    videos whose tracks' clock was kept against the links'."""
    N = len(links.center)
    out = ClockSet.reference_only(links.center.copy(), ref)
    methods = ["unidentified"] * N
    methods[ref] = "reference"
    notes: list[str] = []
    disagree: list[int] = []
    for v in range(N):
        has_l, has_t = bool(links.identified[v]), bool(tracks.identified[v])
        if v == ref or not (has_l or has_t):
            continue
        if has_t and not has_l:
            out.coef[v], out.cov[v] = tracks.coef[v], tracks.cov[v]
            methods[v] = "tracks"
        elif has_l and not has_t:
            out.coef[v], out.cov[v] = links.coef[v], links.cov[v]
            methods[v] = "links"
        else:
            methods[v], note = _choose(links.clock(v), tracks.clock(v), out, v, periods[v], names[v], links_precise)
            if note:
                notes.append(note)
                disagree.append(v)
        out.identified[v] = True
    return out, methods, notes, disagree


def _choose(
    link: Clock, track: Clock, out: ClockSet, v: int, period: float, name: str, links_precise: bool
) -> tuple[str, str | None]:
    """Video v clocked by both: fused when the links are precise and agree, else the tracks' clock (with a note)."""
    # Both centred at the same own time: a is the clock at the video's middle.
    gap = abs(link.coef[0] - track.coef[0])
    sigma = math.sqrt(max(link.cov[0, 0] + track.cov[0, 0], 0.0))
    if not links_precise:
        out.coef[v], out.cov[v] = track.coef, track.cov
        if gap > AGREE_PERIODS * period:
            return "tracks", (
                f"video {name!r}: W links put its middle {gap / period:.1f} frame periods from the "
                "tracks' clock: kept the tracks' clock"
            )
        return "tracks", None
    if gap <= max(AGREE_SIGMAS * sigma, AGREE_PERIODS * period):
        out.coef[v], out.cov[v] = _fuse(link.coef, link.cov, track.coef, track.cov)
        return "combined", None
    out.coef[v], out.cov[v] = track.coef, track.cov
    return "tracks", (
        f"video {name!r}: W links put its middle at {link.coef[0]:.4f} s, the tracks at "
        f"{track.coef[0]:.4f} s ({gap / period:.1f} frame periods apart): kept the tracks' clock"
    )


def _fuse(c1: np.ndarray, v1: np.ndarray, c2: np.ndarray, v2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse-covariance fusion over the free terms (zero-variance terms are fixed and equal)."""
    free = (np.diag(v1) > 0) & (np.diag(v2) > 0)
    out_c, out_v = c2.copy(), v2.copy()
    if not free.any():
        return out_c, out_v
    idx = np.flatnonzero(free)
    try:
        i1 = np.linalg.inv(v1[np.ix_(idx, idx)])
        i2 = np.linalg.inv(v2[np.ix_(idx, idx)])
        cov = np.linalg.inv(i1 + i2)
    except np.linalg.LinAlgError:
        return out_c, out_v
    out_c[idx] = cov @ (i1 @ c1[idx] + i2 @ c2[idx])
    out_v[np.ix_(idx, idx)] = cov
    return out_c, out_v
