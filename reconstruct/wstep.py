"""The W-step: minimize over W, with the shapes S fixed,

    g(W) = 1/(F P) ||S^T - S^T W||_F^2 + lambda1/F ||W - W^T||_F^2,   columns of W on the simplex,
    W_jf = 0 (not a variable) when j = f or video(j) = video(f).

Method (solves the same convex problem as the paper's ADMM; see docs/solver.md):
* Working set. Solutions are sparse and local, so each column only carries the entries in a working set: its nearest
  shapes of other videos plus the previous support, symmetrized so that Psi1's partner entry W_fj is always in the set.
* Accelerated projected gradient (FISTA with function-value restart) on the working set, in a per-column metric:
  the data term is block-diagonal over columns, so step 1/L_f with L_f = 2/(FP) lambda_max(B_f^T B_f) + 8 lambda1/F
  (B_f: candidate shapes minus S_f) majorizes the Hessian and the projection stays a per-column Euclidean simplex
  projection. Warm-started from the previous W.
* Optimality on the full problem: after convergence, the gradient of every allowed entry outside the set is
  checked against the column's simplex multiplier (KKT); violators join the set and the solve continues. When no
  entry violates, the working-set solution is a solution of the full problem.
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import connected_components

from reconstruct.simplex import project_rows_to_simplex

log = logging.getLogger(__name__)

NEGLIGIBLE = 1e-9  # W entries this close to zero are zero (W values lie in [0, 1])
PARALLEL_KKT = 20_000  # free entries to re-solve at and above which independent components are split over threads


@dataclass(kw_only=True)
class WStepOptions:
    lambda1: float = 0.05
    nearest: int = 8  # initial working-set neighbours per column (other videos)
    tolerance: float = 1e-6  # stop when max |W_new - W_extrapolated| (gradient mapping, W units) is below
    max_iterations: int = 2000  # FISTA fallback
    # Warm-started W-steps settle in 2-5 iterations; a cold start with a grown working set needed 30-45 on CMU
    # F = 700 (measured), still 4x cheaper than FISTA. Past this budget
    # FISTA finishes the solve.
    max_active_set_iterations: int = 60
    # A column whose free entries changed in this many active-set iterations changes one entry at a time from then
    # on (_limit_changes).
    cycle_changes: int = 8
    # PDAS can wander near a degenerate optimum, flipping a few entries in and out: measured on CMU F = 700, a
    # cold W-step spent 58 KKT solves to gain 0.03 % of g. It stops with its best iterate once that many iterations
    # have not lowered g by this relative amount (the outer KKT check tolerates far more: kkt_tolerance).
    stall_iterations: int = 5
    stall_tolerance: float = 1e-4
    # Budget of the monotone primal active-set method that finishes when PDAS cycles (each step one KKT solve).
    max_primal_iterations: int = 20
    # Entries whose KKT violation / L_f (the weight a gradient step would give them) exceeds this join the working
    # set. Measured on HDM05: 1e-5 grew the set to ~36 entries per column for the same accuracy at 10x the time.
    kkt_tolerance: float = 1e-3
    max_added_per_column: int = 8
    max_rounds: int = 3
    full_kkt_check: bool = True  # O(F^2 P) per W-step; disable for very long captures
    # Independent components of large KKT systems (windowed dictionaries) are factorized on this many threads.
    workers: int = 2


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


@dataclass(kw_only=True)
class WStepStats:
    iterations: int = 0
    rounds: int = 0
    added: int = 0
    working_set: int = 0
    objective: float = float("nan")
    converged: bool = False
    fallbacks: int = 0  # working-set solves the active-set method left to FISTA
    history: list[float] = field(default_factory=list)


def _videos_contiguous(video_index: np.ndarray) -> tuple[np.ndarray, list[tuple[np.ndarray, int, int]]]:
    """Frame order that makes each video contiguous, and per video (its frames, first and end position in that
    order): masking a video's own frames is then a slice, not an (F, F) boolean mask."""
    order = np.argsort(video_index, kind="stable")
    _, starts, counts = np.unique(video_index[order], return_index=True, return_counts=True)
    groups = [(order[start:start + count], int(start), int(start + count))
              for start, count in zip(starts, counts, strict=True)]
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
            rows = members[start:start + block]
            d2 = shapes[rows] @ ordered.T
            d2 *= -2.0
            d2 += norms
            d2[:, lo:hi] = np.inf
            part = np.argpartition(d2, k - 1, axis=1)[:, :k]
            nearest = np.take_along_axis(part, np.argsort(np.take_along_axis(d2, part, axis=1), axis=1), axis=1)
            result[rows] = order[nearest]
    return result


