"""Linear tetrahedral elasticity assembled once on the host with scikit-fem.

The stiffness is kept as parameter-free blocks so that everything after assembly is a (JAX,
differentiable) function of the material:

    K(E, nu) = lambda(E, nu) K_lam + mu(E, nu) K_mu,     M(rho) = rho M1,

with ``K_lam = int div(u) div(v)``, ``K_mu = int 2 eps(u) : eps(v)`` and ``M1 = int u . v``.

Degrees of freedom are node-major, ``dof = 3 * node + component``; for P2 the nodes are the mesh
vertices followed by the edge midpoints (scikit-fem's ordering). Units: mm, N, MPa, tonne.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import skfem
from skfem.helpers import ddot, div, dot, sym_grad

import jax
import jax.numpy as jnp

from jsnap._core.params import lame
from jsnap._core.pmi import SparseBlocks
from jsnap._geometry.mesh import TetMesh

__all__ = [
    "Assembly", "assemble", "lame", "output_rows", "solve_static", "sparse_blocks", "traction_load", "wrench_rows",
]  # fmt: skip

_ELEMENTS = {"P1": skfem.ElementTetP1, "P2": skfem.ElementTetP2}


@skfem.BilinearForm
def _k_lam(u, v, w):
    return div(u) * div(v)


@skfem.BilinearForm
def _k_mu(u, v, w):
    return 2.0 * ddot(sym_grad(u), sym_grad(v))


@skfem.BilinearForm
def _m1(u, v, w):
    return dot(u, v)


@dataclass(frozen=True)
class Assembly:
    """The parameter-free FEM blocks of one mesh and element (host side, float64).

    Attributes:
        element: ``"P1"`` or ``"P2"``.
        mesh: the tetrahedral mesh (vertices and 4-node cells).
        nodes: (N, 3) positions of all finite-element nodes, mm (vertices, then P2 edge nodes).
        cells: (m, 4) or (m, 10) node indices per element; the 10-node order is VTK's tetra10
            (4 vertices, then edges 01, 12, 02, 03, 13, 23).
        K_lam, K_mu, M1: (3N, 3N) CSR matrices sharing one sparsity pattern.
        fixed: (nb,) sorted dofs clamped at the base (every dof of every node on z = 0).
        free: (nf,) sorted remaining dofs.
        sliding: (3N, 3N) CSR penalty part of ``K_mu`` that holds the nodes of the mesh's
            sliding (symmetry) planes in their planes (see :func:`sliding_penalty`); empty
            without planes.
    """

    element: str
    mesh: TetMesh
    nodes: np.ndarray
    cells: np.ndarray
    K_lam: sp.csr_matrix
    K_mu: sp.csr_matrix
    M1: sp.csr_matrix
    fixed: np.ndarray
    free: np.ndarray
    basis: skfem.CellBasis
    sliding: sp.csr_matrix

    @property
    def n_dof(self) -> int:
        return 3 * self.nodes.shape[0]

    def stiffness(self, E: float, nu: float) -> sp.csr_matrix:
        """K(E, nu) = lambda K_lam + mu K_mu, (3N, 3N), N/mm."""
        lam, mu = lame(E, nu)
        return (lam * self.K_lam + mu * self.K_mu).tocsr()

    def probes(self, points: np.ndarray) -> sp.csr_matrix:
        """(P, N) interpolation matrix from nodal values to values at ``points`` (P, 3), mm."""
        return self._scalar_basis().probes(np.asarray(points, dtype=float).T).tocsr()

    def _scalar_basis(self) -> skfem.CellBasis:
        return skfem.Basis(self.basis.mesh, _ELEMENTS[self.element]())


def _same_pattern(*mats: sp.spmatrix) -> list[sp.csr_matrix]:
    """Put matrices on the union of their sparsity patterns, so they combine entrywise."""
    union = sum(abs(m) for m in mats).tocoo()
    row, col = union.row, union.col
    out = []
    for m in mats:
        vals = np.asarray(m.tocsr()[row, col]).ravel()
        z = sp.csr_matrix((vals, (row, col)), shape=m.shape)
        z.sort_indices()
        out.append(z)
    return out


def assemble(mesh: TetMesh, element: str = "P2") -> Assembly:
    """Assemble K_lam, K_mu, M1 for ``mesh`` with P1 or P2 tetrahedra, clamped at its fixed
    region (``mesh.base_nodes``; a P2 edge node is fixed when both its ends are).

    Args:
        mesh: tetrahedral mesh in mm with its fixed nodes marked.
        element: ``"P1"`` (linear; locks in bending on coarse meshes) or ``"P2"`` (quadratic).
    """
    if element not in _ELEMENTS:
        raise ValueError(f"solver.element = {element!r}: must be one of {', '.join(_ELEMENTS)}")
    skmesh = skfem.MeshTet(mesh.points.T.copy(), mesh.cells.T.copy())
    basis = skfem.Basis(skmesh, skfem.ElementVector(_ELEMENTS[element]()))
    K_lam = _k_lam.assemble(basis)
    K_mu = _k_mu.assemble(basis)
    M1 = _m1.assemble(basis)
    n_nodes = basis.N // 3
    sliding = sliding_penalty(K_mu, _fe_planes(mesh, skmesh, element, n_nodes))
    K_lam, K_mu, M1 = _same_pattern(K_lam, K_mu + sliding, M1)

    nodes = basis.doflocs[:, 0::3].T.copy()
    # Node-major dof numbering is what everything downstream relies on: check, never assume.
    if not np.array_equal(basis.nodal_dofs[0], 3 * np.arange(skmesh.p.shape[1])):
        raise RuntimeError("unexpected scikit-fem dof ordering (expected node-major)")
    scalar = skfem.Basis(skmesh, _ELEMENTS[element]())
    cells = scalar.element_dofs.T.copy()  # (m, 4) or (m, 10), skfem edge order = VTK tetra10

    n_vert = skmesh.p.shape[1]
    vertex = np.zeros(n_vert, dtype=bool)
    vertex[mesh.base_nodes] = True
    base = vertex
    if element == "P2":
        base = np.concatenate([vertex, vertex[skmesh.edges[0]] & vertex[skmesh.edges[1]]])
    if base.size != n_nodes:
        raise RuntimeError("unexpected scikit-fem node numbering (vertices, then edges)")
    fixed = np.flatnonzero(np.repeat(base, 3))
    free = np.flatnonzero(~np.repeat(base, 3))
    return Assembly(element, mesh, nodes, cells, K_lam, K_mu, M1, fixed, free, basis, sliding)


# The penalty stiffness of a sliding plane over the largest diagonal entry of its node's elastic
# block: the constraint is violated by ~1/SLIDING_PENALTY of the node's displacement (a 1e-4
# relative error), while K's condition number grows by the same factor only (sparse float64
# factorisations keep ~1e-4 relative accuracy at 1e12).
SLIDING_PENALTY = 1e4


def _fe_planes(mesh: TetMesh, skmesh, element: str, n_nodes: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """The sliding planes on finite-element nodes: a P2 edge node lies on a plane when both
    its ends do (like the fixed base)."""
    planes = []
    for nodes, normal in mesh.sliding:
        on = np.zeros(skmesh.p.shape[1], dtype=bool)
        on[nodes] = True
        if element == "P2":
            on = np.concatenate([on, on[skmesh.edges[0]] & on[skmesh.edges[1]]])
        planes.append((np.flatnonzero(on[:n_nodes]), normal))
    return planes


def sliding_penalty(K_mu: sp.spmatrix, planes) -> sp.csr_matrix:
    """(3N, 3N) penalty ``sum_i k_i n n'`` on the 3x3 diagonal blocks of the nodes of each
    sliding plane ``(nodes, n)``: a stiff spring along the plane's normal, ``k_i`` =
    :data:`SLIDING_PENALTY` times the largest diagonal entry of node i's block of ``K_mu``, so
    that it scales with the shear modulus like the elastic stiffness. A node on two planes (an
    edge of a sector on its axis) gets both springs."""
    n = K_mu.shape[0]
    diag = K_mu.diagonal().reshape(-1, 3).max(axis=1)
    rows, cols, vals = [], [], []
    for nodes, normal in planes:
        nn = np.outer(normal, normal)
        k = SLIDING_PENALTY * diag[nodes]
        d = 3 * nodes[:, None, None]
        rows.append(np.broadcast_to(d + np.arange(3)[None, :, None], (nodes.size, 3, 3)).ravel())
        cols.append(np.broadcast_to(d + np.arange(3)[None, None, :], (nodes.size, 3, 3)).ravel())
        vals.append((k[:, None, None] * nn[None]).ravel())
    if not rows:
        return sp.csr_matrix((n, n))
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))


def wrench_rows(asm: Assembly) -> np.ndarray:
    """(6, n_fixed) sum of the base reactions (n_fixed,) at the fixed dofs into force (N) and
    moment about the base centroid (N mm)."""
    pos = asm.nodes[asm.fixed[0::3] // 3]
    o = pos - pos.mean(axis=0)
    n = pos.shape[0]
    S = np.zeros((6, 3 * n))
    j = 3 * np.arange(n)
    for a in range(3):
        S[a, j + a] = 1.0
    S[3, j + 2], S[3, j + 1] = o[:, 1], -o[:, 2]
    S[4, j + 0], S[4, j + 2] = o[:, 2], -o[:, 0]
    S[5, j + 1], S[5, j + 0] = o[:, 0], -o[:, 1]
    return S


def output_rows(asm: Assembly, V=None) -> dict:
    """``out_kl, out_km, out_m1`` (6, r): the base wrench per unit of ``K_lam``, ``K_mu`` and
    ``M1`` action of the coordinates ``x_free = V x`` (``V`` (n_free, r); None: the free dofs)."""
    S = wrench_rows(asm)
    out = {}
    for name, block in (("out_kl", asm.K_lam), ("out_km", asm.K_mu), ("out_m1", asm.M1)):
        rows = block[asm.fixed][:, asm.free]
        out[name] = S @ (rows.toarray() if V is None else rows @ V)
    return out


def sparse_blocks(K_lam, K_mu, M1) -> SparseBlocks:
    """:class:`SparseBlocks` (float64) from three scipy matrices on one sparsity pattern."""
    a, b, c = (sp.coo_matrix(m) for m in (K_lam, K_mu, M1))
    if not (np.array_equal(a.row, b.row) and np.array_equal(a.row, c.row)):
        raise ValueError("sparse_blocks: the three blocks must share one sparsity pattern")
    if not (np.array_equal(a.col, b.col) and np.array_equal(a.col, c.col)):
        raise ValueError("sparse_blocks: the three blocks must share one sparsity pattern")
    order = np.lexsort((a.col, a.row))
    with jax.enable_x64(True):
        return SparseBlocks(
            jnp.asarray(a.row[order], jnp.int32),
            jnp.asarray(a.col[order], jnp.int32),
            jnp.asarray(a.data[order]),
            jnp.asarray(b.data[order]),
            jnp.asarray(c.data[order]),
            a.shape[0],
            a.shape[1],
        )


def traction_load(asm: Assembly, where, traction) -> np.ndarray:
    """Consistent nodal load (3N,) in N of a uniform traction (3,) in MPa on boundary facets.

    Args:
        where: predicate ``f(x) -> bool array`` on facet midpoints (x: (3, k) in mm).
        traction: (3,) surface traction, MPa = N/mm^2.
    """
    skmesh = asm.basis.mesh
    facets = skmesh.facets_satisfying(where, boundaries_only=True)
    if len(facets) == 0:
        raise ValueError("traction_load: no boundary facet satisfies the predicate")
    fb = skfem.FacetBasis(skmesh, asm.basis.elem, facets=facets)
    t = np.asarray(traction, dtype=float)

    @skfem.LinearForm
    def load(v, w):
        return t[0] * v[0] + t[1] * v[1] + t[2] * v[2]

    return load.assemble(fb)


def solve_static(asm: Assembly, E: float, nu: float, f: np.ndarray) -> np.ndarray:
    """Static displacement u (3N,) in mm for nodal load f (3N,) in N, base clamped."""
    K = asm.stiffness(E, nu)
    u = np.zeros(asm.n_dof)
    free = asm.free
    Kff = K[free][:, free].tocsc()
    u[free] = sp.linalg.spsolve(Kff, f[free])
    return u


def base_reaction(asm: Assembly, E: float, nu: float, u: np.ndarray, f: np.ndarray):
    """Static reaction at the base: force (3,) in N and moment (3,) in N·mm about the base
    centroid, exerted by the support on the body (like a FEM code's RF)."""
    K = asm.stiffness(E, nu)
    r = (K @ u - f)[asm.fixed]
    nodes = asm.fixed[0::3] // 3
    forces = r.reshape(-1, 3)
    pos = asm.nodes[nodes]
    centre = pos.mean(axis=0)
    return forces.sum(axis=0), np.cross(pos - centre, forces).sum(axis=0)
