"""Initial 3D shapes from nearly-intersecting ray bundles of other videos (paper, Sec. "Initialization").

For frames f and j of different videos, the depths minimizing ||S_f - S_j||^2 decouple per point: they are the
closest points of the two viewing rays. D(f, j) is the mean squared gap over the points both frames observe; a pair
with a negative depth (diverging rays) gets D = inf. Each frame takes the depths from its best partner.

The squared gap of two lines is computed without the depths, from Pluecker coordinates (direction r, moment
m = C x r): the gap is (r_a . m_b + r_b . m_a)^2 / |r_a x r_b|^2, and |r_a x r_b|^2 = 1 - (r_a . r_b)^2 for unit
rays. Both are matrix products over frame pairs. The rounding error of the gap is then ~eps |C| sqrt(gap), not the
~eps |C|^2 of expanding |w + d_a r_a - d_b r_b|^2 (w = C_a - C_b) into |w|^2 + d_a^2 + ...: on nearly meeting rays
D agrees with an explicit `closest_ray_points` evaluation to ~1e-12 instead of ~1e-7. D is symmetric, so each pair
of videos is evaluated once, for the rows of both. Whether a pair diverges needs its depths; it is only checked
for each frame's best candidates, in order, until one does not diverge: the same partner as excluding every
diverging pair first, at a fraction of the cost.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

PARALLEL_EPS = 1e-9
# Below this many shared points a bundle distance says little about the shape; such pairs are skipped when a
# frame has better-supported partners.
MIN_COMMON_POINTS = 3
# Rounds of "take the best candidate, check that it does not diverge" before the remaining frames get the
# divergence of all their candidates at once.
LAZY_ROUNDS = 4
# Frame pairs per tile of the per-point products: their few (R, C) buffers stay in a 1-2 MB cache.
TILE_PAIRS = 32_768


@dataclass(kw_only=True)
class PairInit:
    """Result of the pairwise initialization."""

    partner: np.ndarray  # (F,) best partner frame, -1 when none
    cost: np.ndarray  # (F,) D(f, partner)
    depth: np.ndarray  # (F, P) depth along the ray, NaN where not initialized


def closest_ray_points(
    center_a: np.ndarray, ray_a: np.ndarray, center_b: np.ndarray, ray_b: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depths (d_a, d_b) of the mutually closest points of rays C_a + d_a r_a and C_b + d_b r_b and their squared
    gap. Broadcasts over leading axes; the last axis is xyz. Unit rays. Parallel rays give NaN."""
    w = center_a - center_b
    b = np.sum(ray_a * ray_b, axis=-1)
    d = np.sum(ray_a * w, axis=-1)
    e = np.sum(ray_b * w, axis=-1)
    denom = 1.0 - b * b
    parallel = denom < PARALLEL_EPS
    denom = np.where(parallel, np.nan, denom)
    depth_a = (b * e - d) / denom
    depth_b = (e - b * d) / denom
    gap = w + depth_a[..., None] * ray_a - depth_b[..., None] * ray_b
    return depth_a, depth_b, np.sum(gap * gap, axis=-1)


@dataclass(kw_only=True)
class _Lines:
    """The viewing rays as lines, laid out for per-point matrix products. Unobserved rays are zero vectors: their
    products with anything are 0, so they add nothing to a gap sum and are never parallel."""

    centers: np.ndarray  # (F, 3)
    rays: np.ndarray  # (F, P, 3) zero where unobserved
    seen: np.ndarray  # (F, P) bool
    seen_float: np.ndarray  # (F, P) 1.0 / 0.0, for counting shared points by a matrix product
    need: np.ndarray  # (F,) shared points a partner must have (MIN_COMMON_POINTS, or all the frame observes)
    left: np.ndarray  # (P, F, 6) [m, r] with moments m = (C - origin) x r; [m_a, r_a] . [r_b, m_b] is the
    # reciprocal product r_a . m_b + r_b . m_a = (C_a - C_b) . (r_a x r_b)

    @classmethod
    def of(cls, centers: np.ndarray, rays: np.ndarray) -> _Lines:
        F, P = rays.shape[:2]
        seen = ~np.isnan(rays[..., 0])
        zeroed = np.where(seen[..., None], np.nan_to_num(rays), 0.0)
        # The gap is origin-free; an origin among the cameras keeps the moments, and so the rounding, small.
        origin = centers.mean(axis=0) if F else np.zeros(3)
        left = np.empty((P, F, 6))
        left[..., :3] = np.cross((centers - origin)[:, None, :], zeroed).transpose(1, 0, 2)
        left[..., 3:] = zeroed.transpose(1, 0, 2)
        return cls(
            centers=centers,
            rays=zeroed,
            seen=seen,
            seen_float=seen.astype(float),
            need=np.minimum(MIN_COMMON_POINTS, np.maximum(seen.sum(axis=1), 1)),
            left=left,
        )


