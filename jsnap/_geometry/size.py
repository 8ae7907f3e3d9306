"""The part's size: the scale of the defaults that are lengths.

Some defaults are lengths that only make sense against the part. They were set on the shipped
parts, whose walls are 0.8 to 1.5 mm thick: on a part ten times smaller a 1 mm candidate line
spacing is wider than the part and a 0.8 mm element its whole thickness, and on one ten times
larger they are ten times too fine. Each follows the part's *wall ratio* ``r``, its wall
thickness over the shipped part's:

- for a preset, ``connector.thickness`` over the shipped preset's (:data:`REFERENCE_THICKNESS`);
- for a part from a file, its wall thickness (:func:`wall_thickness` of its surface: its thinnest
  wall, the walls that bend) over the shipped hook's, 1.2 mm (that hook's surface measures
  exactly its arm's thickness).

Two kinds of defaults follow it, each left unset being its value on the shipped parts times:

- the part's geometry and motion (:data:`GEOMETRIC`: the element size, the preset rigid part's
  height, fillet, depth and start clearance, the default stroke's overshoot): ``r`` itself, so
  that a preset scaled by ``k`` is the same scene ``k`` times larger;
- the contact's resolution (:data:`SIZED`: the candidates' spacing, line spacing and margin,
  the normal stencil, the contact segment's margin): the part's *size* ``s`` (:func:`size_of`),
  1 while ``r`` is within a factor 2 of 1, where these defaults hold as they are (the shipped
  parts span that range with one set of them), and beyond that ``r`` over the band's edge
  (``r / 2`` above, ``2 r`` below), so that parts 8 and 16 times the shipped one are sampled
  alike, point for point, at the density per wall that the shipped defaults have at the edge.

A key given in the scene keeps its value.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

__all__ = [
    "GEOMETRIC", "MIN_ELEMENTS_ACROSS", "REFERENCE_THICKNESS", "REFERENCE_WALL", "SIZED", "elements_across",
    "preset_ratio", "preset_size", "size_of", "thinnest_wall", "wall_thickness",
]  # fmt: skip

# connector.thickness of each shipped preset scene (jsnap/scenes/*.toml).
REFERENCE_THICKNESS = {
    "cantilever": 1.2,
    "two_hook_clip": 1.2,
    "box_lid": 1.2,
    "cable_latch": 0.8,
    "annular": 1.0,
}
# The shipped hook's wall thickness (wall_thickness of its surface: its arm, 1.2 mm), mm.
REFERENCE_WALL = 1.2
# Geometry and motion defaults: "section.key" -> the value at wall ratio 1, mm.
GEOMETRIC = {
    "solver.mesh_size": 0.8,
    "plug.fillet": 0.1,
    "plug.height": 0.5,
    "plug.clearance": 0.02,
}
# Contact resolution defaults: "section.key" -> the value at size 1, mm.
SIZED = {
    "solver.segment_margin": 1.0,
    "contact.width_spacing": 1.0,
    "contact.spacing": 0.02,
    "contact.margin": 0.02,
}
# Half-size of the stencil whose deformed shape gives a contact point's normal, mm at size 1:
# along the line of samples (capped by the face's extent) and across. A point force dimples the
# elastic surface over about an element; the normal of the face under the point would tilt with
# that dimple and give frictionless contacts a spurious tangential force, so the normal is taken
# from the deformed positions of points a stencil apart, which follow the face's rotation.
STENCIL_SIDE = 0.25
STENCIL_WIDTH = 0.5
# The preset rigid part's depth beyond the connector's width, and how far below the retention
# faces the default stroke takes it, mm at wall ratio 1.
PLUG_DEPTH_MARGIN = 1.0
OVERSHOOT = 0.3


# Within this factor of the shipped parts' walls the contact's resolution defaults hold as they are.
BAND = 2.0
# Two faces within this angle of facing each other bound a wall (a ray from one crosses the wall
# to the other); a ray that leaves through a face at a steeper angle crossed a wedge (a hook's
# lead ramp meeting its tip), an edge or a corner, not a wall. 15 degrees is the angle at which a
# surface's facets count as one face where jsnap tet-meshes it (jsnap._geometry.part).
WALL_ANGLE = 15.0
# The fewest elements across a part's thinnest wall (elements_across) below which a scene warns.
# P2: 2, that is elements no larger than the wall (the presets' own warning; P2 at one element
# across the reference arm bends 2.6 % short, at the default 0.8 mm, 1.5 per wall, 1.0 %:
# docs/validation.md). P1 locks in bending and needs more: 3, elements at most half the wall.
MIN_ELEMENTS_ACROSS = {"P2": 2, "P1": 3}


def size_of(ratio: float) -> float:
    """The size of a part whose walls are ``ratio`` times the shipped part's: 1 within a factor
    :data:`BAND` of it, and beyond that the ratio over the band's edge (continuous, and
    proportional to the ratio outside the band)."""
    ratio = float(ratio)
    if ratio > BAND:
        return ratio / BAND
    if ratio < 1.0 / BAND:
        return ratio * BAND
    return 1.0


def preset_ratio(connector: Mapping) -> float:
    """A preset's wall ratio: its ``thickness`` over the shipped preset's."""
    return float(connector["thickness"]) / REFERENCE_THICKNESS[connector["type"]]


def preset_size(connector: Mapping) -> float:
    """The size of a preset's part (:func:`size_of` its :func:`preset_ratio`)."""
    return size_of(preset_ratio(connector))


