"""Host side of the signed distances: the exact triangle-mesh SDF's precomputation (trimesh).

The kernels are in :mod:`jsnap._core.sdf`; the neural SDF's training is in
:mod:`jsnap._build.neural_sdf`. Lengths in mm.
"""

import warnings

import jax
import jax.numpy as jnp
import numpy as np

from jsnap._core.sdf import (
    BLOCK,
    FAR_INSIDE,
    FAR_OUTSIDE,
    GridMeshSDF,
    MeshSDF,
    _closest_on_triangle,
    _dot3,
    _signed_on,
    _triangle_terms,
)

__all__ = ["grid_mesh_sdf", "mesh_sdf_from_trimesh"]


def mesh_sdf_from_trimesh(mesh) -> MeshSDF:
    """Precompute triangles and pseudonormals of a closed mesh, in float64.

    Args:
        mesh: ``trimesh.Trimesh``, watertight with consistent winding. A mesh whose normals
            point inwards (negative volume) is flipped, with a warning.

    Zero-area triangles are dropped (their points lie on their neighbours' edges).

    Raises:
        ValueError: the mesh is not watertight, or its winding is inconsistent.
    """
    if not mesh.is_watertight:
        raise ValueError(
            "mesh is not watertight: a signed distance needs a closed surface "
            "(every edge shared by exactly two triangles)"
        )
    if not mesh.is_winding_consistent:
        raise ValueError(
            "mesh winding is inconsistent: neighbouring triangles must list their shared "
            "edge in opposite orders (try trimesh.repair.fix_winding)"
        )
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if mesh.volume < 0:
        warnings.warn(
            "mesh normals point inwards (negative volume); flipping its triangles",
            stacklevel=2,
        )
        faces = faces[:, ::-1]
    tri = vertices[faces]  # (F, 3 corners, 3)

    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(cross, axis=1, keepdims=True)
    # A zero-area triangle has no normal and adds nothing to its neighbours' pseudonormals.
    face_n = np.where(area2 > 0, cross / np.where(area2 > 0, area2, 1.0), 0.0)

    # Interior angle at each corner, for the angle-weighted vertex pseudonormals.
    e1 = tri[:, [1, 2, 0]] - tri
    e2 = tri[:, [2, 0, 1]] - tri
    l1 = np.linalg.norm(e1, axis=2)
    l2 = np.linalg.norm(e2, axis=2)
    cos = np.sum(e1 * e2, axis=2) / np.maximum(l1 * l2, np.finfo(np.float64).tiny)
    angle = np.arccos(np.clip(cos, -1.0, 1.0))  # (F, 3)
    vert_acc = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(vert_acc, faces[:, k], angle[:, k, None] * face_n)
    vertex_n = _normalize(vert_acc)[faces]

    # Edges ab, bc, ca of every face; a watertight mesh has each undirected edge twice.
    edges = np.sort(np.stack([faces, faces[:, [1, 2, 0]]], axis=2), axis=2).reshape(-1, 2)
    _, edge_id = np.unique(edges, axis=0, return_inverse=True)
    edge_id = edge_id.reshape(-1)
    edge_acc = np.zeros((edge_id.max() + 1, 3))
    np.add.at(edge_acc, edge_id, np.repeat(face_n, 3, axis=0))
    edge_n = _normalize(edge_acc)[edge_id].reshape(-1, 3, 3)

    # In-plane edge normals from the float64 face normals: computed from float32 vertices,
    # the long thin fillet triangles (4.8 mm × 0.007 mm) would get normals off by 1e-4.
    edge_vec = tri[:, [1, 2, 0]] - tri
    edge_perp = _normalize(np.cross(edge_vec, face_n[:, None, :]))

    # A zero-area triangle covers no point that its neighbours' edges do not: drop it (after
    # it has contributed, with weight 0, to the pseudonormals).
    keep = area2[:, 0] > 0
    scale = np.linalg.norm(vertices.max(0) - vertices.min(0))
    with jax.enable_x64(True):
        return MeshSDF(
            a=jnp.asarray(tri[keep, 0]),
            b=jnp.asarray(tri[keep, 1]),
            c=jnp.asarray(tri[keep, 2]),
            face_normal=jnp.asarray(face_n[keep]),
            edge_normal=jnp.asarray(edge_n[keep]),
            vertex_normal=jnp.asarray(vertex_n[keep]),
            edge_perp=jnp.asarray(edge_perp[keep]),
            scale=jnp.asarray(scale, dtype=np.float64),
        )


def _normalize(v):
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n > 0, v / np.where(n > 0, n, 1.0), 0.0)