def local_inner(A: np.ndarray, B: np.ndarray, index: np.ndarray, *, chunk: int = 64) -> np.ndarray:
    """(F, C) A[f] . B[index[f, c]] (0 where index < 0), for A, B (F, D). Consecutive frames have neighbouring
    candidates, so each chunk of rows needs B only on the union of its candidates: one small dense product per chunk
    instead of gathering an (F, C, D) array (at F = 2000, P = 44: 160 MB per call)."""
    F, C = index.shape
    out = np.zeros((F, C))
    # The union of a chunk's candidates by marking them in a reused mask: np.unique's sort or hash per chunk cost
    # more than the products.
    marked = np.zeros(len(B), dtype=bool)
    column_of = np.zeros(len(B), dtype=np.int64)
    for start in range(0, F, chunk):
        rows = slice(start, min(F, start + chunk))
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
    return out


def nearest_in_pool(shapes: np.ndarray, pool: np.ndarray, k: int) -> np.ndarray:
    """(F, k) the k nearest shapes among each frame's candidates pool (F, C) (-1 = none); -1 where fewer."""
    C = pool.shape[1]
    k = min(k, C)
    norms = np.einsum("fd,fd->f", shapes, shapes)
    # |S_j|^2 - 2 S_f . S_j ranks the candidates j of frame f like |S_f - S_j|^2 does.
    d2 = norms[np.maximum(pool, 0)] - 2.0 * local_inner(shapes, shapes, pool)
    d2[pool < 0] = np.inf
    part = np.argpartition(d2, k - 1, axis=1)[:, :k]
    chosen = np.take_along_axis(part, np.argsort(np.take_along_axis(d2, part, axis=1), axis=1), axis=1)
    nearest = np.take_along_axis(pool, chosen, axis=1)
    nearest[~np.isfinite(np.take_along_axis(d2, chosen, axis=1))] = -1
    return nearest


def _pack_pairs(rows: np.ndarray, cols: np.ndarray, F: int) -> tuple[np.ndarray, np.ndarray]:
    """Unique (row j, column f) pairs, symmetrized, packed per column -> (cand (F, K), valid (F, K))."""
    rows, cols = np.concatenate([rows, cols]), np.concatenate([cols, rows])
    keys = np.unique(cols.astype(np.int64) * F + rows)
    cols, rows = keys // F, keys % F
    counts = np.bincount(cols, minlength=F)
    K = max(1, int(counts.max()))
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    position = np.arange(len(keys)) - starts[cols]
    cand = np.broadcast_to(np.arange(F)[:, None], (F, K)).copy()  # padding points at the frame itself
    valid = np.zeros((F, K), dtype=bool)
    cand[cols, position] = rows
    valid[cols, position] = True
    return cand, valid


