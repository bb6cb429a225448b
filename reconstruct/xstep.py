"""The X-step: minimize over the 3D points, with W fixed,

    1/(F P) ||S^T (I - W)||_F^2 + lambda2/M Psi2 + [soft rays] lambda3/(F P) sum_observed ||(I - r r^T)(Y - C)||^2

Points decouple: for point p with positions Y_p (F, 3) the cost is sum_fg Q_fg <Y_pf, Y_pg> (+ ray terms) with
Q = 1/(FP) (I - W)(I - W)^T + lambda2/M L, L the Laplacian of consecutive frames of one video (M links). Each
point is one sparse symmetric linear system:
* hard rays: an observed Y_pf = C_f + d r_f has one unknown d; a missing one has three free coordinates;
* soft rays: every Y_pf is free, observed ones are pulled to their ray by lambda3/(FP) (I - r r^T).
The soft weight carries the same 1/(FP) as the data term, so lambda3 is the weight of a squared ray distance
relative to a squared self-expression residual of one point.

How it is solved. The soft ray weight is ~50x the diagonal of Q, so moving a point across its ray is stiff and
moving it along its ray is governed by Q alone. The slow modes of a plain (block-Jacobi) conjugate gradient are
along-ray motions that Q barely penalizes: frames linked by W whose rays are nearly parallel (opposite cameras), and
longer chains of them (eigenvectors of the preconditioned system live on 2 frames), so its iterations grew with F
(226 in the first final-stage X-step of a 2000-frame solve). Per point, the *weak subspace* J_p (one column r_f per
observed frame, three free coordinates per missing frame; exactly the unknowns of the hard-ray system) has the matrix
S_p = J_p^T (Q x I3) J_p, which has the sparsity of Q: a sparse LU with a minimum-degree ordering has almost no fill
(nnz(LU) ~ 1.6 nnz(Q) on captures of 700 ... 20,000 frames), so it costs O(F) per point. Then
* hard rays: the system *is* S_p z = J_p^T b: one direct solve per point;
* soft rays: M_p^-1 = J_p S_p^-1 J_p^T + (block Jacobi on the stiff across-ray directions) is an additive two-level
  preconditioner whose conjugate gradient converges in 2-8 iterations, independent of F.
A factorization costs as much as 20-50 Jacobi iterations of its point, and late in a solve the warm start is nearly
exact (2-20 Jacobi iterations), so every X-step starts with a cheap CG and factors only the points whose
convergence rate predicts many more iterations (`XStepOptions.factor_threshold`). That first CG's preconditioner is
block Jacobi plus the exact 2x2 along-ray block of each pair of frames that are each other's strongest link in Q
(the commonest slow mode: two frames expressing each other from opposite cameras); with it the recorded solves
(F = 700 ... 5000) needed at most 30 iterations and no factorization. Measurements: benchmarks/xstep_speed.py.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla


class RayConstraint(enum.Enum):
    HARD = "hard"
    SOFT = "soft"


@dataclass(kw_only=True)
class XStepOptions:
    lambda2: float = 0.1
    lambda3: float = 100.0
    constraint: RayConstraint = RayConstraint.SOFT
    # Relative residual of the batched conjugate-gradient solve. The alternation does not need exact X-steps: on a
    # 1000-frame capture 1e-8 took 2x less X-step time than 1e-10 for the same accuracy (99.67 %), and HDM05 / walk
    # were unchanged (benchmarks in docs/solver.md).
    cg_tolerance: float = 1e-8
    cg_max_iterations: int = 3000
    # A point leaves the block-Jacobi CG for its weak-subspace factorization (module docstring) once its convergence
    # rate predicts more than this many further Jacobi iterations (0: factor every point at once). One factorization
    # costs about as much as 20-50 Jacobi iterations of that point (SuperLU, measured at F = 700 ... 20,000).
    factor_threshold: float = 30.0


def video_chain_laplacian(video_index: np.ndarray) -> tuple[sp.csr_matrix, int]:
    """Laplacian (F, F) of the graph linking consecutive frames of the same video, and its number of links M.
    Frames of a video must be contiguous and in temporal order (as `build_problem` makes them)."""
    F = len(video_index)
    same = video_index[1:] == video_index[:-1]
    a = np.flatnonzero(same)
    b = a + 1
    M = len(a)
    adjacency = sp.coo_matrix((np.ones(2 * M), (np.concatenate([a, b]), np.concatenate([b, a]))), shape=(F, F))
    degree = sp.diags(np.asarray(adjacency.sum(axis=1)).ravel())
    return (degree - adjacency).tocsr(), M


def quadratic_form(W: sp.spmatrix, video_index: np.ndarray, num_points: int, lambda2: float) -> sp.csr_matrix:
    """Q (F, F) such that the X-step cost of one point is trace(Y^T Q Y)."""
    F = W.shape[0]
    A = sp.identity(F, format="csr") - W.tocsr()
    Q = (A @ A.T) / (F * num_points)
    if lambda2 > 0:
        laplacian, M = video_chain_laplacian(video_index)
        if M > 0:
            # Normalized per point like the data term (the paper writes 1/M over shapes stacking all P points,
            # which made Psi2 P times stronger and collapsed the motion toward the cameras: docs/solver.md).
            Q = Q + (lambda2 / (M * num_points)) * laplacian
    return sp.csr_matrix(Q)


def solve_x(
    W: sp.spmatrix,
    centers: np.ndarray,
    rays: np.ndarray,
    video_index: np.ndarray,
    options: XStepOptions,
    *,
    num_points: int | None = None,
    start: np.ndarray | None = None,
) -> np.ndarray:
    """3D points (F, P, 3) minimizing the X-step cost for fixed W (F, F). rays (F, P, 3), NaN = unobserved.

    All points are solved together by a block-Jacobi preconditioned conjugate gradient, warm-started from `start`
    (the previous points: late in the alternation they barely move); points it would need many more iterations for
    (`options.factor_threshold`) are factored in their weak subspace (module docstring). Points whose CG still does
    not converge are solved directly (sparse LU of the full 3F system). `num_points` is the P of the 1/(FP)
    normalization (defaults to the P of `rays`).
    """
    F, P = rays.shape[:2]
    P_norm = num_points or P
    Q = quadratic_form(W, video_index, P_norm, options.lambda2)
    observed = ~np.isnan(rays[..., 0])
    r = np.where(observed[..., None], rays, 0.0)
    weight = options.lambda3 / (F * P_norm)
    if options.constraint is RayConstraint.HARD:
        points, converged = _solve_hard_points(Q, centers, r, observed, options, start)
    else:
        points, converged = _solve_soft_points(Q, centers, r, observed, weight, options, start)
    if not converged.all():
        Q3 = sp.kron(Q, sp.identity(3), format="csr")
        for p in np.flatnonzero(~converged):
            if options.constraint is RayConstraint.HARD:
                points[:, p] = _solve_hard(Q3, centers, rays[:, p], observed[:, p])
            else:
                points[:, p] = _solve_soft(Q3, centers, rays[:, p], observed[:, p], weight)
    return points


# ------------------------------------------------------------------------------------------------------------
# Weak subspace of one point: J (3F, n) and the factorization of S = J^T (Q x I3) J


def _primary_directions(r: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """E (F, ..., 3): the ray where observed, the x axis where missing (the first of a missing frame's three free
    coordinates)."""
    return np.where(observed[..., None], r, np.array([1.0, 0.0, 0.0]))


class _WeakSubspace:
    """The weak subspace of one point and the sparse LU of its matrix S = J^T (Q x I3) J.

    Unknowns: F primary ones, z_f along E_f (the ray of an observed frame, the x axis of a missing one), then the
    y and the z coordinates of the M missing frames. The primary block is Q o (E E^T) and has Q's pattern, so a
    fully observed point's S is built on Q's CSC structure without sorting."""

    def __init__(self, Q: sp.csc_matrix, rows: np.ndarray, r: np.ndarray, observed: np.ndarray):
        F = len(observed)
        self.E = _primary_directions(r, observed)  # (F, 3)
        self.missing = np.flatnonzero(~observed)
        E, cols = self.E, np.repeat(np.arange(F), np.diff(Q.indptr))
        dots = E[rows, 0] * E[cols, 0] + E[rows, 1] * E[cols, 1] + E[rows, 2] * E[cols, 2]
        S = sp.csc_matrix((Q.data * dots, Q.indices, Q.indptr), shape=(F, F))
        if len(self.missing):
            # Primary z_f with the y / z coordinate of missing frame g: Q_fg E_f[axis]; missing y (z) coordinates
            # couple among themselves through Q, and not with the other axis.
            Q_fm = Q[:, self.missing]
            Q_mm = Q_fm[self.missing]
            B_y = sp.diags(E[:, 1]) @ Q_fm
            B_z = sp.diags(E[:, 2]) @ Q_fm
            S = sp.bmat([[S, B_y, B_z], [B_y.T, Q_mm, None], [B_z.T, None, Q_mm]], format="csc")
        try:
            self.lu = _factor_spd(S)
        except RuntimeError:
            # Exactly singular: a stretch of frames linked by W to no frame where the point is observed (missing
            # data, measured on a squat window with 30 % missing) can shift freely. A tiny ridge picks the
            # smallest such shift; the factor serves as a preconditioner (soft rays) or gives that solution (hard).
            ridge = 1e-6 * max(float(np.abs(S.diagonal()).max()), 1e-300)
            self.lu = _factor_spd((S + ridge * sp.identity(S.shape[0], format="csc")).tocsc())

    def solve(self, primary: np.ndarray, R: np.ndarray) -> np.ndarray:
        """S^-1 J^T R for R (F, 3) whose primary part E . R (F,) is given; returns the unknowns (n,)."""
        b = np.concatenate([primary, R[self.missing, 1], R[self.missing, 2]])
        return np.asarray(self.lu.solve(b))

    def add_extras(self, z: np.ndarray, out: np.ndarray) -> None:
        """out (F, 3) += the y / z coordinates of the missing frames in z (the primary part is added by the
        caller, E z[:F], for all points at once)."""
        F, M = len(self.E), len(self.missing)
        out[self.missing, 1] += z[F:F + M]
        out[self.missing, 2] += z[F + M:]

    def apply_inverse(self, R: np.ndarray) -> np.ndarray:
        """J S^-1 J^T R for one point, R (F, 3)."""
        z = self.solve(np.einsum("fk,fk->f", self.E, R), R)
        out = self.E * z[:len(self.E), None]
        self.add_extras(z, out)
        return out


def _factor_spd(S: sp.csc_matrix) -> spla.SuperLU:
    # Minimum-degree ordering on A^T + A and no pivoting: S is symmetric positive (semi)definite. relax = panel_size
    # = 1: 20-25 % faster on these nearly fill-free factors than SuperLU's supernode defaults.
    return spla.splu(S, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, relax=1, panel_size=1,
                     options={"SymmetricMode": True})


def _weak_subspaces(Q: sp.csr_matrix, r: np.ndarray, observed: np.ndarray, points: np.ndarray) -> list[_WeakSubspace]:
    """Factor the weak subspaces of `points` (indices into the P axis of r (F, P, 3) and observed (F, P))."""
    Q_csc = Q.tocsc()
    Q_csc.sort_indices()
    rows = Q_csc.indices
    return [_WeakSubspace(Q_csc, rows, np.ascontiguousarray(r[:, p]), observed[:, p]) for p in points]


# ------------------------------------------------------------------------------------------------------------
# Batched conjugate gradient

Operators = tuple[Callable[[np.ndarray], np.ndarray], Callable[[np.ndarray], np.ndarray]]


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("fkp,fkp->p", a, b)


class _BatchedCG:
    """Independent preconditioned CG solves, one per point: arrays are (F, 3, P), the point axis last so that the
    per-point dot products reduce over contiguous memory (the (F, P, 3) layout made them 10x slower). The state can
    be narrowed to a subset of the points without restarting them."""

    def __init__(self, operators: Operators, rhs: np.ndarray, x: np.ndarray, tolerance: float):
        self.apply, self.precondition = operators
        self.x = x  # updated in place: callers hand over an array they own
        self.residual = rhs - self.apply(x)
        self.target = tolerance * np.maximum(np.sqrt(_dot(rhs, rhs)), 1e-300)
        self.norm = np.sqrt(_dot(self.residual, self.residual))
        self.done = self.norm <= self.target
        z = self.precondition(self.residual)
        self.direction = z
        self.rz = _dot(self.residual, z)
        self.iterations = 0

    def run(self, iterations: int) -> None:
        for _ in range(iterations):
            if self.done.all():
                return
            Ad = self.apply(self.direction)
            curvature = _dot(self.direction, Ad)
            done = self.done
            alpha = np.where(done | (curvature <= 0), 0.0, self.rz / np.where(curvature > 0, curvature, 1.0))
            # in place: the arrays are the state's own (copied on construction and narrowing)
            self.x += alpha * self.direction
            Ad *= alpha
            self.residual -= Ad
            self.norm = np.sqrt(_dot(self.residual, self.residual))
            done |= self.norm <= self.target
            z = self.precondition(self.residual)
            rz = _dot(self.residual, z)
            beta = np.where(done, 0.0, rz / np.where(self.rz != 0, self.rz, 1.0))
            self.direction *= beta
            self.direction += z
            self.rz = rz
            self.iterations += 1

    def narrow(self, keep: np.ndarray, operators: Operators) -> None:
        """Continue with the points `keep` (indices into the current batch) only; `operators` act on them."""
        self.apply, self.precondition = operators
        for name in ("x", "residual", "direction"):
            setattr(self, name, np.ascontiguousarray(getattr(self, name)[..., keep]))
        for name in ("target", "norm", "done", "rz"):
            setattr(self, name, getattr(self, name)[keep])


# Jacobi CG iterations between two looks at the convergence rates (each look may narrow the batch).
_CHECK_EVERY = 10


def _cg_then_factor(
    jacobi: Callable[[np.ndarray], Operators],
    finish: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]],
    rhs: np.ndarray,
    x: np.ndarray,
    options: XStepOptions,
    labels: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Jacobi CG on all points of rhs, x (F, 3, P'); every `_CHECK_EVERY` iterations the points whose recent convergence
    rate predicts more than `options.factor_threshold` further iterations leave the batch for `finish(labels, x)`,
    which returns their (x, converged); `jacobi(labels)` gives the operators. `labels` (P',) name the points for
    those two. Returns x (F, 3, P') and converged (P',)."""
    P = rhs.shape[2]
    x = x.copy()
    converged = np.zeros(P, dtype=bool)
    batch = np.arange(P)
    if options.factor_threshold <= 0:
        return finish(labels, x)
    cg = _BatchedCG(jacobi(labels), rhs, x, options.cg_tolerance)
    while True:
        before = cg.norm.copy()
        steps = min(_CHECK_EVERY, options.cg_max_iterations - cg.iterations)
        cg.run(steps)
        x[..., batch] = cg.x
        converged[batch] = cg.done
        if cg.done.all() or cg.iterations >= options.cg_max_iterations:
            return x, converged
        # Rate over the last `_CHECK_EVERY` iterations: the first ones remove the stiff error and look deceptively fast.
        rate = (np.maximum(cg.norm, 1e-300) / np.maximum(before, 1e-300)) ** (1.0 / max(steps, 1))
        with np.errstate(divide="ignore", invalid="ignore"):
            remaining = np.where(rate < 1.0, np.log(cg.target / cg.norm) / np.log(rate), np.inf)
        slow = ~cg.done & (remaining > options.factor_threshold)
        if slow.any():
            points = batch[slow]
            x[..., points], converged[points] = finish(labels[points], cg.x[..., slow])
        if slow.any() or cg.done.any():  # finished points leave the batch: they cost as much as the others
            keep = np.flatnonzero(~slow & ~cg.done)
            batch = batch[keep]
            cg.narrow(keep, jacobi(labels[batch]))


