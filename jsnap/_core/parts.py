"""The deformable part as the contact step sees it: a linear PMI system observed at contact points.

One interface, :class:`AbstractPart`, four models of the same part (chosen when the model is
built, ``solver.method``):

- :class:`FullPart`: the full FEM model on the free nodal dofs (sparse blocks, dense ``S^-1``);
- :class:`ModalPart`: the same equations in the coordinates of all the part's modes (one
  multiply per mode instead of the dense ``S^-1`` pass; Poisson's ratio fixed at build);
- :class:`SegmentedPart`: the mesh cut into a contact segment and the rest, shared nodes
  duplicated and joined by stiff PMI springs (the paper's Model 3);
- :class:`ReducedPart`: each segment on a passive balanced basis, joined exactly through shared
  interface coordinates (the paper's Model 4).

The step (``jsnap._core.step``) never looks inside a part. For the part's state ``(x, v)``
(its own coordinates: free nodal dofs, modal or reduced coordinates) it asks:

- ``prepare(material, dt)``: the parameter-dependent operator (differentiable);
- ``free_velocity(op, x, v)``: the midpoint velocity with no contact force, ``S^-1 (2/T M v - K x)``;
- ``sample_disp(x)``: (P, 3) displacement of every contact candidate point;
- ``stencil_disp(x, idx)``: (C, 8, 3) displacement of the normal stencils of the selected points;
- ``contact_operator(op, idx)``: ``A = J S^-1`` (C, 3, n; or what stands for it, see
  ``contact_velocity``) and the Delassus block ``W = J S^-1 J'`` (C, 3, C, 3);
  parts whose block is a product of thin factors (``factored = True``) also give
  ``contact_factors(op, idx) -> (A, J)``;
- ``contact_velocity(op, A, force)``: the midpoint velocity that forces (C, 3) add;
- ``point_velocity(vbar, idx)``: (C, 3) velocity ``J vbar`` of the selected points;
- ``energy(op, x, v)``, :meth:`AbstractPart.base_wrench` and ``free_displacement(x)``.

Units: mm, N, MPa, s, tonne.
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from jsnap._core.params import Material, lame
from jsnap._core.pmi import PMIOperator, SparseBlocks, energy, pmi_operator, pmi_rhs, spd_inverse

__all__ = [
    "AbstractPart",
    "FullPart",
    "ModalOperator",
    "ModalPart",
    "ReducedOperator",
    "ReducedPart",
    "SegmentedPart",
]


class AbstractPart(eqx.Module):
    """A linear model of the deformable part: its PMI step, its contact points, its outputs.

    Attributes shared by every part:
        out_kl, out_km, out_m1: (6, n) force (N) and moment about the base centroid (N mm) that
            the fixed base exerts per unit of ``K_lam``, ``K_mu`` and ``M1`` action of the
            part's coordinates: the base wrench is a linear output of the state.
        sample_nodes, sample_weights: (P, k) each contact point's interpolating nodes (rows of
            ``nodal``) and its face's shape functions there.
        stencil_nodes, stencil_weights: (P, 8, k) the same for each point's normal stencil.
    """

    out_kl: eqx.AbstractVar[jax.Array]
    out_km: eqx.AbstractVar[jax.Array]
    out_m1: eqx.AbstractVar[jax.Array]
    sample_nodes: eqx.AbstractVar[jax.Array]
    sample_weights: eqx.AbstractVar[jax.Array]
    stencil_nodes: eqx.AbstractVar[jax.Array]
    stencil_weights: eqx.AbstractVar[jax.Array]

    # Whether the Delassus block is offered as thin factors (contact_factors).
    factored: ClassVar[bool] = False

    @property
    @abc.abstractmethod
    def n_dof(self) -> int:
        """Coordinates of the part's state."""

    @abc.abstractmethod
    def prepare(self, material: Material, dt):
        """The operator one step needs for ``material`` and time step ``dt`` (s)."""

    @abc.abstractmethod
    def free_velocity(self, op, x, v):
        """Midpoint velocity without contact force, (n,)."""

    @abc.abstractmethod
    def nodal(self, x):
        """(N, 3): coordinates ``x`` (displacements or velocities) at the nodes that the contact
        points and their stencils interpolate (``sample_nodes``, ``stencil_nodes`` index them).
        For a part whose coordinates are not nodal it is a product with the contact nodes' rows
        (c x 3 x r, a few MB), so a step takes it once per vector and interpolates from it."""

    def sample_disp(self, x):
        """(P, 3) displacement of the contact candidate points, mm."""
        return self.sample_at(self.nodal(x))

    def sample_at(self, xn):
        """(P, 3) the candidate points' values of ``nodal`` values ``xn``."""
        return _interpolate_rows(self.sample_weights, self.sample_nodes, xn)

    def stencil_at(self, xn, idx):
        """(C, 8, 3) the selected points' normal stencils' values of ``nodal`` values ``xn``."""
        return _interpolate_rows(self.stencil_weights[idx], self.stencil_nodes[idx], xn)

    def point_at(self, xn, idx):
        """(C, 3) the selected points' values of ``nodal`` values ``xn``."""
        return _interpolate_rows(self.sample_weights[idx], self.sample_nodes[idx], xn)

    @abc.abstractmethod
    def contact_operator(self, op, idx):
        """``(A, W)``: ``J S^-1`` (or what stands for it) and ``J S^-1 J'`` (C, 3, C, 3)."""

    def contact_factors(self, op, idx):
        """``(A, J)`` (C, 3, r) with ``W = A J'`` (parts with ``factored = True``)."""
        raise NotImplementedError(f"{type(self).__name__} has no factored Delassus block")

    @abc.abstractmethod
    def contact_velocity(self, op, A, force):
        """Midpoint velocity (n,) that forces (C, 3) at the selected points add."""

    @abc.abstractmethod
    def energy(self, op, x, v):
        """Discrete energy ``1/2 v'Mv + 1/2 x'Kx``, N mm."""

    @abc.abstractmethod
    def free_displacement(self, x):
        """(n_free,) displacement at the free dofs of the full mesh, mm."""

    def base_wrench(self, material: Material, dt, x, v, v_new, vbar):
        """Reaction of the fixed base on the part over the step: force (3,) in N and moment (3,)
        in N mm about the base centroid, at the interval's midpoint like the PMI equations
        (inertia, Rayleigh damping and stiffness terms of the base rows)."""
        dtype = x.dtype
        lam, mu = lame(material.E, material.nu)
        ok = (lam * self.out_kl + mu * self.out_km).astype(dtype)
        om = (material.rho * self.out_m1).astype(dtype)
        xbar = x + 0.5 * dt * vbar
        w = om @ ((v_new - v) / dt + material.alpha * vbar) + ok @ (xbar + material.beta * vbar)
        return w[:3], w[3:]


