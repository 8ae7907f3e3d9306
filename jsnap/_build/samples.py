"""Contact candidate points on the deformable part's surface (host side).

The canonical cantilever's candidates are its section outline sampled finely along each side
and coarsely across the width, kept where the rigid part can reach along its path
(:func:`section_samples`), each located on a boundary face of the mesh and interpolated from that
face's nodes with the element's own shape functions (:func:`locate_on_faces`), so that contact
resolution does not depend on the FEM resolution. Units: mm.
"""

from __future__ import annotations

import math

import numpy as np

from jsnap._build.fem import Assembly
from jsnap._geometry.cantilever import Cantilever
from jsnap._geometry.mesh import TetMesh

__all__ = ["STENCIL_SIDE", "STENCIL_WIDTH", "locate_on_faces", "reachable_faces", "section_samples"]


def _edge_node_lookup(asm: Assembly):
    """Map a sorted vertex pair (a, b) to its P2 edge node index (P2 only)."""
    edges = np.sort(asm.basis.mesh.edges.T, axis=1)
    n_vert = asm.mesh.points.shape[0]
    return {(int(a), int(b)): n_vert + i for i, (a, b) in enumerate(edges)}


# Half-size of the stencil whose deformed shape gives a contact point's normal, mm: along the
# section side (capped by the side's length) and across the width. A point force dimples the
# elastic surface over about an element; the normal of the face under the point would tilt with
# that dimple and give frictionless contacts a spurious tangential force, so the normal is taken
# from the deformed positions of points a stencil apart, which follow the face's rotation.
STENCIL_SIDE = 0.25
STENCIL_WIDTH = 0.5


def section_samples(geom: Cantilever, lo, hi, spacing: float, width_spacing: float):
    """Candidate points of the extruded connector: its section outline sampled every
    ``spacing`` (mm, fine: across a contact line) times ``width_spacing`` across the width (mm,
    coarse: along it), kept inside the box [lo, hi].

    Returns points (P, 3); the rest outward normals (P, 2, 3) of the side each point lies on and
    of the other side at a corner (the same side elsewhere); a (P,) flag for points on a convex
    corner of the section (an edge of the socket, where its normal is any in the cone between the
    two sides'); the normal stencils (P, 8, 3) of those two sides: for each, two points along
    the side and two across the width, so that ``cross(s3 - s2, s1 - s0)`` is its outward normal;
    and each point's group (P,) (one group per section side and width position, numbered from 0)
    and its order (P,) along its side.
    """
    poly = geom.section()
    half_w = geom.width / 2
    sides = []  # (start, direction, length, outward normal) of the non-degenerate sides
    for i in range(len(poly)):
        a, b = poly[i], poly[(i + 1) % len(poly)]
        length = float(np.hypot(*(b - a)))
        if length > 0:
            d = (b - a) / length
            sides.append((a, d, length, np.array([d[1], -d[0]])))  # outward: counter-clockwise
    pts, nrm, corner, stn, side_of, pos = [], [], [], [], [], []
    for i, (a, d, length, out) in enumerate(sides):
        _, dp, lp, outp = sides[i - 1]
        convex = dp[0] * d[1] - dp[1] * d[0] > 0
        n = max(1, math.ceil(length / spacing))
        for j in range(n):
            s_here = length * j / n
            pts.append(a + d * s_here)
            own = (a + d * max(0.0, s_here - STENCIL_SIDE), a + d * min(length, s_here + STENCIL_SIDE))
            if j == 0 and convex:  # the corner: the previous side's stencil ends here
                other, n_other = (a - dp * min(lp, STENCIL_SIDE), a), outp
            else:
                other, n_other = own, out
            corner.append(j == 0 and convex)
            side_of.append(i)
            pos.append(j)
            nrm.append((out, n_other))
            stn.append((*own, *other))
    pts, nrm, stn = np.array(pts), np.array(nrm), np.array(stn)  # (S, 2), (S, 2, 2), (S, 4, 2)
    ys = np.linspace(-half_w, half_w, math.ceil(geom.width / width_spacing) + 1)
    ny = ys.size

    def lift(xz, y):  # section coordinates (S, 2) x width positions (ny,) -> (S*ny, 3)
        return np.stack(
            [np.repeat(xz[:, 0], ny), np.broadcast_to(y, (len(xz), ny)).ravel(), np.repeat(xz[:, 1], ny)], 1
        )

    X = lift(pts, ys)
    N = np.stack([lift(nrm[:, k], np.zeros(ny)) for k in range(2)], axis=1)
    C = np.repeat(np.array(corner), ny)
    y_lo, y_hi = np.clip(ys - STENCIL_WIDTH, -half_w, half_w), np.clip(ys + STENCIL_WIDTH, -half_w, half_w)
    across = [lift(pts, y_lo), lift(pts, y_hi)]
    stencil = np.stack(
        [lift(stn[:, 0], ys), lift(stn[:, 1], ys), *across, lift(stn[:, 2], ys), lift(stn[:, 3], ys), *across],
        axis=1,
    )
    group = np.repeat(np.array(side_of), ny) * ny + np.tile(np.arange(ny), len(pts))
    order = np.repeat(np.array(pos), ny)
    keep = np.all((X >= lo) & (X <= hi), axis=1)
    _, group = np.unique(group[keep], return_inverse=True)  # renumber 0..G-1
    return X[keep], N[keep], C[keep], stencil[keep], group, order[keep]


