"""Signed distance functions of the rigid part, as interchangeable components.

Convention (shared by every SDF in jsnap): ``φ(p)`` is the signed distance in mm from a point
``p`` given in the rigid part's own frame (its centre at the origin) to its surface, NEGATIVE
inside and positive outside; its gradient ``∇φ`` is the outward unit normal.

:class:`AbstractSDF` is what the step asks: ``sdf(q) -> (φ, n)``, ``sdf.scene_query(q,
margin)`` (the values every contact decision needs) and ``sdf.least_along(...)`` (the
predict-correct path check). Implementations:

* :class:`RoundedBoxSDF`: the analytic rounded box (a box with filleted edges and corners), with
  a ``custom_jvp`` so that gradients are unit vectors (never NaN) even on the kinks of the
  distance field (centre, medial planes, sharp edges). Exact and cheap.
* :class:`RoundedCylinderSDF`: the analytic cylinder (axis z) with rounded circular edges (the
  annular preset's bead): the rounded box's construction in the (radius, height) half-plane.
* :class:`MeshSDF`: the exact signed distance to a closed triangle mesh by brute force over all
  triangles (the paper's "Model 1" collision baseline), signs from angle-weighted
  pseudonormals (Bærentzen & Aanæs 2005). Built on the host by
  ``jsnap._build.sdf.mesh_sdf_from_trimesh``.
* :class:`NeuralSDF`: a trained MLP (the paper's learned SDF), evaluated here in plain JAX;
  trained on the host by ``jsnap._build.neural_sdf``.
* :class:`GridMeshSDF`: the exact mesh distance at every point, each point tested against the
  few triangles that can be nearest anywhere in its grid cell (lists built on the host by
  ``jsnap._build.sdf.grid_mesh_sdf``): exact within a band about the surface, the right side
  of it beyond, at the cost of tens of triangles per point instead of all of them.
* :class:`BoundedSDF`: a costly SDF (a network) evaluated only where a contact decision
  needs it, with a rounded box below it as a lower bound elsewhere.
"""

import abc
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jsnap._core.util import safe_norm

__all__ = [
    "AbstractSDF",
    "BoundedSDF",
    "GridMeshSDF",
    "MeshSDF",
    "NeuralSDF",
    "RoundedBoxSDF",
    "RoundedCylinderSDF",
    "mesh_sdf",
    "mesh_sdf_and_normal",
    "neural_sdf",
    "neural_sdf_and_normal",
    "rounded_box_sdf",
    "rounded_box_sdf_and_normal",
]

# Fractions of a step's straight-line motion at which the predict-correct collision check looks.
PATH_CHECKS = (0.25, 0.5, 0.75, 1.0)


class AbstractSDF(eqx.Module):
    """A rigid part's signed distance, queried in its own frame (mm)."""

    @abc.abstractmethod
    def __call__(self, q):
        """``(φ, n)`` of points ``q`` (P, 3): φ (P,) mm, n (P, 3) outward unit normals."""

    def scene_query(self, q, margin: float):
        """``(φ, n)`` exact wherever a contact decision needs it (φ below ``margin``); the
        default evaluates everywhere."""
        return self(q)

    def least_along(self, points, like, margin: float, need=None):
        """(P,) least signed distance of ``points(f)`` (P, 3) over the fractions
        :data:`PATH_CHECKS` of a step's straight path (the predict-correct check).

        ``need`` (P,) bool, or None for all: the points whose value the caller reads; an SDF
        may skip the others (their values are then unspecified)."""
        return jnp.min(jnp.stack([self.scene_query(points(f), margin)[0] for f in PATH_CHECKS]), axis=0)


# --------------------------------------------------------------------------------------------
# Analytic rounded box
# --------------------------------------------------------------------------------------------


def _float_dtype(*xs):
    """Common floating dtype of ``xs``; Python scalars and sequences do not promote."""
    arrays = [x for x in xs if isinstance(x, jax.Array | np.ndarray | np.generic)]
    dtype = jnp.result_type(*arrays) if arrays else jnp.result_type(float)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.result_type(float)
    return dtype


def _rounded_box_parts(p, h, r):
    """Value, outward normal and ``∂φ/∂q`` of the rounded box.

    With ``q = |p| − (h − r)`` (componentwise), ``φ = |max(q, 0)| + min(max_i q_i, 0) − r``.
    ``g = ∂φ/∂q`` is the unit vector ``max(q,0)/|max(q,0)|`` outside the inner box and the
    one-hot vector of the largest ``q_i`` inside it; the normal is ``g ⊙ sign(p)``. Ties (the
    medial planes, the centre) are broken deterministically — first axis, ``sign(0) = +1`` —
    so the normal is a unit vector everywhere.
    """
    q = jnp.abs(p) - (h - r)
    q_pos = jnp.maximum(q, 0.0)
    out_len = safe_norm(q_pos)
    q_max = jnp.max(q, axis=-1)
    phi = out_len + jnp.minimum(q_max, 0.0) - r
    outside = out_len > 0.0
    g_out = q_pos / jnp.where(outside, out_len, 1.0)[..., None]
    g_in = jax.nn.one_hot(jax.lax.argmax(q, q.ndim - 1, jnp.int32), 3, dtype=q.dtype)
    g = jnp.where(outside[..., None], g_out, g_in)
    n = g * jnp.where(p >= 0.0, 1.0, -1.0)
    return phi, n, g


@jax.custom_jvp
def _rounded_box(p, h, r):
    return _rounded_box_parts(p, h, r)[0]