# --------------------------------------------------------------------------------------------
# Full FEM
# --------------------------------------------------------------------------------------------


def _interpolate_rows(w, nodes, rows):
    """(..., ...): ``einsum("...k,...k*->...*", w, rows[nodes])``, the rows of each point's
    ``k`` nodes weighted, as a sum over the k nodes (the last axis of ``w`` and ``nodes``):
    XLA:CPU runs the einsum as C tiny dots, 1.4-10x slower at 16-256 points (and 2.5x at ~600
    points of (3,) rows)."""
    tail = (1,) * (rows.ndim - 1)
    return sum(w[..., k].reshape(w.shape[:-1] + tail) * rows[nodes[..., k]] for k in range(w.shape[-1]))


def _rows_transpose_times(A, force):
    """(r,): ``einsum("cdr,cd->r", A, force)`` as one matrix-vector product, which XLA:CPU runs
    3.5-9x faster than the einsum at 16-256 points."""
    return force.reshape(-1) @ A.reshape(-1, A.shape[-1])


class FullPart(AbstractPart):
    """The full linear FEM model on the free nodal dofs.

    Attributes:
        blocks: free x free parameter-free blocks (n = free dofs).
        out_kl, out_km, out_m1: see :class:`AbstractPart`.
        sample_nodes: (P, k) free-node index of each contact point's interpolating nodes
            (k = 3 for P1 faces, 6 for P2; clamped nodes point at node 0 with weight 0).
        sample_weights: (P, k) the face's shape functions at the point.
        stencil_nodes, stencil_weights: (P, 8, k) the same for each point's normal stencil.
    """

    blocks: SparseBlocks
    out_kl: jax.Array
    out_km: jax.Array
    out_m1: jax.Array
    sample_nodes: jax.Array
    sample_weights: jax.Array
    stencil_nodes: jax.Array
    stencil_weights: jax.Array

    @property
    def n_dof(self) -> int:
        return self.blocks.n_rows

    def prepare(self, material: Material, dt) -> PMIOperator:
        return pmi_operator(self.blocks, material, dt)

    def free_velocity(self, op: PMIOperator, x, v):
        return op.S_inv @ pmi_rhs(self.blocks, op, x, v, jnp.zeros_like(x))

    def nodal(self, x):
        return x.reshape(-1, 3)

    def _dofs(self, idx):
        return 3 * self.sample_nodes[idx][..., None] + jnp.arange(3)  # (C, k, 3)

    def contact_operator(self, op: PMIOperator, idx):
        # Gathering whole node blocks instead runs this faster in isolation but not in the
        # rollout: XLA runs it on the other core beside the dense free-velocity matvec, which
        # with the solve is the step's critical path.
        wk = self.sample_weights[idx]
        dofs = self._dofs(idx)
        A = jnp.einsum("ck,ckdn->cdn", wk, op.S_inv[dofs])  # (C, 3, n)
        W = jnp.einsum("cdekf,ek->cdef", A[:, :, dofs], wk)  # (C, 3, C, 3)
        return A, W

    def contact_velocity(self, op: PMIOperator, A, force):
        return _rows_transpose_times(A, force)

    def energy(self, op: PMIOperator, x, v):
        return energy(self.blocks, op, x, v)

    def free_displacement(self, x):
        return x


