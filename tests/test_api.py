"""The public API's contracts: layers, no process-wide surprises, batched rollouts, and no
silent wrong answers for bad input (each a clear error naming it, or a flagged result).

Scenes here are coarse (P1, 1.6 mm elements): these tests check behaviour, which other tests
check the physics of.
"""

import json
import math
import os
import pickle
import subprocess
import sys
import textwrap
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jsnap
from jsnap._apps.cli import main as cli_main
from jsnap._core import status
from jsnap._core.params import FIELDS
from jsnap._core.rollout import _result
from jsnap._geometry.scene import SceneError, SceneWarning, with_internal

ROOT = Path(__file__).resolve().parents[1]
COARSE = {"solver.element": "P1", "solver.mesh_size": 1.6}


@pytest.fixture(scope="module")
def scene():
    with pytest.warns(SceneWarning, match="solver.mesh_size"):
        return jsnap.load_scene().replace(COARSE)


@pytest.fixture(scope="module")
def model(scene, cache):
    return jsnap.build(scene)


@pytest.fixture(scope="module")
def full64(scene, cache):
    return jsnap.build(scene.replace({"solver.method": "full", "solver.dtype": "float64"}))


def _run(code: str, env=None, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        env={**os.environ, **(env or {})},
        cwd=cwd,
        timeout=900,
    )


# ------------------------------------------------------------------------------------------------
# Layers


# The host libraries the kernels must not import; JAX itself may (jaxlib's CPU linear algebra
# loads SciPy's LAPACK), so the blocker refuses only imports made by jsnap's own modules.
_BLOCKER = """
import importlib.abc, sys
HOST = ("skfem", "meshio", "trimesh", "gmsh", "scipy", "matplotlib", "flax", "optax")
class Blocker(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] in HOST:
            f = sys._getframe(1)
            skip = ("importlib", "_frozen_importlib")
            while f is not None and f.f_globals.get("__name__", "").startswith(skip):
                f = f.f_back
            caller = f.f_globals.get("__name__", "") if f is not None else ""
            if caller.split(".")[0] == "jsnap":
                raise ImportError(f"host library {name} imported by {caller}")
        return None
sys.meta_path.insert(0, Blocker())
"""


