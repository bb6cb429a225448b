"""The subject bundle's parameters, residuals and their analytic Jacobian (`sfm.subject.bundle` solves it).

Residuals, in order: per camera the (M, 2) reprojection errors in pixels (x then y of each observation), the knots'
acceleration penalty, then the gauge and the intrinsic priors. An observation at global time own + offset takes the
linear interpolation of its point's two neighbouring knots, so the offsets get gradients.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.sparse import csr_matrix

from sfm.subject.chain import Knots
from sfm.subject.geometry import rodrigues
from sfm.subject.observations import VideoObs

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


def n_intrinsics(b: Bundle) -> int:
    """Intrinsics adjusted per unknown-K camera: focal, k1, k2 (and cx, cy when the principal point is free)."""
    return 5 if b.pp_prior is not None else 3


def obs_arrays(b: Bundle, obs: list[VideoObs]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Per camera: frame times (M,), point index (M,), target (M, 2), kept mask rows."""
    out = []
    for j, c in enumerate(b.cams):
        o = obs[c]
        f, p = np.nonzero(b.keep[j])
        target = o.norm[f, p] if o.known_K else o.xy[f, p]
        out.append((o.times[f], p, target, f))
    return out


def layout(b: Bundle, obs: list[VideoObs]) -> tuple[list[int], list[int], list[int], int]:
    free_pose = [j for j in range(len(b.cams)) if j not in b.fixed_pose]
    free_k = [j for j, c in enumerate(b.cams) if not obs[c].known_K]
    free_o = [j for j, c in enumerate(b.cams) if c not in b.fixed_offset]
    n = 6 * len(free_pose) + n_intrinsics(b) * len(free_k) + len(free_o)
    return free_pose, free_k, free_o, n


def unpack(b: Bundle, obs: list[VideoObs], x: np.ndarray) -> tuple[np.ndarray, ...]:
    free_pose, free_k, free_o, n = layout(b, obs)
    rvec, t, focal, k1, k2, pp = b.rvec.copy(), b.t.copy(), b.focal.copy(), b.k1.copy(), b.k2.copy(), b.pp.copy()
    nk = n_intrinsics(b)
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


def pack(b: Bundle, obs: list[VideoObs]) -> np.ndarray:
    free_pose, free_k, free_o, _ = layout(b, obs)
    parts = [np.concatenate([b.rvec[j], b.t[j]]) for j in free_pose]
    parts += [np.array([b.focal[j], b.k1[j], b.k2[j], *(b.pp[j] if n_intrinsics(b) == 5 else [])]) for j in free_k]
    parts += [np.array([b.offsets[b.cams[j]]]) for j in free_o]
    return np.concatenate([*parts, b.knots.X.ravel()]) if parts else b.knots.X.ravel().copy()


def residuals(b: Bundle, obs: list[VideoObs], x: np.ndarray, arrays: list) -> tuple[list[np.ndarray], np.ndarray]:
    """Reprojection residuals per camera (M, 2) in pixels and the smoothness residuals (flattened)."""
    rvec, t, focal, k1, k2, pp, off, X = unpack(b, obs, x)
    R = rodrigues(rvec)  # (C, 3, 3)
    out = []
    for j, c in enumerate(b.cams):
        target = arrays[j][2]
        xy = _seen(b, j, arrays[j], off[j], X, R[j], t[j]).xy
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


@dataclass(kw_only=True)
class _Seen:
    """Camera j's kept observations projected: where they sit between knots and in the camera."""

    k: np.ndarray  # (M,) the knot before each observation's global time
    w_raw: np.ndarray  # (M,) its fraction of the way to the next knot, unclipped
    P3: np.ndarray  # (M, 3) the interpolated point
    R: np.ndarray  # (M, 3, 3) cam_from_world rotation of each observation
    z: np.ndarray  # (M,) depth (held away from 0)
    xy: np.ndarray  # (M, 2) normalized image coordinates


