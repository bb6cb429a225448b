"""The X-step: minimize over the 3D points, with W fixed,

    1/(F P) ||S^T (I - W)||_F^2 + lambda2/(M P) Psi2 + [soft rays] lambda3/(F P) sum_observed ||(I - r r^T)(Y - C)||^2

Points decouple: for point p with positions Y_p (F, 3) the cost is sum_fg Q_fg <Y_pf, Y_pg> (+ ray terms) with
Q = 1/(FP) (I - W)(I - W)^T + lambda2/(M P) L, L the Laplacian of consecutive frames of one video (M links). Each
point is one sparse symmetric linear system:
* hard rays: an observed Y_pf = C_f + d r_f has one unknown d; a missing one has three free coordinates;
* soft rays: every Y_pf is free, observed ones are pulled to their ray by lambda3/(FP) (I - r r^T).
The soft weight carries the same 1/(FP) as the data term, so lambda3 is the weight of a squared ray distance
relative to a squared self-expression residual of one point.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla


class RayConstraint(enum.Enum):
    HARD = "hard"
    SOFT = "soft"


@dataclass(kw_only=True)
class XStepOptions:
    """Options of the X-step (`solve_x`); a solve builds them from its `SolverOptions` (`x_step_options`).

    lambda2, lambda3: weights of the smoothness Psi2 and of the soft ray constraint.
    constraint: points exactly on their rays (hard) or pulled to them (soft).
    workers: points are independent systems: from PARALLEL_SIZE unknowns on they are split over this many threads
    (numpy and the sparse products release the GIL).
    """

    lambda2: float = 0.1
    lambda3: float = 100.0
    constraint: RayConstraint = RayConstraint.SOFT
    workers: int = 2


PARALLEL_SIZE = 100_000  # F * P at and above which the X-step splits the points over `workers` threads
# Relative residual of the batched conjugate-gradient solve: the alternation does not need exact X-steps.
CG_TOLERANCE = 1e-8
CG_MAX_ITERATIONS = 3000


def chain_links(video_index: np.ndarray) -> np.ndarray:
    """(M,) frames f whose next frame f + 1 belongs to the same video: the links of Psi2."""
    return np.flatnonzero(video_index[1:] == video_index[:-1])


def video_chain_laplacian(video_index: np.ndarray) -> tuple[sp.csr_matrix, int]:
    """Laplacian (F, F) of the graph linking consecutive frames of the same video, and its number of links M.
    Frames of a video must be contiguous and in temporal order (as `build_problem` makes them)."""
    F = len(video_index)
    a = chain_links(video_index)
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
    (the previous points: late in the alternation they barely move). Points whose CG does not converge are solved
    directly (sparse LU). `num_points` is the P of the 1/(FP) normalization (defaults to the P of `rays`).
    """
    F, P = rays.shape[:2]
    P_norm = num_points or P
    Q = quadratic_form(W, video_index, P_norm, options.lambda2)
    observed = ~np.isnan(rays[..., 0])
    r = np.where(observed[..., None], rays, 0.0)
    weight = options.lambda3 / (F * P_norm)

    def solve_points(group: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        begin = None if start is None else start[:, group]
        if options.constraint is RayConstraint.HARD:
            return _cg_hard(Q, centers, r[:, group], observed[:, group], options, begin)
        return _cg_soft(Q, centers, r[:, group], observed[:, group], weight, options, begin)

    workers = min(options.workers, P) if F * P >= PARALLEL_SIZE else 1
    if workers > 1:
        groups = np.array_split(np.arange(P), workers)
        points, converged = np.empty((F, P, 3)), np.empty(P, dtype=bool)
        with ThreadPoolExecutor(workers) as pool:
            for group, (part, done) in zip(groups, pool.map(solve_points, groups), strict=True):
                points[:, group], converged[group] = part, done
    else:
        points, converged = solve_points(np.arange(P))
    if not converged.all():
        Q3 = sp.kron(Q, sp.identity(3), format="csr")
        for p in np.flatnonzero(~converged):
            if options.constraint is RayConstraint.HARD:
                points[:, p] = _solve_hard(Q3, centers, rays[:, p], observed[:, p])
            else:
                points[:, p] = _solve_soft(Q3, centers, rays[:, p], observed[:, p], weight)
    return points


Operator = Callable[[np.ndarray, np.ndarray], None]  # op(Y, out): writes into out
Operators = Callable[[np.ndarray], tuple[Operator, Operator]]  # points -> (apply, precondition) for those points


def _batched_cg(
    operators: Operators, rhs: np.ndarray, x: np.ndarray, options: XStepOptions
) -> tuple[np.ndarray, np.ndarray]:
    """Independent CG solves, one per point: arrays are (F, 3, P), the point axis last so that the per-point dot
    products reduce over contiguous memory (the (F, P, 3) layout made them much slower). `operators(points)` returns
    (apply, precondition) for the points `points` (indices into the last axis): `apply(Y, out)` and
    `precondition(R, out)` write into `out`. Returns (x, converged).

    Points converge at very different speeds, so converged points leave the batch once a quarter of it has: the
    products then run over the points still iterating only. Every other update is in place: on long captures the
    arrays are large, and a fresh temporary per operation cost a page-faulting allocation each."""

    def dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.einsum("fkp,fkp->p", a, b)

    solution = np.empty_like(x)  # every point is written in when it leaves the batch, or at the end
    converged = np.zeros(rhs.shape[2], dtype=bool)
    active = np.arange(rhs.shape[2])
    apply, precondition = operators(active)
    x = x.copy()
    residual = np.empty_like(x)
    apply(x, residual)
    np.subtract(rhs, residual, out=residual)
    target = CG_TOLERANCE * np.maximum(np.sqrt(dot(rhs, rhs)), 1e-300)
    z = np.empty_like(x)
    precondition(residual, z)
    direction = z.copy()
    Ad = np.empty_like(x)
    step = np.empty_like(x)
    rz = dot(residual, z)
    done = np.sqrt(dot(residual, residual)) <= target
    for _ in range(CG_MAX_ITERATIONS):
        if done.all():
            break
        if done.sum() >= max(1, len(active) // 4):  # the finished points leave the batch
            solution[:, :, active[done]] = x[:, :, done]
            converged[active[done]] = True
            keep = ~done
            active = active[keep]
            x, residual, direction = (np.ascontiguousarray(a[:, :, keep]) for a in (x, residual, direction))
            target, rz, done = target[keep], rz[keep], done[keep]
            z, Ad, step = np.empty_like(x), np.empty_like(x), np.empty_like(x)
            apply, precondition = operators(active)
        apply(direction, Ad)
        curvature = dot(direction, Ad)
        alpha = np.where(done | (curvature <= 0), 0.0, rz / np.where(curvature > 0, curvature, 1.0))
        x += np.multiply(alpha, direction, out=step)
        residual -= np.multiply(alpha, Ad, out=step)
        done |= np.sqrt(dot(residual, residual)) <= target
        precondition(residual, z)
        rz_new = dot(residual, z)
        beta = np.where(done, 0.0, rz_new / np.where(rz != 0, rz, 1.0))
        direction *= beta
        direction += z
        rz = rz_new
    solution[:, :, active] = x
    converged[active] = done
    return solution, converged


def _along(r: np.ndarray, Y: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """r (r . Y) per (frame, point), arrays (F, 3, P): the component of Y along its ray (zero where r = 0), written
    into `out` when given."""
    # einsum reduces the (strided) axis 1 in one pass, faster than three strided products.
    return np.multiply(r, np.einsum("fkp,fkp->fp", r, Y)[:, None, :], out=out)


def _to_fkp(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a.transpose(0, 2, 1))


def _cg_soft(
    Q: sp.csr_matrix,
    centers: np.ndarray,
    r: np.ndarray,
    observed: np.ndarray,
    weight: float,
    options: XStepOptions,
    start: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray]:
    """The 3x3 ray blocks weight (I - r r^T) and the block-Jacobi preconditioner are applied in closed form:
    (d I + w (I - r r^T))^-1 = (I - r r^T) / (d + w) + r r^T / d for a unit ray r."""
    F, P = observed.shape
    r = _to_fkp(r)
    w = weight * observed[:, None, :]  # (F, 1, P), zero where unobserved
    diagonal = np.maximum(Q.diagonal(), 1e-300)[:, None, None]
    inverse_observed = 1.0 / (diagonal + w)
    inverse_diagonal = 1.0 / diagonal

    def operators(points: np.ndarray) -> tuple[Operator, Operator]:
        n = len(points)
        r_p, w_p, inverse_observed_p = (np.ascontiguousarray(a[:, :, points]) for a in (r, w, inverse_observed))
        scratch = np.empty((F, 3, n))  # used by apply and precondition, never at the same time

        def apply(Y: np.ndarray, out: np.ndarray) -> None:
            out[...] = (Q @ Y.reshape(F, -1)).reshape(F, 3, n)
            _along(r_p, Y, out=scratch)
            np.subtract(Y, scratch, out=scratch)
            np.multiply(scratch, w_p, out=scratch)
            out += scratch

        def precondition(R: np.ndarray, out: np.ndarray) -> None:
            _along(r_p, R, out=scratch)
            np.subtract(R, scratch, out=out)
            out *= inverse_observed_p
            np.multiply(scratch, inverse_diagonal, out=scratch)
            out += scratch

        return apply, precondition

    C = np.broadcast_to(centers[:, :, None], (F, 3, P))
    rhs = w * (C - _along(r, C))
    x0 = _to_fkp(start) if start is not None else C.copy()
    x, done = _batched_cg(operators, rhs, x0, options)
    return x.transpose(0, 2, 1).copy(), done


def _cg_hard(
    Q: sp.csr_matrix,
    centers: np.ndarray,
    r: np.ndarray,
    observed: np.ndarray,
    options: XStepOptions,
    start: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Observed points move along their ray only: CG on Y = y0 + Pi z with Pi = r r^T (observed) or I (missing)."""
    F, P = observed.shape
    r = _to_fkp(r)
    missing = ~observed[:, None, :]
    y0 = np.where(missing, 0.0, centers[:, :, None])
    inverse_diagonal = (1.0 / np.maximum(Q.diagonal(), 1e-300))[:, None, None]

    def projector(points: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
        missing_p, r_p = missing[:, :, points], np.ascontiguousarray(r[:, :, points])
        return lambda Y: np.where(missing_p, Y, _along(r_p, Y))

    def operators(points: np.ndarray) -> tuple[Operator, Operator]:
        n = len(points)
        project = projector(points)

        def apply(Z: np.ndarray, out: np.ndarray) -> None:
            out[...] = project((Q @ project(Z).reshape(F, -1)).reshape(F, 3, n))

        def precondition(R: np.ndarray, out: np.ndarray) -> None:
            out[...] = project(R * inverse_diagonal)

        return apply, precondition

    project_all = projector(np.arange(P))
    rhs = -project_all((Q @ y0.reshape(F, -1)).reshape(F, 3, P))
    z0 = project_all(_to_fkp(start) - y0) if start is not None else np.zeros((F, 3, P))
    z, converged = _batched_cg(operators, rhs, z0, options)
    return (y0 + project_all(z)).transpose(0, 2, 1).copy(), converged


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
    J = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(3 * F, int(n_unknowns.sum()))
    )
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