@dataclass(kw_only=True)
class _Side:
    """The lines of some frames gathered for `_gap_sums`: as left factors (P, n, k) or right factors (P, k, n)."""

    frames: np.ndarray  # (n,)
    pluecker: np.ndarray  # (P, n, 6) [m, r] or (P, 6, n) [r, m]
    direction: np.ndarray  # (P, n, 3) or (P, 3, n): a view of the rays in `pluecker`

    @classmethod
    def rows(cls, lines: _Lines, frames: np.ndarray) -> _Side:
        pluecker = lines.left[:, frames]
        return cls(frames=frames, pluecker=pluecker, direction=pluecker[..., 3:])

    @classmethod
    def cols(cls, lines: _Lines, frames: np.ndarray) -> _Side:
        gathered = lines.left[:, frames]
        pluecker = np.concatenate([gathered[..., 3:], gathered[..., :3]], axis=-1).transpose(0, 2, 1).copy()
        return cls(frames=frames, pluecker=pluecker, direction=pluecker[:, :3])


def _gap_sums(lines: _Lines, a: _Side, b: _Side, rows: slice, cols: slice) -> tuple[np.ndarray, np.ndarray]:
    """Sum over shared, non-parallel points of the squared ray gap, and their number, for a.frames[rows] x
    b.frames[cols] (R, C). One pass per point over (R, C) buffers that should stay in cache."""
    ray_a, ray_b = a.direction[:, rows], b.direction[:, :, cols]
    left, right = a.pluecker[:, rows], b.pluecker[:, :, cols]
    R, C = ray_a.shape[1], ray_b.shape[2]
    total = np.zeros((R, C))
    sine_sq = np.empty((R, C))
    triple = np.empty((R, C))
    parallel: np.ndarray | None = None
    for p in range(ray_a.shape[0]):
        np.matmul(ray_a[p], ray_b[p], out=sine_sq)  # cosine
        np.multiply(sine_sq, sine_sq, out=sine_sq)
        np.subtract(1.0, sine_sq, out=sine_sq)
        np.matmul(left[p], right[p], out=triple)  # (C_a - C_b) . (r_a x r_b)
        if sine_sq.min() < PARALLEL_EPS:  # rare: nearly parallel rays have no meaningful gap and are not counted
            flat = sine_sq < PARALLEL_EPS
            parallel = flat.astype(np.int64) if parallel is None else parallel + flat
            sine_sq[flat] = 1.0
            triple[flat] = 0.0
        np.multiply(triple, triple, out=triple)
        np.divide(triple, sine_sq, out=triple)
        np.add(total, triple, out=total)
    # Exact: sums of a few 0/1 products.
    count = np.rint(lines.seen_float[a.frames[rows]] @ lines.seen_float[b.frames[cols]].T).astype(np.int64)
    if parallel is not None:
        count -= parallel
    return total, count


