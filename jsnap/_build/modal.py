"""The full FEM socket in modal coordinates (``solver.method = "modal"``): every mode kept.

With ``K(E, nu0) = E K1`` and ``M = rho M1``, the generalised eigenvectors ``K1 phi = w M1 phi``
(``Phi' M1 Phi = I``) diagonalise PMI exactly: in ``x = Phi q``, ``v = Phi u`` the step is

    c ubar = (2/T) rho u - E w q + Phi' f,     c = rho (2/T + alpha) + E w (beta + T/2),

one multiply per mode instead of the dense ``S^-1`` pass of :class:`jsnap._core.parts.FullSocket`
(Rayleigh damping ``D = alpha M + beta K`` is diagonal too). The same discrete equations: no
mode is dropped, nothing is approximated. The step reads the modes only at the contact nodes
(the interpolating nodes of the candidate points and their stencils: 182 of the default mesh's
1914 nodes) and the base wrench as six output rows, so its memory traffic is O(c n), not
O(n^2).

The price: the basis is computed for the scene's Poisson ratio ``nu0`` (one dense generalised
eigendecomposition at build time, cached on disk). ``E, rho, alpha, beta`` and the friction stay
exact and differentiable without rebuilding; ``nu`` does not: ``prepare`` rejects another value
and the derivative with respect to ``nu`` is NaN, not a silent zero. Use ``"full"`` to vary
``nu``. Units: mm, N, MPa, s, tonne.
"""

from __future__ import annotations

import hashlib
import json
import time
import warnings
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg as sla

from jsnap._build.cache import cache_dir, load_or_make, read_npz, save_npz
from jsnap._build.fem import lame
from jsnap._core.pmi import Material
from jsnap._build.reduce import _hash_arrays, _wrench_rows
from jsnap._core.parts import ContactRows

__all__ = ["ModalOperator", "ModalSocket", "ModesFileError", "load_or_compute", "modes", "socket_from_modes"]


@jax.custom_jvp
def _no_derivative(x):
    """``x``, whose derivative is NaN: a parameter the model holds fixed is not differentiable."""
    return x


@_no_derivative.defjvp
def _no_derivative_jvp(primals, tangents):
    (x,), (t,) = primals, tangents
    return x, t * jnp.nan  # linear in t, so that reverse mode gives NaN too


class ModalOperator(eqx.Module):
    """What one step needs for one material and time step (derived, differentiable).

    Attributes:
        cinv: (n,) ``1 / c`` per mode, mm/(N s) per unit modal coordinate.
        k: (n,) modal stiffness ``E w``; m2t: ``(2/T) rho``; rho: density (modal mass).
        G: (c, 3, c, 3) ``J_c S^-1 J_c'`` between the contact nodes' dofs.
        dt: time step T, s.
    """

    cinv: jax.Array
    k: jax.Array
    m2t: jax.Array
    rho: jax.Array
    G: jax.Array
    dt: jax.Array

    def astype(self, dtype) -> ModalOperator:
        return jax.tree_util.tree_map(lambda a: a.astype(dtype), self)


