"""Passive midpoint integration (PMI) of linear second-order systems, as pure JAX kernels.

For ``M a + D v + K x = f`` with the midpoint velocity ``vbar = (v_k + v_{k+1}) / 2`` as the
unknown, one step is one solve with a constant matrix (no iteration):

    S vbar = (2/T) M v_k - K x_k + f,      S = 2M/T + D + (T/2) K,
    v_{k+1} = 2 vbar - v_k,                x_{k+1} = x_k + T vbar.

The discrete energy ``E = 1/2 v'Mv + 1/2 x'Kx`` then obeys, exactly,
``E_{k+1} - E_k = T vbar'f - T vbar'D vbar``: with D = 0 and f = 0 it is conserved for any T
and any stiffness, and damping can only remove energy.

Matrices are stored as COO data on one shared sparsity pattern (``row``, ``col``) with the
parameter-free blocks K_lam, K_mu, M1, so that ``K = lambda K_lam + mu K_mu`` etc. are
differentiable functions of the material. Units: mm, N, MPa, s, tonne.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from jsnap._fem import lame

__all__ = ["Material", "PMIOperator", "SparseBlocks", "energy", "pmi_operator", "pmi_step"]


class SparseBlocks(eqx.Module):
    """Parameter-free blocks of a linear elastic system on one COO pattern.

    Attributes:
        row, col: (nnz,) int32 indices into a (n_rows, n_cols) matrix.
        kl, km, m1: (nnz,) data of K_lam, K_mu (MPa^-1 N/mm per MPa) and M1 (mm^3).
        n_rows, n_cols: static shape.
    """

    row: jax.Array
    col: jax.Array
    kl: jax.Array
    km: jax.Array
    m1: jax.Array
    n_rows: int = eqx.field(static=True)
    n_cols: int = eqx.field(static=True)

    @classmethod
    def from_scipy(cls, K_lam, K_mu, M1) -> SparseBlocks:
        """From three scipy matrices that share one sparsity pattern (see ``_fem``)."""
        a, b, c = (sp.coo_matrix(m) for m in (K_lam, K_mu, M1))
        if not (np.array_equal(a.row, b.row) and np.array_equal(a.row, c.row)):
            raise ValueError("SparseBlocks: the three blocks must share one sparsity pattern")
        if not (np.array_equal(a.col, b.col) and np.array_equal(a.col, c.col)):
            raise ValueError("SparseBlocks: the three blocks must share one sparsity pattern")
        order = np.lexsort((a.col, a.row))
        return cls(
            jnp.asarray(a.row[order], jnp.int32),
            jnp.asarray(a.col[order], jnp.int32),
            jnp.asarray(a.data[order]),
            jnp.asarray(b.data[order]),
            jnp.asarray(c.data[order]),
            a.shape[0],
            a.shape[1],
        )

    def matvec(self, data: jax.Array, x: jax.Array) -> jax.Array:
        """(data on this pattern) @ x, for x (n_cols,) -> (n_rows,)."""
        return jax.ops.segment_sum(
            data * x[self.col], self.row, num_segments=self.n_rows, indices_are_sorted=True
        )

    def dense(self, data: jax.Array) -> jax.Array:
        """Dense (n_rows, n_cols) matrix of ``data`` on this pattern."""
        out = jnp.zeros((self.n_rows, self.n_cols), data.dtype)
        return out.at[self.row, self.col].add(data)


class Material(eqx.Module):
    """Material parameters, each a scalar array (traced: differentiable and batchable).

    Attributes:
        E: Young's modulus, MPa.
        nu: Poisson's ratio.
        rho: density, t/mm^3.
        alpha: Rayleigh mass-proportional damping, 1/s.
        beta: Rayleigh stiffness-proportional damping, s.
    """

    E: jax.Array
    nu: jax.Array
    rho: jax.Array
    alpha: jax.Array
    beta: jax.Array

    @classmethod
    def create(cls, E, nu, rho, alpha=0.0, beta=0.0) -> Material:
        return cls(*(jnp.asarray(v, jnp.float64) for v in (E, nu, rho, alpha, beta)))


class PMIOperator(eqx.Module):
    """What one PMI step needs for one material and time step (derived, differentiable).

    Attributes:
        S_inv: (n, n) inverse of S = 2M/T + D + (T/2) K, mm/(N s).
        k, m, d: (nnz,) data of K (N/mm), M (t) and D (N s/mm) on the blocks' pattern.
        dt: scalar time step T, s.
    """

    S_inv: jax.Array
    k: jax.Array
    m: jax.Array
    d: jax.Array
    dt: jax.Array

    def astype(self, dtype) -> PMIOperator:
        """The same operator in another float dtype (float32 for fast rollouts)."""
        return jax.tree_util.tree_map(lambda a: a.astype(dtype), self)


def system_data(blocks: SparseBlocks, mat: Material):
    """K, M, D data (nnz,) for ``mat`` on the blocks' pattern."""
    lam, mu = lame(mat.E, mat.nu)
    k = lam * blocks.kl + mu * blocks.km
    m = mat.rho * blocks.m1
    d = mat.alpha * m + mat.beta * k
    return k, m, d


def pmi_operator(blocks: SparseBlocks, mat: Material, dt) -> PMIOperator:
    """Build the PMI operator (float64) for ``mat`` and time step ``dt`` (s).

    Cost: one dense Cholesky factorisation and inverse of S (n^3); differentiable with respect
    to every field of ``mat``.
    """
    dt = jnp.asarray(dt, jnp.float64)
    k, m, d = system_data(blocks, mat)
    S = blocks.dense(2.0 * m / dt + d + 0.5 * dt * k)
    S = 0.5 * (S + S.T)
    chol = jnp.linalg.cholesky(S)
    eye = jnp.eye(S.shape[0], dtype=S.dtype)
    S_inv = jax.scipy.linalg.cho_solve((chol, True), eye)
    return PMIOperator(0.5 * (S_inv + S_inv.T), k, m, d, dt)


def pmi_rhs(blocks: SparseBlocks, op: PMIOperator, x, v, f):
    """Right-hand side (2/T) M v - K x + f, N."""
    return (2.0 / op.dt) * blocks.matvec(op.m, v) - blocks.matvec(op.k, x) + f


def pmi_step(blocks: SparseBlocks, op: PMIOperator, x, v, f):
    """One PMI step. x, v, f: (n,) in mm, mm/s, N. Returns (x_next, v_next, vbar)."""
    vbar = op.S_inv @ pmi_rhs(blocks, op, x, v, f)
    return x + op.dt * vbar, 2.0 * vbar - v, vbar


def energy(blocks: SparseBlocks, op: PMIOperator, x, v):
    """Discrete energy 1/2 v'Mv + 1/2 x'Kx, N·mm (= mJ)."""
    return 0.5 * v @ blocks.matvec(op.m, v) + 0.5 * x @ blocks.matvec(op.k, x)