# Distance from a face (plane distance plus the barycentric excess scaled by the face's size, mm)
# below which a point counts as lying on it.
_ON_FACE = 1e-7


def _candidate_pairs(tri: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(point, face) index pairs (k,), (k,) of the points X (P, 3) and the triangles tri (F, 3, 3)
    that may lie on one another: the point within the largest circumradius about the centroid
    of the face (any point of a triangle is within that of its centroid), with a margin well
    above :data:`_ON_FACE`. A k-d tree of the centroids keeps this O(P log F) in time and O(P)
    in memory, where testing every point against every face took P x F x 3 floats."""
    from scipy.spatial import cKDTree

    centre = tri.mean(axis=1)
    reach = np.linalg.norm(tri - centre[:, None], axis=2).max()
    reach = reach * (1 + 1e-6) + 1e3 * _ON_FACE
    near = cKDTree(centre).query_ball_point(X, reach)
    counts = np.fromiter((len(c) for c in near), dtype=np.int64, count=len(X))
    p = np.repeat(np.arange(len(X)), counts)
    f = np.fromiter((j for c in near for j in c), dtype=np.int64, count=int(counts.sum()))
    return p, f


def locate_on_faces(asm: Assembly, faces: np.ndarray, X: np.ndarray, normals: np.ndarray):
    """Face of each point (on the boundary) and its interpolating nodes and weights.

    A point on an edge of the socket lies on several faces; it is given the one whose normal is
    closest to ``normals`` (P, 3), the outward normal of the section side it was sampled on, so
    that every point of one side shares that side's normal. The weights are the element's own
    shape functions on the face (P1: barycentric; P2: vertex l(2l-1), edge 4 l_i l_j), so the
    contact resolution is independent of the mesh.
    Returns nodes (P, k), weights (P, k) and the face index (P,).
    """
    pts = asm.mesh.points
    tri = pts[faces]  # (F, 3, 3)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    nrm = np.cross(e1, e2)
    area2 = np.linalg.norm(nrm, axis=1)
    p, f = _candidate_pairs(tri, X)
    d = X[p] - tri[f, 0]  # one row per (point, face) pair near each other
    plane = np.abs(np.einsum("kd,kd->k", d, nrm[f])) / area2[f]
    l2 = np.einsum("kd,kd->k", d, np.cross(nrm, e1)[f]) / area2[f] ** 2
    l1 = np.einsum("kd,kd->k", d, np.cross(e2, nrm)[f]) / area2[f] ** 2
    l0 = 1 - l1 - l2
    outside = np.maximum(np.maximum(-l0, -l1), -l2).clip(min=0)
    score = plane + outside * area2[f] ** 0.5
    on = score <= _ON_FACE
    if not np.all(np.bincount(p[on], minlength=len(X)) > 0):
        raise RuntimeError("contact sample not on the socket surface (geometry/mesh mismatch)")
    align = np.einsum("kd,kd->k", normals[p], nrm[f] / area2[f, None])
    # Per point, the face on it whose normal is closest to the point's (lowest face index on a tie).
    k = np.flatnonzero(on)
    k = k[np.lexsort((f[k], -align[k], p[k]))]
    k = k[np.r_[True, p[k][1:] != p[k][:-1]]]  # the first of each point's run, in point order
    f = f[k]
    L = np.stack([l0[k], l1[k], l2[k]], axis=1).clip(0, 1)
    L /= L.sum(axis=1, keepdims=True)
    a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
    if asm.element == "P1":
        return np.stack([a, b, c], axis=1), L, f
    edge_node = _edge_node_lookup(asm)
    e = [
        [edge_node[tuple(sorted((int(i), int(j))))] for i, j in zip(u, v, strict=True)]
        for u, v in ((a, b), (b, c), (a, c))
    ]
    nodes = np.stack([a, b, c, *[np.array(x) for x in e]], axis=1)
    l0, l1, l2 = L.T
    w = np.stack(
        [
            l0 * (2 * l0 - 1),
            l1 * (2 * l1 - 1),
            l2 * (2 * l2 - 1),
            4 * l0 * l1,
            4 * l1 * l2,
            4 * l0 * l2,
        ],
        axis=1,
    )
    return nodes, w, f


def reachable_faces(mesh: TetMesh, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Boundary faces whose bounding box meets the box [lo, hi] (mm)."""
    faces = mesh.boundary_faces()
    tri = mesh.points[faces]
    fmin, fmax = tri.min(axis=1), tri.max(axis=1)
    hit = np.all(fmax >= lo, axis=1) & np.all(fmin <= hi, axis=1)
    return faces[hit]


