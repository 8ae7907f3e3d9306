"""Contact candidate points on the deformable part's surface (host side).

Candidates lie where the rigid part can reach along its path: for every part but the canonical
cantilever, on its surface (:func:`surface_samples`: flat patches sampled finely along lines that
run with the motion and coarsely across them); for the canonical cantilever, on its section
outline (:func:`section_samples`). Each point is located on a boundary face of the mesh and
interpolated from that face's nodes with the element's own shape functions
(:func:`locate_on_faces`), so that contact resolution does not depend on the FEM resolution.
Units: mm.
"""

from __future__ import annotations

import math

import numpy as np

from jsnap._build.fem import Assembly
from jsnap._geometry.cantilever import Cantilever
from jsnap._geometry.mesh import TetMesh
from jsnap._geometry.size import STENCIL_SIDE, STENCIL_WIDTH

__all__ = [
    "locate_on_faces",
    "near_path",
    "reachable_faces",
    "section_samples",
    "surface_samples",
    "turned_samples",
]


def _edge_node_lookup(asm: Assembly):
    """Map a sorted vertex pair (a, b) to its P2 edge node index (P2 only)."""
    edges = np.sort(asm.basis.mesh.edges.T, axis=1)
    n_vert = asm.mesh.points.shape[0]
    return {(int(a), int(b)): n_vert + i for i, (a, b) in enumerate(edges)}


def section_samples(geom: Cantilever, lo, hi, spacing: float, width_spacing: float, size: float = 1.0):
    """Candidate points of the extruded connector: its section outline sampled every
    ``spacing`` (mm, fine: across a contact line) times ``width_spacing`` across the width (mm,
    coarse: along it), kept inside the box [lo, hi]; ``size``: the part's size (its stencils'
    scale).

    Returns points (P, 3); the rest outward normals (P, 2, 3) of the side each point lies on and
    of the other side at a corner (the same side elsewhere); a (P,) flag for points on a convex
    corner of the section (an edge of the socket, where its normal is any in the cone between the
    two sides'); the normal stencils (P, 8, 3) of those two sides: for each, two points along
    the side and two across the width, so that ``cross(s3 - s2, s1 - s0)`` is its outward normal;
    and each point's group (P,) (one group per section side and width position, numbered from 0)
    and its order (P,) along its side.
    """
    side_half, width_half = STENCIL_SIDE * size, STENCIL_WIDTH * size
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
            own = (a + d * max(0.0, s_here - side_half), a + d * min(length, s_here + side_half))
            if j == 0 and convex:  # the corner: the previous side's stencil ends here
                other, n_other = (a - dp * min(lp, side_half), a), outp
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
    y_lo, y_hi = np.clip(ys - width_half, -half_w, half_w), np.clip(ys + width_half, -half_w, half_w)
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