@_rounded_box.defjvp
def _rounded_box_jvp(primals, tangents):
    # Autodiff of the max/abs/norm formula gives zero or NaN gradients on the kinks; the exact
    # one-sided gradient chosen by the tie-breaking in `_rounded_box_parts` is always a unit
    # vector. With q = |p| − h + r: ∂φ/∂p = n, ∂φ/∂h = −g, ∂φ/∂r = Σg − 1.
    p, h, r = primals
    dp, dh, dr = tangents
    phi, n, g = _rounded_box_parts(p, h, r)
    dphi = jnp.sum(n * dp, -1) - jnp.sum(g * dh, -1) + (jnp.sum(g, -1) - 1.0) * dr
    return phi, dphi


def _rounded_box_args(p, half_extents, radius):
    dtype = _float_dtype(p, half_extents, radius)
    return (
        jnp.asarray(p, dtype),
        jnp.asarray(half_extents, dtype),
        jnp.asarray(radius, dtype),
    )


# Jitted so that eager calls compile once per shape instead of dispatching op by op.
_rounded_box_jit = jax.jit(_rounded_box)


@jax.jit
def _rounded_box_normal(p, h, r):
    return _rounded_box_parts(p, h, r)[1]


def rounded_box_sdf(p, half_extents, radius):
    """Exact signed distance to a rounded box centred at the origin, axes along x, y, z.

    The solid is the Minkowski sum of the box ``|x_i| ≤ half_extents_i − radius`` with a ball of
    radius ``radius``: flat faces at ``±half_extents``, edges and corners rounded with
    ``radius`` (0 gives a sharp box). Requires ``0 ≤ radius ≤ min(half_extents)`` (not checked:
    the arguments may be traced).

    Differentiable w.r.t. all arguments; gradients are finite everywhere and the gradient w.r.t.
    ``p`` is a unit vector everywhere (one-sided at kinks, ties broken towards the first axis
    and the positive side).

    Args:
        p: points, (..., 3), mm.
        half_extents: (3,) (or broadcastable to ``p``), mm.
        radius: fillet radius, scalar (or broadcastable to ``p[..., 0]``), mm.

    Returns:
        φ, (...), mm; negative inside. The dtype is the common floating dtype of the array
        arguments (Python numbers and sequences follow ``p``).
    """
    return _rounded_box_jit(*_rounded_box_args(p, half_extents, radius))


def rounded_box_sdf_and_normal(p, half_extents, radius):
    """Signed distance and outward unit normal ``∇φ`` of the rounded box.

    Args: as :func:`rounded_box_sdf`.

    Returns:
        ``(φ, n)``: φ (...) in mm, n (..., 3) unit vectors (the gradient of φ w.r.t. ``p``).
    """
    p, h, r = _rounded_box_args(p, half_extents, radius)
    return _rounded_box_jit(p, h, r), _rounded_box_normal(p, h, r)


class RoundedBoxSDF(AbstractSDF):
    """The analytic rounded box centred at the origin (see :func:`rounded_box_sdf`).

    Attributes:
        half: (3,) half extents, mm.   radius: () fillet radius, mm.
    """

    half: jax.Array
    radius: jax.Array

    def __call__(self, q):
        return rounded_box_sdf_and_normal(q, self.half, self.radius)

    def least_along(self, points, like, margin: float, need=None):
        return _least_in_loop(self, points, like)


def _least_in_loop(sdf, points, like):
    """:meth:`AbstractSDF.least_along` of a cheap analytic SDF, in a fori_loop over the
    fractions, which XLA:CPU compiles into one small kernel run on the calling thread; the four
    queries written side by side are one fusion heavy enough that XLA splits it across the
    cores, and on the ~600-1000 points of a step handing half to the other core cost more than
    it saved (measured side by side)."""
    fractions = jnp.asarray(PATH_CHECKS, like.dtype)

    def least(k, lo):
        return jnp.minimum(lo, sdf(points(fractions[k]))[0])

    return jax.lax.fori_loop(0, len(PATH_CHECKS), least, jnp.full_like(like, jnp.inf))


# --------------------------------------------------------------------------------------------
# Analytic rounded cylinder
# --------------------------------------------------------------------------------------------


def _rounded_cylinder_parts(p, h, r):
    """Value, outward unit normal and the half-plane gradient ``g = (∂φ/∂ρ, ∂φ/∂|z|)`` of the
    cylinder of radius ``h[0]`` and half height ``h[2]`` (axis z), edges rounded by ``r``: the
    rounded box's formula in the half-plane ``(ρ, |z|)`` with the same tie-breaking (the first
    coordinate; on the axis the radial direction is +x, on z = 0 the normal's z sign is +)."""
    rho = safe_norm(p[..., :2])
    q = jnp.stack([rho - (h[0] - r), jnp.abs(p[..., 2]) - (h[2] - r)], axis=-1)
    q_pos = jnp.maximum(q, 0.0)
    out_len = safe_norm(q_pos)
    phi = out_len + jnp.minimum(jnp.max(q, axis=-1), 0.0) - r
    outside = out_len > 0.0
    g_out = q_pos / jnp.where(outside, out_len, 1.0)[..., None]
    g_in = jax.nn.one_hot(jax.lax.argmax(q, q.ndim - 1, jnp.int32), 2, dtype=q.dtype)
    g = jnp.where(outside[..., None], g_out, g_in)
    off_axis = rho > 0.0
    radial = jnp.where(
        off_axis[..., None],
        p[..., :2] / jnp.where(off_axis, rho, 1.0)[..., None],
        jnp.array([1.0, 0.0], p.dtype),
    )
    n = jnp.concatenate([g[..., :1] * radial, g[..., 1:] * jnp.where(p[..., 2:] >= 0.0, 1.0, -1.0)], axis=-1)
    return phi, n, g


