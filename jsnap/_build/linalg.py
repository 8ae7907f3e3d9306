"""Sparse symmetric positive definite factorisations of the FEM blocks, their memory estimated
before they are made, and Schur complements from a single factorisation (host side, float64).

SuperLU (``scipy.sparse.linalg.splu``) runs in its symmetric mode with diagonal pivots on a
fill-reducing ordering of the *nodes* (minimum degree on the node graph, each node's three dofs
kept together). Factoring the node graph first costs about 1/27 of the real factorisation and
gives its fill, hence its memory, before the real one is attempted (:func:`factor_bytes`).

A Schur complement ``S = A_WW - A_WR A_RR^-1 A_RW`` onto a set W of nodes comes from one
factorisation with W ordered last: then ``L U = P A P'`` has ``L_WW U_WW = S`` as its trailing
block (:func:`schur_complement`), so no solve against the |W| unit vectors is needed; those
solves, one per dof of W, cost as much as that many triangular passes through the whole factor.

SuperLU's supernodal solves call BLAS on small blocks, one supernode at a time; a threaded BLAS
spends more on waking its threads for each than it saves (several times slower on 2 cores, worse
on a loaded machine), so the factorisations and solves here run with one BLAS thread.

Units: whatever the matrix carries.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from threadpoolctl import threadpool_limits

from jsnap._build.memory import require

__all__ = ["Factor", "factor", "factor_bytes", "node_ordering", "schur_complement"]

# Bytes SuperLU keeps per nonzero of L + U (value and row index), and the copy that reading the
# factors out of it (``SuperLU.L``, ``.U``) makes of one of them.
_BYTES_PER_NONZERO = 12
_SPLU = dict(diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))


def _node_graph(A: sp.spmatrix) -> sp.csc_matrix:
    """The node-level matrix of a node-major (3 dofs per node) matrix: the graph Laplacian of its
    3x3 block pattern plus the identity (symmetric positive definite, factored without pivots)."""
    A = sp.csr_matrix(A)
    if A.shape[0] % 3:
        raise ValueError(f"node_ordering: {A.shape[0]} dofs is not 3 per node")
    n_nodes = A.shape[0] // 3
    R = sp.kron(sp.identity(n_nodes, format="csr"), np.ones((1, 3)), format="csr")
    G = (R @ abs(A) @ R.T).tocsr()
    G.setdiag(0)
    G.eliminate_zeros()
    G.data[:] = -1.0
    return (G + sp.diags(1.0 - np.asarray(G.sum(axis=1)).ravel())).tocsc()


def _dofs(nodes: np.ndarray) -> np.ndarray:
    return (3 * np.asarray(nodes)[:, None] + np.arange(3)).ravel()


def node_ordering(A: sp.spmatrix, last: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """A fill-reducing dof ordering of the node-major matrix ``A`` and the nonzeros of L + U it
    gives, estimated from the node graph.

    Args:
        A: (3N, 3N) sparse, structurally symmetric.
        last: node indices to order last, in this order (their dofs then form the trailing
            block); None: none.

    Returns:
        ``(perm, nnz)``: dofs (3N,) in elimination order and the estimated nonzeros of L + U.
    """
    G = _node_graph(A)
    n_nodes = G.shape[0]
    last = np.zeros(0, dtype=np.int64) if last is None else np.asarray(last, dtype=np.int64)
    rest = np.setdiff1d(np.arange(n_nodes), last)
    if rest.size:
        lu = spla.splu(G[rest][:, rest].tocsc(), permc_spec="MMD_AT_PLUS_A", **_SPLU)
        order = rest[np.argsort(lu.perm_c)]
        nnz = lu.L.nnz + lu.U.nnz
    else:
        order, nnz = rest, 0
    if last.size:
        order = np.concatenate([order, last])
        lu = spla.splu(G[order][:, order].tocsc(), permc_spec="NATURAL", **_SPLU)
        nnz = lu.L.nnz + lu.U.nnz
    # A node's 3 x 3 block fills as one: 9 dof nonzeros per node nonzero (less the zeros above
    # the diagonal of the diagonal blocks, which SuperLU stores in its supernodes anyway).
    return _dofs(order), 9 * int(nnz)


def factor_bytes(nnz: int, dense: int = 0, read_out: bool = True) -> int:
    """Bytes to factor a matrix whose L + U have ``nnz`` nonzeros (and, with ``read_out``, to read
    its factors out), with ``dense`` float64 numbers made of the result."""
    return (2 if read_out else 1) * _BYTES_PER_NONZERO * nnz + 8 * dense


class Factor:
    """``A = P' L U P`` of a sparse symmetric positive definite ``A`` (n, n): solves ``A x = b``.

    Attributes:
        n: size.   perm: (n,) the elimination order of the dofs.
    """

    def __init__(self, A: sp.spmatrix, perm: np.ndarray):
        self.n = A.shape[0]
        self.perm = perm
        with threadpool_limits(1):
            self.lu = spla.splu(sp.csc_matrix(A)[perm][:, perm].tocsc(), permc_spec="NATURAL", **_SPLU)

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``A^-1 b`` for b (n,) or (n, k)."""
        b = np.asarray(b, dtype=np.float64)
        x = np.empty_like(b)
        with threadpool_limits(1):
            x[self.perm] = self.lu.solve(np.asfortranarray(b[self.perm]))
        return x


