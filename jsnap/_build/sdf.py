"""Host side of the signed distances: the exact triangle-mesh SDF's precomputation (trimesh).

The kernels are in :mod:`jsnap._core.sdf`; the neural SDF's training is in
:mod:`jsnap._build.neural_sdf`. Lengths in mm.
"""

import warnings

import jax
import jax.numpy as jnp
import numpy as np

from jsnap._core.sdf import MeshSDF

__all__ = ["mesh_sdf_from_trimesh"]


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
