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
a 270-dof P1 arm, ~1e-6 on a 1458-dof P2 arm; docs/status.md). Two remedies, both the same
discrete equations:

* ``pmi_step(..., refine=1)``: one step of iterative refinement with the residual
  ``rhs - (2M/T + D + T/2 K) vbar`` formed from the sparse blocks (not from S): the fixed
  ``dS`` is gone, what is left is the rounding of the residual (30 to 700 times smaller);
* the modal form (``modal_basis``, ``modal_operator``, ``modal_step``): with mass-normalised
  eigenvectors the equations decouple into independent scalar recurrences per mode, whose
  energy is conserved to a few eps per step with no amplification by the frequency spread.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from jsnap._build.fem import lame

__all__ = [
    "Material",
    "ModalBasis",
    "ModalOperator",
    "PMIOperator",
    "SparseBlocks",
    "energy",
    "from_modal",
    "modal_basis",
    "modal_energy",
    "modal_force",
    "modal_operator",
    "modal_step",
    "pmi_operator",
    "pmi_step",
    "to_modal",
]


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


# Below this order the dense inverse stays in XLA: the host call's overhead is not worth it.
_HOST_INVERSE_MIN = 512
# Rows per block when the host route symmetrises S and mirrors the inverse: a whole-matrix
# transpose strides over memory (XLA's on the default mesh's order 5742: 0.5-1.0 s for the mirror,
# 0.3-0.7 s for the symmetric part; by blocks of rows in NumPy ~0.07 s each).
_BLOCK = 512


def _symmetrise_upper(a):
    """In place, by blocks of rows: the upper triangle of ``a`` becomes that of ``(a + a')/2``
    (bit for bit XLA's ``0.5 * (S + S.T)``); the strict lower one is left as it was."""
    n = a.shape[0]
    for i in range(0, n, _BLOCK):
        j = min(i + _BLOCK, n)
        d = a[i:j, i:j]
        d[...] = 0.5 * (d + d.T)
        a[i:j, j:] = 0.5 * (a[i:j, j:] + a[j:, i:j].T)


def _mirror_upper(a):
    """In place: the strict lower triangle from the upper one, by blocks of rows."""
    n = a.shape[0]
    for i in range(0, n, _BLOCK):
        j = min(i + _BLOCK, n)
        d = a[i:j, i:j]
        d[...] = np.triu(d) + np.triu(d, 1).T
        a[j:, i:j] = a[i:j, j:].T


def _host_spd_inverse(S):
    """LAPACK potrf + potri on the host (scipy's LAPACK, the one XLA:CPU calls as well): n^3
    flops, against 7n^3/3 for a Cholesky followed by two triangular solves with n right-hand
    sides, which is how XLA inverts. 5742 dof, 2 cores: 3.1 s against 5.0 s. LAPACK works in
    place on the transposed (column-major) view of one copy of S, symmetrised and mirrored there
    by blocks (``_BLOCK``). A matrix that is not positive definite gives NaN, as
    ``jnp.linalg.cholesky`` does."""

    def host(s):
        a = np.array(s, order="C")  # the callback's buffer is read-only: one copy, worked in place
        _symmetrise_upper(a)
        f = a.T  # column-major: LAPACK takes it without a copy; its lower triangle is a's upper
        potrf, potri = sla.get_lapack_funcs(("potrf", "potri"), (f,))
        c, info = potrf(f, lower=True, overwrite_a=True, clean=False)
        if info == 0:
            c, info = potri(c, lower=True, overwrite_c=True)
        if info != 0:
            return np.full(a.shape, np.nan, a.dtype)
        out = c.T  # row-major again; potri filled the upper triangle (in this view) only
        _mirror_upper(out)
        return out

    return jax.pure_callback(host, jax.ShapeDtypeStruct(S.shape, S.dtype), S, vmap_method="sequential")


def _xla_spd_inverse(S):
    S = 0.5 * (S + S.T)
    chol = jnp.linalg.cholesky(S)
    S_inv = jax.scipy.linalg.cho_solve((chol, True), jnp.eye(S.shape[0], dtype=S.dtype))
    return 0.5 * (S_inv + S_inv.T)


