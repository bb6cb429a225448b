"""Focal and radial distortion self-calibration from the pairs' correspondences.

Distortion first: radial distortion bends epipolar lines, so per camera a division-model coefficient is chosen
that makes every pair's correspondences fit one fundamental matrix best (Fitzgibbon's criterion, searched on a grid
by coordinate descent); the pairs' fundamental matrices are refitted on the undistorted pixels.

Focals (Mendonça–Cipolla):
With the principal points at the image centres, E = K_b F K_a is essential (two equal singular values) only for
the right focals; the cost sums (s1 - s2) / (s1 + s2) over the pairs. A common field-of-view grid, then per-camera
log grids (coordinate descent) and a Nelder-Mead polish in log focal find the minimum; no pair's Bougnoux formula
(unstable near degenerate configurations) is needed.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.optimize import minimize

from sfm.subject.geometry import sampson, weighted_fit
from sfm.subject.observations import VideoObs
from sfm.subject.pairs import PairFit

log = logging.getLogger(__name__)

RANGE = (0.25, 4.0)  # focal searched, in units of the larger image side
LAMBDAS = np.linspace(-0.6, 0.6, 25)  # division-model distortion searched, radius in units of the half long side
TRUNCATE_PX = 6.0  # epipolar errors are truncated here (outliers of the distorted fit)
MIN_GAIN = 0.9  # distortion is modelled only where it lowers the held-out epipolar error below this fraction
BLOCKS = 10  # a pair's correspondences (in time order) in alternate blocks: fitted on one half, tested on the other


def undistort_division(px: np.ndarray, lam: float, half: float) -> np.ndarray:
    """px: (N, 2) pixels from the image centre -> (N, 2) undistorted: px / (1 + lam (|px| / half)^2)."""
    r2 = (px**2).sum(-1, keepdims=True) / half**2
    return px / (1 + lam * r2)


def division_to_opencv(lam: float, focal: float, half: float, width: int, height: int) -> np.ndarray:
    """(5,) OpenCV k1, k2, 0, 0, 0 closest (least squares over the image's radii) to the division model: a start
    for the bundle adjustment, which refines k1, k2."""
    rd = np.linspace(1e-3, 0.5 * float(np.hypot(width, height)), 64)  # distorted radii (pixels)
    ru = rd / (1 + lam * (rd / half) ** 2)  # undistorted radii
    rho2 = (ru / focal) ** 2
    # rd = ru (1 + k1 rho^2 + k2 rho^4): linear in k1, k2
    A = np.column_stack([ru * rho2, ru * rho2**2])
    k, *_ = np.linalg.lstsq(A, rd - ru, rcond=None)
    return np.array([k[0], k[1], 0.0, 0.0, 0.0])


def _pair_error(pa: np.ndarray, pb: np.ndarray, la: float, lb: float, ha: float, hb: float) -> tuple[float, np.ndarray]:
    """Mean truncated squared Sampson error (pixels^2) of one F fitted to the undistorted correspondences, and
    that F in centred undistorted pixels. pa, pb: (N, 2) centred distorted pixels."""
    xa = undistort_division(pa, la, ha) / ha
    xb = undistort_division(pb, lb, hb) / hb
    F = weighted_fit(xa[None], xb[None], np.ones((1, len(xa))), essential=False)[0]
    err = sampson(F[None], xa, xb)[0] * ha * hb  # (N,) squared, in pixels^2 (approximately)
    F_px = np.diag([1 / hb, 1 / hb, 1.0]) @ F @ np.diag([1 / ha, 1 / ha, 1.0])
    return float(np.minimum(err, TRUNCATE_PX**2).mean()), F_px


def _search(
    use: list[PairFit], px: list, half: dict[int, float], unknown: list[int], part: int | None
) -> dict[int, float]:
    """Coefficients minimizing the pairs' epipolar error on the correspondences of `part` (0, 1 or all)."""
    sel = [_part(len(pa), part) for pa, _ in px]

    def cost(trial: dict[int, float], only: int | None = None) -> float:
        total = 0.0
        for f, (pa, pb), s in zip(use, px, sel, strict=True):
            if only is None or only in (f.a, f.b):
                total += _pair_error(pa[s], pb[s], trial.get(f.a, 0.0), trial.get(f.b, 0.0), half[f.a], half[f.b])[0]
        return total

    shared = [cost(dict.fromkeys(unknown, float(g))) for g in LAMBDAS]  # one lens for all first
    lam = dict.fromkeys(unknown, float(LAMBDAS[int(np.argmin(shared))]))
    step = LAMBDAS[1] - LAMBDAS[0]
    for sweep in range(2):  # coordinate descent per camera, then a finer grid around each
        for i in unknown:
            grid = LAMBDAS if sweep == 0 else lam[i] + np.linspace(-step, step, 9)
            costs = [cost({**lam, i: float(g)}, only=i) for g in grid]
            lam[i] = float(grid[int(np.argmin(costs))])
    return lam


def _part(n: int, part: int | None) -> np.ndarray:
    """(n,) mask of the correspondences in alternate blocks (they are in time order): part 0 or 1, None = all."""
    if part is None:
        return np.ones(n, dtype=bool)
    return (np.arange(n) * BLOCKS // max(n, 1)) % 2 == part


def _held_out(use: list[PairFit], px: list, half: dict[int, float], lam: dict[int, float], train: int) -> float:
    """Epipolar error on the other part's correspondences of F fitted on part `train` with coefficients `lam`."""
    total = 0.0
    for f, (pa, pb) in zip(use, px, strict=True):
        fit, test = _part(len(pa), train), _part(len(pa), 1 - train)
        la, lb = lam.get(f.a, 0.0), lam.get(f.b, 0.0)
        F = _pair_error(pa[fit], pb[fit], la, lb, half[f.a], half[f.b])[1]
        xa = undistort_division(pa[test], la, half[f.a])
        xb = undistort_division(pb[test], lb, half[f.b])
        err = sampson(F[None], xa, xb)[0]
        total += float(np.minimum(err, TRUNCATE_PX**2).mean()) if len(err) else 0.0
    return total


def estimate_distortion(obs: list[VideoObs], fits: list[PairFit]) -> dict[int, float]:
    """Division-model coefficient of every unknown-K camera in a pair, and the pairs' `F_px` refitted on the
    undistorted pixels; all 0 (and the fits untouched) unless the coefficients found on alternate time blocks
    lower the other blocks' epipolar error below MIN_GAIN of what no distortion gives (held-out, not the fit's own
    residual). The fits' xa, xb must be normalized with the current focals and no distortion."""
    use = [f for f in fits if f.F_px is not None]
    unknown = sorted({i for f in use for i in (f.a, f.b) if not obs[i].known_K})
    if not unknown:
        return {}
    half = {i: 0.5 * max(o.video.width, o.video.height) for i, o in enumerate(obs)}
    px = [(f.xa * obs[f.a].focal, f.xb * obs[f.b].focal) for f in use]
    none = dict.fromkeys(unknown, 0.0)
    before = after = 0.0
    for part in (0, 1):
        before += _held_out(use, px, half, none, part)
        after += _held_out(use, px, half, _search(use, px, half, unknown, part), part)
    if not after < MIN_GAIN * before:
        log.info("distortion: held-out epipolar error %.3f -> %.3f px^2: not modelled", before, after)
        return none
    lam = _search(use, px, half, unknown, None)
    log.info(
        "distortion: held-out epipolar error %.3f -> %.3f px^2; modelled: %s",
        before,
        after,
        ", ".join(f"{obs[i].name} {lam[i]:+.3f}" for i in unknown),
    )
    for f, (pa, pb) in zip(use, px, strict=True):
        f.F_px = _pair_error(pa, pb, lam.get(f.a, 0.0), lam.get(f.b, 0.0), half[f.a], half[f.b])[1]
    return lam


def _cost_terms(F: np.ndarray, fa: np.ndarray, fb: np.ndarray) -> np.ndarray:
    """F: (N, 3, 3) with pb^T F pa = 0 in centred pixels, fa, fb: (N,) -> (N,) (s1 - s2) / (s1 + s2) of Kb F Ka."""
    E = F * np.stack([fb, fb, np.ones_like(fb)], -1)[:, :, None] * np.stack([fa, fa, np.ones_like(fa)], -1)[:, None]
    s = np.linalg.svd(E, compute_uv=False)  # (N, 3)
    return (s[:, 0] - s[:, 1]) / np.maximum(s[:, 0] + s[:, 1], 1e-300)


def self_calibrate(obs: list[VideoObs], fits: list[PairFit]) -> dict[int, float]:
    """Focal (pixels) of every unknown-K camera in a pair with a fundamental matrix; known focals stay fixed."""
    use = [f for f in fits if f.F_px is not None]
    unknown = sorted({i for f in use for i in (f.a, f.b) if not obs[i].known_K})
    if not unknown:
        return {}
    F = np.array([p / np.linalg.norm(p) for p in (np.asarray(f.F_px) for f in use)])  # (N, 3, 3)
    ia = np.array([f.a for f in use])
    ib = np.array([f.b for f in use])
    w = np.sqrt(np.array([max(f.distinct, 1) for f in use], dtype=float))  # (N,) better spread pairs count more
    w = w / w.sum()
    size = np.array([max(o.video.width, o.video.height) for o in obs], dtype=float)  # (V,)
    base = np.array([o.focal for o in obs])  # (V,) known focals (the unknown ones get overwritten)
    col = {i: k for k, i in enumerate(unknown)}

    def focals(logf: np.ndarray) -> np.ndarray:
        f = base.copy()
        f[unknown] = np.exp(logf) * size[unknown]
        return f

    def cost(logf: np.ndarray) -> float:
        f = focals(logf)
        return float((w * _cost_terms(F, f[ia], f[ib])).sum())

    grid = np.linspace(np.log(RANGE[0]), np.log(RANGE[1]), 49)
    costs = [cost(np.full(len(unknown), g)) for g in grid]  # one common field of view first
    x = np.full(len(unknown), grid[int(np.argmin(costs))])
    for _ in range(3):  # coordinate descent on per-camera grids
        for k in range(len(unknown)):
            trial = np.repeat(x[None], len(grid), 0)
            trial[:, k] = grid
            x = trial[int(np.argmin([cost(t) for t in trial]))]
    sol = minimize(cost, x, method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-9, "maxiter": 400 * len(x)})
    x = np.clip(sol.x, np.log(RANGE[0]), np.log(RANGE[1]))
    log.info("self-calibration: cost %.4f over %d pair(s)", cost(x), len(use))
    f = focals(x)
    return {i: float(f[i]) for i in unknown if i in col}
