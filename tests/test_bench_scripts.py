"""The frequency, throughput, precision, xla_option and xla_kernels benchmarks: registered with `jsnap bench`,
and their committed results have the headline the README table reads (positive rates, the
expected keys); the committed precision measurement justifies the default rollout dtype.

Running the scripts is tested by ``tests/test_bench.py::test_quick_benchmarks_run`` (``jsnap bench
--quick``); quick outputs are not committed.
"""

import json
from pathlib import Path

import numpy as np
import pytest

import jsnap
from jsnap._apps import bench as _bench
from jsnap._apps.xla import LIBRARY_FLAG, SMALL_LOOP_OPTION
from jsnap._build.model import rollout_dtype

# The reduced models' float32 peaks under both kernel choices: round-off, but the box lid's
# tilted peak is a single step's spike of its sawtooth (docs/validation.md), which round-off moves.
PEAK_AGREEMENT = 0.01

ROOT = Path(__file__).resolve().parent.parent / "benchmarks"


def _load(stem):
    path = ROOT / "results" / f"{stem}.json"
    if not path.is_file():
        pytest.skip(f"{path.name} not present")
    return json.loads(path.read_text())


@pytest.mark.parametrize("name", ["frequency", "throughput", "precision", "xla_option", "xla_kernels", "scale"])
def test_registered_with_quick_variant(name):
    bench = {b.name: b for b in _bench.available(ROOT)}
    assert name in bench and bench[name].quick


def test_frequency_headline():
    d = _load("frequency")
    h = d["headline"]
    meshes = ["coarse", "fine"]
    assert set(h["full_dof"]) == set(meshes)
    for key in ("scan_steps_per_second", "python_steps_per_second", "scan_compile_seconds"):
        for mesh in meshes:
            assert set(h[key][mesh]) == {"1", "2", "3", "4"}
    rates = [
        v
        for key in ("scan_steps_per_second", "python_steps_per_second")
        for m in meshes
        for v in h[key][m].values()
    ]
    assert min(rates) > 0
    assert 600 <= h["full_dof"]["coarse"] <= 720 and 1150 <= h["full_dof"]["fine"] <= 1400
    assert "dof" in _bench._frequency(d)


def test_throughput_headline():
    d = _load("throughput")
    h = d["headline"]
    for key in ("device", "full_dof", "dof", "best_batch", "best_scene_steps_per_second"):
        assert key in h
    assert h["best_scene_steps_per_second"] > 0 and h["batch_1_scene_steps_per_second"] > 0
    assert h["dof"] < h["full_dof"]
    for result in d["results"].values():  # one entry per platform (cpu, gpu), kept apart
        for rows in result["series"].values():
            assert [r["batch"] for r in rows] == sorted(r["batch"] for r in rows)
            assert all(r["scene_steps_per_second"] > 0 for r in rows)
    assert "scene-steps/s" in _bench._throughput(d)


def test_precision_headline_justifies_the_default_dtype():
    """Per method, the default rollout dtype is float32 only where the committed measurement puts
    the float32 peak within 1 % of float64's, and the measurement's defaults are the library's
    (a change of either needs the other)."""
    d = _load("precision")
    h = d["headline"]
    assert not h["quick"]
    assert set(h["methods"]) == {"reduced", "full", "segmented"}
    for method, v in h["methods"].items():
        assert v["peak_float32_N"] > 0 and v["peak_float64_N"] > 0 and v["ok"]
        assert v["float32_within_1_percent"] == (abs(v["float32_vs_own_float64"]) <= h["threshold"])
        assert v["default_dtype"] == rollout_dtype(jsnap.load_scene().replace({"solver.method": method}))
        if v["default_dtype"] == "float32":
            assert v["float32_within_1_percent"], method
    assert h["defaults_justified"] and h["all_ok"]
    assert "float64 peak" in _bench._precision(d)


def test_xla_option_headline():
    d = _load("xla_option")
    h = d["headline"]
    assert not h["quick"]
    assert h["with"]["steps_per_second"] > 0 and h["without"]["steps_per_second"] > 0
    assert h["rounds"] == len(d["rounds"]) >= 3
    # Each round measured one process with the option and one without.
    assert all(r["with"]["small_loop_option"] and not r["without"]["small_loop_option"] for r in d["rounds"])
    assert all(r["with"]["configure_xla_cpu"] in ("set", "user") for r in d["rounds"])
    assert h["speedup"] == pytest.approx(h["with"]["steps_per_second"] / h["without"]["steps_per_second"])
    # The option changes how the solver's loops are compiled, not what they compute.
    assert h["float64_force_max_abs_diff_rel_peak"] < 1e-6
    assert "steps/s" in _bench._xla_option(d)


