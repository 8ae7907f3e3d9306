"""Simulation frequency of the paper's four models (its Fig. 4): single-scene steps per second
for a coarse (~660 dof) and a fine (~1300 dof) mesh, in a ``lax.scan`` rollout and stepping a
jitted step from Python, with the compile times apart.

    python benchmarks/frequency.py [--quick] [--models 1 2 3 4] [--runs 3]

The models are the default scene (P2 elements, float32 rollout, the scene's contact settings:
64 slots, up to 500 APGD iterations) with

* Model 1: full FEM socket, exact collision (``solver.sdf = "mesh"``: the plug's triangle mesh);
* Model 2: full FEM socket, neural SDF of the plug (``solver.sdf = "neural"``);
* Model 3: Model 2 with the socket segmented (``solver.method = "segmented"``);
* Model 4: Model 3 with every segment reduced (``solver.method = "reduced"``, default tolerance).

Meshes: P2 at ``solver.mesh_size`` 2.5 mm (690 free dofs) and 1.7 mm (1218 free dofs), the
closest this mesher gets to the paper's 663 and 1266 (P1 gives 645 at 1.0 mm but then jumps
from 936 to 1344 and 1407).

Timings: the PMI operator is prepared once, outside them. Scan: the first call of
``jsnap.rollout`` compiles and runs; the steady time is the median of ``--runs`` further calls,
and the compile time is the first call minus the steady time (Model 1, 3-7 s a pass, is not run
again: its compile time is a two-step rollout's first call, its run time the first call's
less that, and it makes one Python pass). Python: a jitted
``step(state, control)`` is called once per step of the same motion from a Python loop; its
first call (compile + one step) minus a steady step is its compile time, and the rate is the
median over ``--runs`` passes through the motion. Every run covers the scene's whole motion
(233 steps, 2.32 mm at 10 mm/s; contact from the second step on).

``--quick``: the coarse mesh only, Models 1 and 4 only, one timed run each, and a 20-step motion
(0.4 mm at 20 mm/s; a scene may not have fewer steps), for CI: it checks that everything runs,
its rates are rough. If the neural SDF is not cached (it trains once, ~30 s here), the quick run
uses the analytic SDF for Models 2-4 instead and says so in the JSON (``sdf_models_2_4``).
Writes benchmarks/results/frequency{,_quick}.{json,png}.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _common import FLOAT32, code_version, jitted_step, load_scene, scan_timing

import jsnap
from jsnap._build.neural_sdf import NeuralSDFConfig, cache_key, cache_path, shipped_path
from jsnap._geometry.presets import default_rigid

# XLA's small-loop option, before the first JAX computation (the committed timings have it).
jsnap.configure_xla_cpu()

OUT = Path(__file__).parent / "results"
ELEMENT = "P2"
MESHES = {"coarse": 2.5, "fine": 1.7}  # mm -> 690 and 1218 free dofs (paper: 663, 1266)
MODELS = {
    1: ("full", "mesh", "full FEM, exact (mesh) SDF"),
    2: ("full", "neural", "full FEM, neural SDF"),
    3: ("segmented", "neural", "segmented, neural SDF"),
    4: ("reduced", "neural", "segmented + reduced, neural SDF"),
}
QUICK_MOTION = {"motion.stroke": 0.4, "motion.speed": 20.0}  # 20 steps of 1 ms, the fewest allowed


def machine(load) -> str:
    return (
        f"{platform.machine()} {platform.system()}, {os.cpu_count()} CPU cores, "
        f"jax {jax.devices()[0].platform}, load average {min(load):.1f}-{max(load):.1f}"
    )


def neural_cached(scene) -> bool:
    """Whether the default neural SDF of the scene's plug is cached or shipped (no training needed)."""
    key = cache_key(default_rigid("cantilever", scene["connector"], scene["plug"]).mesh(), NeuralSDFConfig())
    return cache_path(key).is_file() or shipped_path(key).is_file()


