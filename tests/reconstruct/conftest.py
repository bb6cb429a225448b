"""Fixtures shared by the reconstruct tests."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_motion import synthetic_problem, truth_array

from reconstruct.solver.alternation import SolveResult, solve
from reconstruct.solver.problem import Problem


@pytest.fixture(scope="module")
def no_times() -> tuple[Problem, np.ndarray, SolveResult, np.ndarray]:
    """The paper's protocol as published: captures assigned to random cameras, neither times nor fps. Returns the
    problem, its truth (F, P, 3), the seed solve and the true capture times (F,)."""
    problem, truth = synthetic_problem(frames=200, points=6, seed=3)
    true_times = problem.times.copy()
    problem.times = np.full(problem.num_frames, np.nan)
    return problem, truth_array(problem, truth), solve(problem), true_times
