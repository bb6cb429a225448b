"""Refinement without a clock model: a time for every frame on its own, then trajectories on those times.

Used when no clock model holds (docs/refinement.md, "Without a clock model"): frames without decoder times whose
videos dropped frames, image sequences, the paper's protocol (each capture assigned to a random camera). Times start
from the spectral order of the solver's W (frames W links are near in time), evenly spaced and monotone within each
video; then trajectories are refined on them and every frame's time is moved, within the bracket of its video's
neighbouring frames, to where the trajectories meet its rays best. Rounds alternate the two.

Free times fit any rays (noise-free, the trajectories pass through every ray at any time), so a second hypothesis is
built beside them: the spectral order polished so that consecutive frames' shapes are nearest (`polish_order`, on the
seed's points, then on the trajectories), frames evenly spaced in that order, the trajectories refined on those fixed
times. These have no time to tune per frame, so their residual tells a wrong order (time_checks decides between the
two); the same retime rounds then start from them.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components, laplacian

from reconstruct.solver.problem import Problem
from reconstruct.solver.rays import viewing_rays
from reconstruct.trajectory import RefineOptions, RefineResult, refine

log = logging.getLogger(__name__)

ROUNDS = 3  # refine-then-retime rounds after the spectral start
CANDIDATES = 24  # trial times per frame inside its bracket
NOMINAL_PERIOD = 1.0 / 30.0  # s per frame of one video: the time unit when nothing about time is known
HUBER_PX = 3.0  # the retiming cost is robust to a false detection beyond this
DENSE_ORDER = 3000  # frames up to which the Fiedler vector comes from a dense eigensolver
ORDER_BAND = 12  # places in the global order a frame may move by in one polish move
ORDER_SWEEPS = 50  # polish sweeps at most (each stops early when no move shortens the path)


@dataclass(kw_only=True)
class FreeTimes:
    times: np.ndarray  # (F,) s, monotone within each video
    result: RefineResult  # the trajectories refined on `times`
    residual_px: list[float] = field(default_factory=list)  # median reprojection residual after each refinement
    rank_times: np.ndarray | None = None  # (F,) s: evenly spaced in the polished global order
    on_ranks: RefineResult | None = None  # the trajectories refined on `rank_times` (their residual judges the order)
    ordered_times: np.ndarray | None = None  # (F,) s: `rank_times` after ROUNDS retime rounds
    ordered: RefineResult | None = None  # the trajectories refined on `ordered_times`
    order_path: list[float] = field(default_factory=list)  # shape path length: spectral, polished, repolished
    spectral_px: float = float("nan")  # median reprojection residual of the trajectories on the spectral times


def spectral_times(W: sp.spmatrix, video_index: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """(F,) times from the Fiedler order of |W| + |W|^T (plus a chain through each video's consecutive frames),
    evenly spaced so that each video's frames are NOMINAL_PERIOD apart on average, sorted within each video."""
    F = len(video_index)
    num_videos = int(video_index.max()) + 1
    order = _fiedler_order(W, video_index, frames)
    rank = np.empty(F)
    rank[order] = np.arange(F)
    times = rank * NOMINAL_PERIOD / num_videos
    return _monotone(times, video_index, frames)


def _fiedler_order(W: sp.spmatrix, video_index: np.ndarray, frames: np.ndarray) -> np.ndarray:
    F = len(video_index)
    A = abs(sp.csr_matrix(W))
    A = (A + A.T) * 0.5
    A.setdiag(0)
    chain = _video_chain(video_index, frames)
    # The chain only orders frames W leaves apart; it weighs less than a typical W link.
    scale = float(np.median(A.data)) if A.nnz else 1.0
    graph = (A + 0.5 * scale * (chain + chain.T)).tocsr()
    _, component = connected_components(graph, directed=False)
    main = np.flatnonzero(component == np.bincount(component).argmax())
    if len(main) < 3:
        return np.lexsort((frames, video_index))
    sub = graph[main][:, main]
    if len(main) <= DENSE_ORDER:
        _, vectors = np.linalg.eigh(laplacian(sub.toarray()))
        fiedler = vectors[:, 1]
    else:
        from scipy.sparse.linalg import eigsh

        _, vectors = eigsh(laplacian(sub.tocsc()).astype(float), k=2, sigma=-1e-6, which="LM")
        fiedler = vectors[:, 1]
    trend = 0.0
    for v in np.unique(video_index[main]):
        members = np.flatnonzero(video_index[main] == v)
        if len(members) > 1 and np.std(fiedler[members]) > 0:
            trend += float(np.corrcoef(frames[main[members]], fiedler[members])[0, 1])
    if trend < 0:
        fiedler = -fiedler
    rest = np.setdiff1d(np.arange(F), main)
    return np.concatenate([main[np.argsort(fiedler, kind="stable")], rest])


def _video_chain(video_index: np.ndarray, frames: np.ndarray) -> sp.csr_matrix:
    F = len(video_index)
    order = np.lexsort((frames, video_index))
    same = video_index[order[1:]] == video_index[order[:-1]]
    rows, cols = order[:-1][same], order[1:][same]
    return sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(F, F))