def turned_samples(
    geom: Cantilever,
    radius: float,
    mesh: TetMesh,
    lo,
    hi,
    spacing: float,
    width_spacing: float,
    size: float = 1.0,
):
    """Candidate points of the annular snap's sector (:func:`jsnap._geometry.presets.generate`):
    :func:`section_samples` of its hook section, turned about the z axis (the section's depth
    ``x`` from the bore is ``r = radius + h - x``, its width position ``y`` the arc ``radius
    phi``), put on the mesh's faceted surface (each point and stencil point moved to the closest
    point of the faces contact can reach: the facets are chords of the turned surface) and kept
    inside the box [lo, hi] (mm). The same arrays as :func:`section_samples`.

    The general :func:`surface_samples` lays lines on flat patches; on a surface of revolution
    every facet is its own patch, and the edges where a flat face (the tube's top) meets a
    turned one (the lip's ramp) are polylines its corner points do not follow.
    """
    import trimesh

    inf = np.full(3, np.inf)
    X, N, C, S, G, O = section_samples(geom, -inf, inf, spacing, width_spacing, size)
    # Lines at the middles of the strips, not on the sector's cut planes.
    ny = math.ceil(geom.width / width_spacing) + 1
    X, S = X * [1, (ny - 1) / ny, 1], S * [1, (ny - 1) / ny, 1]

    def turn(p):
        r, phi = radius + geom.thickness - p[..., 0], p[..., 1] / radius
        return np.stack([r * np.cos(phi), r * np.sin(phi), p[..., 2]], axis=-1)

    phi = X[:, 1] / radius
    c, s = np.cos(phi)[:, None], np.sin(phi)[:, None]
    nr, nphi = -N[..., 0], N[..., 1]
    N = np.stack([nr * c - nphi * s, nr * s + nphi * c, N[..., 2]], axis=-1)
    # x -> -x reverses the frame's handedness: swap the two points across the width in each
    # half of the stencil so that cross(s3 - s2, s1 - s0) stays the outward normal.
    S = turn(S)[:, [0, 1, 3, 2, 4, 5, 7, 6]]
    X = turn(X)
    keep = np.all((X >= lo) & (X <= hi), axis=1)
    surface = trimesh.Trimesh(mesh.points, mesh.contact_faces(), process=False)
    on = lambda q: trimesh.proximity.closest_point(surface, q.reshape(-1, 3))[0].reshape(q.shape)  # noqa: E731
    X, S = on(X[keep]), on(S[keep])
    _, G = np.unique(G[keep], return_inverse=True)
    return X, N[keep], C[keep], S, G, O[keep]


# Distance from a face (plane distance plus the barycentric excess scaled by the face's size, mm
# at the part's size 1) below which a point counts as lying on it, besides the float32 rounding
# of the part's coordinates (_FLOAT32_ROUNDING, below: a file's flat patch is a plane only to it).
_ON_FACE = 1e-7
# Largest distance of a flat patch's vertices from its plane, mm at size 1: faces joined through
# slowly turning neighbours farther from it are a curved surface. Besides it, a part's vertices
# may stand off their plane by float32 rounding (an STL file's; gmsh places its nodes on those
# facets), a few units of 6e-8 of their coordinates: that much more is allowed.
_PLANAR = 1e-7
_FLOAT32_ROUNDING = 4 * 2.0**-24


def _tolerance(base: float, size: float, points: np.ndarray) -> float:
    """A length tolerance, mm: ``base`` at the part's ``size``, plus the float32 rounding of the
    part's coordinates ``points``."""
    return base * size + _FLOAT32_ROUNDING * float(np.max(np.abs(points)))


def _candidate_pairs(tri: np.ndarray, X: np.ndarray, on_face: float) -> tuple[np.ndarray, np.ndarray]:
    """(point, face) index pairs (k,), (k,) of the points X (P, 3) and the triangles tri (F, 3, 3)
    that may lie on one another: the point within the largest circumradius about the centroid
    of the face (any point of a triangle is within that of its centroid), with a margin well
    above the on-face tolerance ``on_face``. A k-d tree of the centroids keeps this O(P log F) in
    time and O(P) in memory, where testing every point against every face took P x F x 3 floats."""
    from scipy.spatial import cKDTree

    centre = tri.mean(axis=1)
    reach = np.linalg.norm(tri - centre[:, None], axis=2).max()
    reach = reach * (1 + 1e-6) + 1e3 * on_face
    near = cKDTree(centre).query_ball_point(X, reach)
    counts = np.fromiter((len(c) for c in near), dtype=np.int64, count=len(X))
    p = np.repeat(np.arange(len(X)), counts)
    f = np.fromiter((j for c in near for j in c), dtype=np.int64, count=int(counts.sum()))
    return p, f


