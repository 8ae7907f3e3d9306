"""Collision: which candidate points touch the rigid part, and their contact frames.

Points sampled on the deformable part's surface (interpolated from its nodes) are put in the
rigid part's frame and queried against its signed distance; along each line of points the
deepest and the two ends within the margin fill the contact buffer (:func:`manifold`); the
normal is the deformed surface's (or, at an edge, the rigid part's within the edge's cone,
:func:`contact_normal`). Units: mm.
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


def contact_normal(stencil, n_plug, corner):
    """(C, 3) contact normals, pointing into the deformable part.

    On a face touched by a rigid-part feature (a fillet), the normal is the part's own
    deformed face normal: the rigid part's SDF normal at a sample point beside the true contact
    line would be off by the fillet's arc (spacing / (2 r) rad). At a convex edge (a corner of
    the section) the normal is the rigid part's, projected into the cone between the two
    adjacent faces' normals: outside that cone the true contact lies on the adjacent face.

    Args:
        stencil: (C, 8, 3) deformed normal stencils (see :class:`Samples`).
        n_plug: (C, 3) the rigid part's SDF normals at the points (outward of it).
        corner: (C,) bool, point on a convex edge.
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
    on_face = jnp.where((jnp.sum(n1 * n_plug, -1) > 0)[:, None], n1, n_plug)
    return jnp.where(corner[:, None], at_edge, on_face)
