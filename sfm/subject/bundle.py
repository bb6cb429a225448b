"""Bundle adjustment of static cameras, clock offsets, focals and a knot trajectory (scipy least_squares).

An observation at global time own + offset takes the linear interpolation of its point's two neighbouring knots,
so the offsets get gradients; a small acceleration penalty determines the knots no camera sees.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Callable

import cv2
import numpy as np
from scipy.optimize import OptimizeResult, least_squares
from scipy.sparse import csr_matrix
from threadpoolctl import threadpool_limits

from sfm.subject.bundle_model import Bundle, jacobian, obs_arrays, pack, residuals, stacked, unpack
from sfm.subject.observations import VideoObs

__all__ = ["Bundle", "adjust", "camera_residuals", "held_out_px", "residuals_px", "rotation", "supported"]

log = logging.getLogger(__name__)

# lsmr's stopping tolerance for each Gauss-Newton step. With every camera's intrinsics known, looser steps moved the
# cameras only within the RANSAC draw (TRF searches the plane of the step and the gradient), while lsmr's default
# spent most of the bundle's time on the step's last digits; with focals to find, looser steps converged more
# slowly, so the default stays there (docs/registration.md, "Speed of the subject path").
LSMR_TOL_KNOWN_K = 1e-4
LSMR_TOL_UNKNOWN_K = 1e-6
# Evaluations per round. The first rounds only find the outliers (false detections keep the robust loss from
# converging soon); the last one, on the inliers, runs longer: stopped early it left a noisy rig's cameras where
# the pair fits' RANSAC draw had started them (docs/registration.md, "The noise scale"). A held-out trial only
# compares, at the first rounds' cap.
NFEV_KNOWN_K, NFEV_UNKNOWN_K = 30, 50
NFEV_LAST = 100
FTOL_LAST = 1e-6


def adjust(b: Bundle, obs: list[VideoObs], inlier_px: float, rounds: int = 2, converge: bool = True) -> None:
    """`rounds` robust solves, the outliers of each but the last removed; the last one runs up to NFEV_LAST
    evaluations unless `converge` is False (a trial that only compares)."""
    for r in range(rounds):
        _solve(b, obs, inlier_px, last=converge and r == rounds - 1)
        if r < rounds - 1:
            n = 0
            for j, (res, f, p) in enumerate(_residuals_px(b, obs)):
                bad = res > 3 * inlier_px
                b.keep[j][f[bad], p[bad]] = False
                n += int(bad.sum())
            log.info("bundle round %d: %d outlier observation(s) removed", r + 1, n)


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


def _solve(b: Bundle, obs: list[VideoObs], inlier_px: float, last: bool = True) -> None:
    b.knots.X = _fill_knots(b.knots.X)
    arrays = obs_arrays(b, obs)
    x0 = pack(b, obs)

    def fun(x: np.ndarray) -> np.ndarray:
        return stacked(b, obs, x, arrays)

    def jac(x: np.ndarray) -> csr_matrix:
        return jacobian(b, obs, x, arrays)

    with threadpool_limits(1, user_api="blas"):  # lsmr's many small vector products only lose with BLAS threads
        sol = _least_squares(fun, jac, x0, inlier_px, all(obs[c].known_K for c in b.cams), last)
    rvec, t, focal, k1, k2, pp, off, X = unpack(b, obs, sol.x)
    b.rvec, b.t, b.focal, b.k1, b.k2, b.pp, b.knots.X = rvec, t, focal, k1, k2, pp, X
    for j, c in enumerate(b.cams):
        b.offsets[c] = off[j]
        if not obs[c].known_K:
            obs[c].K = np.array([[focal[j], 0, pp[j, 0]], [0, focal[j], pp[j, 1]], [0, 0, 1.0]])
    log.info("bundle: cost %.1f -> %.1f in %d evaluations", 0.5 * np.sum(fun(x0) ** 2), sol.cost, sol.nfev)


def _least_squares(
    fun: Callable[[np.ndarray], np.ndarray],
    jac: Callable[[np.ndarray], csr_matrix],
    x0: np.ndarray,
    inlier_px: float,
    known: bool,
    last: bool,
) -> OptimizeResult:
    return least_squares(
        fun,
        x0,
        jac=jac,
        loss="soft_l1",
        f_scale=inlier_px,
        x_scale="jac",
        max_nfev=NFEV_LAST if last else NFEV_KNOWN_K if known else NFEV_UNKNOWN_K,
        xtol=1e-8,
        ftol=FTOL_LAST if last else 1e-5,
        method="trf",
        tr_solver="lsmr",
        tr_options=dict.fromkeys(("atol", "btol"), LSMR_TOL_KNOWN_K if known else LSMR_TOL_UNKNOWN_K),
    )


def _residuals_px(b: Bundle, obs: list[VideoObs]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per camera: (M,) reprojection error in pixels, frame (M,), point (M,) of the kept observations."""
    arrays = obs_arrays(b, obs)
    res, _ = residuals(b, obs, pack(b, obs), arrays)
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
        adjust(trial, obs, inlier_px, rounds=1, converge=False)
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
    for j, (times, p, _, _) in enumerate(obs_arrays(b, obs)):
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