# Fine cells of the candidate grid per side of its band, at least: the cell is half the band,
# unless that would need more than _MAX_BLOCKS coarse blocks over the part's box.
_CELLS_PER_BAND = 2.0
_MAX_BLOCKS = 2**18
# Coarse blocks (of BLOCK³ fine cells each) whose fine cells are sorted out at once.
_BLOCKS_PER_CHUNK = 32
# Coarse centres against all triangles at once, at most (bounds the search's memory).
_PAIRS_PER_CHUNK = 2**22
# A point's cell is found in the rollout's precision: allow it to land in a neighbour by up to
# this fraction of a cell (float32 rounding of its coordinate in cells is ~1e-7 of it).
_CELL_SLACK = 0.02


def grid_mesh_sdf(
    sdf: MeshSDF, band: float, *, cell: float | None = None, progress: bool = False
) -> GridMeshSDF:
    """The candidate-triangle grid of a mesh SDF (:class:`jsnap._core.sdf.GridMeshSDF`).

    Args:
        sdf: the brute-force mesh SDF (:func:`mesh_sdf_from_trimesh`).
        band: mm; φ is exact within ``±band`` of the surface (beyond it, its side).
        cell: fine cell side, mm (default ``band / 2``, coarser where the part's box would need
            more than ``2**18`` blocks of 8³ cells).
        progress: print what is being built.

    Returns:
        The :class:`GridMeshSDF`, in float64.
    """
    if not band > 0:
        raise ValueError(f"band = {band!r}: must be positive (mm)")
    with jax.enable_x64(True):
        tri = np.stack([np.asarray(sdf.a), np.asarray(sdf.b), np.asarray(sdf.c)], axis=1)
        lo, hi = tri.reshape(-1, 3).min(0), tri.reshape(-1, 3).max(0)
        h = float(cell) if cell is not None else band / _CELLS_PER_BAND
        pad = band + BLOCK * h
        extent = hi - lo + 2 * pad
        h = max(h, float(np.prod(extent) / _MAX_BLOCKS) ** (1 / 3) / BLOCK)
        H = BLOCK * h
        origin = lo - band - H
        dims = np.ceil((hi + band + H - origin) / H).astype(np.int64)
        terms = _triangle_terms(sdf, jnp.float64)
        hd_fine = (0.5 * np.sqrt(3.0) + _CELL_SLACK) * h
        hd_coarse = 0.5 * np.sqrt(3.0) * H + _CELL_SLACK * h

        # Coarse blocks: the least distance from each centre and which triangles can be nearest
        # somewhere in the block.
        ijk = np.stack(np.meshgrid(*(np.arange(d) for d in dims), indexing="ij"), -1).reshape(-1, 3)
        centres = origin + (ijk + 0.5) * H
        n_faces = tri.shape[0]
        step = max(1, _PAIRS_PER_CHUNK // n_faces)
        dmin = np.empty(len(centres))
        nearest = np.empty(len(centres), np.int64)
        lists = []
        for i in range(0, len(centres), step):
            d = np.asarray(_distances(terms, jnp.asarray(centres[i : i + step])))  # (chunk, F)
            dmin[i : i + step], nearest[i : i + step] = d.min(1), d.argmin(1)
            for row in d[d.min(1) <= band + hd_coarse]:
                lists.append(np.flatnonzero(row <= row.min() + 2 * hd_coarse))
        near_block = dmin <= band + hd_coarse
        coarse = np.where(
            near_block, -1, np.where(_sides(sdf, terms, centres, nearest) < 0, FAR_INSIDE, FAR_OUTSIDE)
        )
        which = np.flatnonzero(near_block)
        coarse[which] = np.arange(which.size)
        if progress:
            print(
                f"jsnap: SDF grid of {dims.prod()} blocks of {BLOCK}^3 cells of {h:.3g} mm, "
                f"{which.size} near the surface"
            )

        # Fine cells of the near blocks, grouped by their block's list length (padded to a power
        # of two) so that each group is one compiled search.
        local = np.stack(np.meshgrid(*(np.arange(BLOCK),) * 3, indexing="ij"), -1).reshape(-1, 3)
        blocks = np.zeros((which.size, BLOCK**3), np.int64)
        cell_lists = []  # (block, fine cell, candidates): filled per group
        widths = np.array([1 << int(np.ceil(np.log2(max(len(x), 1)))) for x in lists], np.int64)
        for width in np.unique(widths):
            members = np.flatnonzero(widths == width)
            for i in range(0, members.size, _BLOCKS_PER_CHUNK):
                chunk = members[i : i + _BLOCKS_PER_CHUNK]
                ids = np.stack([np.resize(lists[b], width) for b in chunk])  # (nb, W), cycled
                valid = np.stack([np.arange(width) < len(lists[b]) for b in chunk])
                pts = origin + (ijk[which[chunk]][:, None, :] * BLOCK + local[None] + 0.5) * h  # (nb, 512, 3)
                df = np.asarray(_list_distances(terms, jnp.asarray(pts), jnp.asarray(ids)))  # (nb, 512, W)
                df = np.where(valid[:, None, :], df, np.inf)
                dmin_f = df.min(2)
                win = np.take_along_axis(ids, df.argmin(2), axis=1)  # (nb, 512)
                side = _sides(sdf, terms, pts.reshape(-1, 3), win.reshape(-1)).reshape(win.shape)
                near = dmin_f <= band + hd_fine
                blocks[chunk] = np.where(near, 0, np.where(side < 0, FAR_INSIDE, FAR_OUTSIDE))
                keep = (df <= dmin_f[..., None] + 2 * hd_fine) & near[..., None]
                nb, nc = np.nonzero(near)
                cell_lists.append((chunk[nb], nc, ids[nb], keep[nb, nc]))

        # One row per near fine cell (its candidates first, then its first one repeated), equal
        # rows shared.
        block_of = np.concatenate([c[0] for c in cell_lists]) if cell_lists else np.zeros(0, np.int64)
        cell_of = np.concatenate([c[1] for c in cell_lists]) if cell_lists else np.zeros(0, np.int64)
        k = max((int(c[3].sum(1).max()) for c in cell_lists if c[3].size), default=1)
        rows = np.zeros((block_of.size, k), np.int64)
        at = 0
        for _, _, ids, keep in cell_lists:
            order = np.argsort(~keep, axis=1, kind="stable")[:, :k]
            picked = np.take_along_axis(ids, order, axis=1)
            picked = np.concatenate([picked, np.repeat(picked[:, :1], k - picked.shape[1], axis=1)], axis=1)
            count = keep.sum(1)
            picked = np.where(np.arange(k) < count[:, None], picked, picked[:, :1])
            rows[at : at + len(picked)] = np.sort(picked, axis=1)
            at += len(picked)
        rows, code = np.unique(rows, axis=0, return_inverse=True)
        blocks[block_of, cell_of] = code.reshape(-1)
        if progress:
            print(
                f"jsnap: SDF grid: {block_of.size} cells near the surface, "
                f"{rows.shape[0]} lists of <= {k} triangles"
            )
        return GridMeshSDF(
            mesh=sdf,
            origin=jnp.asarray(origin),
            cell=jnp.asarray(h, jnp.float64),
            dims=jnp.asarray(dims, jnp.int32),
            coarse=jnp.asarray(coarse, jnp.int32),
            blocks=jnp.asarray(blocks if blocks.size else np.zeros((1, BLOCK**3), np.int64), jnp.int32),
            rows=jnp.asarray(rows if rows.size else np.zeros((1, 1), np.int64), jnp.int32),
            band=float(band),
        )


@jax.jit
def _distances(terms, points):
    """(N, F) unsigned distances from points (N, 3) to every triangle."""
    t = jax.tree.map(lambda x: x[..., None, :], terms)  # vectors (3, 1, F), scalars (1, F)
    diff, _ = _closest_on_triangle(points.T[:, :, None] - t["a"], t)
    return jnp.sqrt(_dot3(diff, diff))


@jax.jit
def _list_distances(terms, points, ids):
    """(B, N, W) unsigned distances from points (B, N, 3) to their block's triangles ids (B, W)."""

    def one(p, j):
        sel = jax.tree.map(lambda t: t[..., None, j], terms)  # vectors (3, 1, W), scalars (1, W)
        diff, _ = _closest_on_triangle(p.T[:, :, None] - sel["a"], sel)
        return jnp.sqrt(_dot3(diff, diff))

    return jax.vmap(one)(points, ids)


def _sides(sdf, terms, points, nearest):
    """(N,) the sign of φ at points (N, 3) whose nearest triangles are ``nearest`` (N,)."""
    n = len(points)
    size = 1 << int(np.ceil(np.log2(max(n, 1))))  # a few compiled sizes, not one per call
    points = np.concatenate([points, np.zeros((size - n, 3))])
    nearest = np.concatenate([nearest, np.zeros(size - n, np.int64)])
    return np.sign(np.asarray(_signed_phi(sdf, terms, jnp.asarray(points), jnp.asarray(nearest))))[:n]


@jax.jit
def _signed_phi(sdf, terms, points, nearest):
    return _signed_on(sdf, terms, points, nearest, jnp.float64)[0]