def python_timing(model, prepared, runs: int):
    """(first call seconds: compile + one step, seconds of each pass through the motion) of a
    jitted step called once per step from Python."""
    one, dyn, state0 = jitted_step(model, prepared)
    controls = jnp.asarray(model.trajectory()[1:], state0.x.dtype)
    t0 = time.perf_counter()
    jax.block_until_ready(one(dyn, state0, controls[0]))
    first = time.perf_counter() - t0
    times = []
    for _ in range(runs):
        s = state0
        t0 = time.perf_counter()
        for c in controls:
            s = one(dyn, s, c)
        jax.block_until_ready(s)
        times.append(time.perf_counter() - t0)
    return first, times


def run(mesh: str, number: int, changes: dict, runs: int) -> dict:
    method, sdf, label = MODELS[number]
    scene = load_scene(
        {
            "solver.element": ELEMENT,
            "solver.mesh_size": MESHES[mesh],
            "solver.method": method,
            "solver.sdf": sdf,
            **FLOAT32,  # every model in float32 (the default is float64 for all but the reduced one)
            **changes,
        }
    )
    t0 = time.perf_counter()
    model = jsnap.build(scene)
    build_s = time.perf_counter() - t0
    prepared = jsnap.prepare(model)
    # Model 1 (35-80 steps/s: 3-7 s a pass) is not run again in the scan (its compile time is
    # measured apart) and makes one Python pass: the 30-minute budget of `jsnap bench`. Its pass
    # covers the whole motion: its exact mesh query grows with the points near the plug, so the
    # early steps are cheaper than the rest. (In the quick run's 20-step motion a second call is
    # cheaper than the two-step compile.)
    slow = number == 1 and not changes
    res, first, scan_times = scan_timing(model, prepared, 0 if slow else runs)
    n = int(res.energy.shape[0])
    py_first, py_times = python_timing(model, prepared, 1 if slow else runs)
    steady, py_steady = float(np.median(scan_times)), float(np.median(py_times))
    F = np.asarray(res.insertion_force, np.float64)
    row = {
        "mesh": mesh,
        "mesh_size": MESHES[mesh],
        "model": number,
        "label": label,
        "method": method,
        "sdf": sdf,
        "full_dof": model.full_dof,
        "dof": model.n_dof,
        "build_seconds": build_s,
        "steps": n,
        "scan_steps_per_second": n / steady,
        "scan_compile_seconds": first - steady,
        "python_steps_per_second": n / py_steady,
        "python_compile_seconds": py_first - py_steady / n,
        "scan_run_seconds": scan_times,
        "python_run_seconds": py_times,
        "peak_N": float(F.max()),
        "iterations_mean": float(np.asarray(res.iterations).mean()),
        "max_overflow": int(np.asarray(res.overflow).max()),
    }
    if method != "full":
        row["orders"] = [int(k) for k in model.part.orders]
    return row


def chart(rows, title, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    meshes = [m for m in MESHES if any(r["mesh"] == m for r in rows)]
    numbers = sorted({r["model"] for r in rows})
    series = [(m, kind) for m in meshes for kind in ("scan", "python")]
    width = 0.8 / len(series)
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(14, 5), gridspec_kw={"width_ratios": [3, 2]})
    colors = {"coarse": ("C0", "#9ecae1"), "fine": ("C3", "#fcae91")}
    for j, (mesh, kind) in enumerate(series):
        pick = {r["model"]: r for r in rows if r["mesh"] == mesh}
        dof = next(iter(pick.values()))["full_dof"]
        x = np.arange(len(numbers)) + (j - (len(series) - 1) / 2) * width
        ys = [pick[k][f"{kind}_steps_per_second"] if k in pick else np.nan for k in numbers]
        color = colors[mesh][0 if kind == "scan" else 1]
        what = "lax.scan rollout" if kind == "scan" else "jitted step called from Python"
        bars = ax.bar(x, ys, width, color=color, label=f"{mesh} ({dof} dof), {what}")
        ax.bar_label(bars, fmt="%.3g", fontsize=7)
        cs = [pick[k][f"{kind}_compile_seconds"] if k in pick else np.nan for k in numbers]
        bars = bx.bar(x, cs, width, color=color, label=f"{mesh} ({dof} dof), {kind}")
        bx.bar_label(bars, fmt="%.0f", fontsize=7)
    names = [f"Model {k}\n{MODELS[k][2].replace(', ', chr(10))}" for k in numbers]
    for a in (ax, bx):
        a.set_xticks(np.arange(len(numbers)), names, fontsize=8)
        a.grid(alpha=0.3, axis="y", which="both")
    ax.set_yscale("log")
    ax.set_ylabel("simulation frequency (steps/s = Hz), steady state")
    ax.set_title("single scene, compiled (median of runs)", fontsize=10)
    ax.legend(fontsize=7, loc="upper left")
    bx.set_ylabel("compile time (s)")
    bx.set_title("compile time: first call minus a steady call", fontsize=10)
    bx.legend(fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None):
    # The Python rate steps a jitted jsnap.step, which runs in JAX's 64-bit mode (see
    # _common.jitted_step), as every computation here did before the redesign.
    with jax.enable_x64(True):
        _main(argv)


