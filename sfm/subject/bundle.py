"""Bundle adjustment of static cameras, clock offsets, focals and a knot trajectory (scipy least_squares).

An observation at global time own + offset takes the linear interpolation of its point's two neighbouring knots,
so the offsets get gradients; a small acceleration penalty determines the knots no camera sees.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import OptimizeResult, least_squares
from scipy.sparse import coo_matrix
from threadpoolctl import threadpool_limits

from sfm.subject.chain import Knots
from sfm.subject.geometry import rodrigues
from sfm.subject.observations import VideoObs

log = logging.getLogger(__name__)

SMOOTH = 0.05  # weight of the acceleration residual (pixels per pixel of second difference)
FOCAL_SIGMA = 0.1  # relative error of the self-calibrated focal, pulled with the weight of all observations
DIST_SIGMA = 0.1  # k1, k2 near 0 within this, weighted like one pixel of residual


@dataclass(kw_only=True)
class Bundle:
    cams: list[int]  # video indices of the posed cameras
    rvec: np.ndarray  # (C, 3)
    t: np.ndarray  # (C, 3)
    focal: np.ndarray  # (C,) pixels (used for the unknown-K cameras; known ones keep K)
    k1: np.ndarray  # (C,)
    k2: np.ndarray  # (C,)
    pp: np.ndarray  # (C, 2) principal points (pixels) of the unknown-K cameras
    offsets: np.ndarray  # (V,) seconds
    knots: Knots
    fixed_pose: set[int]  # positions in `cams` whose pose is not adjusted
    fixed_offset: set[int]  # video indices whose offset is not adjusted
    gauge: tuple[int, int, float] | None  # (pos a, pos b, distance): fixes the free scale
    keep: list[np.ndarray]  # per camera position: (F, P) observations still trusted
    depth: float = 1.0  # typical camera-to-subject distance (turns the acceleration penalty into pixels)
    focal_prior: np.ndarray | None = None  # (C,) self-calibrated focals the adjusted ones are pulled to
    focal_sigma: float = FOCAL_SIGMA  # relative; the prior weighs like all of the camera's observations
    # (C, 2) image centres the principal points are pulled to, None = principal points held
    pp_prior: np.ndarray | None = None
    pp_sigma: float = 0.0  # pixels; the prior weighs like all of the camera's observations
    # positions in `cams` of videos posed frame by frame (handheld ones the background posed): (F, 3, 3) R and
    # (F, 3) t cam_from_world per frame, held (also in `fixed_pose`); their rvec and t are unused
    frame_poses: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)


def _nk(b: Bundle) -> int:
    """Intrinsics adjusted per unknown-K camera: focal, k1, k2 (and cx, cy when the principal point is free)."""
    return 5 if b.pp_prior is not None else 3


def _obs_arrays(b: Bundle, obs: list[VideoObs]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Per camera: frame times (M,), point index (M,), target (M, 2), kept mask rows."""
    out = []
    for j, c in enumerate(b.cams):
        o = obs[c]
        f, p = np.nonzero(b.keep[j])
        target = o.norm[f, p] if o.known_K else o.xy[f, p]
        out.append((o.times[f], p, target, f))
    return out


def adjust(b: Bundle, obs: list[VideoObs], inlier_px: float, rounds: int = 2) -> None:
    for r in range(rounds):
        _solve(b, obs, inlier_px)
        if r < rounds - 1:
            n = 0
            for j, (res, f, p) in enumerate(_residuals_px(b, obs)):
                bad = res > 3 * inlier_px
                b.keep[j][f[bad], p[bad]] = False
                n += int(bad.sum())
            log.info("bundle round %d: %d outlier observation(s) removed", r + 1, n)


def _layout(b: Bundle, obs: list[VideoObs]) -> tuple[list[int], list[int], list[int], int]:
    free_pose = [j for j in range(len(b.cams)) if j not in b.fixed_pose]
    free_k = [j for j, c in enumerate(b.cams) if not obs[c].known_K]
    free_o = [j for j, c in enumerate(b.cams) if c not in b.fixed_offset]
    n = 6 * len(free_pose) + _nk(b) * len(free_k) + len(free_o)
    return free_pose, free_k, free_o, n


