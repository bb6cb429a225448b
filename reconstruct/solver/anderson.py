"""Anderson acceleration of the W-step/X-step alternation, seen as a fixed-point map X -> G(X) = X-step(W-step(X)).

Block-coordinate descent on this biconvex problem zig-zags: each alternation moves the points a little along a
nearly constant direction, and the final stage needs 50-150 alternations (docs/solver.md). Anderson mixing (type II,
Walker & Ni 2011) extrapolates from the last few (X, G(X)) pairs by a small least-squares fit, which turns that
linear convergence into a much faster one. The solver safeguards it: a mixed point is kept only if it lowers the
objective below what the plain step reached (Zhang, O'Donoghue, Boyd 2020 use the same kind of guard).
"""

from __future__ import annotations

import numpy as np


class AndersonMixer:
    """Keeps the last `memory` differences of iterates and residuals, all flattened to vectors, as the rows of two
    (memory, n) ring buffers: stacking the history anew for every mix copied the whole history every alternation
    (the order of the rows does not change the least-squares mix)."""

    def __init__(self, memory: int, regularization: float = 1e-10):
        self.memory = memory
        self.regularization = regularization
        self._last_x: np.ndarray | None = None
        self._last_g: np.ndarray | None = None
        self._df: np.ndarray | None = None  # (memory, n) differences of residuals f = G(x) - x
        self._dg: np.ndarray | None = None  # (memory, n) differences of G(x)
        self._count = 0  # differences stored (at most memory)
        self._next = 0  # the row the next difference goes to

    def reset(self) -> None:
        self._last_x = self._last_g = None
        self._count = self._next = 0

    def mix(self, x: np.ndarray, g: np.ndarray) -> np.ndarray:
        """Given an iterate x and its image g = G(x) (same shape), return the next iterate."""
        x_flat, g_flat = x.ravel(), g.ravel()
        residual = g_flat - x_flat
        if self._last_x is not None and self._last_g is not None:
            if self._df is None or self._dg is None or self._df.shape[1] != len(residual):
                self._df, self._dg = np.empty((2, self.memory, len(residual)))
            row = self._next
            np.subtract(residual, self._last_g, out=self._df[row])
            self._df[row] += self._last_x
            np.subtract(g_flat, self._last_g, out=self._dg[row])
            self._next = (row + 1) % self.memory
            self._count = min(self._count + 1, self.memory)
        self._last_x, self._last_g = x_flat.copy(), g_flat.copy()
        if self._count == 0 or self._df is None or self._dg is None:
            return g.copy()
        dF, dG = self._df[: self._count], self._dg[: self._count]
        gram = dF @ dF.T
        # Tikhonov on the normal equations: the rows become nearly dependent as the iteration settles.
        gram += self.regularization * max(float(np.trace(gram)), 1e-300) * np.eye(len(gram))
        try:
            gamma = np.linalg.solve(gram, dF @ residual)
        except np.linalg.LinAlgError:
            gamma = None
        mixed = None if gamma is None else g_flat - gamma @ dG
        if mixed is None or not np.all(np.isfinite(mixed)):
            # Degenerate history (e.g. iterates that stopped moving in some coordinates): start over from g.
            self.reset()
            return g.copy()
        return mixed.reshape(g.shape)