def _seen(b: Bundle, j: int, array: tuple, offset: float, X: np.ndarray, R: np.ndarray, t: np.ndarray) -> _Seen:
    """`array`: camera j's entry of `obs_arrays`; `offset`, `R`, `t`: its current clock offset and pose."""
    times, p, _, frames = array
    u = (times + offset - b.knots.t0) / b.knots.h
    k = np.clip(np.floor(u).astype(np.int64), 0, len(X) - 2)
    w_raw = u - k
    w = np.clip(w_raw, 0.0, 1.0)[:, None]
    P3 = (1 - w) * X[k, p] + w * X[k + 1, p]  # (M, 3)
    if j in b.frame_poses:
        Rf, tf = b.frame_poses[j]
        Rm = Rf[frames]
        Xc = np.einsum("mij,mj->mi", Rm, P3) + tf[frames]
    else:
        Rm = np.broadcast_to(R, (len(p), 3, 3))
        Xc = P3 @ R.T + t
    z = np.where(np.abs(Xc[:, 2]) < 1e-9, 1e-9, Xc[:, 2])
    return _Seen(k=k, w_raw=w_raw, P3=P3, R=Rm, z=z, xy=Xc[:, :2] / z[:, None])


def stacked(b: Bundle, obs: list[VideoObs], x: np.ndarray, arrays: list) -> np.ndarray:
    """`residuals` as one vector, in the rows of `jacobian`."""
    res, extra = residuals(b, obs, x, arrays)
    return np.concatenate([*(r.ravel() for r in res), extra])


