"""Small vectorized two- and multi-view geometry helpers (normalized camera coordinates unless stated)."""

from __future__ import annotations

import numpy as np


def homogeneous(x: np.ndarray) -> np.ndarray:
    """(..., 2) -> (..., 3)."""
    return np.concatenate([x, np.ones((*x.shape[:-1], 1))], axis=-1)


def sampson(F: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """Squared Sampson distances of xb^T F xa = 0. F: (..., H, 3, 3), xa, xb: (..., N, 2) -> (..., H, N)."""
    f = [[F[..., i, j, None] for j in range(3)] for i in range(3)]  # (..., H, 1) each: explicit, faster than einsum
    a0, a1 = xa[..., None, :, 0], xa[..., None, :, 1]  # (..., 1, N)
    b0, b1 = xb[..., None, :, 0], xb[..., None, :, 1]
    fa0 = f[0][0] * a0 + f[0][1] * a1 + f[0][2]  # (F xa)_0: (..., H, N)
    fa1 = f[1][0] * a0 + f[1][1] * a1 + f[1][2]
    fa2 = f[2][0] * a0 + f[2][1] * a1 + f[2][2]
    fb0 = f[0][0] * b0 + f[1][0] * b1 + f[2][0]  # (F^T xb)_0
    fb1 = f[0][1] * b0 + f[1][1] * b1 + f[2][1]
    num = (b0 * fa0 + b1 * fa1 + fa2) ** 2
    den = fa0**2 + fa1**2 + fb0**2 + fb1**2
    return num / np.maximum(den, 1e-300)


def eight_point(xa: np.ndarray, xb: np.ndarray, essential: bool) -> np.ndarray:
    """Batched linear 8-point: xa, xb (..., 8, 2) -> (..., 3, 3) (projected onto E's manifold when `essential`)."""
    x1, y1 = xa[..., 0], xa[..., 1]
    x2, y2 = xb[..., 0], xb[..., 1]
    one = np.ones_like(x1)
    A = np.stack([x2 * x1, x2 * y1, x2, y2 * x1, y2 * y1, y2, x1, y1], axis=-1)  # (..., 8, 8)
    # F33 = 1: a batched 8x8 solve is much faster than batched SVDs (the rare F33 = 0 case just scores 0)
    # (a tiny ridge keeps hypotheses with a repeated sample solvable: they simply score low)
    with np.errstate(all="ignore"):
        f = _solve_batch(A + 1e-10 * np.eye(8), -one[..., None])[..., 0]
    F = np.concatenate([f, np.ones((*f.shape[:-1], 1))], axis=-1).reshape((*A.shape[:-2], 3, 3))
    F = np.nan_to_num(F, nan=0.0, posinf=0.0, neginf=0.0)
    U, S, Vt = np.linalg.svd(F)
    S = np.broadcast_to(np.array([1.0, 1.0, 0.0]), S.shape) if essential else S * np.array([1.0, 1.0, 0.0])
    return np.einsum("...ij,...j,...jk->...ik", U, S, Vt)


def _solve_batch(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """np.linalg.solve over a batch (..., n, n), (..., n, 1); a sample whose matrix is still singular (duplicate
    points: the ridge vanishes beside large entries) gives NaN instead of failing the whole batch."""
    try:
        return np.linalg.solve(A, b)
    except np.linalg.LinAlgError:
        flat_A, flat_b = A.reshape(-1, *A.shape[-2:]), b.reshape(-1, *b.shape[-2:])
        out = np.full(flat_b.shape, np.nan)
        for i in range(len(flat_A)):
            try:
                out[i] = np.linalg.solve(flat_A[i], flat_b[i])
            except np.linalg.LinAlgError:
                continue
        return out.reshape(b.shape)


def weighted_fit(xa: np.ndarray, xb: np.ndarray, w: np.ndarray, essential: bool) -> np.ndarray:
    """Weighted linear fit on all correspondences (the local optimization of LO-RANSAC).

    xa, xb: (D, N, 2), w: (D, N) -> (D, 3, 3)."""
    x1, y1 = xa[..., 0], xa[..., 1]
    x2, y2 = xb[..., 0], xb[..., 1]
    A = np.stack([x2 * x1, x2 * y1, x2, y2 * x1, y2 * y1, y2, x1, y1, np.ones_like(x1)], axis=-1)  # (D, N, 9)
    M = np.einsum("dni,dn,dnj->dij", A, w, A)  # (D, 9, 9)
    _, vec = np.linalg.eigh(M)
    F = vec[..., :, 0].reshape(-1, 3, 3)
    U, S, Vt = np.linalg.svd(F)
    S = np.broadcast_to(np.array([1.0, 1.0, 0.0]), S.shape) if essential else S * np.array([1.0, 1.0, 0.0])
    return np.einsum("...ij,...j,...jk->...ik", U, S, Vt)


def bougnoux(F: np.ndarray) -> tuple[float, float]:
    """Focals (fa, fb) from a fundamental matrix in principal-point-centred pixels (xb^T F xa = 0); NaN if imaginary."""
    Ft = F.T  # Bougnoux's convention: x2^T F x1 with image 1 = a
    p = np.array([0.0, 0.0, 1.0])
    II = np.diag([1.0, 1.0, 0.0])

    def one(F1: np.ndarray) -> float:
        # focal of the first image of x2^T F1 x1 = 0
        _, _, Vt = np.linalg.svd(F1.T)
        e2 = Vt[-1]  # F1^T e2 = 0: epipole in image 2
        ex = np.array([[0, -e2[2], e2[1]], [e2[2], 0, -e2[0]], [-e2[1], e2[0], 0]])
        num = p @ ex @ II @ F1 @ np.outer(p, p) @ F1.T @ p
        den = p @ ex @ II @ F1 @ II @ F1.T @ p
        f2 = -num / den if den != 0 else np.nan
        return float(np.sqrt(f2)) if f2 > 0 else float("nan")

    return one(F), one(Ft)


def rodrigues(r: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors -> (..., 3, 3)."""
    theta = np.linalg.norm(r, axis=-1)[..., None, None]
    k = r / np.maximum(theta[..., 0], 1e-12)
    K = np.zeros((*r.shape[:-1], 3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -k[..., 2], k[..., 1], -k[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = k[..., 2], -k[..., 1], k[..., 0]
    small = theta < 1e-8
    sin = np.where(small, 1.0, np.sin(theta))
    cos = np.where(small, 1.0, np.cos(theta))
    eye = np.eye(3)
    R = eye + sin * K + (1 - cos) * (K @ K)
    # first order for tiny angles (the unit axis is meaningless there)
    Kr = np.zeros_like(K)
    Kr[..., 0, 1], Kr[..., 0, 2], Kr[..., 1, 2] = -r[..., 2], r[..., 1], -r[..., 0]
    Kr[..., 1, 0], Kr[..., 2, 0], Kr[..., 2, 1] = r[..., 2], -r[..., 1], r[..., 0]
    return np.where(small, eye + Kr, R)


def triangulate(P: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Multi-view DLT. P: (C, 3, 4) normalized projections, x: (..., C, 2) with NaN = unseen -> (..., 3) (NaN if <2)."""
    seen = np.isfinite(x[..., 0])  # (..., C)
    xz = np.where(seen[..., None], x, 0.0)
    rows_x = xz[..., 0:1] * P[:, 2] - P[:, 0]  # (..., C, 4)
    rows_y = xz[..., 1:2] * P[:, 2] - P[:, 1]
    A = np.concatenate([rows_x, rows_y], axis=-2) * np.concatenate([seen, seen], axis=-1)[..., None]
    out = np.full((*x.shape[:-2], 3), np.nan)
    ok = seen.sum(-1) >= 2
    if ok.any():
        _, _, Vt = np.linalg.svd(A[ok])
        X = Vt[:, -1]
        good = np.abs(X[:, 3]) > 1e-12
        res = np.full((len(X), 3), np.nan)
        res[good] = X[good, :3] / X[good, 3:]
        out[ok] = res
    return out


def project(R: np.ndarray, t: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R: (3, 3), t: (3,), X: (..., 3) -> normalized (..., 2), depth (...)."""
    Xc = X @ R.T + t
    return Xc[..., :2] / Xc[..., 2:3], Xc[..., 2]