def _unpack(b: Bundle, obs: list[VideoObs], x: np.ndarray) -> tuple[np.ndarray, ...]:
    free_pose, free_k, free_o, n = _layout(b, obs)
    rvec, t, focal, k1, k2, pp = b.rvec.copy(), b.t.copy(), b.focal.copy(), b.k1.copy(), b.k2.copy(), b.pp.copy()
    nk = _nk(b)
    off = np.array([b.offsets[c] for c in b.cams])
    i = 0
    for j in free_pose:
        rvec[j], t[j] = x[i : i + 3], x[i + 3 : i + 6]
        i += 6
    for j in free_k:
        focal[j], k1[j], k2[j] = x[i], x[i + 1], x[i + 2]
        if nk == 5:
            pp[j] = x[i + 3 : i + 5]
        i += nk
    for j in free_o:
        off[j] = x[i]
        i += 1
    X = x[n:].reshape(b.knots.X.shape)
    return rvec, t, focal, k1, k2, pp, off, X


def _pack(b: Bundle, obs: list[VideoObs]) -> np.ndarray:
    free_pose, free_k, free_o, _ = _layout(b, obs)
    parts = [np.concatenate([b.rvec[j], b.t[j]]) for j in free_pose]
    parts += [np.array([b.focal[j], b.k1[j], b.k2[j], *(b.pp[j] if _nk(b) == 5 else [])]) for j in free_k]
    parts += [np.array([b.offsets[b.cams[j]]]) for j in free_o]
    return np.concatenate([*parts, b.knots.X.ravel()]) if parts else b.knots.X.ravel().copy()


def _model(b: Bundle, obs: list[VideoObs], x: np.ndarray, arrays: list) -> tuple[list[np.ndarray], np.ndarray]:
    """Reprojection residuals per camera (M, 2) in pixels and the smoothness residuals (flattened)."""
    rvec, t, focal, k1, k2, pp, off, X = _unpack(b, obs, x)
    T = len(X)
    R = rodrigues(rvec)  # (C, 3, 3)
    out = []
    for j, c in enumerate(b.cams):
        times, p, target, _ = arrays[j]
        u = (times + off[j] - b.knots.t0) / b.knots.h
        k = np.clip(np.floor(u).astype(np.int64), 0, T - 2)
        w = np.clip(u - k, 0.0, 1.0)[:, None]
        P3 = (1 - w) * X[k, p] + w * X[k + 1, p]  # (M, 3)
        if j in b.frame_poses:
            frames = arrays[j][3]
            Rf, tf = b.frame_poses[j]
            Xc = np.einsum("mij,mj->mi", Rf[frames], P3) + tf[frames]
        else:
            Xc = P3 @ R[j].T + t[j]
        z = np.where(np.abs(Xc[:, 2]) < 1e-9, 1e-9, Xc[:, 2])
        xy = Xc[:, :2] / z[:, None]
        o = obs[c]
        if o.known_K:
            res = (xy - target) * np.array([o.K[0, 0], o.K[1, 1]])
        else:
            r2 = (xy**2).sum(1, keepdims=True)
            res = focal[j] * xy * (1 + k1[j] * r2 + k2[j] * r2**2) + pp[j] - target
        out.append(res)
    scale = SMOOTH * float(np.mean([obs[c].focal for c in b.cams])) / b.depth
    acc = (X[:-2] - 2 * X[1:-1] + X[2:]) * scale  # (T - 2, P, 3)
    extra = [acc.ravel()]
    if b.gauge is not None:
        ja, jb, d = b.gauge
        ca, cb = -R[ja].T @ t[ja], -R[jb].T @ t[jb]
        extra.append(np.array([1e3 * (np.linalg.norm(ca - cb) - d) / d]))
    free_k = [j for j, c in enumerate(b.cams) if not obs[c].known_K]
    # weak prior (like one pixel of residual): distortion near 0
    extra.append(np.concatenate([k1[free_k], k2[free_k]]) / DIST_SIGMA)
    n_obs = np.sqrt(np.array([len(arrays[j][1]) for j in free_k], dtype=float))
    if b.focal_prior is not None and free_k:
        # weighted like all of the camera's observations: otherwise the focal trades off against distortion
        ratio = np.maximum(focal[free_k], 1e-6) / b.focal_prior[free_k]
        extra.append(np.log(ratio) / b.focal_sigma * n_obs)
    if b.pp_prior is not None and free_k:
        extra.append(((pp[free_k] - b.pp_prior[free_k]) / b.pp_sigma * n_obs[:, None]).ravel())
    return out, np.concatenate(extra)