def jacobian(b: Bundle, obs: list[VideoObs], x: np.ndarray, arrays: list) -> csr_matrix:
    """d `residuals` / d x, in the order of `residuals` (reprojections, acceleration, gauge, priors)."""
    free_pose, free_k, free_o, n = layout(b, obs)
    nk = n_intrinsics(b)
    col_pose = {j: 6 * i for i, j in enumerate(free_pose)}
    col_k = {j: 6 * len(free_pose) + nk * i for i, j in enumerate(free_k)}
    col_o = {j: 6 * len(free_pose) + nk * len(free_k) + i for i, j in enumerate(free_o)}
    rvec, t, focal, k1, k2, _, off, X = unpack(b, obs, x)
    R = rodrigues(rvec)  # (C, 3, 3)
    T, P, _ = X.shape
    rows: list[np.ndarray] = []
    cols: list[np.ndarray] = []
    vals: list[np.ndarray] = []

    def put(r: np.ndarray | int, c: np.ndarray | int, v: np.ndarray | float) -> None:
        v = np.asarray(v, dtype=float)
        rows.append(np.broadcast_to(r, v.shape).ravel())
        cols.append(np.broadcast_to(c, v.shape).ravel())
        vals.append(v.ravel())

    r0 = 0
    for j, c in enumerate(b.cams):
        p = arrays[j][1]
        M = len(p)
        rr = r0 + 2 * np.arange(M)[:, None] + np.arange(2)  # (M, 2) rows of x and y
        seen = _seen(b, j, arrays[j], off[j], X, R[j], t[j])
        k, P3, z, xy = seen.k, seen.P3, seen.z, seen.xy
        w = np.clip(seen.w_raw, 0.0, 1.0)[:, None]
        dxy = np.zeros((M, 2, 3))  # d xy / d Xc
        dxy[:, 0, 0] = dxy[:, 1, 1] = 1 / z
        dxy[:, :, 2] = -xy / z[:, None]
        o = obs[c]
        if o.known_K:
            A = dxy * np.array([o.K[0, 0], o.K[1, 1]])[None, :, None]  # (M, 2, 3) d res / d Xc
        else:
            r2 = (xy**2).sum(1)
            radial = 1 + k1[j] * r2 + k2[j] * r2**2
            slope = 2 * (k1[j] + 2 * k2[j] * r2)  # d radial / d r2, times 2 for d r2 / d xy = 2 xy
            D = focal[j] * (radial[:, None, None] * np.eye(2) + slope[:, None, None] * xy[:, :, None] * xy[:, None, :])
            A = D @ dxy
            if j in col_k:
                ck = col_k[j]
                put(rr, ck, xy * radial[:, None])
                put(rr, ck + 1, focal[j] * xy * r2[:, None])
                put(rr, ck + 2, focal[j] * xy * (r2**2)[:, None])
                if nk == 5:
                    put(rr[:, 0], ck + 3, np.ones(M))
                    put(rr[:, 1], ck + 4, np.ones(M))
        AR = A @ seen.R  # (M, 2, 3) d res / d P3
        knot = n + (k * P + p) * 3  # (M,) first column of knot k of each observation's point
        for step, weight in ((0, 1 - w), (1, w)):
            put(rr[:, :, None], (knot + 3 * P * step)[:, None, None] + np.arange(3), AR * weight[:, :, None])
        if j in col_o:
            inside = ((seen.w_raw >= 0) & (seen.w_raw < 1))[:, None]  # at a knot: the forward slope
            velocity = (X[k + 1, p] - X[k, p]) / b.knots.h * inside  # (M, 3) d P3 / d offset
            put(rr, col_o[j], np.einsum("mij,mj->mi", AR, velocity))
        if j in col_pose:
            cp = col_pose[j]
            dR = cv2.Rodrigues(np.asarray(rvec[j], dtype=np.float64))[1].reshape(3, 3, 3)  # [i] = d R / d rvec_i
            dXc_dr = np.einsum("iab,mb->mai", dR, P3)  # (M, 3, 3): d Xc / d rvec
            put(rr[:, :, None], cp + np.arange(3), A @ dXc_dr)
            put(rr[:, :, None], cp + 3 + np.arange(3), A)
        r0 += 2 * M
    scale = SMOOTH * float(np.mean([obs[c].focal for c in b.cams])) / b.depth
    idx = np.arange((T - 2) * P * 3)
    kk, rest = idx // (P * 3), idx % (P * 3)
    for dk, coefficient in ((0, 1.0), (1, -2.0), (2, 1.0)):
        put(r0 + idx, n + (kk + dk) * P * 3 + rest, np.full(len(idx), coefficient * scale))
    r0 += len(idx)
    if b.gauge is not None:
        ja, jb, d = b.gauge
        ca, cb = -R[ja].T @ t[ja], -R[jb].T @ t[jb]
        length = float(np.linalg.norm(ca - cb))
        unit = 1e3 / d * (ca - cb) / max(length, 1e-12)
        for pos, sign in ((ja, 1.0), (jb, -1.0)):
            if pos in col_pose:
                dR = cv2.Rodrigues(np.asarray(rvec[pos], dtype=np.float64))[1].reshape(3, 3, 3)
                dc_dr = -np.einsum("iba,b->ai", dR, t[pos])  # d (-R^T t) / d rvec
                put(r0, col_pose[pos] + np.arange(3), sign * unit @ dc_dr)
                put(r0, col_pose[pos] + 3 + np.arange(3), sign * unit @ -R[pos].T)
        r0 += 1
    for step in (1, 2):  # k1, then k2, near 0
        for j in free_k:
            put(r0, col_k[j] + step, 1.0 / DIST_SIGMA)
            r0 += 1
    n_obs = {j: np.sqrt(float(len(arrays[j][1]))) for j in free_k}
    if b.focal_prior is not None:
        for j in free_k:
            slope = n_obs[j] / (b.focal_sigma * focal[j]) if focal[j] > 1e-6 else 0.0
            put(r0, col_k[j], slope)
            r0 += 1
    if b.pp_prior is not None:
        for j in free_k:
            for axis in (3, 4):
                put(r0, col_k[j] + axis, n_obs[j] / b.pp_sigma)
                r0 += 1
    return csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(r0, n + X.size))