# --------------------------------------------------------------------------------------------
# Parts whose coordinates are not nodal
# --------------------------------------------------------------------------------------------


class _ContactNodeRows(AbstractPart):
    """What the parts whose coordinates are not nodal (modal, segmented, reduced) share: they
    see the contact points through the displacement of the contact nodes per unit coordinate.

    Attributes:
        node_rows: (c, 3, r) displacement of the contact nodes (the interpolating nodes of the
            candidate points and of their stencils) per unit coordinate; ``sample_nodes`` and
            ``stencil_nodes`` index its rows.
    """

    node_rows: eqx.AbstractVar[jax.Array]

    def nodal(self, x):
        return jnp.einsum("cdr,r->cd", self.node_rows, x)


@jax.custom_jvp
def _no_derivative(x):
    """``x``, whose derivative is NaN: a parameter the model holds fixed is not differentiable."""
    return x


@_no_derivative.defjvp
def _no_derivative_jvp(primals, tangents):
    (x,), (t,) = primals, tangents
    return x, t * jnp.nan  # linear in t, so that reverse mode gives NaN too


class ModalOperator(eqx.Module):
    """What one modal step needs for one material and time step (derived, differentiable).

    Attributes:
        cinv: (n,) ``1 / c`` per mode.   k: (n,) modal stiffness ``E w``.
        m2t: ``(2/T) rho``.   rho: density (the modal mass).
        G: (c, 3, c, 3) ``J_c S^-1 J_c'`` between the contact nodes' dofs.
        dt: time step T, s.
    """

    cinv: jax.Array
    k: jax.Array
    m2t: jax.Array
    rho: jax.Array
    G: jax.Array
    dt: jax.Array


