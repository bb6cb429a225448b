"""The W-step: minimize over W, with the shapes S fixed,

    g(W) = 1/(F P) ||S^T - S^T W||_F^2 + lambda1/F ||W - W^T||_F^2,   columns of W on the simplex,
    W_jf = 0 (not a variable) when j = f or video(j) = video(f).

Method (solves the same convex problem as the paper's ADMM; see docs/solver.md):
* Working set. Solutions are sparse and local, so each column only carries the entries in a working set: its nearest
  shapes of other videos (or of its candidate pool on long captures) plus the previous support, symmetrized so that
  Psi1's partner entry W_fj is always in the set.
* Exact solve on the working set (reconstruct/solver/active_set.py): a primal-dual active-set method, one reduced
  positive definite solve on the free set per iteration, warm-started from the previous W.
* Optimality on the full problem: the gradient of every allowed entry outside the set is then checked against the
  column's simplex multiplier (KKT); violators join the set and the solve continues. When no entry violates, the
  working-set solution is a solution of the full problem.
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from reconstruct.solver.active_set import WorkingSetProblem, active_set, find_sorted, fista
from reconstruct.solver.wstep_options import WStepOptions, WStepStats

log = logging.getLogger(__name__)

PARALLEL_ROWS = 4096  # frames from which local_inner splits its rows over threads
MAX_ADDED_PER_COLUMN = 8  # KKT violators that may join one column's working set per round


@dataclass(kw_only=True)
class SparseW:
    """Column-padded sparse W: W[cand[f, k], f] = value[f, k] where valid[f, k]."""

    cand: np.ndarray  # (F, K) int
    valid: np.ndarray  # (F, K) bool
    value: np.ndarray  # (F, K) float

    @property
    def num_frames(self) -> int:
        return self.cand.shape[0]

    def to_csc(self) -> sp.csc_matrix:
        F = self.num_frames
        cols = np.broadcast_to(np.arange(F)[:, None], self.cand.shape)
        keep = self.valid & (self.value != 0)
        return sp.csc_matrix((self.value[keep], (self.cand[keep], cols[keep])), shape=(F, F))

    def column(self, f: int, threshold: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(neighbours, weights) of column f with weights above `threshold`."""
        keep = self.valid[f] & (self.value[f] > threshold)
        return self.cand[f, keep], self.value[f, keep]


def _videos_contiguous(video_index: np.ndarray) -> tuple[np.ndarray, list[tuple[np.ndarray, int, int]]]:
    """Frame order that makes each video contiguous, and per video (its frames, first and end position in that
    order): masking a video's own frames is then a slice, not an (F, F) boolean mask."""
    order = np.argsort(video_index, kind="stable")
    _, starts, counts = np.unique(video_index[order], return_index=True, return_counts=True)
    groups = [
        (order[start : start + count], int(start), int(start + count))
        for start, count in zip(starts, counts, strict=True)
    ]
    return order, groups


def nearest_other_video(shapes: np.ndarray, video_index: np.ndarray, k: int, *, block: int = 1024) -> np.ndarray:
    """(F, k') indices of the k nearest shapes of other videos (k' = min(k, available)), in row blocks."""
    F = len(shapes)
    k = min(k, F - 1)
    order, groups = _videos_contiguous(video_index)
    ordered = shapes[order]
    # |S_j|^2 - 2 S_f . S_j ranks the frames j like |S_f - S_j|^2 does.
    norms = np.einsum("fd,fd->f", ordered, ordered)
    result = np.empty((F, k), dtype=np.int64)
    for members, lo, hi in groups:
        for start in range(0, len(members), block):
            rows = members[start : start + block]
            d2 = shapes[rows] @ ordered.T
            d2 *= -2.0
            d2 += norms
            d2[:, lo:hi] = np.inf
            result[rows] = order[smallest_per_row(d2, k)[0]]
    return result


