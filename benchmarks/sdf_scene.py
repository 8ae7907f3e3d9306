"""The default scene with each plug SDF: neural against the exact triangle-mesh SDF (and the
analytic rounded box), insertion-force RMSE and the whole-step rate.

    python benchmarks/sdf_scene.py [--quick]

Each run is the default scene as the committed results were taken (full P2 model, float32
rollout: both stated, the shipped scene now defaults to the reduced model and to float64 for
the full one). The compile time
is the first call less the faster of two further runs, whose rate is the step rate; the
exact-mesh SDF's rollout (~20 s here) runs once, its compile time measured as the first call of
a two-step rollout (the same scan body) and its run time as the rest. The PMI operator is
prepared once, outside the timings. Writes benchmarks/results/sdf_scene.{json,png}.

``--from-pareto`` (what ``jsnap bench`` runs, after ``pareto``): the three rollouts are the
speed-against-accuracy benchmark's "default", "neural SDF" and "mesh SDF" settings, the same
runs timed the same way; they are taken from ``pareto.json`` when that file was written at the
current commit with an unmodified library (``code`` in both files), instead of being run a
second time (~80 s). Otherwise, or without the flag, they are run here.
"""

from __future__ import annotations

import argparse
import json
import platform
from pathlib import Path

import jax
import numpy as np
from _common import FLOAT32, FULL, code_version, load_scene, scan_timing

import jsnap

# XLA's small-loop option, before the first JAX computation (the committed timings have it).
jsnap.configure_xla_cpu()

OUT = Path(__file__).parent / "results"


def run(sdf, changes, steps=None, repeats=2):
    """One SDF's rollout; ``repeats = 0``: run once, its compile time measured by a two-step call."""
    model = jsnap.build(load_scene({**FULL, **FLOAT32, "solver.sdf": sdf, **changes}))
    prepared = jsnap.prepare(model)  # the PMI operator: the same for every SDF, not timed
    controls = None if steps is None else model.trajectory()[1 : steps + 1]
    res, first, times = scan_timing(model, prepared, repeats, controls)
    run_s = min(times)
    compile_s = first - run_s
    F = np.asarray(res.insertion_force)
    return {
        "sdf": sdf,
        "steps": int(F.size),
        "steps_per_second": F.size / run_s,
        "compile_seconds": compile_s,
        "peak_N": float(F.max()),
        "travel": np.asarray(res.travel).tolist(),
        "insertion_force": F.tolist(),
        "max_overflow": int(np.asarray(res.overflow).max()),
    }


SDF_KINDS = ("mesh", "neural", "analytic")  # the order of the rows and of PARETO_CHANGES
PARETO_CHANGES = {"mesh": {"solver.sdf": "mesh"}, "neural": {"solver.sdf": "neural"}, "analytic": {}}
# What a row holds (pareto's rows hold the same, under the same names).
ROW_KEYS = (
    "steps",
    "steps_per_second",
    "compile_seconds",
    "peak_N",
    "travel",
    "insertion_force",
    "max_overflow",
)


def from_pareto(code):
    """The three rollouts from ``pareto.json``, or (None, why not)."""
    path = OUT / "pareto.json"
    if not path.exists():
        return None, f"no {path.name}"
    saved = json.loads(path.read_text())
    if saved.get("code") != code or code["modified"]:
        return None, f"{path.name} is from another commit or a modified library ({saved.get('code')})"
    rows = {}
    for sdf, changes in PARETO_CHANGES.items():
        r = next((r for r in saved["rows"] if r["changes"] == changes), None)
        if r is None or "travel" not in r:
            return None, f"{path.name} has no run with {changes} (or an older format)"
        rows[sdf] = {"sdf": sdf, **{k: r[k] for k in ROW_KEYS}}
    return rows, path.name


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="coarse mesh (2.0 mm), the first 20 steps")
    ap.add_argument("--from-pareto", action="store_true", help="take the runs from pareto.json (see above)")
    a = ap.parse_args(argv)
    changes = {"solver.mesh_size": 2.0} if a.quick else {}
    steps, repeats = (20, 1) if a.quick else (None, 2)
    code = code_version()
    rows, source = from_pareto(code) if a.from_pareto and not a.quick else (None, "run here")
    if rows is None:
        if a.from_pareto:
            print(f"sdf_scene: running the rollouts here: {source}", flush=True)
            source = "run here"
        rows = {
            # The exact-mesh rollout once (a two-step call measures its compile); quick: every one once.
            sdf: run(sdf, changes, steps, 0 if sdf == "mesh" and not a.quick else repeats)
            for sdf in SDF_KINDS
        }
    ref = np.asarray(rows["mesh"]["insertion_force"])
    for r in rows.values():
        F = np.asarray(r["insertion_force"])
        r["rmse_vs_mesh_N"] = float(np.sqrt(np.mean((F - ref) ** 2)))
        r["rmse_vs_mesh_rel_peak"] = r["rmse_vs_mesh_N"] / float(ref.max())
        print({k: v for k, v in r.items() if k not in ("travel", "insertion_force")}, flush=True)
    machine = f"{platform.machine()}, {platform.processor() or platform.system()}, {jax.devices()[0].platform}"
    stem = "sdf_scene_quick" if a.quick else "sdf_scene"
    OUT.mkdir(exist_ok=True)
    result = {"machine": machine, "code": code, "changes": changes, "source": source, "runs": rows}
    (OUT / f"{stem}.json").write_text(json.dumps(result))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5))
    for sdf, r in rows.items():
        ax.plot(
            r["travel"],
            r["insertion_force"],
            lw=1.2,
            label=f"{sdf}: {r['steps_per_second']:.0f} steps/s, "
            f"RMSE vs mesh {100 * r['rmse_vs_mesh_rel_peak']:.2f}% of peak",
        )
    ax.set_xlabel("plug travel (mm)")
    ax.set_ylabel("insertion force (N)")
    ax.set_title(f"Default scene, plug SDF kinds ({machine})", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(OUT / f"{stem}.png", dpi=120)


if __name__ == "__main__":
    main()
