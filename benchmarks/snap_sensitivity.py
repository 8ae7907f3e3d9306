"""How precisely the full model itself determines a preset's whole force curve, against how far
the shipped reduced model is from it: the yardstick for the "insertion-force RMSE within 2 % of
the peak against the full model" target.

    python benchmarks/snap_sensitivity.py [--presets two_hook_clip,cable_latch,box_lid,annular]

(``--presets`` with some of them reruns those and keeps the other presets' rows of the JSON.)

For each connector preset, frictionless and at mu = 0.3, the reference is the full model in
float64 with its contact solved by APGD to the scene's tolerance (up to 5000 iterations), as in
the presets' own benchmarks (the box lid on its 1.2 mm mesh, both models, as
``benchmarks/box_lid.py`` compares them). Against it, the RMS difference in % of its peak over
the whole motion, over the rise (up to its peak), and split at the snap (the largest one-step
drop of the reference: the part before and after it, each over the whole motion's steps, so that
their squares add up to the whole's):

- the same full model in float32 (round-off only);
- the same full model in float64 with the contact solved to 1e-8 (the solve's stopping point);
- the reference delayed by one step (every event 1 ms, 0.01 mm of travel, late);
- the shipped reduced model in float32, and the same reduced model in float64.

The first three are the full model's own determinacy: where they already exceed 2 %, no model
can be held to 2 % of it over the whole motion. The reduced model's own float32 round-off is
measured the same way (its float32 curve against its float64 one, ``reduced_own_float32``):
where that exceeds its difference from the full model, the difference is of the size of the
reduced model's own determinacy. Also the RMS of each curve after the snap in %
of the peak (how hard the parts keep hitting each other once the hooks are free).

Writes benchmarks/results/snap_sensitivity.{json,png}. Untimed (the numbers are differences
between curves); ~35 min on two cores.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from _common import (
    LID_DEFAULT_SAMPLING,
    kept_rows,
    load_scene,
    presets_option,
    previous_result,
    stamped,
    write_result,
)

import jsnap
from jsnap._geometry.scene import default_scene_path

jsnap.configure_xla_cpu()

OUT = Path(__file__).parent / "results"
SCENES = default_scene_path().parent
PRESETS = ("two_hook_clip", "cable_latch", "box_lid", "annular")
FULL_CONTACT = {"contact.solver": "apgd", "contact.iterations": 5000}
TIGHT = {"contact.tolerance": 1e-8}
# The box lid's full model on the shipped 0.8 mm mesh needs ~10 GB: both models on 1.2 mm.
MESH = {"box_lid": {"solver.mesh_size": 1.2, **LID_DEFAULT_SAMPLING}}


def snap_step(ref) -> int:
    """The step after ``ref``'s largest one-step drop (the snap)."""
    return int(np.argmax(-np.diff(ref))) + 1


def split(F, ref) -> dict:
    """RMS differences of ``F`` from ``ref`` in % of ``ref``'s peak: whole, rise, and the parts
    before and after ``ref``'s largest one-step drop; and each curve's RMS after it."""
    peak = ref.max()
    e2 = (F - ref) ** 2
    n = len(ref)
    snap = snap_step(ref)
    rise = int(np.argmax(ref)) + 1
    return {
        "whole": float(np.sqrt(e2.mean()) / peak),
        "rise": float(np.sqrt(e2[:rise].mean()) / peak),
        "before_snap": float(np.sqrt(e2[:snap].sum() / n) / peak),
        "after_snap": float(np.sqrt(e2[snap:].sum() / n) / peak),
        "rms_after_snap_of_peak": float(np.sqrt(np.mean(F[snap:] ** 2)) / peak),
    }


