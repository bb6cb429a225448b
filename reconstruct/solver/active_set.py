"""The W-step's problem restricted to a working set of entries, and its exact solvers.

g restricted to the working set is a QP over per-column simplices whose Hessian is block-diagonal over columns
(the per-column Gram matrices of the data term) plus Psi1's links between partner entries W_jf and W_fj. It is
solved exactly by a primal-dual active-set method, each iteration one sparse solve of the equality-constrained QP
in its null space (only the components of columns whose free entries changed), with Murty's single changes for
columns that keep changing, a monotone primal active-set method when PDAS cycles, and FISTA only for a singular
system. See docs/solver.md ("W-step").
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import connected_components

from reconstruct.solver.simplex import project_rows_to_simplex
from reconstruct.solver.wstep_options import WStepOptions, WStepStats

log = logging.getLogger(__name__)

FISTA_MAX_ITERATIONS = 2000  # budget of the FISTA fallback
# PDAS stalls when `WStepOptions.stall_iterations` iterations in a row lowered g by less than this share.
STALL_TOLERANCE = 1e-4

NEGLIGIBLE = 1e-9  # W entries this close to zero are zero (W values lie in [0, 1])
WHOLE_SHARE = 0.9  # share of the columns re-solved at once from which FreeSetSolver stops looking for components
PARALLEL_GRAMS = 200_000  # Gram entries from which column_grams splits the columns over threads
PARALLEL_KKT = 20_000  # free entries to re-solve at and above which independent components are split over threads


def find_sorted(sorted_keys: np.ndarray, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(where, found), shaped like `keys`: each key's position in the ascending `sorted_keys` (clipped to a valid
    index) and whether it is there."""
    if len(sorted_keys) == 0:
        return np.zeros(keys.shape, dtype=np.int64), np.zeros(keys.shape, dtype=bool)
    where = np.minimum(np.searchsorted(sorted_keys, keys), len(sorted_keys) - 1)
    return where, sorted_keys[where] == keys


