"""Host side of the modal part: every mode of the part, computed once per mesh and Poisson ratio
and cached (``jsnap._core.parts.ModalPart`` is the model that uses them).

Units: mm, N, MPa, s, tonne.
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg as sla

from jsnap._build.cache import ArtefactError, KeyHash, cached
from jsnap._build.fem import Assembly, output_rows
from jsnap._core.params import lame
from jsnap._core.parts import ModalPart

__all__ = ["modal_part", "modes"]


def modes(asm: Assembly, nu: float):
    """``(w, Phi)``: all generalised eigenpairs of ``K(1, nu)`` and ``M1`` on the free dofs,
    ``Phi' M1 Phi = I`` (LAPACK's divide and conquer, dense: n^3)."""
    f = asm.free
    lam, mu = lame(1.0, nu)
    K = (lam * asm.K_lam + mu * asm.K_mu)[f][:, f].toarray()
    M = asm.M1[f][:, f].toarray()
    w, Phi = sla.eigh(0.5 * (K + K.T), 0.5 * (M + M.T), driver="gvd", overwrite_a=True, overwrite_b=True)
    return w, Phi


def cached_modes(asm: Assembly, nu: float, *, progress: bool = False):
    """``(w, Phi, meta)`` of ``asm`` at ``nu``, from the cache or computed and cached."""
    key = KeyHash("modal").settings(dict(element=asm.element, nu=nu))
    key = key.arrays(asm.mesh.points, asm.mesh.cells, asm.fixed).hexdigest()

    def make():
        if progress:
            print(f"jsnap: the part's {asm.free.size} modes (dense eigendecomposition, once) ...", flush=True)
        t0 = time.perf_counter()
        w, Phi = modes(asm, nu)
        return {"w": w, "Phi": Phi}, dict(seconds=time.perf_counter() - t0, dof=int(asm.free.size), nu=nu)

    def check(arrays, meta):
        n = arrays["w"].shape[0] if "w" in arrays else -1
        if set(arrays) != {"w", "Phi"} or arrays["Phi"].shape != (n, n):
            raise ArtefactError(f"{meta.get('path', 'modes file')}: arrays {sorted(arrays)} are not n modes")

    arrays, meta = cached("modal", key, make, what="the part's modes", check=check)
    return arrays["w"], arrays["Phi"], meta


def modal_part(asm: Assembly, nu: float, sample, stencil, *, progress: bool = False):
    """The :class:`ModalPart` of ``asm`` at ``nu`` and what was done (``meta``).

    Args:
        sample, stencil: (nodes, weights) of the contact points and their normal stencils in
            free-node numbering, as :class:`jsnap._core.parts.FullPart` holds them.
    """
    w, Phi, meta = cached_modes(asm, nu, progress=progress)
    nodes, weights = (np.asarray(a) for a in sample)
    st_nodes, st_weights = (np.asarray(a) for a in stencil)
    used = np.concatenate([nodes[weights != 0], st_nodes[st_weights != 0]])
    contact = np.unique(used)
    remap = np.zeros(Phi.shape[0] // 3, np.int64)
    remap[contact] = np.arange(contact.size)
    dofs = 3 * contact[:, None] + np.arange(3)
    out = output_rows(asm, Phi)
    with jax.enable_x64(True):

        def local(n, wt):
            return jnp.asarray(np.where(wt != 0, remap[n], 0), jnp.int32), jnp.asarray(wt)

        sn, sw = local(nodes, weights)
        tn, tw = local(st_nodes, st_weights)
        part = ModalPart(
            w=jnp.asarray(w),
            nu=jnp.asarray(nu, jnp.float64),
            node_rows=jnp.asarray(Phi[dofs]),
            sample_nodes=sn,
            sample_weights=sw,
            stencil_nodes=tn,
            stencil_weights=tw,
            **{k: jnp.asarray(v) for k, v in out.items()},
            recon=jnp.asarray(Phi),
        )
    return part, meta
