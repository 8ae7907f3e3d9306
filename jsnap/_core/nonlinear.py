"""St. Venant–Kirchhoff (SVK) nonlinear FEM and its time integrators: the stability reference.

Geometric nonlinearity, linear material, on the same tetrahedral meshes and elements as
``_fem`` (P1 or P2, base clamped, node-major dofs ``3 * node + component``, free dofs only).
The model is energy-based: with the displacement gradient ``H = grad u``, ``F = I + H`` and the
Green–Lagrange strain ``E = 1/2 (F'F - I) = 1/2 (H + H' + H'H)``,

    W(u) = sum_elements sum_quadrature  w |J| (lambda/2 tr(E)^2 + mu tr(E^2)),

the internal force is ``jax.grad(W)`` and the tangent stiffness its Jacobian, formed element by
element (``jax.hessian`` of one element's energy, scattered into a dense matrix: the benchmark
meshes have a few hundred dofs). At ``u = 0`` the tangent is exactly ``_fem``'s
``K = lambda K_lam + mu K_mu``; the mass is ``rho M1`` from ``_fem`` (consistent).

Integrators of ``M a + grad W(u) = 0`` (no damping, no load), one function per method, each a
pure step ``(u, v) -> (u, v)`` on free dofs (mm, mm/s), run by :func:`simulate`:

* ``"linearised_euler"``: one Newton iteration of backward Euler from ``v_{k+1} = 0`` (the
  linearly implicit step of Baraff & Witkin 1998):
  ``(M + T^2 K_t(u_k)) v_{k+1} = M v_k - T f(u_k)``, ``u_{k+1} = u_k + T v_{k+1}``.
* ``"linearised_midpoint"``: one Newton iteration of the implicit midpoint rule from
  ``vbar = 0``: ``(2M/T + T/2 K_t(u_k)) vbar = (2/T) M v_k - f(u_k)``; it is PMI with the
  tangent re-linearised at every step (equal to linear PMI when ``f = K u``).
* ``"newton_midpoint"``: the implicit midpoint rule solved by Newton's method to a relative
  residual ``rtol``: ``(2/T) M (vbar - v_k) + f(u_k + T/2 vbar) = 0``; steps whose Newton
  iteration does not converge within ``max_iter`` are reported, not hidden.
* ``"verlet"``: velocity Verlet (symplectic, explicit; consistent mass, solved by Cholesky).
* ``"linear_pmi"``: passive midpoint integration of the linearised model (``jsnap._core.pmi``).

Units: mm, N, MPa, s, tonne; energies in N·mm (mJ).
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from jsnap._core.params import Material, lame
from jsnap._core.pmi import SparseBlocks, energy, pmi_operator, pmi_step
from jsnap._core.util import x64

__all__ = [
    "METHODS",
    "SVKModel",
    "Trajectory",
    "internal_force",
    "simulate",
    "static_deflection",
    "strain_energy",
    "strain_energy_nodal",
    "tangent",
]

METHODS = ("linearised_euler", "linearised_midpoint", "newton_midpoint", "verlet", "linear_pmi")


class SVKModel(eqx.Module):
    """SVK model of one mesh and element, clamped at the base (free dofs only).

    Attributes:
        cells: (m, a) node indices of each element (a = 4 or 10).
        grads: (m, q, a, 3) gradients of the a shape functions at the q quadrature points, 1/mm.
        dx: (m, q) quadrature weights times |J|, mm^3.
        free: (nf,) free dofs (into the node-major 3N vector).
        local: (m, 3a) free-dof index of each element dof (``3 * a_local + component``), nf
            where the dof is clamped (dropped when scattering).
        linear: the linearised model's blocks K_lam, K_mu, M1 on the free dofs.
        n_nodes: static number of nodes N.
    """

    cells: jax.Array
    grads: jax.Array
    dx: jax.Array
    free: jax.Array
    local: jax.Array
    linear: SparseBlocks
    n_nodes: int = eqx.field(static=True)

    @property
    def n_free(self) -> int:
        return self.free.shape[0]


def _density(H, lam, mu):
    """SVK energy density (MPa = N·mm/mm^3) of displacement gradients H (..., 3, 3).

    E is formed as 1/2 (H + H' + H'H), not 1/2 (F'F - I): the latter loses the small strains
    of a nearly undeformed body to cancellation against I.
    """
    E = 0.5 * (H + jnp.swapaxes(H, -1, -2) + jnp.swapaxes(H, -1, -2) @ H)
    tr = jnp.trace(E, axis1=-2, axis2=-1)
    return 0.5 * lam * tr**2 + mu * jnp.sum(E * E, axis=(-2, -1))


def _element_energy(ue, grads_e, dx_e, lam, mu):
    """Energy (N·mm) of one element: ue (a, 3) mm, grads_e (q, a, 3), dx_e (q,)."""
    H = jnp.einsum("ai,qaj->qij", ue, grads_e)
    return dx_e @ _density(H, lam, mu)


def strain_energy_nodal(model: SVKModel, mat: Material, U) -> jax.Array:
    """Strain energy W (N·mm) of a nodal displacement field U (N, 3) in mm, clamped or not
    (every node may move: used to check frame invariance)."""
    lam, mu = lame(mat.E, mat.nu)
    H = jnp.einsum("eai,eqaj->eqij", U[model.cells], model.grads)
    return jnp.sum(model.dx * _density(H, lam, mu))


def _nodal(model: SVKModel, u):
    full = jnp.zeros(3 * model.n_nodes, u.dtype).at[model.free].set(u)
    return full.reshape(model.n_nodes, 3)


def strain_energy(model: SVKModel, mat: Material, u) -> jax.Array:
    """Strain energy W(u) (N·mm) of free-dof displacements u (nf,) in mm."""
    return strain_energy_nodal(model, mat, _nodal(model, u))


@jax.jit
def internal_force(model: SVKModel, mat: Material, u) -> jax.Array:
    """Internal force ``grad W(u)`` (nf,) in N; equals ``K u`` to first order in u."""
    return jax.grad(strain_energy, argnums=2)(model, mat, u)


@jax.jit
def tangent(model: SVKModel, mat: Material, u) -> jax.Array:
    """Dense tangent stiffness ``d grad W / du`` (nf, nf) in N/mm at u (nf,) mm.

    Element Hessians (``jax.hessian`` of one element's energy, (3a, 3a)) scattered into the
    free-dof matrix: the cost is that of m small Hessians, not nf reverse passes.
    """
    lam, mu = lame(mat.E, mat.nu)
    ue = _nodal(model, u)[model.cells]  # (m, a, 3)
    a3 = 3 * model.cells.shape[1]

    def one(ue, g, w):
        h = jax.hessian(_element_energy)(ue, g, w, lam, mu)
        return h.reshape(a3, a3)

    He = jax.vmap(one)(ue, model.grads, model.dx)
    n = model.n_free
    idx = model.local
    K = jnp.zeros((n, n), He.dtype)
    return K.at[idx[:, :, None], idx[:, None, :]].add(He, mode="drop")


@x64
def static_deflection(
    model: SVKModel, mat: Material, load, probe, target: float, increments: int = 8, rtol: float = 1e-10
):
    """Nonlinear static equilibrium ``grad W(u) = P load`` with ``probe @ u = target``
    (displacement control: the load factor P is the extra unknown).

    Newton's method on the bordered system ``[K_t, -load; probe', 0]``, the target reached in
    ``increments`` equal steps, each iterated until the force residual is below ``rtol``
    times ``|P load|`` (at most 30 iterations; a step that does not converge raises).

    Args:
        load: (nf,) load shape, N (e.g. ``K u`` of a linear static solution).
        probe: (nf,) weights of the controlled displacement, mm.
        target: the value of ``probe @ u`` to reach, mm.

    Returns:
        (u (nf,) mm, P): the equilibrium and its load factor.
    """
    load, probe = jnp.asarray(load), jnp.asarray(probe)
    n = model.n_free

    @jax.jit
    def newton(u, P, goal):
        A = jnp.zeros((n + 1, n + 1)).at[:n, :n].set(tangent(model, mat, u))
        A = A.at[:n, n].set(-load).at[n, :n].set(probe)
        r = jnp.concatenate([internal_force(model, mat, u) - P * load, (probe @ u - goal)[None]])
        d = jnp.linalg.solve(A, -r)
        u, P = u + d[:n], P + d[n]
        res = internal_force(model, mat, u) - P * load
        return u, P, jnp.linalg.norm(res) / (jnp.abs(P) * jnp.linalg.norm(load))

    u, P = jnp.zeros(n), jnp.asarray(0.0)
    for i in range(1, increments + 1):
        for _ in range(30):
            u, P, err = newton(u, P, target * i / increments)
            if err <= rtol:
                break
        else:
            raise RuntimeError(f"static_deflection: no convergence at increment {i} (residual {err:.2e})")
    return u, P


# --------------------------------------------------------------------------------------------
# Integrators
# --------------------------------------------------------------------------------------------


class Trajectory(NamedTuple):
    """Per-step record of :func:`simulate` over n steps.

    Attributes:
        energy: (n + 1,) discrete energy 1/2 v'Mv + W(u) (1/2 u'Ku for linear PMI), N·mm,
            starting with the initial state's.
        probe: (n + 1,) ``probe @ u``, mm (e.g. the tip deflection).
        iterations: (n,) Newton iterations per step (1 for the linearised steps, 0 explicit).
        converged: (n,) whether the step's solve met its tolerance (always True but for
            ``newton_midpoint``).
    """

    energy: jax.Array
    probe: jax.Array
    iterations: jax.Array
    converged: jax.Array


def _mass(model: SVKModel, mat: Material):
    return mat.rho * model.linear.dense(model.linear.m1)


def _linearised_euler(model, mat, dt, M, u, v):
    A = M + dt**2 * tangent(model, mat, u)
    v1 = jnp.linalg.solve(A, M @ v - dt * internal_force(model, mat, u))
    return u + dt * v1, v1


def _linearised_midpoint(model, mat, dt, M, u, v):
    A = (2.0 / dt) * M + (0.5 * dt) * tangent(model, mat, u)
    vbar = jnp.linalg.solve(A, (2.0 / dt) * (M @ v) - internal_force(model, mat, u))
    return u + dt * vbar, 2.0 * vbar - v


def _newton_midpoint(model, mat, dt, M, u, v, rtol, max_iter):
    """Implicit midpoint by Newton from ``vbar = v``. Returns (u, v, iterations, converged).

    The residual ``R = (2/T) M (vbar - v) + f(u + T/2 vbar)`` (N) is measured against the size
    of its two terms at the start of the step, ``|(2/T) M v| + |f(u)|``; a step stops when
    ``|R| <= rtol`` times that, after ``max_iter`` iterations, or when R is not finite.
    """
    Mv = (2.0 / dt) * (M @ v)
    scale = jnp.linalg.norm(Mv) + jnp.linalg.norm(internal_force(model, mat, u))

    def residual(vbar):
        return (2.0 / dt) * (M @ vbar) - Mv + internal_force(model, mat, u + 0.5 * dt * vbar)

    def cond(c):
        _, r, it = c
        rn = jnp.linalg.norm(r)
        return (rn > rtol * scale) & jnp.isfinite(rn) & (it < max_iter)

    def body(c):
        vbar, r, it = c
        J = (2.0 / dt) * M + (0.5 * dt) * tangent(model, mat, u + 0.5 * dt * vbar)
        vbar = vbar - jnp.linalg.solve(J, r)
        return vbar, residual(vbar), it + 1

    vbar, r, it = jax.lax.while_loop(cond, body, (v, residual(v), 0))
    ok = jnp.linalg.norm(r) <= rtol * scale
    return u + dt * vbar, 2.0 * vbar - v, it, ok


def _verlet(model, mat, dt, chol, u, v):
    def acc(u):
        return -jax.scipy.linalg.cho_solve((chol, True), internal_force(model, mat, u))

    vh = v + 0.5 * dt * acc(u)
    u1 = u + dt * vh
    return u1, vh + 0.5 * dt * acc(u1)


@x64
@partial(jax.jit, static_argnames=("method", "n_steps", "max_iter"))
def simulate(
    method: str,
    model: SVKModel,
    mat: Material,
    dt,
    u0,
    v0,
    n_steps: int,
    probe=None,
    rtol=1e-10,
    max_iter: int = 40,
    stop_ratio=jnp.inf,
) -> Trajectory:
    """Integrate the undamped, unloaded SVK model (or its linearisation) from (u0, v0).

    Args:
        method: one of :data:`METHODS` (static).
        model: from :func:`svk_model`.
        mat: material (E, nu, rho used; damping ignored: this is the D = 0 benchmark).
        dt: time step T, s.
        u0, v0: (nf,) initial displacement (mm) and velocity (mm/s) on the free dofs.
        n_steps: number of steps (static).
        probe: (nf,) weights of the recorded scalar ``probe @ u`` (mm); default zeros.
        rtol, max_iter: Newton tolerance and iteration cap of ``"newton_midpoint"``.
        stop_ratio: once the energy exceeds ``stop_ratio`` times the initial energy the run is
            declared diverged and its state set to NaN (every later step is then skipped).
            Default: never.

    Returns:
        A :class:`Trajectory`. A diverged or overflowing run is recorded as NaN to the end
        (its steps are skipped): the step count and shapes never depend on the data.
    """
    if method not in METHODS:
        raise ValueError(f"method = {method!r}: must be one of {', '.join(METHODS)}")
    dt = jnp.asarray(dt, jnp.float64)
    probe = jnp.zeros_like(u0) if probe is None else probe
    M = _mass(model, mat)
    one, yes = jnp.asarray(1), jnp.asarray(True)

    if method == "linear_pmi":
        blocks = model.linear
        op = pmi_operator(blocks, Material.create(mat.E, mat.nu, mat.rho), dt)
        zero = jnp.zeros_like(u0)

        def step(u, v):
            u, v, _ = pmi_step(blocks, op, u, v, zero, refine=1)
            return u, v, one, yes

        def total(u, v):
            return energy(blocks, op, u, v)

    else:

        def total(u, v):
            return 0.5 * v @ (M @ v) + strain_energy(model, mat, u)

        if method == "linearised_euler":

            def step(u, v):
                return (*_linearised_euler(model, mat, dt, M, u, v), one, yes)

        elif method == "linearised_midpoint":

            def step(u, v):
                return (*_linearised_midpoint(model, mat, dt, M, u, v), one, yes)

        elif method == "newton_midpoint":

            def step(u, v):
                return _newton_midpoint(model, mat, dt, M, u, v, rtol, max_iter)

        else:  # verlet
            chol = jnp.linalg.cholesky(0.5 * (M + M.T))

            def step(u, v):
                return (*_verlet(model, mat, dt, chol, u, v), jnp.asarray(0), yes)

    e0 = total(u0, v0)

    it_shape = jax.eval_shape(step, u0, v0)[2]

    def skip(u, v):  # a stopped run: NaN state, no work
        return u, v, jnp.zeros(it_shape.shape, it_shape.dtype), yes

    def body(c, _):
        u, v, it, ok = jax.lax.cond(jnp.all(jnp.isfinite(c[0])), step, skip, *c)
        e = total(u, v)
        stop = ~(e <= stop_ratio * e0)  # NaN compares False: stops too
        u, v = (jnp.where(stop, jnp.nan, a) for a in (u, v))
        return (u, v), (jnp.where(stop, jnp.nan, e), probe @ u, it, ok)

    _, (e, p, it, ok) = jax.lax.scan(body, (u0, v0), None, length=n_steps)
    e = jnp.concatenate([e0[None], e])
    p = jnp.concatenate([(probe @ u0)[None], p])
    return Trajectory(e, p, it, ok)
