"""Candidate dictionaries for long captures: each frame may only be expressed by a window of frames of each other
video, so that every step costs O(F) instead of O(F^2).

Frames of one video are in temporal order, and every video's clock runs forward. So if frame f of video a shows the
same instant as position q of video b, frame f+1 shows an instant near q (+ the frame-rate ratio). An *anchor*
(F, V) holds, for each frame and each video, the position in that video of the frame's best match; the frame's
candidates are the positions anchor +- half_window of every other video.

* Initialization (coarse to fine): every `stride`-th frame of each video is compared with every `stride`-th frame of
  all others by the paper's ray-bundle distance; the best coarse match per video, carried to the frames in between by
  their coarse neighbours, becomes the anchor; a fine search over the anchor windows then picks each frame's partner
  and its depths exactly as the dense initialization does inside those windows.
* During the solve the anchors follow W: a frame's anchor in video b moves to the position of its largest W entry in
  b once that has drifted more than `recentre` positions away; frames with no entry in b keep their anchor.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from reconstruct.solver.initialize import (
    MIN_COMMON_POINTS,
    PARALLEL_EPS,
    PairInit,
    _Lines,
    _pair_depths,
    _Side,
    closest_ray_points,
    lazy_best,
    partner_depths,
    video_pair_best,
)
from reconstruct.solver.wstep import first_per_group

# Coarse stage: a video pair's coarse frames are compared in one symmetric block up to this many pairs (two float
# arrays of that size), as `initialize_depths` does.
COARSE_BLOCK = 2_000_000
# Fine stage: a run of frames is evaluated in (P, R, S) buffers of at most this many elements (2 MB each: faster
# than both smaller runs, whose per-call overhead dominates, and larger ones, which fall out of cache).
RUN_ELEMENTS = 2**18
# Explicit pairs (divergence checks, pairs the runs missed) evaluated at once: (n, P, 3) gathers.
EXPLICIT_PAIRS = 4096


@dataclass(kw_only=True)
class CandidateOptions:
    """Candidate windows of long captures (`SolverOptions.candidates`, used above `SolverOptions.dense_limit`)."""

    stride: int = 16  # coarse initialization: compare every stride-th frame of each video
    half_window: int = 12  # candidates: this many positions either side of the anchor in each other video
    recentre: int = 6  # an anchor follows W only when its match has moved more than this many positions
    pair_block: int = 40_000  # frame pairs evaluated at once by the ray-bundle distance (memory ~ 100 B x P each)


@dataclass(kw_only=True)
class VideoLayout:
    """Where each video's frames sit in the flat frame axis (frames of a video contiguous, in temporal order)."""

    starts: np.ndarray  # (V,) first flat index of each video
    lengths: np.ndarray  # (V,)
    position: np.ndarray  # (F,) position of each frame within its video

    @classmethod
    def of(cls, video_index: np.ndarray) -> VideoLayout:
        V = int(video_index.max()) + 1
        lengths = np.bincount(video_index, minlength=V)
        starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
        return cls(starts=starts, lengths=lengths, position=np.arange(len(video_index)) - starts[video_index])