def locate_on_faces(asm: Assembly, faces: np.ndarray, X: np.ndarray, normals: np.ndarray, size: float = 1.0):
    """Face of each point (on the boundary) and its interpolating nodes and weights.

    A point on an edge of the socket lies on several faces; it is given the one whose normal is
    closest to ``normals`` (P, 3), the outward normal of the section side it was sampled on, so
    that every point of one side shares that side's normal. The weights are the element's own
    shape functions on the face (P1: barycentric; P2: vertex l(2l-1), edge 4 l_i l_j), so the
    contact resolution is independent of the mesh. ``size``: the part's size.
    Returns nodes (P, k), weights (P, k) and the face index (P,).
    """
    pts = asm.mesh.points
    tri = pts[faces]  # (F, 3, 3)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    nrm = np.cross(e1, e2)
    area2 = np.linalg.norm(nrm, axis=1)
    on_face = _tolerance(_ON_FACE, size, pts)
    p, f = _candidate_pairs(tri, X, on_face)
    d = X[p] - tri[f, 0]  # one row per (point, face) pair near each other
    plane = np.abs(np.einsum("kd,kd->k", d, nrm[f])) / area2[f]
    l2 = np.einsum("kd,kd->k", d, np.cross(nrm, e1)[f]) / area2[f] ** 2
    l1 = np.einsum("kd,kd->k", d, np.cross(e2, nrm)[f]) / area2[f] ** 2
    l0 = 1 - l1 - l2
    outside = np.maximum(np.maximum(-l0, -l1), -l2).clip(min=0)
    score = plane + outside * area2[f] ** 0.5
    on = score <= on_face
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


