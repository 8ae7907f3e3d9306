"""Segmentation and passive balanced model reduction of the socket (the paper's Models 3 and 4).

**Segmentation** (``solver.method = "segmented"``). The elements that own the faces of the
contact candidate points and of their normal stencils (``jsnap._build.model``), grown by
``solver.segment_margin`` mm, form the *contact segment*; the other elements form
``solver.segments`` non-contact segments (cut by graph distance from the contact segment).
Every segment has its own copy of the nodes it shares with another. In the segmented model
(the paper's Model 3) the copies are joined by PMI spring-dampers ``(k_c, b_c)``
(``solver.interface_stiffness``, ``interface_damping``):

    M = diag(M_i),   K = diag(K_i) + k_c G,   D = diag(D_i) + b_c G,   G = Dg' Dg,

with ``Dg`` the difference operator of the joined copies. It is passive for any ``k_c, b_c >= 0``
and tends to the full model as ``k_c`` grows. The coupling is eliminated analytically once per
parameter set: with dense operators it is part of ``S^-1`` (a Schur complement in all but
name, see :meth:`jsnap._core.parts.SegmentedPart.prepare`).

**Balanced reduction** (``solver.method = "reduced"``, the paper's Model 4). The part's
displacement is ``x = V z`` (a one-sided congruence), so ``M_r = V'MV``, ``K_r = V'KV``,
``D_r = V'DV`` stay symmetric positive (semi)definite and PMI applies unchanged: the reduced
model is passive by construction, for every parameter set. Two-sided (Petrov-Galerkin) balanced
truncation is not used: it breaks the symmetry that passivity rests on. ``V`` is a Craig-Bampton
basis whose interior parts are balanced. The segments share their interface coordinates (the
amplitudes of the interface shapes below), so the copies of a shared node move together for
every ``z``: the segments are joined exactly, with no springs (stiff penalty springs make the
float32 rollout of a fine mesh gain energy and blow up). The *contact load cases* are unit
forces along the surface normal at every candidate point (both sides' normals at an edge), or,
with the scene key ``solver.load_patch`` > 0, each spread over the candidate points around
it by a Gaussian of that standard deviation (:func:`_patch_weights`); ``tol =
solver.hsv_tolerance``.

* *Interface shapes*: the six rigid motions of the interface nodes, then the interface traces of
  the full model's static responses to the load cases, added greedily until restricting the
  interface to them loses at most ``tol/2`` of every case's static compliance (measured in the
  norm of the interface's condensed stiffness, :func:`interface_shapes`). Every segment gets the
  same shapes on its copy of the interface, extended statically into its interior (constraint
  modes), so the interface traces of all segments span the same space: stiff coupling does not
  lock.
* *Interior* (interface held): inside a subspace that a sparse solver affords (the lowest
  fixed-interface modes by shift-invert Lanczos, plus the static responses to the segment's
  inputs: contact forces at the candidate points on the contact segment, the inertia loads of
  the interface shapes on the others), the position Gramians of ``M q'' + D q' + K q = B u,
  y = B' q`` are computed exactly for a nominal modal damping (:data:`GRAMIAN_DAMPING`),
  balanced, and truncated where the Hankel singular values fall below ``tol`` times a
  reference: the segment's own largest, but for the contact segment the whole part's (the
  full model's largest static gain from the contact loads, :func:`_hankel_reference`), since
  its own largest depends on where the segment's interface falls in the mesh.
* *Static correction* (contact segment): the static responses to the load cases that the
  truncation lost are put back, greedily, until every case keeps its static compliance to
  ``tol/2`` of the full model's. Quasi-static insertion forces are set by that compliance.
* *Joining* (:func:`join_bases`): the interface amplitudes and every segment's interior
  coordinates, changed to the reduced model's own modes at the nominal material (mass
  identity, stiffness diagonal), which keeps float32 products free of cancellation between
  stiff and soft coordinates.

Together: the normal compliance at every candidate point is within ``tol`` of the full model's,
which tests/test_reduce.py checks.

Cost. The segments' interiors are reduced at once, a thread each (SuperLU's factorisations and
solves run without Python's lock), when the memory their factors and subspaces are estimated to
need fits together; the condensations onto the contact and interface dofs run one after the
other, since each is the build's largest allocation.

``V`` is computed once at the scene's material and held fixed: the stored blocks are
parameter-free (``V'K_lam V``, ``V'K_mu V``, ``V'M1 V``, base-reaction rows), so E, nu,
rho, alpha, beta stay exact and differentiable without rebuilding the basis. Reduced models are
cached on disk under a hash of everything they depend on (:func:`load_or_build`). The full
displacement is reconstructed only when asked (``free_displacement``); the base wrench is a
reduced linear output.

Units: mm, N, MPa, s, tonne.
"""

from __future__ import annotations

import itertools
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import skfem
from scipy.spatial import cKDTree
from threadpoolctl import threadpool_limits

from jsnap._build.cache import ArtefactError, KeyHash, cached
from jsnap._build.fem import _ELEMENTS, Assembly, _k_lam, _k_mu, _m1, wrench_rows
from jsnap._build.linalg import factor, factor_bytes, node_ordering, schur_complement
from jsnap._build.memory import MEMORY_SHARE, available_memory, require
from jsnap._core.params import lame
from jsnap._core.parts import ReducedPart, SegmentedPart

__all__ = ["GRAMIAN_DAMPING", "Segmentation", "build_part", "cache_key", "load_or_build", "segment"]

# Modal damping ratio under which the position Gramians are computed. The socket may have no
# damping at all (the default scene), and the Gramians of an undamped system do not exist. For
# well-separated modes the position Hankel singular values are |b_k|^2 / (4 zeta omega_k^2): all
# scale by 1/zeta alike, so the truncation (relative to the largest) barely depends on it.
GRAMIAN_DAMPING = 0.05
# How the reduced segments are joined; part of the cache key (files made with springs between
# the segments' copies hold other arrays).
_JOINT = "shared interface coordinates"
# What the contact segment's Hankel singular values are measured against (part of the cache key).
_TRUNCATION = "the whole part's static gain"
# The settings that shrink the reduction's arrays, named when one would not fit in memory.
_MESH_HINT = "a larger solver.mesh_size"
# Those of the arrays that grow with the contact nodes and load cases.
_CONTACT_HINT = "a larger solver.mesh_size (fewer contact nodes) or a larger contact.spacing (fewer load cases)"


# --------------------------------------------------------------------------------------------
# Segmentation (host)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Segmentation:
    """A socket mesh cut into segments whose shared nodes are duplicated.

    Attributes:
        element_segment: (m,) segment of each element; 0 is the contact segment.
        nodes: per segment, the sorted global node ids (``Assembly.nodes`` numbering) of its
            unclamped nodes; the segment's local dofs are ``3 * local_node + component``.
        pairs: (p, 4) joined copies ``(segment_a, local_node_a, segment_b, local_node_b)``:
            one spring-damper per pair and component.
    """

    element_segment: np.ndarray
    nodes: tuple[np.ndarray, ...]
    pairs: np.ndarray

    @property
    def n_segments(self) -> int:
        return len(self.nodes)

    def interface_nodes(self, i: int) -> np.ndarray:
        """(k,) sorted local node indices of segment ``i`` that are joined to another segment."""
        p = self.pairs
        return np.unique(np.concatenate([p[p[:, 0] == i, 1], p[p[:, 2] == i, 3]]))


