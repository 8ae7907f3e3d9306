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
from functools import partial
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jsnap._core.contact import ContactSolution, solve_admm, solve_apgd, solve_pgs, solve_spg
from jsnap._core.implicit import implicit_solver
from jsnap._build.model import Model, Params
from jsnap._build.neural_sdf import neural_sdf_and_normal
from jsnap._core.sdf import mesh_sdf_and_normal, rounded_box_sdf_and_normal
from jsnap._core.util import safe_norm

__all__ = ["Prepared", "Result", "State", "init_state", "prepare", "rollout", "step"]

# Points at which the exact triangle-mesh SDF and the neural SDF are evaluated per query, at
# most (the nearest to the plug by a box's distance; see _near_plug_sdf).
_MESH_SDF_POINTS = 384
# Block of points of those queries (see _near_plug_sdf): the points near the plug number ~30 at
# the median and ~120 at the 99th percentile of the default scene's steps (1165 queries
# counted), so one block serves nearly every step.
_MESH_SDF_FEW = 128
# Slack on the margin for the points that must be exact: covers the float32 rounding of the
# mesh's vertices off the rounded box (~1e-7 of the plug's size), with room to spare.
_NEAR_SLACK = 1e-3
# The same for the neural SDF, whose lower bound is the plug's bounding box: the network may
# read below it by its own error (default plug: 1.3 µm mean, 46 µm at most within 0.2 mm of
# the surface, benchmarks/sdf_accuracy.py), so points up to 50 µm past the margin get the
# network too (70 of 1055 at the median step of the default scene, 160-360 near the snap).
_NEURAL_NEAR_SLACK = 5e-2
# Fractions of a step's straight-line motion at which the predict-correct collision check looks.
_PATH_CHECKS = (0.25, 0.5, 0.75, 1.0)


class Prepared(eqx.Module):
    """Parameters plus what the step needs from them: the socket's PMI operator (for the full
    model the factorised S^-1, see ``_socket``)."""

    params: Params
    op: eqx.Module


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
    contact_index: jax.Array
    overflow: jax.Array
    residual: jax.Array
    iterations: jax.Array
    corrected: jax.Array


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
        contact_index: (n, C) candidate point of each slot (index into ``model.sample_rest``).
        overflow: (n,) candidates that did not fit in the buffer (0 = none dropped).
        residual, iterations: (n,) contact solver's normalised KKT residual and iterations (of
            the second solve where ``corrected``).
        corrected: (n,) bool, the step was solved a second time: its solved motion carried
            points that were not in the buffer into the plug (predict-correct, see ``step``).
        travel: (n,) plug travel along -z since t = 0, mm.
        x: (n, dof) socket coordinates (None unless kept): the displacement at the free dofs
            (mm) for the full model; modal or reduced coordinates otherwise, which
            ``model.socket.free_displacement`` maps to the free dofs.
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
    contact_index: jax.Array
    overflow: jax.Array
    residual: jax.Array
    iterations: jax.Array
    corrected: jax.Array
    x: jax.Array | None


def prepare(model: Model, params: Params | None = None) -> Prepared:
    """The socket's PMI operator for ``params`` (default: the scene's), float64.

    Differentiable with respect to every field of ``params``; cost ~ n^3 for the full model.
    Non-finite or impossible values are a ValueError naming the field (not checked when traced).
    """
    params = model.params if params is None else params
    _check_params(params)
    return Prepared(params, model.socket.prepare(params.material, model.dt))


def init_state(model: Model, dtype=None) -> State:
    """Socket at rest, plug at its start pose."""
    dtype = jnp.dtype(dtype or model.dtype)
    z = jnp.zeros(model.n_dof, dtype)
    p = model.plug_start.astype(dtype)
    g = jnp.zeros((model.n_samples, 3), dtype)
    return State(z, z, p, jnp.zeros(3, dtype), p, jnp.zeros((), dtype), g)


def _plug_sdf(model: Model, q):
    """Signed distance (P,) and outward normal (P, 3) of the plug at points q (P, 3), plug frame."""
    if model.sdf == "mesh":
        exact = partial(mesh_sdf_and_normal, model.mesh_sdf)
        return _near_plug_sdf(model, q, exact, model.plug_radius, _NEAR_SLACK)
    if model.sdf == "neural":
        exact = partial(neural_sdf_and_normal, model.neural_sdf)
        return _near_plug_sdf(model, q, exact, 0.0, _NEURAL_NEAR_SLACK)
    return rounded_box_sdf_and_normal(q, model.plug_half, model.plug_radius)


