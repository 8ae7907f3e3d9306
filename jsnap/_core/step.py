"""One time step of a whole scene: PMI deformable part + driven rigid part + SDF collision +
cone contact.

Pure functions of ``(model, prepared, state, control)``; no Python branching on traced values;
``jit``, ``vmap`` and ``grad`` apply. One step:

1. free midpoint velocity of the deformable part, ``vbar_free = S^-1 ((2/T) M v - K x)``, and
   of the rigid part (its drive);
2. candidate points (interpolated from the part's nodes) are put in the rigid part's frame and
   queried against its SDF; the ``capacity`` closest with ``phi < margin`` fill the contact
   buffer (masked slots; the number that did not fit is reported as ``overflow``);
3. the Delassus operator ``W = R'(J S^-1 J' + rigid mobility)R`` and the free relative
   velocity with the gap stabilisation ``phi / T`` give the cone problem, solved by the model's
   contact solver;
4. predict-correct: where the solved motion carries points that were not in the buffer into
   the rigid part, they are added and the problem solved again;
5. ``vbar = vbar_free + S^-1 J' Gamma``; ``x += T vbar``; ``v = 2 vbar - v``.

Units: mm, N, MPa, s, tonne. ``Gamma`` is the force of the rigid part on the deformable part.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from jsnap._core import status
from jsnap._core.collision import contact_normal, frames, manifold
from jsnap._core.contact import ContactSolution
from jsnap._core.model import Model
from jsnap._core.params import Params, params_valid
from jsnap._core.pose import angular_velocity, quat_matrix
from jsnap._core.util import cast_floats, safe_norm, x64

__all__ = ["Prepared", "State", "StepOutput", "init_state", "prepare", "step"]


class Prepared(eqx.Module):
    """Parameters plus what the step needs from them.

    Attributes:
        params: the physical parameters.
        op: the deformable part's PMI operator (its ``prepare``; for the full model the
            inverse of ``S``), float64 unless cast.
        valid: bool array, every parameter finite and in its range (else the step flags
            ``INVALID_PARAMS`` and a rollout's outputs are NaN).
    """

    params: Params
    op: eqx.Module
    valid: jax.Array

    def astype(self, dtype) -> Prepared:
        """The same operator with its floating arrays in ``dtype``."""
        return cast_floats(self, dtype)


class State(eqx.Module):
    """Dynamic state.

    Attributes:
        x, v: (n,) the deformable part's coordinates (mm) and velocities (mm/s).
        plug, plug_vel: (3,) the rigid part's centre (mm) and velocity (mm/s).
        target: (3,) last desired centre, mm.
        t: time, s.
        gamma: (P, 3) last contact force per candidate point, contact frame, N (the warm start
            of the contact solver: quasi-static contact changes little from step to step).
        rotation: (4,) the rigid part's orientation, a unit quaternion (w, x, y, z): its frame
            (where its signed distance is given) turned into the base's.
    """

    x: jax.Array
    v: jax.Array
    plug: jax.Array
    plug_vel: jax.Array
    target: jax.Array
    t: jax.Array
    gamma: jax.Array
    rotation: jax.Array


class StepOutput(eqx.Module):
    """What one step reports (see :class:`jsnap.Result`, which stacks them)."""

    insertion_force: jax.Array
    lateral_force: jax.Array
    base_force: jax.Array
    base_moment: jax.Array
    coupling_force: jax.Array
    coupling_moment: jax.Array
    energy: jax.Array
    work: jax.Array
    friction_dissipation: jax.Array
    normal_dissipation: jax.Array
    penetration: jax.Array
    plug: jax.Array
    plug_rotation: jax.Array
    contact_force: jax.Array
    contact_point: jax.Array
    contact_active: jax.Array
    contact_index: jax.Array
    overflow: jax.Array
    residual: jax.Array
    iterations: jax.Array
    corrected: jax.Array
    flags: jax.Array


def _prepare(model: Model, params: Params) -> Prepared:
    """:func:`prepare` without the host-side check (traced parameters)."""
    demoted = {
        str(a.dtype) for a in jax.tree_util.tree_leaves(model.part) if jnp.issubdtype(a.dtype, jnp.floating)
    }
    if demoted != {"float64"}:
        # A float32 model would be factorised from rounded blocks: on the coarse default hook its
        # snap moved by whole steps (3.5 N in a 26 N peak). Say so rather than compute it.
        raise ValueError(
            f"prepare needs the model's float64 arrays, but its part holds {', '.join(sorted(demoted))}: "
            "it was cast (model.astype) or demoted by JAX outside 64-bit mode (e.g. unpickled or made "
            "without jax.enable_x64); prepare the model jsnap.build returned, or load it inside "
            "`with jax.enable_x64(True):`"
        )
    return Prepared(params, model.part.prepare(params.material, model.dt), params_valid(params))


@x64
def prepare(model: Model, params: Params | None = None) -> Prepared:
    """The deformable part's PMI operator for ``params`` (default: the scene's), in float64.

    Differentiable with respect to every field of ``params``; costs one dense factorisation of
    the part's order (n^3 for the full model, the reduced order for the reduced one).

    Raises:
        ValueError: a parameter that is not traced is not finite or out of its range (traced
            ones are flagged in the result instead).
    """
    params = model.params if params is None else params
    params.check()
    return _prepare(model, params)


@x64
def init_state(model: Model, dtype=None, plug_start=None) -> State:
    """The deformable part at rest, the rigid part at ``plug_start`` (3,) mm (default: the
    scene's start) in the scene's start orientation, and at rest."""
    dtype = jnp.dtype(dtype or model.dtype)
    z = jnp.zeros(model.n_dof, dtype)
    p = jnp.asarray(model.plug_start if plug_start is None else plug_start, dtype)
    if p.shape != (3,):
        raise ValueError(f"plug_start must be (3,), the rigid part's centre in mm; got shape {p.shape}")
    g = jnp.zeros((model.n_samples, 3), dtype)
    q = jnp.asarray(model.rotation_start, dtype)
    return State(z, z, p, jnp.zeros(3, dtype), p, jnp.zeros((), dtype), g, q)


class _Frame(NamedTuple):
    """The rigid part's frame over one step: points into it, normals out of it, and the
    velocity of its material points. Without rotation (3-wide controls) every map is the
    identity and costs nothing."""

    plug: jax.Array  # (3,) centre at the start of the step, mm
    R: jax.Array | None  # (3, 3) its orientation (None: the base's axes)
    omega: jax.Array | None  # (3,) angular velocity over the step, rad/s

    def local(self, p):
        """Points (..., 3) in the base's frame -> the rigid part's frame."""
        d = p - self.plug
        return d if self.R is None else d @ self.R

    def world(self, n):
        """Directions (..., 3) in the rigid part's frame -> the base's."""
        return n if self.R is None else n @ self.R.T

    def spin(self, p):
        """(..., 3) velocity of the rigid part's points at ``p`` due to its rotation, mm/s."""
        if self.omega is None:
            return jnp.zeros_like(p)
        return jnp.cross(self.omega, p - self.plug)


def _rotate_blocks(R, W):
    """``einsum("cdi,cdef,efj->ciej", R, W, R)``: the (C, 3, C, 3) operator ``W`` in the
    frames ``R`` (C, 3, 3), as two broadcast products summed over 3 terms each. XLA:CPU runs
    the einsum as batched dots of 3 x 3 blocks, 6-12x slower than these two elementwise
    kernels at 24-64 slots."""
    T = sum(R[:, d, :, None, None] * W[:, d, None] for d in range(3))  # (c, i, e, f)
    return sum(T[..., f, None] * R[None, None, :, f, :] for f in range(3))


def _rotate_rows(R, A):
    """``einsum("cdi,cdr->cir", R, A)``: the (C, 3, r) rows ``A`` in the frames ``R`` (C, 3, 3),
    as broadcast products summed over 3 terms (see ``_rotate_blocks``)."""
    return sum(R[:, d, :, None] * A[:, d, None, :] for d in range(3))


def _local_operator(part, op, idx, R, s_p):
    """``(A, W)``: the part's ``A`` and the Delassus block with the rigid part's mobility
    ``s_p`` in the contact frames ``R``, unsymmetrised and without the compliance: the block
    itself (C, 3, C, 3), or its factors ``(left, right)`` (C, 3, m) with
    ``W[c, i, e, j] = left[c, i] · right[e, j]``.

    Where the part gives its block as thin factors ``W = A J'`` (segmented and reduced parts)
    and they are thin enough (r ≤ 4 x 3C), the factors are turned into the frames, with the
    rigid part's term ``s_p Rᵀ R`` as three more columns:
    ``W_loc = [R'A, s_p R'] [R'J, R']'``, multiplied out by :func:`_delassus`. Turning the
    (C, 3, C, 3) block instead is heavy enough for XLA:CPU to split it across the cores, which
    cost ~30 µs of a ~100 µs reduced step; for a part whose r is its nodal dofs (segmented,
    coarse meshes aside) the block's turn is the cheaper one.
    """
    if part.factored and part.n_dof <= 4 * 3 * idx.shape[0]:
        A, J = part.contact_factors(op, idx)
        Rt = jnp.swapaxes(R, 1, 2)  # (C, 3, 3): Rt[c, i, d] = R[c, d, i]
        left = jnp.concatenate([_rotate_rows(R, A), s_p * Rt], axis=-1)
        right = jnp.concatenate([_rotate_rows(R, J), Rt], axis=-1)
        return A, (left, right)
    A, W = part.contact_operator(op, idx)  # J S^-1 (C, 3, n); J S^-1 J' (C, 3, C, 3), world
    W = W + s_p * jnp.eye(3, dtype=W.dtype)[None, :, None, :]
    return A, _rotate_blocks(R, W)


class ContactProblem(eqx.Module):
    """One step's cone problem and what maps it back to the deformable part.

    shift: the contact compliance over the step, added to the Delassus matrix's diagonal; q:
    (3C,) free relative velocity plus gap stabilisation, mm/s; mu: (C,); active: (C,) bool;
    idx: (C,) candidate index of each slot; R: (C, 3, 3) frames [n, t1, t2]; points: (C, 3)
    slot positions, mm; s_p: the rigid part's mobility over the step, mm/(N s); gamma0: (C, 3)
    warm start, N; overflow: candidates that did not fit.

    The Delassus operator is not part of it: :func:`_solve` forms it (``_local_operator``) for
    only the leading slots it solves on.
    """

    shift: jax.Array
    q: jax.Array
    mu: jax.Array
    active: jax.Array
    idx: jax.Array
    R: jax.Array
    points: jax.Array
    s_p: jax.Array
    gamma0: jax.Array
    overflow: jax.Array


def _delassus(W, shift, k: int) -> jax.Array:
    """(3k, 3k) Delassus matrix of ``k`` slots from ``_local_operator``'s ``W`` for them,
    symmetrised, with the compliance ``shift`` on its diagonal."""
    if isinstance(W, tuple):
        left, right = W
        W = left.reshape(3 * k, -1) @ right.reshape(3 * k, -1).T
    W = W.reshape(3 * k, 3 * k)
    return 0.5 * (W + W.T) + shift * jnp.eye(3 * k, dtype=W.dtype)


def _contact_problem(
    model: Model, prepared: Prepared, state: State, frame: _Frame, nodal, vp_free, s_p, y, score, gamma
):
    """The cone problem of one step (before solving it).

    Args:
        nodal: ``(xn, vn)``, the part's ``nodal`` values of its coordinates and of its free
            midpoint velocity.
        y: (P, 3) candidate points at the start of the step, mm.
        score: (P,) selection score: the points with ``score < margin`` are candidates, the
            lowest first (normally the signed distance to the rigid part).
        gamma: (P, 3) warm start per candidate point, N.
    """
    op = prepared.op
    T = op.dt
    dtype = state.x.dtype
    part = model.part
    settings = model.contact
    C = settings.capacity
    keep = manifold(model.samples, score, settings.margin)
    n_cand = jnp.sum(keep)
    _, idx = jax.lax.top_k(jnp.where(keep, -score, -jnp.inf), C)
    phi, n_plug = model.rigid.scene_query(frame.local(y[idx]), settings.margin)
    n_plug = frame.world(n_plug)
    active = keep[idx]
    smp = model.samples
    xn, vn_free = nodal
    stencil = smp.stencil[idx] + part.stencil_at(xn, idx)
    spacing = smp.spacing

    def rigid_normal_at(points):
        return frame.world(model.rigid.scene_query(frame.local(points), settings.margin + spacing)[1])

    normal, carries = contact_normal(
        stencil, phi, n_plug, smp.corner[idx], y[idx], smp.line[idx], smp.reach[idx], spacing, rigid_normal_at,
        smp.hand_over,
    )  # fmt: skip
    active = active & carries
    R = frames(normal)
    shift = jnp.asarray(settings.compliance / T, dtype)
    u_free = part.point_at(vn_free, idx) - vp_free - frame.spin(y[idx])
    # A gap closes within the step; a penetration (the linearised gap drifts inward where a
    # point slides around a curved feature of the rigid part) is removed by the fraction
    # contact.stabilisation of it.
    gap = jnp.where(phi > 0, phi, settings.stabilisation * phi)
    q = jnp.einsum("cdi,cd->ci", R, u_free).at[:, 0].add(gap / T).reshape(-1)
    mu = jnp.broadcast_to(prepared.params.friction, (C,)).astype(dtype)
    overflow = jnp.maximum(n_cand - C, 0)
    s_p = jnp.asarray(s_p, dtype)
    return ContactProblem(shift, q, mu, active, idx, R, y[idx], s_p, gamma[idx], overflow)


def _buckets(capacity: int) -> tuple[int, ...]:
    """Problem sizes (slots) the solve is cut to: a quarter (or, when that is below 8, half) of
    ``capacity``, an eighth of it when that is at least 32 slots, half of it when that is at
    least 64 slots, and all of it; and for a buffer of at least 256 slots a sixteenth, three
    thirty-seconds and three sixteenths of it too. Each size is one more compiled copy of the
    solver (~1.5 s more to compile a rollout). Half of a 64-slot buffer gained nothing
    measurable on the default scene, where a small matvec costs its kernel launch; half of 128
    doubles the two-hook clip's APGD step rate (60 active slots at its peak: the matvecs shrink
    fourfold; ``benchmarks/two_hook_clip.py``). A large buffer's steps mostly hold a few dozen
    contacts, and forming the Delassus matrix (its order squared times the reduced order) is
    then most of the solve: the box lid's 256 slots hold 1-42, and the sizes 16, 24, 32, 48,
    64 in place of 32 and 64 step its rollout 1.2 times faster (docs/contact.md)."""
    small = next((k for k in (capacity // 4, capacity // 2) if k >= 8), capacity)
    eighth = capacity // 8 if capacity // 8 >= 32 else capacity
    half = capacity // 2 if capacity // 2 >= 64 else capacity
    return tuple(sorted({*_fine_buckets(capacity), eighth, small, half, capacity}))


def _fine_buckets(capacity: int) -> tuple[int, ...]:
    """The sizes of :func:`_buckets` that only a buffer of at least 256 slots gets."""
    return (capacity // 16, 3 * capacity // 32, 3 * capacity // 16) if capacity >= 256 else ()


def _solve(model: Model, op, prob: ContactProblem):
    """Solve the step's cone problem; ``(solution, Gamma, dv)`` with Gamma (C, 3) in world axes
    and dv the part's velocity change from it (``contact_velocity``).

    Only the active slots carry force, and the buffer fills its slots from the front (top_k),
    so the solver runs on the smallest of ``_buckets(C)`` leading slots that holds every active
    one (a ``lax.switch``). The branch forms the operator (``_local_operator``), the Delassus
    matrix and the velocity change for its slots only: every per-slot cost shrinks with the
    size (the Delassus matrix and each iteration's matvec with its square), and the solution is
    the same, since the inactive slots would enter only as zero rows and columns.

    Under ``vmap`` the switch runs every branch (a select): the branches not taken get no
    active slot, so their solves stop at their first check instead of running to the
    iteration cap on a truncated problem.
    """
    solver = model.contact.solver
    C = prob.mu.shape[0]
    sizes = _buckets(C)
    # Slots up to the last active one (a prefix however the buffer was filled).
    n = jnp.max(jnp.where(prob.active, jnp.arange(1, C + 1), 0))
    branch = jnp.sum(n > jnp.asarray(sizes[:-1]))

    def leading(i, k):
        def f(_):
            A, W = _local_operator(model.part, op, prob.idx[:k], prob.R[:k], prob.s_p)
            active = prob.active[:k] & (branch == i)  # the branch taken: prob.active[:k]
            sol = solver.solve(
                _delassus(W, prob.shift, k), prob.q[: 3 * k], prob.mu[:k], active, gamma0=prob.gamma0[:k]
            )
            Gamma = jnp.einsum("cij,cj->ci", prob.R[:k], sol.gamma) * active[:, None]  # on the part, world
            dv = model.part.contact_velocity(op, A, Gamma)
            pad = jnp.zeros((C, 3), sol.gamma.dtype)
            return sol._replace(gamma=pad.at[:k].set(sol.gamma)), pad.at[:k].set(Gamma), dv

        return f

    branches = [leading(i, k) for i, k in enumerate(sizes)]
    return jax.lax.switch(branch, branches, None) if len(sizes) > 1 else branches[0](None)


class _Pass(NamedTuple):
    """One solve of a step's contact: what the update and the predict-correct check need."""

    dv: jax.Array  # the contact's velocity change, the part's contact_velocity(op, A, Gamma)
    Gamma: jax.Array  # (C, 3) forces on the part, world axes, N
    sol: ContactSolution
    idx: jax.Array
    active: jax.Array
    points: jax.Array
    normal: jax.Array  # (C, 3) contact normals, world axes
    overflow: jax.Array
    velocity: jax.Array  # (P, 3) the points' midpoint velocity with this solve's dv, mm/s
    phi_end: jax.Array  # (P,) least signed distance along the solved path
    fresh: jax.Array  # (P,) points that path carries into the rigid part, not in the buffer
    corrected: jax.Array  # this is the second solve


def _in_dtype(tree, dtype):
    """``tree`` with its floating leaves in ``dtype``, leaving it untouched when they are."""
    leaves = [a for a in jax.tree_util.tree_leaves(tree) if hasattr(a, "dtype")]
    if all(a.dtype == dtype for a in leaves if jnp.issubdtype(a.dtype, jnp.floating)):
        return tree
    return cast_floats(tree, dtype)


def _step(model: Model, prepared: Prepared, state: State, control):
    """:func:`step` (model and prepared in the state's dtype)."""
    op = prepared.op
    T = op.dt
    part = model.part
    settings = model.contact
    x, v = state.x, state.v
    # The orientation is position-controlled under either drive; 3-wide controls keep it.
    rotation = control[3:] if control.shape[-1] == 7 else state.rotation
    turning = control.shape[-1] == 7 or model.rotates
    control = control[:3]
    frame = _Frame(
        state.plug,
        quat_matrix(state.rotation) if turning else None,
        angular_velocity(state.rotation, rotation, T) if turning else None,
    )

    # 1. Free motion of both parts.
    vbar_free = part.free_velocity(op, x, v)
    vp_free, s_p = model.drive.free(state.plug, state.plug_vel, state.target, control, T)

    # 2.-3. Collision and the cone problem: candidates within the margin now.
    # The contact nodes' displacements and free velocities, once: both solves interpolate them.
    nodal = (part.nodal(x), part.nodal(vbar_free))
    y = model.samples.rest + part.sample_at(nodal[0])
    phi_now, _ = model.rigid.scene_query(frame.local(y), settings.margin)

    def attempt(score, warm, second):
        prob = _contact_problem(model, prepared, state, frame, nodal, vp_free, s_p, y, score, warm)
        sol, Gamma, dv = _solve(model, op, prob)
        # 4. Predict-correct: where the solved motion would carry points that were not in the
        # buffer into the rigid part (a stiff, light part released by it springs back through a
        # large gap within one step), add them and solve again, warm-started. The path within
        # the step is straight, but a released stiff part can move farther than the rigid part
        # is thick in one step (PMI's undamped high modes flip sign), so the path is checked at
        # several points, not only at its end.
        vel = part.sample_at(nodal[1] + part.nodal(dv))  # (P, 3) the points' solved midpoint velocity
        dy = T * vel
        dp = T * (vp_free - s_p * jnp.sum(Gamma, axis=0))
        spin = T * frame.spin(y)  # the rigid part's turn over the step, to first order
        in_buffer = jnp.zeros(phi_now.shape, bool).at[prob.idx].set(prob.active)
        # φ is 1-Lipschitz and the path straight: no point of it lies deeper than φ now less its
        # length, so only the points that could end fresh are searched (the others' decision is
        # already known; a sliver of slack keeps rounding from flipping one).
        reach = safe_norm(dy - spin - dp)
        need = ~in_buffer & (phi_now - reach < -0.5 * settings.margin + 1e-3 * settings.margin)
        phi_end = model.rigid.least_along(
            lambda f: frame.local(y + f * (dy - spin) - f * dp), phi_now, settings.margin, need
        )
        fresh = need & (phi_end < -0.5 * settings.margin)
        slots = (prob.idx, prob.active, prob.points, prob.R[:, :, 0], prob.overflow)
        return _Pass(dv, Gamma, sol, *slots, vel, phi_end, fresh, jnp.asarray(second))

    def solve_pass(p: _Pass, second):
        """The first solve, or the second after ``p``: its fresh points added, warm-started
        from its forces."""
        score = jnp.where(second & p.fresh, p.phi_end, phi_now)
        warm = jnp.where(second, state.gamma.at[p.idx].set(p.sol.gamma * p.active[:, None]), state.gamma)
        return attempt(score, warm, second)

    def maybe(p: _Pass, second):
        return jax.lax.cond(~second | jnp.any(p.fresh), solve_pass, lambda p, _: p, p, second), None

    # Both solves are one compiled attempt, run by a two-pass scan whose second pass is skipped
    # when the first carried no fresh point into the rigid part. The attempt (collision, every
    # size's solver) written out twice took about an eighth more time to compile a rollout.
    blank = jax.tree_util.tree_map(
        lambda s: jnp.zeros(s.shape, s.dtype), jax.eval_shape(attempt, phi_now, state.gamma, jnp.asarray(False))
    )
    res, _ = jax.lax.scan(maybe, blank, jnp.asarray([False, True]))
    Gamma, sol, idx, active = res.Gamma, res.sol, res.idx, res.active

    # 5. Update.
    vbar = vbar_free + res.dv
    x_new = x + T * vbar
    v_new = 2.0 * vbar - v
    total = jnp.sum(Gamma, axis=0)
    vbar_p = vp_free - s_p * total
    plug_new, coupling = model.drive.finish(state.plug, state.target, control, vbar_p, total, T)

    material = prepared.params.material
    base_force, base_moment = part.base_wrench(material, T, x, v, v_new, vbar)
    finite = jnp.all(jnp.isfinite(x_new)) & jnp.all(jnp.isfinite(v_new)) & jnp.all(jnp.isfinite(Gamma))
    finite = finite & jnp.all(jnp.isfinite(plug_new)) & jnp.all(jnp.isfinite(coupling))
    flags = (
        jnp.where(prepared.valid, 0, status.INVALID_PARAMS)
        | jnp.where(finite, 0, status.NON_FINITE)
        | jnp.where(res.overflow > 0, status.CONTACT_OVERFLOW, 0)
        | jnp.where(sol.residual > 100 * settings.solver.tol, status.NOT_CONVERGED, 0)
    ).astype(jnp.int32)
    arm = res.points - state.plug
    friction_loss, normal_loss = _contact_dissipation(
        T, Gamma, res.normal, res.velocity[idx] - vbar_p - frame.spin(res.points)
    )
    out = StepOutput(
        insertion_force=jnp.sum(total * model.axis),
        lateral_force=-total[0],
        base_force=base_force,
        base_moment=base_moment,
        coupling_force=coupling,
        coupling_moment=jnp.sum(jnp.cross(arm, Gamma), axis=0),
        energy=part.energy(op, x_new, v_new),
        work=T * (jnp.sum(Gamma * vbar_p) + jnp.sum(Gamma * frame.spin(res.points))),
        friction_dissipation=friction_loss,
        normal_dissipation=normal_loss,
        penetration=jnp.maximum(-jnp.min(phi_now), 0.0),
        plug=plug_new,
        plug_rotation=rotation,
        contact_force=Gamma,
        contact_point=res.points,
        contact_active=active,
        contact_index=idx,
        overflow=res.overflow,
        residual=sol.residual,
        iterations=sol.iterations,
        corrected=res.corrected,
        flags=flags,
    )
    gamma = jnp.zeros_like(state.gamma).at[idx].set(sol.gamma * active[:, None])
    new = State(x_new, v_new, plug_new, vbar_p * 2 - state.plug_vel, control, state.t + T, gamma, rotation)
    return new, out


def _contact_dissipation(T, Gamma, normal, u):
    """``(friction, normal)``: the energy the contact forces take from the two parts in the
    step, N mm, split along the contact normals. ``Gamma`` (C, 3) the forces on the deformable
    part, ``u`` (C, 3) its points' midpoint velocity relative to the rigid part's surface
    there, both in world axes (inactive slots carry no force).

    The midpoint rule's energy balance is exact: the rigid part's work less the change of the
    deformable part's energy is the damping's ``T v̄'Dv̄`` plus ``-T Γ·u``, which these two
    terms split. The friction term is non-negative at a solution of the cone problem
    (maximal dissipation). The normal term is zero where a contact persists with its gap
    closed; it is positive where the contact closes a gap within the step (an inelastic
    impact, or a point held across a gap it does not touch) and negative where the
    stabilisation pushes a penetrating point out."""
    n_force = jnp.sum(Gamma * normal, axis=-1)
    n_speed = jnp.sum(u * normal, axis=-1)
    normal_loss = -T * jnp.sum(n_force * n_speed)
    return -T * jnp.sum(Gamma * u) - normal_loss, normal_loss


@x64
def step(model: Model, prepared: Prepared, state: State, control) -> tuple[State, StepOutput]:
    """Advance one time step.

    ``model`` and ``prepared`` are used in the state's dtype: cast them once
    (``model.astype(dtype)``, ``prepared.astype(dtype)``) when stepping from a Python loop, or
    each call casts them anew.

    Args:
        model: built scene.
        prepared: ``prepare(model, params)``.
        state: current :class:`State` (its dtype is the step's).
        control: (3,) desired centre of the rigid part at the end of the step, mm; or (7,)
            with its desired orientation, a unit quaternion (w, x, y, z), in the last four.

    Returns:
        ``(next_state, StepOutput)``; ``StepOutput.flags`` holds the step's
        ``jsnap._core.status`` bits.
    """
    if jnp.shape(control) not in ((3,), (7,)):
        raise ValueError(
            "control must be (3,), the desired rigid-part centre in mm, or (7,) with a unit quaternion "
            f"(w, x, y, z) after it; got shape {jnp.shape(control)}"
        )
    dtype = state.x.dtype
    model = _in_dtype(model, dtype)
    prepared = _in_dtype(prepared, dtype)
    return _step(model, prepared, state, jnp.asarray(control, dtype))
