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
    """Keeps the last `memory` differences of iterates and residuals, all flattened to vectors."""

    def __init__(self, memory: int, regularization: float = 1e-10):
        self.memory = memory
        self.regularization = regularization
        self._last_x: np.ndarray | None = None
        self._last_g: np.ndarray | None = None
        self._dx: list[np.ndarray] = []  # differences of residuals f = G(x) - x
        self._dg: list[np.ndarray] = []  # differences of G(x)

    def reset(self) -> None:
        self._last_x = self._last_g = None
        self._dx.clear()
        self._dg.clear()

    def mix(self, x: np.ndarray, g: np.ndarray) -> np.ndarray:
        """Given an iterate x and its image g = G(x) (same shape), return the next iterate."""
        x_flat, g_flat = x.ravel(), g.ravel()
        residual = g_flat - x_flat
        if self._last_x is not None and self._last_g is not None:
            self._dx.append(residual - (self._last_g - self._last_x))
            self._dg.append(g_flat - self._last_g)
            if len(self._dx) > self.memory:
                self._dx.pop(0)
                self._dg.pop(0)
        self._last_x, self._last_g = x_flat.copy(), g_flat.copy()
        if not self._dx:
            return g.copy()
        dF = np.stack(self._dx, axis=1)  # (n, m)
        dG = np.stack(self._dg, axis=1)
        gram = dF.T @ dF
        # Tikhonov on the normal equations: the columns become nearly dependent as the iteration settles.
        gram += self.regularization * max(float(np.trace(gram)), 1e-300) * np.eye(len(gram))
        try:
            gamma = np.linalg.solve(gram, dF.T @ residual)
        except np.linalg.LinAlgError:
            gamma = None
        mixed = None if gamma is None else g_flat - dG @ gamma
        if mixed is None or not np.all(np.isfinite(mixed)):
            # Degenerate history (e.g. iterates that stopped moving in some coordinates): start over from g.
            self.reset()
            return g.copy()
        return mixed.reshape(g.shape)