def transpose_index(cand: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Flat index of the entry (f, j) for every valid entry (j, f); the set must be symmetric. (F, K), -1 padding."""
    F, K = cand.shape
    flat = np.flatnonzero(valid.ravel())
    cols = flat // K
    keys = cols * F + cand.ravel()[flat]
    order = np.argsort(keys)
    sorted_keys = keys[order]
    transposed = cand.ravel()[flat] * F + cols
    where, found = find_sorted(sorted_keys, transposed)
    if not found.all():
        raise RuntimeError("working set is not symmetric")
    index = np.full(F * K, -1, dtype=np.int64)
    index[flat] = flat[order[where]]
    return index.reshape(F, K)


def column_grams(
    shapes: np.ndarray, cand: np.ndarray, valid: np.ndarray, workers: int = 1
) -> tuple[sp.csr_matrix, np.ndarray]:
    """The per-column Gram matrices of B_f = candidate shapes - S_f as one block-diagonal sparse matrix G (F K, F K)
    over the flat entries f * K + k, and each block's largest eigenvalue (F,). The working set must be packed, each
    column's entries in its first slots (wstep._pack_pairs makes it so).

    Columns are batched by their number of entries, and G holds only the blocks: K is the largest column's, twice
    the mean on long captures, so a padded (F, K, K) array held several times the entries and every product with
    it, the Hessian's assembly included, paid for the padding. From PARALLEL_GRAMS entries on, `workers` threads
    take a share of the columns each (the batched products and eigenvalues release the GIL), with the same blocks to
    the bit."""
    F, K = cand.shape
    counts = valid.sum(axis=1)
    if not np.array_equal(valid, np.arange(K)[None, :] < counts[:, None]):
        raise ValueError("the working set is not packed: each column's entries must fill its first slots")
    squares = counts * counts
    offset = np.r_[0, np.cumsum(squares)]  # where each column's block starts, row-major, in G's entries
    index_type = np.int32 if F * K < 2**31 and offset[-1] < 2**31 else np.int64
    data = np.empty(int(offset[-1]))
    # Row f K + i (i < k_f) holds k_f entries, at the columns f K + j: G's entries in CSR order are the blocks,
    # column after column, each row-major.
    indices = np.empty(len(data), dtype=index_type)
    lam_max = np.zeros(F)

    def fill(columns: np.ndarray) -> None:
        sizes = counts[columns]
        for size in np.unique(sizes):
            cols = columns[sizes == size]
            B = shapes[cand[cols, :size]] - shapes[cols][:, None, :]  # (n, size, D)
            block = np.matmul(B, B.transpose(0, 2, 1))
            at = offset[cols][:, None] + np.arange(size * size)
            data[at] = block.reshape(len(cols), -1)
            indices[at] = (cols * K)[:, None] + np.tile(np.arange(size), size)
            # B B^T and B^T B share their nonzero eigenvalues: with few points (3P < size) the small one is far cheaper
            small = np.matmul(B.transpose(0, 2, 1), B) if B.shape[2] < size else block
            lam_max[cols] = np.linalg.eigvalsh(small)[:, -1]

    nonempty = np.flatnonzero(counts > 0)
    if workers > 1 and len(data) >= PARALLEL_GRAMS:
        with ThreadPoolExecutor(workers) as pool:
            list(pool.map(fill, np.array_split(nonempty, workers)))
    else:
        fill(nonempty)
    row_length = np.where(valid, counts[:, None], 0).ravel()
    indptr = np.r_[0, np.cumsum(row_length)].astype(index_type)
    gram = sp.csr_matrix((data, indices, indptr), shape=(F * K, F * K))
    return gram, lam_max


class WorkingSetProblem:
    """g restricted to a working set, with the per-column Gram matrices precomputed."""

    def __init__(
        self, shapes: np.ndarray, cand: np.ndarray, valid: np.ndarray, lambda1: float, num_points: int, workers: int = 1
    ):
        F = len(shapes)
        self.cand, self.valid = cand, valid
        self.data_weight = 1.0 / (F * num_points)
        self.sym_weight = lambda1 / F
        self.transpose = transpose_index(cand, valid)
        self.gram, lam_max = column_grams(shapes, cand, valid, workers)
        self.lipschitz = 2.0 * self.data_weight * np.maximum(lam_max, 0.0) + 8.0 * self.sym_weight
        self.lipschitz = np.maximum(self.lipschitz, 1e-300)

    def _transposed(self, V: np.ndarray) -> np.ndarray:
        flat = V.ravel()
        return np.where(self.valid, flat[np.maximum(self.transpose, 0)].reshape(V.shape), 0.0)

    def objective(self, V: np.ndarray) -> float:
        v = V.ravel()
        # einsum, not v @ ...: a BLAS dot product of this length starts OpenBLAS's threads, whose spinning then
        # slowed the KKT component threads.
        data = float(np.einsum("i,i->", v, self.gram @ v))
        asym = V - self._transposed(V)
        return float(self.data_weight * data + self.sym_weight * np.sum(asym * asym))

    def gradient(self, V: np.ndarray) -> np.ndarray:
        grad = 2.0 * self.data_weight * (self.gram @ V.ravel()).reshape(V.shape)
        grad += 4.0 * self.sym_weight * (V - self._transposed(V))
        return np.where(self.valid, grad, 0.0)

    def hessian(self) -> sp.csr_matrix:
        """H (n, n) over the flat entries f*K + k, with objective = 1/2 v^T H v."""
        n = self.valid.size
        flat = np.flatnonzero(self.valid.ravel())
        partner = self.transpose.ravel()[flat]
        sym = 4.0 * self.sym_weight
        # Psi1: sym on the diagonal, -sym between partners
        psi1 = sp.csr_matrix(
            (np.r_[np.full(len(flat), sym), np.full(len(flat), -sym)], (np.r_[flat, flat], np.r_[flat, partner])),
            shape=(n, n),
        )
        return sp.csr_matrix(2.0 * self.data_weight * self.gram + psi1)

    def project(self, V: np.ndarray) -> np.ndarray:
        """V (F, K) projected onto the columns' simplices. Only columns off the simplex are projected: an active-set
        iterate has a few columns with negative entries, and projecting all of them costs every iteration."""
        out = np.where(self.valid, V, 0.0)
        off = np.flatnonzero((out < 0).any(axis=1) | (np.abs(out.sum(axis=1) - 1.0) > 1e-12))
        if len(off):
            out[off] = project_rows_to_simplex(V[off], self.valid[off])
        return out


def fista(problem: WorkingSetProblem, V: np.ndarray, options: WStepOptions, stats: WStepStats) -> np.ndarray:
    step = 1.0 / problem.lipschitz[:, None]
    x = problem.project(V)
    y = x.copy()
    t = 1.0
    f_x = problem.objective(x)
    for _ in range(FISTA_MAX_ITERATIONS):
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


class FreeSetSolver:
    """Equality-constrained QPs of g on a free set I (all other entries fixed at 0), one sparse solve each: the
    minimizer of 1/2 v_I^T (H_II + ridge) v_I with each column's free entries summing to 1, and each column's
    multiplier mu_f (the common gradient of its free entries).

    Columns are coupled only by Psi1's partner entries (W_jf, W_fj both free), so the system splits into
    independent components of columns. A component whose columns all kept their free entries since the previous
    solve has the same system and keeps its solution: only components holding a changed column are re-solved. With
    windowed dictionaries the system has many components on long captures and late active-set iterations change a
    few of them; a dense dictionary gives one giant component (nothing saved, nothing lost)."""

    def __init__(self, problem: WorkingSetProblem, workers: int = 1):
        F, K = problem.cand.shape
        self.F, self.K = F, K
        self.H = problem.hessian()
        ridge = 1e-12 * max(float(np.abs(self.H.diagonal()).max()), 1e-300)
        self.H_ridge = sp.csr_matrix(self.H + sp.diags(np.where(problem.valid.ravel(), ridge, 0.0)))
        self.column_of = np.repeat(np.arange(F), K)
        self.valid = problem.valid.ravel()
        self.lipschitz = problem.lipschitz
        self.entry_lipschitz = self.lipschitz[self.column_of]  # (F*K,) each entry's column's L_f
        self.partner = problem.transpose.ravel()  # flat index of each entry's Psi1 partner, -1 for padding
        # The links between columns are H's Psi1 entries (W_jf, W_fj): every valid entry and its partner, which lies
        # in another column (j != f), read off the transpose index rather than filtered out of H's COO form.
        self.link_rows = np.flatnonzero(self.valid)
        self.link_cols = self.partner[self.link_rows]
        self.link_columns = (self.column_of[self.link_rows], self.column_of[self.link_cols])  # the columns linked
        self.last: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # (free, v, mu) of the previous solve
        self.workers = workers
        # Once a re-solve covers nearly every column (one giant component: dense dictionaries), the rest of the
        # active-set run re-solves everything without looking for components. Re-solving an unchanged component
        # only repeats its solution, and the search is a sizeable share of such a solve.
        self.whole = False

    def _components(self, free: np.ndarray, last_free: np.ndarray) -> np.ndarray:
        """(F,) component label of every column. Links count when free before or now: a column whose partner
        left the free set was solved coupled to it and must be solved again."""
        both = (free[self.link_rows] & free[self.link_cols]) | (last_free[self.link_rows] & last_free[self.link_cols])
        a, b = self.link_columns[0][both], self.link_columns[1][both]
        graph = sp.csr_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(self.F, self.F))
        return connected_components(graph, directed=False)[1]

    def solve(self, free: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """(v (F*K,), mu (F,)) or None when the system is singular."""
        if self.last is None:
            last_free, changed = free, np.arange(self.F)
            v, mu = np.zeros(self.F * self.K), np.zeros(self.F)
        else:
            last_free, v, mu = self.last
            changed = np.flatnonzero((free != last_free).reshape(self.F, self.K).any(axis=1))
            v, mu = v.copy(), mu.copy()
        if len(changed):
            if self.whole:
                groups = [np.ones(self.F, dtype=bool)]
            else:
                label = self._components(free, last_free)
                redo = np.zeros(label.max() + 1, dtype=bool)
                redo[label[changed]] = True
                groups = self._groups(label, redo, free)
                # A first solve re-solves every column whatever its components: it says nothing.
                self.whole = self.last is not None and len(groups) == 1 and groups[0].sum() >= WHOLE_SHARE * self.F
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
        for component in np.argsort(-size)[: np.count_nonzero(size)]:  # largest first, to the least loaded
            worker_of[component] = np.argmin(load)
            load[worker_of[component]] += size[component]
        return [columns & (worker_of[label] == w) for w in range(self.workers) if load[w] > 0]

    def _solve_columns(self, free: np.ndarray, columns: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """The QP on the free entries of `columns` (F,) bool (closed under partner links), in its null space: each
        column's simplex equality is eliminated through one pivot entry, v_p = 1 - (sum of the column's other free
        entries), leaving the symmetric positive definite reduced Hessian Z^T H Z. Its LU without pivoting (SuperLU,
        symmetric mode, minimum degree on A^T + A) is a Cholesky in all but name; the KKT system [[H, E^T], [E, 0]]
        it replaces has zero diagonal entries that force SuperLU's partial pivoting, and has about twice the unknowns
        and several times the factor entries, for the same iterates. Reusing one minimum-degree order across a
        W-step's systems gave more fill. The systems have almost no fill, so SuperLU's panels of 10 columns, meant
        for wide supernodes, only cost: single-column panels factorize faster, with the same iterates.

        The pivot is a column's first free entry whose partner is not free, when it has one: eliminating an entry
        spreads its Psi1 link over the whole column, so such pivots keep the reduced system as sparse as H."""
        free = free & columns[self.column_of]
        idx = np.flatnonzero(free)  # flat f * K + k: grouped by column, in column order
        n = len(idx)
        column = self.column_of[idx]
        first = np.r_[True, column[1:] != column[:-1]] if n else np.zeros(0, dtype=bool)  # of its column
        starts = np.flatnonzero(first)
        if len(starts) != int(columns.sum()):  # a column without free entries: its simplex cannot be met
            log.debug("active set: a column has no free entry")
            return None
        partner = self.partner[idx]
        linked = (partner >= 0) & free[np.maximum(partner, 0)]
        pivot_at = np.minimum.reduceat(np.where(linked, n, np.arange(n)), starts)
        pivot_at = np.where(pivot_at < n, pivot_at, starts)  # every entry linked: the column's first
        group = np.cumsum(first) - 1
        is_pivot = np.zeros(n, dtype=bool)
        is_pivot[pivot_at] = True
        others = np.flatnonzero(~is_pivot)
        m = len(others)
        # v = v0 + Z z: non-pivot entries are the unknowns z, a pivot is 1 minus its column's unknowns. Z^T H Z
        # is formed from H's rows of the free entries times Z with a row for every working-set entry (zero off the
        # free set): no copy of H's free block, whose assembly cost as much as the factorization.
        z_rows, z_cols = np.r_[others, pivot_at[group[others]]], np.r_[np.arange(m), np.arange(m)]
        z_values = np.r_[np.ones(m), -np.ones(m)]
        Z_free = sp.csr_matrix((z_values, (z_rows, z_cols)), shape=(n, m))
        Z_all = sp.csr_matrix((z_values, (idx[z_rows], z_cols)), shape=(self.F * self.K, m))
        H_rows = self.H_ridge[idx]  # (n, F K)
        v = np.zeros(self.F * self.K)
        v[idx[pivot_at]] = 1.0
        if m:
            reduced = sp.csc_matrix(Z_free.T @ (H_rows @ Z_all))
            rhs = -(Z_free.T @ (H_rows @ v))
            try:
                factor = spla.splu(
                    reduced,
                    permc_spec="MMD_AT_PLUS_A",
                    diag_pivot_thresh=0.0,
                    panel_size=1,
                    options={"SymmetricMode": True},
                )
            except RuntimeError:
                log.debug("active set: singular reduced system")
                return None
            z = factor.solve(rhs)
            z += factor.solve(rhs - reduced @ z)  # one step of iterative refinement: the system's condition
            # number reaches 1e8 on near-duplicate shapes
            if not np.all(np.isfinite(z)):
                log.debug("active set: singular reduced system")
                return None
            v += Z_all @ z
        # At the QP's solution every free entry of a column has the same gradient: the column's multiplier.
        mu = np.add.reduceat(H_rows @ v, starts) / np.diff(np.r_[starts, n])
        return v, mu

    def violation(self, v: np.ndarray, mu: np.ndarray, hv: np.ndarray | None = None) -> np.ndarray:
        """(F*K,) how far each entry's gradient lies below its column's multiplier, in W units (/ L_f); `hv`:
        H v when the caller has it."""
        return (mu[self.column_of] - (self.H @ v if hv is None else hv)) / self.entry_lipschitz

    def projected_objective(self, v: np.ndarray, hv: np.ndarray, projected: np.ndarray) -> float:
        """g = 1/2 p^T H p of p = `projected` (F, K), from v (F*K,) and H v: p differs from v only in the few
        columns the projection moved (an active-set iterate's columns with negative entries), so this needs H's
        rows of those entries only, not a product over all of H (a full product every iteration)."""
        delta = projected.ravel() - v
        moved = np.flatnonzero(delta)
        value = 0.5 * float(np.einsum("i,i->", v, hv))
        if len(moved):
            step = delta[moved]
            value += float(np.einsum("i,i->", step, hv[moved]))
            value += 0.5 * float(np.einsum("i,i->", step, (self.H[moved] @ delta)))
        return value

    def ensure_nonempty_columns(self, free: np.ndarray, v: np.ndarray) -> None:
        """Every column needs one free entry: give an empty one its lowest-gradient entry."""
        empty = np.bincount(self.column_of[free], minlength=self.F) == 0
        if empty.any():
            g = np.where(self.valid, self.H @ v, np.inf).reshape(self.F, self.K)
            free.reshape(self.F, self.K)[empty, np.argmin(g[empty], axis=1)] = True


def active_set(
    problem: WorkingSetProblem, V: np.ndarray, options: WStepOptions, stats: WStepStats
) -> np.ndarray | None:
    """Exact minimizer on the working set by a primal-dual active-set method (Hintermueller, Ito, Kunisch 2002).

    Each iteration solves the equality-constrained QP on a free set I, which also gives each column's simplex
    multiplier mu_f. The next free set keeps the entries that came out positive and adds those outside I whose
    gradient lies below their column's multiplier. When the set repeats, the solution is non-negative and satisfies
    KKT: it is the exact minimizer. PDAS is fast but not monotone and can cycle on nearly degenerate entries (a
    handful of entries flipping in and out); a repeated set hands the best iterate seen so
    far to the monotone primal active-set method, which cannot cycle; so does a PDAS that has not settled within its
    budget. Returns None only when a free-set system is singular (the caller then falls back to FISTA).
    """
    F, K = V.shape
    solver = FreeSetSolver(problem, options.workers)
    valid = solver.valid
    # Dust left by the previous solve (values below NEGLIGIBLE) is not support: starting with it free costs a
    # whole extra sparse solve to drop it again.
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
        hv = solver.H @ v
        violation = solver.violation(v, mu, hv)
        entering = valid & ~free & (violation > options.tolerance)
        if not entering.any() and v[free].min() > -NEGLIGIBLE:
            return _finish(problem, v, stats)
        projected = problem.project(v.reshape(F, K))
        objective = solver.projected_objective(v, hv, projected)
        # Stalling counts only once PDAS has beaten the start: its first iterates are often worse than a warm start.
        if objective < best_objective * (1.0 - STALL_TOLERANCE):
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
        proposal = limit_changes(free, proposal, v, violation, changes >= options.cycle_changes, F, K)
        changes += (proposal != free).reshape(F, K).any(axis=1)
        free = proposal
        key = np.packbits(free).tobytes()
        if key in seen:
            log.debug("active set: PDAS cycles after %d iterations; primal active set from the best iterate", len(seen))
            return primal_active_set(problem, solver, best, options, stats)
        seen.add(key)
        solver.ensure_nonempty_columns(free, v)
    log.debug(
        "active set: PDAS has not settled in %d iterations; primal active set from the best iterate",
        options.max_active_set_iterations,
    )
    return primal_active_set(problem, solver, best, options, stats)


def limit_changes(
    free: np.ndarray, proposal: np.ndarray, v: np.ndarray, violation: np.ndarray, restricted: np.ndarray, F: int, K: int
) -> np.ndarray:
    """The proposed free set (flat F*K), with one change per `restricted` column (F,): its most negative entry
    leaves, else its most violating entry enters. PDAS swaps whole sets and can wander for dozens of iterations on
    columns with nearly degenerate entries; single changes there (Murty's rule) settle them like the primal method
    does, while the other columns keep PDAS's fast steps."""
    if not restricted.any():
        return proposal
    leaving = (free & ~proposal).reshape(F, K)
    entering = proposal & ~free
    rows = np.flatnonzero(restricted & (leaving.any(axis=1) | entering.reshape(F, K).any(axis=1)))
    out = proposal.reshape(F, K).copy()
    out[rows] = free.reshape(F, K)[rows]
    worst = np.argmin(np.where(leaving[rows], v.reshape(F, K)[rows], np.inf), axis=1)
    removes = leaving[rows].any(axis=1)
    out[rows[removes], worst[removes]] = False
    adds = rows[~removes]
    out[adds] |= _most_violating_per_column(entering, violation, F, K).reshape(F, K)[adds]
    return out.ravel()


def primal_active_set(
    problem: WorkingSetProblem,
    solver: FreeSetSolver,
    start: np.ndarray,
    options: WStepOptions,
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


def _finish(problem: WorkingSetProblem, v: np.ndarray, stats: WStepStats, *, converged: bool = True) -> np.ndarray:
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