@jax.custom_jvp
def _rounded_cylinder(p, h, r):
    return _rounded_cylinder_parts(p, h, r)[0]


@_rounded_cylinder.defjvp
def _rounded_cylinder_jvp(primals, tangents):
    # As the box's: the exact one-sided gradient, a unit vector everywhere. ∂φ/∂R = −g_ρ,
    # ∂φ/∂H = −g_z, ∂φ/∂r = g_ρ + g_z − 1 (h[1] is not used).
    p, h, r = primals
    dp, dh, dr = tangents
    phi, n, g = _rounded_cylinder_parts(p, h, r)
    dphi = jnp.sum(n * dp, -1) - g[..., 0] * dh[..., 0] - g[..., 1] * dh[..., 2] + (jnp.sum(g, -1) - 1.0) * dr
    return phi, dphi


@jax.jit
def _rounded_cylinder_and_normal(p, h, r):
    return _rounded_cylinder(p, h, r), _rounded_cylinder_parts(p, h, r)[1]


class RoundedCylinderSDF(AbstractSDF):
    """The analytic cylinder about the z axis centred at the origin, its two circular edges
    rounded.

    Attributes:
        half: (3,) radius, radius, half height, mm.   radius: () fillet radius, mm
            (``0 ≤ radius ≤ min(half)``, not checked: the arguments may be traced).
    """

    half: jax.Array
    radius: jax.Array

    def __call__(self, q):
        dtype = _float_dtype(q, self.half, self.radius)
        return _rounded_cylinder_and_normal(
            jnp.asarray(q, dtype), jnp.asarray(self.half, dtype), jnp.asarray(self.radius, dtype)
        )

    def least_along(self, points, like, margin: float, need=None):
        return _least_in_loop(self, points, like)


# --------------------------------------------------------------------------------------------
# Exact triangle-mesh SDF
# --------------------------------------------------------------------------------------------

# Closest feature codes returned by `_closest_on_triangle`: index into the (F, 7, 3) table of
# pseudonormals [face, edge ab, edge bc, edge ca, vertex a, vertex b, vertex c].
_FACE, _EDGE_AB, _EDGE_BC, _EDGE_CA, _VERT_A, _VERT_B, _VERT_C = range(7)

# Point–triangle pairs evaluated at once; bounds the working memory of the brute-force search.
# XLA fuses the search into one loop that materialises only p − a, (chunk, 3, F): 6 MiB in
# float64. Measured on CPU for N = 4096, F = 5516: 7.6 MB of temporaries for φ, 19 MB for ∇φ.
_PAIRS_PER_CHUNK = 2**18


class MeshSDF(AbstractSDF):
    """Exact signed distance to a closed triangle mesh (the rigid part's surface), as a pytree.

    Built on the host in float64 (``jsnap._build.sdf.mesh_sdf_from_trimesh``); cast with
    :meth:`astype` for float32 queries. Lengths in mm.

    Attributes:
        a, b, c: triangle vertices, (F, 3) each, counter-clockwise seen from outside.
        face_normal: unit outward normal of each triangle, (F, 3).
        edge_normal: pseudonormals of the edges ab, bc, ca of each triangle, (F, 3, 3): the
            normalised sum of the normals of the two triangles sharing the edge.
        vertex_normal: angle-weighted pseudonormals of the vertices a, b, c of each triangle,
            (F, 3, 3).
        edge_perp: unit in-plane outward normals of the edges ab, bc, ca, (F, 3, 3)
            (``edge × face_normal``), for the face-region test.
        scale: length of the bounding-box diagonal, (), mm; sets the distance below which the
            normal falls back to the pseudonormal.
    """

    a: jax.Array
    b: jax.Array
    c: jax.Array
    face_normal: jax.Array
    edge_normal: jax.Array
    vertex_normal: jax.Array
    edge_perp: jax.Array
    scale: jax.Array

    def __call__(self, q):
        return mesh_sdf_and_normal(self, q)

    @property
    def num_faces(self):
        """Number of triangles F."""
        return self.a.shape[0]

    def astype(self, dtype):
        """The same SDF with every array cast to ``dtype`` (e.g. ``jnp.float32``)."""
        return jax.tree.map(lambda x: x.astype(dtype), self)


def _dot3(u, v):
    # Vectors here keep their x, y, z components on the LEADING axis, so that every product
    # below is elementwise over triangles (and points) and XLA fuses the whole search into
    # one loop; a trailing axis of size 3 defeated the fusion (measured 2x slower).
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def _triangle_terms(sdf, dtype):
    """Per-triangle constants of the closest-point test: vectors (3, F), scalars (F,)."""

    def vec(x):
        return x.astype(dtype).T

    a = vec(sdf.a)
    ab = vec(sdf.b) - a
    ac = vec(sdf.c) - a
    ab2 = _dot3(ab, ab)
    ac2 = _dot3(ac, ac)
    abac = _dot3(ab, ac)
    m_ab, m_bc, m_ca = (vec(sdf.edge_perp[:, k]) for k in range(3))

    def inv(x):  # zero-length edges: their regions are never chosen
        return jnp.where(x > 0, 1.0 / jnp.where(x > 0, x, 1.0), 0.0)

    return dict(
        a=a, ab=ab, ac=ac, n=vec(sdf.face_normal), m_ab=m_ab, m_bc=m_bc, m_ca=m_ca,
        m_bc_ab=_dot3(m_bc, ab), ab2=ab2, ac2=ac2, abac=abac,
        inv_ab2=inv(ab2), inv_ac2=inv(ac2), inv_bc2=inv(ab2 + ac2 - 2.0 * abac),
    )  # fmt: skip