def _transpose_index(cand: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Flat index of the entry (f, j) for every valid entry (j, f); the set must be symmetric. (F, K), -1 padding."""
    F, K = cand.shape
    flat = np.flatnonzero(valid.ravel())
    cols = flat // K
    keys = cols * F + cand.ravel()[flat]
    order = np.argsort(keys)
    sorted_keys = keys[order]
    transposed = cand.ravel()[flat] * F + cols
    where = np.searchsorted(sorted_keys, transposed)
    if np.any(where >= len(sorted_keys)) or np.any(sorted_keys[np.minimum(where, len(keys) - 1)] != transposed):
        raise RuntimeError("working set is not symmetric")
    index = np.full(F * K, -1, dtype=np.int64)
    index[flat] = flat[order[where]]
    return index.reshape(F, K)


def _column_grams(shapes: np.ndarray, cand: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-column Gram matrices of B_f = candidate shapes - S_f, (F, K, K) zero-padded, and their largest
    eigenvalues (F,). Columns are batched by their number of entries: K is the largest column's, twice the mean on
    long captures, and a padded (F, K, D) gather plus (F, K, K) eigvalsh cost 7x more (F = 20,000: 1.08 -> 0.15 s)."""
    F, K = cand.shape
    counts = valid.sum(axis=1)
    slots = np.argsort(~valid, axis=1, kind="stable")  # each column's entries first
    gram = np.zeros((F, K, K))
    lam_max = np.zeros(F)
    for size in np.unique(counts[counts > 0]):
        cols = np.flatnonzero(counts == size)
        idx = slots[cols, :size]
        B = shapes[np.take_along_axis(cand[cols], idx, axis=1)] - shapes[cols][:, None, :]  # (n, size, D)
        block = np.matmul(B, B.transpose(0, 2, 1))
        gram[cols[:, None, None], idx[:, :, None], idx[:, None, :]] = block
        lam_max[cols] = np.linalg.eigvalsh(block)[:, -1]
    return gram, lam_max


class _WorkingSetProblem:
    """g restricted to a working set, with the per-column Gram matrices precomputed."""

    def __init__(self, shapes: np.ndarray, cand: np.ndarray, valid: np.ndarray, lambda1: float, num_points: int):
        F = len(shapes)
        self.cand, self.valid = cand, valid
        self.data_weight = 1.0 / (F * num_points)
        self.sym_weight = lambda1 / F
        self.transpose = _transpose_index(cand, valid)
        self.gram, lam_max = _column_grams(shapes, cand, valid)
        self.lipschitz = 2.0 * self.data_weight * np.maximum(lam_max, 0.0) + 8.0 * self.sym_weight
        self.lipschitz = np.maximum(self.lipschitz, 1e-300)

    def _transposed(self, V: np.ndarray) -> np.ndarray:
        flat = V.ravel()
        return np.where(self.valid, flat[np.maximum(self.transpose, 0)].reshape(V.shape), 0.0)

    def objective(self, V: np.ndarray) -> float:
        data = float(np.sum(V * np.matmul(self.gram, V[:, :, None])[:, :, 0]))
        asym = V - self._transposed(V)
        return float(self.data_weight * data + self.sym_weight * np.sum(asym * asym))

    def gradient(self, V: np.ndarray) -> np.ndarray:
        grad = 2.0 * self.data_weight * np.matmul(self.gram, V[:, :, None])[:, :, 0]
        grad += 4.0 * self.sym_weight * (V - self._transposed(V))
        return np.where(self.valid, grad, 0.0)

    def hessian(self) -> sp.csr_matrix:
        """H (n, n) over the flat entries f*K + k, with objective = 1/2 v^T H v."""
        F, K = self.cand.shape
        base = (np.arange(F) * K)[:, None, None]
        rows = np.broadcast_to(base + np.arange(K)[None, :, None], self.gram.shape)
        cols = np.broadcast_to(base + np.arange(K)[None, None, :], self.gram.shape)
        pair = self.valid[:, :, None] & self.valid[:, None, :]
        flat = np.flatnonzero(self.valid.ravel())
        partner = self.transpose.ravel()[flat]
        sym = 4.0 * self.sym_weight
        return sp.csr_matrix(
            (np.concatenate([2.0 * self.data_weight * self.gram[pair], np.full(len(flat), sym),
                             np.full(len(flat), -sym)]),
             (np.concatenate([rows[pair], flat, flat]), np.concatenate([cols[pair], flat, partner]))),
            shape=(F * K, F * K))

    def project(self, V: np.ndarray) -> np.ndarray:
        return project_rows_to_simplex(V, self.valid)


def _fista(problem: _WorkingSetProblem, V: np.ndarray, options: WStepOptions, stats: WStepStats) -> np.ndarray:
    step = 1.0 / problem.lipschitz[:, None]
    x = problem.project(V)
    y = x.copy()
    t = 1.0
    f_x = problem.objective(x)
    for _ in range(options.max_iterations):
        stats.iterations += 1
        x_new = problem.project(y - step * problem.gradient(y))
        f_new = problem.objective(x_new)
        if f_new > f_x:
            # Momentum overshot: restart from x with a plain projected-gradient step (monotone, O'Donoghue-Candes).
            y, t = x.copy(), 1.0
            continue
        change = float(np.max(np.abs(x_new - y)))
        t_new = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * t * t))
        y = x_new + ((t - 1.0) / t_new) * (x_new - x)
        x, f_x, t = x_new, f_new, t_new
        if change < options.tolerance:
            stats.converged = True
            break
    stats.objective = f_x
    return x


