"""The two-hook clip preset (jsnap/scenes/two_hook_clip.toml): its reduced model against its full
model, both against CalculiX, and the contact solvers on its symmetric squeeze.

    python benchmarks/two_hook_clip.py [--quick]

1. Accuracy: the shipped reduced model (float32) and the full model (float64, its contact
   solved by APGD to the tolerance with up to 5000 iterations), frictionless and at mu = 0.3:
   peak insertion force, travel at the peak, RMSE of the insertion force in % of the full
   model's peak over the whole motion and over the rise; both against CalculiX's linear-geometry
   curves of the same clip (jsnap/data/calculix-two_hook_clip/: frictionless on its finest mesh,
   mu = 0.3 on the medium one), over the travel CalculiX covers.
2. The symmetric squeeze: the shipped reduced model at mu = 0.3 with each contact solver (SPG,
   the scene's; APGD, the default elsewhere; ADMM and projected Gauss-Seidel, internal), each
   rolled out twice: at the scene's iteration cap (steps that end at it, largest KKT residual,
   peak force, steps/s of the compiled rollout, side by side in one process) and with a cap of
   5000 (iterations each step needs to reach the tolerance: median, 95th percentile, largest).

Writes benchmarks/results/two_hook_clip.{json,png} (--quick: a 1.2 mm mesh, mu = 0.3 only, SPG
and PGS at the scene's cap, one timing run, no CalculiX; results/two_hook_clip_quick.json).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
from _common import calculix_row, code_version, curve_stats, load_scene, plot_curves, scan_timing

import jsnap
from jsnap._geometry.scene import default_scene_path

jsnap.configure_xla_cpu()

OUT = Path(__file__).parent / "results"
SCENE = default_scene_path().parent / "two_hook_clip.toml"
DATA = Path(jsnap.__file__).parent / "data" / "calculix-two_hook_clip"
# Friction: the CalculiX curve of each mu the accuracy part runs.
REFS = {0.0: DATA / "clip_mu0_lin_curve.csv", 0.3: DATA / "clip_mu03_lin_curve.csv"}
SOLVERS = {
    "SPG": {},
    "APGD": {"contact.solver": "apgd"},
    "ADMM": {"contact.solver": "admm"},
    "PGS": {"contact.solver": "pgs"},
}
# The full model's contact: APGD to the scene's tolerance, with room to get there.
FULL_CONTACT = {"contact.solver": "apgd", "contact.iterations": 5000}
LONG_CAP = 5000


def solver_run(scene, runs):
    """One rollout of ``scene``'s reduced model: the solver's iterations and residuals, and
    steps/s over ``runs`` timed calls."""
    model = jsnap.build(scene)
    prepared = jsnap.prepare(model)
    res, _, times = scan_timing(model, prepared, runs)
    it = np.asarray(res.iterations)
    r = np.asarray(res.residual)
    contact = it > 0
    cap = scene["contact"]["iterations"]
    tol = scene["contact"]["tolerance"]
    return {
        "iteration_cap": cap,
        "steps_in_contact": int(contact.sum()),
        "steps_at_cap": int(np.sum(it >= cap)),
        "steps_not_converged": int(np.sum(contact & (r > tol))),
        "median_iterations": float(np.median(it[contact])),
        "p95_iterations": float(np.percentile(it[contact], 95)),
        "max_iterations": int(it.max()),
        "max_residual": float(r.max()),
        "tolerance": tol,
        "peak_N": float(np.asarray(res.insertion_force).max()),
        "status": res.status if not res.ok else "ok",
        "steps_per_second": (model.motion.shape[0] - 1) / float(np.median(times)),
        "iterations": it.tolist(),
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
        full_model = jsnap.build(
            load_scene({"solver.method": "full", "contact.friction": mu, **FULL_CONTACT}, base)
        )
        full = jsnap.rollout(full_model, dtype="float64")
        red_model = jsnap.build(base.replace({"contact.friction": mu}))
        red = jsnap.rollout(red_model)
        travel = np.asarray(full.travel)
        Ff, Fr = np.asarray(full.insertion_force), np.asarray(red.insertion_force)
        curves[mu] = (travel, Ff, Fr)
        acc = out["accuracy"][f"mu {mu:g}"] = {
            "full_dof": full_model.full_dof,
            "reduced_orders": list(red_model.part.orders),
            "full_float64": {**curve_stats(Ff, travel, Ff), "ok": bool(full.ok)},
            "reduced_float32": {**curve_stats(Fr, travel, Ff), "ok": bool(red.ok)},
            "curves": {"travel_mm": travel.tolist(), "full_N": Ff.tolist(), "reduced_N": Fr.tolist()},
        }
        if not args.quick and REFS[mu].is_file():
            acc["calculix"] = calculix_row(REFS[mu], travel, {"full_float64": Ff, "reduced_float32": Fr})
        print(f"mu {mu:g}:", json.dumps({k: v for k, v in acc.items() if k != "curves"}), flush=True)
    # The squeeze: each contact solver on the shipped reduced model, mu = 0.3.
    for name, changes in SOLVERS.items():
        if args.quick and name in ("APGD", "ADMM"):
            continue
        scene = load_scene(changes, base)
        row = out["solvers"][name] = {"scene_cap": solver_run(scene, runs)}
        if not args.quick:
            row["long_cap"] = solver_run(load_scene({"contact.iterations": LONG_CAP}, scene), 1)
            del row["long_cap"]["steps_per_second"]  # one untimed run: its iterations are the point
        print(name, {k: {q: w for q, w in v.items() if q != "iterations"} for k, v in row.items()}, flush=True)
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

    fig, ax = plt.subplots(1, 3, figsize=(17, 4.8))
    plot_curves(ax[0], curves, REFS)
    ax[0].set(xlabel="travel (mm)", ylabel="insertion force (N)", title="two-hook clip: insertion force")
    ax[0].legend(fontsize=7)
    for name, s in out["solvers"].items():
        long = s["long_cap"]
        ax[1].semilogy(
            np.maximum(long["iterations"], 1), lw=1, label=f"{name} (median {long['median_iterations']:.0f})"
        )
    ax[1].set(
        xlabel="step",
        ylabel="iterations to the tolerance",
        title=f"the squeeze, reduced, mu 0.3: cap {LONG_CAP}",
    )
    ax[1].legend(fontsize=8)
    names = list(out["solvers"])
    cap = out["solvers"][names[0]]["scene_cap"]
    conv = [
        1 - s["scene_cap"]["steps_not_converged"] / s["scene_cap"]["steps_in_contact"]
        for s in out["solvers"].values()
    ]
    rate = [s["scene_cap"]["steps_per_second"] for s in out["solvers"].values()]
    ax[2].bar(np.arange(len(names)) - 0.2, np.array(conv) * 100, 0.4, label="steps converged (%)")
    ax[2].bar(np.arange(len(names)) + 0.2, np.array(rate) / 10, 0.4, label="steps/s / 10")
    ax[2].set_xticks(np.arange(len(names)), names)
    ax[2].set(title=f"at the scene's cap ({cap['iteration_cap']} iterations)")
    ax[2].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(OUT / "two_hook_clip.png", dpi=110)


if __name__ == "__main__":
    raise SystemExit(main())