def _closest_on_triangle(ap, t):
    """Closest point on triangles by Ericson's Voronoi-region test (RTCD §5.1.5).

    Broadcasts ``ap = p − a`` (3, ...) against the per-triangle terms ``t`` (vectors (3, ...),
    scalars (...)). The vertex and edge-parameter tests are Ericson's (``d1 … d6``, two dot
    products per pair, the rest from precomputed edge products). His face-region test and
    barycentrics (``va, vb, vc``, differences of products of dot products) lose all precision
    in float32 on long thin triangles such as the fillet strips of the plug mesh (measured:
    1.4e-4 mm errors); they are replaced by the equivalent tests against the precomputed unit
    in-plane edge normals (``vc ≤ 0 ⟺ m_ab · (p − a) ≥ 0``, etc.) and the face-region closest
    point by the projection onto the plane, both accurate to rounding of the coordinates.

    Returns:
        ``(diff, feature)``: ``diff = p − closest`` (3, ...) and the closest feature code
        (int32, ...): face, edge ab/bc/ca, vertex a/b/c.
    """
    ab, ac = t["ab"], t["ac"]
    d1 = _dot3(ab, ap)
    d2 = _dot3(ac, ap)
    d3 = d1 - t["ab2"]  # ab · (p − b)
    d4 = d2 - t["abac"]  # ac · (p − b)
    d5 = d1 - t["abac"]  # ab · (p − c)
    d6 = d2 - t["ac2"]  # ac · (p − c)
    out_ab = _dot3(t["m_ab"], ap) >= 0
    out_ca = _dot3(t["m_ca"], ap) >= 0
    out_bc = _dot3(t["m_bc"], ap) >= t["m_bc_ab"]
    zero = jnp.zeros_like(d1)
    one = jnp.ones_like(d1)

    # Regions from lowest to highest priority, so that the first test of Ericson's sequence
    # that succeeds wins (as with his early returns). Off the face the closest point is
    # a + v·ab + w·ac.
    v, w, f = zero, zero, jnp.full(d1.shape, _FACE, jnp.int32)

    def pick(cond, v_new, w_new, code):
        return (jnp.where(cond, v_new, v), jnp.where(cond, w_new, w), jnp.where(cond, code, f))

    t_bc = (d4 - d3) * t["inv_bc2"]
    v, w, f = pick(out_bc & (d4 >= d3) & (d5 >= d6), 1.0 - t_bc, t_bc, _EDGE_BC)
    v, w, f = pick(out_ca & (d2 >= 0) & (d6 <= 0), zero, d2 * t["inv_ac2"], _EDGE_CA)
    v, w, f = pick((d6 >= 0) & (d5 <= d6), zero, one, _VERT_C)
    v, w, f = pick(out_ab & (d1 >= 0) & (d3 <= 0), d1 * t["inv_ab2"], zero, _EDGE_AB)
    v, w, f = pick((d3 >= 0) & (d4 <= d3), one, zero, _VERT_B)
    v, w, f = pick((d1 <= 0) & (d2 <= 0), zero, zero, _VERT_A)
    # Formed from ap rather than as p − closest so that no large coordinates cancel.
    face_diff = _dot3(t["n"], ap) * t["n"]
    return jnp.where(f == _FACE, face_diff, ap - v * ab - w * ac), f


def _nearest_triangles(terms, p):
    """Index of the triangle nearest to each point of ``p`` (n, 3), brute force over all F.

    The lowest index among ties, as ``argmin``. The squared distances are materialised as an
    (n, F) array (the optimisation barrier keeps XLA from fusing them into the reductions) and
    reduced twice, to the minimum and then to the first index that attains it: measured on
    CPU for 384 points and 5516 triangles in float32, chunks of 48 points, 7.7 ms against
    23.8 ms for the fused argmin (a reduction over (value, index) pairs) of one point at a time.
    """

    def dist2(x):
        diff, _ = _closest_on_triangle(x[:, None] - terms["a"], terms)
        return _dot3(diff, diff)

    d2 = jax.lax.optimization_barrier(jax.vmap(dist2)(p))
    n = d2.shape[1]
    first = jnp.where(d2 == jnp.min(d2, axis=1, keepdims=True), jnp.arange(n, dtype=jnp.int32), n - 1)
    return jnp.min(first, axis=1)


