"""Implicit differentiation of the contact solve (the cone problem's solution as a function).

The contact solvers (``jsnap._core.contact.algorithms``) are bounded scans of hundreds of
projected-gradient iterations. Differentiating them unrolled stores every iterate and gives the
derivative of the *iteration*, not of the solution. Here the solution ``gamma*`` of

    min ½ γᵀWγ + γᵀq   s.t.  γ_i ∈ F_i(mu_i)  (active),  γ_i = 0  (inactive)

is differentiated through its fixed-point (natural-map) condition, which holds for any step
``η > 0`` exactly at a KKT point:

    G(γ; W, q, mu) = γ − Π_F(γ − η (W γ + q); mu) = 0.

By the implicit function theorem, ``dγ* = −(∂G/∂γ)⁻¹ ∂G/∂θ dθ`` with
``∂G/∂γ = I − P (I − η W)`` and ``P`` the Jacobian of the cone projection at ``γ* − η u*``
(block diagonal, 3×3 per contact: ``I`` for a sticking contact, ``0`` for a separating one, a
rank-2 map for a sliding one). This is ``jax.lax.custom_root``: forward and reverse mode, the
solver itself is never differentiated, and the warm start gets no derivative (the solution of
the convex problem does not depend on it). The tangent system is 3C × 3C (C = buffer slots):
formed densely and solved by LU.

Where the active set is degenerate (a contact exactly at the stick/slip or touch/separate
boundary) the solution is not differentiable; the derivative returned is that of the active set
classified at ``γ* − η u*``, a one-sided derivative.

Soft modes. The Delassus operator of a line contact is very ill-conditioned (eigenvalues down to
1e-7 ‖W‖, docs/contact.md): the distribution of force among neighbouring sample points. A solve
stopped at a KKT residual ``tol`` leaves forces in modes with eigenvalues below ~``tol ‖W‖``
unresolved, yet the exact tangent amplifies perturbations in those modes by ``‖W‖/λ``; through the
gap term ``max(φ, 0)/T`` such amplified perturbations feed back into the next steps and, in
stick–slip, grow from step to step. The tangent system is therefore regularised by a ridge
``_RIDGE_PER_TOL × tol`` (relative to ``η W``, whose norm is ≤ 1): the derivative of the
solution in the modes the solve resolves. Measured on the coarse default scene
(docs/differentiation.md): at ``tol = 1e-6`` it brings d(Σ F²)/dμ from 7 % to 0.5 % of the
converged-solve derivative; at ``tol = 1e-11`` it changes derivatives by < 1e-5.

Units as in ``_contact``: forces N, velocities mm/s, W mm/(N s).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jsnap._core.contact.algorithms import ContactSolution, _norm_estimate, _prepare, project_cone

__all__ = ["implicit_solver"]

# Ridge of the tangent system per unit of the solve's tolerance (units of η W, which is ≤ 1), and
# its bounds: above the round-off of a singular sticking block, below any physical mode.
_RIDGE_PER_TOL = 100.0
_RIDGE_MIN, _RIDGE_MAX = 1e-12, 1e-2


def implicit_solver(solve):
    """Wrap a contact solver so that its solution is differentiated implicitly.

    Args:
        solve: ``solve_apgd``, ``solve_admm``, ``solve_spg`` or ``solve_pgs`` (same signature as the
            returned function).

    Returns:
        ``solve_implicit(W, q, mu, mask, *, max_iters, tol, gamma0=None) -> ContactSolution``:
        the same forward result; derivatives of ``gamma`` with respect to ``W`` (3C, 3C),
        ``q`` (3C,) and ``mu`` (C,) by the implicit function theorem, none with respect to
        ``gamma0``; ``iterations``, ``residual`` and ``converged`` carry no derivative.
    """

    def solve_implicit(W, q, mu, mask, *, max_iters, tol, gamma0=None):
        W, q, mu, mask = (jnp.asarray(a) for a in (W, q, mu, mask))
        dtype = jnp.result_type(W.dtype, q.dtype)
        c = mu.shape[0]
        g0 = jnp.zeros((c, 3), dtype) if gamma0 is None else jnp.asarray(gamma0, dtype)
        # The step of the fixed-point map only scales the tangent system; no derivative.
        eta = jax.lax.stop_gradient(1.0 / _norm_estimate(_prepare(W, q, mu, mask)[0]))

        def G(g):
            Wm, qm, mu_, _, m3 = _prepare(W, q, mu, mask)
            flat = g.reshape(-1) * m3
            z = flat - eta * (Wm @ flat + qm)
            return g - (project_cone(z.reshape(c, 3), mu_).reshape(-1) * m3).reshape(c, 3)

        def run(_, guess):
            sol = solve(
                jax.lax.stop_gradient(W),
                jax.lax.stop_gradient(q),
                jax.lax.stop_gradient(mu),
                mask,
                max_iters=max_iters,
                tol=tol,
                gamma0=guess,
                differentiable=False,  # the iterations are never differentiated here
            )
            # (custom_root's JVP gives integer/bool aux outputs integer tangents, which JAX then
            # rejects: pass them as floats.)
            return sol.gamma, (sol.iterations.astype(dtype), sol.residual, sol.converged.astype(dtype))

        def tangent_solve(g_lin, y):
            n = 3 * c
            cols = jax.vmap(lambda e: g_lin(e.reshape(c, 3)).reshape(-1))(jnp.eye(n, dtype=dtype))
            A = cols.T  # A[:, i] = g_lin(e_i)
            ridge = jnp.clip(_RIDGE_PER_TOL * jnp.asarray(tol, dtype), _RIDGE_MIN, _RIDGE_MAX)
            return jnp.linalg.solve(A + ridge * jnp.eye(n, dtype=dtype), y.reshape(-1)).reshape(c, 3)

        guess = jax.lax.stop_gradient(g0)
        gamma, (it, res, conv) = jax.lax.custom_root(G, guess, run, tangent_solve, has_aux=True)
        return ContactSolution(
            gamma=gamma,
            iterations=jax.lax.stop_gradient(it).astype(jnp.int32),
            residual=jax.lax.stop_gradient(res),
            converged=jax.lax.stop_gradient(conv) > 0,
        )

    solve_implicit.__name__ = f"implicit_{getattr(solve, '__name__', 'solve')}"
    return solve_implicit