class ModalPart(_ContactNodeRows):
    """The full FEM model in the coordinates of all its modes: every mode kept, nothing
    approximated.

    With ``K(E, nu0) = E K1`` and ``M = rho M1``, the generalised eigenvectors
    ``K1 phi = w M1 phi`` (``Phi' M1 Phi = I``) diagonalise PMI exactly: in ``x = Phi q``,
    ``v = Phi u`` the step is

        c ubar = (2/T) rho u - E w q + Phi' f,     c = rho (2/T + alpha) + E w (beta + T/2),

    one multiply per mode (Rayleigh damping is diagonal too). ``E, rho, alpha, beta`` and the
    friction stay exact and differentiable; ``nu`` is the basis's: :meth:`prepare` rejects
    another value and the derivative with respect to it is NaN, not a silent zero.

    Attributes:
        w: (n,) eigenvalues of ``K(1, nu0)`` with respect to ``M1``, ascending.
        nu: the Poisson ratio the basis was computed for.
        recon: (n, n) ``Phi``: free-dof displacement per unit modal coordinate (outputs only).
        node_rows, sample_*, stencil_*, out_*: see :class:`_ContactNodeRows`, :class:`AbstractPart`.
    """

    w: jax.Array
    nu: jax.Array
    node_rows: jax.Array
    sample_nodes: jax.Array
    sample_weights: jax.Array
    stencil_nodes: jax.Array
    stencil_weights: jax.Array
    out_kl: jax.Array
    out_km: jax.Array
    out_m1: jax.Array
    recon: jax.Array

    @property
    def n_dof(self) -> int:
        return self.w.shape[0]

    def prepare(self, material: Material, dt) -> ModalOperator:
        """O(c^2 n): no factorisation. Raises (at run time) when ``material.nu`` is not the
        basis's."""
        dt = jnp.asarray(dt, jnp.float64)
        nu = eqx.error_if(
            jnp.asarray(material.nu, jnp.float64),
            jnp.abs(material.nu - self.nu) > 1e-12,
            "the modal part's modes were computed for another Poisson ratio; build the model "
            "with this nu, or use the full part",
        )
        k = material.E * self.w + 0.0 * _no_derivative(nu)
        c = material.rho * (2.0 / dt + material.alpha) + k * (material.beta + 0.5 * dt)
        cinv = 1.0 / c
        G = jnp.einsum("cdn,efn->cdef", self.node_rows * cinv, self.node_rows)
        G = 0.5 * (G + G.transpose(2, 3, 0, 1))
        return ModalOperator(cinv, k, 2.0 * material.rho / dt, material.rho, G, dt)

    def free_velocity(self, op: ModalOperator, x, v):
        return (op.m2t * v - op.k * x) * op.cinv

    def contact_operator(self, op: ModalOperator, idx):
        """``A``: the points' interpolation ``(weights, contact nodes)``, which
        :meth:`contact_velocity` applies as ``S^-1 J'`` without forming ``J S^-1``; ``W`` from
        the contact nodes' ``G``."""
        w, nodes = self.sample_weights[idx], self.sample_nodes[idx]
        Gc = jnp.einsum("ck,ckdgf->cdgf", w, op.G[nodes])  # (C, 3, c, 3)
        W = jnp.einsum("cdekf,ek->cdef", Gc[:, :, nodes], w)
        return (w, nodes), W

    def contact_velocity(self, op: ModalOperator, A, force):
        w, nodes = A
        g = jnp.zeros(self.node_rows.shape[:2], force.dtype).at[nodes].add(w[..., None] * force[:, None, :])
        return op.cinv * jnp.einsum("cdn,cd->n", self.node_rows, g)

    def energy(self, op: ModalOperator, x, v):
        # Modal form: no cancellation in x'Kx for a smooth x.
        return 0.5 * op.rho * (v @ v) + 0.5 * x @ (op.k * x)

    def free_displacement(self, x):
        return self.recon @ x


