"""St. Venant–Kirchhoff FEM and the stability comparison (benchmarks/stability.py, docs/stability.md).

Everything runs on the coarse (2 mm, P1, 153 free dofs) default hook, released from the
undercut's deflection at dt = 1 ms: the benchmark's scenario on a smaller mesh.
"""

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jsnap._build.nonlinear import snap_release
from jsnap._core import nonlinear as N
from jsnap._core.params import Material
from jsnap._geometry.scene import connector_geometry, load_scene

# Kernel tests in float64 (jsnap's scoped 64-bit mode, as its entry points use internally).
pytestmark = pytest.mark.usefixtures("x64")

RHO, NU, DT = 1.05e-9, 0.35, 1e-3


@pytest.fixture(scope="module")
def snap():
    return snap_release(connector_geometry(load_scene()), 2.0, "P1", NU)


def mat(E):
    return Material.create(E, NU, RHO)


def linear_K(snap, E):
    return snap.asm.stiffness(E, NU)[snap.asm.free][:, snap.asm.free].toarray()


def test_tangent_at_rest_is_the_linear_stiffness(snap):
    Kt = np.asarray(N.tangent(snap.model, mat(2200.0), jnp.zeros(snap.model.n_free)))
    K = linear_K(snap, 2200.0)
    assert np.abs(Kt - K).max() < 1e-12 * np.abs(K).max()


def test_small_displacement_force_is_linear_to_first_order(snap):
    """|grad W(a u) - K a u| / |K a u| is O(a): the SVK model is linear elasticity plus terms
    of higher order in the displacement. (At a = 1, the 0.8 mm deflection, the ratio is 44:
    K u is the small load on the flat, the membrane forces of a linear bending field that does
    not shorten are not small. Measured 0.0436 a.)"""
    K = linear_K(snap, 2200.0)
    amps = np.array([1e-3, 1e-4, 1e-5])
    err = []
    for a in amps:
        u = a * snap.u_linear
        f = np.asarray(N.internal_force(snap.model, mat(2200.0), jnp.asarray(u)))
        err.append(np.linalg.norm(f - K @ u) / np.linalg.norm(K @ u))
    slopes = np.diff(np.log10(err)) / np.diff(np.log10(amps))
    assert err[-1] < 1e-3
    np.testing.assert_allclose(slopes, 1.0, atol=0.05)


def test_energy_is_frame_invariant(snap):
    """A rigid rotation stores no energy, and rotating a deformed body does not change its
    energy (the linear strain energy of the same displacements is large)."""
    model, m = snap.model, mat(2200.0)
    X = snap.asm.nodes
    R = Rotation.from_rotvec([0.3, -0.5, 0.4]).as_matrix()
    rigid = X @ R.T - X
    lin = 0.5 * rigid.ravel() @ (snap.asm.stiffness(2200.0, NU) @ rigid.ravel())
    assert float(N.strain_energy_nodal(model, m, jnp.asarray(rigid))) < 1e-12 * lin

    U = np.zeros_like(X)
    U.reshape(-1)[snap.asm.free] = snap.u_svk
    rotated = (X + U) @ R.T - X
    w = float(N.strain_energy_nodal(model, m, jnp.asarray(U)))
    w_rot = float(N.strain_energy_nodal(model, m, jnp.asarray(rotated)))
    assert w > 0
    assert abs(w_rot - w) < 1e-11 * w
    assert w == pytest.approx(float(N.strain_energy(model, m, jnp.asarray(snap.u_svk))), rel=1e-13)


def test_tangent_is_the_derivative_of_the_force(snap):
    model, m = snap.model, mat(2200.0)
    u = jnp.asarray(snap.u_svk)
    d = jnp.asarray(np.random.default_rng(0).standard_normal(model.n_free)) * 1e-2
    h = 1e-4
    fd = (N.internal_force(model, m, u + h * d) - N.internal_force(model, m, u - h * d)) / (2 * h)
    Kd = N.tangent(model, m, u) @ d
    assert float(jnp.linalg.norm(fd - Kd) / jnp.linalg.norm(Kd)) < 1e-7
    # At the deflected state the tangent is not the linear K: the check above is not vacuous.
    K0d = linear_K(snap, 2200.0) @ np.asarray(d)
    assert float(jnp.linalg.norm(Kd - K0d) / jnp.linalg.norm(Kd)) > 1e-3


