"""The annular snap preset (jsnap/scenes/annular.toml): its reduced model against its full model,
both against CalculiX, the design guide and shell theory, and their speed side by side.

    python benchmarks/annular.py

The model is a sector of the ring (``connector.sector`` degrees, its cut faces sliding on their
planes); every force here is the whole ring's, the sector's times ``360 / sector``.

1. Accuracy, frictionless and at mu = 0.3: the full model in float64 (its contact solved by APGD
   to the tolerance with up to 5000 iterations) on the shipped mesh and on one with half the
   element size, and the shipped reduced model in float32: peak insertion force, travel at the
   peak, the force at 0.15, 0.20 and 0.25 mm of travel (the rise, where no snap is near), the
   RMSE of the reduced model's force in % of the full model's peak over the whole motion and
   over the rise. Against CalculiX's linear-geometry curves of the same snap
   (jsnap/data/calculix-annular/: a 1-degree sector on three meshes frictionless, the finest at
   mu = 0.3).
2. contact.stabilisation: the frictionless full model's peak with 0.1, 0.3 (shipped) and 1 of a
   penetration removed per step, and whether the rollout stays passive.
   The reduced model at several ``solver.hsv_tolerance`` values against the same full model
   (why the scene reduces at 1e-3). And three snaps the scene's settings were not chosen on:
   the full model's peak (float64) against the reduced model's (float32), and flagged steps.
3. The radial force that holds the lip open on the bead's side against shell theory (a
   semi-infinite cylinder under a ring load at its end: w = Q / (2 beta^3 D)), and the peak
   against the design guide's annular mating force.
4. Speed: steps/s of the compiled rollout (median of the timed calls) of the shipped reduced
   model and of the full model (float32 and float64), in one process, with the load average.

Writes benchmarks/results/annular.{json,png}.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
from _common import calculix_row, curve_stats, load_scene, plot_speed, speed, write_result

import jsnap
from jsnap._apps.simulate import design_guide_force, ring_copies
from jsnap._geometry.scene import default_scene_path

jsnap.configure_xla_cpu()

OUT = Path(__file__).parent / "results"
SCENE = default_scene_path().parent / "annular.toml"
DATA = Path(jsnap.__file__).parent / "data" / "calculix-annular"
# friction -> CalculiX curves (finest mesh first)
REFS = {
    0.0: [
        DATA / "annular_mu0_lin_curve.csv",
        DATA / "annular_mu0_lin_m2_curve.csv",
        DATA / "annular_mu0_lin_m1_curve.csv",
    ],
    0.3: [DATA / "annular_mu03_lin_curve.csv"],
}
FULL_CONTACT = {"contact.solver": "apgd", "contact.iterations": 5000}
RISE = (0.15, 0.20, 0.25)
# solver.hsv_tolerance of the reduced models compared (the scene's is 1e-3).
TOLERANCES = (1e-2, 3e-3, 1e-3, 3e-4)
# Snaps the scene's settings were not chosen on (the scene's contact and reduction settings).
OTHER_SNAPS = (
    {"connector.radius": 5.0, "connector.thickness": 1.5, "connector.undercut": 0.2},
    {
        "connector.radius": 2.0,
        "connector.thickness": 0.8,
        "connector.undercut": 0.08,
        "connector.lead_angle": 40.0,
        "contact.friction": 0.5,
    },
    {"connector.lead_angle": 20.0, "connector.length": 6.0, "contact.friction": 0.0},
)


def shell_radial_force(c: dict, E: float, nu: float) -> float:
    """Ring force (N) that holds the end of a semi-infinite tube (mean radius a, wall h) open by
    the undercut: the end ring load Q = 2 beta^3 D y_u per length of the inner circumference,
    beta^4 = 3 (1 - nu^2) / (a h)^2, D = E h^3 / (12 (1 - nu^2)) (Timoshenko, Theory of Plates
    and Shells, sec. 115)."""
    h, a = c["thickness"], c["radius"] + 0.5 * c["thickness"]
    beta = (3 * (1 - nu**2) / (a * h) ** 2) ** 0.25
    D = E * h**3 / (12 * (1 - nu**2))
    return 2 * math.pi * (c["radius"] - c["undercut"]) * 2 * beta**3 * D * c["undercut"]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--plot-only", action="store_true", help="only redraw the figure from results/annular.json"
    )
    if parser.parse_args(argv).plot_only:
        out = json.loads((OUT / "annular.json").read_text())
        curves = {
            float(key.split()[1]): tuple(
                np.asarray(acc["curves"][k]) for k in ("travel_mm", "full_N", "half_mesh_N", "reduced_N")
            )
            for key, acc in out["accuracy"].items()
        }
        plot(out, curves)
        return 0
    base = jsnap.load_scene(SCENE)
    c = base["connector"]
    copies = ring_copies(base)
    out = {"scene": SCENE.name, "sector_deg": c["sector"], "ring_copies": copies, "accuracy": {}}
    curves = {}
    for mu in (0.0, 0.3):
        scene = base.replace({"contact.friction": mu})
        full_model = jsnap.build(load_scene({"solver.method": "full", **FULL_CONTACT}, scene))
        full = jsnap.rollout(full_model, dtype="float64")
        fine_scene = load_scene(
            {"solver.method": "full", "solver.mesh_size": 0.5 * base["solver"]["mesh_size"], **FULL_CONTACT},
            scene,
        )
        fine_model = jsnap.build(fine_scene)
        fine = jsnap.rollout(fine_model, dtype="float64")
        red_model = jsnap.build(scene)
        red = jsnap.rollout(red_model)
        travel = np.asarray(full.travel)
        Ff, Fh, Fr = (copies * np.asarray(r.insertion_force, np.float64) for r in (full, fine, red))
        radial = -copies * np.asarray(full.lateral_force, np.float64)
        curves[mu] = (travel, Ff, Fh, Fr)
        acc = out["accuracy"][f"mu {mu:g}"] = {
            "full_dof": full_model.full_dof,
            "full_dof_half_mesh": fine_model.full_dof,
            "reduced_orders": list(red_model.part.orders),
            "full_float64": {**curve_stats(Ff, travel, Ff), "ok": bool(full.ok)},
            "full_float64_half_mesh": {**curve_stats(Fh, travel, Ff), "ok": bool(fine.ok)},
            "reduced_float32": {**curve_stats(Fr, travel, Ff), "ok": bool(red.ok)},
            "rise_N": {
                name: [float(np.interp(t, travel, F)) for t in RISE]
                for name, F in (("full_float64", Ff), ("full_float64_half_mesh", Fh), ("reduced_float32", Fr))
            },
            "radial_force_lip_open_N": float(np.interp(travel[np.argmax(Ff)] + 0.15, travel, radial)),
            "calculix": [
                calculix_row(
                    ref, travel, {"full_float64": Ff, "full_float64_half_mesh": Fh, "reduced_float32": Fr}
                )
                for ref in REFS[mu]
            ],
            "curves": {
                "travel_mm": travel.tolist(),
                "full_N": Ff.tolist(),
                "half_mesh_N": Fh.tolist(),
                "reduced_N": Fr.tolist(),
            },
        }
        # The reduction's tolerance: how the reduced model converges to the full one.
        acc["hsv_tolerance"] = {}
        for tol in TOLERANCES:
            model = jsnap.build(scene.replace({"solver.hsv_tolerance": tol}))
            res = jsnap.rollout(model)
            F = copies * np.asarray(res.insertion_force, np.float64)
            acc["hsv_tolerance"][f"{tol:g}"] = {
                "orders": [int(o) for o in model.part.orders],
                **curve_stats(F, travel, Ff),
                "ok": bool(res.ok),
            }
            print(f"mu {mu:g}, hsv_tolerance {tol:g}:", acc["hsv_tolerance"][f"{tol:g}"], flush=True)
        for row, ref in zip(acc["calculix"], REFS[mu], strict=True):
            d = np.genfromtxt(ref, delimiter=",", names=True)
            row["rise_N"] = [float(np.interp(t, d["plug_travel_mm"], d["insertion_force_N"])) for t in RISE]
        print(f"mu {mu:g}:", {k: acc[k] for k in ("full_float64", "reduced_float32", "rise_N")}, flush=True)
    m = base["material"]
    out["shell_theory_radial_force_N"] = shell_radial_force(c, m["youngs_modulus"], m["poissons_ratio"])
    # design_guide_force gives the modelled sector's share: the whole ring's here.
    out["design_guide_mating_force_N"] = {
        f"mu {mu:g}": copies * design_guide_force(base.replace({"contact.friction": mu})) for mu in (0.0, 0.3)
    }
    out["other_snaps"] = []
    for changes in OTHER_SNAPS:
        scene = base.replace(changes)
        full_scene = load_scene({"solver.method": "full", "solver.dtype": "float64"}, scene)
        full = jsnap.rollout(jsnap.build(full_scene))
        red_model = jsnap.build(scene)
        red = jsnap.rollout(red_model)
        row = {"changes": changes, "reduced_orders": [int(o) for o in red_model.part.orders]}
        for name, res in (("full_float64", full), ("reduced_float32", red)):
            row[name] = {
                "peak_N": copies * float(np.max(np.asarray(res.insertion_force))),
                "flagged_steps": int(np.sum(np.asarray(res.flags) != 0)),
            }
        out["other_snaps"].append(row)
        print("other snap", row, flush=True)
    out["stabilisation"] = {}
    for s in (0.1, 0.3, 1.0):
        scene = load_scene(
            {"solver.method": "full", "contact.friction": 0.0, "contact.stabilisation": s, **FULL_CONTACT}, base
        )
        res = jsnap.rollout(jsnap.build(scene), dtype="float64")
        F = copies * np.asarray(res.insertion_force, np.float64)
        out["stabilisation"][f"{s:g}"] = {
            "peak_N": float(F.max()),
            "travel_at_peak_mm": float(np.asarray(res.travel)[np.argmax(F)]),
            "flagged_steps": int(np.sum(np.asarray(res.flags) != 0)),
        }
        print("stabilisation", s, out["stabilisation"][f"{s:g}"], flush=True)
    out["speed"] = speed(base, runs=5)
    write_result(out, OUT / "annular.json")
    plot(out, curves)
    return 0


def plot(out, curves):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(13, 4.8), gridspec_kw={"width_ratios": [2.2, 1]})
    a = ax[0]
    for mu, (travel, Ff, Fh, Fr) in curves.items():
        colour = a.plot(travel, Fr, label=f"shipped: reduced float32, mu {mu:g}")[0].get_color()
        a.plot(travel, Ff, "--", color=colour, lw=1.0, label=f"full float64, mu {mu:g}")
        a.plot(travel, Fh, ":", color=colour, lw=1.0, label=f"full float64, half the element size, mu {mu:g}")
        d = np.genfromtxt(REFS[mu][0], delimiter=",", names=True)
        a.plot(
            d["plug_travel_mm"], d["insertion_force_N"], ".", color=colour, ms=3, label=f"CalculiX, mu {mu:g}"
        )
        guide = out["design_guide_mating_force_N"][f"mu {mu:g}"]
        a.axhline(guide, color=colour, ls="-.", lw=0.8, label=f"design guide, mu {mu:g}")
    a.axhline(0, color="0.6", lw=0.5)
    a.set(
        xlabel="travel of the bead (mm)",
        ylabel="insertion force of the whole ring (N)",
        title=f"annular snap, a {out['sector_deg']:g} degree sector x {out['ring_copies']:g}",
    )
    a.legend(fontsize=7)
    plot_speed(ax[1], out["speed"])
    fig.tight_layout()
    fig.savefig(OUT / "annular.png", dpi=110)


if __name__ == "__main__":
    raise SystemExit(main())