class ReducedOperator(eqx.Module):
    """What one step of a segmented or reduced part needs for one material and time step.

    The interface springs of a segmented part stay factored (``k_c Dg'Dg``), so that the
    residual of the PMI equations can be formed without the rounding of a dense stiff matrix.

    Attributes:
        S_inv: (r, r) inverse of ``S_r = 2 M_r/T + D_r + (T/2) K_r`` (a segmented part's
            interface springs included: the coupling is eliminated here, once per parameter set).
        S_el: (r, r) ``S_r`` without the interface springs.
        M2T: (r, r) ``(2/T) M_r``.   K_el: (r, r) ``K_r`` without the interface springs, N/mm.
        m: (r, r) ``M_r``, t.
        kc: interface spring stiffness, N/mm (0 for a reduced part: no springs).
        sc: ``b_c + (T/2) k_c``, N s/mm.
        NS: (c, 3, r) ``J_c S_inv`` for the contact nodes: a step's ``J S_inv`` is
            interpolated from it without an (r, r) product.
        dt: time step T, s.
    """

    S_inv: jax.Array
    S_el: jax.Array
    M2T: jax.Array
    K_el: jax.Array
    m: jax.Array
    kc: jax.Array
    sc: jax.Array
    NS: jax.Array
    dt: jax.Array


class _SegmentBlocks(_ContactNodeRows):
    """A part on dense (r, r) parameter-free blocks: the segmented and the reduced part. All
    blocks are parameter-free, so every method is exact and differentiable in the material.

    Attributes:
        kl, km, m1: (r, r) ``V'K_lam V``, ``V'K_mu V``, ``V'M1 V``.
        out_kl, out_km, out_m1: see :class:`AbstractPart`.
        node_rows, sample_*, stencil_*: see :class:`_ContactNodeRows`.
        orders: static, a description of the coordinates (see the subclasses); they add up to r.
    """

    kl: jax.Array
    km: jax.Array
    m1: jax.Array
    out_kl: jax.Array
    out_km: jax.Array
    out_m1: jax.Array
    node_rows: jax.Array
    sample_nodes: jax.Array
    sample_weights: jax.Array
    stencil_nodes: jax.Array
    stencil_weights: jax.Array
    orders: tuple[int, ...] = eqx.field(static=True)

    factored: ClassVar[bool] = True

    def _springs(self):
        """``(Dg (3p, r), k_c, b_c)`` of stiff springs joining copies of shared nodes, or None."""
        return None

    @property
    def n_dof(self) -> int:
        return self.kl.shape[0]

    def stiffness(self, material: Material):
        """(r, r) stiffness ``K_r`` of the part's coordinates, interface springs included, N/mm."""
        lam, mu = lame(material.E, material.nu)
        K = lam * self.kl + mu * self.km
        springs = self._springs()
        if springs is not None:
            Dg, kc, _ = springs
            K = K + kc * (Dg.T @ Dg)
        return K

    def prepare(self, material: Material, dt) -> ReducedOperator:
        """One dense inverse of (r, r), differentiable with respect to every field of
        ``material``; interface springs, if any, are folded into ``S_r``."""
        dt = jnp.asarray(dt, jnp.float64)
        lam, mu = lame(material.E, material.nu)
        K_el = lam * self.kl + mu * self.km
        M = material.rho * self.m1
        S_el = 2.0 * M / dt + material.alpha * M + material.beta * K_el + 0.5 * dt * K_el
        springs = self._springs()
        if springs is None:
            kc = sc = jnp.zeros((), jnp.float64)
            S = S_el
        else:
            Dg, kc, bc = springs
            sc = bc + 0.5 * dt * kc
            S = S_el + sc * (Dg.T @ Dg)
        S_inv = spd_inverse(S)
        NS = jnp.einsum("cdr,rs->cds", self.node_rows, S_inv)
        return ReducedOperator(S_inv, S_el, (2.0 / dt) * M, K_el, M, kc, sc, NS, dt)

    def free_velocity(self, op: ReducedOperator, x, v):
        """``S_r^-1 ((2/T) M_r v - K_r x)`` with one step of iterative refinement whose residual
        is formed from the blocks (springs factored): a computed ``S_inv`` is the exact inverse
        of a nearby ``S + dS``, and that fixed ``dS`` would act as a spurious damping or
        anti-damping that drifts the energy linearly in the steps."""
        rhs = op.M2T @ v - op.K_el @ x
        springs = self._springs()
        if springs is not None:
            Dg = springs[0]
            rhs = rhs - op.kc * (Dg.T @ (Dg @ x))
        vbar = op.S_inv @ rhs
        res = rhs - op.S_el @ vbar
        if springs is not None:
            res = res - op.sc * (Dg.T @ (Dg @ vbar))
        return vbar + op.S_inv @ res

    def contact_factors(self, op: ReducedOperator, idx):
        """``A = J S^-1`` and ``J`` (C, 3, r), interpolated from the contact nodes'
        precomputed rows: the Delassus block is ``A J'``. O(C k r) per step."""
        w, nodes = self.sample_weights[idx], self.sample_nodes[idx]
        return _interpolate_rows(w, nodes, op.NS), _interpolate_rows(w, nodes, self.node_rows)

    def contact_operator(self, op: ReducedOperator, idx):
        A, J = self.contact_factors(op, idx)
        return A, jnp.einsum("cdr,efr->cdef", A, J)

    def contact_velocity(self, op: ReducedOperator, A, force):
        return _rows_transpose_times(A, force)

    def energy(self, op: ReducedOperator, x, v):
        """``1/2 v'M_r v + 1/2 x'K_r x`` (with the interface springs' energy), N mm."""
        e = 0.5 * v @ (op.m @ v) + 0.5 * x @ (op.K_el @ x)
        springs = self._springs()
        if springs is not None:
            gap = springs[0] @ x
            e = e + 0.5 * op.kc * gap @ gap
        return e