def _main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="coarse mesh, 20-step motion")
    ap.add_argument("--models", type=int, nargs="+", choices=sorted(MODELS), default=None)
    ap.add_argument("--runs", type=int, default=None, help="timed runs per rate (median); 3, quick 1")
    a = ap.parse_args(argv)
    # The quick run (a CI smoke run) times the two ends, Models 1 and 4, once each.
    a.models = a.models or ([1, 4] if a.quick else sorted(MODELS))
    a.runs = a.runs or (1 if a.quick else 3)
    t_start = time.perf_counter()
    code = code_version()  # the code as imported, before anyone commits during the run
    meshes = ["coarse"] if a.quick else list(MESHES)
    changes = dict(QUICK_MOTION) if a.quick else {}
    note = None
    if a.quick and not neural_cached(jsnap.load_scene()):
        MODELS.update(
            {
                k: (m, "analytic", lbl.replace("neural", "analytic"))
                for k, (m, s, lbl) in MODELS.items()
                if s == "neural"
            }
        )
        note = "neural SDF not cached: Models 2-4 used the analytic SDF (rounded box) instead"
    load = [os.getloadavg()[0]]
    rows = []
    for mesh in meshes:
        for k in a.models:
            rows.append(run(mesh, k, changes, a.runs))
            print(rows[-1], flush=True)
            load.append(os.getloadavg()[0])
    mach = machine(load)

    def rates(key):
        return {m: {str(r["model"]): r[key] for r in rows if r["mesh"] == m} for m in meshes}

    headline = {
        "element": ELEMENT,
        "mesh_size_mm": {m: MESHES[m] for m in meshes},
        "full_dof": {m: next(r["full_dof"] for r in rows if r["mesh"] == m) for m in meshes},
        "steps": rows[0]["steps"],
        "sdf_models_2_4": MODELS[2][1],
        "scan_steps_per_second": rates("scan_steps_per_second"),
        "python_steps_per_second": rates("python_steps_per_second"),
        "scan_compile_seconds": rates("scan_compile_seconds"),
        "python_compile_seconds": rates("python_compile_seconds"),
    }
    doc = {
        "code": code,
        "machine": mach,
        "quick": a.quick,
        "changes": changes,
        "runs": a.runs,
        "note": note,
        "models": {str(k): {"method": v[0], "sdf": v[1], "label": v[2]} for k, v in MODELS.items()},
        "headline": headline,
        "rows": rows,
        "wall_seconds": time.perf_counter() - t_start,
    }
    stem = "frequency_quick" if a.quick else "frequency"
    OUT.mkdir(exist_ok=True)
    (OUT / f"{stem}.json").write_text(json.dumps(doc, indent=1))
    motion = "20-step motion (0.4 mm at 20 mm/s)" if a.quick else "default motion, 233 steps"
    title = (
        f"Simulation frequency, one scene ({ELEMENT}, float32, {motion}); Models 2-4 SDF: {MODELS[2][1]}\n"
        f"{mach}"
    )
    chart(rows, title, OUT / f"{stem}.png")
    print(f"wrote {OUT / stem}.json in {doc['wall_seconds']:.0f} s", flush=True)


if __name__ == "__main__":
    main()
