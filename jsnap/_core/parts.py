"""The socket as the contact step sees it: a linear PMI system observed at contact points.

The whole-scene kernel (``_sim.step``) never looks inside the socket's model. It needs, for the
socket's state ``(x, v)`` (generalised coordinates: free nodal dofs for the full model, modal
or reduced coordinates otherwise):

- ``prepare(material, dt)``: the parameter-dependent operator (differentiable);
- ``free_velocity(op, x, v)``: the midpoint velocity with no contact force, ``S^-1 (2/T M v - K x)``;
- ``sample_disp(x)``: (P, 3) displacement of every contact candidate point;
- ``stencil_disp(x, idx)``: (C, 8, 3) displacement of the normal stencils of each selected point
  (the deformed socket normal, see ``_model._section_samples``);
- ``contact_operator(op, idx)``: ``A = J S^-1`` (C, 3, n; or what stands for it, see
  ``contact_velocity``) and the Delassus block ``W = J S^-1 J'`` (C, 3, C, 3) for the selected
  points; a socket whose block is a product of two thin factors (the reduced one, ``W = A J'``
  with r columns) may offer ``contact_factors(op, idx) -> (A, J)`` as well, and while r is small
  enough the step turns the factors into the contact frames, not the (C, 3, C, 3) block
  (``_sim._local_operator``);
- ``contact_velocity(op, A, force)``: ``A' force``, the midpoint velocity that forces (C, 3) at
  the selected points add;
- ``point_velocity(vbar, idx)``: (C, 3) velocity ``J vbar`` of the selected points;
- ``energy(op, x, v)`` and ``base_wrench(op, material, x, v, v_new, vbar)``;
- ``free_displacement(x)``: displacement at the free dofs of the full mesh (outputs, viewer).

:class:`FullSocket` is the full FEM model (sparse blocks, dense S^-1). The same model in modal
coordinates (``_modal``) and reduced models (``_reduce``) implement the same methods.
Units: mm, N, MPa, s, tonne.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from jsnap._build.fem import lame
from jsnap._core.pmi import Material, PMIOperator, SparseBlocks, energy, pmi_operator, pmi_rhs

__all__ = ["ContactRows", "FullSocket"]


class ContactRows(eqx.Module):
    """What the sockets whose coordinates are not nodal (modal, reduced) share: they see the
    contact points through the displacement of the contact nodes per unit coordinate.

    Attributes:
        node_rows: (c, 3, r) displacement of the contact nodes (the interpolating nodes of the
            candidate points and of their stencils) per unit coordinate.
        sample_nodes, sample_weights: (P, k) indices into ``node_rows`` and shape functions.
        stencil_nodes, stencil_weights: (P, 8, k) the same for the normal stencils.
    """

    node_rows: jax.Array
    sample_nodes: jax.Array
    sample_weights: jax.Array
    stencil_nodes: jax.Array
    stencil_weights: jax.Array

    def _nodes(self, x):
        return jnp.einsum("cdr,r->cd", self.node_rows, x)

    def sample_disp(self, x):
        # A sum over the k nodes, not einsum("pk,pkd->pd"): XLA:CPU runs that as P tiny dots,
        # 2.5x slower at ~600 points (the step calls this twice).
        xn, w, nodes = self._nodes(x), self.sample_weights, self.sample_nodes
        return sum(w[:, k, None] * xn[nodes[:, k]] for k in range(w.shape[1]))

    def stencil_disp(self, x, idx):
        xn = self._nodes(x)
        return jnp.einsum("csk,cskd->csd", self.stencil_weights[idx], xn[self.stencil_nodes[idx]])

    def point_velocity(self, vbar, idx):
        return jnp.einsum("ck,ckd->cd", self.sample_weights[idx], self._nodes(vbar)[self.sample_nodes[idx]])


class FullSocket(eqx.Module):
    """Full linear FEM socket.

    Attributes:
        blocks: free x free parameter-free blocks (n = free dofs).
        reaction: fixed x free blocks, for the base wrench.
        base_offsets: (nb, 3) base node positions minus the base centroid, mm.
        sample_nodes: (P, k) free-node index of each contact point's interpolating nodes
            (k = 3 for P1 faces, 6 for P2; clamped nodes point at node 0 with weight 0).
        sample_weights: (P, k) the face's shape functions at the point.
        stencil_nodes, stencil_weights: (P, 8, k) the same for each point's normal stencil.
    """

    blocks: SparseBlocks
    reaction: SparseBlocks
    base_offsets: jax.Array
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

    def sample_disp(self, x):
        xn = x.reshape(-1, 3)
        return jnp.einsum("pk,pkd->pd", self.sample_weights, xn[self.sample_nodes])

    def stencil_disp(self, x, idx):
        xn = x.reshape(-1, 3)
        return jnp.einsum("csk,cskd->csd", self.stencil_weights[idx], xn[self.stencil_nodes[idx]])

    def _dofs(self, idx):
        return 3 * self.sample_nodes[idx][..., None] + jnp.arange(3)  # (C, k, 3)

    def contact_operator(self, op: PMIOperator, idx):
        # Gathering whole node blocks instead (S^-1's three rows of a node for A, A's three
        # columns of a node for W) runs this 3-12x faster in a scan of its own (float64 8.2 ->
        # 2.5 ms, float32 5.6 -> 0.45 ms on the default scene) but not the rollout (float32
        # 17.7-19.7 against 16.8-17.6 ms per step, side by side): XLA runs it on the other core
        # beside the dense free-velocity matvec, which with the solve is the step's critical path.
        wk = self.sample_weights[idx]
        dofs = self._dofs(idx)
        A = jnp.einsum("ck,ckdn->cdn", wk, op.S_inv[dofs])  # (C, 3, n)
        W = jnp.einsum("cdekf,ek->cdef", A[:, :, dofs], wk)  # (C, 3, C, 3)
        return A, W

    def contact_velocity(self, op: PMIOperator, A, force):
        """``A' force``: the midpoint velocity that point forces (C, 3) add."""
        return jnp.einsum("cdn,cd->n", A, force)

    def point_velocity(self, vbar, idx):
        return jnp.einsum("ck,ckd->cd", self.sample_weights[idx], vbar.reshape(-1, 3)[self.sample_nodes[idx]])

    def energy(self, op: PMIOperator, x, v):
        return energy(self.blocks, op, x, v)

    def base_wrench(self, op: PMIOperator, material: Material, x, v, v_new, vbar):
        """Reaction of the fixed base on the socket over the step (force N, moment N mm about
        the base centroid), evaluated at the interval's midpoint like the PMI equations."""
        r = self.reaction
        dtype = x.dtype
        lam, mu = lame(material.E, material.nu)
        rk = (lam * r.kl + mu * r.km).astype(dtype)
        rm = (material.rho * r.m1).astype(dtype)
        T = op.dt
        xbar = x + 0.5 * T * vbar
        react = (
            r.matvec(rm, (v_new - v) / T)
            + r.matvec(material.alpha * rm + material.beta * rk, vbar)
            + r.matvec(rk, xbar)
        ).reshape(-1, 3)
        moment = jnp.cross(self.base_offsets.astype(dtype), react).sum(axis=0)
        return react.sum(axis=0), moment

    def free_displacement(self, x):
        return x