def factor(A: sp.spmatrix, what: str, hint: str, ordering: tuple[np.ndarray, int] | None = None) -> Factor:
    """:class:`Factor` of the node-major SPD matrix ``A``, refused (:class:`BuildError` naming
    ``hint``) before SuperLU allocates anything when its estimated memory would not fit.

    Args:
        what: what the matrix is, for the message.
        hint: the setting to change, for the message.
        ordering: ``node_ordering(A)``, if made already.
    """
    perm, nnz = node_ordering(A) if ordering is None else ordering
    require(factor_bytes(nnz, read_out=False), f"the sparse factor of {what} ({A.shape[0]} dof)", hint)
    return Factor(A, perm)


def schur_complement(A: sp.spmatrix, keep: np.ndarray, what: str, hint: str) -> np.ndarray:
    """Dense Schur complement ``A_WW - A_WR A_RR^-1 A_RW`` of the node-major SPD matrix ``A``
    onto the dofs of the nodes ``keep`` (W, node-major, in ``keep``'s order), from one sparse
    factorisation with W ordered last (its memory checked first, as by :func:`factor`).

    ``A`` itself may be singular (a segment that is held only through W): the factorisation is
    of ``A + sigma E_W E_W'``, whose trailing block ``S + sigma I`` has no small pivot
    (``sigma`` the largest diagonal entry of ``A_WW``, above S's largest eigenvalue's scale),
    and ``sigma I`` is taken off again.

    Returns:
        (3w, 3w) symmetric positive semidefinite.
    """
    keep = np.asarray(keep, dtype=np.int64)
    perm, nnz = node_ordering(A, last=keep)
    m = 3 * keep.size
    n = A.shape[0]
    require(factor_bytes(nnz, dense=3 * m * m), f"the Schur complement of {what} onto {m} dof", hint)
    A = sp.csc_matrix(A)[perm][:, perm].tocsc()
    sigma = float(A.diagonal()[n - m :].max()) if m else 0.0
    A = (A + sp.diags(np.r_[np.zeros(n - m), np.full(m, sigma)])).tocsc()
    with threadpool_limits(1):
        lu = spla.splu(A, permc_spec="NATURAL", **_SPLU)
    del A
    pc = lu.perm_c
    # SuperLU post-orders the elimination tree; W stays last when the trailing block is dense
    # (a connected part): checked, since the identity below needs it.
    if not (np.array_equal(lu.perm_r, pc) and np.all(pc[n - m :] >= n - m)):
        raise RuntimeError("schur_complement: the factorisation did not keep the kept dofs last")
    at = pc[n - m :] - (n - m)  # the factor position of each kept dof
    L = lu.L[n - m :, n - m :].toarray()[np.ix_(at, at)]
    U = lu.U[n - m :, n - m :].toarray()[np.ix_(at, at)]
    del lu
    # L_WW U_WW is the trailing block's Schur complement in the factor's order; the rows and
    # columns of both, re-indexed together, give it in W's order.
    S = L @ U
    del L, U
    S[np.diag_indices(m)] -= sigma
    return 0.5 * (S + S.T)