def _sparsity(b: Bundle, obs: list[VideoObs], arrays: list, n_res: int) -> coo_matrix:
    free_pose, free_k, free_o, n = _layout(b, obs)
    T, P, _ = b.knots.X.shape
    col_pose = {j: 6 * i for i, j in enumerate(free_pose)}
    nk = _nk(b)
    col_k = {j: 6 * len(free_pose) + nk * i for i, j in enumerate(free_k)}
    col_o = {j: 6 * len(free_pose) + nk * len(free_k) + i for i, j in enumerate(free_o)}
    rows, cols = [], []
    r0 = 0
    for j in range(len(b.cams)):
        times, p, _, _ = arrays[j]
        M = len(p)
        rr = r0 + np.arange(2 * M)  # rows (x then y of each observation interleaved)
        obs_of_row = np.arange(2 * M) // 2
        block: list[np.ndarray] = []
        if j in col_pose:
            block.append(col_pose[j] + np.arange(6))
        if j in col_k:
            block.append(col_k[j] + np.arange(nk))
        if j in col_o:
            block.append(np.array([col_o[j]]))
        if block:
            cc = np.concatenate(block)
            rows.append(np.repeat(rr, len(cc)))
            cols.append(np.tile(cc, len(rr)))
        u = (times + b.offsets[b.cams[j]] - b.knots.t0) / b.knots.h
        k = np.clip(np.floor(u).astype(np.int64), 0, T - 2)
        for dk in (-1, 0, 1, 2):  # one knot of slack each way: the offsets move during the solve
            kk = np.clip(k + dk, 0, T - 1)
            base = n + (kk * P + p) * 3  # (M,)
            for d in range(3):
                rows.append(rr)
                cols.append(base[obs_of_row] + d)
        r0 += 2 * M
    # smoothness rows: (T - 2, P, 3) each touching knots k, k+1, k+2 of the same coordinate
    idx = np.arange((T - 2) * P * 3)
    kk, rest = idx // (P * 3), idx % (P * 3)
    for dk in range(3):
        rows.append(r0 + idx)
        cols.append(n + (kk + dk) * P * 3 + rest)
    r0 += len(idx)
    tail = n_res - r0  # gauge + intrinsic priors: tie them to all camera parameters (few rows)
    if tail and n:
        rows.append(np.repeat(r0 + np.arange(tail), n))
        cols.append(np.tile(np.arange(n), tail))
    R_ = np.concatenate(rows)
    C_ = np.concatenate(cols)
    keep = n_res > R_
    return coo_matrix((np.ones(int(keep.sum())), (R_[keep], C_[keep])), shape=(n_res, n + b.knots.X.size))


def _fill_knots(X: np.ndarray) -> np.ndarray:
    """Interpolate each point's untriangulated knots along time (edges held) so the solver starts finite."""
    T, P, _ = X.shape
    out = X.copy()
    for p in range(P):
        ok = np.isfinite(X[:, p, 0])
        if not ok.any():
            out[:, p] = 0.0
            continue
        for d in range(3):
            out[:, p, d] = np.interp(np.arange(T), np.nonzero(ok)[0], X[ok, p, d])
    return out


