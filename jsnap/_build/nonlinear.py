"""Host side of the St. Venant–Kirchhoff reference: its model from an assembly, and the snap
release scenario of the stability benchmark. The kernels are in :mod:`jsnap._core.nonlinear`.

Units: mm, N, MPa, s, tonne.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import skfem

from jsnap._build.fem import Assembly, assemble, solve_static, sparse_blocks, traction_load
from jsnap._core.nonlinear import SVKModel, static_deflection
from jsnap._core.params import Material
from jsnap._geometry.cantilever import Cantilever, mesh_cantilever

__all__ = ["SnapRelease", "release_state", "snap_release", "svk_model"]

_SCALAR = {"P1": skfem.ElementTetP1, "P2": skfem.ElementTetP2}


def svk_model(asm: Assembly, intorder: int | None = None) -> SVKModel:
    """Build the SVK model on the host from an ``_fem`` assembly.

    Args:
        asm: the assembly (its mesh, element, node order and free dofs are reused).
        intorder: quadrature degree; default 4 for P2 (the energy density of a quadratic
            displacement is a polynomial of degree 4) and 1 for P1 (constant strain).
    """
    if intorder is None:
        intorder = 4 if asm.element == "P2" else 1
    skmesh = asm.basis.mesh
    scalar = skfem.Basis(skmesh, _SCALAR[asm.element](), intorder=intorder)
    cells = scalar.element_dofs.T  # (m, a), the same numbering as asm.cells
    if not np.array_equal(cells, asm.cells):
        raise RuntimeError("svk_model: scalar basis numbering differs from the assembly's cells")
    # scalar.basis[i][0].grad: (3, m, q) -> grads (m, q, a, 3)
    grads = np.stack([scalar.basis[i][0].grad for i in range(cells.shape[1])], axis=0)
    grads = np.transpose(grads, (2, 3, 0, 1))
    n_nodes = asm.nodes.shape[0]
    to_free = np.full(3 * n_nodes, asm.free.size, dtype=np.int64)
    to_free[asm.free] = np.arange(asm.free.size)
    local = to_free[(3 * cells[:, :, None] + np.arange(3)).reshape(cells.shape[0], -1)]
    f = asm.free
    linear = sparse_blocks(*(m[f][:, f] for m in (asm.K_lam, asm.K_mu, asm.M1)))
    with jax.enable_x64(True):
        return SVKModel(
            jnp.asarray(cells, jnp.int32),
            jnp.asarray(grads),
            jnp.asarray(scalar.dx),
            jnp.asarray(asm.free, jnp.int32),
            jnp.asarray(local, jnp.int32),
            linear,
            n_nodes,
        )


def release_state(asm: Assembly, geom: Cantilever, nu: float, deflection: float | None = None):
    """The snap's release: the hook pressed in by the undercut, as at the peak of insertion.

    A uniform traction in -x on the hook's flat (``x = h_tip + y_u``, where the plug's face
    rests when the hook is fully deflected), scaled so that the linear static solution moves
    the flat's nodes by ``deflection`` (default the undercut ``y_u``) in -x on average. The
    linear static shape does not depend on E, so every E starts from the same geometry.

    Returns:
        u0: (nf,) free-dof displacement, mm.
        probe: (nf,) weights with ``probe @ u`` = mean x displacement of the flat's nodes, mm
            (``probe @ u0 = -deflection``).
    """
    deflection = geom.undercut if deflection is None else float(deflection)
    x_flat = geom.h_tip + geom.undercut
    f = traction_load(asm, lambda x: np.isclose(x[0], x_flat, atol=1e-9), [-1.0, 0.0, 0.0])
    u = solve_static(asm, 1.0, nu, f)[asm.free]
    on_flat = np.flatnonzero(np.isclose(asm.nodes[:, 0], x_flat, atol=1e-9))
    to_free = np.full(asm.n_dof, -1)
    to_free[asm.free] = np.arange(asm.free.size)
    probe = np.zeros(asm.free.size)
    probe[to_free[3 * on_flat]] = 1.0 / on_flat.size
    return u * (-deflection / (probe @ u)), probe


class SnapRelease(NamedTuple):
    """The stability benchmark's scenario: a hook held pressed in by the undercut, released.

    Attributes:
        asm: the assembly of the cantilever's mesh.
        model: its SVK model.
        u_linear: (nf,) linear static deflection (initial state of linear PMI), mm.
        u_svk: (nf,) SVK static equilibrium with the same flat deflection (initial state of the
            nonlinear integrators), mm.
        probe: (nf,) weights of the flat's mean x displacement, mm.
        load_ratio: SVK over linear load needed for that deflection (1 for a linear hook).
    """

    asm: Assembly
    model: SVKModel
    u_linear: np.ndarray
    u_svk: np.ndarray
    probe: np.ndarray
    load_ratio: float


def snap_release(
    geom: Cantilever, mesh_size: float, element: str = "P1", nu: float = 0.35, deflection=None
) -> SnapRelease:
    """Build the snap-release scenario (see :func:`release_state`) for any E.

    Both initial states are independent of E (W and K scale with E at fixed nu), so they are
    computed once, at E = 1 MPa. The SVK state is the nonlinear equilibrium under the same
    load shape, scaled to the same flat deflection: released from it, a nonlinear integrator
    starts at rest in equilibrium with the load that was just removed, as linear PMI does.
    """
    asm = assemble(mesh_cantilever(geom, mesh_size), element)
    model = svk_model(asm)
    u_lin, probe = release_state(asm, geom, nu, deflection)
    K = asm.stiffness(1.0, nu)[asm.free][:, asm.free]
    with jax.enable_x64(True):
        mat = Material.create(1.0, nu, 1.0)
        u_svk, P = static_deflection(model, mat, K @ u_lin, probe, probe @ u_lin)
    return SnapRelease(asm, model, u_lin, np.asarray(u_svk), probe, float(P))


