"""The self-expressive solver of Zheng, Ji, Dunn, Frahm (PAMI; ICCV 2015), on in-memory arrays.

`alternation.solve` runs the paper's alternation: rays (`rays`), the initialization (`initialize`, candidate windows
`candidates`), the W-step (`wstep`: working set and KKT check; `active_set`, `simplex`: the QP solvers;
`wstep_options`: its options), the X-step (`xstep`) and Anderson acceleration (`anderson`). It reads no file and
imports nothing from the other stages.
"""

from reconstruct.solver.alternation import SolveResult, SolverOptions, solve
from reconstruct.solver.problem import Problem

__all__ = ["Problem", "SolveResult", "SolverOptions", "solve"]
