"""The part's size: the scale of the defaults that are lengths.

Some defaults are lengths that only make sense against the part. They were set on the shipped
parts, whose walls are 0.8 to 1.5 mm thick: on a part ten times smaller a 1 mm candidate line
spacing is wider than the part and a 0.8 mm element its whole thickness, and on one ten times
larger they are ten times too fine. Each follows the part's *wall ratio* ``r``, its wall
thickness over the shipped part's:

- for a preset, ``connector.thickness`` over the shipped preset's (:data:`REFERENCE_THICKNESS`);
- for a part from a file, its wall thickness (:func:`wall_thickness` of its surface) over the
  shipped hook's, 1.2 mm (that hook's surface measures exactly its arm's thickness).

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

from collections.abc import Mapping

import numpy as np

__all__ = [
    "GEOMETRIC", "REFERENCE_THICKNESS", "REFERENCE_WALL", "SIZED", "preset_ratio", "preset_size", "size_of",
    "wall_thickness",
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


def wall_thickness(vertices: np.ndarray, faces: np.ndarray, rays: int = 512) -> float:
    """The wall thickness of a closed surface, mm: the median, weighted by area, of its
    thickness along the inward normal (a ray from each face's centroid to the surface's other
    side).

    A snap-fit part is thin-walled: most of its surface faces a wall's other side across the
    wall, so the median is the thickness of the walls that make most of its area (the default
    hook: its arm, 1.2 mm; a plate: its thickness). Faces that look along a wall (its edges)
    see farther and are outweighed. For a large surface ``rays`` faces are taken at evenly
    spaced quantiles of the cumulative area, each standing for an equal share of it.
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
        weights = np.ones(rays)
    else:
        picks = np.flatnonzero(good)
        weights = area[picks]
    origin = tri[picks].mean(axis=1)
    direction = -normal[picks]  # inward, for an outward-wound surface
    t = _first_hits(origin, direction, tri[good], eps=1e-9 * float(np.linalg.norm(np.ptp(v, axis=0))))
    seen = np.isfinite(t)
    if not seen.any():
        raise ValueError(
            "no ray from the surface meets its other side: is the surface closed and wound outward?"
        )
    t, weights = t[seen], weights[seen]
    order = np.argsort(t)
    cum = np.cumsum(weights[order])
    return float(t[order][np.searchsorted(cum, 0.5 * cum[-1])])


def _first_hits(origin, direction, tri, eps: float, chunk: int = 2_000_000) -> np.ndarray:
    """(R,) distance along each ray to the nearest triangle beyond ``eps`` (inf: none), by the
    Moller-Trumbore test; edges and vertices count as hits (a ray through a shared edge of a
    structured mesh hits it)."""
    a, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    best = np.full(origin.shape[0], np.inf)
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
        best[i : i + step] = np.min(np.where(hit, t, np.inf), axis=1)
    return best