def _pair_depths(lines: _Lines, f: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For explicit pairs (n,): the depths (n, P) of f's points at the mutually closest ray points (NaN where a
    frame misses the point or the rays are parallel), and whether the pair diverges (n,)."""
    # The closed form of `closest_ray_points`, in its own summation order: the chosen partners' depths are the
    # solver's start, and a rounding-level change there moves a long solve's result.
    ra, rb = lines.rays[f], lines.rays[j]  # (n, P, 3)
    w = lines.centers[f] - lines.centers[j]  # (n, 3)
    b = np.einsum("npk,npk->np", ra, rb)
    d = np.einsum("npk,nk->np", ra, w)
    e = np.einsum("npk,nk->np", rb, w)
    denom = 1.0 - b * b
    usable = lines.seen[f] & lines.seen[j] & (denom >= PARALLEL_EPS)
    safe = np.where(usable, denom, 1.0)
    depth_a = (b * e - d) / safe
    depth_b = (e - b * d) / safe
    diverging = np.any(usable & ((depth_a < 0) | (depth_b < 0)), axis=1)
    return np.where(usable, depth_a, np.nan), diverging


def _pair_matrix(lines: _Lines, rows: np.ndarray, cols: np.ndarray, depth: np.ndarray | None = None) -> np.ndarray:
    """Whether each pair of rows x cols (R, C) diverges, by per-point matrix products; with `depth` (P, R, C), also
    the rows' depths there (NaN where a frame misses the point or the rays are parallel). A depth's sign is its
    numerator's: the denominator is in (0, 1]."""
    ca, cb = lines.centers[rows], lines.centers[cols]
    diverging = np.zeros((len(rows), len(cols)), dtype=bool)
    for p in range(lines.rays.shape[1]):
        ra, rb = lines.rays[rows, p], lines.rays[cols, p]  # zero where unobserved
        sa, sb = lines.seen_float[rows, p, None], lines.seen_float[cols, p, None]
        b = ra @ rb.T
        # d = r_a . (C_a - C_b), e = r_b . (C_a - C_b), as products of augmented factors; both 0 where either
        # frame misses the point (its ray, or its seen factor, is 0).
        d = np.hstack([ra, np.sum(ra * ca, axis=1, keepdims=True)]) @ np.hstack([-cb * sb, sb]).T
        e = np.hstack([ca * sa, sa]) @ np.hstack([rb, -np.sum(rb * cb, axis=1, keepdims=True)]).T
        denom = 1.0 - b * b
        usable = denom >= PARALLEL_EPS
        numerator_a = b * e
        numerator_a -= d
        d *= b
        np.subtract(e, d, out=e)  # numerator of the column frame's depth
        np.minimum(e, numerator_a, out=e)
        diverging |= usable & (e < 0)
        if depth is not None:
            usable &= lines.seen[rows, p][:, None] & lines.seen[cols, p][None, :]
            depth[p] = np.nan
            np.divide(numerator_a, denom, out=depth[p], where=usable)
    return diverging