def elements_across(wall: float, mesh_size: float) -> int:
    """The elements across a wall ``wall`` mm thick at element size ``mesh_size``: the element
    edges it takes to span it, as gmsh divides an edge of length ``t`` at size ``h`` into
    ``ceil(t / h)`` segments, within 1 % (an edge 1.005 h long stays one segment, one 1.02 h
    long becomes two; gmsh 4.15).

    This counts along the wall's surface. Inside, gmsh's tetrahedra may be fewer layers thick:
    the shipped hook.stl at 0.8 mm (two across its 1.2 mm arm by this count) has one layer of
    tetrahedra through the arm, nodes on its faces only; its peak force is within 2.5 % of the
    structured mesh's at that size (docs/own-connector.md).
    """
    return max(1, math.ceil(float(wall) / float(mesh_size) - 0.01))


def wall_thickness(vertices: np.ndarray, faces: np.ndarray, rays: int = 512) -> float:
    """The wall thickness of a closed surface, mm: its thinnest wall (:func:`thinnest_wall`)."""
    return thinnest_wall(vertices, faces, rays)[0]


def thinnest_wall(vertices: np.ndarray, faces: np.ndarray, rays: int = 512) -> tuple[float, np.ndarray]:
    """The thinnest wall of a closed surface: its thickness, mm, and (3,) the point of the
    surface it was measured from.

    A wall's thickness is measured along the inward normal: a ray from a face's centroid to the
    surface's other side, where it leaves through a face within :data:`WALL_ANGLE` of facing it
    (a ray that leaves through a steeper face crossed a wedge, an edge or a corner). The walls
    that bend in a snap-fit are its thin ones: the arm of a hook, not the base or the housing it
    stands on, nor the lip at its end. So the thinnest wall is taken, not a typical one: the
    median by area, used before, measured the bulk of the surface, and a printed hook with
    6 x 7 mm arms on a 40 x 40 x 20 mm base measured 20 mm (its base), which made 13.3 mm
    elements, one across the arms. The thinnest wall resolves every wall the element size
    follows; a thin wall that does not bend (a fixed flange) costs a finer mesh, not a wrong
    force. The default hook measures its arm, 1.2 mm; a plate its thickness; a tube its wall.

    For a large surface ``rays`` faces are taken at evenly spaced quantiles of the cumulative
    area, each standing for an equal share of it: a wall of less than about 1/``rays`` of the
    surface's area may go unseen.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    tri = v[f]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    cross = np.cross(e1, e2)
    area = 0.5 * np.linalg.norm(cross, axis=1)
    good = area > 0
    if not good.any():
        raise ValueError("the surface has no triangle of positive area")
    normal = np.zeros_like(cross)
    normal[good] = cross[good] / (2 * area[good, None])
    if good.sum() > rays:
        cum = np.cumsum(np.where(good, area, 0.0))
        picks = np.searchsorted(cum, (np.arange(rays) + 0.5) / rays * cum[-1])
    else:
        picks = np.flatnonzero(good)
    origin = tri[picks].mean(axis=1)
    direction = -normal[picks]  # inward, for an outward-wound surface
    eps = 1e-9 * float(np.linalg.norm(np.ptp(v, axis=0)))
    t, hit = _first_hits(origin, direction, tri[good], eps=eps, which=True)
    seen = np.isfinite(t)
    if not seen.any():
        raise ValueError(
            "no ray from the surface meets its other side: is the surface closed and wound outward?"
        )
    # The face it leaves through faces the ray's own face: along the ray, within WALL_ANGLE.
    facing = np.zeros_like(seen)
    facing[seen] = np.einsum("rk,rk->r", direction[seen], normal[good][hit[seen]]) >= np.cos(
        np.radians(WALL_ANGLE)
    )
    if not facing.any():  # no two faces face each other (a tetrahedron): the nearest other side
        facing = seen
    i = int(np.flatnonzero(facing)[np.argmin(t[facing])])
    return float(t[i]), origin[i]


def _first_hits(origin, direction, tri, eps: float, chunk: int = 2_000_000, which: bool = False):
    """(R,) distance along each ray to the nearest triangle beyond ``eps`` (inf: none), by the
    Moller-Trumbore test; edges and vertices count as hits (a ray through a shared edge of a
    structured mesh hits it). ``which``: also (R,) the index of that triangle (0 where none)."""
    a, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    best = np.full(origin.shape[0], np.inf)
    index = np.zeros(origin.shape[0], np.int64)
    step = max(1, chunk // max(1, tri.shape[0]))
    for i in range(0, origin.shape[0], step):
        o, d = origin[i : i + step, None, :], direction[i : i + step, None, :]
        p = np.cross(d, e2[None])
        det = np.einsum("rtk,tk->rt", p, e1)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            s = o - a[None]
            u = np.einsum("rtk,rtk->rt", s, p) * inv
            q = np.cross(s, e1[None])
            w = np.einsum("rtk,rtk->rt", d, q) * inv
            t = np.einsum("rtk,tk->rt", q, e2) * inv
            tol = 1e-9
            hit = (np.abs(det) > 1e-30) & (u >= -tol) & (w >= -tol) & (u + w <= 1 + tol) & (t > eps)
        t = np.where(hit, t, np.inf)
        nearest = np.argmin(t, axis=1)
        index[i : i + step] = nearest
        best[i : i + step] = np.take_along_axis(t, nearest[:, None], axis=1)[:, 0]
    return (best, index) if which else best