class _FreeSetSolver:
    """Equality-constrained QPs of g on a free set I (all other entries fixed at 0), one sparse KKT solve each:
    [[H_II + ridge, E^T], [E, 0]] [v_I; -mu] = [0; 1], E summing each column's free entries.

    Columns are coupled only by Psi1's partner entries (W_jf, W_fj both free), so the system splits into
    independent components of columns. A component whose columns all kept their free entries since the previous
    solve has the same system and keeps its solution: only components holding a changed column are re-solved. With
    windowed dictionaries the system has ~1000 components at F = 20,000 and late active-set iterations change a few
    of them; a dense dictionary gives one giant component (nothing saved, nothing lost)."""

    def __init__(self, problem: _WorkingSetProblem, workers: int = 1):
        F, K = problem.cand.shape
        self.F, self.K = F, K
        self.H = problem.hessian()
        self.H_coo = self.H.tocoo()
        self.ridge = 1e-12 * max(float(np.abs(self.H.diagonal()).max()), 1e-300)
        self.column_of = np.repeat(np.arange(F), K)
        self.valid = problem.valid.ravel()
        self.lipschitz = problem.lipschitz
        H = self.H_coo
        link = self.column_of[H.row] != self.column_of[H.col]  # partner entries of different columns
        self.link_rows, self.link_cols = H.row[link], H.col[link]
        self.last: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # (free, v, mu) of the previous solve
        self.workers = workers

    def _components(self, free: np.ndarray, last_free: np.ndarray) -> np.ndarray:
        """(F,) component label of every column. Links count when free before or now: a column whose partner
        left the free set was solved coupled to it and must be solved again."""
        both = (free[self.link_rows] & free[self.link_cols]) | (last_free[self.link_rows] & last_free[self.link_cols])
        a, b = self.column_of[self.link_rows[both]], self.column_of[self.link_cols[both]]
        graph = sp.csr_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(self.F, self.F))
        return connected_components(graph, directed=False)[1]

    def solve(self, free: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """(v (F*K,), mu (F,)) or None when the system is singular."""
        if self.last is None:
            last_free, changed = free, np.arange(self.F)
            v, mu = np.zeros(self.F * self.K), np.zeros(self.F)
        else:
            last_free, v, mu = self.last
            changed = np.unique(self.column_of[free != last_free])
            v, mu = v.copy(), mu.copy()
        if len(changed):
            label = self._components(free, last_free)
            redo = np.zeros(label.max() + 1, dtype=bool)
            redo[label[changed]] = True
            groups = self._groups(label, redo, free)
            if len(groups) > 1:
                with ThreadPoolExecutor(len(groups)) as pool:
                    parts = list(pool.map(lambda columns: self._solve_columns(free, columns), groups))
            else:
                parts = [self._solve_columns(free, groups[0])]
            for columns, solved in zip(groups, parts, strict=True):
                if solved is None:
                    return None
                entries = columns[self.column_of]
                v[entries] = solved[0][entries]
                mu[columns] = solved[1]
        self.last = (free.copy(), v, mu)
        return v, mu

    def _groups(self, label: np.ndarray, redo: np.ndarray, free: np.ndarray) -> list[np.ndarray]:
        """Column masks (F,) covering the components to re-solve: one, or `workers` of about equal size (free
        entries) when the system is large enough for threads to pay (SuperLU releases the GIL)."""
        columns = redo[label]
        size = np.bincount(label, weights=free.reshape(self.F, self.K).sum(axis=1), minlength=len(redo))
        size[~redo] = 0
        if self.workers < 2 or size.sum() < PARALLEL_KKT or np.count_nonzero(size) < 2:
            return [columns]
        load = np.zeros(self.workers)
        worker_of = np.zeros(len(size), dtype=np.int64)
        for component in np.argsort(-size)[:np.count_nonzero(size)]:  # largest first, to the least loaded
            worker_of[component] = np.argmin(load)
            load[worker_of[component]] += size[component]
        return [columns & (worker_of[label] == w) for w in range(self.workers) if load[w] > 0]

    def _solve_columns(self, free: np.ndarray, columns: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """The KKT system of the free entries of `columns` (F,) bool (closed under partner links)."""
        free = free & columns[self.column_of]
        idx = np.flatnonzero(free)
        m = len(idx)
        n_columns = int(columns.sum())
        # Assembled as one COO: slicing H and sp.bmat cost more than the sparse factorization itself.
        position = np.cumsum(free) - 1  # new index of every free entry
        constraint_of = np.cumsum(columns) - 1 + m  # row of each column's simplex constraint
        H = self.H_coo
        inside = free[H.row] & free[H.col]
        constraint_rows = constraint_of[self.column_of[idx]]
        kkt = sp.csc_matrix(
            (np.concatenate([H.data[inside], np.full(m, self.ridge), np.ones(m), np.ones(m)]),
             (np.concatenate([position[H.row[inside]], np.arange(m), constraint_rows, np.arange(m)]),
              np.concatenate([position[H.col[inside]], np.arange(m), np.arange(m), constraint_rows]))),
            shape=(m + n_columns, m + n_columns))
        rhs = np.concatenate([np.zeros(m), np.ones(n_columns)])
        try:
            solution = spla.spsolve(kkt, rhs)
        except RuntimeError:
            log.debug("active set: singular KKT system")
            return None
        if not np.all(np.isfinite(solution)):
            log.debug("active set: singular KKT system")
            return None
        v = np.zeros(self.F * self.K)
        v[idx] = solution[:m]
        return v, -solution[m:]

    def violation(self, v: np.ndarray, mu: np.ndarray) -> np.ndarray:
        """(F*K,) how far each entry's gradient lies below its column's multiplier, in W units (/ L_f)."""
        return (mu[self.column_of] - self.H @ v) / self.lipschitz[self.column_of]

    def ensure_nonempty_columns(self, free: np.ndarray, v: np.ndarray) -> None:
        """Every column needs one free entry: give an empty one its lowest-gradient entry."""
        empty = np.bincount(self.column_of[free], minlength=self.F) == 0
        if empty.any():
            g = np.where(self.valid, self.H @ v, np.inf).reshape(self.F, self.K)
            free.reshape(self.F, self.K)[empty, np.argmin(g[empty], axis=1)] = True


def _active_set(
    problem: _WorkingSetProblem, V: np.ndarray, options: WStepOptions, stats: WStepStats
) -> np.ndarray | None:
    """Exact minimizer on the working set by a primal-dual active-set method (Hintermueller, Ito, Kunisch 2002).

    Each iteration solves the equality-constrained QP on a free set I, which also gives each column's simplex
    multiplier mu_f. The next free set keeps the entries that came out positive and adds those outside I whose
    gradient lies below their column's multiplier. When the set repeats, the solution is non-negative and satisfies
    KKT: it is the exact minimizer. PDAS is fast but not monotone and can cycle on nearly degenerate entries (a
    handful of entries flipping in and out, measured on CMU F = 2000); a repeated set hands the best iterate seen so
    far to the monotone primal active-set method, which cannot cycle; so does a PDAS that has not settled within its
    budget. Returns None only when a KKT system is singular (the caller then falls back to FISTA).
    """
    F, K = V.shape
    solver = _FreeSetSolver(problem, options.workers)
    valid = solver.valid
    # Dust left by the previous solve (values below NEGLIGIBLE) is not support: starting with it free costs a
    # whole extra KKT solve to drop it again.
    best = problem.project(V)
    best_objective = start_objective = problem.objective(best)
    free = (best.ravel() > NEGLIGIBLE) & valid
    seen: set[bytes] = set()
    stalled = 0
    changes = np.zeros(F, dtype=np.int64)  # active-set iterations that changed each column's free entries
    for _ in range(options.max_active_set_iterations):
        stats.iterations += 1
        solved = solver.solve(free)
        if solved is None:
            return None
        v, mu = solved
        violation = solver.violation(v, mu)
        entering = valid & ~free & (violation > options.tolerance)
        if not entering.any() and v[free].min() > -NEGLIGIBLE:
            return _finish(problem, v, stats)
        projected = problem.project(v.reshape(F, K))
        objective = problem.objective(projected)
        # Stalling counts only once PDAS has beaten the start: its first iterates are often worse than a warm start.
        if objective < best_objective * (1.0 - options.stall_tolerance):
            stalled = 0
        elif best_objective < start_objective:
            stalled += 1
        if objective < best_objective:
            best, best_objective = projected, objective
        if stalled >= options.stall_iterations:
            log.debug("active set: PDAS stalled after %d iterations; keeping the best iterate", len(seen))
            stats.objective = best_objective
            stats.converged = False  # a previous round's exact solve does not make this one exact
            return best
        # Round-off makes degenerate entries (optimal value 0, gradient = multiplier) flip sign from one solve to
        # the next; treat |v| below NEGLIGIBLE as zero.
        proposal = (free & (v > NEGLIGIBLE)) | entering
        proposal = _limit_changes(free, proposal, v, violation, changes >= options.cycle_changes, F, K)
        changes += (proposal != free).reshape(F, K).any(axis=1)
        free = proposal
        key = np.packbits(free).tobytes()
        if key in seen:
            log.debug("active set: PDAS cycles after %d iterations; primal active set from the best iterate",
                      len(seen))
            return _primal_active_set(problem, solver, best, options, stats)
        seen.add(key)
        solver.ensure_nonempty_columns(free, v)
    log.debug("active set: PDAS has not settled in %d iterations; primal active set from the best iterate",
              options.max_active_set_iterations)
    return _primal_active_set(problem, solver, best, options, stats)


def _limit_changes(free: np.ndarray, proposal: np.ndarray, v: np.ndarray, violation: np.ndarray,
                   restricted: np.ndarray, F: int, K: int) -> np.ndarray:
    """The proposed free set (flat F*K), with one change per `restricted` column (F,): its most negative entry
    leaves, else its most violating entry enters. PDAS swaps whole sets and can wander for dozens of iterations on
    columns with nearly degenerate entries; single changes there (Murty's rule) settle them like the primal method
    does, while the other columns keep PDAS's fast steps."""
    if not restricted.any():
        return proposal
    leaving = (free & ~proposal).reshape(F, K)
    entering = (proposal & ~free).reshape(F, K)
    rows = np.flatnonzero(restricted & (leaving.any(axis=1) | entering.any(axis=1)))
    out = proposal.reshape(F, K).copy()
    out[rows] = free.reshape(F, K)[rows]
    worst = np.argmin(np.where(leaving[rows], v.reshape(F, K)[rows], np.inf), axis=1)
    best = np.argmax(np.where(entering[rows], violation.reshape(F, K)[rows], -np.inf), axis=1)
    removes = leaving[rows].any(axis=1)
    out[rows[removes], worst[removes]] = False
    out[rows[~removes], best[~removes]] = True
    return out.ravel()


def _primal_active_set(
    problem: _WorkingSetProblem, solver: _FreeSetSolver, start: np.ndarray, options: WStepOptions,
    stats: WStepStats,
) -> np.ndarray:
    """Primal active-set method (Nocedal & Wright, Alg. 16.3) from a feasible start: every step solves the QP on
    the free set and moves toward its solution only as far as the simplex allows, so g never increases and no free
    set repeats. Entries at zero whose QP value is negative leave the set; when the QP solution is feasible, the
    entries that violate KKT most (one per column) join it. Near a degenerate optimum most steps remove one entry,
    so after `max_primal_iterations` the feasible iterate reached is returned (never worse than `start`)."""
    F, K = start.shape
    x = start.ravel().copy()
    free = (x > 0) & solver.valid
    for _ in range(options.max_primal_iterations):
        stats.iterations += 1
        solved = solver.solve(free)
        if solved is None:
            break
        v, mu = solved
        blocking = free & (v < -NEGLIGIBLE)
        if not blocking.any():
            x = np.where(free, np.maximum(v, 0.0), 0.0)
            violation = solver.violation(v, mu)
            entering = solver.valid & ~free & (violation > options.tolerance)
            if not entering.any():
                return _finish(problem, v, stats)
            free |= _most_violating_per_column(entering, violation, F, K)
            continue
        # Entries already at zero that the QP wants negative leave without a step; the others block the step.
        at_zero = blocking & (x <= NEGLIGIBLE)
        if at_zero.any():
            free &= ~at_zero
            x[at_zero] = 0.0
            continue
        x = x + float(np.min(x[blocking] / (x[blocking] - v[blocking]))) * (v - x)
        hit = blocking & (x <= NEGLIGIBLE)
        x[hit] = 0.0
        free &= ~hit
    return _finish(problem, x, stats, converged=False)


def _finish(problem: _WorkingSetProblem, v: np.ndarray, stats: WStepStats, *, converged: bool = True) -> np.ndarray:
    """The flat iterate v (F*K,) as W values on the simplices, its objective recorded."""
    F, K = problem.cand.shape
    stats.converged = converged
    V_out = np.maximum(v, 0.0).reshape(F, K)
    V_out /= V_out.sum(axis=1, keepdims=True)
    stats.objective = problem.objective(V_out)
    return V_out


def _most_violating_per_column(entering: np.ndarray, violation: np.ndarray, F: int, K: int) -> np.ndarray:
    """Keep, in each column, only the entering entry (flat mask over F*K) with the largest violation."""
    scores = np.where(entering, violation, -np.inf).reshape(F, K)
    best = np.argmax(scores, axis=1)
    kept = np.zeros((F, K), dtype=bool)
    has = np.isfinite(scores[np.arange(F), best])
    kept[np.flatnonzero(has), best[has]] = True
    return kept.ravel()


def kkt_violations(
    shapes: np.ndarray, video_index: np.ndarray, W: SparseW, problem: _WorkingSetProblem, options: WStepOptions,
    *, block: int = 1024, pool: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Allowed entries (rows j, columns f) outside the working set whose gradient lies below the column's simplex
    multiplier by more than kkt_tolerance * L_f: moving weight onto them would lower g. With a candidate `pool`
    (F, C) only the pool's entries are allowed (long captures)."""
    F = len(shapes)
    grad = problem.gradient(W.value)
    mu = np.where(W.valid, grad, np.inf).min(axis=1)  # (F,) multiplier: min gradient over the column's entries
    # (F, D): S W_f - S_f, as a sparse product (gathering shapes[W.cand], (F, K, D), took 0.2 s at F = 20,000)
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
    k = min(options.max_added_per_column, F - 1)
    found_rows: list[np.ndarray] = []
    found_cols: list[np.ndarray] = []
    found_inner: list[np.ndarray] = []
    for members, lo, hi in groups:
        for start in range(0, len(members), block):
            cols = members[start:start + block]
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
    shapes: np.ndarray, W: SparseW, problem: _WorkingSetProblem, options: WStepOptions, mu: np.ndarray,
    residual: np.ndarray, pool: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    F, C = pool.shape
    inner = local_inner(residual, shapes, pool)
    g = 2.0 * problem.data_weight * (inner - np.einsum("fd,fd->f", residual, shapes)[:, None])
    violation = (mu[:, None] - g) / problem.lipschitz[:, None]
    violation[pool < 0] = -np.inf
    in_set = np.zeros_like(violation, dtype=bool)
    for k in range(W.cand.shape[1]):  # pool entries already in the working set
        in_set |= (pool == W.cand[:, k:k + 1]) & W.valid[:, k:k + 1]
    violation[in_set] = -np.inf
    k = min(options.max_added_per_column, C)
    top = np.argpartition(-violation, k - 1, axis=1)[:, :k]
    chosen = np.take_along_axis(violation, top, axis=1) > options.kkt_tolerance
    return np.take_along_axis(pool, top, axis=1)[chosen], np.broadcast_to(np.arange(F)[:, None], top.shape)[chosen]


def solve_w(
    shapes: np.ndarray, video_index: np.ndarray, num_points: int, options: WStepOptions,
    previous: SparseW | None = None, pool: np.ndarray | None = None,
) -> tuple[SparseW, WStepStats]:
    """Solve the W-step for shapes (F, 3P), warm-started from `previous`. With a candidate `pool` (F, C) of frame
    indices (-1 = none; reconstruct/candidates.py) W is restricted to it: cost O(F C) instead of O(F^2)."""
    F = len(shapes)
    stats = WStepStats()
    if pool is None:
        near = nearest_other_video(shapes, video_index, options.nearest)
    else:
        near = nearest_in_pool(shapes, pool, options.nearest)
    near_cols = np.repeat(np.arange(F), near.shape[1])
    # fewer other-video frames than `nearest`, or a short pool
    other = (near.ravel() >= 0) & (video_index[near.ravel()] != video_index[near_cols])
    seed_rows, seed_cols = _limit_seeds_per_frame(near.ravel()[other], near_cols[other],
                                                  np.tile(np.arange(near.shape[1]), F)[other], 3 * options.nearest)
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
        problem = _WorkingSetProblem(shapes, cand, valid, options.lambda1, num_points)
        V = _start_values(cand, valid, V_start, near)
        exact = _active_set(problem, V, options, stats)
        if exact is None:
            log.debug("active-set W-step did not finish; falling back to FISTA")
            stats.fallbacks += 1
            exact = _fista(problem, V, options, stats)
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


def _limit_seeds_per_frame(rows: np.ndarray, cols: np.ndarray, rank: np.ndarray, limit: int
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Keep at most `limit` seed pairs (row j, column f) per frame j, those where j ranks nearest for f. The working
    set is symmetrized, so a frame that is the nearest of thousands of frames would get a column of thousands of
    entries, and the per-column Gram matrices (F, K, K) are padded to the largest column: measured on a
    20,000-frame capture, the last frame of a video, where out-of-range anchors were clipped, was a seed of 255
    columns (K = 258, > 12 GB)."""
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
        where = np.clip(np.searchsorted(old_keys, new_keys), 0, len(old_keys) - 1)
        hit = valid & (old_keys[where] == new_keys)
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