def test_xla_kernels_headline():
    """Every preset measured in both kinds of process, each round one of each; the library
    processes ran with XLA's default fusions, the others with configure_xla_cpu's flags. The
    option changes which kernels run, not what they compute: the reduced models' float32 peaks
    agree to round-off, a step of the force's sawtooth at most."""
    d = _load("xla_kernels")
    h = d["headline"]
    assert not d["quick"] and d["rounds_run"] == len(d["rounds"]) >= 3
    assert {"default", "two_hook_clip", "box_lid", "annular", "cable_latch"} <= set(h)
    for r in d["rounds"]:
        assert LIBRARY_FLAG not in r["library"]["xla_flags"] and SMALL_LOOP_OPTION in r["library"]["xla_flags"]
        assert r["own"]["configure_xla_cpu"] == "set" and f"{LIBRARY_FLAG}=" in r["own"]["xla_flags"].split()
    for name, v in h.items():
        assert v["ok"], name
        assert v["library_steps_per_second"] > 0 and v["own_steps_per_second"] > 0
        assert v["speedup"] == pytest.approx(v["own_steps_per_second"] / v["library_steps_per_second"])
        assert v["peak_rel_diff"] < PEAK_AGREEMENT, name
    assert "steps/s" in _bench._xla_kernels(d)


def test_scale_headline():
    """The committed scale run: at least four sizes of the default hook up to ~100k dofs, each
    measured in its own process, the reduced model far smaller than the full one, a valid rollout
    behind every quoted rate of the default hook, and the design-guide hook's peak force beside
    the guide's (its rollout's flags recorded)."""
    d = _load("scale")
    rows = [r for r in d["rows"] if r["part"] == "default_hook"]
    sizes = sorted(r["full_dof"] for r in rows)
    assert len(sizes) >= 4 and sizes[-1] >= 90_000
    for r in d["rows"]:
        assert sum(r["orders"]) < r["full_dof"] / 20
        assert r["build_peak_rss_bytes"] > 0 and r["reduction_seconds"] > 0 and r["scan_steps_per_second"] > 0
        assert r[r["quoted_dtype"]]["ok"] or r["part"] != "default_hook"
        assert r[r["quoted_dtype"]]["ok"] == (r[r["quoted_dtype"]]["status"] == "ok")
    h = d["headline"]
    assert h["largest_full_dof"] == sizes[-1]
    assert set(h["targets_met"]) == {"build_seconds", "peak_rss_gb", "steps_per_second"}
    # The same meshes with patch loads: the order no larger than the point loads' on every
    # mesh, and each curve compared with the point-load curve recorded beside it.
    point = {r["mesh_size"]: r for r in rows}
    patched = [r for r in d["rows"] if r["part"] == "default_hook_patch"]
    assert {r["mesh_size"] for r in patched} == set(point)
    for r in patched:
        p = point[r["mesh_size"]]
        assert r["full_dof"] == p["full_dof"] and r["orders"][1] <= p["orders"][1]
        cmp = r["against_point_loads"]
        a, b = (np.asarray(x[cmp["dtype"]]["insertion_force_N"]) for x in (r, p))
        assert cmp["peak_ratio"] == pytest.approx(a.max() / b.max())
        assert cmp["rmse_of_peak"] == pytest.approx(np.sqrt(np.mean((a - b) ** 2)) / b.max())
    lp = h["load_patch"]
    assert lp["largest_full_dof"] == sizes[-1]
    assert set(lp["targets_met"]) == set(h["targets_met"])
    g = h["design_guide_hook"]
    assert g["peak_N"] > 0 and g["peak_over_guide"] == pytest.approx(g["peak_N"] / g["design_guide_N"])
    assert "steps/s" in _bench._scale(d)


