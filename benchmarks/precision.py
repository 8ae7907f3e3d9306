"""Rollout precision: the peak insertion force of each deformable-part model in float32 and in
float64, side by side, on the shipped default scene (the measurement behind the default
``solver.dtype``).

    python benchmarks/precision.py [--quick]

The scene is ``jsnap.load_scene()`` (the shipped default: P2 0.8 mm, analytic plug, 10 mm/s,
the scene's contact settings) with ``solver.method`` = ``reduced``, ``full`` and ``segmented``
in turn. Each model is built and prepared once (the PMI operator is float64 in every case) and
rolled out over the scene's whole motion in float32 and in float64. For each method it records
the peak insertion force in both precisions and

* the float32 peak's relative difference from the same method's float64 peak: what float32
  costs that model;
* the float32 peak's relative difference from the full model's float64 peak: how far a float32
  run of that model is from the reference the others approximate (the float64 differences from
  it, the models' own gaps, are recorded too);
* the float32 curve's RMSE against the float64 curve (relative to the float64 peak) and the
  steps of both peaks, whether every step of both runs is clean (``Result.flags``).

The default rollout dtype (``jsnap._build.model.rollout_dtype``) may be float32 only where the
float32 peak is within 1 % of the same method's float64 peak: the headline says, per method,
whether the default is justified so (a float32 default needs the 1 %; float64 is always allowed)
and lists the methods whose float32 would be within 1 % although their default is float64. A
full run exits with status 1 if a default is not justified or a run is flagged (the quick run,
on a coarse mesh, only checks that everything runs).

``--quick``: the 2.0 mm mesh (780 free dofs) instead of 0.8 mm. Writes
benchmarks/results/precision{,_quick}.{json,png}.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import jax
import numpy as np
from _common import code_version

import jsnap
from jsnap._build.model import rollout_dtype

# XLA's small-loop option, before the first JAX computation (as every benchmark runs).
jsnap.configure_xla_cpu()

OUT = Path(__file__).parent / "results"
METHODS = ("reduced", "full", "segmented")
DTYPES = ("float32", "float64")
THRESHOLD = 0.01  # float32 is the default only where its peak is within 1 % of float64's


def machine(load) -> str:
    return (
        f"{platform.machine()} {platform.system()}, {os.cpu_count()} CPU cores, "
        f"jax {jax.devices()[0].platform}, load average {min(load):.1f}-{max(load):.1f}"
    )


def run(scene, method: str) -> dict:
    """Both rollouts of one method: ``{dtype: row}`` and what the model is."""
    scene = scene.replace({"solver.method": method})
    t0 = time.perf_counter()
    model = jsnap.build(scene)
    build_s = time.perf_counter() - t0
    prepared = jsnap.prepare(model)
    rows = {}
    for dtype in DTYPES:
        t0 = time.perf_counter()
        res = jsnap.rollout(model, prepared=prepared, dtype=dtype)
        F = np.asarray(res.insertion_force, np.float64)
        seconds = time.perf_counter() - t0
        k = int(F.argmax())
        rows[dtype] = {
            "peak_N": float(F[k]),
            "peak_step": k + 1,
            "travel_at_peak_mm": float(np.asarray(res.travel)[k]),
            "status": res.status(),
            "ok": bool(res.ok),
            "iterations_mean": float(np.asarray(res.iterations).mean()),
            "seconds_with_compile": seconds,
            "insertion_force": F.tolist(),
        }
        print(method, dtype, {k: v for k, v in rows[dtype].items() if k != "insertion_force"}, flush=True)
    return {
        "method": method,
        "default_dtype": rollout_dtype(scene),
        "dof": model.n_dof,
        "full_dof": model.full_dof,
        "orders": list(model.part.orders) if hasattr(model.part, "orders") else None,
        "build_seconds": build_s,
        "runs": rows,
    }


def compare(results: dict) -> dict:
    """Per method: the float32 peak against its own float64 peak and the full model's."""
    ref = results["full"]["runs"]["float64"]["peak_N"]
    out = {}
    for method, r in results.items():
        p32, p64 = r["runs"]["float32"]["peak_N"], r["runs"]["float64"]["peak_N"]
        F32 = np.asarray(r["runs"]["float32"]["insertion_force"])
        F64 = np.asarray(r["runs"]["float64"]["insertion_force"])
        within = abs(p32 / p64 - 1) <= THRESHOLD
        out[method] = {
            "peak_float32_N": p32,
            "peak_float64_N": p64,
            "float32_vs_own_float64": p32 / p64 - 1,
            "float32_vs_full_float64": p32 / ref - 1,
            "float64_vs_full_float64": p64 / ref - 1,
            "float32_rmse_vs_own_float64_rel_peak": float(np.sqrt(np.mean((F32 - F64) ** 2)) / p64),
            "peak_step_float32": r["runs"]["float32"]["peak_step"],
            "peak_step_float64": r["runs"]["float64"]["peak_step"],
            "float32_within_1_percent": bool(within),
            "default_dtype": r["default_dtype"],
            "default_justified": bool(r["default_dtype"] == "float64" or within),
            "ok": r["runs"]["float32"]["ok"] and r["runs"]["float64"]["ok"],
        }
    return out


