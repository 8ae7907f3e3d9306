"""Collision: which candidate points touch the rigid part, and their contact frames.

Points sampled on the deformable part's surface (interpolated from its nodes) are put in the
rigid part's frame and queried against its signed distance; along each line of points the
deepest and the two ends within the margin fill the contact buffer (:func:`manifold`); the
normal is the deformed surface's (or, at an edge, the rigid part's within the edge's cone), and
a face point beside an edge the rigid part presses leaves that contact to the edge's points
(:func:`contact_normal`). Units: mm.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jsnap._core.model import Samples
from jsnap._core.util import safe_norm

__all__ = ["contact_normal", "frames", "manifold"]


def manifold(samples: Samples, phi, margin: float):
    """(P,) bool: the candidates (``phi < margin``) kept for the contact buffer.

    Along each line of points (one section side at one width position) only the deepest point
    and the first and last points within the margin are kept: the deepest carries a fillet's
    line contact, the two ends bound a flat-on-flat patch (its reaction and moment). The number
    kept is then set by the geometry, not by the sampling density, so the spacing can be fine
    enough that the contact moves smoothly from point to point without filling the buffer.
    """
    cand = phi < margin
    G = samples.n_groups
    g = samples.group
    pos = samples.order
    big = jnp.iinfo(jnp.int32).max
    deepest = jax.ops.segment_min(jnp.where(cand, phi, jnp.inf), g, num_segments=G)
    # One deepest point per line, even when several tie (coplanar faces).
    at_deepest = jax.ops.segment_min(jnp.where(cand & (phi <= deepest[g]), pos, big), g, num_segments=G)
    first = jax.ops.segment_min(jnp.where(cand, pos, big), g, num_segments=G)
    last = jax.ops.segment_max(jnp.where(cand, pos, -1), g, num_segments=G)
    return cand & ((pos == at_deepest[g]) | (pos == first[g]) | (pos == last[g]))


def frames(n):
    """(C, 3, 3) orthonormal frames with columns [n, t1, t2] for unit normals n (C, 3)."""
    a = jnp.where(jnp.abs(n[:, :1]) < 0.9, jnp.array([1.0, 0, 0]), jnp.array([0, 1.0, 0]))
    t1 = jnp.cross(n, a.astype(n.dtype))
    t1 = t1 / safe_norm(t1, keepdims=True)
    t2 = jnp.cross(n, t1)
    return jnp.stack([n, t1, t2], axis=-1)


# A face point leaves its contact to an edge only where the rigid part's normal is tilted from
# the face's by more than _EDGE_TILT (rad, 10 degrees) and turns by at most _EDGE_TURN (rad,
# 5 degrees) over one spacing along the line: there the face's normal would hold the point
# across a gap that opens slowly. Nearly parallel faces, and small fillets (radius under about
# 11 spacings, whose gap opens fast), keep the face's normal.
_EDGE_TILT = 0.1745
_EDGE_TURN = 0.0873


def contact_normal(
    stencil, phi, n_plug, corner, points, line, reach, spacing: float, rigid_normal_at, hand_over: bool = True
):
    """``(normal, carries)``: (C, 3) contact normals, pointing into the deformable part, and
    (C,) whether each point carries a contact.

    At a convex edge (a corner of the section) the normal is the rigid part's, projected into
    the cone between the two adjacent faces' normals: outside that cone the true contact lies
    on the adjacent face, whose normal it takes.

    On a face the normal is the face's own (deformed) normal where the rigid part's point
    deepest along it (its tangency with the face's plane) lies on the face: a fillet or an edge
    of the rigid part pressing the face, whose SDF normal at a sample beside the true contact
    line is off by the fillet's arc (spacing / r rad), so that a force along it would push the
    part along the face like friction. Where that point lies beyond the face's end, the rigid
    part touches the face's edge, and the face point carries no contact: the edge's corner
    points do (a large pin spreading a clip's mouth: the face normal at a point beside the edge
    would hold it across a gap, taking energy out of a frictionless contact). A point the rigid
    part has entered keeps its face's normal and its contact, wherever the tangency. Where the
    tangency lies is read from how the rigid part's normal turns over one ``spacing`` along
    the face from the point toward it (a second SDF query): at a tilt ``a`` that turns by
    ``da`` it lies ``spacing a / da`` away; a rigid surface that does not turn toward the face
    has none. Both are taken along the sample's line (the rigid part's motion in the face,
    sampled every ``spacing``), and the face's extent is the line's, ``reach`` back and on.
    Only a tilt above ``_EDGE_TILT`` that turns by at most ``_EDGE_TURN`` per spacing leaves
    the contact to the edge: a small fillet opens its gap beside the edge within a step or two,
    a nearly parallel rigid face hardly at all. Across the lines (sampled every
    ``contact.width_spacing``, too coarse to place a tangency) the face normal is kept.

    Args:
        stencil: (C, 8, 3) deformed normal stencils (see :class:`Samples`).
        phi: (C,) the rigid part's signed distance at the points, mm.
        n_plug: (C, 3) the rigid part's SDF normals at the points (outward of it).
        corner: (C,) bool, point on a convex edge.
        points: (C, 3) the points, mm.
        line: (C, 3) unit direction of each point's line of samples (rest).
        reach: (C, 2) distances along it from the point back to the line's first point and on
            to its last, mm.
        spacing: the sampling's spacing along its lines, mm.
        rigid_normal_at: (C, 3) points -> (C, 3) the rigid part's SDF normals there.
        hand_over: leave such contacts to the edges (static). The general surface sampling
            does; the presets' own samplers (section and turned) keep every face point's
            contact, as checked against CalculiX: on the annular snap's full model at friction
            0.3 the hand-over changes the snap's transient (1.8 % RMS of the peak) while its
            reduced model, unchanged, follows the former.
    """

    def side_normal(s):
        n = jnp.cross(s[:, 3] - s[:, 2], s[:, 1] - s[:, 0])
        return -n / safe_norm(n, keepdims=True)  # into the part

    n1, n2 = side_normal(stencil[:, :4]), side_normal(stencil[:, 4:])
    axis = jnp.cross(n1, n2)
    inside = (jnp.sum(jnp.cross(n1, n_plug) * axis, -1) >= 0) & (jnp.sum(jnp.cross(n_plug, n2) * axis, -1) >= 0)
    nearest = jnp.where((jnp.sum(n1 * n_plug, -1) >= jnp.sum(n2 * n_plug, -1))[:, None], n1, n2)
    at_edge = jnp.where(inside[:, None], n_plug, nearest)
    # A face point whose face normal opposes the rigid part's (deep inside it) is pushed out its way.
    deep = jnp.sum(n1 * n_plug, -1) <= 0
    normal = jnp.where(corner[:, None], at_edge, jnp.where(deep[:, None], n_plug, n1))
    if not hand_over:
        return normal, jnp.ones_like(corner)
    # Along the point's line (in the deformed face) the rigid part's normal tilts by `tilt`
    # (rad) to the side `side`; the tangency lies the other way, where the tilt would be 0.
    ell = line - jnp.sum(line * n1, -1, keepdims=True) * n1
    ell = ell / jnp.maximum(safe_norm(ell), jnp.finfo(ell.dtype).tiny)[:, None]
    lean = jnp.sum(n_plug * ell, -1)
    side = jnp.where(lean >= 0, 1.0, -1.0).astype(lean.dtype)
    tilt = jnp.arcsin(jnp.minimum(jnp.abs(lean), 1.0))
    probe = rigid_normal_at(points - (spacing * side)[:, None] * ell)
    turn = tilt - jnp.arcsin(jnp.clip(side * jnp.sum(probe * ell, -1), -1.0, 1.0))
    # The room the face has that way (a spacing more: a side's last point may be the next
    # side's corner, kept on that side's line). The tangency lies spacing * tilt / turn away.
    room = jnp.where(side < 0, reach[:, 1], reach[:, 0]) + spacing
    beyond = (tilt > _EDGE_TILT) & (turn <= _EDGE_TURN) & (room * jnp.maximum(turn, 0.0) < spacing * tilt)
    # A point inside the rigid part is touched by it, wherever the tangency: it keeps its face.
    return normal, corner | deep | ~beyond | (phi <= 0)