class ModalSocket(ContactRows):
    """Full linear FEM socket in modal coordinates; implements the interface of
    :class:`jsnap._core.parts.FullSocket` with the state ``x = q``, ``v = u`` (modal).

    Attributes:
        w: (n,) eigenvalues of ``K(1, nu0)`` with respect to ``M1``, ascending.
        nu: the Poisson ratio the basis was computed for.
        out_k, out_m1: (6, n) base force (N) and moment about the base centroid (N mm) per unit
            of ``K(1, nu0) Phi`` and ``M1 Phi`` action.
        recon: (n, n) ``Phi``: free-dof displacement per unit modal coordinate (outputs only).
        node_rows and the contact points' fields: see :class:`jsnap._core.parts.ContactRows`
            (``node_rows`` is ``Phi`` at the contact nodes' dofs).
    """

    w: jax.Array
    nu: jax.Array
    out_k: jax.Array
    out_m1: jax.Array
    recon: jax.Array

    @property
    def n_dof(self) -> int:
        return self.w.shape[0]

    def prepare(self, material: Material, dt) -> ModalOperator:
        """O(c^2 n): no factorisation. Differentiable in ``E, rho, alpha, beta``; raises (at run
        time) when ``material.nu`` is not the basis's ``nu``."""
        dt = jnp.asarray(dt, jnp.float64)
        nu = eqx.error_if(
            jnp.asarray(material.nu, jnp.float64),
            jnp.abs(material.nu - self.nu) > 1e-12,
            "solver.method = 'modal': the modes were computed for another Poisson ratio; "
            "build the model with this nu, or use method 'full'",
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
        """``A``: the points' interpolation ``(weights (C, k), contact nodes (C, k))``, which
        :meth:`contact_velocity` applies as ``S^-1 J'`` without forming the (C, 3, n) ``J S^-1``;
        ``W = J S^-1 J'`` (C, 3, C, 3) from the contact nodes' ``G``."""
        w, nodes = self.sample_weights[idx], self.sample_nodes[idx]
        Gc = jnp.einsum("ck,ckdgf->cdgf", w, op.G[nodes])  # (C, 3, c, 3)
        W = jnp.einsum("cdekf,ek->cdef", Gc[:, :, nodes], w)
        return (w, nodes), W

    def contact_velocity(self, op: ModalOperator, A, force):
        """``S^-1 J' force``: the midpoint velocity (modal) that point forces (C, 3) add."""
        w, nodes = A
        g = jnp.zeros(self.node_rows.shape[:2], force.dtype).at[nodes].add(w[..., None] * force[:, None, :])
        return op.cinv * jnp.einsum("cdn,cd->n", self.node_rows, g)

    def energy(self, op: ModalOperator, x, v):
        """``1/2 v'Mv + 1/2 x'Kx`` in modal coordinates, N mm."""
        return 0.5 * op.rho * (v @ v) + 0.5 * x @ (op.k * x)

    def base_wrench(self, op: ModalOperator, material: Material, x, v, v_new, vbar):
        """Reaction of the fixed base over the step at the interval's midpoint, as
        :class:`jsnap._core.parts.FullSocket` computes it, from the modal output rows."""
        dtype = x.dtype
        ok = (material.E * self.out_k).astype(dtype)
        om = (material.rho * self.out_m1).astype(dtype)
        T = op.dt
        xbar = x + 0.5 * T * vbar
        wr = om @ ((v_new - v) / T + material.alpha * vbar) + ok @ (xbar + material.beta * vbar)
        return wr[:3], wr[3:]

    def free_displacement(self, x):
        """(n,) displacement at the free dofs, mm: ``Phi q``."""
        return self.recon @ x


# --------------------------------------------------------------------------------------------
# Building (host)
# --------------------------------------------------------------------------------------------


def modes(asm, nu: float):
    """``(w, Phi)``: all generalised eigenpairs of ``K(1, nu)`` and ``M1`` on the free dofs,
    ``Phi' M1 Phi = I`` (LAPACK's divide and conquer, dense: n^3; 26 s at 5742 dof on 2 cores)."""
    f = asm.free
    lam, mu = lame(1.0, nu)
    K = (lam * asm.K_lam + mu * asm.K_mu)[f][:, f].toarray()
    M = asm.M1[f][:, f].toarray()
    w, Phi = sla.eigh(0.5 * (K + K.T), 0.5 * (M + M.T), driver="gvd", overwrite_a=True, overwrite_b=True)
    return w, Phi


def socket_from_modes(asm, nu: float, w, Phi, sample, stencil) -> ModalSocket:
    """The :class:`ModalSocket` for the modes ``(w, Phi)`` of ``asm`` at ``nu``; ``sample`` and
    ``stencil``: (nodes, weights) in free-node numbering, as :class:`FullSocket` holds them."""
    nodes, weights = (np.asarray(a) for a in sample)
    st_nodes, st_weights = (np.asarray(a) for a in stencil)
    used = np.concatenate([nodes[weights != 0], st_nodes[st_weights != 0]])
    contact = np.unique(used)
    remap = np.zeros(Phi.shape[0] // 3, np.int64)
    remap[contact] = np.arange(contact.size)

    def local(n, wt):
        return jnp.asarray(np.where(wt != 0, remap[n], 0), jnp.int32), jnp.asarray(wt)

    dofs = 3 * contact[:, None] + np.arange(3)
    node_rows = Phi[dofs]  # (c, 3, n)
    f, fx = asm.free, asm.fixed
    lam, mu = lame(1.0, nu)
    S = _wrench_rows(asm)
    out_k = S @ ((lam * asm.K_lam + mu * asm.K_mu)[fx][:, f] @ Phi)
    out_m1 = S @ (asm.M1[fx][:, f] @ Phi)
    sn, sw = local(nodes, weights)
    tn, tw = local(st_nodes, st_weights)
    return ModalSocket(
        w=jnp.asarray(w),
        nu=jnp.asarray(nu, jnp.float64),
        node_rows=jnp.asarray(node_rows),
        out_k=jnp.asarray(out_k),
        out_m1=jnp.asarray(out_m1),
        recon=jnp.asarray(Phi),
        sample_nodes=sn,
        sample_weights=sw,
        stencil_nodes=tn,
        stencil_weights=tw,
    )


# Cache: the modes of one mesh, element, clamping and Poisson ratio (Phi is n^2 float64).
FORMAT_NAME = "jsnap-modes"
FORMAT_VERSION = 1


class ModesFileError(ValueError):
    """A cached modes file that cannot be used (corrupt, foreign, another version or scene)."""


def cache_key(asm, nu: float) -> str:
    """SHA-256 of what the modes depend on: format, element, mesh, clamped dofs and ``nu``."""
    h = hashlib.sha256()
    h.update(json.dumps(dict(format=FORMAT_NAME, version=FORMAT_VERSION, element=asm.element, nu=nu)).encode())
    _hash_arrays(h, asm.mesh.points, asm.mesh.cells, asm.fixed)
    return h.hexdigest()


def cache_path(key: str) -> Path:
    """``cache_dir()/modal/<key>.npz``."""
    return cache_dir() / "modal" / f"{key[:32]}.npz"


def load(path, key: str):
    """``(w, Phi, meta)`` from a file written for ``key``; raises :class:`ModesFileError` for a
    file that is unreadable, foreign, corrupt or another mesh's (FileNotFoundError: none)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such modes file")

    def bad(why):
        return ModesFileError(f"{path}: {why}; not using it (jsnap.build computes the modes again)")

    data, meta = read_npz(path, FORMAT_NAME, FORMAT_VERSION, "jsnap modes file", bad)
    if set(data) != {"w", "Phi"}:
        raise bad(f"arrays {sorted(data)}, expected w and Phi")
    if meta.get("key") != key:
        raise bad("computed for another mesh or Poisson ratio")
    n = data["w"].shape[0]
    if data["Phi"].shape != (n, n):
        raise bad(f"Phi of shape {data['Phi'].shape} for {n} modes")
    return data["w"], data["Phi"], meta


def load_or_compute(asm, nu: float, *, progress: bool = False):
    """``(w, Phi, meta)`` for ``asm`` at ``nu``: from the cache, or computed (:func:`modes`) and
    cached. A file that cannot be used is reported with a warning and replaced; processes that
    need the same modes at once compute them once (:func:`jsnap._build.cache.load_or_make`)."""
    key = cache_key(asm, nu)
    path = cache_path(key)

    def cached():
        try:
            w, Phi, meta = load(path, key)
        except FileNotFoundError:
            return None
        except ModesFileError as err:
            warnings.warn(str(err), stacklevel=4)
            return None
        return w, Phi, dict(meta, path=str(path), cached=True)

    def make():
        if progress:
            print(f"jsnap: the socket's {asm.free.size} modes (dense eigendecomposition, once) ...", flush=True)
        t0 = time.perf_counter()
        w, Phi = modes(asm, nu)
        meta = dict(key=key, seconds=time.perf_counter() - t0, dof=int(asm.free.size), nu=nu)
        save_npz(path, FORMAT_NAME, FORMAT_VERSION, meta, {"w": w, "Phi": Phi})
        return w, Phi, dict(meta, path=str(path), cached=False)

    return load_or_make(path, cached, make, what="the socket's modes")