def chart(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h = result["headline"]["methods"]
    methods = list(h)
    x = np.arange(len(methods))
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(13, 4.8))
    for j, (dtype, color) in enumerate((("float32", "C0"), ("float64", "C3"))):
        peaks = [h[m][f"peak_{dtype}_N"] for m in methods]
        bars = ax.bar(x + (j - 0.5) * 0.38, peaks, 0.38, color=color, label=dtype)
        ax.bar_label(bars, fmt="%.3f", fontsize=8)
    ax.set_xticks(x, [f"{m}\n({result['models'][m]['dof']} dof)" for m in methods])
    ax.set_ylabel("peak insertion force (N)")
    lo = min(min(h[m]["peak_float32_N"], h[m]["peak_float64_N"]) for m in methods)
    hi = max(max(h[m]["peak_float32_N"], h[m]["peak_float64_N"]) for m in methods)
    ax.set_ylim(lo - 0.15 * (hi - lo + 0.05 * hi), hi + 0.15 * (hi - lo + 0.05 * hi))
    ax.set_title("peak insertion force, float32 beside float64", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="y")
    for j, (key, label, color) in enumerate(
        (
            ("float32_vs_own_float64", "float32 vs the same method in float64", "C0"),
            ("float32_vs_full_float64", "float32 vs the full model in float64", "C1"),
            ("float64_vs_full_float64", "float64 vs the full model in float64", "0.6"),
        )
    ):
        vals = [100 * h[m][key] for m in methods]
        bars = bx.bar(x + (j - 1) * 0.27, vals, 0.27, color=color, label=label)
        bx.bar_label(bars, fmt="%+.2f", fontsize=7)
    for y in (-100 * THRESHOLD, 100 * THRESHOLD):
        bx.axhline(y, color="k", ls="--", lw=0.8)
    bx.axhline(0, color="0.5", lw=0.6)
    bx.set_xticks(x, [f"{m}\n(default {h[m]['default_dtype']})" for m in methods])
    bx.set_ylabel("relative difference of the peak (%)")
    bx.set_title("dashed: ±1 %, within which float32 may be the default", fontsize=10)
    bx.legend(fontsize=8)
    bx.grid(alpha=0.3, axis="y")
    fig.suptitle(
        f"Rollout precision, {result['scene_label']}\n{result['machine']}",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the 2.0 mm mesh (CI: checks that it runs)")
    a = ap.parse_args(argv)
    t_start = time.perf_counter()
    code = code_version()
    scene = jsnap.load_scene()
    changes = {"solver.mesh_size": 2.0} if a.quick else {}
    scene = scene.replace(changes)
    s = scene["solver"]
    label = (
        f"shipped default scene{' (quick: 2.0 mm mesh)' if a.quick else ''}: {s['element']} "
        f"{s['mesh_size']:g} mm, dt {1e3 * s['dt']:g} ms, {s['sdf']} plug, {scene['contact']['solver']} contact"
    )
    load = [os.getloadavg()[0]]
    models = {}
    for method in METHODS:
        models[method] = run(scene, method)
        load.append(os.getloadavg()[0])
    methods = compare(models)
    headline = {
        "quick": a.quick,
        "threshold": THRESHOLD,
        "methods": methods,
        "float32_within_1_percent": [m for m, v in methods.items() if v["float32_within_1_percent"]],
        "defaults_justified": all(v["default_justified"] for v in methods.values()),
        "float64_default_but_float32_within_1_percent": [
            m for m, v in methods.items() if v["default_dtype"] == "float64" and v["float32_within_1_percent"]
        ],
        "all_ok": all(v["ok"] for v in methods.values()),
    }
    result = {
        "benchmark": "precision",
        "machine": machine(load),
        "code": code,
        "scene_label": label,
        "changes": changes,
        "headline": headline,
        "models": models,
        "wall_seconds": time.perf_counter() - t_start,
    }
    stem = "precision_quick" if a.quick else "precision"
    OUT.mkdir(exist_ok=True)
    (OUT / f"{stem}.json").write_text(json.dumps(result, indent=1))
    chart(result, OUT / f"{stem}.png")
    for m, v in methods.items():
        print(
            f"{m:10s} peak float32 {v['peak_float32_N']:.4f} N, float64 {v['peak_float64_N']:.4f} N: "
            f"{100 * v['float32_vs_own_float64']:+.3f} % (own float64), "
            f"{100 * v['float32_vs_full_float64']:+.3f} % (full float64); default {v['default_dtype']}"
            f"{'' if v['default_justified'] else ' (NOT justified: float32 is more than 1 % off)'}",
            flush=True,
        )
    # Judged on the full run only: the quick run's coarse mesh is not the shipped scene.
    return 0 if a.quick or (headline["defaults_justified"] and headline["all_ok"]) else 1


if __name__ == "__main__":
    raise SystemExit(main())