def _monotone(times: np.ndarray, video_index: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """Each video's times sorted and given to its frames in frame order (a video's frames are in time order)."""
    out = times.copy()
    for v in np.unique(video_index):
        members = np.flatnonzero(video_index == v)
        out[members[np.argsort(frames[members], kind="stable")]] = np.sort(times[members])
    return out


def refine_free_times(
    problem: Problem,
    points: np.ndarray,
    W: sp.spmatrix,
    options: RefineOptions | None = None,
    rays: np.ndarray | None = None,
) -> FreeTimes:
    """Trajectories and per-frame times without any clock model, started from the seed `points (F, P, 3)`;
    `rays (F, P, 3)`: `viewing_rays(problem)` when the caller has them."""
    options = options or RefineOptions()
    times = spectral_times(W, problem.video_index, problem.frames)
    rays = viewing_rays(problem) if rays is None else rays
    centers = problem.centers  # (F, 3)
    history: list[float] = []
    result = refine(problem, points, times, options)
    history.append(_median_residual(result))
    start = times
    first = reprojection_px(problem, result.points, rays)
    spectral_px = float(np.median(first[np.isfinite(first)])) if np.isfinite(first).any() else float("nan")
    for _ in range(ROUNDS):
        times = retime(problem, rays, centers, result.points, times)
        result = refine(problem, points, times, options)
        history.append(_median_residual(result))
    free = FreeTimes(times=times, result=result, residual_px=history, spectral_px=spectral_px)
    _add_ordered(free, problem, points, start, options, rays)
    return free


def _add_ordered(
    free: FreeTimes,
    problem: Problem,
    points: np.ndarray,
    spectral: np.ndarray,
    options: RefineOptions,
    rays: np.ndarray,
) -> None:
    """The polished-order hypothesis: the spectral order polished on the seed's `points (F, P, 3)`, trajectories
    on it, the order polished again on the trajectories (nearer the truth than the seed) and the trajectories
    refined once more when it moved; then ROUNDS retime rounds from those times (noise moves a frame's best time
    off its rank)."""
    video = problem.video_index
    num_videos = int(video.max()) + 1
    order = np.argsort(spectral, kind="stable")
    path = [order_path_length(order, points)]
    order = polish_order(order, points, video)
    path.append(order_path_length(order, points))
    times = rank_times(order, num_videos)
    result = refine(problem, points, times, options)
    again = polish_order(order, result.points, video)
    path.append(order_path_length(again, points))
    if not np.array_equal(again, order):
        times = rank_times(again, num_videos)
        result = refine(problem, points, times, options)
    free.rank_times, free.on_ranks, free.order_path = times, result, path
    for _ in range(ROUNDS):
        times = retime(problem, rays, problem.centers, result.points, times)
        result = refine(problem, points, times, options)
    free.ordered_times, free.ordered = times, result


def rank_times(order: np.ndarray, num_videos: int) -> np.ndarray:
    """(F,) times of frames evenly spaced in the global `order (F,)` (frame indices, earliest first), each video's
    frames NOMINAL_PERIOD apart on average."""
    times = np.empty(len(order))
    times[order] = np.arange(len(order)) * NOMINAL_PERIOD / num_videos
    return times


class _ShapeDistance:
    """Median over points of the distance between two frames' points (a few wrong points do not count)."""

    def __init__(self, points: np.ndarray) -> None:
        self.points = points  # (F, P, 3)
        self.cache: dict[tuple[int, int], float] = {}

    def __call__(self, a: int, b: int) -> float:
        key = (a, b) if a < b else (b, a)
        value = self.cache.get(key)
        if value is None:
            step = np.linalg.norm(self.points[a] - self.points[b], axis=-1)
            step = step[np.isfinite(step)]
            value = float(np.median(step)) if len(step) else 0.0
            self.cache[key] = value
        return value


def order_path_length(order: np.ndarray, points: np.ndarray) -> float:
    """Sum of the shape distances between consecutive frames of `order (F,)`, `points (F, P, 3)`."""
    distance = _ShapeDistance(points)
    return float(sum(distance(int(a), int(b)) for a, b in itertools.pairwise(order)))


def polish_order(order: np.ndarray, points: np.ndarray, video_index: np.ndarray) -> np.ndarray:
    """The global `order (F,)` with frames moved, one at a time and only between their own video's neighbours
    (at most ORDER_BAND places), wherever the move shortens the path through the frames' shapes `points (F, P, 3)`:
    the frames of a motion sampled densely lie on a short path in the order they were captured."""
    distance = _ShapeDistance(points)
    current = [int(f) for f in order]
    F = len(current)
    for _ in range(ORDER_SWEEPS):
        moved = False
        for i in range(F):
            target = _best_insertion(current, i, distance, video_index)
            if target is not None:
                frame = current.pop(i)
                current.insert(target, frame)
                moved = True
        if not moved:
            break
    return np.array(current, dtype=np.int64)


def _best_insertion(order: list[int], i: int, distance: _ShapeDistance, video_index: np.ndarray) -> int | None:
    """Where, in `order` without its i-th frame, that frame shortens the path most; None where nowhere does."""
    F = len(order)
    frame = order[i]
    video = video_index[frame]
    low = i - 1
    while low >= 0 and video_index[order[low]] != video and i - low <= ORDER_BAND:
        low -= 1
    high = i + 1
    while high < F and video_index[order[high]] != video and high - i <= ORDER_BAND:
        high += 1
    saved = 0.0
    if i > 0:
        saved += distance(order[i - 1], frame)
    if i < F - 1:
        saved += distance(frame, order[i + 1])
    if 0 < i < F - 1:
        saved -= distance(order[i - 1], order[i + 1])
    rest = order[:i] + order[i + 1 :]
    best, target = 1e-12, None
    # inserting before rest[j]: positions between the video's neighbours, which sit at low and high - 1 in rest
    for j in range(low + 1, high):
        if j == i:
            continue
        before = rest[j - 1] if j > 0 else None
        after = rest[j] if j < F - 1 else None
        added = 0.0
        if before is not None:
            added += distance(before, frame)
        if after is not None:
            added += distance(frame, after)
        if before is not None and after is not None:
            added -= distance(before, after)
        if saved - added > best:
            best, target = saved - added, j
    return target


def _median_residual(result: RefineResult) -> float:
    finite = result.residual_px[np.isfinite(result.residual_px)]
    return float(np.median(finite)) if len(finite) else float("nan")


def retime(
    problem: Problem, rays: np.ndarray, centers: np.ndarray, trajectory: np.ndarray, times: np.ndarray
) -> np.ndarray:
    """Every frame's time moved, inside the bracket of its video's previous and next frames, to where the
    trajectories (`trajectory (F, P, 3)` at `times (F,)`, linear between frames) meet the frame's rays best.
    Frames at even then odd positions of their video move in turn, so that the order within a video holds."""
    times = times.copy()
    order = np.lexsort((problem.frames, problem.video_index))
    position = np.empty(len(order), dtype=np.int64)
    video = problem.video_index[order]
    starts = np.r_[0, np.flatnonzero(video[1:] != video[:-1]) + 1]
    for s, e in zip(starts, np.r_[starts[1:], len(order)], strict=True):
        position[order[s:e]] = np.arange(e - s)
    curves = _Curves(trajectory, times)
    for parity in (0, 1):
        low, high = _brackets(times, order, video)
        moving = np.flatnonzero((position % 2) == parity)
        times[moving] = _best_times(problem, rays, centers, curves, moving, low[moving], high[moving], times[moving])
    return times


def _brackets(times: np.ndarray, order: np.ndarray, video: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F,) open interval each frame may move in: halfway... the neighbours' times, one typical gap at the ends."""
    sorted_times = times[order]
    previous = np.r_[np.nan, sorted_times[:-1]]
    following = np.r_[sorted_times[1:], np.nan]
    first = np.r_[True, video[1:] != video[:-1]]
    last = np.r_[video[1:] != video[:-1], True]
    gaps = np.diff(sorted_times)
    typical = float(np.median(gaps[gaps > 0])) if np.any(gaps > 0) else NOMINAL_PERIOD
    previous[first] = sorted_times[first] - typical
    following[last] = sorted_times[last] + typical
    low, high = np.empty_like(times), np.empty_like(times)
    low[order], high[order] = previous, following
    return low, high


class _Curves:
    """Every point's trajectory as a piecewise-linear function of time through the refined points."""

    def __init__(self, trajectory: np.ndarray, times: np.ndarray) -> None:
        sort = np.argsort(times, kind="stable")
        self.t = times[sort]
        self.x = trajectory[sort]  # (F, P, 3)

    def at(self, query: np.ndarray, p: int) -> np.ndarray:
        """(..., 3) point p at times `query (...)`."""
        x = self.x[:, p]
        good = np.isfinite(x[:, 0])
        if good.sum() < 2:
            return np.full((*query.shape, 3), np.nan)
        return np.stack([np.interp(query, self.t[good], x[good, k]) for k in range(3)], axis=-1)


def _best_times(
    problem: Problem,
    rays: np.ndarray,
    centers: np.ndarray,
    curves: _Curves,
    frames: np.ndarray,
    low: np.ndarray,
    high: np.ndarray,
    current: np.ndarray,
) -> np.ndarray:
    fractions = (np.arange(CANDIDATES) + 0.5) / CANDIDATES
    trial = np.column_stack([current, low[:, None] + (high - low)[:, None] * fractions])  # (n, C+1)
    cost = np.zeros(trial.shape)
    focal = problem.K[frames, 0, 0]
    for p in range(problem.num_points):
        seen = np.isfinite(rays[frames, p, 0])
        if not seen.any():
            continue
        X = curves.at(trial[seen], p)  # (m, C+1, 3)
        offset = X - centers[frames[seen], None, :]
        along = np.einsum("mck,mk->mc", offset, rays[frames[seen], p])
        distance = np.linalg.norm(offset - along[..., None] * rays[frames[seen], p][:, None, :], axis=-1)
        residual = distance * focal[seen, None] / np.maximum(along, 1e-9)
        residual = np.where(np.isfinite(residual), residual, 1e6)
        cost[seen] += np.where(residual <= HUBER_PX, 0.5 * residual**2, HUBER_PX * (residual - 0.5 * HUBER_PX))
    best = np.argmin(cost, axis=1)
    return trial[np.arange(len(frames)), best]


def reprojection_px(problem: Problem, points: np.ndarray, rays: np.ndarray | None = None) -> np.ndarray:
    """(F, P) distance of every point from its frame's ray in pixels at its depth (ray distance x focal / depth);
    NaN where unobserved."""
    rays = viewing_rays(problem) if rays is None else rays
    centers = problem.centers
    offset = points - centers[:, None, :]
    along = np.einsum("fpk,fpk->fp", offset, rays)
    distance = np.linalg.norm(offset - along[..., None] * rays, axis=-1)
    return distance * problem.K[:, 0, 0][:, None] / np.maximum(along, 1e-9)


def gap_spread(times: np.ndarray, video_index: np.ndarray, frames: np.ndarray) -> float:
    """Median over videos of the coefficient of variation of the time gaps between a video's consecutive frames
    (per frame number step): 0 for evenly spaced frames."""
    spreads = []
    for v in np.unique(video_index):
        members = np.flatnonzero(video_index == v)
        members = members[np.argsort(frames[members])]
        if len(members) < 3:
            continue
        gaps = np.diff(times[members]) / np.maximum(np.diff(frames[members]), 1)
        if np.mean(gaps) > 0:
            spreads.append(float(np.std(gaps) / np.mean(gaps)))
    return float(np.median(spreads)) if spreads else float("nan")