def test_annular_spacing_headline():
    """The committed candidate-spacing sweep of the annular snap backs what docs/validation.md
    says of it: the shipped spacing among those swept and its rollout unflagged, the averaged
    rise up to 0.20 mm within 3 % of CalculiX at every spacing, and the reduced model within
    1 % of the full model's peak at each."""
    d = _load("annular_spacing")
    rows = {r["spacing_mm"]: r for r in d["rows"]}
    assert d["shipped_spacing_mm"] in rows and rows[d["shipped_spacing_mm"]]["full_float64"]["flags"] == "ok"
    assert d["travels_mm"][:2] == [0.15, 0.20]
    for r in rows.values():
        assert all(abs(x - 1) < 0.03 for x in r["full_float64"]["averaged_over_calculix"][:2])
        assert abs(r["reduced_float32"]["peak_over_full"] - 1) < 0.01
        assert r["reduced_float32"]["rmse_rise_of_full_peak"] < 0.01
    assert "CalculiX" in _bench._annular_spacing(d)


def test_part_size_headline():
    """The committed size sweep on the shipped meshes: dimensional analysis (force over k^2
    independent of k) holds within 1 % for the preset at every size and friction, the sizes
    sampled alike give the same history, and each run's status and buffer are recorded."""
    d = _load("part_size")
    for r in d["preset"]:
        for mu in (0.0, 0.3):
            assert abs(r[f"peak_ratio_mu{mu}"] - 1) < 0.01, (r["k"], mu)
            assert r[f"status_mu{mu}"] == "ok"
            twin = [
                v
                for key, v in r.items()
                if key.startswith("max_difference_pct_to_k") and key.endswith(f"mu{mu}")
            ]
            assert all(v < 1e-4 for v in twin), (r["k"], mu, twin)
    files = {r["k"]: r for r in d["files"]}
    assert abs(files[0.1]["peak_ratio_mu0.3"] - 1) < 0.03 and abs(files[10.0]["peak_ratio_mu0.0"] - 1) < 0.03
    assert "files" in _bench._part_size(d)


def test_part_size_large_file_hook_with_friction_is_flagged():
    """The file hook ten times larger at friction 0.3: after the snap its lip stays inside the
    rigid part and the force runs away. The run is flagged DEEP_PENETRATION (no silent wrong
    answer), and run again with the remedy the flag's message names it is unflagged and obeys
    dimensional analysis; no other run of the sweep is flagged."""
    d = _load("part_size")
    r = {c["k"]: c for c in d["files"]}[10.0]
    assert abs(r["peak_ratio_mu0.3"] - 1) > 0.5
    assert r["status_mu0.3"] != "ok" and "stayed inside the rigid part" in r["status_mu0.3"]
    assert r["status_mu0.3_stabilised"] == "ok" and abs(r["peak_ratio_mu0.3_stabilised"] - 1) < 0.03
    others = [
        (c["k"], mu)
        for family in ("preset", "files")
        for c in d[family]
        for mu in (0.0, 0.3)
        if c[f"status_mu{mu}"] != "ok" and (family, c["k"], mu) != ("files", 10.0, 0.3)
    ]
    assert not others, others


def test_penetration_headline():
    """The committed penetration sweep: no shipped scene comes near the DEEP_PENETRATION limit
    (each run's longest spell beyond the limit at most 2 steps, where more than 5 are flagged),
    nor does the ten-times file hook frictionless at its time step or half of it; that hook at
    friction 0.3 (its lip lost in the snap) is flagged. The limit recorded is the library's."""
    from jsnap._core.rollout import PENETRATION_DEPTH, PENETRATION_STEPS

    d = _load("penetration")
    assert d["limit_resolutions"] == PENETRATION_DEPTH and d["limit_steps"] == PENETRATION_STEPS
    shipped = {"default", "two_hook_clip", "box_lid", "annular", "cable_latch", "pipe_clip", "own_connector"}
    assert set(d["parts"]) == shipped | {"file_hook_10x", "file_hook_10x_half_dt"}
    lost = d["parts"]["file_hook_10x"]["mu0.3"]
    assert lost["longest_run_deeper_than_limit"] > 3 * PENETRATION_STEPS
    assert "stayed inside the rigid part" in lost["status"]
    for name, r in d["parts"].items():
        for mu in (0.0, 0.3):
            row = r[f"mu{mu}"]
            assert max(row["depth_resolutions"]) == pytest.approx(row["deepest_resolutions"])
            if row is not lost:
                assert row["status"] == "ok", (name, mu)
                assert row["longest_run_deeper_than_limit"] <= 2, (name, mu)
    assert "DEEP_PENETRATION" in _bench._penetration(d)