def _solve(b: Bundle, obs: list[VideoObs], inlier_px: float) -> None:
    b.knots.X = _fill_knots(b.knots.X)
    arrays = _obs_arrays(b, obs)
    x0 = _pack(b, obs)

    def fun(x: np.ndarray) -> np.ndarray:
        res, extra = _model(b, obs, x, arrays)
        return np.concatenate([*(r.ravel() for r in res), extra])

    n_res = len(fun(x0))
    sparsity = _sparsity(b, obs, arrays, n_res)
    with threadpool_limits(1, user_api="blas"):  # lsmr's many small vector products only lose with BLAS threads
        sol = _least_squares(fun, x0, sparsity, inlier_px, all(obs[c].known_K for c in b.cams))
    rvec, t, focal, k1, k2, pp, off, X = _unpack(b, obs, sol.x)
    b.rvec, b.t, b.focal, b.k1, b.k2, b.pp, b.knots.X = rvec, t, focal, k1, k2, pp, X
    for j, c in enumerate(b.cams):
        b.offsets[c] = off[j]
        if not obs[c].known_K:
            obs[c].K = np.array([[focal[j], 0, pp[j, 0]], [0, focal[j], pp[j, 1]], [0, 0, 1.0]])
    log.info("bundle: cost %.1f -> %.1f in %d evaluations", 0.5 * np.sum(fun(x0) ** 2), sol.cost, sol.nfev)


def _least_squares(
    fun: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, sparsity: coo_matrix, inlier_px: float, known: bool
) -> OptimizeResult:
    return least_squares(
        fun,
        x0,
        jac_sparsity=sparsity,
        loss="soft_l1",
        f_scale=inlier_px,
        x_scale="jac",
        max_nfev=30 if known else 50,
        xtol=1e-8,
        ftol=1e-5,
        method="trf",
        tr_solver="lsmr",
    )


def _residuals_px(b: Bundle, obs: list[VideoObs]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per camera: (M,) reprojection error in pixels, frame (M,), point (M,) of the kept observations."""
    arrays = _obs_arrays(b, obs)
    res, _ = _model(b, obs, _pack(b, obs), arrays)
    out = []
    for j in range(len(b.cams)):
        _, p, _, f = arrays[j]
        out.append((np.linalg.norm(res[j], axis=1), f, p))
    return out


def held_out_px(b: Bundle, obs: list[VideoObs], inlier_px: float, block: float, test: list[np.ndarray]) -> float:
    """Median reprojection error (pixels) of observations the adjustment did not see.

    `test`: per camera position, (F, P) candidate observations. Camera j's observations in its own-time blocks
    `block` long with (index + j) even are left out, so that at any time other cameras still fix the subject;
    a copy of `b` is adjusted without them, and they are predicted by the copy. `b` and `obs` are unchanged."""
    trial = copy.deepcopy(b)
    saved = [o.K.copy() for o in obs]
    held = []
    for j, c in enumerate(trial.cams):
        out = test[j] & ((np.floor(obs[c].times / block).astype(np.int64) + j) % 2 == 0)[:, None]
        trial.keep[j] = trial.keep[j] & ~out
        held.append(out)
    try:
        adjust(trial, obs, inlier_px, rounds=1)
        trial.keep = held
        errors = [r for r, _, _ in _residuals_px(trial, obs)]
    finally:
        for o, K in zip(obs, saved, strict=True):
            o.K = K
    pooled = np.concatenate(errors) if errors else np.zeros(0)
    pooled = pooled[np.isfinite(pooled)]
    return float(np.median(pooled)) if len(pooled) else float("inf")


def supported(b: Bundle, obs: list[VideoObs]) -> np.ndarray:
    """(T, P) knots next to trusted observations of at least two cameras (the rest only follow the smoothness)."""
    T, P, _ = b.knots.X.shape
    count = np.zeros((T, P), dtype=np.int64)
    for j, (times, p, _, _) in enumerate(_obs_arrays(b, obs)):
        u = (times + b.offsets[b.cams[j]] - b.knots.t0) / b.knots.h
        k = np.clip(np.floor(u).astype(np.int64), 0, T - 2)
        seen = np.zeros((T, P), dtype=bool)
        seen[k, p] = True
        seen[k + 1, p] = True
        count += seen
    return count >= 2


def camera_residuals(b: Bundle, obs: list[VideoObs]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per camera: (M,) reprojection error in pixels, frame (M,), point (M,) of the observations still trusted."""
    return _residuals_px(b, obs)


def residuals_px(b: Bundle, obs: list[VideoObs]) -> list[np.ndarray]:
    return [r for r, _, _ in _residuals_px(b, obs)]


def rotation(rvec: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))[0]