def _patches(points: np.ndarray, faces: np.ndarray, normals: np.ndarray, cos_tol: float):
    """Label (F,) of flat patches: faces joined across shared edges whose normals agree within
    ``cos_tol``; and the edge -> faces map (every edge of ``faces``)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    F = faces.shape[0]
    edges = np.sort(faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)  # (3F, 2)
    owner = np.repeat(np.arange(F), 3)
    _, inverse = np.unique(edges, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    order = np.argsort(inverse, kind="stable")
    key, own = inverse[order], owner[order]
    same = np.flatnonzero(key[1:] == key[:-1])
    a, b = own[same], own[same + 1]
    flat = np.einsum("ij,ij->i", normals[a], normals[b]) > cos_tol
    graph = coo_matrix((np.ones(int(flat.sum())), (a[flat], b[flat])), shape=(F, F))
    _, label = connected_components(graph, directed=False)
    neighbour = -np.ones((F, 3), np.int64)  # the face across each edge (-1: none among `faces`)
    slot = order % 3
    neighbour[own[same], slot[same]] = own[same + 1]
    neighbour[own[same + 1], slot[same + 1]] = own[same]
    return label, neighbour


def _line_hits(P2, v: float, tol: float):
    """For triangles P2 (T, 3, 2) in patch coordinates (u, v), the u-interval each meets on the
    line v (NaN where it misses) and which edge gives each end: (lo, hi, edge_lo, edge_hi)."""
    a = P2[:, [0, 1, 2]]
    b = P2[:, [1, 2, 0]]
    dv = b[..., 1] - a[..., 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (v - a[..., 1]) / dv
    cross = (np.abs(dv) > tol) & (s >= -1e-12) & (s <= 1 + 1e-12)
    u = np.where(cross, a[..., 0] + s.clip(0, 1) * (b[..., 0] - a[..., 0]), np.nan)
    # An edge lying on the line gives both its ends.
    on = (np.abs(dv) <= tol) & (np.abs(a[..., 1] - v) <= tol)
    u_lo = np.fmin(np.where(on, np.minimum(a[..., 0], b[..., 0]), np.nan), u)
    u_hi = np.fmax(np.where(on, np.maximum(a[..., 0], b[..., 0]), np.nan), u)
    lo, hi = np.nanmin(u_lo, axis=1, initial=np.inf), np.nanmax(u_hi, axis=1, initial=-np.inf)
    e_lo = np.argmin(np.where(np.isnan(u_lo), np.inf, u_lo), axis=1)
    e_hi = np.argmax(np.where(np.isnan(u_hi), -np.inf, u_hi), axis=1)
    return lo, hi, e_lo, e_hi


def _inside(P2, q, tol: float) -> np.ndarray:
    """(k,) bool: points q (k, 2) inside any triangle of P2 (T, 3, 2), with tolerance."""
    a, b, c = P2[:, 0], P2[:, 1], P2[:, 2]

    def side(s, e):
        return (e[None, :, 0] - s[None, :, 0]) * (q[:, None, 1] - s[None, :, 1]) - (
            e[None, :, 1] - s[None, :, 1]
        ) * (q[:, None, 0] - s[None, :, 0])

    d1, d2, d3 = side(a, b), side(b, c), side(c, a)
    pos = (d1 >= -tol) & (d2 >= -tol) & (d3 >= -tol)
    neg = (d1 <= tol) & (d2 <= tol) & (d3 <= tol)
    return np.any(pos | neg, axis=1)


def _patch_frame(normal_sum: np.ndarray, direction: np.ndarray, points: np.ndarray):
    """(n, u, v): a flat patch's unit normal, the motion's direction in it (when the patch
    faces the motion: across its narrower extent, its vertices being ``points``) and
    ``v = u x n`` across, so that ``cross(v, u) = n``."""
    n = normal_sum / np.linalg.norm(normal_sum)
    u = direction - np.dot(direction, n) * n
    if np.linalg.norm(u) < 1e-6:  # the patch faces the motion: lines across its narrower side
        a = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
        a /= np.linalg.norm(a)
        b = np.cross(n, a)
        span = lambda axis: np.ptp(points @ axis)  # noqa: E731
        u = a if span(a) <= span(b) else b
    u /= np.linalg.norm(u)
    return n, u, np.cross(u, n)


def surface_samples(mesh: TetMesh, lo, hi, direction, spacing: float, width_spacing: float, size: float = 1.0):
    """Candidate points on any part's surface within the box [lo, hi] (mm).

    The boundary faces there are joined into flat patches (normals within 1 degree), and each
    patch is sampled along lines that run with the rigid part's motion (``direction`` projected
    into the patch) from one edge of the patch to the other: every ``spacing`` along a line
    (fine: the contact line moves along it) and every ``width_spacing`` across (coarse). Points
    that coincide (the ends of two patches' lines on their common edge) are kept once; a line's
    end on a convex edge is a corner point, whose second normal stencil lies on the patch
    across the edge. On a prismatic part moved along its faces this is the section sampling of
    :func:`section_samples`.

    Returns the same arrays as :func:`section_samples` (points, normals (P, 2, 3), corner,
    stencils (P, 8, 3), group, order).
    """
    side_half, width_half = STENCIL_SIDE * size, STENCIL_WIDTH * size
    pts = mesh.points
    # Whole patches are sampled (their grid does not depend on the box), then cut to the box.
    faces = mesh.boundary_faces()
    tri = pts[faces]
    near = np.all(tri.max(axis=1) >= lo, axis=1) & np.all(tri.min(axis=1) <= hi, axis=1)
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    unit = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
    flat = math.cos(math.radians(1.0))
    label, neighbour = _patches(pts, faces, unit, flat)
    scale = float(np.linalg.norm(np.ptp(pts, axis=0)))
    tol = 1e-9 * scale
    planar = _tolerance(_PLANAR, size, pts)
    # Faces joined through slowly turning neighbours (a curved surface) are not one plane:
    # each of those is its own patch.
    for p in np.unique(label):
        members = np.flatnonzero(label == p)
        n = np.sum(nrm[members], axis=0)
        if np.max(np.abs((tri[members] - tri[members[0], 0]) @ (n / np.linalg.norm(n)))) > planar:
            label[members] = label.max() + 1 + np.arange(members.size)
    d = np.asarray(direction, np.float64) / np.linalg.norm(direction)
    frames = {
        int(p): _patch_frame(np.sum(nrm[label == p], axis=0), d, tri[label == p].reshape(-1, 3))
        for p in np.unique(label)
    }
    flat2d = {}  # patch -> (origin, its triangles in its (u, v) coordinates)
    for patch, (_, u, v) in frames.items():
        t = tri[label == patch]
        flat2d[patch] = (t[0, 0], np.stack([(t - t[0, 0]) @ u, (t - t[0, 0]) @ v], axis=-1))

    def on_patch(patch, q) -> bool:
        o, P2 = flat2d[patch]
        _, u, v = frames[patch]
        return bool(_inside(P2, np.array([[(q - o) @ u, (q - o) @ v]]), tol * scale)[0])

    X, N, C, S, G, O = [], [], [], [], [], []
    line = 0
    for patch, (n, u, v) in frames.items():
        members = np.flatnonzero(label == patch)
        if not near[members].any():
            continue
        o, P2 = flat2d[patch]  # P2: (T, 3, 2)
        v_lo, v_hi = P2[..., 1].min(), P2[..., 1].max()
        k = max(1, math.ceil((v_hi - v_lo) / width_spacing - 1e-9))
        for vk in np.clip(np.linspace(v_lo, v_hi, k + 1), v_lo + 2 * tol, v_hi - 2 * tol):
            lo_t, hi_t, e_lo, e_hi = _line_hits(P2, vk, tol)
            hit = np.isfinite(lo_t) & (hi_t >= lo_t)
            if not hit.any():
                continue
            t_lo = int(np.argmin(np.where(hit, lo_t, np.inf)))
            t_hi = int(np.argmax(np.where(hit, hi_t, -np.inf)))
            u_lo, u_hi = lo_t[t_lo], hi_t[t_hi]
            m = max(1, math.ceil((u_hi - u_lo) / spacing - 1e-9))
            us = u_lo + (u_hi - u_lo) * np.arange(m + 1) / m
            inside = _inside(P2, np.stack([us, np.full_like(us, vk)], 1), tol * scale)
            ends = {0: (members[t_lo], e_lo[t_lo]), m: (members[t_hi], e_hi[t_hi])}
            for j in np.flatnonzero(inside):
                p = o + us[j] * u + vk * v
                # The stencil along the line and across it, each arm shortened until it stays on
                # the patch (a line may cross a non-convex patch in several pieces).
                own = [
                    p - _on_patch_step(P2, us[j], vk, (-1.0, 0.0), us[j] - u_lo, side_half, tol * scale) * u,
                    p + _on_patch_step(P2, us[j], vk, (1.0, 0.0), u_hi - us[j], side_half, tol * scale) * u,
                ]
                for sign in (-1.0, 1.0):
                    room = (vk - v_lo) if sign < 0 else (v_hi - vk)
                    step = _on_patch_step(P2, us[j], vk, (0.0, sign), room, width_half, tol * scale)
                    own.append(p + sign * step * v)
                own = _sound(
                    own, tri[members[_triangle_at(P2, us[j], vk, tol * scale)]], n, side_half * width_half
                )
                other, n_other, corner = own, n, False
                if j in ends:
                    face, edge = _boundary_edge_at(P2, members, ends[j], neighbour, label, us[j], vk, 4 * tol)
                    nb = neighbour[face, edge]
                    if nb >= 0 and label[nb] != patch and np.dot(unit[nb], n) < flat:
                        far = tri[nb].mean(axis=0)
                        if np.dot(far - p, n) < -tol:  # convex: the patch across turns away
                            a, b = pts[faces[face, edge]], pts[faces[face, (edge + 1) % 3]]
                            e = (b - a) / np.linalg.norm(b - a)
                            square = abs(np.dot(v, e)) > 1 - 1e-9  # the line crosses the edge squarely
                            e = v if square else e  # the stencil's axes: cross(e, w) = n2 below
                            n2 = unit[nb]
                            w = np.cross(n2, e)  # in the neighbour, across the edge
                            into = 1.0 if np.dot(far - p, w) >= 0 else -1.0
                            step = side_half  # shortened to stay on the neighbour
                            while step > 1e-3 * side_half and not on_patch(int(label[nb]), p + into * step * w):
                                step *= 0.5
                            if on_patch(int(label[nb]), p + into * step * w):  # else: a face point
                                side = [p, p + step * w] if into > 0 else [p - step * w, p]
                                if square:
                                    along = own[2:]  # the points across lie on the edge, on both patches
                                else:
                                    length = np.linalg.norm(b - a)
                                    half = 0.5 * min(length, 2 * width_half)
                                    mid = np.clip(np.dot(p - a, e), half, length - half)
                                    along = [a + (mid - half) * e, a + (mid + half) * e]
                                other, n_other, corner = [*side, *along], n2, True
                                other = _sound(other, tri[nb], n2, side_half * width_half)
                X.append(p)
                N.append((n, n_other))
                C.append(corner)
                S.append((*own, *other))
                G.append(line)
                O.append(j)
            line += 1
    if not X:
        empty = np.zeros((0, 3))
        return (
            empty,
            np.zeros((0, 2, 3)),
            np.zeros(0, bool),
            np.zeros((0, 8, 3)),
            np.zeros(0, int),
            np.zeros(0, int),
        )
    X, N, C, S, G, O = (np.array(a) for a in (X, N, C, S, G, O))
    keep = _dedupe(X, C, N, d, 1e-6 * scale)
    keep = keep[np.all((X[keep] >= lo) & (X[keep] <= hi), axis=1)]
    _, G = np.unique(G[keep], return_inverse=True)
    return X[keep], N[keep], C[keep], S[keep], G, O[keep]


def _surface_points(vertices: np.ndarray, faces: np.ndarray, step: float) -> np.ndarray:
    """Points covering every triangle of a surface, no point of it farther than ``step`` from
    one of them (a barycentric grid of each triangle, as fine as its longest edge needs)."""
    tri = np.asarray(vertices, np.float64)[np.asarray(faces)]
    longest = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1)
    out = [tri.reshape(-1, 3)]
    for n in np.unique(np.ceil(longest / step).astype(int)):
        if n < 2:
            continue
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        ok = i + j <= n
        a, b = i[ok] / n, j[ok] / n
        w = np.stack([1.0 - a - b, a, b], axis=1)  # (g, 3) barycentric weights
        out.append(np.einsum("gk,tkd->tgd", w, tri[np.ceil(longest / step).astype(int) == n]).reshape(-1, 3))
    return np.concatenate(out)


def near_path(X: np.ndarray, vertices, faces, poses: np.ndarray, reach: float) -> np.ndarray:
    """(P,) which points X (P, 3) the rigid part's surface (``vertices`` (v, 3) in its own frame,
    triangles ``faces``) comes within ``reach`` of at some pose along its path (``poses`` (n, 3)
    translations or (n, 7) translation and unit quaternion), mm.

    A part that slides along the deformable part (a housing over a hook's prongs) reaches only
    the faces it passes close to, while the box it sweeps can enclose the whole part: the points
    of the faces far from every pose of its surface can never touch it. A point the rigid part
    passes through is near its surface at some pose on the way in, so the distance needs no sign;
    the poses are taken every ``reach / 4`` of travel and the surface is covered by points no
    farther than ``reach / 8`` from any of it, and the test allows for both (a point is kept
    within ``1.25 reach`` of a sample of the surface at a chosen pose).
    """
    from scipy.spatial import cKDTree

    from jsnap._geometry.motion import quat_matrix

    X = np.asarray(X, np.float64)
    poses = np.asarray(poses, np.float64)
    step = 0.125 * reach
    tree = cKDTree(_surface_points(vertices, faces, step))
    # Poses close enough together that a point's distance changes by under reach / 4 between two.
    v = np.asarray(vertices, np.float64)
    span = float(np.linalg.norm(np.ptp(v, axis=0)))
    moves = np.linalg.norm(np.diff(poses[:, :3], axis=0), axis=1)
    if poses.shape[1] == 7:
        turns = 2 * np.arccos(np.clip(np.abs(np.sum(poses[1:, 3:] * poses[:-1, 3:], axis=1)), 0, 1))
        moves = moves + turns * (span + float(np.max(np.linalg.norm(X - poses[0, :3], axis=1))))
    travelled = np.r_[0.0, np.cumsum(moves)]
    marks = np.unique(np.searchsorted(travelled, np.arange(0, travelled[-1] + step, 2 * step)))
    chosen = poses[np.r_[marks[marks < len(poses)], len(poses) - 1]]
    near = np.zeros(X.shape[0], bool)
    limit = reach + 2 * step  # allowing for the surface's cover and the poses' spacing
    for pose in chosen:
        rel = X - pose[:3]
        if poses.shape[1] == 7:
            rel = rel @ quat_matrix(pose[3:])  # R' (x - t), row-wise
        todo = ~near
        if np.any(todo):
            d, _ = tree.query(rel[todo], distance_upper_bound=limit)
            near[np.flatnonzero(todo)[np.isfinite(d)]] = True
    return near


def line_reach(X: np.ndarray, group: np.ndarray, order: np.ndarray):
    """Each point's line of samples: its unit direction (P, 3), from the line's first point
    (lowest ``order``) to its last (zero for a line of one point), and the distances (P, 2)
    along it from the point back to the first and on to the last, mm. A line runs across its
    face from edge to edge (the box [lo, hi] may cut it short), so these say how far the face
    extends from a point along the rigid part's motion."""
    by_line = np.lexsort((order, group))  # each line's points in order, line after line
    starts = np.flatnonzero(np.r_[True, np.diff(group[by_line]) != 0])
    ends = np.r_[starts[1:], by_line.size] - 1
    first = np.zeros(int(group.max()) + 1 if group.size else 0, np.int64)
    last = first.copy()
    first[group[by_line[starts]]], last[group[by_line[ends]]] = by_line[starts], by_line[ends]
    d = X[last[group]] - X[first[group]]
    length = np.linalg.norm(d, axis=1)
    u = np.where(length[:, None] > 0, d / np.maximum(length, 1e-300)[:, None], 0.0)
    back = np.einsum("pi,pi->p", X - X[first[group]], u)
    return u, np.stack([back, length - back], axis=1)


def _triangle_at(P2, u: float, v: float, tol: float) -> int:
    """Index into the patch's triangles ``P2`` (T, 3, 2) of one that holds (u, v) (the first)."""
    # Every triangle at once: a loop over a long patch's triangles, one call each, was most of
    # the sampling's time on a part with long faces.
    a, b, c = P2[:, 0], P2[:, 1], P2[:, 2]
    q = np.array([u, v])

    def side(s, e):
        return (e[:, 0] - s[:, 0]) * (q[1] - s[:, 1]) - (e[:, 1] - s[:, 1]) * (q[0] - s[:, 0])

    d1, d2, d3 = side(a, b), side(b, c), side(c, a)
    inside = ((d1 >= -tol) & (d2 >= -tol) & (d3 >= -tol)) | ((d1 <= tol) & (d2 <= tol) & (d3 <= tol))
    return int(np.argmax(inside)) if inside.any() else 0


def _sound(stencil, triangle, n, area: float):
    """``stencil`` (4 points) if its normal ``cross(s3 - s2, s1 - s0)`` is ``n``'s (and its
    cross product above a thousandth of ``area``, the full stencil's), else one on the mesh
    ``triangle`` (3, 3) it lies on, oriented to ``n``.

    A line that meets its patch only at a vertex (a curved surface's facets are patches of one
    triangle each, and a line may just touch one) has arms of zero length along it: no normal
    at all, which at a corner would hand the contact the other face's normal."""
    m = np.cross(stencil[3] - stencil[2], stencil[1] - stencil[0])
    size = np.linalg.norm(m)
    if size > 1e-3 * area and np.dot(m, n) > (1 - 1e-6) * size:
        return stencil
    a, b, c = triangle
    if np.dot(np.cross(c - a, b - a), n) < 0:
        b, c = c, b
    return [a, b, a, c]


def _boundary_edge_at(P2, members, found, neighbour, label, u: float, v: float, tol: float):
    """The (face, edge) of the patch's boundary through the line's end (u, v): where the line
    leaves the patch through a mesh vertex, the edge :func:`_line_hits` gives may be an interior
    one (its neighbour in the same patch); then a boundary edge through that point is taken, so
    that the convex edge of the part there is seen. ``found``: the edge the line hit."""
    face, edge = found
    nb = neighbour[face, edge]
    if nb < 0 or label[nb] != label[face]:
        return face, edge
    a = P2
    b = P2[:, [1, 2, 0]]
    d = b - a
    t = np.clip(np.einsum("tek,tek->te", np.array([u, v]) - a, d) / np.einsum("tek,tek->te", d, d), 0.0, 1.0)
    dist = np.linalg.norm(a + t[..., None] * d - np.array([u, v]), axis=-1)
    own = label[members][:, None]
    nbr = neighbour[members]
    boundary = (nbr < 0) | (label[np.maximum(nbr, 0)] != own)
    hit = np.argwhere((dist <= max(tol, 1e-9)) & boundary)
    if hit.size == 0:
        return found
    t_i, e_i = hit[0]
    return members[t_i], int(e_i)


def _on_patch_step(P2, u0: float, v0: float, d, room: float, length: float, tol: float) -> float:
    """The longest step <= min(``length``, ``room``) from (u0, v0) along the unit direction ``d``
    whose segment stays on the patch's triangles ``P2`` (checked at ten points along it),
    halved until it does; 0 when none longer than a thousandth of ``length`` does."""
    step = min(length, max(room, 0.0))
    fractions = np.linspace(0.1, 1.0, 10)[:, None]
    while step >= 1e-3 * length:
        q = np.array([u0, v0]) + fractions * step * np.asarray(d)
        if np.all(_inside(P2, q, tol)):
            return float(step)
        step *= 0.5
    return 0.0


def _dedupe(X: np.ndarray, corner: np.ndarray, normals: np.ndarray, direction, tol: float) -> np.ndarray:
    """Indices of points kept when several coincide (within ``tol``): a corner one first and,
    of several corners (a vertex, where three or more faces meet), the one whose edge runs most
    across the motion ``direction``.

    A corner carries the normal cone of two faces only. At a vertex the rigid part moving along
    ``direction`` meets it on the edge it sweeps across (a catch's ramp-to-land edge), not on an
    edge it slides along (the land's edge with the part's side face): that face's lines along
    the edge sample it already, and its cone (side face, ramp) would tilt a rigid face's push on
    the vertex into the ramp's normal.
    """
    key = np.round(X / tol).astype(np.int64)
    edge = np.cross(normals[:, 0], normals[:, 1])
    d = np.asarray(direction, np.float64) / np.linalg.norm(direction)
    # |cos| of the edge to the motion (face points, whose two normals agree: 0, never compared).
    along = np.abs(edge @ d) / np.maximum(np.linalg.norm(edge, axis=1), 1e-12)
    order = np.lexsort((np.round(along, 9), ~corner, *key.T[::-1]))
    k = key[order]
    new = np.ones(len(order), bool)
    new[1:] = np.any(k[1:] != k[:-1], axis=1)
    return np.sort(order[new])
