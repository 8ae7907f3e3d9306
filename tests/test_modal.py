"""The full socket in modal coordinates (``solver.method = "modal"``, jsnap/_modal.py).

The same discrete equations as the dense full model in other coordinates: checked against it
(an independent implementation: sparse blocks and a dense inverse of S) on a coarse scene with
Rayleigh damping, forces, base wrench, energy and gradients.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jsnap
from jsnap._build import modal as _modal

SMALL = {
    "solver.mesh_size": 2.0,
    "solver.dtype": "float64",
    "motion.speed": 20.0,
    "material.rayleigh_alpha": 20.0,
    "material.rayleigh_beta": 1e-5,
}


@pytest.fixture(scope="module")
def models(cache):
    scene = jsnap.load_scene().replace(SMALL)
    return {m: jsnap.build(scene.replace({"solver.method": m})) for m in ("full", "modal")}


@pytest.fixture(scope="module")
def rollouts(models):
    return {m: jsnap.rollout(models[m], keep_x=True) for m in models}


def test_modes_diagonalise_the_pmi_operator(models):
    """Phi' M1 Phi = I and Phi' K1 Phi = diag(w), so S^-1 = Phi diag(1/c) Phi' (checked against
    the dense full model's S^-1 from its own prepare)."""
    full, modal = models["full"], models["modal"]
    s = modal.socket
    Phi, w = np.asarray(s.recon), np.asarray(s.w)
    M1 = full.host.assembly.M1[full.host.free][:, full.host.free]
    assert np.abs(Phi.T @ (M1 @ Phi) - np.eye(w.size)).max() < 1e-9
    assert np.all(w > 0)
    S_inv = np.asarray(jsnap.prepare(full).op.S_inv)
    op = jsnap.prepare(modal).op
    dense = (Phi * np.asarray(op.cinv)) @ Phi.T
    assert np.abs(dense - S_inv).max() < 1e-9 * np.abs(S_inv).max()


def test_modal_rollout_is_the_full_model(models, rollouts):
    full, modal = rollouts["full"], rollouts["modal"]
    F0 = np.asarray(full.insertion_force)
    assert F0.max() > 1.0  # the hook was pushed aside and snapped
    for field in ("insertion_force", "base_force", "base_moment", "energy", "work"):
        a, b = np.asarray(getattr(modal, field)), np.asarray(getattr(full, field))
        assert np.abs(a - b).max() < 1e-6 * np.abs(b).max(), field
    assert np.array_equal(np.asarray(modal.contact_index), np.asarray(full.contact_index))
    # Result.x holds the socket's coordinates (modal here); free_displacement maps them back.
    x = np.asarray(jax.vmap(models["modal"].socket.free_displacement)(modal.x))
    assert np.abs(x - np.asarray(full.x)).max() < 1e-6 * np.abs(np.asarray(full.x)).max()
    assert models["modal"].n_dof == models["full"].n_dof


def test_modal_gradients_are_the_full_models_and_nu_is_refused(models):
    """E, rho, alpha, beta and friction differentiate as in the full model; nu, which the
    modes are computed for, gives NaN (not a silent zero) and another value is an error."""
    names = ("E", "rho", "alpha", "beta", "friction", "nu")

    def loss(model):
        controls = model.trajectory()[1:40]  # on the ramp, in contact

        @jax.jit
        @jax.value_and_grad
        def f(x):
            p = model.params.replace(**dict(zip(names, x, strict=True)))
            return jnp.sum(jsnap.rollout(model, p, controls=controls, dtype="float64").insertion_force ** 2)

        return f

    x0 = tuple(jnp.asarray(getattr(models["full"].params, n), jnp.float64) for n in names)
    v_full, g_full = loss(models["full"])(x0)
    v_modal, g_modal = loss(models["modal"])(x0)
    assert float(v_full) > 1.0
    assert float(v_modal) == pytest.approx(float(v_full), rel=1e-9)
    for n, a, b in zip(names[:-1], g_modal, g_full, strict=False):
        assert float(b) != 0.0, n
        assert float(a) == pytest.approx(float(b), rel=1e-6), n
    assert np.isnan(float(g_modal[-1])) and np.isfinite(float(g_full[-1]))
    with pytest.raises(Exception, match="another Poisson ratio"):
        jsnap.rollout(models["modal"], models["modal"].params.replace(nu=0.3))


def test_modes_are_cached_and_a_corrupt_file_is_recomputed(models, cache):
    modal = models["modal"]
    info = modal.host.reduction
    assert not info["cached"]  # computed by the fixture in this fresh cache
    again = jsnap.build(modal.host.scene)
    assert again.host.reduction["cached"] and again.host.reduction["path"] == info["path"]
    assert np.array_equal(np.asarray(again.socket.recon), np.asarray(modal.socket.recon))
    raw = bytearray(open(info["path"], "rb").read())
    raw[len(raw) // 2] ^= 0xFF
    open(info["path"], "wb").write(bytes(raw))
    with pytest.warns(UserWarning, match="not using it"):
        rebuilt = jsnap.build(modal.host.scene)
    assert not rebuilt.host.reduction["cached"]
    assert np.array_equal(np.asarray(rebuilt.socket.w), np.asarray(modal.socket.w))
    with pytest.raises(_modal.ModesFileError, match="another mesh"):
        _modal.load(info["path"], key="0" * 64)