def _best_partners(
    lines: _Lines, D: np.ndarray, rows: np.ndarray, cols: np.ndarray
) -> tuple[np.ndarray, np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    """Per row of D (R, C; modified: diverging pairs become inf), the first column of least D among the
    non-diverging ones. Returns the column position (R,) (-1 where none), its D (R,), and the diverging pairs
    found (row positions, column positions)."""
    return lazy_best(
        D,
        lambda pending, pick: _pair_depths(lines, rows[pending], cols[pick])[1],
        lambda pending, sub: _pair_matrix(lines, rows[pending], cols),
    )


def lazy_best(
    D: np.ndarray,
    diverging_at: Callable[[np.ndarray, np.ndarray], np.ndarray],
    diverging_rows: Callable[[np.ndarray, np.ndarray], np.ndarray],
) -> tuple[np.ndarray, np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    """Per row of D (R, C; modified: diverging pairs become inf), the first column of least D among the
    non-diverging pairs. Divergence needs the depths, so it is checked for each row's best candidate, then the
    next (`diverging_at(rows (n,), columns (n,)) -> (n,) bool`); rows still unresolved after LAZY_ROUNDS get
    their whole row checked at once (`diverging_rows(rows (n,), D[rows] (n, C)) -> (n, C) bool`). Returns the
    column (R,) (-1 where none), its D (R,), and the diverging pairs found (rows, columns)."""
    R = len(D)
    best = np.full(R, -1, dtype=np.int64)
    cost = np.full(R, np.inf)
    found: list[tuple[np.ndarray, np.ndarray]] = []
    pending = np.arange(R)
    for _ in range(LAZY_ROUNDS):
        if not len(pending):
            return best, cost, found
        pick = np.argmin(D if len(pending) == R else D[pending], axis=1)  # no copy of the whole block
        value = D[pending, pick]
        finite = np.isfinite(value)
        pending, pick, value = pending[finite], pick[finite], value[finite]
        diverging = diverging_at(pending, pick)
        keep = ~diverging
        best[pending[keep]], cost[pending[keep]] = pick[keep], value[keep]
        D[pending[diverging], pick[diverging]] = np.inf
        found.append((pending[diverging], pick[diverging]))
        pending = pending[diverging]
    if len(pending):
        sub = D[pending]
        diverging_all = diverging_rows(pending, sub)
        sub[diverging_all] = np.inf
        D[pending] = sub
        r, c = np.nonzero(diverging_all)
        found.append((pending[r], c))
        pick = np.argmin(sub, axis=1)
        value = sub[np.arange(len(pending)), pick]
        finite = np.isfinite(value)
        best[pending[finite]], cost[pending[finite]] = pick[finite], value[finite]
    return best, cost, found


def _merge(
    partner: np.ndarray,
    cost: np.ndarray,
    frames: np.ndarray,
    best: np.ndarray,
    best_cost: np.ndarray,
    cols: np.ndarray,
) -> None:
    """Merge the best column positions (-1: none) of `frames` among `cols` into partner / cost (F,): least cost
    wins, the lower frame index on ties (as argmin over a whole row)."""
    ok = best >= 0
    frames, candidate, candidate_cost = frames[ok], cols[best[ok]], best_cost[ok]
    old_cost, old = cost[frames], partner[frames]
    better = (candidate_cost < old_cost) | ((candidate_cost == old_cost) & (candidate < old))
    partner[frames[better]] = candidate[better]
    cost[frames[better]] = candidate_cost[better]


def bundle_distances(
    centers: np.ndarray, rays: np.ndarray, rows: np.ndarray, video_index: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """D(f, j) for the frames `rows` against all frames, and the depths of `rows` in each pair.

    centers: (F, 3); rays: (F, P, 3) NaN = unobserved; rows: (B,). Returns D (B, F) and depth (B, F, P), NaN where
    either frame misses the point, the rays are parallel, or the frames are of the same video (D = inf there)."""
    F, P = rays.shape[:2]
    rows = np.asarray(rows)
    lines = _Lines.of(centers, rays)
    D = np.full((len(rows), F), np.inf)
    depth = np.full((len(rows), F, P), np.nan)
    for v in np.unique(video_index[rows]):
        positions = np.flatnonzero(video_index[rows] == v)
        cols = np.flatnonzero(video_index != v)
        if not len(cols):
            continue
        step = max(1, TILE_PAIRS // len(cols))
        b = _Side.cols(lines, cols)
        for start in range(0, len(positions), step):
            at = positions[start : start + step]
            f = rows[at]
            total, count = _gap_sums(lines, _Side.rows(lines, f), b, slice(None), slice(None))
            depth_block = np.empty((P, len(f), len(cols)))
            diverging = _pair_matrix(lines, f, cols, depth_block)
            with np.errstate(invalid="ignore", divide="ignore"):
                d = total / count
            d[(count < lines.need[f][:, None]) | diverging] = np.inf
            D[np.ix_(at, cols)] = d
            depth[np.ix_(at, cols)] = depth_block.transpose(1, 2, 0)
    return D, depth


def initialize_depths(
    centers: np.ndarray, rays: np.ndarray, video_index: np.ndarray, *, memory_elements: int = 2_000_000
) -> PairInit:
    """Pick each frame's best partner of another video and take the depths from that pair: the first column of
    least D in the frame's row of `bundle_distances` (-1 and cost inf where the row is all inf). O(F^2 P) time; the
    memory beyond the inputs is O(F P) plus a few arrays of min(memory_elements, frame pairs of two videos); two
    videos with more frame pairs than memory_elements cost twice the arithmetic."""
    F = len(rays)
    lines = _Lines.of(centers, rays)
    partner = np.full(F, -1, dtype=np.int64)
    cost = np.full(F, np.inf)
    members = [np.flatnonzero(video_index == v) for v in np.unique(video_index)]
    for ia, frames_a in enumerate(members):
        for frames_b in members[ia + 1 :]:
            (best_a, cost_a), (best_b, cost_b) = video_pair_best(
                lines, frames_a, frames_b, memory_elements=memory_elements
            )
            _merge(partner, cost, frames_a, best_a, cost_a, frames_b)
            _merge(partner, cost, frames_b, best_b, cost_b, frames_a)
    return PairInit(partner=partner, cost=cost, depth=partner_depths(lines, partner))


def video_pair_best(
    lines: _Lines, frames_a: np.ndarray, frames_b: np.ndarray, *, memory_elements: int
) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """For two videos' frames, each frame's best partner in the other video (`_best_partners`): (position (R,),
    D (R,)) for `frames_a` among `frames_b`, and the same for `frames_b` among `frames_a`. One symmetric block
    when it holds at most `memory_elements` pairs (D is symmetric: one evaluation serves both videos), else bands
    of whole rows in each direction (twice the arithmetic)."""
    if len(frames_a) * len(frames_b) <= memory_elements:
        D_rows, D_cols = _distance_block(lines, frames_a, frames_b, both=True)
        best_a, cost_a, diverging = _best_partners(lines, D_rows, frames_a, frames_b)
        for r, c in diverging:
            D_cols[c, r] = np.inf
        best_b, cost_b, _ = _best_partners(lines, D_cols, frames_b, frames_a)
        return (best_a, cost_a), (best_b, cost_b)
    found = []
    for rows_all, cols in ((frames_a, frames_b), (frames_b, frames_a)):
        best = np.full(len(rows_all), -1, dtype=np.int64)
        best_cost = np.full(len(rows_all), np.inf)
        band = max(1, memory_elements // len(cols))
        for start in range(0, len(rows_all), band):
            rows = rows_all[start : start + band]
            D_rows, _ = _distance_block(lines, rows, cols, both=False)
            best[start : start + band], best_cost[start : start + band], _ = _best_partners(lines, D_rows, rows, cols)
        found.append((best, best_cost))
    return found[0], found[1]


def partner_depths(lines: _Lines, partner: np.ndarray) -> np.ndarray:
    """(F, P) depths of each frame's points at the mutually closest points of its partner's rays (`_pair_depths`);
    NaN for frames without a partner (-1)."""
    depth = np.full(lines.rays.shape[:2], np.nan)
    matched = np.flatnonzero(partner >= 0)
    for start in range(0, len(matched), 256):
        f = matched[start : start + 256]
        depth[f], _ = _pair_depths(lines, f, partner[f])
    return depth


def _distance_block(lines: _Lines, rows: np.ndarray, cols: np.ndarray, *, both: bool) -> tuple[np.ndarray, np.ndarray]:
    """D for rows x cols (R, C), inf where the pair shares too few points for the row frame; with `both`, also
    the same for the column frames, transposed (C, R) (else an empty array). Divergence is not checked here.
    Evaluated in cache-sized tiles."""
    R, C = len(rows), len(cols)
    D_rows = np.empty((R, C))
    D_cols = np.empty((C, R) if both else (0, 0))
    col_step = min(C, TILE_PAIRS)
    row_step = max(1, TILE_PAIRS // col_step)
    a, b = _Side.rows(lines, rows), _Side.cols(lines, cols)
    for r0 in range(0, R, row_step):
        r1 = min(R, r0 + row_step)
        for c0 in range(0, C, col_step):
            c1 = min(C, c0 + col_step)
            total, count = _gap_sums(lines, a, b, slice(r0, r1), slice(c0, c1))
            with np.errstate(invalid="ignore", divide="ignore"):
                D = np.divide(total, count, out=total)
            D_rows[r0:r1, c0:c1] = np.where(count >= lines.need[rows[r0:r1]][:, None], D, np.inf)
            if both:
                D_cols[c0:c1, r0:r1] = np.where(count >= lines.need[cols[c0:c1]][None, :], D, np.inf).T
    return D_rows, D_cols


def fill_missing_points(points: np.ndarray, video_index: np.ndarray) -> np.ndarray:
    """Fill NaN 3D points (F, P, 3) for a start value: interpolate within the same video over frame order, else use
    the point's mean over all frames; a point with no start on any frame (its rays never met another video's in
    front of both cameras: cameras that do not fit the tracks) the other points' mean on each frame. Only a
    starting point for the solver, which re-estimates them."""
    filled = points.copy()
    P = points.shape[1]
    for vi in np.unique(video_index):
        members = np.flatnonzero(video_index == vi)
        for p in range(P):
            known = ~np.isnan(filled[members, p, 0])
            if known.all() or not known.any():
                continue
            positions = np.arange(len(members))
            for axis in range(3):
                filled[members[~known], p, axis] = np.interp(
                    positions[~known], positions[known], filled[members[known], p, axis]
                )
    for p in range(P):
        missing = np.isnan(filled[:, p, 0])
        if missing.any() and not missing.all():
            filled[missing, p] = np.nanmean(filled[:, p], axis=0)
    empty = np.isnan(filled[:, :, 0]).all(axis=0)
    if empty.any() and not empty.all():
        with np.errstate(invalid="ignore"):
            others = np.nanmean(filled[:, ~empty], axis=1)  # (F, 3): NaN on frames where every point is empty
        others[np.isnan(others[:, 0])] = np.nanmean(others, axis=0)
        filled[:, empty] = others[:, None, :]
    return filled
