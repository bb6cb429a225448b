"""Focal self-calibration from the pairs' fundamental matrices (Mendonça–Cipolla).

With the principal points at the image centres, E = K_b F K_a is essential (two equal singular values) only for
the right focals; the cost sums (s1 - s2) / (s1 + s2) over the pairs. A common field-of-view grid, then per-camera
log grids (coordinate descent) and a Nelder-Mead polish in log focal find the minimum; no pair's Bougnoux formula
(unstable near degenerate configurations) is needed.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.optimize import minimize

from sfm.subject.observations import VideoObs
from sfm.subject.pairs import PairFit

log = logging.getLogger(__name__)

RANGE = (0.25, 4.0)  # focal searched, in units of the larger image side


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
