"""Options and statistics of the W-step, shared by the working set (`wstep`) and the QP solvers (`active_set`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass(kw_only=True)
class WStepOptions:
    """Options of the W-step (`solve_w`); `SolverOptions.w_step` carries them into a solve.

    lambda1: weight of the structural coherence Psi1 (a solve sets it from `SolverOptions.lambda1`).
    nearest: initial working-set neighbours per column (nearest shapes of other videos).
    tolerance: the active-set methods' and FISTA's stopping tests (KKT violation, and the change of W per FISTA
    step, in W units).
    max_active_set_iterations: budget of the primal-dual active-set method (PDAS); FISTA finishes a solve past it.
    cycle_changes: a column whose free entries changed in this many PDAS iterations changes one entry at a time
    from then on (`limit_changes`).
    stall_iterations: PDAS stops with its best iterate once this many iterations have not lowered g by
    `active_set.STALL_TOLERANCE` (it can wander near a degenerate optimum, flipping a few entries in and out).
    max_primal_iterations: budget of the monotone primal active-set method that finishes when PDAS cycles.
    kkt_tolerance: entries whose KKT violation / L_f (the weight a gradient step would give them) exceeds this join
    the working set.
    max_rounds: rounds of KKT check + re-solve on the grown working set.
    full_kkt_check: check every allowed entry (O(F^2 P) per W-step); disable for very long captures.
    workers: threads for the independent components of large KKT systems (a solve sets it from
    `SolverOptions.workers`).
    """

    lambda1: float = 0.05
    nearest: int = 8
    tolerance: float = 1e-6
    # Warm-started W-steps settle in a few iterations; cold starts with a grown working set need more, still far
    # cheaper than FISTA.
    max_active_set_iterations: int = 60
    cycle_changes: int = 8
    stall_iterations: int = 5
    max_primal_iterations: int = 20
    # The outer test tolerates far more than the inner solve's: a smaller one grows the working sets for the same
    # accuracy at a much higher cost.
    kkt_tolerance: float = 1e-3
    max_rounds: int = 3
    full_kkt_check: bool = True
    workers: int = 2

    @classmethod
    def exact(cls, **overrides: Any) -> WStepOptions:
        """Settings under which the W-step returns the minimizer of g on the full problem: KKT tests at round-off,
        no stall guard, budgets that are not reached (`SolverOptions(w_step=WStepOptions.exact())`). The default
        stops above the optimum with a sparser W that reconstructs better (docs/solver.md)."""
        settings: dict[str, Any] = {
            "kkt_tolerance": 1e-12,
            "tolerance": 1e-12,
            "max_rounds": 100,
            "stall_iterations": 10**6,
            "max_active_set_iterations": 500,
            "max_primal_iterations": 500,
        }
        return cls(**{**settings, **overrides})


@dataclass(kw_only=True)
class WStepStats:
    iterations: int = 0
    rounds: int = 0
    added: int = 0
    working_set: int = 0
    objective: float = float("nan")
    converged: bool = False
    fallbacks: int = 0  # working-set solves the active-set method left to FISTA
    history: list[float] = field(default_factory=list)