@jax.custom_jvp
def spd_inverse(S):
    """Inverse of the symmetric part ``(S + S')/2`` of ``S``, which must be positive definite;
    symmetric to the last bit. On the CPU, from order ``_HOST_INVERSE_MIN`` up, by LAPACK's
    potri (2.3x fewer flops than XLA's route); elsewhere by XLA's Cholesky. Differentiable:
    ``d(S^-1) = -S^-1 sym(dS) S^-1``; batches under ``vmap`` one matrix at a time."""
    if S.shape[-1] < _HOST_INVERSE_MIN:
        return _xla_spd_inverse(S)
    return jax.lax.platform_dependent(S, cpu=_host_spd_inverse, default=_xla_spd_inverse)


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


# --------------------------------------------------------------------------------------------
# Modal (diagonalised) PMI
# --------------------------------------------------------------------------------------------


class ModalBasis(eqx.Module):
    """Eigenvectors of the unit-parameter pencil ``K(E=1, nu) phi = lam M1 phi``.

    They depend on ``nu`` only: ``K(E, nu) = E K(1, nu)`` and ``M = rho M1``, so the modes of
    any (E, rho) are ``phi / sqrt(rho)`` with ``omega^2 = E lam / rho``. Gradients with respect
    to E and rho therefore never pass through the eigensolver; those with respect to nu do
    (``jnp.linalg.eigh``, whose derivative needs distinct eigenvalues: true for the arms
    here, smallest relative gap 7e-5 on the 1458-dof P2 arm).

    Attributes:
        phi: (n, r) eigenvectors with ``phi' M1 phi = I``, mm^-3/2.
        lam: (r,) eigenvalues in ascending order, 1/mm^2.
        nu: scalar Poisson's ratio they were computed for.
    """

    phi: jax.Array
    lam: jax.Array
    nu: jax.Array


def modal_basis(blocks: SparseBlocks, nu, n_modes: int | None = None) -> ModalBasis:
    """The lowest ``n_modes`` (static; default all n) modes for Poisson's ratio ``nu``.

    Cost: a dense symmetric eigendecomposition (n^3), differentiable with respect to ``nu``.
    Compute it once and pass it to :func:`modal_operator` to batch or differentiate over
    (E, rho, alpha, beta) cheaply. ``n_modes < n`` is the PMI of the Galerkin projection onto
    the lowest modes (a one-sided congruence: passive, but no longer the full model).
    """
    nu = jnp.asarray(nu, jnp.float64)
    lam_1, mu_1 = lame(1.0, nu)
    K1 = blocks.dense(lam_1 * blocks.kl + mu_1 * blocks.km)
    M1 = blocks.dense(blocks.m1)
    # Generalised -> standard symmetric problem with M1 = L L' (M1 is parameter-free).
    L = jnp.linalg.cholesky(0.5 * (M1 + M1.T))
    solve_l = jax.scipy.linalg.solve_triangular
    A = solve_l(L, solve_l(L, 0.5 * (K1 + K1.T), lower=True).T, lower=True)
    lam, U = jnp.linalg.eigh(0.5 * (A + A.T))
    phi = solve_l(L.T, U, lower=False)
    if n_modes is not None:
        if not 1 <= n_modes <= lam.shape[0]:
            raise ValueError(f"n_modes = {n_modes}: must be in 1..{lam.shape[0]}")
        lam, phi = lam[:n_modes], phi[:, :n_modes]
    return ModalBasis(phi, lam, nu)


