"""Kernels of a whole scene: PMI socket + rigid plug + SDF collision + cone contact.

Pure functions of ``(model, prepared, state, control)``; no Python branching on traced values;
``jit``, ``vmap`` and ``grad`` apply. One step:

1. free midpoint velocity of the socket, ``vbar_free = S^-1 ((2/T) M v - K x)``;
2. candidate points on the socket (interpolated from its nodes) are put in the plug's frame and
   queried against the plug's SDF; the ``capacity`` closest with ``phi < margin`` fill the
   contact buffer (masked slots; the number that did not fit is reported as ``overflow``);
3. the Delassus operator ``W = R'(J S^-1 J' + plug mobility)R`` and the free relative velocity
   with the gap stabilisation ``phi / T`` give the cone problem, solved by APGD (or PGS);
4. ``vbar = vbar_free + S^-1 J' Gamma``; ``x += T vbar``; ``v = 2 vbar - v``.

Units: mm, N, MPa, s, tonne. Forces: ``Gamma`` is the force of the plug on the socket.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jsnap._contact import solve_apgd, solve_pgs
from jsnap._integrate import PMIOperator, energy, pmi_operator, pmi_rhs
from jsnap._model import Model, Params
from jsnap._neural_sdf import neural_sdf_and_normal
from jsnap._sdf import mesh_sdf_and_normal, rounded_box_sdf_and_normal
from jsnap._util import safe_norm

__all__ = ["Prepared", "Result", "State", "init_state", "prepare", "rollout", "step"]


class Prepared(eqx.Module):
    """Parameters plus what the step needs from them (the factorised PMI operator)."""

    params: Params
    op: PMIOperator


class State(eqx.Module):
    """Dynamic state. x, v: (n,) socket displacement (mm) and velocity (mm/s) at free dofs;
    plug, plug_vel: (3,) plug centre (mm) and velocity (mm/s); target: (3,) last desired plug
    centre (mm); t: time (s); gamma: (P, 3) last contact force per candidate point (warm start
    of the contact solver: quasi-static contact changes little from one step to the next)."""

    x: jax.Array
    v: jax.Array
    plug: jax.Array
    plug_vel: jax.Array
    target: jax.Array
    t: jax.Array
    gamma: jax.Array  # (P, 3) last contact force of each candidate point, contact frame, N


class StepOutput(eqx.Module):
    """Per-step outputs (see :class:`Result`)."""

    insertion_force: jax.Array
    lateral_force: jax.Array
    base_force: jax.Array
    base_moment: jax.Array
    coupling_force: jax.Array
    energy: jax.Array
    work: jax.Array
    plug: jax.Array
    contact_force: jax.Array
    contact_point: jax.Array
    contact_active: jax.Array
    overflow: jax.Array
    residual: jax.Array
    iterations: jax.Array


class Result(eqx.Module):
    """A rollout's history; every array has the step axis first (n = steps).

    Attributes:
        t: (n,) time at the end of each step, s.
        insertion_force: (n,) force that pushes the plug along -z against the socket, N
            (positive while the socket resists).
        lateral_force: (n,) x-component of the socket's force on the plug, N.
        base_force: (n, 3) reaction of the fixed base on the socket, N (what a force sensor
            under the socket reads; in statics it balances the contact force).
        base_moment: (n, 3) its moment about the base centroid, N mm.
        coupling_force: (n, 3) force of the drive on the plug, N (the haptic force under
            impedance control).
        energy: (n,) socket energy 1/2 v'Mv + 1/2 x'Kx at the end of the step, N mm.
        work: (n,) work done by the plug on the socket during the step, N mm.
        plug: (n, 3) plug centre, mm.
        contact_force: (n, C, 3) force of the plug on the socket at each slot, N.
        contact_point: (n, C, 3) slot positions, mm.   contact_active: (n, C) bool.
        overflow: (n,) candidates that did not fit in the buffer (0 = none dropped).
        residual, iterations: (n,) contact solver's normalised KKT residual and iterations.
        travel: (n,) plug travel along -z since t = 0, mm.
        x: (n, dof) socket displacement at free dofs, mm (None unless kept).
    """

    t: jax.Array
    travel: jax.Array
    insertion_force: jax.Array
    lateral_force: jax.Array
    base_force: jax.Array
    base_moment: jax.Array
    coupling_force: jax.Array
    energy: jax.Array
    work: jax.Array
    plug: jax.Array
    contact_force: jax.Array
    contact_point: jax.Array
    contact_active: jax.Array
    overflow: jax.Array
    residual: jax.Array
    iterations: jax.Array
    x: jax.Array | None


def prepare(model: Model, params: Params | None = None) -> Prepared:
    """Factorise the PMI operator for ``params`` (default: the scene's), float64.

    Differentiable with respect to every field of ``params``; cost ~ n^3 for the full model.
    """
    params = model.params if params is None else params
    return Prepared(params, pmi_operator(model.blocks, params.material, model.dt))


def init_state(model: Model, dtype=None) -> State:
    """Socket at rest, plug at its start pose."""
    dtype = jnp.dtype(dtype or model.dtype)
    z = jnp.zeros(model.n_dof, dtype)
    p = model.plug_start.astype(dtype)
    g = jnp.zeros((model.n_samples, 3), dtype)
    return State(z, z, p, jnp.zeros(3, dtype), p, jnp.zeros((), dtype), g)


def _plug_sdf(model: Model, q):
    if model.sdf == "mesh":
        return mesh_sdf_and_normal(model.mesh_sdf, q)
    if model.sdf == "neural":
        return neural_sdf_and_normal(model.neural_sdf, q)
    return rounded_box_sdf_and_normal(q, model.plug_half, model.plug_radius)


def _frames(n):
    """(C, 3, 3) orthonormal frames with columns [n, t1, t2]."""
    a = jnp.where(jnp.abs(n[:, :1]) < 0.9, jnp.array([1.0, 0, 0]), jnp.array([0, 1.0, 0]))
    t1 = jnp.cross(n, a.astype(n.dtype))
    t1 = t1 / safe_norm(t1, keepdims=True)[..., :]
    t2 = jnp.cross(n, t1)
    return jnp.stack([n, t1, t2], axis=-1)


def step(model: Model, prepared: Prepared, state: State, control: jax.Array):
    """Advance one time step.

    Args:
        model: built scene.
        prepared: ``prepare(model, params)`` (cast to the rollout dtype).
        state: current :class:`State`.
        control: (3,) desired plug centre at the end of the step, mm.

    Returns:
        ``(next_state, StepOutput)``.
    """
    op = prepared.op
    T = op.dt
    dtype = state.x.dtype
    blocks = model.blocks
    x, v = state.x, state.v
    C = model.capacity

    # 1. Free socket motion.
    rhs = pmi_rhs(blocks, op, x, v, jnp.zeros_like(x))
    vbar_free = op.S_inv @ rhs

    # Plug: kinematic (s_p = 0) or driven through the virtual coupling (PMI on the plug too).
    v_des = (control - state.target) / T
    if model.control == "position":
        s_p = jnp.zeros((), dtype)
        vp_free = v_des
    else:
        k, b, m = model.coupling[0], model.coupling[1], model.coupling[2]
        s_p = 1.0 / (2 * m / T + b + 0.5 * T * k)
        mid_target = 0.5 * (control + state.target)
        vp_free = s_p * (2 * m / T * state.plug_vel + k * (mid_target - state.plug) + b * v_des)

    # 2. Collision: candidate points in the plug frame.
    xn = x.reshape(-1, 3)
    w = model.sample_weights
    disp = jnp.einsum("pk,pkd->pd", w, xn[model.sample_nodes])
    y = model.sample_rest + disp
    phi_all, _ = _plug_sdf(model, y - state.plug)
    n_cand = jnp.sum(phi_all < model.margin)
    _, idx = jax.lax.top_k(-phi_all, C)
    phi, n_plug = _plug_sdf(model, y[idx] - state.plug)
    active = phi < model.margin
    # On a flat socket face touched by a plug feature (a fillet), the contact normal is the
    # socket's own (deformed) face normal; the plug's SDF normal at a point beside the true
    # contact line would be off by the fillet's arc. At socket edges the plug's normal is used.
    tri = (
        model.sample_tri[idx]
        + xn[model.sample_nodes[idx, :3]] * (model.sample_weights[idx, :3] != 0)[..., None]
    )
    n_face = jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n_face = -n_face / safe_norm(n_face, keepdims=True)
    agree = jnp.sum(n_face * n_plug, axis=-1) > 0.7
    normal = jnp.where((agree & ~model.sample_corner[idx])[:, None], n_face, n_plug)

    # 3. Delassus operator in contact frames.
    nodes = model.sample_nodes[idx]  # (C, k)
    wk = w[idx]  # (C, k)
    dofs = 3 * nodes[..., None] + jnp.arange(3)  # (C, k, 3)
    A = jnp.einsum("ck,ckdn->cdn", wk, op.S_inv[dofs])  # (C, 3, n) = J S^-1
    W = jnp.einsum("cdekf,ek->cdef", A[:, :, dofs], wk)  # (C, 3, C, 3) world
    R = _frames(normal)
    W = W + s_p * jnp.eye(3, dtype=dtype)[None, :, None, :]
    W_loc = jnp.einsum("cdi,cdef,efj->ciej", R, W, R).reshape(3 * C, 3 * C)
    W_loc = 0.5 * (W_loc + W_loc.T)
    u_free = jnp.einsum("ck,ckd->cd", wk, vbar_free.reshape(-1, 3)[nodes]) - vp_free
    q = jnp.einsum("cdi,cd->ci", R, u_free).at[:, 0].add(phi / T).reshape(-1)
    mu = jnp.broadcast_to(prepared.params.friction, (C,)).astype(dtype)
    solve = solve_apgd if model.contact_solver == "apgd" else solve_pgs
    sol = solve(
        W_loc,
        q,
        mu,
        active,
        max_iters=model.iterations,
        tol=model.tolerance,
        gamma0=state.gamma[idx],
    )
    Gamma = jnp.einsum("cij,cj->ci", R, sol.gamma) * active[:, None]  # on socket, world

    # 4. Update.
    vbar = vbar_free + jnp.einsum("cdn,cd->n", A, Gamma)
    x_new = x + T * vbar
    v_new = 2.0 * vbar - v
    total = jnp.sum(Gamma, axis=0)
    vbar_p = vp_free - s_p * total
    plug_new = state.plug + T * vbar_p
    if model.control == "position":
        plug_new = control
        coupling = total
    else:
        xbar_p = state.plug + 0.5 * T * vbar_p
        coupling = k * (0.5 * (control + state.target) - xbar_p) + b * (v_des - vbar_p)

    # Base reaction at the interval's midpoint, consistent with the PMI equations.
    r = model.reaction
    rk, rm = _reaction_data(model, prepared, dtype)
    xbar = x + 0.5 * T * vbar
    react = (
        r.matvec(rm, (v_new - v) / T)
        + r.matvec(prepared.params.alpha * rm + prepared.params.beta * rk, vbar)
        + r.matvec(rk, xbar)
    ).reshape(-1, 3)
    out = StepOutput(
        insertion_force=-total[2],
        lateral_force=-total[0],
        base_force=react.sum(axis=0),
        base_moment=jnp.cross(model.base_offsets.astype(dtype), react).sum(axis=0),
        coupling_force=coupling,
        energy=energy(blocks, op, x_new, v_new),
        work=T * jnp.sum(Gamma * vbar_p),
        plug=plug_new,
        contact_force=Gamma,
        contact_point=y[idx],
        contact_active=active,
        overflow=jnp.maximum(n_cand - C, 0),
        residual=sol.residual,
        iterations=sol.iterations,
    )
    gamma = jnp.zeros_like(state.gamma).at[idx].set(sol.gamma * active[:, None])
    new = State(x_new, v_new, plug_new, vbar_p * 2 - state.plug_vel, control, state.t + T, gamma)
    return new, out


def _reaction_data(model: Model, prepared: Prepared, dtype):
    from jsnap._fem import lame

    p = prepared.params
    lam, mu = lame(p.E, p.nu)
    r = model.reaction
    return (lam * r.kl + mu * r.km).astype(dtype), (p.rho * r.m1).astype(dtype)


def _cast(tree, dtype):
    def f(a):
        if isinstance(a, jax.Array | np.ndarray) and jnp.issubdtype(a.dtype, jnp.floating):
            return a.astype(dtype)
        return a

    return jax.tree_util.tree_map(f, tree)


@eqx.filter_jit
def _scan(model, prepared, state, controls, keep_x):
    def body(s, c):
        s, out = step(model, prepared, s, c)
        return s, (out, s.x if keep_x else None)

    return jax.lax.scan(body, state, controls)


def rollout(
    model: Model,
    params: Params | None = None,
    *,
    controls=None,
    dtype=None,
    keep_x: bool = False,
    progress: bool = False,
) -> Result:
    """Run the scene's motion (or ``controls``) from rest and return the history.

    Args:
        model: ``jsnap.build(scene)``.
        params: physical parameters (default: the scene's); differentiable.
        controls: (steps, 3) desired plug centres at the end of each step, mm (default: the
            scene's motion, ``model.trajectory()[1:]``).
        dtype: rollout precision, ``"float32"`` or ``"float64"`` (default: the scene's).
        keep_x: also return the displacement history (``Result.x``).
        progress: show a progress bar (runs the scan in chunks; not for use under ``jit``).
    """
    dtype = jnp.dtype(dtype or model.dtype)
    prepared = _cast(prepare(model, params), dtype)
    m = _cast(model, dtype)
    if controls is None:
        controls = model.trajectory()[1:]
    controls = jnp.asarray(controls, dtype)
    state = init_state(model, dtype)
    if not progress:
        _, (out, xs) = _scan(m, prepared, state, controls, keep_x)
        return _result(out, xs, model, dtype)
    from tqdm.auto import tqdm

    chunk = max(1, math.ceil(controls.shape[0] / 20))
    outs, xs_all = [], []
    with tqdm(total=controls.shape[0], unit="step", desc="jsnap rollout") as bar:
        for i in range(0, controls.shape[0], chunk):
            c = controls[i : i + chunk]
            if c.shape[0] < chunk:
                c = jnp.concatenate([c, jnp.repeat(c[-1:], chunk - c.shape[0], 0)])
            n_real = min(chunk, controls.shape[0] - i)
            state_next, (out, xs) = _scan(m, prepared, state, c, keep_x)
            if n_real < chunk:  # padded tail: keep only the real steps
                out = jax.tree_util.tree_map(lambda a: a[:n_real], out)
                xs = None if xs is None else xs[:n_real]
            else:
                state = state_next
            outs.append(out)
            xs_all.append(xs)
            bar.update(n_real)
    out = jax.tree_util.tree_map(lambda *a: jnp.concatenate(a), *outs)
    xs = None if not keep_x else jnp.concatenate(xs_all)
    return _result(out, xs, model, dtype)


def _result(out: StepOutput, xs, model: Model, dtype) -> Result:
    n = out.energy.shape[0]
    return Result(
        t=(jnp.arange(n) + 1) * jnp.asarray(model.dt, dtype),
        travel=model.plug_start[2].astype(dtype) - out.plug[:, 2],
        insertion_force=out.insertion_force,
        lateral_force=out.lateral_force,
        base_force=out.base_force,
        base_moment=out.base_moment,
        coupling_force=out.coupling_force,
        energy=out.energy,
        work=out.work,
        plug=out.plug,
        contact_force=out.contact_force,
        contact_point=out.contact_point,
        contact_active=out.contact_active,
        overflow=out.overflow,
        residual=out.residual,
        iterations=out.iterations,
        x=xs,
    )