class SegmentedPart(_SegmentBlocks):
    """The paper's Model 3: every segment keeps its nodal dofs (no reduction); the copies of
    the nodes that segments share are joined by stiff PMI spring-dampers ``(k_c, b_c)``.
    The state ``x`` (r,) stacks every segment's nodal dofs.

    Attributes:
        coupling_rows: (3p, r) ``Dg``: the gap of each joined pair of copies, per component.
        coupling: (2,) interface spring stiffness k_c (N/mm) and damping b_c (N s/mm).
        recon_index: (n_free,) coordinate of each free dof of the full mesh (one copy of each).
        orders: dofs per segment (segment 0 is the contact segment).
        Others: see :class:`_SegmentBlocks`.
    """

    coupling_rows: jax.Array = eqx.field(kw_only=True)
    coupling: jax.Array = eqx.field(kw_only=True)
    recon_index: jax.Array = eqx.field(kw_only=True)

    def _springs(self):
        return self.coupling_rows, self.coupling[0], self.coupling[1]

    def free_displacement(self, x):
        return x[self.recon_index]


class ReducedPart(_SegmentBlocks):
    """The paper's Model 4: the part's displacement ``x = V z`` on a passive balanced
    Craig-Bampton basis (a one-sided congruence, so PMI stays passive for every parameter set).
    The segments share their interface coordinates, so they are joined exactly: no springs.

    Attributes:
        recon: (n_free, r) free-dof displacement of the full mesh per unit coordinate.
        orders: interface shapes, then the interior coordinates of each segment (segment 0 is
            the contact segment); the coordinates themselves mix them (mass-orthonormal).
        Others: see :class:`_SegmentBlocks`.
    """

    recon: jax.Array = eqx.field(kw_only=True)

    def free_displacement(self, x):
        return self.recon @ x