def test_core_runs_a_built_model_with_the_host_libraries_unimportable(model, tmp_path):
    """Build here; in a fresh process where jsnap's modules cannot import scikit-fem, meshio,
    trimesh, gmsh, SciPy, matplotlib, Flax or optax, import the kernels, step the model and
    roll it out: the same forces as here, and no host library loaded by jsnap."""
    (tmp_path / "model.pkl").write_bytes(pickle.dumps(model))
    res = jsnap.rollout(model, dtype="float64")
    np.save(tmp_path / "force.npy", np.asarray(res.insertion_force))
    proc = _run(
        _BLOCKER
        + """
import pickle, jax, numpy as np
import jsnap
from jsnap._core import parts, rollout, step, contact, collision, sdf, pmi  # the kernels
with jax.enable_x64(True):  # the model's float64 arrays stay float64 when unpickled
    model = pickle.load(open("model.pkl", "rb"))
prepared = jsnap.prepare(model)
state = jsnap.init_state(model, "float64")
state, out = jsnap.step(model, prepared, state, model.trajectory()[1])
assert int(out.flags) == 0, int(out.flags)
res = jsnap.rollout(model, dtype="float64")
ref = np.load("force.npy")
err = float(np.max(np.abs(np.asarray(res.insertion_force) - ref)))
loaded = sorted({m.split(".")[0] for m in sys.modules} & set(HOST) - {"scipy"})  # scipy: jaxlib's
print("RESULT", err, res.status(), loaded)
""",
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    line = next(x for x in proc.stdout.splitlines() if x.startswith("RESULT"))
    err, state, loaded = line.split(" ", 3)[1:]
    assert float(err) <= 1e-9 * float(np.max(np.abs(np.asarray(res.insertion_force))))
    assert state == "ok" and loaded == "[]"


def test_import_changes_no_process_setting():
    """``import jsnap`` (and a build and rollout) leave JAX's 64-bit mode and XLA_FLAGS alone."""
    proc = _run(
        """
import os, jax
before = os.environ.get("XLA_FLAGS")
import jsnap
sc = jsnap.load_scene().replace({"solver.element": "P1", "solver.mesh_size": 1.6})
m = jsnap.build(sc)
r = jsnap.rollout(m)
same = os.environ.get("XLA_FLAGS") == before
print("RESULT", jax.config.jax_enable_x64, same, r.insertion_force.dtype, jax.numpy.ones(1).dtype)
""",
        env={"XLA_FLAGS": "--xla_cpu_enable_fast_math=false"},
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    line = next(x for x in proc.stdout.splitlines() if x.startswith("RESULT"))
    assert line.split()[1:] == ["False", "True", "float32", "float32"]


def test_a_demoted_model_is_refused(model):
    """A model whose float64 arrays became float32 (cast, or unpickled outside 64-bit mode)
    would be factorised from rounded blocks: prepare says so instead."""
    with pytest.raises(ValueError, match="float64 arrays"):
        jsnap.prepare(model.astype("float32"))


# ------------------------------------------------------------------------------------------------
# Batched rollouts


@pytest.fixture(scope="module")
def product(cache):
    """The shipped default scene's model (reduced, P2)."""
    return jsnap.build(jsnap.load_scene())


def test_rollout_batch_equals_a_loop(product):
    """vmap over parameters, motions and start positions at once equals one rollout each, in
    float64 to the contact solver's tolerance: where a solve stops at its iteration cap (its
    residual 5e-5 above the 1e-6 asked on some steps of this scene) the last bits of the two
    compiled programs lead it to slightly different iterates. In float32 such steps differed
    by up to 6 % of the peak (the peak itself by 0.06 %), as the same rollout does from its
    float64 history (benchmarks/precision.py)."""
    model = product
    B = 3
    params = model.params.replace(E=jnp.array([2000.0, 2200.0, 2400.0]), friction=jnp.array([0.2, 0.3, 0.4]))
    base = model.trajectory()[1:]
    controls = np.stack([base + np.array([0.0, 0.0, -0.02 * k]) for k in range(B)])
    starts = np.stack([model.trajectory()[0] + np.array([0.0, 0.1 * k, 0.0]) for k in range(B)])
    batch = jsnap.rollout_batch(model, params, controls=controls, plug_start=starts, dtype="float64")
    assert batch.insertion_force.shape == (B, base.shape[0])
    assert np.asarray(batch.ok).all()
    for k in range(B):
        p = model.params.replace(E=params.E[k], friction=params.friction[k])
        one = jsnap.rollout(model, p, controls=controls[k], plug_start=starts[k], dtype="float64")
        for field in ("insertion_force", "base_force", "base_moment", "energy", "plug"):
            a, b = np.asarray(getattr(batch, field)[k]), np.asarray(getattr(one, field))
            assert np.abs(a - b).max() <= 1e-4 * np.abs(b).max(), field
    # The three differ: each lane used its own inputs.
    peaks = np.asarray(batch.insertion_force).max(axis=1)
    assert len(set(np.round(peaks, 6))) == B


def test_rollout_batch_argument_errors(model):
    with pytest.raises(ValueError, match="nothing is batched"):
        jsnap.rollout_batch(model)
    with pytest.raises(ValueError, match="batch sizes differ"):
        jsnap.rollout_batch(model, model.params.replace(E=jnp.ones(2) * 2200.0), plug_start=np.zeros((3, 3)))


# ------------------------------------------------------------------------------------------------
# Bad scene values: errors naming the key


@pytest.mark.parametrize(
    ("change", "key"),
    [
        ({"solver.dt": 10.0}, "solver.dt"),
        ({"solver.mesh_size": 100.0}, "solver.mesh_size"),
        ({"connector.undercut": 5.0, "connector.thickness": 1.2}, "connector.undercut"),
        ({"contact.margin": 0.1}, "contact.margin"),  # internal: not a scene key
        ({"solver.method": "modal"}, "solver.method"),  # internal choice
    ],
)
def test_meaningless_scene_values_are_errors_naming_the_key(change, key):
    with pytest.raises(SceneError, match=key.replace(".", r"\.")):
        jsnap.load_scene().replace(change)


def test_dt_error_says_what_would_work():
    with pytest.raises(SceneError, match=r"233 mm|steps; at least 20") as err:
        jsnap.load_scene().replace({"solver.dt": 10.0})
    assert "solver.dt <=" in str(err.value)


def test_internal_keys_are_reachable_for_tests_and_benchmarks():
    sc = with_internal(jsnap.load_scene(), {"contact.margin": 0.05, "contact.solver": "pgs"})
    assert sc.get("contact.margin") == 0.05 and sc.get("contact.solver") == "pgs"
    # ... and survive a later user-level replace.
    assert sc.replace({"solver.dt": 5e-4}).get("contact.solver") == "pgs"


def test_scene_files_reject_internal_keys(tmp_path):
    text = (jsnap.load_scene().source and Path(jsnap.load_scene().source).read_text()) + "\n"
    path = tmp_path / "s.toml"
    path.write_text(text.replace("[contact]\n", "[contact]\nmargin = 0.1\n"))
    with pytest.raises(SceneError, match=r"unknown key contact\.margin"):
        jsnap.load_scene(path)


# ------------------------------------------------------------------------------------------------
# Bad parameters: an error when concrete, a flagged result when traced


BAD = [("E", math.nan), ("E", -1.0), ("friction", math.nan), ("friction", -0.5), ("nu", 0.6)]


@pytest.mark.parametrize(("name", "value"), BAD)
def test_bad_parameters_are_errors_when_concrete(model, name, value):
    with pytest.raises(ValueError, match=f"Params.{name}"):
        jsnap.rollout(model, model.params.replace(**{name: value}))


def test_transformations_outside_64_bit_mode_are_refused_with_the_remedy(model):
    """A user's jit compiles after jsnap's own 64-bit scope has closed: say how to run it."""
    with pytest.raises(RuntimeError, match=r"with jax\.enable_x64\(True\)"):
        jax.jit(lambda E: jsnap.rollout(model, model.params.replace(E=E)))(2200.0)


@pytest.fixture(scope="module")
def under_jit(model):
    """One compiled program for every parameter set: the values are traced."""
    with jax.enable_x64(True):
        run = jax.jit(lambda p: jsnap.rollout(model, p))
        yield lambda p: run(p)


@pytest.mark.parametrize(("name", "value"), BAD)
def test_bad_parameters_are_flagged_under_jit(model, under_jit, name, value):
    res = under_jit(model.params.replace(**{name: value}))
    flags = np.asarray(res.flags)
    assert np.all(flags & status.INVALID_PARAMS), "every step flagged"
    assert not bool(res.ok)
    assert np.all(np.isnan(np.asarray(res.insertion_force))), "no silent zeros: NaN"
    assert res.status().startswith("step 1: invalid parameters")
    with pytest.raises(jsnap.SimulationError, match="invalid parameters"):
        res.check()
    # The same program with the scene's value is clean.
    good = under_jit(model.params)
    assert bool(good.ok) and np.isfinite(np.asarray(good.insertion_force)).all()


@pytest.fixture(scope="module")
def under_vmap(model):
    """Lane 0 the scene's parameters, lane i + 1 the scene's with BAD[i]: one vmap of a user's
    function over them, and jsnap's own rollout_batch."""
    columns = {f: [float(getattr(model.params, f))] * (len(BAD) + 1) for f in FIELDS}
    for i, (name, value) in enumerate(BAD):
        columns[name][i + 1] = value
    batch = model.params.replace(**{f: jnp.array(v) for f, v in columns.items()})
    with jax.enable_x64(True):
        users = jax.vmap(lambda p: jsnap.rollout(model, p))(batch)
    return users, jsnap.rollout_batch(model, batch)


@pytest.mark.parametrize(("lane", "bad"), list(enumerate(BAD, start=1)), ids=[f"{n}={v}" for n, v in BAD])
def test_bad_parameters_are_flagged_under_vmap(under_vmap, lane, bad):
    """Each lane's flags are its own: the bad lane is flagged and NaN, the good one runs."""
    for res in under_vmap:
        ok = np.asarray(res.ok)
        assert ok[0] and not ok[lane]
        assert np.isfinite(np.asarray(res.insertion_force[0])).all()
        assert np.isnan(np.asarray(res.insertion_force[lane])).all()
        assert res.status()[0] == "ok" and res.status()[lane].startswith("step 1: invalid parameters")


def test_non_finite_steps_are_flagged_at_the_step(model):
    """A motion that turns NaN mid-way (under jit, so not checked on the host) is flagged from
    that step on, and the message names it."""
    controls = np.array(model.trajectory()[1:])
    controls[40:, 2] = np.nan
    with jax.enable_x64(True):
        res = jax.jit(lambda c: jsnap.rollout(model, controls=c))(controls)
    flags = np.asarray(res.flags)
    assert not np.any(flags[:40] & status.ERRORS)
    assert flags[40] & status.NON_FINITE
    assert res.status().startswith("step 41: non-finite")


def test_energy_creation_is_flagged(model):
    """The passivity check of the result: the part never holds more energy than the rigid
    part's work put in. A clean rollout passes it by a wide margin; the same history with the
    work of one step understated (as a failed contact solve would make it) is flagged there."""
    from jsnap._core.rollout import _run
    from jsnap._core.step import prepare

    with jax.enable_x64(True):
        prepared = prepare(model)
        controls = jnp.asarray(model.trajectory()[1:], jnp.float64)
        out, xs, start = _run(model, prepared, controls, jnp.asarray(model.plug_start), False)
        clean = _result(out, xs, start, prepared.valid, model)
        assert not np.any(np.asarray(clean.flags) & status.ENERGY_CREATED)
        excess = np.asarray(out.energy - jnp.cumsum(out.work))
        assert excess.max() <= 1e-6 * np.abs(np.asarray(out.energy)).max()
        k = int(np.argmax(np.asarray(out.energy)))  # most energy stored: the snap's peak
        # The work so far, less what friction dissipated, less a tenth of the energy held.
        deficit = jnp.cumsum(out.work)[k] - 0.9 * out.energy[k]
        forged = eqx.tree_at(lambda o: o.work, out, out.work.at[k].add(-deficit))
        flagged = _result(forged, xs, start, prepared.valid, model)
    flags = np.asarray(flagged.flags)
    assert not np.any(flags[:k] & status.ENERGY_CREATED) and flags[k] & status.ENERGY_CREATED
    assert f"step {k + 1}: the deformable part gained more energy" in flagged.status()


def test_deep_runs_flag_exactly_the_long_runs():
    """The run-length rule against a plain loop over random histories (a batch axis first):
    every step of a run of more than PENETRATION_STEPS steps deeper than the limit, from the
    run's first step, and nothing else."""
    from jsnap._core.rollout import PENETRATION_STEPS, _deep_runs

    rng = np.random.default_rng(0)
    pen = rng.choice([0.0, 1.0, 5.0], size=(40, 60), p=[0.15, 0.05, 0.8])
    got = np.asarray(_deep_runs(jnp.asarray(pen), 2.0))
    want = np.zeros_like(got)
    for b, row in enumerate(pen):
        k = 0
        while k < row.size:
            if row[k] > 2.0:
                end = k
                while end < row.size and row[end] > 2.0:
                    end += 1
                want[b, k:end] = end - k > PENETRATION_STEPS
                k = end
            else:
                k += 1
    assert want.any() and not want.all()
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("stabilisation", [0.0, 0.8])
def test_a_point_held_inside_the_rigid_part_is_flagged(model, stabilisation):
    """The rigid part held still, 0.1 mm (5 contact spacings) into the arm's outer face. Without
    stabilisation the contact holds velocities only: the part at rest stays put, the overlap
    stays exactly 0.1 mm with no force, and the result is flagged from its first step. With
    stabilisation the contact pushes the arm out (doing work, which the energy check flags)
    and the overlap falls below the limit before the run is long enough to be flagged."""
    from jsnap._core.rollout import penetration_depth

    ct = model.contact
    held = eqx.tree_at(lambda m: m.contact, model, type(ct)(ct.solver, ct.capacity, ct.margin, ct.compliance,
                                                               stabilisation))  # fmt: skip
    latched = np.asarray(model.trajectory())[-1]  # the rigid part's face on the arm's outer face
    inside = latched - np.array([0.1, 0.0, 0.0])
    res = jsnap.rollout(held, controls=np.repeat(inside[None], 20, 0), plug_start=inside)
    pen, flags = np.asarray(res.penetration), np.asarray(res.flags)
    assert pen[0] == pytest.approx(0.1, rel=1e-5)
    assert penetration_depth(model) == pytest.approx(4 * 0.02)
    if stabilisation == 0:
        np.testing.assert_allclose(pen, 0.1, rtol=1e-5)
        np.testing.assert_allclose(np.asarray(res.insertion_force), 0.0, atol=1e-6)
        assert np.all(flags & status.DEEP_PENETRATION) and not res.ok
        assert res.status().startswith("step 1: a point of the deformable part stayed inside the rigid part")
    else:
        assert pen[1] < penetration_depth(model) < pen[0]  # pushed out within a step
        assert not np.any(flags & status.DEEP_PENETRATION)


# ------------------------------------------------------------------------------------------------
# The command line


def _scene_file(tmp_path, scene_changes: str = "") -> Path:
    text = Path(jsnap.load_scene().source).read_text()
    text = text.replace('element = "P2"', 'element = "P1"').replace("mesh_size = 0.8", "mesh_size = 1.6")
    path = tmp_path / "coarse.toml"
    path.write_text(text + scene_changes)
    return path


def test_cli_refuses_a_bad_out_folder_before_any_work(tmp_path, capsys):
    afile = tmp_path / "a_file"
    afile.write_text("x")
    for out in (afile, afile / "under"):
        assert cli_main(["simulate", str(_scene_file(tmp_path)), "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert f"--out {out}" in err and "jsnap: error" in err and "P1 mesh" not in err  # nothing built
    # A place nobody can write, root included.
    assert cli_main(["simulate", "--out", "/proc/jsnap-out"]) == 2
    assert "--out /proc/jsnap-out: cannot write there" in capsys.readouterr().err


def test_cli_json_summary_is_strict_and_timings_apart(tmp_path, capsys):
    out = tmp_path / "out"
    assert cli_main(["simulate", str(_scene_file(tmp_path)), "--out", str(out), "--json"]) == 0
    text = capsys.readouterr().out.strip().splitlines()[-1]

    def no_constants(name):
        raise AssertionError(f"non-strict JSON constant {name}")

    summary = json.loads(text, parse_constant=no_constants)
    assert summary["status"] == "ok" and summary["method"] == "reduced"
    for key in ("steps", "dt", "steps_per_second", "compile_seconds", "build_seconds", "peak_insertion_force_N",
                "peak_base_force_N", "dof", "reduced_orders"):  # fmt: skip
        assert key in summary, key
    assert summary["steps_per_second"] * summary["run_seconds"] == pytest.approx(summary["steps"])
    assert summary["compile_seconds"] > 0 and summary["build_seconds"] > 0
    assert json.loads((out / "summary.json").read_text(), parse_constant=no_constants)["status"] == "ok"
    header = (out / "forces.csv").read_text().splitlines()[0]
    assert header.endswith(
        "energy_Nmm,work_Nmm,friction_dissipation_Nmm,normal_dissipation_Nmm,penetration_mm,flags"
    )
    assert summary["max_penetration_mm"] >= 0 and summary["max_penetration_resolutions"] < 4
    # Undamped: up to the peak the work went into the part's energy, friction and the normal forces.
    budget = summary["energy_to_peak"]
    assert budget["work_Nmm"] > 0 and budget["friction_dissipation_Nmm"] > 0
    taken = budget["energy_Nmm"] + budget["friction_dissipation_Nmm"] + budget["normal_dissipation_Nmm"]
    assert taken == pytest.approx(budget["work_Nmm"], rel=1e-4)
    assert not any("normal contact forces" in w for w in summary["warnings"])


def test_cli_exits_non_zero_on_a_flagged_result(tmp_path, capsys):
    """Dropped contacts make a wrong force: the run writes its outputs, names the step and
    exits with 1."""
    path = _scene_file(tmp_path)
    text = path.read_text().replace("[contact]\n", "[contact]\ncapacity = 2\n")
    path.write_text(text)
    out = tmp_path / "out"
    assert cli_main(["simulate", str(path), "--out", str(out), "--json"]) == 1
    captured = capsys.readouterr()
    summary = json.loads(captured.out.strip().splitlines()[-1])
    assert summary["status"].startswith("step ") and "contact.capacity" in summary["status"]
    assert "jsnap: error: step " in captured.err
    assert (out / "forces.csv").is_file()


def test_a_build_that_would_not_fit_in_memory_is_refused_naming_the_setting():
    """A dense model of 30 000 dof needs ~43 GiB: refused before anything is allocated, with
    the setting to change; the reduced model of the same part fits."""
    from jsnap._build.model import BuildError, check_memory

    with pytest.raises(BuildError, match=r"solver\.method = 'full' with 30000 dof needs about 40\.2 GiB.*"
                       r"solver\.method = 'reduced' or a larger solver\.mesh_size"):  # fmt: skip
        check_memory(30000, "full", available=16 * 2**30)
    assert check_memory(30000, "reduced", available=16 * 2**30) < 16 * 2**30
