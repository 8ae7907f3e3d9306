"""Point or patch load cases in the reduction: the reduced order and the insertion force when
the static correction keeps the compliance of loads spread over a patch instead of each
candidate point's own (the scene key ``solver.load_patch``, a Gaussian's standard
deviation in mm; 0, the default, is each point alone).

    python benchmarks/load_patch.py

A point load's local compliance grows without bound as the mesh is refined, and the static
correction keeps it at every candidate point, so the contact segment's order grows with the
mesh (docs/reduction.md, "Large parts"). A patch load's does not. This measures what that
buys and what it costs, at ``PATCHES``:

1. The default hook at P2 meshes ``MESHES``: the reduced orders, and the peak insertion force
   of the reduced model (float32) at the default friction (0.3).
2. The default hook on the shipped 0.8 mm mesh against its full model (float64), frictionless
   and at mu = 0.3: peak, RMS difference over the rise and over the whole motion, in % of the
   full model's peak.
3. The box lid (four hooks, the box tilted 3 degrees, whose contact lines creep along the
   slanted edges point by point) on a 1.2 mm mesh against its full model (float64, APGD to
   the tolerance with up to 5000 iterations), frictionless and at mu = 0.3, and the reduced
   models' step rates (median of 3 compiled rollouts after the first, one after the other).
4. Wider patches, ``WIDE``, on the default hook as in 2 (their rows beside 2's): how far the
   patch may grow past the hook's features (the undercut is 0.8 mm, the arm 1.2 mm thick)
   before the force moves.

5. The default hook on a finer mesh, ``FINE_MESH`` (11 070 dof: the finest of the meshes
   tried whose full model this machine holds; 0.5 mm is refused for memory), against its full
   model as in 2, at point loads and ``FINE_PATCHES``: whether the curves of the two kinds of
   load case stay as close to the full model's as on the shipped mesh once the mesh is finer
   than the contact features.

    python benchmarks/load_patch.py --wide-only   # only 4, into the existing JSON
    python benchmarks/load_patch.py --fine-only   # only 5, into the existing JSON

Writes benchmarks/results/load_patch.{json,png}.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np
from _common import LID_DEFAULT_SAMPLING, curve_stats, load_scene, stamped, timing_row, write_result

import jsnap
from jsnap._geometry.scene import default_scene_path

jsnap.configure_xla_cpu()

OUT = Path(__file__).parent / "results"
LID = default_scene_path().parent / "box_lid.toml"
PATCHES = (0.0, 0.2, 0.5)
WIDE = (0.8, 1.2, 2.0)
MESHES = (0.8, 0.5, 0.3)
FRICTIONS = (0.0, 0.3)
FINE_MESH, FINE_PATCHES = 0.6, (0.0, 0.2)
# The box lid's full model fits in memory on this mesh (benchmarks/box_lid.py).
LID_MESH = 1.2
FULL_CONTACT = {"contact.solver": "apgd", "contact.iterations": 5000}


def patched(scene, patch: float, **changes):
    return load_scene({"solver.load_patch": patch, **changes}, scene)


def against_full(scene, name: str, rates: bool, patches=PATCHES) -> dict:
    """``scene`` (each of ``FRICTIONS``) reduced at each of ``patches`` (float32) against its
    full model (float64)."""
    out = {}
    for mu in FRICTIONS:
        base = scene.replace({"contact.friction": mu})
        full = jsnap.rollout(
            jsnap.build(load_scene({"solver.method": "full", **FULL_CONTACT}, base)), dtype="float64"
        )
        Ff, travel = np.asarray(full.insertion_force), np.asarray(full.travel)
        rows = {"full_float64": {**curve_stats(Ff, travel, Ff), "ok": bool(full.ok)}}
        curves = {"travel_mm": travel.tolist(), "full_N": Ff.tolist()}
        for patch in patches:
            model = jsnap.build(patched(base, patch))
            res = jsnap.rollout(model)
            F = np.asarray(res.insertion_force)
            row = {
                "orders": [int(o) for o in model.part.orders],
                **curve_stats(F, travel, Ff),
                "ok": bool(res.ok),
            }
            if rates and mu == FRICTIONS[-1]:
                row["speed"] = timing_row(model, 3)
            rows[f"{patch:g}"] = row
            curves[f"patch_{patch:g}_N"] = F.tolist()
            print(f"{name} mu {mu:g} patch {patch:g}:", row, flush=True)
        out[f"mu {mu:g}"] = {"rows": rows, "curves": curves}
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--wide-only", action="store_true", help="only the wide patches, into the existing JSON"
    )
    parser.add_argument(
        "--fine-only",
        action="store_true",
        help="only the finer mesh against its full model, into the existing JSON",
    )
    args = parser.parse_args()
    default = jsnap.load_scene()
    if args.fine_only:
        out = json.loads((OUT / "load_patch.json").read_text())
        fine = default.replace({"solver.mesh_size": FINE_MESH})
        section = against_full(fine, f"default hook {FINE_MESH:g} mm", rates=False, patches=FINE_PATCHES)
        out[f"default_hook_{FINE_MESH:g}mm"] = section
        # Stamped on its own: the other sections keep the stamp of the run that measured them.
        out["section_5"] = stamped({"load_average": os.getloadavg()[0]})
        (OUT / "load_patch.json").write_text(json.dumps(out, indent=1) + "\n")
        plot(out)
        return 0
    if args.wide_only:
        out = json.loads((OUT / "load_patch.json").read_text())
        # Sections 1-3 keep the stamp of the run that measured them.
        out.setdefault("sections_1_3", {k: out[k] for k in ("date", "code", "load_average_after")})
        wide = against_full(default, "default hook", rates=False, patches=WIDE)
        for mu, case in out["default_hook_0.8mm"].items():
            # The full model's float64 rollout is deterministic: the same curve in both runs.
            assert wide[mu]["curves"]["full_N"] == case["curves"]["full_N"], mu
            case["rows"].update(wide[mu]["rows"])
            case["curves"].update(wide[mu]["curves"])
        out["load_average_wide"] = os.getloadavg()[0]
        write_result(out, OUT / "load_patch.json")
        plot(out)
        return 0
    out = {"patches_mm": list(PATCHES), "orders": {}}
    for mesh in MESHES:
        for patch in PATCHES:
            model = jsnap.build(patched(default, patch, **{"solver.mesh_size": mesh}))
            res = jsnap.rollout(model)
            row = {
                "full_dof": int(model.full_dof),
                "orders": [int(o) for o in model.part.orders],
                "peak_N": float(np.max(np.asarray(res.insertion_force))),
                "ok": bool(res.ok),
            }
            out["orders"][f"mesh {mesh:g} patch {patch:g}"] = row
            print(f"default hook mesh {mesh:g} patch {patch:g}:", row, flush=True)
    out["default_hook_0.8mm"] = against_full(default, "default hook", rates=False, patches=PATCHES + WIDE)
    lid = jsnap.load_scene(LID).replace({**LID_DEFAULT_SAMPLING, "solver.mesh_size": LID_MESH})
    out["box_lid_1.2mm"] = against_full(lid, "box lid", rates=True)
    out["load_average"] = os.getloadavg()[0]
    write_result(out, OUT / "load_patch.json")
    plot(out)
    return 0


def plot(out):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fine = f"default_hook_{FINE_MESH:g}mm"
    panels = [("default_hook_0.8mm", "default hook, 0.8 mm"), ("box_lid_1.2mm", "box lid tilted 3 deg, 1.2 mm")]
    if fine in out:
        panels.insert(1, (fine, f"default hook, {FINE_MESH:g} mm"))
    fig, ax = plt.subplots(1, 1 + len(panels), figsize=(5.7 * (1 + len(panels)), 4.8))
    for patch in out["patches_mm"]:
        rows = [v for k, v in out["orders"].items() if k.endswith(f"patch {patch:g}")]
        ax[0].plot(
            [r["full_dof"] for r in rows],
            [r["orders"][1] for r in rows],
            "o-",
            label=f"load_patch {patch:g} mm",
        )
    ax[0].set(
        xscale="log",
        xlabel="full dof (default hook, P2 meshes)",
        ylabel="contact segment's coordinates",
        title="order against the mesh",
    )
    ax[0].legend(fontsize=8)
    for a, (key, title) in zip(ax[1:], panels, strict=True):
        for mu, case in out[key].items():
            rows = case["rows"]
            patches = [k for k in rows if k != "full_float64"]
            coords = [sum(rows[k]["orders"]) for k in patches]
            for stat, ls in (("rmse_rise_of_full_peak", "-"), ("rmse_of_full_peak", ":")):
                a.plot(
                    coords,
                    [100 * rows[k][stat] for k in patches],
                    "o" + ls,
                    label=f"{mu}, {'rise' if 'rise' in stat else 'whole motion'}",
                )
            for k, x in zip(patches, coords, strict=True):
                a.annotate(f"{k} mm", (x, 100 * rows[k]["rmse_rise_of_full_peak"]), fontsize=7)
        a.set(
            xlabel="reduced coordinates (patch in mm marked)",
            ylabel="RMS difference from the full model (% of its peak)",
            title=title,
            ylim=(0, None),
        )
        a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(OUT / "load_patch.png", dpi=110)


if __name__ == "__main__":
    raise SystemExit(main())
