"""Differentiable rollouts and parameter identification (jsnap.identify, jsnap fit).

Coarse full-model sockets (``solver.method = "full"``; the default is the reduced model) keep
each rollout short: P1 1.5 mm (288 dofs) for the gradient check and the CLI,
P2 1.5 mm (1554 dofs) for the identification (a coarse P1 arm locks and its force history is too
rough to fit to 0.1 %). The identify and unit-check tests share one model, so that their
gradient compiles once (every build compiles anew).
"""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jsnap
from jsnap._apps.cli import main as cli_main

COARSE = {
    "solver.method": "full",
    "solver.element": "P1",
    "solver.mesh_size": 1.5,
    "solver.dtype": "float64",
    "motion.speed": 20.0,
}


@pytest.fixture(scope="module")
def coarse():
    """Model and its own force history at the scene's parameters (the synthetic measurement),
    time (s) and force (N), over the first 70 ms: the ramp, the peak and the snap."""
    scene = jsnap.load_scene().replace({**COARSE, "solver.element": "P2"})
    model = jsnap.build(scene)
    res = jsnap.rollout(model, controls=model.trajectory()[1:71])
    return model, np.asarray(res.t), np.asarray(res.insertion_force)


def _write_csv(path, t, F, header="t_s,insertion_force_N"):
    np.savetxt(path, np.column_stack([t, F]), delimiter=",", header=header, comments="", fmt="%.10g")
    return path


def test_gradient_through_contact_matches_central_differences(x64):
    """d(Σ F²) with respect to E, μ, α, β and the plug's path, through a rollout with contact,
    float64, converged contact solves, against central differences (relative steps where the
    quotient is flat: the contact set is discrete, docs/differentiation.md). JAX transformations
    of jsnap calls run in 64-bit mode (the ``x64`` fixture; see the next test)."""
    scene = jsnap.load_scene().replace({**COARSE, "contact.iterations": 20000, "contact.tolerance": 1e-11})
    model = jsnap.build(scene)
    base = model.params.replace(alpha=20.0, beta=1e-5)
    names = ("E", "friction", "alpha", "beta")
    controls = jnp.asarray(model.trajectory()[1:51])  # the ramp

    def loss(x, c):
        r = jsnap.rollout(model, base.replace(**dict(zip(names, x, strict=True))), controls=c)
        return jnp.sum(r.insertion_force**2)

    x0 = tuple(jnp.asarray(getattr(base, n)) for n in names)
    value, (grad, grad_c) = jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))(x0, controls)
    assert float(value) > 1.0  # there is contact
    f = jax.jit(loss)
    steps = {"E": 1e-3, "friction": 1e-4, "alpha": 1e-2, "beta": 1e-3}
    for i, n in enumerate(names):
        d = steps[n] * float(x0[i])
        xp, xm = list(x0), list(x0)
        xp[i], xm[i] = x0[i] + d, x0[i] - d
        fd = float(f(tuple(xp), controls) - f(tuple(xm), controls)) / (2 * d)
        assert abs(float(grad[i]) / fd - 1) < 1e-3, (n, float(grad[i]), fd)
    # Quasi-static insertion: F ∝ E, so d(Σ F²)/dE = 2 Σ F² / E (up to the tiny inertia).
    assert abs(float(grad[0]) * float(x0[0]) / (2 * float(value)) - 1) < 0.01
    # The plug's path: lowering it (−z) from step k on, on the ramp, raises the force.
    k = 30
    e = jnp.zeros_like(controls).at[k:, 2].set(1.0)
    h = 1e-5  # mm
    fd = float(f(x0, controls + h * e) - f(x0, controls - h * e)) / (2 * h)
    ad = float(jnp.sum(grad_c * e))
    assert fd < 0
    assert abs(ad / fd - 1) < 1e-3, (ad, fd)


def test_a_transformation_outside_64_bit_mode_is_refused_with_advice():
    """JAX compiles a transformed program (grad, jit, vmap) after jsnap's call has returned,
    outside its 64-bit scope: a program in JAX's default 32-bit mode is told to run the
    transformation inside ``with jax.enable_x64(True):``, and doing so works (for that block
    only)."""
    model = jsnap.build(jsnap.load_scene().replace({**COARSE, "solver.dtype": "float32"}))
    controls = model.trajectory()[1:15]  # on the ramp

    def loss(E):
        return jnp.sum(jsnap.rollout(model, model.params.replace(E=E), controls=controls).insertion_force ** 2)

    assert not jax.config.jax_enable_x64
    with pytest.raises(RuntimeError, match=r"jsnap\.rollout is being traced by a JAX transformation"):
        jax.grad(loss)(jnp.asarray(2200.0))
    with jax.enable_x64(True):
        g = jax.grad(loss)(jnp.asarray(2200.0))
    assert not jax.config.jax_enable_x64
    assert np.isfinite(float(g)) and float(g) > 0  # a stiffer hook resists more


def test_identify_recovers_E_from_noise_free_data(coarse, tmp_path):
    model, t, F = coarse
    csv = _write_csv(tmp_path / "m.csv", t, F)
    fit = jsnap.identify(model, csv, fit=("E",), initial={"E": 1540.0}, progress=False)
    assert abs(fit.values["E"] / 2200.0 - 1) < 1e-3
    assert fit.converged
    assert fit.loss_history[-1] < 1e-4 * fit.loss_history[0]
    # Noise-free, same model: the residual is the solver's tolerance; so is the error bar.
    assert fit.std_errors["E"] < 5.0
    assert fit.rms_residual < 1e-3 * F.max()
    png = fit.plot(tmp_path / "fit.png")
    assert png.stat().st_size > 10_000


