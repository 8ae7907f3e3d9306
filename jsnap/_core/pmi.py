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

Round-off. A factorised or inverted S is, in floating point, the exact inverse of a nearby
``S + dS`` with a small, fixed, indefinite ``dS`` (1e-14..2e-13 of |S| measured). The recurrence then integrates
the system with a spurious damping ``dS``: every step changes the energy by
``-T vbar' dS vbar``, which keeps its sign on a trajectory that keeps returning to the same
modes, so the energy drifts *linearly* in the number of steps (after 1e5 steps: 1e-8..6e-8 on
a 270-dof P1 arm, ~1e-6 on a 1458-dof P2 arm; docs/validation.md). Two remedies, both the same
discrete equations:

* ``pmi_step(..., refine=1)``: one step of iterative refinement with the residual
  ``rhs - (2M/T + D + T/2 K) vbar`` formed from the sparse blocks (not from S): the fixed
  ``dS`` is gone, what is left is the rounding of the residual (30 to 700 times smaller);
* the modal form (:class:`jsnap._core.parts.ModalPart`): with mass-normalised eigenvectors
  the equations decouple into independent scalar recurrences per mode, whose energy is
  conserved to a few eps per step with no amplification by the frequency spread.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from jsnap._core.params import Material, lame

__all__ = ["PMIOperator", "SparseBlocks", "energy", "pmi_operator", "pmi_rhs", "pmi_step", "spd_inverse"]


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

    def matvec(self, data: jax.Array, x: jax.Array) -> jax.Array:
        """(data on this pattern) @ x, for x (n_cols,) -> (n_rows,)."""
        return jax.ops.segment_sum(
            data * x[self.col], self.row, num_segments=self.n_rows, indices_are_sorted=True
        )

    def dense(self, data: jax.Array) -> jax.Array:
        """Dense (n_rows, n_cols) matrix of ``data`` on this pattern."""
        out = jnp.zeros((self.n_rows, self.n_cols), data.dtype)
        return out.at[self.row, self.col].add(data)


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


@jax.custom_jvp
def spd_inverse(S):
    """Inverse of the symmetric part ``(S + S')/2`` of ``S``, which must be positive definite
    (else NaN), by Cholesky: symmetric to the last bit. Differentiable:
    ``d(S^-1) = -S^-1 sym(dS) S^-1``; batches under ``vmap``."""
    S = 0.5 * (S + S.T)
    chol = jnp.linalg.cholesky(S)
    S_inv = jax.scipy.linalg.cho_solve((chol, True), jnp.eye(S.shape[0], dtype=S.dtype))
    return 0.5 * (S_inv + S_inv.T)


@spd_inverse.defjvp
def _spd_inverse_jvp(primals, tangents):
    (S,), (dS,) = primals, tangents
    X = spd_inverse(S)
    return X, -X @ (0.5 * (dS + dS.T)) @ X


def pmi_operator(blocks: SparseBlocks, mat: Material, dt) -> PMIOperator:
    """Build the PMI operator (float64) for ``mat`` and time step ``dt`` (s).

    Cost: one dense inverse of S (``spd_inverse``, n^3); differentiable with respect
    to every field of ``mat``.
    """
    dt = jnp.asarray(dt, jnp.float64)
    k, m, d = system_data(blocks, mat)
    S = blocks.dense(2.0 * m / dt + d + 0.5 * dt * k)
    return PMIOperator(spd_inverse(S), k, m, d, dt)


def pmi_rhs(blocks: SparseBlocks, op: PMIOperator, x, v, f):
    """Right-hand side (2/T) M v - K x + f, N."""
    return (2.0 / op.dt) * blocks.matvec(op.m, v) - blocks.matvec(op.k, x) + f


def pmi_step(blocks: SparseBlocks, op: PMIOperator, x, v, f, refine: int = 0):
    """One PMI step. x, v, f: (n,) in mm, mm/s, N. Returns (x_next, v_next, vbar).

    ``refine`` (static) steps of iterative refinement, each one more dense and three sparse
    matvecs: the residual is formed from the sparse K, M, D rather than from ``S_inv``, which
    removes the energy drift caused by the rounding of S's factorisation (module docstring).
    """
    rhs = pmi_rhs(blocks, op, x, v, f)
    vbar = op.S_inv @ rhs
    for _ in range(refine):
        s_vbar = (
            (2.0 / op.dt) * blocks.matvec(op.m, vbar)
            + blocks.matvec(op.d, vbar)
            + (0.5 * op.dt) * blocks.matvec(op.k, vbar)
        )
        vbar = vbar + op.S_inv @ (rhs - s_vbar)
    return x + op.dt * vbar, 2.0 * vbar - v, vbar


def energy(blocks: SparseBlocks, op: PMIOperator, x, v):
    """Discrete energy 1/2 v'Mv + 1/2 x'Kx, N·mm (= mJ)."""
    return 0.5 * v @ blocks.matvec(op.m, v) + 0.5 * x @ blocks.matvec(op.k, x)