def pair_distances(
    centers: np.ndarray, rays: np.ndarray, f: np.ndarray, j: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The initialization's bundle distance D(f, j) for explicit pairs (n,), and the depths (n, P) of f's points at
    the mutually closest ray points; same conventions as `initialize.bundle_distances` (inf for diverging pairs
    or too few shared points). An explicit evaluation, kept as the reference for the windowed search below."""
    ra = rays[f]  # (n, P, 3)
    depth_a, depth_b, gap = closest_ray_points(centers[f][:, None, :], ra, centers[j][:, None, :], rays[j])
    usable = np.isfinite(depth_a)  # NaN where a frame misses the point or the rays are parallel
    gap_sq = np.where(usable, gap, 0.0)
    count = usable.sum(axis=1)
    diverging = np.any(usable & ((depth_a < 0) | (depth_b < 0)), axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        D = gap_sq.sum(axis=1) / count
    observed_in_f = np.sum(~np.isnan(ra[..., 0]), axis=1)
    enough = count >= np.minimum(MIN_COMMON_POINTS, np.maximum(observed_in_f, 1))
    D[~enough | (count == 0) | diverging] = np.inf
    return D, depth_a


def _window_distances(
    lines: _Lines,
    frames_a: np.ndarray,
    first: np.ndarray,
    side_b: _Side,
    window: int,
    pair_block: int,
    back: tuple[np.ndarray, int] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """D (R, window) of each frame of `frames_a` (R,) against the `window` consecutive frames of video b from
    position `first` (R,) on (`side_b`: all of b's frames as column factors), inf where too few points are shared;
    divergence not checked. Frames are taken in the order of their windows, so that a run of them needs one range
    of b; D of the run against the whole range is one stacked matrix product over the points (`_run_gap_sums`),
    from which each frame's window is picked. A run spans at most one window length of starts, so at most half of
    what is evaluated is unused, and holds at most pair_block pairs.

    With `back` = (first_b (L_b,), window_b): also, since D is symmetric, the same for b's frames against their
    windows in the frames_a video (positions first_b ... + window_b), as far as the runs cover them (their windows
    lie around the same clock line), NaN where not. Returns (D (R, window), D_back (L_b, window_b) or (0, 0))."""
    D = np.empty((len(frames_a), window))
    need_a, need_b = lines.need[frames_a], lines.need[side_b.frames]
    if back is not None:
        first_b, window_b = back
        D_back = np.full((len(first_b), window_b), np.nan)
        slot = np.full(len(frames_a), -1, dtype=np.int64)  # a's position -> its row in the current run
        offsets_b = np.arange(window_b)
    else:
        D_back = np.empty((0, 0))
    order = np.argsort(first, kind="stable")
    sorted_first = first[order]
    max_rows = max(1, min(pair_block, RUN_ELEMENTS // lines.left.shape[0]) // (2 * window))
    offsets = np.arange(window)
    start = 0
    while start < len(order):
        stop = min(start + max_rows, int(np.searchsorted(sorted_first, sorted_first[start] + window, "right")))
        at = order[start:stop]
        c0, c1 = int(sorted_first[start]), int(sorted_first[stop - 1]) + window
        total, count = _run_gap_sums(lines, frames_a[at], side_b, c0, c1)
        with np.errstate(invalid="ignore", divide="ignore"):
            block = np.divide(total, count, out=total)  # NaN where nothing is shared: below every need
        pick = (first[at] - c0)[:, None] + offsets[None, :]
        D[at] = np.where(
            np.take_along_axis(count, pick, axis=1) >= need_a[at][:, None],
            np.take_along_axis(block, pick, axis=1),
            np.inf,
        )
        if back is not None:
            slot[at] = np.arange(len(at))
            row = slot[first_b[c0:c1, None] + offsets_b[None, :]]  # (S, window_b): the run's row, -1 outside
            g, k = np.nonzero(row >= 0)
            r = row[g, k]
            D_back[c0 + g, k] = np.where(count[r, g] >= need_b[c0 + g], block[r, g], np.inf)
            slot[at] = -1
        start = stop
    return D, D_back


def _fill_uncovered(
    lines: _Lines,
    D: np.ndarray,
    frames: np.ndarray,
    first_col: np.ndarray,
    members_b: np.ndarray,
    first: np.ndarray,
    pair_block: int,
) -> None:
    """Fill the NaN entries of D (R, K) of `frames` (R,) against frames first_col + k: a few pair by pair, or, when
    they are many (the two videos' anchors disagree), the rows that hold them by runs (`_window_distances`
    against video b, whose frames are `members_b`, from positions `first` on)."""
    missing = np.isnan(D)
    if not missing.any():
        return
    if missing.mean() <= 0.25:
        r, k = np.nonzero(missing)
        for start in range(0, len(r), EXPLICIT_PAIRS):
            rr, kk = r[start : start + EXPLICIT_PAIRS], k[start : start + EXPLICIT_PAIRS]
            D[rr, kk] = _explicit_distances(lines, frames[rr], first_col[rr] + kk)
        return
    rows = missing.any(axis=1)
    D[rows], _ = _window_distances(
        lines, frames[rows], first[rows], _Side.cols(lines, members_b), D.shape[1], pair_block
    )


def _explicit_distances(lines: _Lines, f: np.ndarray, j: np.ndarray) -> np.ndarray:
    """D of explicit pairs (n,) by the same Pluecker products as `_run_gap_sums`, inf where too few points are
    shared; divergence not checked."""
    left_f, left_j = lines.left[:, f], lines.left[:, j]  # (P, n, 6) [m, r]
    sine_sq = np.einsum("pnk,pnk->pn", left_f[..., 3:], left_j[..., 3:])  # cosine
    triple = np.einsum("pnk,pnk->pn", left_f[..., :3], left_j[..., 3:])
    triple += np.einsum("pnk,pnk->pn", left_f[..., 3:], left_j[..., :3])
    sine_sq = 1.0 - sine_sq * sine_sq
    flat = sine_sq < PARALLEL_EPS
    count = np.sum(lines.seen[f] & lines.seen[j], axis=1) - flat.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        D = np.sum(np.where(flat, 0.0, triple * triple / np.where(flat, 1.0, sine_sq)), axis=0) / count
    return np.where(count >= lines.need[f], D, np.inf)


def _run_gap_sums(lines: _Lines, rows: np.ndarray, side_b: _Side, c0: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
    """`initialize._gap_sums` for the frames `rows` (R,) against side_b's frames c0 ... c1 - 1 (S): the sum over
    shared, non-parallel points of the squared ray gap, and their number (R, S). All points in one stacked product:
    a run's (P, R, S) buffers are small, and the per-call overhead of a loop over points would dominate them."""
    left = lines.left[:, rows]  # (P, R, 6) [m, r]
    sine_sq = np.matmul(left[..., 3:], side_b.direction[:, :, c0:c1])  # cosine (P, R, S)
    triple = np.matmul(left, side_b.pluecker[:, :, c0:c1])  # (C_a - C_b) . (r_a x r_b)
    np.multiply(sine_sq, sine_sq, out=sine_sq)
    np.subtract(1.0, sine_sq, out=sine_sq)
    count = np.rint(lines.seen_float[rows] @ lines.seen_float[side_b.frames[c0:c1]].T).astype(np.int64)
    if sine_sq.min() < PARALLEL_EPS:  # rare: nearly parallel rays have no meaningful gap and are not counted
        flat = sine_sq < PARALLEL_EPS
        count -= flat.sum(axis=0)
        sine_sq[flat] = 1.0
        triple[flat] = 0.0
    np.multiply(triple, triple, out=triple)
    np.divide(triple, sine_sq, out=triple)
    return triple.sum(axis=0), count


def _window_best(
    lines: _Lines, D: np.ndarray, rows: np.ndarray, first_col: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per row of D (R, K; modified: diverging pairs become inf) the first offset k of least D among the
    non-diverging pairs (rows[r], first_col[r] + k), and that D; -1 and inf where none (`initialize.lazy_best`:
    divergence checked for each row's best candidate in turn, then for all finite candidates of the rest)."""

    def diverging_rows(pending: np.ndarray, sub: np.ndarray) -> np.ndarray:
        r, k = np.nonzero(np.isfinite(sub))
        out = np.zeros(sub.shape, dtype=bool)
        out[r, k] = _diverging(lines, rows[pending[r]], first_col[pending[r]] + k)
        return out

    best, cost, _ = lazy_best(
        D, lambda pending, pick: _diverging(lines, rows[pending], first_col[pending] + pick), diverging_rows
    )
    return best, cost


def _diverging(lines: _Lines, f: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Whether each explicit pair (f[i], j[i]) has a negative depth (n,)."""
    out = np.zeros(len(f), dtype=bool)
    for start in range(0, len(f), EXPLICIT_PAIRS):
        stop = start + EXPLICIT_PAIRS
        _, out[start:stop] = _pair_depths(lines, f[start:stop], j[start:stop])
    return out


def _fill_anchor_gaps(anchor: np.ndarray, video_index: np.ndarray, layout: VideoLayout) -> np.ndarray:
    """Frames without an anchor in some video take it by linear interpolation over their own video's positions."""
    filled = anchor.astype(float)
    V = anchor.shape[1]
    for a in range(V):
        members = slice(layout.starts[a], layout.starts[a] + layout.lengths[a])
        positions = np.arange(layout.lengths[a])
        for b in range(V):
            if a == b:
                continue
            column = filled[members, b]
            known = column >= 0
            if known.all() or not known.any():
                if not known.any():
                    column[:] = (layout.lengths[b] - 1) * positions / max(layout.lengths[a] - 1, 1)
                continue
            column[~known] = np.interp(positions[~known], positions[known], column[known])
    return np.rint(filled).astype(np.int64)


def anchor_tolerance(options: CandidateOptions, times: np.ndarray | None) -> int:
    """How far an anchor may stray from its video pair's line: with decoder times the line is exact up to jitter;
    without them, positions wander around it (irregular capture)."""
    return options.recentre if _all_timed(times) else options.half_window


def _all_timed(times: np.ndarray | None) -> bool:
    return times is not None and bool(np.all(np.isfinite(times)))


def consistent_anchors(
    anchor: np.ndarray,
    video_index: np.ndarray,
    layout: VideoLayout,
    *,
    tolerance: int,
    times: np.ndarray | None = None,
    trials: int = 200,
) -> np.ndarray:
    """Every video's clock runs forward at a steady rate, so the anchors of a's frames in video b lie on a line:
    time in b against time in a when every frame has a decoder time (`times` (F,)), else position in b against
    position in a (only roughly a line: irregular capture makes positions a random walk around it). Anchors further
    than `tolerance` positions from the line that RANSAC fits through them matched a repeated pose elsewhere in the
    capture and are moved onto it. On repetitive motion such wrong anchors come in runs of frames that a running
    median would follow, hence the line."""
    rng = np.random.default_rng(0)
    fixed = anchor.copy()
    V = anchor.shape[1]
    timed = _all_timed(times)
    # Each frame's coordinate on its video's axis: decoder time, or position.
    axis = np.asarray(times, dtype=float) if timed else layout.position.astype(float)
    for a in range(V):
        members = np.arange(layout.starts[a], layout.starts[a] + layout.lengths[a])
        if len(members) < 3:
            continue
        x = axis[members]
        for b in range(V):
            if a == b or layout.lengths[b] < 2:
                continue
            b_axis = axis[layout.starts[b] : layout.starts[b] + layout.lengths[b]]
            # tolerance in b's axis units: positions, or that many of b's median frame periods
            scale = float(np.median(np.diff(b_axis))) if timed else 1.0
            y = b_axis[fixed[members, b]]
            line = _ransac_line(x, y, tolerance * scale, trials, rng)
            if line is None:
                continue
            predicted = line[0] + line[1] * x
            # Where the line leaves b (no overlap, or a wrong line in periodic motion) clipping would pile anchors
            # onto b's first or last frame: those keep their own match.
            inside = (predicted >= b_axis[0]) & (predicted <= b_axis[-1])
            stray = (np.abs(y - predicted) > tolerance * scale) & inside
            nearest = np.clip(np.searchsorted(b_axis, predicted[stray]), 1, len(b_axis) - 1)
            closer_left = predicted[stray] - b_axis[nearest - 1] < b_axis[nearest] - predicted[stray]
            fixed[members[stray], b] = nearest - closer_left
    return fixed


def _ransac_line(
    x: np.ndarray, y: np.ndarray, tolerance: float, trials: int, rng: np.random.Generator
) -> tuple[float, float] | None:
    """(intercept, slope > 0) of the line through most points within `tolerance`, refitted on them."""
    picks = rng.integers(0, len(x), size=(trials, 2))
    picks = picks[x[picks[:, 0]] != x[picks[:, 1]]]
    slope = (y[picks[:, 1]] - y[picks[:, 0]]) / (x[picks[:, 1]] - x[picks[:, 0]])
    forward = slope > 0  # clocks run forward
    if not forward.any():
        return None
    slope, intercept = slope[forward], (y[picks[:, 0]] - slope * x[picks[:, 0]])[forward]
    inliers = np.abs(y[None, :] - (intercept[:, None] + slope[:, None] * x[None, :])) <= tolerance
    chosen = inliers[int(np.argmax(inliers.sum(axis=1)))]
    if chosen.sum() < 2 or np.ptp(x[chosen]) == 0:
        return None
    fitted_slope, fitted_intercept = np.polyfit(x[chosen], y[chosen], 1)
    return float(fitted_intercept), float(fitted_slope)


def window_pool(anchor: np.ndarray, video_index: np.ndarray, layout: VideoLayout, half_window: int) -> np.ndarray:
    """(F, C) flat frame indices of each frame's candidates: anchor +- half_window in every other video (clipped to
    the video; duplicates from clipping are replaced by -1)."""
    F, V = anchor.shape
    offsets = np.arange(-half_window, half_window + 1)
    blocks = []
    for b in range(V):
        centre = np.clip(anchor[:, b], half_window, max(layout.lengths[b] - 1 - half_window, half_window))
        position = np.clip(centre[:, None] + offsets[None, :], 0, layout.lengths[b] - 1)
        flat = layout.starts[b] + position
        flat[video_index == b] = -1
        blocks.append(flat)
    pool = np.concatenate(blocks, axis=1)
    ordered = np.sort(pool, axis=1)
    repeated = np.concatenate([np.zeros((F, 1), dtype=bool), ordered[:, 1:] == ordered[:, :-1]], axis=1)
    ordered[repeated] = -1
    return ordered


def coarse_to_fine_init(
    centers: np.ndarray,
    rays: np.ndarray,
    video_index: np.ndarray,
    options: CandidateOptions,
    times: np.ndarray | None = None,
) -> tuple[PairInit, np.ndarray]:
    """The pairwise initialization restricted to anchor windows. Returns (init, anchor (F, V)). `times` (F,):
    decoder times, which make the anchors' consistency check exact (`consistent_anchors`).

    Both stages use the dense initialization's Pluecker products (`initialize`): the coarse stage is the
    dense search on each video pair's coarse frames; the fine stage evaluates runs of frames against the range of
    the other video that their windows cover. Divergence is checked lazily, for each best candidate in turn. Time
    O((F / stride)^2 P + F V window P), memory O(F P + F window)."""
    F = len(rays)
    layout = VideoLayout.of(video_index)
    V = len(layout.starts)
    lines = _Lines.of(centers, rays)
    members = [np.arange(layout.starts[v], layout.starts[v] + layout.lengths[v]) for v in range(V)]
    anchor = np.full((F, V), -1, dtype=np.int64)
    coarse = [m[:: options.stride] for m in members]
    for a in range(V):
        for b in range(a + 1, V):
            if not len(coarse[a]) or not len(coarse[b]):
                continue
            (best_a, _), (best_b, _) = video_pair_best(lines, coarse[a], coarse[b], memory_elements=COARSE_BLOCK)
            anchor[coarse[a], b] = np.where(best_a >= 0, best_a * options.stride, -1)
            anchor[coarse[b], a] = np.where(best_b >= 0, best_b * options.stride, -1)
    anchor = _fill_anchor_gaps(anchor, video_index, layout)
    anchor = consistent_anchors(anchor, video_index, layout, tolerance=options.stride, times=times)
    # Fine stage: each frame against anchor +- (stride + half_window) of every other video, the windows of
    # `window_pool` (shifted inside the video, the whole video when it is shorter).
    half = options.stride + options.half_window
    position = np.full((F, V), -1, dtype=np.int64)
    best_d = np.full((F, V), np.inf)
    window = np.minimum(2 * half + 1, layout.lengths)
    for b in range(V):
        if not window[b]:
            continue
        side_b = _Side.cols(lines, members[b])
        for a in range(b):
            if not window[a]:
                continue
            first_ab = np.clip(anchor[members[a], b] - half, 0, layout.lengths[b] - window[b])
            first_ba = np.clip(anchor[members[b], a] - half, 0, layout.lengths[a] - window[a])
            D_ab, D_ba = _window_distances(
                lines, members[a], first_ab, side_b, int(window[b]), options.pair_block, back=(first_ba, int(window[a]))
            )
            _fill_uncovered(
                lines, D_ba, members[b], layout.starts[a] + first_ba, members[a], first_ba, options.pair_block
            )
            for rows, cols, first, D in ((a, b, first_ab, D_ab), (b, a, first_ba, D_ba)):
                best, best_d[members[rows], cols] = _window_best(lines, D, members[rows], layout.starts[cols] + first)
                position[members[rows], cols] = np.where(best >= 0, first + best, -1)
    anchor = np.where(position >= 0, position, anchor)
    anchor[np.arange(F), video_index] = layout.position
    anchor = consistent_anchors(anchor, video_index, layout, tolerance=anchor_tolerance(options, times), times=times)
    choice = np.argmin(best_d, axis=1)  # the first video on ties: the lower frame index, as the dense search
    cost = best_d[np.arange(F), choice]
    ok = np.isfinite(cost)
    partner = np.where(ok, layout.starts[choice] + position[np.arange(F), choice], -1)
    return PairInit(partner=partner, cost=cost, depth=partner_depths(lines, partner)), anchor


def follow_w(
    anchor: np.ndarray, W: sp.csc_matrix, video_index: np.ndarray, layout: VideoLayout, *, slack: int = 0
) -> np.ndarray:
    """Move each frame's anchor in each other video to the position of its largest W entry there, when that lies
    more than `slack` positions from the current anchor. The largest entry, not the weighted mean: in repetitive
    motion a frame can take weight from two distant passes through the same pose, and their mean is neither. The
    slack keeps the pools, and so the W-step's problem, fixed while the matches stay inside their windows: a pool
    that moved every alternation kept the alternation from settling."""
    W = W.tocoo()
    V = anchor.shape[1]
    winners = first_per_group(W.col * V + video_index[W.row], -W.data, 1)  # per (frame, video): largest weight
    frames, videos = W.col[winners], video_index[W.row[winners]]
    target = layout.position[W.row[winners]]
    move = np.abs(target - anchor[frames, videos]) > slack
    updated = anchor.copy()
    updated[frames[move], videos[move]] = target[move]
    return updated


class MovingWindows:
    """The candidate windows of a windowed solve: its anchors (F, V), which follow W after every W-step, and the
    candidate pool they give. Once the matches settle, most alternations leave the anchors where they were, and the
    pool is then reused instead of rebuilt."""

    def __init__(
        self, anchor: np.ndarray, video_index: np.ndarray, options: CandidateOptions, times: np.ndarray | None = None
    ):
        self.anchor = anchor
        self.video_index = video_index
        self.layout = VideoLayout.of(video_index)
        self.options = options
        self.times = times
        self._pool: tuple[np.ndarray, np.ndarray] | None = None  # (anchor, its pool)

    def pool(self) -> np.ndarray:
        """(F, C) each frame's candidates (`window_pool`)."""
        if self._pool is None or not np.array_equal(self._pool[0], self.anchor):
            self._pool = (
                self.anchor,
                window_pool(self.anchor, self.video_index, self.layout, self.options.half_window),
            )
        return self._pool[1]

    def follow(self, W: sp.csc_matrix) -> None:
        """Move the anchors to W's matches (`follow_w`) and back onto their video pairs' lines
        (`consistent_anchors`)."""
        followed = follow_w(self.anchor, W, self.video_index, self.layout, slack=self.options.recentre)
        self.anchor = consistent_anchors(
            followed,
            self.video_index,
            self.layout,
            times=self.times,
            tolerance=anchor_tolerance(self.options, self.times),
        )