def test_static_deflection_is_an_equilibrium(snap):
    """grad W(u_svk) = P K u_linear (the same load shape) with the flat pressed in by y_u."""
    model, m = snap.model, mat(1.0)
    load = snap.asm.stiffness(1.0, NU)[snap.asm.free][:, snap.asm.free] @ snap.u_linear
    f = np.asarray(N.internal_force(model, m, jnp.asarray(snap.u_svk)))
    assert np.linalg.norm(f - snap.load_ratio * load) < 1e-9 * np.linalg.norm(load)
    assert snap.probe @ snap.u_svk == pytest.approx(-0.8, abs=1e-12)
    assert snap.probe @ snap.u_linear == pytest.approx(-0.8, abs=1e-12)
    assert 0.9 < snap.load_ratio < 1.1  # 0.8 mm on a 10 mm arm: moderately nonlinear


def run(snap, method, E, steps, u0=None, **kw):
    u0 = snap.u_svk if u0 is None else u0
    u0, probe = jnp.asarray(u0), jnp.asarray(snap.probe)
    return N.simulate(method, snap.model, mat(E), DT, u0, jnp.zeros_like(u0), steps, probe, **kw)


@pytest.mark.parametrize("E", [2200.0, 2e5])
def test_linear_pmi_conserves_energy_and_verlet_diverges(snap, E):
    """At dt = 1 ms (T omega_1 ~ 10 at 2.2 GPa, and the mesh's highest modes far beyond)
    linear PMI keeps the energy to round-off; velocity Verlet, whose stability limit is
    T omega_max < 2 (microseconds here), blows up within a few steps."""
    pmi = run(snap, "linear_pmi", E, 200, snap.u_linear)
    e = np.asarray(pmi.energy)
    assert np.all(np.isfinite(e))
    assert np.max(np.abs(e / e[0] - 1)) < 1e-10
    assert np.max(np.abs(np.asarray(pmi.probe))) < 1.5  # still oscillating, bounded

    verlet = np.asarray(run(snap, "verlet", E, 10).energy)
    assert not (np.all(np.isfinite(verlet)) and verlet.max() < 10 * verlet[0])


def test_linearised_euler_damps(snap):
    """Backward Euler takes 1/(1 + (T omega)^2) of a mode's energy per step: the released hook
    stops dead. (Not monotone: on the 1.2 mm mesh step 1 adds 20 %, the linearisation error.)"""
    e = np.asarray(run(snap, "linearised_euler", 2200.0, 20).energy)
    assert np.all(np.isfinite(e)) and e.max() < 1.5 * e[0]
    assert e[-1] < 1e-6 * e[0]


def test_newton_midpoint_energy_error_is_the_nonlinearity(snap):
    """Newton-implicit midpoint converges at every step for small amplitudes, and its energy
    error is the non-quadratic part of the SVK energy, O(amplitude): the midpoint rule
    conserves quadratic energies only (measured 4.1e-5 at 1e-3, 4.2e-6 at 1e-4, from the
    linear static shape)."""
    err = []
    for a in (1e-3, 1e-4):
        tr = run(snap, "newton_midpoint", 2200.0, 30, a * snap.u_linear, rtol=1e-11)
        assert bool(jnp.all(tr.converged))
        e = np.asarray(tr.energy)
        err.append(np.max(np.abs(e / e[0] - 1)))
    assert err[1] < 1e-5
    assert 5.0 < err[0] / err[1] < 20.0


def test_linearised_midpoint_is_pmi_in_the_small_amplitude_limit(snap):
    """One Newton iteration of the midpoint rule on the SVK model is PMI with a re-linearised
    stiffness: as the amplitude goes to 0 it becomes linear PMI (difference O(amplitude))."""
    diff = []
    for a in (1e-3, 1e-4):
        u0 = a * snap.u_linear
        lin = np.asarray(run(snap, "linear_pmi", 2200.0, 20, u0).probe)
        nl = np.asarray(run(snap, "linearised_midpoint", 2200.0, 20, u0).probe)
        diff.append(np.max(np.abs(nl - lin)) / np.max(np.abs(lin)))
    assert diff[1] < 1e-3
    assert 5.0 < diff[0] / diff[1] < 20.0


def test_divergence_stops_the_run(snap):
    tr = run(snap, "verlet", 2200.0, 6, stop_ratio=1e3)
    e = np.asarray(tr.energy)
    first = int(np.argmax(~np.isfinite(e)))
    assert first > 0 and np.all(np.isnan(e[first:]))
    assert np.all(e[:first] <= 1e3 * e[0])


def test_unknown_method_is_rejected(snap):
    with pytest.raises(ValueError, match="method = 'rk4'"):
        run(snap, "rk4", 2200.0, 2)


def test_simulate_does_not_recompile_for_another_E(snap):
    jitted = N.simulate.__wrapped__  # the jitted kernel inside the scoped-x64 wrapper
    run(snap, "linearised_euler", 2200.0, 3)
    n = jitted._cache_size()
    run(snap, "linearised_euler", 2e4, 3)
    assert jitted._cache_size() == n
