"""Start clocks from pair relations: both the link fit and the track search first relate videos two at a time
(own_u = alpha + beta own_v), then compose those relations along a spanning tree from the reference video."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import minimum_spanning_tree

from reconstruct.clocks.model import Clock


def chain_clocks(
    strength: np.ndarray, ref: int, centers: np.ndarray, relation: Callable[[int, int], tuple[float, float]]
) -> tuple[np.ndarray, np.ndarray]:
    """Clock coefficients (N, 3) and `reached` (N,) by composing pair relations along a maximum spanning tree of
    `strength` (N, N symmetric, 0 = no relation) from the reference. `relation(v, u)` gives (alpha, beta) with
    own_u = alpha + beta own_v. Composed clocks are affine (no drift term)."""
    num_videos = len(strength)
    coef = np.full((num_videos, 3), np.nan)
    coef[ref] = Clock.identity(centers[ref]).coef
    reached = np.zeros(num_videos, dtype=bool)
    reached[ref] = True
    if num_videos < 2 or not strength.any():
        return coef, reached
    tree = minimum_spanning_tree(sp.csr_matrix(np.where(strength > 0, 1.0 / (1.0 + strength), 0.0)))
    tree = (tree + tree.T).tocsr()
    queue = [ref]
    while queue:
        v = queue.pop()
        for u in tree.indices[tree.indptr[v] : tree.indptr[v + 1]]:
            if reached[u]:
                continue
            alpha, beta = relation(v, int(u))
            # g_u(own_u) = g_v(own_v) with own_v = (own_u - alpha) / beta; g_v linear: offset o_v + rate r_v own
            o_v = coef[v, 0] - coef[v, 1] * centers[v]
            r_v = coef[v, 1]
            o_u, r_u = o_v - r_v * alpha / beta, r_v / beta
            coef[u] = [o_u + r_u * centers[u], r_u, 0.0]
            reached[u] = True
            queue.append(int(u))
    return coef, reached
