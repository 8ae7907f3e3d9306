"""The contact stage: the cone complementarity problem, its solvers and their derivatives.

- :mod:`.algorithms`: the problem (projection onto the friction cones, KKT residual) and the
  iterative algorithms (APGD, SPG, ADMM, PGS);
- :mod:`.implicit`: implicit differentiation of a converged solve;
- :mod:`.solver`: the solvers as components of a model.
"""

from jsnap._core.contact.algorithms import (
    ContactSolution,
    KKTTerms,
    SqueezeProblem,
    kkt_residual,
    kkt_terms,
    project_cone,
    solve_admm,
    solve_apgd,
    solve_pgs,
    solve_spg,
    symmetric_squeeze_problem,
)
from jsnap._core.contact.implicit import implicit_solver
from jsnap._core.contact.solver import ADMM, APGD, PGS, SPG, AbstractContactSolver

__all__ = [
    "ADMM",
    "APGD",
    "PGS",
    "SPG",
    "AbstractContactSolver",
    "ContactSolution",
    "KKTTerms",
    "SqueezeProblem",
    "implicit_solver",
    "kkt_residual",
    "kkt_terms",
    "project_cone",
    "solve_admm",
    "solve_apgd",
    "solve_pgs",
    "solve_spg",
    "symmetric_squeeze_problem",
]