def _along(r: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """r (r . Y) per (frame, point), arrays (F, 3, P): the component of Y along its ray (zero where r = 0)."""
    # einsum reduces the (strided) axis 1 in one pass: 5x faster than three strided products at F = 20,000.
    return r * np.einsum("fkp,fkp->fp", r, Y)[:, None, :]


def _to_fkp(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a.transpose(0, 2, 1))


# ------------------------------------------------------------------------------------------------------------
# Soft rays


def _solve_soft_points(
    Q: sp.csr_matrix, centers: np.ndarray, r: np.ndarray, observed: np.ndarray, weight: float,
    options: XStepOptions, start: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Jacobi CG for all points; the slow ones continue with the weak-subspace preconditioned CG.
    Returns points (F, P, 3) and converged (P,)."""
    P = observed.shape[1]
    r_fkp = _to_fkp(r)
    w = weight * observed[:, None, :]  # (F, 1, P), zero where unobserved
    diagonal = np.maximum(Q.diagonal(), 1e-300)[:, None, None]
    # rhs = w (I - r r^T) C, per (frame, point)
    C = centers[:, :, None]
    rhs = w * (C - r_fkp * np.einsum("fkp,fk->fp", r_fkp, centers)[:, None, :])
    x0 = _to_fkp(start) if start is not None else np.repeat(C, P, axis=2)

    def subset(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if len(points) == P:  # all points, in order: no copies
            return r_fkp, w
        return np.ascontiguousarray(r_fkp[..., points]), np.ascontiguousarray(w[..., points])

    partners = _mutual_partners(Q)

    def jacobi(points: np.ndarray) -> Operators:
        r_s, w_s = subset(points)
        return _soft_operator(Q, r_s, w_s), _soft_jacobi(r_s, w_s, diagonal, partners)

    def finish(points: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r_s, w_s = subset(points)
        subspaces = _weak_subspaces(Q, r, observed, points)
        cg = _BatchedCG((_soft_operator(Q, r_s, w_s), _soft_two_level(subspaces, r_s, w_s, diagonal)),
                        np.ascontiguousarray(rhs[..., points]), x, options.cg_tolerance)
        cg.run(options.cg_max_iterations)
        return cg.x, cg.done

    x, done = _cg_then_factor(jacobi, finish, rhs, x0, options, np.arange(P))
    return x.transpose(0, 2, 1).copy(), done


def _soft_operator(Q: sp.csr_matrix, r: np.ndarray, w: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """Y (F, 3, P) -> (Q x I3) Y + w (I - r r^T) Y."""
    F, _, P = r.shape
    wr = w * r

    def apply(Y: np.ndarray) -> np.ndarray:
        out = (Q @ Y.reshape(F, -1)).reshape(F, 3, P)
        out += w * Y
        out -= wr * np.einsum("fkp,fkp->fp", r, Y)[:, None, :]
        return out

    return apply


def _mutual_partners(Q: sp.csr_matrix, min_coupling: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """partner (F,): the frame g that frame f is most strongly coupled to in Q (|Q_fg| / sqrt(Q_ff Q_gg)) when f is
    also g's strongest and the coupling exceeds `min_coupling`, else f itself; and Q_f,partner (0 if unpaired)."""
    F = Q.shape[0]
    Q = sp.csr_matrix(Q)
    Q.sort_indices()
    rows = np.repeat(np.arange(F), np.diff(Q.indptr))
    d = np.maximum(Q.diagonal(), 1e-300)
    strength = np.where(rows == Q.indices, -1.0, np.abs(Q.data) / np.sqrt(d[rows] * d[Q.indices]))
    present = np.diff(Q.indptr) > 0
    best_value = np.full(F, -1.0)
    best_value[present] = np.maximum.reduceat(strength, Q.indptr[:-1][present])
    candidates = np.flatnonzero(strength == best_value[rows])
    first_rows, first = np.unique(rows[candidates], return_index=True)
    best = np.arange(F)
    best[first_rows] = Q.indices[candidates[first]]
    mutual = (best[best] == np.arange(F)) & (best != np.arange(F)) & (best_value > min_coupling)
    partner = np.where(mutual, best, np.arange(F))
    coupling = np.zeros(F)
    coupling[first_rows] = Q.data[candidates[first]]
    return partner, np.where(mutual, coupling, 0.0)


def _soft_jacobi(
    r: np.ndarray, w: np.ndarray, diagonal: np.ndarray, partners: tuple[np.ndarray, np.ndarray]
) -> Callable[[np.ndarray], np.ndarray]:
    """Block Jacobi in closed form, (d I + w (I - r r^T))^-1 = (I - r r^T) / (d + w) + r r^T / d for a unit r,
    except that the along-ray components of two mutually most strongly coupled frames (`_mutual_partners`) are
    solved together by their 2x2 block [[d_f, c], [c, d_g]], c = Q_fg r_f . r_g. Such pairs (two frames that
    express each other, seen from nearly opposite cameras) were the slowest modes of the plain block Jacobi CG:
    226 -> 22 iterations on the hardest X-step of a 2000-frame solve, 12-42 -> 9-17 on later ones."""
    partner, coupling = partners
    inverse_observed = 1.0 / (diagonal + w)  # (F, 1, P)
    d_f = diagonal[:, 0, :]  # (F, 1)
    d_g = d_f[partner]
    c = coupling[:, None] * np.einsum("fkp,fkp->fp", r, r[partner])  # (F, P)
    # Q is positive semidefinite, so c^2 <= d_f d_g; the floor only guards exactly parallel rays of a singular pair.
    determinant = np.maximum(d_f * d_g - c * c, 1e-12 * d_f * d_g)
    gain_f, gain_g = d_g / determinant, c / determinant
    inverse_along = inverse_observed[:, 0, :]

    def precondition(R: np.ndarray) -> np.ndarray:
        along = np.einsum("fkp,fkp->fp", r, R)  # (F, P)
        solved = gain_f * along - gain_g * along[partner]
        out = R * inverse_observed
        out += r * (solved - along * inverse_along)[:, None, :]
        return out

    return precondition


def _soft_two_level(
    subspaces: list[_WeakSubspace], r: np.ndarray, w: np.ndarray, diagonal: np.ndarray
) -> Callable[[np.ndarray], np.ndarray]:
    """J S^-1 J^T R + the across-ray components of R divided by (d + w): exact in the weak subspace, Jacobi in the
    stiff one (a missing frame lies wholly in the weak subspace). Arrays (F, 3, P'), one subspace per point."""
    E = np.ascontiguousarray(np.stack([s.E for s in subspaces], axis=2))  # (F, 3, P')
    inverse_stiff = (w > 0) / (diagonal + w)

    def precondition(R: np.ndarray) -> np.ndarray:
        out = (R - _along(r, R)) * inverse_stiff
        primary = np.einsum("fkp,fkp->pf", E, R)  # (P', F), one contiguous row per point
        solutions = np.empty_like(primary)
        for i, subspace in enumerate(subspaces):
            z = subspace.solve(primary[i], R[:, :, i])
            solutions[i] = z[:len(primary[i])]
            if len(subspace.missing):
                extras = np.zeros((len(subspace.E), 3))
                subspace.add_extras(z, extras)
                out[:, :, i] += extras
        out += E * solutions.T[:, None, :]
        return out

    return precondition


# ------------------------------------------------------------------------------------------------------------
# Hard rays


def _solve_hard_points(
    Q: sp.csr_matrix, centers: np.ndarray, r: np.ndarray, observed: np.ndarray, options: XStepOptions,
    start: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Observed points move along their ray only: Jacobi CG on Y = y0 + Pi z with Pi = r r^T (observed) or I
    (missing); the slow points are solved directly in their weak subspace, which is exactly Pi's range."""
    F, P = observed.shape
    r_fkp = _to_fkp(r)
    missing = ~observed[:, None, :]
    y0 = np.where(missing, 0.0, centers[:, :, None])
    inverse_diagonal = (1.0 / np.maximum(Q.diagonal(), 1e-300))[:, None, None]

    def projector(points: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
        missing_s, r_s = missing[..., points], np.ascontiguousarray(r_fkp[..., points])
        return lambda Y: np.where(missing_s, Y, _along(r_s, Y))

    def jacobi(points: np.ndarray) -> Operators:
        project, n = projector(points), len(points)

        def apply(Z: np.ndarray) -> np.ndarray:
            return project((Q @ project(Z).reshape(F, -1)).reshape(F, 3, n))

        return apply, lambda R: project(R * inverse_diagonal)

    project_all = projector(np.arange(P))
    rhs = -project_all((Q @ y0.reshape(F, -1)).reshape(F, 3, P))

    def finish(points: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        out = np.empty_like(z)
        for i, subspace in enumerate(_weak_subspaces(Q, r, observed, points)):
            out[:, :, i] = subspace.apply_inverse(rhs[:, :, points[i]])
        return out, np.all(np.isfinite(out), axis=(0, 1))

    z0 = project_all(_to_fkp(start) - y0) if start is not None else np.zeros((F, 3, P))
    z, done = _cg_then_factor(jacobi, finish, rhs, z0, options, np.arange(P))
    return (y0 + project_all(z)).transpose(0, 2, 1).copy(), done


# ------------------------------------------------------------------------------------------------------------
# Last-resort direct solves of one point's full system


def _solve_hard(Q3: sp.csr_matrix, centers: np.ndarray, rays: np.ndarray, observed: np.ndarray) -> np.ndarray:
    F = len(centers)
    # Columns of J: one per observed frame (its ray), three per missing frame (free xyz).
    n_unknowns = np.where(observed, 1, 3)
    first = np.concatenate([[0], np.cumsum(n_unknowns)[:-1]])
    rows, cols, vals = [], [], []
    obs = np.flatnonzero(observed)
    for axis in range(3):
        rows.append(3 * obs + axis)
        cols.append(first[obs])
        vals.append(rays[obs, axis])
    mis = np.flatnonzero(~observed)
    for axis in range(3):
        rows.append(3 * mis + axis)
        cols.append(first[mis] + axis)
        vals.append(np.ones(len(mis)))
    J = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(3 * F, int(n_unknowns.sum())))
    y0 = np.where(observed[:, None], centers, 0.0).ravel()
    H = (J.T @ Q3 @ J).tocsc()
    rhs = -(J.T @ (Q3 @ y0))
    z = _spd_solve(H, rhs)
    return (y0 + J @ z).reshape(F, 3)


def _solve_soft(
    Q3: sp.csr_matrix, centers: np.ndarray, rays: np.ndarray, observed: np.ndarray, weight: float
) -> np.ndarray:
    F = len(centers)
    r = np.where(observed[:, None], rays, 0.0)
    # Blocks weight * (I - r r^T) for observed frames, zero for missing ones.
    blocks = weight * (np.eye(3)[None] - r[:, :, None] * r[:, None, :])
    blocks[~observed] = 0.0
    block_rows = (3 * np.arange(F)[:, None, None] + np.arange(3)[None, :, None]).repeat(3, axis=2)
    block_cols = (3 * np.arange(F)[:, None, None] + np.arange(3)[None, None, :]).repeat(3, axis=1)
    penalty = sp.csr_matrix((blocks.ravel(), (block_rows.ravel(), block_cols.ravel())), shape=(3 * F, 3 * F))
    H = (Q3 + penalty).tocsc()
    rhs = penalty @ centers.ravel()
    return _spd_solve(H, rhs).reshape(F, 3)


def _spd_solve(H: sp.csc_matrix, rhs: np.ndarray) -> np.ndarray:
    # Minimum-degree ordering on A^T + A suits these symmetric systems better than the default COLAMD.
    return np.asarray(spla.spsolve(H, rhs, permc_spec="MMD_AT_PLUS_A"))