def _mesh_eval(sdf, p, chunk):
    """φ (N,) and normal (N, 3) of points ``p`` (N, 3); differentiable given the winners."""
    dtype = p.dtype
    terms = _triangle_terms(sdf, dtype)
    n_points, n_faces = p.shape[0], sdf.num_faces
    if chunk is None:
        chunk = max(1, _PAIRS_PER_CHUNK // n_faces)
    # Equal chunks, the last padded with copies of point 0: one compiled loop body, no
    # remainder pass. A chunk of a multiple of 16 points: XLA's CPU code for the (chunk, F)
    # distances is ~5x slower for other sizes (measured, 384 points, 5516 triangles, float32:
    # 7-8 ms for chunks of 32, 48, 64 or 128 points, 35-43 ms for 40, 43, 47 or 56).
    n_chunks = max(1, -(-n_points // chunk))
    chunk = 16 * -(-n_points // (16 * n_chunks))
    # The search is discrete: keep it out of autodiff so no (N, F) tangents are ever built.
    p_search = jax.lax.stop_gradient(p)
    p_search = jnp.concatenate([p_search, jnp.broadcast_to(p_search[:1], (n_chunks * chunk - n_points, 3))])
    if n_chunks == 1:
        j = _nearest_triangles(terms, p_search)[:n_points]
    else:
        blocks = p_search.reshape(n_chunks, chunk, 3)
        j = jax.lax.map(lambda x: _nearest_triangles(terms, x), blocks).reshape(-1)[:n_points]

    # Re-solve exactly on the winning triangle: this part is differentiable in p.
    return _signed_on(sdf, terms, p, j, dtype)


@partial(jax.custom_jvp, nondiff_argnums=(2,))
def _mesh_query(sdf, p, chunk):
    return _mesh_eval(sdf, p, chunk)


@_mesh_query.defjvp
def _mesh_query_jvp(chunk, primals, tangents):
    # ∇φ = n exactly, including on the surface where |p − closest| has no derivative.
    # The normal's own tangent (for second derivatives) comes from autodiff of the
    # closest-point formulas on the winning triangle. Tangents of the mesh are ignored:
    # the SDF is not differentiable w.r.t. the triangles here.
    sdf, p = primals
    dp = tangents[1]
    (phi, n), (_, dn) = jax.jvp(lambda x: _mesh_eval(sdf, x, chunk), (p,), (dp,))
    return (phi, n), (jnp.sum(n * dp, -1), dn)


# Jitted so that eager calls compile once per shape instead of dispatching op by op.
@partial(jax.jit, static_argnums=2)
def _mesh_query_jit(sdf, p, chunk):
    return _mesh_query(sdf, p, chunk)


def _mesh_points(sdf, p):
    dtype = _float_dtype(p, sdf.a)
    p = jnp.asarray(p, dtype)
    return p.reshape(-1, 3), p.shape[:-1]


def mesh_sdf_and_normal(sdf, p, chunk=None):
    """Exact signed distance and outward normal of points w.r.t. a triangle mesh.

    Brute force over all F triangles for every point (jittable, vmappable). Points are processed
    ``chunk`` at a time with ``lax.map`` so that the working memory stays bounded (default:
    ``2**18 // F`` points per chunk, i.e. about 2**18 point–triangle pairs in flight).
    ``jax.grad`` of φ w.r.t. ``p`` equals the returned normal, also on the surface; second
    derivatives exist (the curvature of the distance field). Derivatives w.r.t. the mesh
    arrays are zero (not implemented).

    Args:
        sdf: :class:`MeshSDF`.
        p: points in the plug frame, (..., 3), mm. The computation runs in the common dtype of
            ``p`` and the ``sdf`` arrays (cast the SDF with ``sdf.astype`` for float32).
        chunk: points per chunk (static), or None for the default.

    Returns:
        ``(φ, n)``: φ (...) mm, negative inside; n (..., 3) unit normals, ``n = ∇φ``: the
        direction from the closest surface point to ``p`` (flipped inside), or the closest
        feature's pseudonormal for points on the surface.
    """
    q, shape = _mesh_points(sdf, p)
    phi, n = _mesh_query_jit(sdf, q, chunk)
    return phi.reshape(shape), n.reshape(*shape, 3)


def mesh_sdf(sdf, p, chunk=None):
    """Exact signed distance of points w.r.t. a triangle mesh, (...,) in mm.

    See :func:`mesh_sdf_and_normal` for arguments; its gradient w.r.t. ``p`` is the normal.
    """
    return mesh_sdf_and_normal(sdf, p, chunk)[0]


# --------------------------------------------------------------------------------------------
# Exact mesh SDF through per-cell candidate triangles
# --------------------------------------------------------------------------------------------

# Points whose exact distance is searched at once (a block of a scan, skipped past the last
# point that needs it): the points near the rigid part number ~30 at the median and ~120 at the
# 99th percentile of the default scene's steps, so one block serves nearly every step.
_NEAR_BLOCK = 128
# Codes of a fine cell (or of a whole coarse block) far from the surface, by side.
FAR_OUTSIDE = -1
FAR_INSIDE = -2
# Fine cells along each side of a coarse block.
BLOCK = 8


class GridMeshSDF(AbstractSDF):
    """The exact signed distance to a closed triangle mesh at every query point, each point
    tested only against the triangles that can be nearest to some point of its grid cell.

    A two-level grid covers the mesh's box grown by ``band`` and a coarse cell: coarse blocks of
    ``BLOCK``³ fine cells of side ``cell``. A fine cell whose centre lies within ``band`` plus
    its half-diagonal of the surface, on either side, holds a row of ``rows``: every triangle
    whose distance from the centre is within twice the half-diagonal of the least, which
    contains the nearest triangle of every point of the cell (``|d(p,t) − d(c,t)| ≤`` the
    half-diagonal for every triangle). Its φ and normal are then those of the brute-force
    :class:`MeshSDF`, exactly, with the same pseudonormal signs. Every other cell (and block) is
    ``FAR_OUTSIDE`` or ``FAR_INSIDE``: its points are farther than ``band`` from the surface, on
    that side, and read ``±band`` (φ is exact within ``±band``; beyond it only its side is,
    which is all a contact decision there needs) with a unit normal from the centre ``centre``.

    Built on the host by ``jsnap._build.sdf.grid_mesh_sdf``. The cost of a query is that of
    ``rows.shape[1]`` point–triangle tests per point, whatever the mesh's size, and no point is
    left out: the contact decision at every candidate is the exact distance's.

    Attributes:
        mesh: the brute-force :class:`MeshSDF` (its triangles and pseudonormals).
        origin: (3,) the grid's lowest corner, mm.   cell: () fine cell side, mm.
        dims: (3,) int32 coarse blocks along x, y, z.
        coarse: (Bx·By·Bz,) int32 a block's index into ``blocks``, or a far code.
        blocks: (nb, BLOCK³) int32 a fine cell's row of ``rows``, or a far code.
        rows: (R, K) int32 candidate triangles (a short row repeats its first entry).
        band: mm (static): φ is exact within ``±band`` of the surface.
    """

    mesh: MeshSDF
    origin: jax.Array
    cell: jax.Array
    dims: jax.Array
    coarse: jax.Array
    blocks: jax.Array
    rows: jax.Array
    band: float = eqx.field(static=True)

    def __call__(self, q):
        q, shape = _mesh_points(self.mesh, q)
        phi, n = _grid_query(self, q)
        return phi.reshape(shape), n.reshape(*shape, 3)

    def least_along(self, points, like, margin: float, need=None):
        # The four fractions' points in one query: one pass over the codes, the near points of
        # all four (of those needed) searched in the same blocks, φ signed there and only there.
        q = jax.lax.stop_gradient(jnp.concatenate([points(f) for f in PATH_CHECKS]))
        code = self.codes(q)
        if need is not None:
            code = jnp.where(jnp.tile(need, len(PATH_CHECKS)), code, FAR_OUTSIDE)
        terms = _triangle_terms(self.mesh, q.dtype)
        _, phi = _grid_winners(self, terms, q, code, signed=True)
        band = jnp.asarray(self.band, q.dtype)
        phi = jnp.where(code >= 0, phi, jnp.where(code == FAR_INSIDE, -band, band))
        return jnp.min(phi.reshape(len(PATH_CHECKS), -1), axis=0)

    @property
    def row_length(self) -> int:
        """K, the triangles tested per point."""
        return self.rows.shape[1]

    def astype(self, dtype):
        """The same SDF with every floating array cast to ``dtype``."""
        return jax.tree.map(lambda x: x.astype(dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x, self)

    def codes(self, q):
        """(P,) int32: the row of ``rows`` that serves each point of ``q`` (P, 3), or a far code."""
        dtype = q.dtype
        rel = (q - self.origin.astype(dtype)) / (BLOCK * self.cell.astype(dtype))  # in blocks
        # Floats throughout: XLA:CPU's integer division and clamps cost more than the gathers.
        dims = self.dims.astype(dtype)
        block = jnp.clip(jnp.floor(rel), 0.0, dims - 1.0)
        inside = jnp.all((rel >= 0.0) & (rel < dims), axis=-1)
        local = jnp.clip(jnp.floor(BLOCK * (rel - block)), 0.0, BLOCK - 1.0)
        at = ((block[:, 0] * dims[1] + block[:, 1]) * dims[2] + block[:, 2]).astype(jnp.int32)
        b = self.coarse.at[at].get(mode="promise_in_bounds")
        cell = ((local[:, 0] * BLOCK + local[:, 1]) * BLOCK + local[:, 2]).astype(jnp.int32)
        code = self.blocks.at[jnp.maximum(b, 0), cell].get(mode="promise_in_bounds")
        return jnp.where(inside, jnp.where(b >= 0, code, b), FAR_OUTSIDE)


def _grid_winners(sdf: GridMeshSDF, terms, p, code, signed: bool = False):
    """(N,) the nearest triangle to each point of ``p`` (N, 3) among its cell's candidates
    (``code`` (N,) its row, or a far code: then any index). Blocks of ``_NEAR_BLOCK`` points,
    the near ones first, each skipped by a ``cond`` past the last near point: a single scene
    pays for the points near the surface only (under ``vmap`` every block runs).

    With ``signed``, also the (N,) signed distance of each near point (0 at the others),
    signed in the block by :func:`_signed_on`'s pseudonormal test: no pass over all N points.
    Not differentiable."""
    n = p.shape[0]
    near = code >= 0
    size = min(n, _NEAR_BLOCK)
    n_blocks = -(-n // size)
    # The near points first, in their order (a prefix sum and a scatter: XLA:CPU's sort of a
    # few thousand keys costs more than the search it saves).
    rank = jnp.cumsum(near) - 1
    n_near = rank[-1] + 1
    slot = jnp.where(near, rank, n_near + jnp.cumsum(~near) - 1)
    order = jnp.zeros(n, jnp.int32).at[slot].set(jnp.arange(n, dtype=jnp.int32), unique_indices=True)
    k = sdf.rows.shape[1]

    def block(carry, b):
        def evaluate(carry):
            at = jax.lax.dynamic_slice_in_dim(order, jnp.minimum(b * size, n - size), size)
            cand = sdf.rows[jnp.maximum(code[at], 0)]  # (size, K)
            sel = jax.tree.map(lambda t: t[..., cand], terms)  # vectors (3, size, K), scalars (size, K)
            diff, _ = _closest_on_triangle(p[at].T[:, :, None] - sel["a"], sel)
            d2 = _dot3(diff, diff)
            first = jnp.where(d2 == jnp.min(d2, axis=1, keepdims=True), jnp.arange(k, dtype=jnp.int32), k - 1)
            win = jnp.take_along_axis(cand, jnp.min(first, axis=1)[:, None], axis=1)[:, 0]
            if not signed:
                return carry.at[at].set(win)
            phi, _ = _signed_on(sdf.mesh, terms, p[at], win, p.dtype)
            return carry[0].at[at].set(win), carry[1].at[at].set(phi)

        return jax.lax.cond(b * size < n_near, evaluate, lambda c: c, carry), None

    j = jnp.zeros(n, jnp.int32)
    out, _ = jax.lax.scan(block, (j, jnp.zeros(n, p.dtype)) if signed else j, jnp.arange(n_blocks))
    return out


def _grid_eval(sdf: GridMeshSDF, p):
    """φ (N,) and normal (N, 3) of points ``p`` (N, 3); differentiable given the winners."""
    dtype = p.dtype
    # The search is discrete: the winners, out of autodiff; the re-solve on them is not.
    p_search = jax.lax.stop_gradient(p)
    code = sdf.codes(p_search)
    near = code >= 0
    terms = _triangle_terms(sdf.mesh, dtype)
    j = _grid_winners(sdf, terms, p_search, code)
    phi, normal = _signed_on(sdf.mesh, terms, p, j, dtype)

    # Far points: their side at the band's edge, a unit normal pointing away from the centre.
    band = jnp.asarray(sdf.band, dtype)
    side = jnp.where(code == FAR_INSIDE, -1.0, 1.0).astype(dtype)
    # Any unit vector serves there (no contact is made): away from the grid's centre.
    away = p_search - (sdf.origin.astype(dtype) + 0.5 * BLOCK * sdf.cell.astype(dtype) * sdf.dims.astype(dtype))
    length = safe_norm(away, keepdims=True)
    unit = jnp.where(length > 0, away / jnp.where(length > 0, length, 1.0), jnp.array([1.0, 0.0, 0.0], dtype))
    return jnp.where(near, phi, side * band), jnp.where(near[:, None], normal, side[:, None] * unit)


def _signed_on(mesh: MeshSDF, terms, p, j, dtype):
    """Signed distance and normal of points ``p`` (N, 3) to their triangles ``j`` (N,): the
    brute-force SDF's re-solve on the winner (differentiable in ``p``)."""
    sel = jax.tree.map(lambda t: t[..., j], terms)
    diff, feature = _closest_on_triangle(p.T - sel["a"], sel)
    diff = diff.T  # (N, 3)
    pseudo = jnp.concatenate([mesh.face_normal[:, None], mesh.edge_normal, mesh.vertex_normal], axis=1).astype(
        dtype
    )[j, feature]
    # Bærentzen & Aanæs: the sign of (p − closest) · (pseudonormal of the closest feature)
    # is the inside/outside test, robust at edges and vertices.
    sign = jnp.where(jnp.sum(diff * pseudo, -1) >= 0, 1.0, -1.0).astype(dtype)
    dist = safe_norm(diff)
    # Below a few hundred ulps of the mesh size (p − closest) is rounding noise: use the
    # feature's pseudonormal, which is the one-sided limit of the normal on the surface.
    tol = 100.0 * jnp.finfo(dtype).eps * mesh.scale.astype(dtype)
    far = dist > tol
    normal = jnp.where(far[:, None], sign[:, None] * diff / jnp.where(far, dist, 1.0)[:, None], pseudo)
    return sign * dist, normal


@jax.custom_jvp
def _grid_query(sdf, p):
    return _grid_eval(sdf, p)


@_grid_query.defjvp
def _grid_query_jvp(primals, tangents):
    # As the brute-force SDF's: ∇φ = n exactly, the normal's tangent by autodiff on the winner.
    sdf, p = primals
    dp = tangents[1]
    (phi, n), (_, dn) = jax.jvp(lambda x: _grid_eval(sdf, x), (p,), (dp,))
    return (phi, n), (jnp.sum(n * dp, -1), dn)


# --------------------------------------------------------------------------------------------
# Neural SDF (evaluation; training lives in jsnap._build.neural_sdf)
# --------------------------------------------------------------------------------------------


def activation(name: str, beta: float):
    """The hidden layers' activation: ``softplus`` (with sharpness ``beta``), ``silu``,
    ``gelu`` or ``tanh``."""
    if name == "softplus":
        return lambda x: jax.nn.softplus(beta * x) / beta
    return {"silu": jax.nn.silu, "gelu": jax.nn.gelu, "tanh": jnp.tanh}[name]


class NeuralSDF(AbstractSDF):
    """A trained neural SDF: weights and normalisation are array leaves.

    φ(p) = MLP((clip(p) − center) / half) · out_scale + |p − clip(p)|, with ``clip`` onto the
    training box; normals are the normalised ``jax.grad`` of φ.

    Attributes:
        params: the MLP's layers, ``{"hidden_0": {"kernel", "bias"}, …, "out": {…}}`` (Flax's
            layout: the training code's parameter tree, used here as plain arrays).
        center: (3,) centre of the training domain, mm.
        half: (3,) half extents of the training domain (the input normalisation), mm.
        out_scale: () mm per unit of network output.
        width, depth, activation, softplus_beta: architecture (static).
    """

    params: dict
    center: jax.Array
    half: jax.Array
    out_scale: jax.Array
    width: int = eqx.field(static=True)
    depth: int = eqx.field(static=True)
    activation: str = eqx.field(static=True)
    softplus_beta: float = eqx.field(static=True)

    def __call__(self, q):
        return neural_sdf_and_normal(self, q)

    def network(self, x):
        """The MLP on normalised inputs x (N, 3) -> (N,)."""
        act = activation(self.activation, self.softplus_beta)
        for i in range(self.depth):
            layer = self.params[f"hidden_{i}"]
            x = act(x @ layer["kernel"] + layer["bias"])
        out = self.params["out"]
        return (x @ out["kernel"] + out["bias"])[..., 0]

    def astype(self, dtype):
        """The same SDF with every array cast to ``dtype``."""
        return jax.tree.map(lambda x: x.astype(dtype), self)


def _neural_phi(net: NeuralSDF, p):
    """φ (N,) of points p (N, 3); outside the domain, distance to it plus φ at the clamp."""
    lo = net.center - net.half
    hi = net.center + net.half
    q = jnp.clip(p, lo, hi)
    return net.network((q - net.center) / net.half) * net.out_scale + safe_norm(p - q)


def _neural_phi_and_normal(net: NeuralSDF, p):
    phi, vjp = jax.vjp(lambda x: _neural_phi(net, x), p)
    (g,) = vjp(jnp.ones_like(phi))
    norm = safe_norm(g, keepdims=True)
    # A zero gradient (measure zero for a trained net) gets the first axis, as the analytic
    # SDF's tie-breaking does: a unit normal everywhere keeps contact frames finite.
    fallback = jnp.zeros_like(g).at[:, 0].set(1.0)
    n = jnp.where(norm > 0, g / jnp.where(norm > 0, norm, 1.0), fallback)
    return phi, n


# Jitted so that eager calls compile once per shape instead of dispatching op by op.
_neural_phi_jit = jax.jit(_neural_phi)
_neural_phi_and_normal_jit = jax.jit(_neural_phi_and_normal)


def _neural_points(net: NeuralSDF, p):
    arrays = [x for x in (p, net.center) if isinstance(x, jax.Array | np.ndarray)]
    dtype = jnp.result_type(*arrays)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = net.center.dtype
    p = jnp.asarray(p, dtype)
    if p.shape[-1:] != (3,):
        raise ValueError(f"points must have shape (..., 3), got {p.shape}")
    return p.reshape(-1, 3), p.shape[:-1]


def neural_sdf(net: NeuralSDF, p):
    """Signed distance (...) in mm of points ``p`` (..., 3) by the network (computed in the
    common dtype of ``p`` and the weights)."""
    q, shape = _neural_points(net, p)
    return _neural_phi_jit(net, q).reshape(shape)


def neural_sdf_and_normal(net: NeuralSDF, p):
    """Signed distance (...) mm and outward unit normal ``∇φ / |∇φ|`` (..., 3) of points
    ``p`` (..., 3) by the network. Pure JAX: jit, vmap and grad (w.r.t. ``p`` and ``net``)."""
    q, shape = _neural_points(net, p)
    phi, n = _neural_phi_and_normal_jit(net, q)
    return phi.reshape(shape), n.reshape(*shape, 3)


# --------------------------------------------------------------------------------------------
# Costly SDFs where the contact needs them
# --------------------------------------------------------------------------------------------

# Points at which the costly SDF is evaluated per query, at most (the nearest by the bound).
_NEAR_POINTS = 384


class BoundedSDF(AbstractSDF):
    """A costly SDF ``exact`` (a triangle mesh's, a network's) evaluated where the contact
    needs it, and a cheap lower bound ``bound`` elsewhere.

    ``bound`` must lie below ``exact`` everywhere, up to ``slack``: a mesh inscribed in the
    analytic rounded box it was tessellated from (slack: the float32 rounding of its vertices),
    a network trained on a mesh inside its bounding box (slack: the network's own error). A point
    whose bound is at least the margin plus ``slack`` is no contact candidate whatever its exact
    distance, and keeps the bound; ``exact`` is evaluated at the points with the lowest bounds, in
    blocks of ``_NEAR_BLOCK``: as many blocks as the points below the margin plus ``slack`` need
    (one on most steps), up to ``_NEAR_POINTS`` points. Every contact decision (candidates,
    predict-correct) is then the one the exact distance at every point would give, as long as at
    most ``_NEAR_POINTS`` points lie within the margin. The blocks are a scan over one compiled
    copy of the search (each skipped by a ``cond`` when not needed; under ``vmap`` every block
    is evaluated).

    Attributes:
        exact: the costly SDF.   bound: a rounded box below it.   slack: mm (static).
    """

    exact: AbstractSDF
    bound: RoundedBoxSDF
    slack: float = eqx.field(static=True)

    def __call__(self, q):
        return self.exact(q)

    def scene_query(self, q, margin: float):
        n = q.shape[0]
        if n <= _NEAR_BLOCK:
            return self.exact(q)
        lower, lower_normal = self.bound(q)
        n_blocks = -(-min(n, _NEAR_POINTS) // _NEAR_BLOCK)
        # Lowest bounds first; with fewer points than the blocks hold, the last block overlaps the
        # one before (dynamic_slice keeps it in range), evaluating some points twice.
        _, order = jax.lax.top_k(-lower, min(n, n_blocks * _NEAR_BLOCK))
        n_near = jnp.sum(lower < margin + self.slack)

        def block(carry, k):
            def evaluate(c):
                near = jax.lax.dynamic_slice_in_dim(order, k * _NEAR_BLOCK, _NEAR_BLOCK)
                phi, normal = self.exact(q[near])
                return c[0].at[near].set(phi), c[1].at[near].set(normal)

            # Block 0 always; a later one only when the points below the margin reach into it.
            return jax.lax.cond(k * _NEAR_BLOCK < jnp.maximum(n_near, 1), evaluate, lambda c: c, carry), None

        (phi, normal), _ = jax.lax.scan(block, (lower, lower_normal), jnp.arange(n_blocks))
        return phi, normal