def smallest_per_row(values: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, k) column indices of each row's k smallest values (n, m), ascending, and those values; `values` is
    overwritten. One vectorized argmin per rank: for the small k of the working sets it beats argpartition +
    argsort. A row with fewer than k finite values gets +inf values,
    with meaningless columns, in the remaining ranks."""
    rows = np.arange(len(values))
    index = np.empty((len(values), k), dtype=np.int64)
    picked = np.empty((len(values), k))
    for rank in range(k):
        column = np.argmin(values, axis=1)
        index[:, rank] = column
        picked[:, rank] = values[rows, column]
        values[rows, column] = np.inf
    return index, picked


def local_inner(A: np.ndarray, B: np.ndarray, index: np.ndarray, *, chunk: int = 64, workers: int = 1) -> np.ndarray:
    """(F, C) A[f] . B[index[f, c]] (0 where index < 0), for A, B (F, D). Consecutive frames have neighbouring
    candidates, so each chunk of rows needs B only on the union of its candidates: one small dense product per chunk
    instead of gathering an (F, C, D) array (hundreds of MB on long captures). From PARALLEL_ROWS rows on,
    `workers` threads take a share of the rows each (same values to the bit)."""
    F, C = index.shape
    out = np.zeros((F, C))

    def fill(first: int, stop: int) -> None:
        # The union of a chunk's candidates by marking them in a reused mask: np.unique's sort or hash per chunk
        # cost more than the products.
        marked = np.zeros(len(B), dtype=bool)
        column_of = np.zeros(len(B), dtype=np.int64)
        for start in range(first, stop, chunk):
            rows = slice(start, min(stop, start + chunk))
            idx = index[rows]
            present = idx >= 0
            marked[idx[present]] = True
            union = np.flatnonzero(marked)
            if len(union) == 0:
                continue
            marked[union] = False
            column_of[union] = np.arange(len(union))
            product = A[rows] @ B[union].T  # (chunk, U)
            local = np.take_along_axis(product, column_of[np.maximum(idx, 0)], axis=1)
            out[rows] = np.where(present, local, 0.0)

    if workers > 1 and F >= PARALLEL_ROWS:
        bounds = [chunk * (F // chunk * w // workers) for w in range(workers)] + [F]
        with ThreadPoolExecutor(workers) as pool:
            list(pool.map(fill, bounds[:-1], bounds[1:]))
    else:
        fill(0, F)
    return out


def nearest_in_pool(shapes: np.ndarray, pool: np.ndarray, k: int, workers: int = 1) -> np.ndarray:
    """(F, k) the k nearest shapes among each frame's candidates pool (F, C) (-1 = none); -1 where fewer."""
    C = pool.shape[1]
    k = min(k, C)
    norms = np.einsum("fd,fd->f", shapes, shapes)
    # |S_j|^2 - 2 S_f . S_j ranks the candidates j of frame f like |S_f - S_j|^2 does.
    d2 = norms[np.maximum(pool, 0)] - 2.0 * local_inner(shapes, shapes, pool, workers=workers)
    d2[pool < 0] = np.inf
    chosen, distance = smallest_per_row(d2, k)
    nearest = np.take_along_axis(pool, chosen, axis=1)
    nearest[~np.isfinite(distance)] = -1
    return nearest


def _pack_pairs(rows: np.ndarray, cols: np.ndarray, F: int) -> tuple[np.ndarray, np.ndarray]:
    """Unique (row j, column f) pairs, symmetrized, packed per column -> (cand (F, K), valid (F, K)), each column's
    rows ascending."""
    rows, cols = np.concatenate([rows, cols]), np.concatenate([cols, rows])
    # A sparse matrix with a row per column f sorts and merges the pairs row by row: np.unique's global sort of the
    # keys f * F + j was an order of magnitude slower on long captures, same result.
    pairs = sp.csr_matrix((np.ones(len(rows), dtype=np.int32), (cols, rows)), shape=(F, F))
    pairs.sum_duplicates()
    counts = np.diff(pairs.indptr)
    K = max(1, int(counts.max()))
    cols = np.repeat(np.arange(F), counts)
    position = np.arange(len(cols)) - pairs.indptr[:-1][cols]
    cand = np.broadcast_to(np.arange(F)[:, None], (F, K)).copy()  # padding points at the frame itself
    valid = np.zeros((F, K), dtype=bool)
    cand[cols, position] = pairs.indices
    valid[cols, position] = True
    return cand, valid


