"""The contact solver as a component of the model: which algorithm, how far, and how its
solution is differentiated.

The step asks ``model.contact.solver.solve(W, q, mu, mask, gamma0)``; the algorithm is the
solver's type, chosen when the model is built (``contact.solver`` in the scene), never a string
switch inside the step. Units as in :mod:`jsnap._core.contact.algorithms`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar

import equinox as eqx

from jsnap._core.contact.algorithms import ContactSolution, solve_admm, solve_apgd, solve_pgs, solve_spg
from jsnap._core.contact.implicit import implicit_solver

__all__ = ["ADMM", "APGD", "PGS", "SPG", "AbstractContactSolver"]


class AbstractContactSolver(eqx.Module):
    """A cone-complementarity solver.

    Attributes:
        max_iters: iteration cap per solve (static).
        tol: normalised KKT residual to stop at (static; see ``kkt_residual``).
        implicit: derivatives of the converged solution by the implicit function theorem
            (True), or of the unrolled iterations (False) (static).
    """

    max_iters: int = eqx.field(static=True, default=500)
    tol: float = eqx.field(static=True, default=1e-6)
    implicit: bool = eqx.field(static=True, default=True)

    algorithm: ClassVar[Callable]

    def __check_init__(self):
        if not (isinstance(self.max_iters, int) and self.max_iters >= 1):
            raise ValueError(f"{type(self).__name__}: max_iters must be a positive int, got {self.max_iters!r}")
        if not self.tol > 0:
            raise ValueError(f"{type(self).__name__}: tol must be > 0, got {self.tol!r}")

    def solve(self, W, q, mu, mask, gamma0=None) -> ContactSolution:
        """Solve ``min ½γᵀWγ + γᵀq`` over the friction cones of the active slots.

        Args: W (3C, 3C), q (3C,), mu (C,), mask (C,) bool, gamma0 (C, 3) warm start.
        """
        solve = type(self).algorithm
        if self.implicit:
            solve = implicit_solver(solve)
        return solve(W, q, mu, mask, max_iters=self.max_iters, tol=self.tol, gamma0=gamma0)


class APGD(AbstractContactSolver):
    """Accelerated projected gradient with adaptive restart (the default)."""

    algorithm = staticmethod(solve_apgd)


class SPG(AbstractContactSolver):
    """Spectral projected gradient: Barzilai–Borwein steps with a non-monotone line search.
    About half APGD's iterations on line contacts; its derivatives are taken implicitly."""

    algorithm = staticmethod(solve_spg)

    def __check_init__(self):
        super().__check_init__()
        if not self.implicit:
            # Measured: 0.3 % off the solution's derivative on a well-conditioned problem solved
            # to 1e-13, where unrolled APGD and ADMM agree with finite differences to 1e-5.
            raise ValueError(
                "SPG with unrolled derivatives: SPG's spectral steps reach past 2/||W||, so the "
                "unrolled iteration's derivative does not settle on the solution's; use implicit=True"
            )


class ADMM(AbstractContactSolver):
    """Alternating direction method of multipliers with ``(W + ρI)⁻¹`` formed once per solve:
    fewer iterations than APGD on the scenes' line contacts, two matvecs each."""

    algorithm = staticmethod(solve_admm)


class PGS(AbstractContactSolver):
    """Projected block Gauss–Seidel: the classic baseline, which stalls on the symmetric squeeze
    (kept to show that)."""

    algorithm = staticmethod(solve_pgs)