class ModalOperator(eqx.Module):
    """Modal PMI for one material and time step: x = phi q, v = phi p.

    With ``phi' M phi = I``, ``phi' K phi = diag(omega2)`` and Rayleigh damping
    ``phi' D phi = diag(alpha + beta omega2)``, PMI decouples exactly into one scalar
    recurrence per mode (see :func:`modal_step`).

    Attributes:
        phi: (n, r) mass-normalised modes (``phi' M phi = I``), t^-1/2 (q is in t^1/2 mm).
        omega2: (r,) squared angular frequencies, 1/s^2.
        zeta2w: (r,) modal damping ``alpha + beta omega2`` (= 2 zeta omega), 1/s.
        c: (r,) modal ``S = 2/T + zeta2w + T/2 omega2``, 1/s.
        k, m, d: (nnz,) K, M, D data on the blocks' pattern, so that :func:`energy` and
            :func:`to_modal` work in physical coordinates.
        dt: scalar time step T, s.
    """

    phi: jax.Array
    omega2: jax.Array
    zeta2w: jax.Array
    c: jax.Array
    k: jax.Array
    m: jax.Array
    d: jax.Array
    dt: jax.Array

    def astype(self, dtype) -> ModalOperator:
        """The same operator in another float dtype."""
        return jax.tree_util.tree_map(lambda a: a.astype(dtype), self)


def modal_operator(blocks: SparseBlocks, mat: Material, dt, basis: ModalBasis | None = None) -> ModalOperator:
    """Build the modal PMI operator for ``mat`` and time step ``dt`` (s).

    Args:
        basis: from :func:`modal_basis` for ``mat.nu`` (checked under jit); computed here when
            omitted (then gradients with respect to ``mat.nu`` flow through the eigensolver).
    """
    if basis is None:
        basis = modal_basis(blocks, mat.nu)
    rho = eqx.error_if(
        mat.rho,
        jnp.abs(basis.nu - mat.nu) > 1e-12 * jnp.abs(mat.nu),
        "modal_operator: the basis was computed for another Poisson's ratio than mat.nu",
    )
    dt = jnp.asarray(dt, jnp.float64)
    k, m, d = system_data(blocks, mat)
    omega2 = mat.E * basis.lam / rho
    zeta2w = mat.alpha + mat.beta * omega2
    c = 2.0 / dt + zeta2w + 0.5 * dt * omega2
    return ModalOperator(basis.phi / jnp.sqrt(rho), omega2, zeta2w, c, k, m, d, dt)


def to_modal(blocks: SparseBlocks, op: ModalOperator, x):
    """Modal coordinates ``phi' M x`` (r,) of a physical displacement (mm) or velocity (mm/s)
    (n,). Exact for r = n; the M-orthogonal projection onto the kept modes otherwise."""
    return op.phi.T @ blocks.matvec(op.m, x)


def modal_force(op: ModalOperator, f):
    """Modal load ``phi' f`` (r,) of a nodal load f (n,) in N."""
    return op.phi.T @ f


def from_modal(op: ModalOperator, q):
    """Physical vector ``phi q`` (n,): displacement (mm) from q, velocity (mm/s) from p."""
    return op.phi @ q


def modal_step(op: ModalOperator, q, p, g):
    """One PMI step in modal coordinates: for every mode i, independently,

        c_i pbar_i = (2/T) p_i - omega2_i q_i + g_i,   q_i += T pbar_i,   p_i = 2 pbar_i - p_i,

    which is exactly ``S vbar = (2/T) M v - K x + f`` premultiplied by phi'. q, p, g: (r,)
    (``g = phi' f``). Returns (q_next, p_next, pbar). Cost O(r) per step (plus ``phi @ q``
    when physical outputs are needed).
    """
    pbar = ((2.0 / op.dt) * p - op.omega2 * q + g) / op.c
    return q + op.dt * pbar, 2.0 * pbar - p, pbar


def modal_energy(op: ModalOperator, q, p):
    """Discrete energy ``1/2 |p|^2 + 1/2 sum omega2 q^2`` (N·mm): the physical
    ``1/2 v'Mv + 1/2 x'Kx`` of ``x = phi q, v = phi p``, without the cancellation that makes
    ``x'Kx`` lose ``(omega_max / omega_1)^2`` eps for a smooth x."""
    return 0.5 * (p @ p) + 0.5 * (op.omega2 * q) @ q