def run(preset: str, mu: float) -> dict:
    scene = load_scene(
        {"contact.friction": mu, **MESH.get(preset, {})}, jsnap.load_scene(SCENES / f"{preset}.toml")
    )
    full_model = jsnap.build(load_scene({"solver.method": "full", **FULL_CONTACT}, scene))
    ref = jsnap.rollout(full_model, dtype="float64")
    F = np.asarray(ref.insertion_force, np.float64)
    f32 = jsnap.rollout(full_model, dtype="float32")
    tight = jsnap.rollout(
        jsnap.build(load_scene({"solver.method": "full", **FULL_CONTACT, **TIGHT}, scene)), dtype="float64"
    )
    red_model = jsnap.build(scene)
    red = jsnap.rollout(red_model)
    red64 = jsnap.rollout(red_model, dtype="float64")
    R64 = np.asarray(red64.insertion_force, np.float64)
    curves = {
        "full_float32": np.asarray(f32.insertion_force, np.float64),
        "full_float64_tol_1e-8": np.asarray(tight.insertion_force, np.float64),
        "full_one_step_late": np.concatenate([F[:1], F[:-1]]),
        "reduced_float32": np.asarray(red.insertion_force, np.float64),
        "reduced_float64": R64,
    }
    snap = snap_step(F)
    return {
        "full_dof": int(full_model.full_dof),
        "reduced_orders": [int(k) for k in red_model.part.orders],
        "mesh_size": float(scene["solver"]["mesh_size"]),
        "peak_N": float(F.max()),
        "snap_step": snap,
        "snap_drop_of_peak": float((F[snap - 1] - F[snap]) / F.max()),
        "steps": len(F),
        "ok": {
            "full_float64": bool(ref.ok),
            "full_float32": bool(f32.ok),
            "tight": bool(tight.ok),
            "reduced": bool(red.ok),
            "reduced_float64": bool(red64.ok),
        },
        "reference_rms_after_snap_of_peak": split(F, F)["rms_after_snap_of_peak"],
        "against_full_float64": {name: split(G, F) for name, G in curves.items()},
        "reduced_own_float32": split(curves["reduced_float32"], R64),
        "curves": {"travel_mm": np.asarray(ref.travel).tolist(), "full_float64_N": F.tolist()}
        | {f"{k}_N": v.tolist() for k, v in curves.items() if k != "full_one_step_late"},
    }


def plot(out: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [(p, mu, r) for p, by_mu in out["presets"].items() for mu, r in by_mu.items()]
    names = [
        "full_float32",
        "full_float64_tol_1e-8",
        "full_one_step_late",
        "reduced_float32",
        "reduced_float64",
    ]
    labels = [
        "full, float32",
        "full, contact tol 1e-8",
        "full, one step late",
        "reduced (shipped)",
        "reduced, float64",
    ]
    fig, ax = plt.subplots(figsize=(11, 4.2))
    width = 0.8 / len(names)
    x = np.arange(len(rows))
    for i, (name, label) in enumerate(zip(names, labels, strict=True)):
        ax.bar(
            x + i * width,
            # Rows kept from a run before a variant was added have no bar for it.
            [100 * r["against_full_float64"].get(name, {"whole": np.nan})["whole"] for _, _, r in rows],
            width,
            label=label,
        )
    ax.axhline(2.0, color="k", lw=0.8, ls="--", label="2 % target")
    ax.set_xticks(x + 0.4 - width / 2, [f"{p}\n{mu}" for p, mu, _ in rows], fontsize=8)
    ax.set_ylabel("whole-motion RMS difference\nfrom full float64, % of peak")
    ax.set_yscale("log")
    ax.legend(fontsize=8)
    ax.set_title("The full model's own determinacy against the reduced model's difference")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    presets = presets_option(ap, PRESETS, argv)
    path = OUT / "snap_sensitivity.json"
    out = {"what": __doc__.splitlines()[0], "full_contact": FULL_CONTACT, "tight": TIGHT}
    out["presets"] = kept_rows(previous_result(path, presets, PRESETS), presets, PRESETS)
    for preset in presets:
        for mu in (0.0, 0.3):
            r = out["presets"].setdefault(preset, {})[f"mu {mu:g}"] = stamped(run(preset, mu))
            print(preset, mu, json.dumps({k: v for k, v in r.items() if k != "curves"}), flush=True)
    write_result(out, path)
    plot(out, OUT / "snap_sensitivity.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
