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

from reconstruct.initialize import MIN_COMMON_POINTS, PARALLEL_EPS, PairInit


@dataclass(kw_only=True)
class CandidateOptions:
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
    or too few shared points)."""
    ra, rb = rays[f], rays[j]  # (n, P, 3)
    w = (centers[f] - centers[j])[:, None, :]
    b = np.einsum("npk,npk->np", ra, rb)
    d = np.einsum("npk,npk->np", ra, np.broadcast_to(w, ra.shape))
    e = np.einsum("npk,npk->np", rb, np.broadcast_to(w, rb.shape))
    denom = 1.0 - b * b
    usable = ~np.isnan(denom) & (np.nan_to_num(denom) >= PARALLEL_EPS)
    safe = np.where(usable, denom, 1.0)
    depth_a = (b * e - d) / safe
    depth_b = (e - b * d) / safe
    gap = w + depth_a[..., None] * ra - depth_b[..., None] * rb
    gap_sq = np.where(usable, np.einsum("npk,npk->np", gap, gap), 0.0)
    count = usable.sum(axis=1)
    diverging = np.any(usable & ((depth_a < 0) | (depth_b < 0)), axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        D = gap_sq.sum(axis=1) / count
    observed_in_f = np.sum(~np.isnan(ra[..., 0]), axis=1)
    enough = count >= np.minimum(MIN_COMMON_POINTS, np.maximum(observed_in_f, 1))
    D[~enough | (count == 0) | diverging] = np.inf
    return D, np.where(usable, depth_a, np.nan)


def _best_per_video(
    centers: np.ndarray, rays: np.ndarray, rows: np.ndarray, cols: np.ndarray, video_index: np.ndarray,
    layout: VideoLayout, options: CandidateOptions,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For the pairs (rows[i], cols[i]): per row frame and video, the best column. Returns best position (R, V)
    (-1 where none), best D (R, V), and the flat pair index of the best (R, V) (-1 where none)."""
    V = len(layout.starts)
    unique_rows, row_of = np.unique(rows, return_inverse=True)
    best_d = np.full((len(unique_rows), V), np.inf)
    best_pair = np.full((len(unique_rows), V), -1, dtype=np.int64)
    D_all = np.empty(len(rows))
    for start in range(0, len(rows), options.pair_block):
        stop = min(len(rows), start + options.pair_block)
        D_all[start:stop], _ = pair_distances(centers, rays, rows[start:stop], cols[start:stop])
    col_video = video_index[cols]
    # Per (row, video) argmin via a lexicographic sort: smallest D first within each group.
    order = np.lexsort((D_all, col_video, row_of))
    group = row_of[order] * V + col_video[order]
    first = np.concatenate([[True], group[1:] != group[:-1]])
    winners = order[first]
    r, v = row_of[winners], col_video[winners]
    finite = np.isfinite(D_all[winners])
    best_d[r[finite], v[finite]] = D_all[winners][finite]
    best_pair[r[finite], v[finite]] = winners[finite]
    best_position = np.where(best_pair >= 0, layout.position[cols[np.maximum(best_pair, 0)]], -1)
    return best_position, best_d, best_pair


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
    without them, positions wander around it (irregular capture), by up to ~20 positions in 500 frames (measured)."""
    timed = times is not None and bool(np.all(np.isfinite(times)))
    return options.recentre if timed else options.half_window


def consistent_anchors(
    anchor: np.ndarray, video_index: np.ndarray, layout: VideoLayout, *, tolerance: int,
    times: np.ndarray | None = None, trials: int = 200,
) -> np.ndarray:
    """Every video's clock runs forward at a steady rate, so the anchors of a's frames in video b lie on a line:
    time in b against time in a when every frame has a decoder time (`times` (F,)), else position in b against
    position in a (only roughly a line: irregular capture makes positions a random walk around it). Anchors further
    than `tolerance` positions from the line that RANSAC fits through them matched a repeated pose elsewhere in the
    capture and are moved onto it. Measured on a 2000-frame capture of a repeated knee exercise: after the
    coarse-to-fine search 14 % of the anchors were more than 12 positions off (up to 357), in runs of up to 60
    frames that a running median follows."""
    rng = np.random.default_rng(0)
    fixed = anchor.copy()
    V = anchor.shape[1]
    timed = times is not None and bool(np.all(np.isfinite(times)))
    for a in range(V):
        members = np.arange(layout.starts[a], layout.starts[a] + layout.lengths[a])
        if len(members) < 3:
            continue
        x = times[members] if timed and times is not None else layout.position[members].astype(float)
        for b in range(V):
            if a == b or layout.lengths[b] < 2:
                continue
            b_frames = np.arange(layout.starts[b], layout.starts[b] + layout.lengths[b])
            b_axis = times[b_frames] if timed and times is not None else np.arange(len(b_frames), dtype=float)
            # tolerance in b's axis units: positions, or that many of b's median frame periods
            scale = float(np.median(np.diff(b_axis))) if timed else 1.0
            y = b_axis[fixed[members, b]]
            line = _ransac_line(x, y, tolerance * scale, trials, rng)
            if line is None:
                continue
            predicted = line[0] + line[1] * x
            stray = np.abs(y - predicted) > tolerance * scale
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
    centers: np.ndarray, rays: np.ndarray, video_index: np.ndarray, options: CandidateOptions,
    times: np.ndarray | None = None,
) -> tuple[PairInit, np.ndarray]:
    """The pairwise initialization restricted to anchor windows. Returns (init, anchor (F, V)). `times` (F,):
    decoder times, which make the anchors' consistency check exact (`consistent_anchors`)."""
    F, P = rays.shape[:2]
    layout = VideoLayout.of(video_index)
    V = len(layout.starts)
    coarse = np.flatnonzero(layout.position % options.stride == 0)
    rows = np.repeat(coarse, len(coarse))
    cols = np.tile(coarse, len(coarse))
    other = video_index[rows] != video_index[cols]
    position, _, _ = _best_per_video(centers, rays, rows[other], cols[other], video_index, layout, options)
    coarse_rows = np.unique(rows[other])
    anchor = np.full((F, V), -1, dtype=np.int64)
    anchor[coarse_rows] = position
    anchor = _fill_anchor_gaps(anchor, video_index, layout)
    anchor = consistent_anchors(anchor, video_index, layout, tolerance=options.stride, times=times)
    pool = window_pool(anchor, video_index, layout, options.stride + options.half_window)
    rows = np.repeat(np.arange(F), pool.shape[1])
    cols = pool.ravel()
    keep = cols >= 0
    rows, cols = rows[keep], cols[keep]
    position, best_d, best_pair = _best_per_video(centers, rays, rows, cols, video_index, layout, options)
    has = best_pair >= 0
    anchor = np.where(has, position, anchor)
    anchor[np.arange(F), video_index] = layout.position
    anchor = consistent_anchors(anchor, video_index, layout, tolerance=anchor_tolerance(options, times), times=times)
    choice = np.argmin(best_d, axis=1)
    best = best_pair[np.arange(F), choice]
    ok = best >= 0
    partner = np.full(F, -1, dtype=np.int64)
    cost = np.full(F, np.inf)
    depth = np.full((F, P), np.nan)
    partner[ok] = cols[best[ok]]
    cost[ok] = best_d[np.arange(F), choice][ok]
    if ok.any():
        _, depth[ok] = pair_distances(centers, rays, np.flatnonzero(ok), partner[ok])
    return PairInit(partner=partner, cost=cost, depth=depth), anchor


def follow_w(
    anchor: np.ndarray, W: sp.csc_matrix, video_index: np.ndarray, layout: VideoLayout, *, slack: int = 0
) -> np.ndarray:
    """Move each frame's anchor in each other video to the position of its largest W entry there, when that lies
    more than `slack` positions from the current anchor. The largest entry, not the weighted mean: in repetitive
    motion a frame can take weight from two distant passes through the same pose, and their mean is neither. The
    slack keeps the pools, and so the W-step's problem, fixed while the matches stay inside their windows: a pool
    that moved every alternation kept the alternation from settling (F = 2000: 147 alternations)."""
    W = W.tocoo()
    V = anchor.shape[1]
    key = W.col * V + video_index[W.row]
    order = np.lexsort((-W.data, key))  # per (frame, video) group, the largest weight first
    first = np.concatenate([[True], key[order][1:] != key[order][:-1]]) if len(order) else np.zeros(0, bool)
    winners = order[first]
    frames, videos = W.col[winners], video_index[W.row[winners]]
    target = layout.position[W.row[winners]]
    move = np.abs(target - anchor[frames, videos]) > slack
    updated = anchor.copy()
    updated[frames[move], videos[move]] = target[move]
    return updated