def _face_owners(asm: Assembly, faces: np.ndarray) -> np.ndarray:
    """(f,) element owning each boundary face (f, 3) (vertex ids)."""
    from jsnap._geometry.mesh import TET_FACES as _TET_FACES

    cells = asm.mesh.cells
    all_faces = np.sort(cells[:, _TET_FACES].reshape(-1, 3), axis=1)
    lookup = {tuple(f): i // 4 for i, f in enumerate(all_faces)}
    try:
        return np.array([lookup[tuple(f)] for f in np.sort(faces, axis=1)], dtype=np.int64)
    except KeyError:
        raise ValueError("segment: a seed face is not a face of the mesh") from None


def segment(asm: Assembly, seed_faces: np.ndarray, margin: float, n_rest: int = 1) -> Segmentation:
    """Cut the mesh into a contact segment and ``n_rest`` non-contact segments.

    Args:
        asm: the assembled socket.
        seed_faces: (f, 3) vertex ids of the boundary faces the plug can touch (the faces of the
            contact candidate points and of their normal stencils).
        margin: elements whose centroid lies within ``margin`` (mm) of a node of an element
            owning a seed face join the contact segment, as does every element touching a seed
            face (so that no contact node lies on an interface).
        n_rest: number of non-contact segments; the elements outside the contact segment are
            cut into this many pieces of about equal size by their graph distance (elements
            sharing a vertex) from the contact segment, so each piece touches the previous one.

    Raises:
        ValueError: no seed face, nothing left outside the contact segment, or more segments
            asked for than elements are left.
    """
    from scipy.spatial import cKDTree

    mesh = asm.mesh
    cells = mesh.cells
    if len(seed_faces) == 0:
        raise ValueError("segment: no seed face (the plug never comes near the socket)")
    seed_faces = np.asarray(seed_faces)
    seed = np.unique(_face_owners(asm, seed_faces))
    centroids = mesh.points[cells].mean(axis=1)
    near = cKDTree(mesh.points[np.unique(cells[seed])]).query(centroids)[0] <= margin
    contact = np.zeros(len(cells), dtype=bool)
    contact[seed] = True
    contact |= near
    # Every element touching a seed face joins too, so no contact node lies on an interface.
    contact |= np.isin(cells, seed_faces).any(axis=1)
    rest = np.flatnonzero(~contact)
    if rest.size == 0:
        raise ValueError(
            f"solver.segment_margin = {margin!r}: the contact segment holds the whole socket, "
            "there is nothing to segment (use a smaller margin or solver.method = 'full')"
        )
    if n_rest > rest.size:
        raise ValueError(
            f"solver.segments = {n_rest}: only {rest.size} elements lie outside the contact segment"
        )
    label = np.zeros(len(cells), dtype=np.int64)
    if n_rest > 1:
        # Breadth-first levels over vertex-sharing elements, from the contact segment.
        n_vert = mesh.points.shape[0]
        inc = sp.csr_matrix(
            (np.ones(cells.size), (np.repeat(np.arange(len(cells)), 4), cells.ravel())),
            shape=(len(cells), n_vert),
        )
        adj = (inc @ inc.T).tocsr()
        level = np.full(len(cells), -1)
        frontier = np.flatnonzero(contact)
        level[frontier] = 0
        d = 0
        while frontier.size:
            d += 1
            nxt = np.unique(adj[frontier].indices)
            nxt = nxt[level[nxt] < 0]
            level[nxt] = d
            frontier = nxt
        if np.any(level[rest] < 0):
            raise ValueError("segment: the mesh is not connected")
        order = rest[np.argsort(level[rest], kind="stable")]
        for k, chunk in enumerate(np.array_split(order, n_rest)):
            label[chunk] = k + 1
    else:
        label[rest] = 1
    clamped = np.zeros(asm.nodes.shape[0], dtype=bool)
    clamped[asm.fixed[0::3] // 3] = True
    nodes = []
    for i in range(n_rest + 1):
        ids = np.unique(asm.cells[label == i])
        nodes.append(ids[~clamped[ids]])
    # Copies of one node in segments s1 < s2 < ... are joined in a chain s1-s2, s2-s3, ...
    owners: dict[int, list[tuple[int, int]]] = {}
    for i, ids in enumerate(nodes):
        for local, g in enumerate(ids):
            owners.setdefault(int(g), []).append((i, local))
    pairs = [(*a, *b) for copies in owners.values() for a, b in itertools.pairwise(copies)]
    return Segmentation(label, tuple(nodes), np.array(pairs, dtype=np.int64).reshape(-1, 4))


def _dofs(nodes: np.ndarray) -> np.ndarray:
    return (3 * np.asarray(nodes)[:, None] + np.arange(3)).ravel()


def _own_sliding(asm: Assembly, seg: Segmentation, i: int) -> sp.csr_matrix:
    """Segment ``i``'s part of the sliding planes' springs (nodal, see fem.sliding_penalty): a
    node's go to the first segment that has a copy of it, so the segments' sum is the part's."""
    first = np.full(asm.nodes.shape[0], len(seg.nodes))
    for j in range(len(seg.nodes) - 1, -1, -1):
        first[seg.nodes[j]] = j
    return (sp.diags(np.repeat(first == i, 3).astype(np.float64)) @ asm.sliding).tocsr()


def segment_blocks(asm: Assembly, seg: Segmentation, i: int):
    """Parameter-free blocks of segment ``i`` from its own elements only.

    They are the part's blocks on the segment's dofs less what the other segments' elements add
    at the nodes it shares with them: only those elements that touch the segment's nodes (a
    layer along the interface) are assembled, not the segment's own.

    Returns ``(blocks, reaction)``: ``blocks`` the (n_i, n_i) CSR matrices ``K_lam, K_mu, M1`` on
    the segment's local dofs, ``reaction`` the (n_fixed, n_i) rows of the same matrices at the
    clamped base dofs (``asm.fixed``), for the base wrench.
    """
    mine = np.zeros(asm.nodes.shape[0], dtype=bool)
    mine[seg.nodes[i]] = True
    layer = np.flatnonzero((seg.element_segment != i) & mine[asm.cells].any(axis=1))
    basis = None
    if layer.size:
        basis = skfem.Basis(asm.basis.mesh, skfem.ElementVector(_ELEMENTS[asm.element]()), elements=layer)
    dofs = _dofs(seg.nodes[i])
    out, react = [], []
    for form, whole in ((_k_lam, asm.K_lam), (_k_mu, asm.K_mu), (_m1, asm.M1)):
        A = whole.tocsr()
        if basis is not None:
            A = A - form.assemble(basis)
        if form is _k_mu and asm.sliding.nnz:  # the part's K_mu holds every segment's springs
            A = A - asm.sliding + _own_sliding(asm, seg, i)
        out.append(A[dofs][:, dofs].tocsr())
        react.append(A[asm.fixed][:, dofs].tocsr())
    return out, react


# --------------------------------------------------------------------------------------------
# Balanced reduction (host, float64)
# --------------------------------------------------------------------------------------------


def _orthonormalizer(G: np.ndarray, rtol: float = 1e-10) -> np.ndarray:
    """T (k, j) with ``T' G T = I`` for a Gram matrix G (k, k) of k vectors, rank-revealing:
    directions with an eigenvalue below ``rtol`` times the largest are dropped."""
    lam, Q = np.linalg.eigh(0.5 * (G + G.T))
    keep = lam > rtol * lam.max()
    T = Q[:, keep] / np.sqrt(lam[keep])
    # One more pass (Cholesky-QR style) removes the round-off of the first.
    G2 = T.T @ G @ T
    L = np.linalg.cholesky(0.5 * (G2 + G2.T))
    return sla.solve_triangular(L, T.T, lower=True).T


def _m_orthonormal(U: np.ndarray, M, rtol: float = 1e-10) -> np.ndarray:
    """A basis of range(U) (n, k) orthonormal in the M inner product, rank-revealing."""
    if U.shape[1] == 0:
        return U
    scale = np.linalg.norm(U, axis=0)
    U = U[:, scale > 0] / scale[scale > 0]
    return U @ _orthonormalizer(U.T @ (M @ U), rtol)


def position_gramians(omega: np.ndarray, b: np.ndarray, zeta: float = GRAMIAN_DAMPING):
    """Position Gramians of ``q'' + 2 zeta Omega q' + Omega^2 q = b u``, ``y = b' q`` (modal form).

    Exact solutions of the first-order Lyapunov equations of the state ``(q, q')``, through the
    closed-form eigenvectors ``(1, lambda)`` of each mode's 2x2 block; the position Gramians are
    their ``q``-blocks.

    Args:
        omega: (s,) angular frequencies > 0, rad/s.
        b: (s, m) modal input matrix (the output matrix is its transpose).
        zeta: modal damping ratio in (0, 1).

    Returns:
        ``(P_p, Q_p)``, (s, s) symmetric positive semidefinite.
    """
    w = np.asarray(omega, dtype=np.float64)
    root = np.sqrt(1.0 - zeta**2)
    lam = np.stack([w * (-zeta + 1j * root), w * (-zeta - 1j * root)], axis=1)  # (s, 2): slots +, -
    d = lam[:, 1] - lam[:, 0]  # (s,)
    bb = b @ b.T
    sgn = np.array([-1.0, 1.0])
    # Controllability: slot a of mode j has input row sgn_a b_j / d_j.
    denom = lam[:, None, :, None] + np.conj(lam)[None, :, None, :]  # (j, k, a, c)
    wc = (sgn[:, None] * sgn[None, :])[None, None] / (d[:, None, None, None] * np.conj(d)[None, :, None, None])
    Ip = -np.sum(wc / denom, axis=(2, 3)).real
    # Observability: the output sees slot a of mode j with weight b_j; the position
    # coordinate q_j is recovered from the slots with g = (lam_-, -lam_+) / d.
    g = np.stack([lam[:, 1] / d, -lam[:, 0] / d], axis=1)  # (s, 2)
    denom_o = np.conj(lam)[:, None, :, None] + lam[None, :, None, :]
    Iq = -np.sum(np.conj(g)[:, None, :, None] * g[None, :, None, :] / denom_o, axis=(2, 3)).real
    P = bb * Ip
    Q = bb * Iq
    return 0.5 * (P + P.T), 0.5 * (Q + Q.T)


def _psd_factor(A: np.ndarray) -> np.ndarray:
    """R with R R' = A for a symmetric positive semidefinite A (negative round-off clipped)."""
    lam, Q = np.linalg.eigh(A)
    keep = lam > lam.max() * 1e-15
    return Q[:, keep] * np.sqrt(lam[keep])


def _hankel_reference(gain: float, zeta: float = GRAMIAN_DAMPING) -> float:
    """The position Hankel singular value of a lone mode whose static gain is ``gain``:
    ``gain sqrt(1 + 4 zeta^2) / (4 zeta)`` (:func:`position_gramians` for one mode)."""
    return gain * np.sqrt(1.0 + 4.0 * zeta**2) / (4.0 * zeta)


def balance(K: np.ndarray, B: np.ndarray, tol: float, zeta: float = GRAMIAN_DAMPING, ref: float | None = None):
    """Second-order position-balanced truncation of ``q'' + D q' + K q = B u``, ``y = B' q``,
    in coordinates where the mass is the identity (``D`` the modal damping ``zeta``).

    Args:
        K: (s, s) symmetric positive definite stiffness, 1/s^2.
        B: (s, m) inputs.
        tol: keep the states whose Hankel singular value exceeds ``tol`` times the reference.
        ref: the reference Hankel singular value, or None for the largest of this system. The
            contact segment's interior is measured against the whole part's: its own largest
            depends on where the segment's interface falls in the mesh.

    Returns:
        ``(Y, hsv)``: Y (s, r) the leading right balancing vectors (the basis to project on),
        hsv (min(s, m...),) all position Hankel singular values, descending.
    """
    w2, Phi = np.linalg.eigh(0.5 * (K + K.T))
    if w2[0] <= 0:
        raise ValueError("balance: the stiffness is not positive definite (a floating segment?)")
    b = Phi.T @ B
    P, Q = position_gramians(np.sqrt(w2), b, zeta)
    R, L = _psd_factor(P), _psd_factor(Q)
    _U, hsv, Wt = np.linalg.svd(L.T @ R, full_matrices=False)
    r = int(np.sum(hsv > tol * max(hsv[0], ref or 0.0)))
    T = R @ (Wt[:r].T / np.sqrt(hsv[:r]))
    return Phi @ T, hsv


def _rigid_shapes(points: np.ndarray) -> np.ndarray:
    """(3k, 6) translations and small rotations (about the centroid) of k points (k, 3), node-major."""
    c = points - points.mean(axis=0)
    out = np.zeros((points.shape[0], 3, 6))
    for a in range(3):
        out[:, a, a] = 1.0
    for a in range(3):  # rotation about axis a: e_a x c
        e = np.zeros(3)
        e[a] = 1.0
        out[:, :, 3 + a] = np.cross(e, c)
    return out.reshape(-1, 6)


def _contact_interp(nodes: np.ndarray, weights: np.ndarray):
    """The candidate points as a dense interpolation: contact node ids (c,) and ``Jn`` (P, c),
    the point's displacement (per component) from the nodes'. Zero weights are dropped."""
    used = weights != 0
    cnodes = np.unique(nodes[used])
    Jn = np.zeros((nodes.shape[0], cnodes.size))
    rows = np.repeat(np.arange(nodes.shape[0]), nodes.shape[1]).reshape(nodes.shape)
    np.add.at(Jn, (rows[used], np.searchsorted(cnodes, nodes[used])), weights[used])
    return cnodes, Jn


def _kron3(A: np.ndarray) -> np.ndarray:
    """(3m, 3n) node-major ``kron(A, I_3)`` of A (m, n): the same map on every component."""
    return np.kron(A, np.eye(3))


def _load_factor(Jn: np.ndarray) -> np.ndarray:
    """Factor F (c, q) with ``F F' = Jn'Jn``: white-noise forces at the candidate points load the
    nodes with covariance ``kron(Jn'Jn, I_3)`` (sampled surface tractions). Null directions
    dropped."""
    lam, Q = np.linalg.eigh(Jn.T @ Jn)
    keep = lam > 1e-12 * lam.max()
    return Q[:, keep] * np.sqrt(lam[keep])


def _factor(K, ordering=None, what: str = "a segment's interior"):
    """Sparse factorisation of a symmetric positive definite node-major matrix (a fill-reducing
    ordering of its nodes, diagonal pivots: :func:`jsnap._build.linalg.factor`), its memory
    checked before it is made; ``ordering``: ``node_ordering(K)``, if made already."""
    return factor(K, what, _MESH_HINT, ordering=ordering)


def _unit_responses(lu, n: int, at: np.ndarray, chunk: int = 256) -> np.ndarray:
    """(n, len(at)) responses ``K^-1 e_j`` to a unit load at each dof ``at`` (``lu`` K's factor),
    solved a chunk of loads at a time: no dense (n, len(at)) load matrix besides the result."""
    X = np.empty((n, at.size))
    for j in range(0, at.size, chunk):
        cols = np.arange(min(chunk, at.size - j))
        E = np.zeros((n, cols.size))
        E[at[j + cols], cols] = 1.0
        X[:, j + cols] = lu.solve(E)
    return X


def _lowest_modes(K, M, lu, k: int):
    """(n, k) lowest eigenvectors of (K, M), by shift-invert Lanczos (dense when small)."""
    n = K.shape[0]
    k = min(k, n - 2)
    if k <= 0:
        return np.zeros((n, 0))
    if n <= 3 * k + 20:  # too small for Lanczos
        _, vec = sla.eigh(K.toarray(), M.toarray(), subset_by_index=(0, k - 1))
        return vec
    op = spla.LinearOperator((n, n), matvec=lu.solve, dtype=np.float64)
    # A fixed start vector: ARPACK's default is random, and the same scene must give the same
    # basis (reproducible caches and results).
    v0 = np.cos(np.arange(n) + 0.5)
    _, vec = spla.eigsh(K, k=k, M=M, sigma=0.0, which="LM", OPinv=op, tol=1e-10, v0=v0)
    return vec


def _greedy_energy(
    X: np.ndarray, S: np.ndarray, Q0: np.ndarray, ref: np.ndarray, tol: float, SX: np.ndarray | None = None
) -> np.ndarray:
    """Greedy energy-norm span: vectors to add to Q0 so that every column x_j of X is represented
    to ``|x_j - P x_j|_S^2 <= tol ref_j`` (P the S-orthogonal projection onto the span).

    For static responses ``x_j = K^-1 l_j`` in the ``S = K`` norm, ``|x_j - P x_j|^2`` is exactly
    the static compliance ``l_j'K^-1 l_j`` that a Galerkin model on the span loses (it can only
    be too stiff). At each step the worst column's residual is added.

    Args:
        X: (m, n) candidate vectors.   S: (m, m) symmetric positive definite.
        Q0: (m, k) vectors already in the basis.   ref: (n,) > 0 reference per column.
        SX: ``S @ X`` when the caller has it for less than the product costs, or None.

    Returns:
        (m, a) the added vectors, S-orthonormal and S-orthogonal to Q0.
    """
    if Q0.shape[1]:
        G = Q0.T @ S @ Q0
        Q = Q0 @ np.linalg.inv(np.linalg.cholesky(0.5 * (G + G.T))).T  # S-orthonormal
    else:
        Q = Q0
    SX = S @ X if SX is None else SX
    A = Q.T @ SX
    lost = np.einsum("mn,mn->n", X, SX) - np.einsum("kn,kn->n", A, A)
    added = []
    while Q.shape[1] < X.shape[0]:
        j = int(np.argmax(lost / ref))
        if lost[j] <= tol * ref[j]:
            break
        q = X[:, j] - Q @ A[:, j]
        q -= Q @ (Q.T @ (S @ q))  # re-orthogonalise (round-off)
        q /= np.sqrt(q @ S @ q)
        a = q @ SX
        Q = np.concatenate([Q, q[:, None]], axis=1)
        A = np.concatenate([A, a[None]], axis=0)
        lost = lost - a * a
        added.append(q)
    return np.stack(added, axis=1) if added else np.zeros((X.shape[0], 0))


def _normal_loads(
    Jn: np.ndarray, normals: np.ndarray, points: np.ndarray | None = None, patch: float = 0.0
) -> np.ndarray:
    """(3c, Q) nodal loads of a unit force along each candidate point's surface normal(s), or,
    with ``patch > 0``, of a unit force spread over the points around it (:func:`_patch_weights`).

    Args:
        Jn: (P, c) interpolation of the points from the contact nodes.
        normals: (P, m, 3) normals per point (m = 2: its side's and, at an edge, the other
            side's); repeated normals add nothing and are dropped.
        points: (P, 3) the points' rest positions, mm (needed with ``patch``).
        patch: the patch's standard deviation, mm (``solver.load_patch``); 0: each point alone.
    """
    P, m = normals.shape[:2]
    L = np.einsum("pa,pjd->adpj", Jn, normals).reshape(3 * Jn.shape[1], P * m)
    distinct = np.ones((P, m), dtype=bool)
    for j in range(1, m):
        distinct[:, j] = np.linalg.norm(normals[:, j] - normals[:, 0], axis=1) > 1e-9
    L = L[:, distinct.ravel()]
    if patch > 0:
        at = np.repeat(np.asarray(points, dtype=np.float64)[:, None], m, axis=1)[distinct]
        L = np.asarray((_patch_weights(at, normals[distinct], patch).T @ L.T).T)
    return L


# Load cases on faces whose normals differ by more than this angle (cosine) are not mixed by a
# patch: the two sides of an edge of 90 degrees or sharper stay apart.
_PATCH_SAME_SIDE = 0.5
# The patch's Gaussian is cut at this many standard deviations.
_PATCH_CUT = 4.0
# What a patch is (part of the cache key of the models reduced at patch loads).
_PATCH = f"Gaussian over the candidate points, cut at {_PATCH_CUT:g} sd, sides within cos {_PATCH_SAME_SIDE:g}"


def _patch_weights(at: np.ndarray, normals: np.ndarray, patch: float) -> sp.csc_matrix:
    """(Q, Q) sparse weights: column j spreads load case j (a unit normal force at ``at[j]``)
    over the cases within ``_PATCH_CUT`` standard deviations ``patch`` of it on the same side
    (normals within 60 degrees), Gaussian in the distance, summing to 1 (a unit total)."""
    tree = cKDTree(at)
    D = tree.sparse_distance_matrix(tree, _PATCH_CUT * patch, output_type="coo_matrix")
    i, j = D.row, D.col
    keep = (np.einsum("qd,qd->q", normals[i], normals[j]) > _PATCH_SAME_SIDE) & (i != j)
    i, j, d = i[keep], j[keep], D.data[keep]
    # Every case's own weight (1) added once, here: the distance matrix holds each case's zero
    # distance to itself (cKDTree stores it explicitly), which would count it twice.
    n = at.shape[0]
    i, j = np.concatenate([i, np.arange(n)]), np.concatenate([j, np.arange(n)])
    w = np.concatenate([np.exp(-0.5 * (d / patch) ** 2), np.ones(n)])
    W = sp.csc_matrix((w, (i, j)), shape=(n, n))
    return W @ sp.diags(1.0 / np.asarray(W.sum(axis=0)).ravel())


def _each_segment(work, need: list[int]) -> list:
    """``[work(i) for i in range(len(need))]``, the segments on a thread per core when their
    memory needs (bytes, ``need[i]`` for segment i) fit together: the sparse factorisations and
    solves (SuperLU) run without Python's lock, and the segments are independent."""
    n = len(need)
    workers = min(n, os.cpu_count() or 1)
    if workers < 2 or sum(need) > MEMORY_SHARE * available_memory():
        return [work(i) for i in range(n)]
    # One BLAS thread each: the workers already fill the cores.
    with threadpool_limits(1), ThreadPoolExecutor(workers) as pool:
        return list(pool.map(work, range(n)))


def interface_shapes(
    asm: Assembly, seg: Segmentation, blocks, lame0, cnodes, cases, factor, tol: float, say=None
):
    """Shapes of the interface nodes, shared by every segment's copy of them, and the full
    model's static compliance of each contact load case.

    The six rigid motions of the interface node set, then the interface traces ``t_j`` of the
    full model's static responses to the contact load cases, added greedily until restricting
    the interface to the shapes loses at most ``tol`` of each case's static compliance. That
    loss is ``|t_j - P t_j|^2`` in the norm of the interface's condensed stiffness
    ``S_G = (E_G' K^-1 E_G)^-1``, P the S_G-orthogonal projection (the Craig-Bampton model with
    exact interiors is exact but for it).

    The full model is never factored: each segment is condensed onto its interface nodes (the
    contact segment onto its contact nodes as well) by one sparse factorisation with those nodes
    ordered last (:func:`jsnap._build.linalg.schur_complement`), and the condensed stiffnesses
    add up to the full model's on the contact and interface dofs, ``S_W`` (dense, of their
    size), from which the contact compliance, the traces and ``S_G`` follow by dense algebra.

    Args:
        blocks: per segment, its (K_lam, K_mu, M1) on its local dofs (:func:`segment_blocks`).
        lame0: nominal (lambda, mu), MPa.
        cnodes: (c,) global ids of the contact nodes (all in the contact segment's interior).
        cases: (3c, Q) contact load cases on their dofs (:func:`_normal_loads`), N.
        factor: (c, q) the contact forces' load covariance factor (:func:`_load_factor`).
        say: progress printer, or None.

    Returns:
        ``(gamma, Psi, compliance, gain)``: interface node ids (k,), an orthonormal (3k, q) basis
        of shapes, the full model's static compliance (Q,) of each case, mm/N, and the full
        model's largest static gain from the loads ``kron(factor, I_3)`` to their own dofs: the
        reference the contact segment's interior is truncated against.
    """
    say = say or (lambda *a, **k: None)
    gamma = np.unique(np.concatenate([seg.nodes[i][seg.interface_nodes(i)] for i in range(seg.n_segments)]))
    c3, g3 = 3 * cnodes.size, 3 * gamma.size
    m = c3 + g3
    # S_W, its contact and interface blocks and the factors of the dense algebra below; the
    # load cases, the traces and their S_G products (m x Q each, at most).
    need = 8 * m * (5 * m + 4 * cases.shape[1])
    require(need, f"the condensed stiffness of the contact and interface dofs ({m} dof)", _MESH_HINT)
    lam0, mu0 = lame0
    S_W = np.zeros((m, m))
    # One segment at a time: each factorisation is the build's largest allocation, and two at
    # once raised the 118k-dof hook's build peak from 5.3 to 8.7 GB.
    for i in range(seg.n_segments):
        t0 = time.perf_counter()
        K = (lam0 * blocks[i][0] + mu0 * blocks[i][1]).tocsr()
        local_g = seg.interface_nodes(i)
        at = c3 + _dofs(np.searchsorted(gamma, seg.nodes[i][local_g]))
        keep = local_g
        if i == 0:
            local_c = np.searchsorted(seg.nodes[0], cnodes)
            if not np.array_equal(seg.nodes[0][local_c], cnodes):
                raise RuntimeError("segment: a contact node lies outside the contact segment")
            keep = np.concatenate([local_c, local_g])
            at = np.concatenate([np.arange(c3), at])
        S_W[np.ix_(at, at)] += schur_complement(K, keep, f"segment {i}", _MESH_HINT)
        dt = time.perf_counter() - t0
        say(f"jsnap:   segment {i} ({K.shape[0]} dof) condensed onto {at.size} dof in {dt:.1f} s")
    # The full model on W = (contact, interface): [S_cc S_cG; S_Gc S_GG] [u_c; u_G] = [I; 0].
    S_cc, S_cG, S_GG = S_W[:c3, :c3], S_W[:c3, c3:], S_W[c3:, c3:]
    del S_W
    cho_c = sla.cho_factor(S_cc)
    Y = sla.cho_solve(cho_c, S_cG)  # S_cc^-1 S_cG
    S_G = S_GG - S_cG.T @ Y  # the full model condensed onto the interface
    S_G = 0.5 * (S_G + S_G.T)
    traces_unit = -sla.cho_solve(sla.cho_factor(S_G), Y.T)  # u_G for unit loads at the contact dofs
    C = sla.cho_solve(cho_c, np.eye(c3)) - Y @ traces_unit  # static compliance of the contact dofs
    C = 0.5 * (C + C.T)
    compliance = np.sum(cases * (C @ cases), axis=0)
    B = _kron3(factor)
    G = B.T @ C @ B
    gain = float(sla.eigh(G, eigvals_only=True, subset_by_index=(G.shape[0] - 1, G.shape[0] - 1))[0])
    traces = traces_unit @ cases
    rigid, _ = np.linalg.qr(_rigid_shapes(asm.nodes[gamma]))
    # S_G traces = -S_cG' S_cc^-1 cases: the greedy's S X without a (3k)^2 x Q product.
    extra = _greedy_energy(traces, S_G, rigid, compliance, tol, SX=-Y.T @ cases)
    psi, _ = np.linalg.qr(np.concatenate([rigid, extra], axis=1))
    return gamma, psi, compliance, gain


@dataclass(frozen=True, eq=False)
class SegmentBasis:
    """The reduced basis of one segment and how it was obtained.

    Attributes:
        V: (n_i, r_i) basis on the segment's local dofs: ``n_interface`` constraint modes (the
            interface shapes extended statically into the interior, one per shape, whose
            coordinates all segments share), then interior vectors (zero on the interface,
            M-orthonormal at the nominal material).
        n_interface: number of interface shapes (constraint modes) in it.
        n_balanced: interior states kept by the Hankel singular value tolerance.
        n_static: static-correction vectors added for the contact compliance.
        hsv: interior position Hankel singular values, descending (relative to the largest).
        subspace: dimension of the interior subspace the balancing ran in.
    """

    V: np.ndarray
    n_interface: int
    n_balanced: int
    n_static: int
    hsv: np.ndarray
    subspace: int


@dataclass(frozen=True, eq=False)
class SegmentInterior:
    """A segment's interior blocks at the nominal material, split from its interface dofs ``g``,
    and what :func:`segment_basis` will need to factor and reduce them.

    Attributes:
        K_II, K_IG, M_II, M_IG: interior-interior and interior-interface blocks.
        g, inner: the segment's interface and interior local dofs.   n: its dofs.
        inner_pos: (n,) position of each local dof among the interior's, -1 on the interface.
        ordering: ``node_ordering(K_II)``: the factor's elimination order and nonzeros.
        s_max: the balancing subspace's largest width (lowest modes plus the segment's inputs).
        need: bytes at the peak of ``segment_basis``: the factor and the balancing subspace.
    """

    K_II: sp.csc_matrix
    K_IG: sp.csr_matrix
    M_II: sp.csc_matrix
    M_IG: sp.csr_matrix
    g: np.ndarray
    inner: np.ndarray
    inner_pos: np.ndarray
    n: int
    ordering: tuple[np.ndarray, int]
    s_max: int
    need: int


def _subspace_bytes(n_inner: int, s_max: int) -> int:
    """Bytes of a balancing subspace (n_inner x s_max) and the few copies of it that
    orthonormalising and projecting make, and of the balancing's (s, s, 2, 2) complex Gramian
    terms (position_gramians), a few at once."""
    return 5 * 8 * n_inner * s_max + 4 * 64 * s_max**2


def reduction_bytes(seg: Segmentation, n_contact_nodes: int, n_cases: int, n_modes: int) -> list:
    """The reduction's largest allocations, estimated from the segmentation alone (before any
    factorisation): ``(bytes, what)`` for the condensed stiffness of the contact and interface
    dofs (:func:`interface_shapes`) and for the contact segment's balancing subspace with its
    static correction (:func:`segment_basis`). Both grow with the contact nodes: a rigid part
    that slides along a long face makes them large."""
    gamma = np.unique(np.concatenate([seg.nodes[i][seg.interface_nodes(i)] for i in range(seg.n_segments)]))
    m = 3 * (n_contact_nodes + gamma.size)
    condensed = 8 * m * (5 * m + 4 * n_cases)
    n_inner = 3 * (len(seg.nodes[0]) - len(seg.interface_nodes(0)))
    s_max = min(n_modes, n_inner) + 3 * n_contact_nodes
    # The subspace and its Gramians, then the static correction's (s, cases) solves and loads.
    subspace = _subspace_bytes(n_inner, s_max) + 3 * 8 * s_max * n_cases
    return [
        (condensed, f"the condensed stiffness of the contact and interface dofs ({m} dof)"),
        (subspace, f"the contact segment's balancing subspace ({n_inner} x {s_max}, {n_cases} load cases)"),
    ]


def check_reduction(asm: Assembly, seed_faces, sample, normals, scene) -> list[tuple[int, str]]:
    """Refuse, in seconds, a reduced model whose build would not fit in memory: the estimates
    of :func:`reduction_bytes` from the scene's segmentation and contact candidates, checked
    before the candidates' SDF and the reduction's factorisations are made.

    Raises:
        BuildError: an estimate exceeds the memory this process can have, naming the setting.
    """
    s = scene["solver"]
    seg = segment(asm, seed_faces, s["segment_margin"], s["segments"])
    nodes, weights = (np.asarray(a) for a in sample)
    n_contact = np.unique((asm.free[0::3] // 3)[nodes][weights != 0]).size  # as _contact_interp's
    normals = np.asarray(normals, np.float64).reshape(nodes.shape[0], -1, 3)
    # One case per point and normal, a repeated normal dropped (as _normal_loads does).
    apart = np.linalg.norm(normals[:, 1:] - normals[:, :1], axis=2) > 1e-9
    n_cases = nodes.shape[0] + int(np.sum(apart))
    estimates = reduction_bytes(seg, n_contact, n_cases, s["subspace_modes"])
    for need, what in estimates:
        require(need, what, _CONTACT_HINT)
    return estimates


def segment_interior(blocks, lam0, mu0, rho0, gamma_local, psi, contact, n_modes: int) -> SegmentInterior:
    """:class:`SegmentInterior` of one segment (arguments as :func:`segment_basis`'s)."""
    kl, km, m1 = blocks
    K = (lam0 * kl + mu0 * km).tocsr()
    M = (rho0 * m1).tocsr()
    n = K.shape[0]
    g = _dofs(gamma_local)
    inner = np.setdiff1d(np.arange(n), g)
    inner_pos = -np.ones(n, dtype=np.int64)
    inner_pos[inner] = np.arange(inner.size)
    K_II, K_IG = K[inner][:, inner].tocsc(), K[inner][:, g]
    M_II, M_IG = M[inner][:, inner].tocsc(), M[inner][:, g]
    ordering = node_ordering(K_II)
    span = 3 * len(contact[0]) if contact is not None else psi.shape[1]
    s_max = min(n_modes, inner.size) + span
    need = factor_bytes(ordering[1], read_out=False) + _subspace_bytes(inner.size, s_max)
    return SegmentInterior(K_II, K_IG, M_II, M_IG, g, inner, inner_pos, n, ordering, s_max, need)


def segment_basis(
    blocks,
    lam0: float,
    mu0: float,
    rho0: float,
    gamma_local: np.ndarray,
    psi: np.ndarray,
    contact: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    tol: float,
    n_modes: int,
    interior: SegmentInterior | None = None,
) -> SegmentBasis:
    """Balanced Craig-Bampton basis of one segment (see the module docstring).

    Args:
        blocks: the segment's (K_lam, K_mu, M1) on its local dofs.
        lam0, mu0, rho0: nominal material (MPa, MPa, t/mm^3).
        gamma_local: (k,) local indices of the segment's interface nodes.
        psi: (3k, q) interface shapes on those nodes (node-major).
        contact: for the contact segment, (local indices (c,) of the contact nodes, the factor
            (c, q) of their load covariance (:func:`_load_factor`), the contact load cases
            (3c, Q) on their dofs (:func:`_normal_loads`), the full model's static compliance of
            each case (Q,)); None for the others.
        tol: relative Hankel singular value tolerance; the static correction keeps the compliance
            that the basis loses below ``tol`` times the full model's, for every case.
        n_modes: lowest interior modes in the balancing subspace.
        interior: ``segment_interior`` of the same arguments, if made already.
    """
    it = interior or segment_interior(blocks, lam0, mu0, rho0, gamma_local, psi, contact, n_modes)
    K_II, K_IG, M_II, M_IG, g, inner, inner_pos, n = (
        it.K_II, it.K_IG, it.M_II, it.M_IG, it.g, it.inner, it.inner_pos, it.n
    )
    lu = _factor(K_II, it.ordering)
    C_I = -lu.solve(np.asarray(K_IG @ psi)) if psi.shape[1] else np.zeros((inner.size, 0))
    if contact is not None:
        rows, factor, cases, compliance, gain = contact
        at = inner_pos[_dofs(rows)]  # the contact dofs among the interior's
        if np.any(at < 0):
            raise RuntimeError("segment: a contact node lies on the segment interface (raise the margin)")
        B = np.zeros((inner.size, 3 * factor.shape[1]))
        B[at] = _kron3(factor)  # the contact forces' covariance factor on the contact dofs
    else:  # the interface shapes' accelerations load the interior through the mass
        B = np.asarray(M_II @ C_I + M_IG @ psi)
    require(_subspace_bytes(inner.size, it.s_max), f"the balancing subspace ({inner.size} x {it.s_max})", _MESH_HINT)
    if contact is not None:
        X = _unit_responses(lu, inner.size, at)  # K_II^-1 of a unit force on each contact dof
    else:
        X = lu.solve(B) if B.shape[1] else np.zeros((inner.size, 0))
    U = _m_orthonormal(np.concatenate([_lowest_modes(K_II, M_II, lu, n_modes), X], axis=1), M_II)
    Kh = U.T @ (K_II @ U)
    Kh = 0.5 * (Kh + Kh.T)
    n_static = 0
    if B.shape[1] and np.abs(B).max() > 0:
        Y, hsv = balance(Kh, U.T @ B, tol, ref=None if contact is None else _hankel_reference(gain))
        n_bal = Y.shape[1]
        hsv = hsv / hsv[0]
        if contact is not None:  # static correction: compliance lost below tol x the full model's
            L = U[at].T @ cases
            Z = _greedy_energy(np.linalg.solve(Kh, L), Kh, Y, compliance, tol, SX=L)
            Y = np.concatenate([Y, Z], axis=1)
            n_static = Z.shape[1]
    else:
        Y, hsv, n_bal = np.zeros((U.shape[1], 0)), np.zeros(0), 0
    # Constraint modes as they are (their coordinates are the interface shapes' amplitudes,
    # shared with the other segments), interior vectors mass-orthonormal.
    V = np.zeros((n, psi.shape[1]))
    V[g] = psi
    V[inner] = C_I
    interior = np.zeros((n, Y.shape[1]))
    interior[inner] = _m_orthonormal(U @ Y, M_II)
    return SegmentBasis(np.concatenate([V, interior], axis=1), psi.shape[1], n_bal, n_static, hsv, U.shape[1])


# --------------------------------------------------------------------------------------------
# Building the part (host)
# --------------------------------------------------------------------------------------------

# Arrays of a built reduced part (the fields of jsnap._core.parts.ReducedPart); a segmented
# part has ``coupling_rows`` and ``recon_index`` in place of ``recon``.
_ARRAYS = (
    "kl", "km", "m1", "out_kl", "out_km", "out_m1", "node_rows",
    "sample_nodes", "sample_weights", "stencil_nodes", "stencil_weights", "recon",
)  # fmt: skip


def _contact_maps(asm: Assembly, seg: Segmentation, nodes: np.ndarray, weights: np.ndarray):
    """Global ids of the contact nodes (c,) and the index of each interpolating node (same shape
    as ``nodes``, free-node numbering) into them; nodes with weight 0 (clamped) point at 0."""
    free_nodes = asm.free[0::3] // 3
    g = free_nodes[nodes]
    used = weights != 0
    contact = np.unique(g[used])
    if not np.all(np.isin(contact, seg.nodes[0])):
        raise RuntimeError("segment: a contact point interpolates a node outside the contact segment")
    idx = np.where(used, np.searchsorted(contact, g), 0)
    return contact, idx


def _dense(A) -> np.ndarray:
    return A.toarray() if sp.issparse(A) else np.asarray(A)


def _part_arrays(asm, seg, blocks, reactions, Vs, sample, stencil, springs: bool) -> dict:
    """The part's arrays (float64 numpy).

    Args:
        Vs: per segment, its rows of the part's basis: (n_i, r), the displacement of the
            segment's local dofs per unit coordinate of the whole part (sparse or dense).
        springs: also the rows ``Dg`` of the gaps between the copies of shared nodes (segmented
            parts, whose copies are joined by springs; a reduced part's copies share their
            coordinates, so its gaps are zero).
    """
    n_seg = seg.n_segments
    r = Vs[0].shape[1]
    out = {}
    for name, b in zip(("kl", "km", "m1"), range(3), strict=True):
        A = sum(_dense(V.T @ (blocks[i][b] @ V)) for i, V in enumerate(Vs))
        out[name] = 0.5 * (A + A.T)

    def rows(i, local_dofs):  # (len, r) rows of the basis for local dofs of segment i
        return _dense(Vs[i][local_dofs])

    if springs:
        P = seg.pairs
        cr = np.zeros((3 * len(P), r))
        for a in range(3):
            for sa in range(n_seg):
                for sb in range(n_seg):
                    sel = np.flatnonzero((P[:, 0] == sa) & (P[:, 2] == sb))
                    if sel.size:
                        cr[3 * sel + a] = rows(sa, 3 * P[sel, 1] + a) - rows(sb, 3 * P[sel, 3] + a)
        out["coupling_rows"] = cr
    S = wrench_rows(asm)
    for name, b in zip(("out_kl", "out_km", "out_m1"), range(3), strict=True):
        out[name] = sum(S @ _dense(reactions[i][b] @ V) for i, V in enumerate(Vs))
    (s_nodes, s_w), (t_nodes, t_w) = sample, stencil
    contact, _ = _contact_maps(
        asm, seg, np.concatenate([s_nodes.ravel(), t_nodes.ravel()]), np.concatenate([s_w.ravel(), t_w.ravel()])
    )
    local = np.searchsorted(seg.nodes[0], contact)
    out["node_rows"] = rows(0, _dofs(local)).reshape(len(contact), 3, r)
    for name, (nodes, w) in (("sample", sample), ("stencil", stencil)):
        used = w != 0
        g = (asm.free[0::3] // 3)[nodes]
        out[f"{name}_nodes"] = np.where(used, np.searchsorted(contact, g), 0).astype(np.int32)
        out[f"{name}_weights"] = np.where(used, w, 0.0)
    # Each free dof of the full mesh is read from its copy in the lowest-numbered segment.
    n_free = asm.free.size
    seg_of = np.full(asm.nodes.shape[0], -1)
    loc_of = np.zeros(asm.nodes.shape[0], dtype=np.int64)
    for i in reversed(range(n_seg)):
        seg_of[seg.nodes[i]] = i
        loc_of[seg.nodes[i]] = np.arange(len(seg.nodes[i]))
    fnode, comp = asm.free // 3, asm.free % 3
    s_of, l_of = seg_of[fnode], loc_of[fnode]
    if np.any(s_of < 0):
        raise RuntimeError("segment: a free node belongs to no segment")
    if springs:  # the identity basis: a coordinate per local dof, segment after segment
        offs = np.concatenate([[0], np.cumsum([3 * len(n) for n in seg.nodes])])
        out["recon_index"] = (offs[s_of] + 3 * l_of + comp).astype(np.int32)
    else:
        recon = np.zeros((n_free, r))
        for i in range(n_seg):
            sel = np.flatnonzero(s_of == i)
            recon[sel] = rows(i, 3 * l_of[sel] + comp[sel])
        out["recon"] = recon
    return out


def _identity_bases(seg: Segmentation) -> list:
    """The segmented part's basis rows: every segment's local dofs are coordinates of their own."""
    sizes = [3 * len(n) for n in seg.nodes]
    offs = np.concatenate([[0], np.cumsum(sizes)])
    r = int(offs[-1])
    return [
        sp.csr_matrix((np.ones(n), (np.arange(n), offs[i] + np.arange(n))), shape=(n, r))
        for i, n in enumerate(sizes)
    ]


def join_bases(bases, blocks, material: tuple[float, float, float]) -> tuple[list[np.ndarray], tuple[int, ...]]:
    """The segments' bases joined into one basis of the whole part, exactly.

    Every segment's constraint modes carry the same interface shapes (:func:`interface_shapes`),
    so their coordinates are shared: the part's coordinates are ``(q, z_0, z_1, ...)``, the
    interface shapes' amplitudes then each segment's interior coordinates, and the copies of a
    shared node move together for every ``z``. The joined basis is then changed to the reduced
    model's modal coordinates at the nominal material (mass-orthonormal, stiffness diagonal:
    well scaled for float32 rollouts).

    Args:
        material: nominal (E MPa, nu, rho t/mm^3).

    Returns:
        ``(Vs, orders)``: per segment its rows (n_i, r) of the joined basis, and the orders
        ``(interface shapes, interior coordinates of segment 0, of segment 1, ...)``.
    """
    lam0, mu0 = lame(material[0], material[1])
    rho0 = material[2]
    q = bases[0].n_interface
    if any(b.n_interface != q for b in bases):
        raise RuntimeError("join_bases: the segments do not carry the same interface shapes")
    interior = [b.V.shape[1] - q for b in bases]
    offs = q + np.concatenate([[0], np.cumsum(interior)])
    r = int(offs[-1])
    Vs = []
    for i, b in enumerate(bases):
        V = np.zeros((b.V.shape[0], r))
        V[:, :q] = b.V[:, :q]
        V[:, offs[i] : offs[i + 1]] = b.V[:, q:]
        Vs.append(V)
    G = sum(V.T @ (rho0 * blocks[i][2] @ V) for i, V in enumerate(Vs))
    # Scaled to a unit diagonal first: the constraint modes' masses are ~1e-10 of the interior
    # vectors' (unit), and the rank test is relative.
    d = np.sqrt(np.diag(G))
    T = _orthonormalizer(G / np.outer(d, d)) / d[:, None]
    # Then rotated onto the reduced model's own modes at the nominal material: M_r = I and K_r
    # diagonal, for every E and density, and nearly so for another Poisson ratio. A dense
    # float32 product with K_r or S_r^-1 then adds no cancellation between stiff and soft
    # coordinates (their frequencies span ~4 decades on a fine mesh).
    Vs = [V @ T for V in Vs]
    K = sum(V.T @ ((lam0 * blocks[i][0] + mu0 * blocks[i][1]) @ V) for i, V in enumerate(Vs))
    _, Phi = np.linalg.eigh(0.5 * (K + K.T))
    Vs = [V @ Phi for V in Vs]
    return Vs, (T.shape[1] - sum(interior), *interior)


def _to_part(arrays: dict, orders, method: str, kc: float, bc: float) -> SegmentedPart | ReducedPart:
    with jax.enable_x64(True):
        if method == "reduced":
            return ReducedPart(**{k: jnp.asarray(arrays[k]) for k in _ARRAYS}, orders=tuple(orders))
        return SegmentedPart(
            **{k: jnp.asarray(arrays[k]) for k in _ARRAYS if k != "recon"},
            coupling_rows=jnp.asarray(arrays["coupling_rows"]),
            coupling=jnp.asarray([kc, bc], jnp.float64),
            recon_index=jnp.asarray(arrays["recon_index"]),
            orders=tuple(orders),
        )


def reduce_bases(
    asm,
    seg,
    blocks,
    material: tuple[float, float, float],
    sample,
    normals,
    tol: float,
    n_modes: int,
    say=None,
    patch: float = 0.0,
    points: np.ndarray | None = None,
):
    """Per-segment balanced bases (see the module docstring).

    Args:
        material: nominal (E MPa, nu, rho t/mm^3) the basis is computed at.
        sample: (nodes (P, k) free-node indices, weights (P, k)) of the contact candidate points.
        normals: (P, m, 3) outward normals of the section side(s) each point lies on.
        tol: ``solver.hsv_tolerance``.
        n_modes: lowest interior modes per segment in the balancing subspace.
        say: progress printer (long builds), or None.
        patch: ``solver.load_patch``, mm: the contact load cases are unit forces spread over a
            Gaussian patch of this standard deviation (:func:`_patch_weights`); 0: at each
            candidate point alone.
        points: (P, 3) the candidate points' rest positions, mm: needed with ``patch`` (the
            interpolation weights of clamped nodes are zero in ``sample``, so they do not place
            the points on faces that touch the fixed region).

    Returns:
        ``(bases, info)``: a :class:`SegmentBasis` per segment and a dict of sizes.
    """
    say = say or (lambda *a, **k: None)
    E, nu, rho = material
    lam0, mu0 = lame(E, nu)
    free = asm.free
    nodes, weights = sample
    cnodes, Jn = _contact_interp((free[0::3] // 3)[nodes], weights)
    normals = np.asarray(normals, dtype=np.float64).reshape(Jn.shape[0], -1, 3)
    if patch > 0 and points is None:
        raise ValueError("reduce_bases: a load patch needs the candidate points' rest positions (points)")
    cases = _normal_loads(Jn, normals, points, patch)
    # Half the tolerance for the interface, half for the interiors: the static compliance lost by
    # the two adds up.
    t0 = time.perf_counter()
    factor = _load_factor(Jn)
    gamma, psi, compliance, gain = interface_shapes(
        asm, seg, blocks, (lam0, mu0), cnodes, cases, factor, tol / 2, say=say
    )
    say(f"jsnap:   {psi.shape[1]} interface shapes on {len(gamma)} nodes in {time.perf_counter() - t0:.1f} s")
    psi = psi.reshape(len(gamma), 3, -1)

    args = []
    for i in range(seg.n_segments):
        gl = seg.interface_nodes(i)
        # The shapes as they are on this segment's interface nodes (where a segment touches
        # only part of the interface some may vanish there): one coordinate per shape, shared.
        psi_i = psi[np.searchsorted(gamma, seg.nodes[i][gl])].reshape(3 * len(gl), -1)
        contact = None
        if i == 0:
            contact = (np.searchsorted(seg.nodes[0], cnodes), factor, cases, compliance, gain)
        args.append((blocks[i], lam0, mu0, rho, gl, psi_i, contact))
    interiors = [segment_interior(*a, n_modes) for a in args]
    need = [it.need for it in interiors]

    def basis(i):
        t0 = time.perf_counter()
        it, interiors[i] = interiors[i], None  # freed once used: held no longer than before
        b = segment_basis(*args[i], tol, n_modes, interior=it)
        say(
            f"jsnap:   segment {i}: {b.V.shape[1]} coordinates (subspace {b.subspace}, "
            f"{b.n_balanced} balanced, {b.n_static} static) in {time.perf_counter() - t0:.1f} s"
        )
        return b

    bases = _each_segment(basis, need)
    info = dict(
        interface_nodes=len(gamma),
        interface_shapes=int(psi.shape[2]),
        contact_nodes=len(cnodes),
        contact_load_cases=int(cases.shape[1]),
    )
    return bases, info


# --------------------------------------------------------------------------------------------
# Cache
# --------------------------------------------------------------------------------------------


def cache_key(asm: Assembly, seed_faces, sample, stencil, normals, settings: dict, points=None) -> str:
    """SHA-256 of everything a reduced model depends on: mesh and element, fixed dofs, seed
    faces, the contact points' and stencils' nodes and weights, the points' normals and the
    settings (material it was balanced at, tolerance, subspace modes, margin, segments, and the
    load patch with the points' positions where one is set)."""
    h = KeyHash("reduced").settings(
        dict(settings, element=asm.element, gramian_damping=GRAMIAN_DAMPING, joint=_JOINT, truncation=_TRUNCATION)
    )
    h.arrays(asm.mesh.points, asm.mesh.cells, asm.fixed, np.sort(np.sort(seed_faces, axis=1), axis=0))
    if asm.sliding.nnz:
        h.arrays(asm.sliding.indices, asm.sliding.indptr, asm.sliding.data)
    if settings.get("load_patch"):
        h.arrays(np.asarray(points, dtype=np.float64))
    return h.arrays(*sample, *stencil, np.asarray(normals, dtype=np.float64)).hexdigest()


def _check_arrays(arrays: dict, meta: dict) -> None:
    """A cached file's arrays must be those of a reduced model of its stored orders."""
    try:
        r = sum(int(o) for o in meta["orders"])
    except (KeyError, ValueError, TypeError) as err:
        raise ArtefactError(f"corrupt metadata ({type(err).__name__}: {err})") from None
    missing = [k for k in _ARRAYS if k not in arrays]
    square = ("kl", "km", "m1", "node_rows", "recon")
    if missing or any(arrays[k].shape[-1] != r for k in square if k in arrays):
        raise ArtefactError(f"arrays missing or not of order {r} ({', '.join(missing) or 'shapes'})")


def _settings(scene) -> dict:
    s, m = scene["solver"], scene["material"]
    return dict(
        youngs_modulus=m["youngs_modulus"],
        poissons_ratio=m["poissons_ratio"],
        density=m["density"],
        hsv_tolerance=s["hsv_tolerance"],
        subspace_modes=s["subspace_modes"],
        segment_margin=s["segment_margin"],
        segments=s["segments"],
        # Only when set, so that models reduced at point loads keep their cache keys.
        **({"load_patch": s["load_patch"], "patch_weights": _PATCH} if s["load_patch"] else {}),
    )


def load_or_build(
    asm: Assembly, seed_faces, sample, stencil, normals, scene, *, progress: bool = False, rebuild=False, points=None
):
    """The reduced model's arrays for a scene, from the cache or built (and cached).

    A cached file that is corrupt or was built for something else is never used: it is reported
    with a warning and rebuilt. Processes that build the same model at once build it once.

    Returns:
        ``(arrays, meta)``; meta holds ``orders``, ``key``, ``path``, ``cached``, ``seconds``
        (build time), the per-segment reduction details and the Hankel singular values.
    """
    settings = _settings(scene)
    key = cache_key(asm, seed_faces, sample, stencil, normals, settings, points)
    return cached(
        "reduced",
        key,
        lambda: _build(asm, seed_faces, sample, stencil, normals, settings, progress, points),
        what="the reduced model",
        check=_check_arrays,
        fresh=rebuild,
    )


def _build(asm: Assembly, seed_faces, sample, stencil, normals, settings, progress, points=None):
    """Segment and reduce (:func:`load_or_build`'s build): ``(arrays, meta)``."""
    say = print if progress else (lambda *a, **k: None)
    t0 = time.perf_counter()
    seg = segment(asm, seed_faces, settings["segment_margin"], settings["segments"])
    blocks, reactions = zip(*(segment_blocks(asm, seg, i) for i in range(seg.n_segments)), strict=True)
    say(f"jsnap: reducing {asm.free.size} dof: segments of {', '.join(str(3 * len(n)) for n in seg.nodes)} dof")
    material = (settings["youngs_modulus"], settings["poissons_ratio"], settings["density"])
    bases, info = reduce_bases(
        asm,
        seg,
        blocks,
        material,
        sample,
        normals,
        settings["hsv_tolerance"],
        settings["subspace_modes"],
        say,
        patch=settings.get("load_patch", 0.0),
        points=points,
    )
    Vs, orders = join_bases(bases, blocks, material)
    arrays = _part_arrays(asm, seg, blocks, reactions, Vs, sample, stencil, springs=False)
    seconds = time.perf_counter() - t0
    meta = dict(
        orders=list(orders),
        seconds=seconds,
        settings=settings,
        full_dof=int(asm.free.size),
        segment_dof=[3 * len(n) for n in seg.nodes],
        segment_elements=np.bincount(seg.element_segment).tolist(),
        interface_pairs=len(seg.pairs),
        segments=[
            dict(
                order=int(b.V.shape[1]),
                interface=b.n_interface,
                balanced=b.n_balanced,
                static=b.n_static,
                subspace=b.subspace,
                hsv=[float(x) for x in b.hsv],
            )
            for b in bases
        ],
        **info,
    )
    say(f"jsnap: reduced {asm.free.size} dof to {' + '.join(map(str, orders))} in {seconds:.1f} s")
    return {k: v for k, v in arrays.items() if v is not None}, meta


def build_part(
    asm: Assembly, seed_faces, sample, stencil, normals, scene, *, progress: bool = False, points=None
):
    """The part of a segmented or reduced scene (``solver.method``), and a dict describing it.

    Args:
        asm: the full assembly.
        seed_faces: (f, 3) vertex ids of the boundary faces of the contact candidate points and
            of their stencils (``_model.build``).
        sample: (nodes (P, k) free-node indices, weights (P, k)) of the candidate points.
        stencil: (nodes (P, 8, k), weights (P, 8, k)) of their normal stencils.
        normals: (P, 2, 3) outward normals of the section side each point lies on and (at an
            edge) of the other side: the contact load cases of the static correction.
        scene: the validated scene (``solver`` keys: method, hsv_tolerance, subspace_modes,
            segment_margin, segments, load_patch, interface_stiffness, interface_damping, dt).
        points: (P, 3) the candidate points' rest positions, mm (used with ``solver.load_patch``).
    """
    s = scene["solver"]
    sample = tuple(np.asarray(a) for a in sample)
    stencil = tuple(np.asarray(a) for a in stencil)
    kc = s["interface_stiffness"]
    bc = s["interface_damping"] if s["interface_damping"] is not None else 0.5 * kc * s["dt"]
    if s["method"] == "segmented":
        seg = segment(asm, seed_faces, s["segment_margin"], s["segments"])
        blocks, reactions = zip(*(segment_blocks(asm, seg, i) for i in range(seg.n_segments)), strict=True)
        arrays = _part_arrays(asm, seg, blocks, reactions, _identity_bases(seg), sample, stencil, springs=True)
        orders = [3 * len(n) for n in seg.nodes]
        info = dict(orders=orders, interface_pairs=len(seg.pairs))
    elif s["method"] == "reduced":
        arrays, info = load_or_build(
            asm, seed_faces, sample, stencil, normals, scene, progress=progress, points=points
        )
        orders = info["orders"]
    else:
        raise ValueError(
            f"solver.method = {s['method']!r}: build_part makes 'segmented' or 'reduced' parts"
        )
    return _to_part(arrays, orders, s["method"], kc, bc), info