def _near_plug_sdf(model: Model, q, exact, radius, slack):
    """A costly SDF ``exact`` (the triangle mesh's, the network's) where the contact needs it, a
    lower bound elsewhere.

    The lower bound is the distance to the rounded box of half extents ``model.plug_half`` and
    fillet ``radius``: the plug's mesh is inscribed in the analytic rounded box (its vertices lie
    on it), so that box's distance is a lower bound of the mesh's, inside and out; for the
    network, trained on the mesh, the bound is the plain bounding box (``radius`` 0), up to the
    network's error. A point whose bound is at least the margin plus ``slack`` is no contact
    candidate whatever its exact distance, and keeps the bound; ``exact`` is evaluated at the
    points with the lowest bounds, in blocks of ``_MESH_SDF_FEW``: as many blocks as the points
    below the margin plus ``slack`` need (one on most steps), up to ``_MESH_SDF_POINTS`` points.
    Every contact decision (candidates, predict-correct) is the one the exact distance at every
    point would give, as long as at most ``_MESH_SDF_POINTS`` points lie within the margin. The
    blocks are a scan over one compiled copy of the search (each skipped by a ``cond`` when not
    needed; under ``vmap`` every block is evaluated). The network at the 384 nearest points on
    every query instead (sessions 3-17) made neural-SDF rollouts 1.1-2.2x slower, with the same
    forces bit for bit (docs/neural_sdf.md).
    """
    n = q.shape[0]
    if n <= _MESH_SDF_FEW:
        return exact(q)
    lower, lower_normal = rounded_box_sdf_and_normal(q, model.plug_half, radius)
    n_blocks = -(-min(n, _MESH_SDF_POINTS) // _MESH_SDF_FEW)
    # Lowest bounds first; with fewer points than the blocks hold, the last block overlaps the one
    # before (dynamic_slice keeps it in range), evaluating some points twice.
    _, order = jax.lax.top_k(-lower, min(n, n_blocks * _MESH_SDF_FEW))
    n_near = jnp.sum(lower < model.margin + slack)

    def block(carry, k):
        def evaluate(c):
            near = jax.lax.dynamic_slice_in_dim(order, k * _MESH_SDF_FEW, _MESH_SDF_FEW)
            phi, normal = exact(q[near])
            return c[0].at[near].set(phi), c[1].at[near].set(normal)

        # Block 0 always; a later one only when the points below the margin reach into it.
        return jax.lax.cond(k * _MESH_SDF_FEW < jnp.maximum(n_near, 1), evaluate, lambda c: c, carry), None

    (phi, normal), _ = jax.lax.scan(block, (lower, lower_normal), jnp.arange(n_blocks))
    return phi, normal


def _frames(n):
    """(C, 3, 3) orthonormal frames with columns [n, t1, t2]."""
    a = jnp.where(jnp.abs(n[:, :1]) < 0.9, jnp.array([1.0, 0, 0]), jnp.array([0, 1.0, 0]))
    t1 = jnp.cross(n, a.astype(n.dtype))
    t1 = t1 / safe_norm(t1, keepdims=True)[..., :]
    t2 = jnp.cross(n, t1)
    return jnp.stack([n, t1, t2], axis=-1)


def _contact_normal(stencil, n_plug, corner):
    """(C, 3) contact normals, pointing into the socket.

    On a socket face touched by a plug feature (a fillet), the normal is the socket's own
    deformed face normal: the plug's SDF normal at a sample point beside the true contact line
    would be off by the fillet's arc (spacing / (2 r) rad). At a convex socket edge (a corner of
    the section) the normal is the plug's, projected into the cone between the two adjacent
    faces' normals: outside that cone the true contact lies on the adjacent face, not the edge.

    Args:
        stencil: (C, 8, 3) deformed normal stencils (see ``_model._section_samples``).
        n_plug: (C, 3) plug SDF normals at the points (outward of the plug).
        corner: (C,) bool, point on a convex edge.
    """

    def side_normal(s):
        n = jnp.cross(s[:, 3] - s[:, 2], s[:, 1] - s[:, 0])
        return -n / safe_norm(n, keepdims=True)  # into the socket

    n1, n2 = side_normal(stencil[:, :4]), side_normal(stencil[:, 4:])
    axis = jnp.cross(n1, n2)
    inside = (jnp.sum(jnp.cross(n1, n_plug) * axis, -1) >= 0) & (jnp.sum(jnp.cross(n_plug, n2) * axis, -1) >= 0)
    nearest = jnp.where((jnp.sum(n1 * n_plug, -1) >= jnp.sum(n2 * n_plug, -1))[:, None], n1, n2)
    at_edge = jnp.where(inside[:, None], n_plug, nearest)
    # A face point whose face normal opposes the plug's (deep inside it) is pushed out the
    # plug's way.
    on_face = jnp.where((jnp.sum(n1 * n_plug, -1) > 0)[:, None], n1, n_plug)
    return jnp.where(corner[:, None], at_edge, on_face)


def _rotate_blocks(R, W):
    """``einsum("cdi,cdef,efj->ciej", R, W, R)``: the (C, 3, C, 3) operator ``W`` in the
    frames ``R`` (C, 3, 3), as two broadcast products summed over 3 terms each. XLA:CPU runs
    the einsum as batched dots of 3 x 3 blocks, 6-12x slower than these two elementwise
    kernels at 24-64 slots (measured: 66 vs 5 µs at C = 24, 273 vs 45 µs at C = 64)."""
    T = sum(R[:, d, :, None, None] * W[:, d, None] for d in range(3))  # (c, i, e, f)
    return sum(T[..., f, None] * R[None, None, :, f, :] for f in range(3))


def _rotate_rows(R, A):
    """``einsum("cdi,cdr->cir", R, A)``: the (C, 3, r) rows ``A`` in the frames ``R`` (C, 3, 3),
    as broadcast products summed over 3 terms (not batched 3 x 3 dots, see ``_rotate_blocks``)."""
    return sum(R[:, d, :, None] * A[:, d, None, :] for d in range(3))


def _local_operator(sock, op, idx, R, s_p):
    """``(A, W)``: the socket's ``A`` (see ``_socket``) and the Delassus block with the plug's
    mobility ``s_p`` in the contact frames ``R``, unsymmetrised and without the compliance
    (``ContactProblem.delassus`` forms the solver's matrix from it): the block itself (C, 3, C,
    3), or its factors ``(left, right)`` (C, 3, m) with ``W[c, i, e, j] = left[c, i] · right[e,
    j]``.

    Where the socket gives its block as thin factors ``W = A J'`` (``contact_factors``: the
    reduced socket, r ~ 50-170 columns) and they are thin enough (r ≤ 4 x 3C), the factors are
    turned into the frames, with the plug's term ``s_p Rᵀ R`` as three more columns:
    ``W_loc = [R'A, s_p R'] [R'J, R']'``, multiplied out only for the leading slots the solve
    takes (``ContactProblem.delassus``).
    Turning the (C, 3, C, 3) block instead (``_rotate_blocks``: 2 x 3 multiply-adds over its
    5184 entries at 24 slots) is heavy enough for XLA:CPU to split it across the cores, and that
    cost ~30 µs per step of the 1344-dof reduced scene with light contact settings (measured
    with it taken out: 73-75 against 101-103 µs per step without the solve, session 22); the
    factors' turn is 2 x 3 multiply-adds over (C, 3, r) and runs as it is. The same block to
    round-off: float64 rollouts of the reduced scenes take the same iterations in every step,
    forces within 8e-12 of the peak on the default contact settings (position and impedance
    control) and 9e-10 with the light ones, whose solves stop at their cap and carry round-off
    further (session 22). Other sockets, and the segmented socket (its r is the mesh's nodal dofs:
    1407 at the 1.6 mm mesh, where turning the factors ran 2717-2949 against 2638-2672 µs per step
    turning the block; the reduced 2.0 mm mesh's r = 165, 168-184 against 193-205): their block,
    turned."""
    factors = getattr(sock, "contact_factors", None)
    if factors is not None and sock.n_dof <= 4 * 3 * idx.shape[0]:
        A, J = factors(op, idx)
        Rt = jnp.swapaxes(R, 1, 2)  # (C, 3, 3): Rt[c, i, d] = R[c, d, i]
        left = jnp.concatenate([_rotate_rows(R, A), s_p * Rt], axis=-1)
        right = jnp.concatenate([_rotate_rows(R, J), Rt], axis=-1)
        return A, (left, right)
    A, W = sock.contact_operator(op, idx)  # J S^-1 (C, 3, n); J S^-1 J' (C, 3, C, 3), world
    W = W + s_p * jnp.eye(3, dtype=W.dtype)[None, :, None, :]
    return A, _rotate_blocks(R, W)


def _least_along_path(model: Model, points, like):
    """(P,) least plug signed distance of ``points(f)`` (P, 3), plug frame, over the fractions
    ``f`` of ``_PATH_CHECKS``: the predict-correct check of a solved step's straight path.

    For the analytic plug the fractions are a ``fori_loop``, which XLA:CPU compiles into one
    kernel (a small loop, jsnap._apps.xla) run on the calling thread. Written side by side, the four
    queries are one loop fusion heavy enough in arithmetic that XLA splits it across the cores,
    and on the ~600-1000 points of a step handing half to the other core cost more than it
    saved: the 1344-dof reduced scene with light contact settings stepped in 173-181 against
    203-220 µs, the same forces to the bit (side by side, session 21). The mesh and network
    SDFs' queries (top_k, blocks of a scan) are not small loops: they stay side by side.
    ``like``: a (P,) array of the rollout's dtype.
    """
    if model.sdf != "analytic":
        return jnp.min(jnp.stack([_plug_sdf(model, points(f))[0] for f in _PATH_CHECKS]), axis=0)
    fractions = jnp.asarray(_PATH_CHECKS, like.dtype)

    def least(k, lo):
        return jnp.minimum(lo, _plug_sdf(model, points(fractions[k]))[0])

    return jax.lax.fori_loop(0, len(_PATH_CHECKS), least, jnp.full_like(like, jnp.inf))


class _Pass(NamedTuple):
    """One solve of a step's contact (``step``'s ``attempt``): what the update and the
    predict-correct check need from it."""

    dv: jax.Array  # the contact's velocity change, the socket's contact_velocity(op, A, Gamma)
    Gamma: jax.Array  # (C, 3) forces on the socket, world axes, N
    sol: ContactSolution
    idx: jax.Array
    active: jax.Array
    points: jax.Array
    overflow: jax.Array
    phi_end: jax.Array  # (P,) least signed distance along the solved path
    fresh: jax.Array  # (P,) points that path carries into the plug, not in the buffer
    corrected: jax.Array  # this is the second solve


class ContactProblem(eqx.Module):
    """One step's cone problem (see ``_contact``) and what maps it back to the socket.

    W: the Delassus block in contact frames, mm/(N s), as ``_local_operator`` gives it (the
    (C, 3, C, 3) block or its factors; the solver's matrix is ``delassus(k)``); shift: the
    contact compliance over the step, added to its diagonal; q: (3C,) free relative velocity
    plus gap stabilisation, mm/s; mu: (C,); active: (C,) bool; idx: (C,) candidate index of
    each slot; A: (C, 3, n) ``J S^-1``, or what the socket's ``contact_velocity`` applies in
    its stead (the modal socket: the slots' interpolation); R: (C, 3, 3) frames [n, t1, t2];
    points: (C, 3) slot positions, mm; gamma0: (C, 3) warm start, N; overflow: candidates that
    did not fit.
    """

    W: jax.Array | tuple[jax.Array, jax.Array]
    shift: jax.Array
    q: jax.Array
    mu: jax.Array
    active: jax.Array
    idx: jax.Array
    A: jax.Array
    R: jax.Array
    points: jax.Array
    gamma0: jax.Array
    overflow: jax.Array

    def delassus(self, k: int) -> jax.Array:
        """(3k, 3k) Delassus matrix of the leading ``k`` slots, symmetrised, with the compliance
        on its diagonal. From factors, only the leading rows are multiplied: the solve takes
        the leading slots that hold the active ones (``_solve``), most often a quarter or half
        of the buffer, and the whole product was the step's largest kernel (a 72 x 56 x 72 dot
        at 24 slots on the 1344-dof reduced scene; the leading rows alone, 36 x 56 x 36 on most
        of its light steps, took the step with one solver iteration from 83-85 to 70-76 µs,
        session 23)."""
        if isinstance(self.W, tuple):
            left, right = self.W
            W = jnp.einsum("cir,ejr->ciej", left[:k], right[:k])
        else:
            W = self.W[:k, :, :k]
        W = W.reshape(3 * k, 3 * k)
        return 0.5 * (W + W.T) + self.shift * jnp.eye(3 * k, dtype=W.dtype)


def _manifold(model: Model, phi):
    """(P,) bool: the candidates (``phi < margin``) kept for the contact buffer.

    Along each line of points (one section side at one width position) only the deepest point
    and the first and last points within the margin are kept: the deepest carries a fillet's
    line contact, the two ends bound a flat-on-flat patch (its reaction and moment). The number
    kept is then set by the geometry, not by the sampling density, so the spacing can be fine
    enough that the contact moves smoothly from point to point without filling the buffer.
    """
    cand = phi < model.margin
    G = model.n_groups
    g = model.sample_group
    pos = model.sample_order
    big = jnp.iinfo(jnp.int32).max
    deepest = jax.ops.segment_min(jnp.where(cand, phi, jnp.inf), g, num_segments=G)
    # One deepest point per line, even when several tie (coplanar faces).
    at_deepest = jax.ops.segment_min(jnp.where(cand & (phi <= deepest[g]), pos, big), g, num_segments=G)
    first = jax.ops.segment_min(jnp.where(cand, pos, big), g, num_segments=G)
    last = jax.ops.segment_max(jnp.where(cand, pos, -1), g, num_segments=G)
    return cand & ((pos == at_deepest[g]) | (pos == first[g]) | (pos == last[g]))


def _contact_problem(model: Model, prepared: Prepared, state: State, vbar_free, vp_free, s_p, y, score, gamma):
    """The cone problem of one step (before solving it).

    Args:
        y: (P, 3) candidate points at the start of the step, mm.
        score: (P,) selection score: the points with ``score < margin`` are candidates, the
            lowest first (normally the signed distance to the plug).
        gamma: (P, 3) warm start per candidate point, N.
    """
    op = prepared.op
    T = op.dt
    dtype = state.x.dtype
    sock = model.socket
    C = model.capacity
    keep = _manifold(model, score)
    n_cand = jnp.sum(keep)
    _, idx = jax.lax.top_k(jnp.where(keep, -score, -jnp.inf), C)
    phi, n_plug = _plug_sdf(model, y[idx] - state.plug)
    active = keep[idx]
    stencil = model.sample_stencil[idx] + sock.stencil_disp(state.x, idx)
    normal = _contact_normal(stencil, n_plug, model.sample_corner[idx])

    # Delassus operator in contact frames.
    R = _frames(normal)
    A, W_loc = _local_operator(sock, op, idx, R, s_p)
    shift = jnp.asarray(model.compliance / T, dtype)
    u_free = sock.point_velocity(vbar_free, idx) - vp_free
    q = jnp.einsum("cdi,cd->ci", R, u_free).at[:, 0].add(jnp.maximum(phi, 0) / T).reshape(-1)
    mu = jnp.broadcast_to(prepared.params.friction, (C,)).astype(dtype)
    overflow = jnp.maximum(n_cand - C, 0)
    return ContactProblem(W_loc, shift, q, mu, active, idx, A, R, y[idx], gamma[idx], overflow)


def _buckets(capacity: int) -> tuple[int, ...]:
    """Problem sizes (slots) the solve is cut to: a quarter (or, when that is below 8, half)
    of ``capacity``, and all of it. Each size is one more compiled copy of the solver: a third
    size (quarter, half and all) was measured 3 % faster per step on the default contact and
    ~1 s slower to compile."""
    small = next((k for k in (capacity // 4, capacity // 2) if k >= 8), capacity)
    return tuple(sorted({small, capacity}))


def _solve(model: Model, prob: ContactProblem, whole=False):
    """Solve the step's cone problem; ``(solution, Gamma)`` with Gamma (C, 3) in world axes.

    Only the active slots carry force, and the buffer fills its slots from the front (top_k),
    so the solver runs on the smallest of ``_buckets(C)`` leading slots that holds every active
    one (a ``lax.switch``): inactive slots enter the problem only as zero rows and columns of
    W, so the solution is the same, while each APGD iteration's matvec shrinks with the square
    of the size (the default 64 slots hold 10-15 active ones: a 16-slot solve, measured 2x
    faster per step). ``whole`` (a bool, traced or not) takes the whole buffer, as the
    predict-correct second solve does; ``True`` compiles that size alone.

    Under ``vmap`` the switch runs every branch (a select): the branches not taken get no
    active slot, so their solves stop at their first check instead of running to the
    iteration cap on a truncated problem (that cost ~1.3x a whole-buffer solve).
    ``benchmarks/throughput.py`` side by side with the code before: 337 against 276
    scene-steps/s at batch 1, 373 against 354 at batch 16 (docs/contact.md).
    """
    solve = {"apgd": solve_apgd, "admm": solve_admm, "spg": solve_spg, "pgs": solve_pgs}[model.contact_solver]
    if model.contact_gradient == "implicit":  # derivatives of the solution, not the iterations
        solve = implicit_solver(solve)
    C = prob.mu.shape[0]
    sizes = (C,) if whole is True else _buckets(C)
    # Slots up to the last active one (a prefix however the buffer was filled).
    n = jnp.max(jnp.where(prob.active, jnp.arange(1, C + 1), 0))
    branch = jnp.where(whole, len(sizes) - 1, jnp.sum(n > jnp.asarray(sizes[:-1])))

    def leading(i, k):
        def f(_):
            sol = solve(
                prob.delassus(k),
                prob.q[: 3 * k],
                prob.mu[:k],
                prob.active[:k] & (branch == i),  # the branch taken: prob.active[:k]
                max_iters=model.iterations,
                tol=model.tolerance,
                gamma0=prob.gamma0[:k],
            )
            return sol._replace(gamma=jnp.zeros((C, 3), sol.gamma.dtype).at[:k].set(sol.gamma))

        return f

    branches = [leading(i, k) for i, k in enumerate(sizes)]
    sol = jax.lax.switch(branch, branches, None) if len(sizes) > 1 else branches[0](None)
    Gamma = jnp.einsum("cij,cj->ci", prob.R, sol.gamma) * prob.active[:, None]  # on socket, world
    return sol, Gamma


def step(model: Model, prepared: Prepared, state: State, control: jax.Array, rolled: bool | None = None):
    """Advance one time step.

    Args:
        model: built scene.
        prepared: ``prepare(model, params)`` (cast to the rollout dtype).
        state: current :class:`State`.
        control: (3,) desired plug centre at the end of the step, mm.
        rolled: how the predict-correct second solve is compiled (the same results either
            way: bit for bit in the steps that are not corrected, to round-off in the others).
            ``True``: a two-pass ``lax.scan`` around one copy of the contact stage (problem,
            solver, path check); the program compiles ~1 s faster (one copy of the solver
            fewer), but reverse-mode derivatives through the loop cost ~20 % more (JAX stores
            and zero-fills the skipped second pass's residuals). ``False``: the two passes
            written out. ``None`` (default): ``False`` when the inputs are being
            differentiated or batched (JAX's JVP, linearize or ``vmap`` tracers: under
            ``vmap`` both passes run for every lane, and the rolled second pass's path check,
            four more SDF queries, made batched neural-SDF rollouts slower), else ``True``.
            ``rollout`` makes that choice from its own inputs (inside its compiled scan it
            cannot see them).

    Returns:
        ``(next_state, StepOutput)``.
    """
    if jnp.shape(control) != (3,):
        raise ValueError(f"control must be (3,), the desired plug centre in mm; got shape {jnp.shape(control)}")
    if rolled is None:
        rolled = not _differentiated_or_batched(model, prepared, state, control)
    op = prepared.op
    T = op.dt
    dtype = state.x.dtype
    sock = model.socket
    x, v = state.x, state.v

    # 1. Free socket motion.
    vbar_free = sock.free_velocity(op, x, v)

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

    # 2.-3. Collision and the cone problem: candidates within the margin now.
    y = model.sample_rest + sock.sample_disp(x)
    phi_now, _ = _plug_sdf(model, y - state.plug)

    def attempt(score, warm, second):
        prob = _contact_problem(model, prepared, state, vbar_free, vp_free, s_p, y, score, warm)
        sol, Gamma = _solve(model, prob, whole=second)
        # Predict-correct: where the solved motion would carry points that were not in the
        # buffer into the plug (a stiff, light socket released by the plug springs back through
        # a large gap within one step), add them and solve again, warm-started. The path within
        # the step is straight (x + s T vbar), but a released stiff socket can move farther than
        # the plug is thick in one step (PMI's undamped high modes flip sign), so the path is
        # checked at several points, not only at its end.
        dv = sock.contact_velocity(op, prob.A, Gamma)
        dy = T * sock.sample_disp(vbar_free + dv)
        dp = T * (vp_free - s_p * jnp.sum(Gamma, axis=0))
        phi_end = _least_along_path(model, lambda f: y + f * dy - state.plug - f * dp, phi_now)
        in_buffer = jnp.zeros(phi_now.shape, bool).at[prob.idx].set(prob.active)
        fresh = (phi_end < -0.5 * model.margin) & ~in_buffer
        slots = (prob.idx, prob.active, prob.points, prob.overflow)
        return _Pass(dv, Gamma, sol, *slots, phi_end, fresh, jnp.asarray(second))

    def again(p, second=True):
        """The second solve after ``p``: its fresh points added, warm-started from its forces
        (with ``second`` traced and false: the first solve)."""
        score = jnp.where(second & p.fresh, p.phi_end, phi_now)
        warm = jnp.where(second, state.gamma.at[p.idx].set(p.sol.gamma * p.active[:, None]), state.gamma)
        return attempt(score, warm, second)

    if rolled:
        # The second pass runs when the first found fresh points (a lax.cond). A reverse-
        # differentiable loop, unlike lax.while_loop: its second pass is skipped, not absent.
        def one_pass(p, k):
            return jax.lax.cond((k == 0) | jnp.any(p.fresh), lambda p: again(p, k > 0), lambda p: p, p), None

        C, P = model.capacity, phi_now.shape[0]
        zero = jnp.zeros((), dtype)
        nothing = _Pass(
            dv=jnp.zeros_like(vbar_free),
            Gamma=jnp.zeros((C, 3), dtype),
            sol=ContactSolution(jnp.zeros((C, 3), dtype), jnp.zeros((), jnp.int32), zero, jnp.zeros((), bool)),
            idx=jnp.zeros((C,), jnp.int32),
            active=jnp.zeros((C,), bool),
            points=jnp.zeros((C, 3), dtype),
            overflow=jnp.zeros((), int),  # a count (jnp.sum of bools): the default int
            phi_end=jnp.zeros((P,), dtype),
            fresh=jnp.zeros((P,), bool),
            corrected=jnp.zeros((), bool),
        )
        res, _ = jax.lax.scan(one_pass, nothing, jnp.arange(2))
    else:
        first = attempt(phi_now, state.gamma, False)
        res = jax.lax.cond(jnp.any(first.fresh), again, lambda p: p, first)
    Gamma, sol, idx, active = res.Gamma, res.sol, res.idx, res.active

    # 4. Update.
    vbar = vbar_free + res.dv
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

    base_force, base_moment = sock.base_wrench(op, prepared.params.material, x, v, v_new, vbar)
    out = StepOutput(
        insertion_force=-total[2],
        lateral_force=-total[0],
        base_force=base_force,
        base_moment=base_moment,
        coupling_force=coupling,
        energy=sock.energy(op, x_new, v_new),
        work=T * jnp.sum(Gamma * vbar_p),
        plug=plug_new,
        contact_force=Gamma,
        contact_point=res.points,
        contact_active=active,
        contact_index=idx,
        overflow=res.overflow,
        residual=sol.residual,
        iterations=sol.iterations,
        corrected=res.corrected,
    )
    gamma = jnp.zeros_like(state.gamma).at[idx].set(sol.gamma * active[:, None])
    new = State(x_new, v_new, plug_new, vbar_p * 2 - state.plug_vel, control, state.t + T, gamma)
    return new, out


def _cast(tree, dtype):
    def f(a):
        if isinstance(a, jax.Array | np.ndarray) and jnp.issubdtype(a.dtype, jnp.floating):
            return a.astype(dtype)
        return a

    return jax.tree_util.tree_map(f, tree)


@eqx.filter_jit
def _scan(model, prepared, state, controls, keep_x, rolled=True):
    # Checkpointed: reverse mode keeps only each step's state and recomputes the step (its
    # contact problems) on the way back (docs/differentiation.md); forward runs are unaffected.
    @jax.checkpoint
    def body(s, c):
        s, out = step(model, prepared, s, c, rolled)
        return s, (out, s.x if keep_x else None)

    return jax.lax.scan(body, state, controls)


def _differentiated_or_batched(*trees) -> bool:
    """Whether any array of ``trees`` is being differentiated or batched: a tracer of JAX's
    forward mode (``jvp``), of its linearisation (``grad``, ``vjp``, ``linearize``) or of
    ``vmap``; then ``step`` writes its two passes out (see there). Under ``jit`` alone, no.
    Inside a function that JAX transforms after tracing it (``grad(jit(f))``, ``vmap(jit(f))``),
    the arrays are ``jit``'s tracers: no, so such code takes the rolled step, whose results are
    the same and which is slower there."""
    names = ("JVPTracer", "LinearizeTracer", "BatchTracer")
    return any(type(a).__name__ in names for a in jax.tree_util.tree_leaves(trees))


def _check_params(params: Params) -> None:
    """Reject non-finite or impossible parameter values (skipped when they are traced)."""
    limits = {"E": (0, None), "rho": (0, None), "nu": (-1, 0.5)}
    for name in ("E", "nu", "rho", "alpha", "beta", "friction"):
        v = getattr(params, name)
        if isinstance(v, jax.core.Tracer):
            continue
        v = np.asarray(v)
        if not np.all(np.isfinite(v)):
            raise ValueError(f"Params.{name} must be finite, got {v}")
        lo, hi = limits.get(name, (None, None))
        bad = (v < 0) if lo is None else (v <= lo)
        if hi is not None:
            bad = bad | (v >= hi)
        if np.any(bad):
            rng = f"in ({lo}, {hi})" if hi is not None else (f"> {lo}" if lo is not None else ">= 0")
            raise ValueError(f"Params.{name} must be {rng}, got {v}")


def _check_controls(controls):
    """``controls`` must be (steps, 3), steps >= 1, and finite (checked when not traced).
    Returns them as a host array when concrete (checked there, before the cast), else as is."""
    if not isinstance(controls, jax.core.Tracer):
        controls = np.asarray(controls)
    if controls.ndim != 2 or controls.shape[1] != 3 or controls.shape[0] < 1:
        raise ValueError(
            f"controls must be (steps, 3) desired plug centres, mm, with steps >= 1; got shape {controls.shape}"
        )
    if isinstance(controls, np.ndarray):
        bad = ~np.isfinite(controls).all(axis=1)
        if bad.any():
            i = int(np.argmax(bad))
            raise ValueError(f"controls must be finite; row {i} (of {bad.size}) is {controls[i]}")
    return controls


def progress_chunk(n_steps: int) -> int:
    """Steps per compiled chunk when ``rollout`` shows progress (20 updates)."""
    return max(1, math.ceil(n_steps / 20))


def rollout(
    model: Model,
    params: Params | None = None,
    *,
    controls=None,
    dtype=None,
    keep_x: bool = False,
    progress: bool = False,
    prepared: Prepared | None = None,
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
        prepared: ``prepare(model, params)`` computed once and reused (it factorises the PMI
            operator, ~n^3 for the full model); give it or ``params``, not both.

    Raises:
        ValueError: controls not (steps, 3) or not finite, a dtype other than float32/float64,
            both ``params`` and ``prepared``, or non-finite or impossible parameter values.
    """
    dtype = jnp.dtype(dtype or model.dtype)
    if dtype not in (jnp.float32, jnp.float64):
        raise ValueError(f"dtype must be 'float32' or 'float64', got {dtype.name!r}")
    if prepared is None:
        prepared = prepare(model, params)
    elif params is not None and params is not prepared.params:
        # Silently ignoring params would be a wrong answer (and a zero gradient under jax.grad).
        raise ValueError(
            "rollout got both params and prepared: prepared = prepare(model, params) holds the "
            "parameters it was made from; pass one of them"
        )
    if controls is None:
        controls = model.trajectory()[1:]
    controls = _check_controls(controls)
    # The predict-correct loop rolled (compiles faster) unless differentiated or batched (``step``).
    rolled = not _differentiated_or_batched(prepared, model, controls)
    controls = jnp.asarray(controls, dtype)
    state = init_state(model, dtype)
    # The plug starts moving with the drive (no start-up transient in the virtual coupling).
    state = eqx.tree_at(lambda s: s.plug_vel, state, (controls[0] - state.plug) / jnp.asarray(model.dt, dtype))
    if not progress:
        out, xs = _whole(model, prepared, state, controls, keep_x, rolled)
        return _result(out, xs, model, dtype)
    prepared = _cast(prepared, dtype)
    m = _cast(model, dtype)
    from tqdm.auto import tqdm

    chunk = progress_chunk(controls.shape[0])
    outs, xs_all = [], []
    with tqdm(total=controls.shape[0], unit="step", desc="jsnap rollout") as bar:
        for i in range(0, controls.shape[0], chunk):
            c = controls[i : i + chunk]
            if c.shape[0] < chunk:
                c = jnp.concatenate([c, jnp.repeat(c[-1:], chunk - c.shape[0], 0)])
            n_real = min(chunk, controls.shape[0] - i)
            state_next, (out, xs) = _scan(m, prepared, state, c, keep_x, rolled)
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


@eqx.filter_jit
def _whole(model: Model, prepared: Prepared, state: State, controls, keep_x, rolled):
    """``rollout`` without progress from ``state``: the casts to the rollout's dtype and the scan
    in one compiled call. Done eagerly before the scan, the casts' hundreds of small operations
    cost 3-5 ms per call with the rest of ``rollout``'s eager work (13-20 µs per step of the
    default 233-step motion on the 1344-dof reduced scene, measured side by side with the scan
    alone), a tenth of such a rollout. The result's assembly stays eager: compiled with the
    scan, it changed how XLA compiled the step, and the plain rollout of a chaotic scene came
    4e-6 of its peak away from the primal of its ``jvp`` (float64,
    ``test_rolled_and_unrolled_predict_correct_agree``; bit for bit as it is)."""
    dtype = controls.dtype
    _, (out, xs) = _scan(_cast(model, dtype), _cast(prepared, dtype), state, controls, keep_x, rolled)
    return out, xs


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
        contact_index=out.contact_index,
        overflow=out.overflow,
        residual=out.residual,
        iterations=out.iterations,
        corrected=out.corrected,
        x=xs,
    )