def kkt_violations(
    shapes: np.ndarray,
    video_index: np.ndarray,
    W: SparseW,
    problem: WorkingSetProblem,
    options: WStepOptions,
    *,
    block: int = 1024,
    pool: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Allowed entries (rows j, columns f) outside the working set whose gradient lies below the column's simplex
    multiplier by more than kkt_tolerance * L_f: moving weight onto them would lower g. With a candidate `pool`
    (F, C) only the pool's entries are allowed (long captures)."""
    F = len(shapes)
    grad = problem.gradient(W.value)
    mu = np.where(W.valid, grad, np.inf).min(axis=1)  # (F,) multiplier: min gradient over the column's entries
    # (F, D): S W_f - S_f, as a sparse product (gathering shapes[W.cand], (F, K, D), is slow on long captures)
    residual = W.to_csc().T @ shapes - shapes
    if pool is not None:
        return _pool_violations(shapes, W, problem, options, mu, residual, pool)
    order, groups = _videos_contiguous(video_index)
    ordered = shapes[order]
    position_of = np.empty(F, dtype=np.int64)
    position_of[order] = np.arange(F)
    # Violation > kkt_tolerance  <=>  r_f . S_j < threshold_f, and within a column a smaller r_f . S_j is a larger
    # violation: one comparison per entry, and only the few entries past it are ranked.
    self_inner = np.einsum("fd,fd->f", residual, shapes)
    threshold = (mu - options.kkt_tolerance * problem.lipschitz) / (2.0 * problem.data_weight) + self_inner
    k = min(MAX_ADDED_PER_COLUMN, F - 1)
    found_rows: list[np.ndarray] = []
    found_cols: list[np.ndarray] = []
    found_inner: list[np.ndarray] = []
    for members, lo, hi in groups:
        for start in range(0, len(members), block):
            cols = members[start : start + block]
            inner = residual[cols] @ ordered.T  # (B, F): r_f . S_j, columns in video order
            inner[:, lo:hi] = np.inf
            local, slot = np.nonzero(W.valid[cols])
            inner[local, position_of[W.cand[cols][local, slot]]] = np.inf  # already in the working set
            below = inner < threshold[cols, None]
            count = int(np.count_nonzero(below))
            if count == 0:
                continue
            if count <= 4 * k * len(cols):
                local, position = np.nonzero(below)
            else:  # a cold start: many violators, keep each column's k largest
                part = np.argpartition(inner, k - 1, axis=1)[:, :k]
                chosen = np.take_along_axis(below, part, axis=1)
                local, position = np.nonzero(chosen)[0], part[chosen]
            found_rows.append(order[position])
            found_cols.append(cols[local])
            found_inner.append(inner[local, position])
    if not found_rows:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    rows, cols = np.concatenate(found_rows), np.concatenate(found_cols)
    keep = first_per_group(cols, np.concatenate(found_inner), k)
    return rows[keep], cols[keep]


def _pool_violations(
    shapes: np.ndarray,
    W: SparseW,
    problem: WorkingSetProblem,
    options: WStepOptions,
    mu: np.ndarray,
    residual: np.ndarray,
    pool: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    inner = local_inner(residual, shapes, pool, workers=options.workers)
    g = 2.0 * problem.data_weight * (inner - np.einsum("fd,fd->f", residual, shapes)[:, None])
    violation = (mu[:, None] - g) / problem.lipschitz[:, None]
    # Violators are few: find them first, then drop the empty slots and the entries already in the working set
    # among them, and rank only the rest: cheaper than ranking or marking the whole (F, C) pool.
    cols, slots = np.nonzero(violation > options.kkt_tolerance)
    rows = pool[cols, slots]
    F = len(pool)
    in_set = (np.arange(F)[:, None] * F + W.cand)[W.valid]  # keys f F + j of the working set's entries
    if np.any(in_set[1:] < in_set[:-1]):  # packed sets (wstep._pack_pairs) are sorted already
        in_set = np.sort(in_set)
    new = (rows >= 0) & ~find_sorted(in_set, cols * F + rows)[1]
    cols, rows, violation_new = cols[new], rows[new], violation[cols[new], slots[new]]
    keep = first_per_group(cols, -violation_new, MAX_ADDED_PER_COLUMN)
    return rows[keep], cols[keep]


def solve_w(
    shapes: np.ndarray,
    video_index: np.ndarray,
    num_points: int,
    options: WStepOptions,
    previous: SparseW | None = None,
    pool: np.ndarray | None = None,
) -> tuple[SparseW, WStepStats]:
    """Solve the W-step for shapes (F, 3P), warm-started from `previous`. With a candidate `pool` (F, C) of frame
    indices (-1 = none; reconstruct/solver/candidates.py) W is restricted to it: cost O(F C) instead of O(F^2)."""
    F = len(shapes)
    stats = WStepStats()
    if pool is None:
        near = nearest_other_video(shapes, video_index, options.nearest)
    else:
        near = nearest_in_pool(shapes, pool, options.nearest, options.workers)
    near_cols = np.repeat(np.arange(F), near.shape[1])
    # fewer other-video frames than `nearest`, or a short pool
    other = (near.ravel() >= 0) & (video_index[near.ravel()] != video_index[near_cols])
    seed_rows, seed_cols = _limit_seeds_per_frame(
        near.ravel()[other], near_cols[other], np.tile(np.arange(near.shape[1]), F)[other], 3 * options.nearest
    )
    rows = [seed_rows]
    cols = [seed_cols]
    if previous is not None:
        keep = previous.valid & (previous.value > 0)
        rows.append(previous.cand[keep])
        cols.append(np.broadcast_to(np.arange(F)[:, None], previous.cand.shape)[keep])
    all_rows, all_cols = np.concatenate(rows), np.concatenate(cols)
    # Warm start: the previous W on the first round, then each round's own solution.
    V_start = None if previous is None else _sparse_lookup(previous)
    for round_index in range(options.max_rounds):
        cand, valid = _pack_pairs(all_rows, all_cols, F)
        problem = WorkingSetProblem(shapes, cand, valid, options.lambda1, num_points, options.workers)
        V = _start_values(cand, valid, V_start, near)
        exact = active_set(problem, V, options, stats)
        if exact is None:
            log.debug("active-set W-step did not finish; falling back to FISTA")
            stats.fallbacks += 1
            exact = fista(problem, V, options, stats)
        V = exact
        W = SparseW(cand=cand, valid=valid, value=V)
        stats.rounds = round_index + 1
        stats.working_set = int(valid.sum())
        if not options.full_kkt_check:
            break
        add_rows, add_cols = kkt_violations(shapes, video_index, W, problem, options, pool=pool)
        if len(add_rows) == 0:
            break
        stats.added += len(add_rows)
        all_rows = np.concatenate([cand[valid], add_rows])
        all_cols = np.concatenate([np.broadcast_to(np.arange(F)[:, None], cand.shape)[valid], add_cols])
        V_start = _sparse_lookup(W)
    stats.history.append(stats.objective)
    return W, stats


def _limit_seeds_per_frame(
    rows: np.ndarray, cols: np.ndarray, rank: np.ndarray, limit: int
) -> tuple[np.ndarray, np.ndarray]:
    """Keep at most `limit` seed pairs (row j, column f) per frame j, those where j ranks nearest for f. The working
    set is symmetrized, so a frame that is the nearest of thousands of frames would get a column of thousands of
    entries, and the per-column Gram matrices (F, K, K) are padded to the largest column (the last frame of a
    video, where out-of-range anchors are clipped, can be such a frame)."""
    keep = first_per_group(rows, rank, limit)
    return rows[keep], cols[keep]


def first_per_group(group: np.ndarray, score: np.ndarray, limit: int) -> np.ndarray:
    """Indices of at most `limit` items per value of `group` (n,), lowest `score` first (ties in input order),
    sorted by group."""
    order = np.lexsort((score, group))
    grouped = group[order]
    return order[np.arange(len(order)) - np.searchsorted(grouped, grouped) < limit]


def _sparse_lookup(W: SparseW) -> np.ndarray:
    """The entries of W as (column, row, value) triplets, (3, nnz): keyed like a sparse matrix, never dense F x F."""
    F = W.num_frames
    cols = np.broadcast_to(np.arange(F)[:, None], W.cand.shape)[W.valid]
    return np.stack([cols, W.cand[W.valid], W.value[W.valid]])


def _start_values(cand: np.ndarray, valid: np.ndarray, triplets: np.ndarray | None, near: np.ndarray) -> np.ndarray:
    """Warm start on a new working set: previous values (triplets of `_sparse_lookup`) where the entry existed,
    else all weight on the nearest."""
    F, K = cand.shape
    V = np.zeros((F, K))
    if triplets is not None and triplets.shape[1]:
        old_keys = triplets[0].astype(np.int64) * F + triplets[1].astype(np.int64)
        order = np.argsort(old_keys)
        old_keys, old_values = old_keys[order], triplets[2][order]
        new_keys = np.arange(F)[:, None] * F + cand
        where, found = find_sorted(old_keys, new_keys)
        hit = valid & found
        V[hit] = old_values[where[hit]]
    empty = V.sum(axis=1) <= 0
    if np.any(empty):
        nearest = near[:, 0]
        match = valid & (cand == nearest[:, None])
        V[empty] = np.where(match[empty], 1.0, 0.0)
    return V


def objective_full(shapes: np.ndarray, W: sp.spmatrix, lambda1: float, num_points: int) -> float:
    """g(W) evaluated with a sparse W (F, F) — for reports and tests."""
    F = len(shapes)
    residual = shapes - W.T @ shapes
    asym = W - W.T
    return float(np.sum(residual * residual) / (F * num_points) + lambda1 / F * asym.multiply(asym).sum())
