"""The two-hook clip preset (jsnap/scenes/two_hook_clip.toml): its reduced model against its full
model, both against CalculiX when its reference is in the project, and the contact solvers on
its symmetric squeeze.

    python benchmarks/two_hook_clip.py [--quick]

1. Accuracy: the shipped reduced model (float32) and the full model (float64), frictionless and
   at mu = 0.3: peak insertion force, travel at the peak, RMSE of the insertion force over the
   motion in % of the full model's peak; frictionless also against CalculiX's linear-geometry,
   frictionless curve (jsnap/data/calculix-two_hook_clip/clip_mu0_lin_curve.csv, when present).
2. The symmetric squeeze: the shipped reduced model at mu = 0.3 with each contact solver
   (APGD, the default; SPG; projected Gauss-Seidel, the paper's counter-example, internal):
   iterations per step (median, largest), steps that end at the iteration cap, the largest KKT
   residual, peak force and steps/s of the compiled rollout, side by side in one process.

Writes benchmarks/results/two_hook_clip.{json,png} (--quick: a 1.2 mm mesh, mu = 0.3 only, APGD
and PGS, one timing run; results/two_hook_clip_quick.json).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
from _common import code_version, load_scene, scan_timing

import jsnap
from jsnap._geometry.scene import default_scene_path

jsnap.configure_xla_cpu()

OUT = Path(__file__).parent / "results"
SCENE = default_scene_path().parent / "two_hook_clip.toml"
REF = Path(jsnap.__file__).parent / "data" / "calculix-two_hook_clip" / "clip_mu0_lin_curve.csv"
SOLVERS = {"APGD": {}, "SPG": {"contact.solver": "spg"}, "PGS": {"contact.solver": "pgs"}}


def curve_stats(F, travel, ref_F):
    """Peak, its travel, and the RMS difference from ``ref_F`` in % of its peak over the whole
    motion and over the rise (up to ``ref_F``'s peak: after the snap the hooks ring against the
    block's sides, which are exactly where their inner faces rest)."""
    k, rise = int(np.argmax(F)), int(np.argmax(ref_F)) + 1
    rmse = float(np.sqrt(np.mean((F - ref_F) ** 2)) / ref_F.max())
    rmse_rise = float(np.sqrt(np.mean((F[:rise] - ref_F[:rise]) ** 2)) / ref_F.max())
    return {
        "peak_N": float(F[k]),
        "travel_at_peak_mm": float(travel[k]),
        "rmse_of_full_peak": rmse,
        "rmse_rise_of_full_peak": rmse_rise,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    base = jsnap.load_scene(SCENE)
    if args.quick:
        base = base.replace({"solver.mesh_size": 1.2})
    runs = 1 if args.quick else 3
    out = {"scene": str(SCENE.name), "mesh_size": base["solver"]["mesh_size"], "accuracy": {}, "solvers": {}}
    curves = {}
    for mu in (0.3,) if args.quick else (0.0, 0.3):
        full_model = jsnap.build(base.replace({"solver.method": "full", "contact.friction": mu}))
        full = jsnap.rollout(full_model, dtype="float64")
        red_model = jsnap.build(base.replace({"contact.friction": mu}))
        red = jsnap.rollout(red_model)
        travel = np.asarray(full.travel)
        Ff, Fr = np.asarray(full.insertion_force), np.asarray(red.insertion_force)
        curves[mu] = (travel, Ff, Fr)
        out["accuracy"][f"mu {mu:g}"] = {
            "full_dof": full_model.full_dof,
            "reduced_orders": list(red_model.part.orders),
            "full_float64": {**curve_stats(Ff, travel, Ff), "ok": bool(full.ok)},
            "reduced_float32": {**curve_stats(Fr, travel, Ff), "ok": bool(red.ok)},
            "curves": {"travel_mm": travel.tolist(), "full_N": Ff.tolist(), "reduced_N": Fr.tolist()},
        }
        shown = {k: v for k, v in out["accuracy"][f"mu {mu:g}"].items() if k != "curves"}
        print(f"mu {mu:g}:", json.dumps(shown), flush=True)
    if REF.is_file() and 0.0 in curves:
        d = np.genfromtxt(REF, delimiter=",", names=True)
        ref_travel, ref_F = d["plug_travel_mm"], d["insertion_force_N"]
        travel, Ff, Fr = curves[0.0]
        window = travel <= ref_travel.max()
        row = {"reference": str(REF.relative_to(Path(jsnap.__file__).parent)), "peak_N": float(ref_F.max())}
        for name, F in (("full_float64", Ff), ("reduced_float32", Fr)):
            interp = np.interp(travel[window], ref_travel, ref_F)
            row[name] = {
                "peak_over_reference": float(F[window].max() / ref_F.max()),
                "rms_difference_of_reference_peak": float(
                    np.sqrt(np.mean((F[window] - interp) ** 2)) / ref_F.max()
                ),
            }
        out["calculix_mu0"] = row
        print("CalculiX:", json.dumps(row), flush=True)
    # The squeeze: each contact solver on the shipped reduced model, mu = 0.3.
    for name, changes in SOLVERS.items():
        if args.quick and name == "SPG":
            continue
        scene = load_scene(changes, base)
        model = jsnap.build(scene)
        prepared = jsnap.prepare(model)
        res, _, times = scan_timing(model, prepared, runs)
        it = np.asarray(res.iterations)
        cap = scene["contact"]["iterations"]
        contact = it > 0
        steps = model.motion.shape[0] - 1
        out["solvers"][name] = {
            "iteration_cap": cap,
            "median_iterations": float(np.median(it[contact])),
            "max_iterations": int(it.max()),
            "steps_at_cap": int(np.sum(it >= cap)),
            "steps_in_contact": int(contact.sum()),
            "max_residual": float(np.asarray(res.residual).max()),
            "tolerance": scene["contact"]["tolerance"],
            "peak_N": float(np.asarray(res.insertion_force).max()),
            "status": res.status if not res.ok else "ok",
            "steps_per_second": steps / float(np.median(times)),
            "iterations": it.tolist(),
        }
        print(name, {k: v for k, v in out["solvers"][name].items() if k != "iterations"}, flush=True)
    out["load_average_after"] = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    out["cpus"] = os.cpu_count()
    out["date"] = time.strftime("%Y-%m-%d %H:%M")
    out["code"] = code_version()
    OUT.mkdir(exist_ok=True)
    stem = "two_hook_clip_quick" if args.quick else "two_hook_clip"
    (OUT / f"{stem}.json").write_text(json.dumps(out, indent=1) + "\n")
    if not args.quick:
        plot(out, curves)
    return 0


def plot(out, curves):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(13, 4.8))
    for mu, (travel, Ff, Fr) in curves.items():
        ax[0].plot(travel, Ff, label=f"full float64, mu {mu:g}")
        ax[0].plot(travel, Fr, "--", label=f"reduced float32 (shipped), mu {mu:g}")
    if REF.is_file() and 0.0 in curves:
        d = np.genfromtxt(REF, delimiter=",", names=True)
        ax[0].plot(d["plug_travel_mm"], d["insertion_force_N"], "k.", ms=3, label="CalculiX, linear, mu 0")
    ax[0].set(xlabel="travel (mm)", ylabel="insertion force (N)", title="two-hook clip: insertion force")
    ax[0].legend(fontsize=8)
    for name, s in out["solvers"].items():
        ax[1].semilogy(np.maximum(s["iterations"], 1), label=f"{name} (cap {s['iteration_cap']})")
    ax[1].set(xlabel="step", ylabel="contact solver iterations", title="the symmetric squeeze, reduced, mu 0.3")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(OUT / "two_hook_clip.png", dpi=110)


if __name__ == "__main__":
    raise SystemExit(main())
