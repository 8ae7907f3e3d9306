"""Rigid parts as a user draws them in CAD, placed against a cantilever hook: the family of
shapes the exact-contact test and benchmark (``benchmarks/rigid_family.py``,
``tests/test_rigid_family.py``) run at default settings. Nothing here was tuned on a scene.

Each shape pushes the hook by its full undercut: its face toward the hook lies in the plane of
the arm's outer face at the tip (``x = h_tip``), ``clearance`` above the hook's top, and it is
wide enough to cover the arm's width. Sharp edges are sharp (no fillet); the cylinder and the
sphere are faceted as an STL export is. Lengths in mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import equinox as eqx
import numpy as np
import trimesh

SHAPES = ("cylinder", "sphere", "sharp_block", "chamfered_block", "wedge", "sleeve")


@dataclass(frozen=True)
class Hook:
    """What a shape is placed against: the arm's outer face at the tip (x), its width (y), the
    top of the hook (z) and the retention face's height (z)."""

    h_tip: float
    width: float
    z_top: float
    length: float
    undercut: float


def shape(name: str, hook: Hook, clearance: float = 0.02) -> tuple[trimesh.Trimesh, float]:
    """``(surface, stroke)``: the rigid part ``name`` of :data:`SHAPES` at its start pose and the
    travel along −z that latches it (its lowest pushing point 0.3 mm below the retention face).
    """
    x0, b, top = hook.h_tip, hook.width, hook.z_top + clearance
    depth = b + 2.0  # covers the arm's width with 1 mm to spare each side
    if name == "cylinder":  # a pin across the arm, as a CAD export facets it
        r = 1.0
        m = trimesh.creation.cylinder(radius=r, height=depth, sections=48)
        m.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
        m.apply_translation([x0 + r, 0.0, top + r])
        return m, top + r - hook.length + 0.3
    if name == "sphere":  # a ball pressed on the hook's centre line
        r = 1.5
        m = trimesh.creation.icosphere(subdivisions=3, radius=r)
        m.apply_translation([x0 + r, 0.0, top + r])
        return m, top + r - hook.length + 0.3
    if name == "sharp_block":
        section = [(x0, top), (x0 + 1.0, top), (x0 + 1.0, top + 1.0), (x0, top + 1.0)]
        return _extrude(section, depth), top - hook.length + 0.3
    if name == "chamfered_block":  # a 0.2 mm x 45 degree chamfer along its pushing edge
        c = 0.2
        section = [(x0, top + c), (x0 + c, top), (x0 + 1.0, top), (x0 + 1.0, top + 1.0), (x0, top + 1.0)]
        return _extrude(section, depth), top - hook.length + 0.3
    if name == "wedge":  # its sloped underside rises toward the hook: its edge at x0 pushes
        section = [(x0, top + 0.6), (x0 + 1.5, top), (x0 + 1.5, top + 2.0), (x0, top + 2.0)]
        return _extrude(section, depth), top + 0.6 - hook.length + 0.3
    if name == "sleeve":  # a housing 2 mm thick with a hole the arm passes through
        wall = 2.0
        outer = [(-2.5, -b / 2 - 2.0), (x0 + 2.5, b / 2 + 2.0)]
        hole = [(-1.0, -b / 2 - 0.5), (x0, b / 2 + 0.5)]
        return _frame(outer, hole, top, top + wall), top + wall - hook.length + 0.3
    raise ValueError(f"unknown shape {name!r}; expected one of {', '.join(SHAPES)}")


def _frame(outer, hole, z0, z1):
    """A rectangular plate between ``z0`` and ``z1`` with a rectangular through-hole: its outer
    and inner rectangles ``[(x0, y0), (x1, y1)]`` in the x-y plane."""

    def ring(r):
        (a, b), (c, d) = r
        return [(a, b), (c, b), (c, d), (a, d)]  # counter-clockwise seen from +z

    o, i = ring(outer), ring(hole)
    v = np.array([(*p, z) for z in (z0, z1) for p in o + i], float)  # 0-3 outer, 4-7 inner; +8 at z1
    faces = []
    for k in range(4):
        m = (k + 1) % 4
        faces += [[k, m, 8 + m], [k, 8 + m, 8 + k]]  # outer walls, facing out
        faces += [[4 + k, 12 + k, 12 + m], [4 + k, 12 + m, 4 + m]]  # the hole's walls, facing in
        faces += [[8 + k, 8 + m, 12 + m], [8 + k, 12 + m, 12 + k]]  # top, between the rectangles
        faces += [[k, 4 + m, m], [k, 4 + k, 4 + m]]  # bottom
    m = trimesh.Trimesh(v, faces, process=True)
    if m.volume < 0:
        m.invert()
    return m


def _extrude(section, depth):
    """A prism of the x-z polygon ``section`` (counter-clockwise) over ``y ∈ ±depth/2``."""
    poly = np.asarray(section, float)
    n = len(poly)
    v = np.concatenate(
        [np.column_stack([poly[:, 0], np.full(n, -depth / 2), poly[:, 1]]),
         np.column_stack([poly[:, 0], np.full(n, depth / 2), poly[:, 1]])]
    )  # fmt: skip
    faces = []
    for i in range(1, n - 1):  # the two caps (the section is convex)
        faces += [[0, i + 1, i], [n, n + i, n + i + 1]]
    for i in range(n):
        j = (i + 1) % n
        faces += [[i, j, n + j], [i, n + j, n + i]]
    m = trimesh.Trimesh(v, faces, process=True)
    if m.volume < 0:
        m.invert()
    return m


def with_distance(rigid, make):
    """The rigid part's SDF with its mesh distance (a ``GridMeshSDF``) replaced by
    ``make(grid)``: inside the edge rounding (``contact.edge_radius``) where there is one, so the
    replacement answers for the same rounded surface."""
    if hasattr(rigid, "inner"):
        return eqx.tree_at(lambda r: r.inner, rigid, make(rigid.inner))
    return make(rigid)
