"""The full part in modal coordinates (``solver.method = "modal"``, jsnap/_core/parts.py
``ModalPart``, built by jsnap/_build/modal.py).

The same discrete equations as the dense full model in other coordinates: checked against it
(an independent implementation: sparse blocks and a dense inverse of S) on a coarse scene with
Rayleigh damping, forces, base wrench, energy and gradients.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jsnap
from jsnap._build.cache import ArtefactError, load_artefact
from jsnap._build.fem import assemble
from jsnap._build.model import build_model
from jsnap._geometry.cantilever import mesh_cantilever
from jsnap._geometry.scene import connector_geometry, with_internal

SMALL = {
    "solver.mesh_size": 2.0,
    "solver.dtype": "float64",
    "motion.speed": 20.0,
    "material.rayleigh_alpha": 20.0,
    "material.rayleigh_beta": 1e-5,
}


@pytest.fixture(scope="module")
def scene():
    return jsnap.load_scene().replace(SMALL)


@pytest.fixture(scope="module")
def built(cache, scene):
    """``{method: (model, build report)}``."""
    # "modal" is an internal choice of solver.method.
    return {m: build_model(with_internal(scene, {"solver.method": m})) for m in ("full", "modal")}


@pytest.fixture(scope="module")
def models(built):
    return {m: built[m][0] for m in built}


@pytest.fixture(scope="module")
def rollouts(models):
    return {m: jsnap.rollout(models[m], keep_x=True) for m in models}


def test_modes_diagonalise_the_pmi_operator(models, scene):
    """Phi' M1 Phi = I and Phi' K1 Phi = diag(w), so S^-1 = Phi diag(1/c) Phi' (checked against
    the dense full model's S^-1 from its own prepare)."""
    full, modal = models["full"], models["modal"]
    s = modal.part
    Phi, w = np.asarray(s.recon), np.asarray(s.w)
    asm = assemble(mesh_cantilever(connector_geometry(scene), scene["solver"]["mesh_size"]), full.element)
    free = np.asarray(full.mesh.free)
    assert np.array_equal(free, asm.free)
    M1 = asm.M1[free][:, free]
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
    # Result.x holds the part's coordinates (modal here); free_displacement maps them back.
    with jax.enable_x64(True):  # the part's float64 kernel, called directly
        x = np.asarray(jax.vmap(models["modal"].part.free_displacement)(modal.x))
    assert np.abs(x - np.asarray(full.x)).max() < 1e-6 * np.abs(np.asarray(full.x)).max()
    assert models["modal"].n_dof == models["full"].n_dof


@pytest.mark.usefixtures("x64")
def test_modal_gradients_are_the_full_models_and_nu_is_refused(models):
    """E, rho, alpha, beta and friction differentiate as in the full model; nu, which the
    modes are computed for, gives NaN (not a silent zero) and another value is an error.

    In 64-bit mode: the parameters and their gradients are float64 arrays of this program, and a
    rollout traced by a JAX transformation (here jit and grad) must run inside 64-bit mode
    (jsnap refuses it otherwise, ``jsnap._core.util.x64``)."""
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


def test_modes_are_cached_and_a_corrupt_file_is_recomputed(built, scene, cache):
    modal, report = built["modal"]
    info = report.reduction
    assert not info["cached"]  # computed by the fixture in this fresh cache
    modal_scene = with_internal(scene, {"solver.method": "modal"})
    again, again_report = build_model(modal_scene)
    assert again_report.reduction["cached"] and again_report.reduction["path"] == info["path"]
    assert np.array_equal(np.asarray(again.part.recon), np.asarray(modal.part.recon))
    raw = bytearray(open(info["path"], "rb").read())
    raw[len(raw) // 2] ^= 0xFF
    open(info["path"], "wb").write(bytes(raw))
    with pytest.warns(UserWarning, match="not using it"):
        rebuilt, rebuilt_report = build_model(modal_scene)
    assert not rebuilt_report.reduction["cached"]
    assert np.array_equal(np.asarray(rebuilt.part.w), np.asarray(modal.part.w))
    with pytest.raises(ArtefactError, match="made for something else"):
        load_artefact(info["path"], "modal", key="0" * 64)