def test_resampling_a_fast_noisy_sensor():
    """A 10 kHz record is averaged over each 1 ms step (noise down by ~sqrt(10))."""
    from jsnap._apps.identify import Measurement, resample

    rng = np.random.default_rng(0)
    t = np.arange(1, 2001) * 1e-4
    meas = Measurement(t, np.sin(20 * t) + 0.1 * rng.normal(size=t.size))
    t_sim = (np.arange(200) + 1) * 1e-3
    F, mask = resample(meas, t_sim, 1e-3)
    assert mask[:-1].all() and not mask[-1]  # the last window runs past the record
    err = (F - np.sin(20 * t_sim))[mask]
    assert 0.015 < err.std() < 0.05


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("time,travel\n0,1\n1,2\n2,3\n3,4\n", r"missing force column: none of time, travel"),
        ("F,x\n1,2\n2,3\n3,4\n4,5\n", r"missing time column"),
        ("0.001,1\n0.002,2\n", r"no header row"),
        ("t_s,force\n0.001,1\n0.003,2\n0.002,3\n0.004,4\n", r"not strictly increasing: data row 3"),
        (
            "t_s,force\n0.001,1\n0.002,nan\n0.003,3\n0.004,4\n",
            r"'force' has 1 NaN/inf value\(s\) \(data rows 2\)",
        ),
        ("t_s,force\n0.001,1\n0.002,abc\n0.003,3\n0.004,4\n", r"line 3, column 'force': 'abc' is not a number"),
        ("t_s,force\n0.001,1\n", r"1 samples; at least 4"),
    ],
)
def test_bad_csv_is_an_error_naming_the_problem(tmp_path, text, match):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(jsnap.MeasurementError, match=match):
        jsnap.load_measurement(path)


def test_missing_file_is_an_error(tmp_path):
    with pytest.raises(jsnap.MeasurementError, match="does not exist"):
        jsnap.load_measurement(tmp_path / "nope.csv")


def test_units_obviously_off_are_errors(coarse, tmp_path):
    model, t, F = coarse
    with pytest.raises(jsnap.MeasurementError, match=r"time column 't_s' spans .* is it in ms\?"):
        jsnap.identify(model, _write_csv(tmp_path / "ms.csv", t * 1e3, F), progress=False)
    with pytest.raises(jsnap.MeasurementError, match=r"force column 'insertion_force_N' .* is it in mN\?"):
        jsnap.identify(model, _write_csv(tmp_path / "mN.csv", t, F * 1e3), fit=("E",), progress=False)
    with pytest.raises(jsnap.MeasurementError, match=r"is it in kN\?"):
        jsnap.identify(
            model, _write_csv(tmp_path / "kN.csv", t, F * 1e-3, "time,force"), fit=("E",), progress=False
        )
    # Declared units are converted, not rejected.
    meas = jsnap.load_measurement(_write_csv(tmp_path / "dec.csv", t * 1e3, F * 1e3, "t_ms,force_mN"))
    np.testing.assert_allclose(meas.t, t, rtol=1e-9)
    np.testing.assert_allclose(meas.force, F, rtol=1e-9, atol=1e-12)
    with pytest.raises(ValueError, match=r"fit: unknown parameter\(s\) \['G'\]"):
        jsnap.identify(model, jsnap.Measurement(t, F), fit=("G",), progress=False)


def test_cli_fit_on_simulate_output(tmp_path, capsys):
    """`jsnap simulate`'s forces.csv is accepted as the measurement; `jsnap fit` moves E from a
    scene 30 % off toward the one that made the data and writes its outputs; bad input is an
    error naming the problem (exit code 2)."""
    text = open(jsnap.load_scene().source).read()
    body = text.split("[motion]")[0]  # the default scene's connector, material, contact, plug
    tiny = (
        "[motion]\nspeed = 40.0\n"
        "[solver]\nmethod = 'full'\nelement = 'P1'\nmesh_size = 1.5\ndtype = 'float64'\n"
    )
    truth = tmp_path / "truth.toml"
    truth.write_text(body + tiny)
    assert cli_main(["simulate", str(truth), "--out", str(tmp_path / "sim"), "--json"]) == 0
    capsys.readouterr()
    forces = tmp_path / "sim" / "forces.csv"
    assert jsnap.load_measurement(forces).columns == ("t_s", "insertion_force_N")
    start = tmp_path / "start.toml"
    start.write_text(truth.read_text().replace("youngs_modulus = 2200.0", "youngs_modulus = 1540.0"))
    out = tmp_path / "fit"
    args = ["fit", str(start), str(forces), "--fit", "E", "--max-iters", "4", "--out", str(out), "--json"]
    assert cli_main(args) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["initial"]["E"] == 1540.0
    assert abs(summary["values"]["E"] - 2200.0) < 0.1 * (2200.0 - 1540.0)
    assert summary["std_errors"]["E"] > 0 and summary["samples"] > 50
    for f in ("fit.json", "fit.csv", "fit.png"):
        assert (out / f).stat().st_size > 0
    bad = tmp_path / "bad.csv"
    bad.write_text("time,force\n0,1\n0,2\n1,3\n2,4\n")
    assert cli_main(["fit", str(start), str(bad), "--out", str(out)]) == 2
    assert "not strictly increasing: data row 2" in capsys.readouterr().err
    assert cli_main(["fit", str(start), str(forces), "--fit", "E,G", "--out", str(out)]) == 2
    assert "unknown parameter(s) ['G']" in capsys.readouterr().err
