"""Euclidean projection of many vectors onto the probability simplex, restricted to allowed entries."""

from __future__ import annotations

import numpy as np

# Stand-in for "not allowed": sorts last and never enters the support; finite so that cumulative sums stay finite
# where they matter (before the first excluded entry).
_EXCLUDED = -1e30


def project_rows_to_simplex(values: np.ndarray, allowed: np.ndarray | None = None) -> np.ndarray:
    """Project each row of `values` (n, k) onto {w >= 0, sum w = 1, w = 0 where not allowed} (Duchi et al. 2008).

    `allowed` (n, k) bool; every row must allow at least one entry. O(n k log k), vectorized over rows.
    """
    v = np.asarray(values, dtype=float)
    if allowed is not None:
        v = np.where(allowed, v, _EXCLUDED)
    u = -np.sort(-v, axis=1)
    css = np.cumsum(u, axis=1)
    k = np.arange(1, v.shape[1] + 1)
    condition = u - (css - 1.0) / k > 0
    # Largest index where the condition holds (it holds on a prefix of the sorted row).
    rho = v.shape[1] - 1 - np.argmax(condition[:, ::-1], axis=1)
    theta = (css[np.arange(len(v)), rho] - 1.0) / (rho + 1)
    projected = np.maximum(v - theta[:, None], 0.0)
    if allowed is not None:
        projected[~allowed] = 0.0
    return projected
