"""The summary's headline numbers under mesh refinement: the peak insertion force and the
bending strain of every preset and example, at two element sizes each.

    python benchmarks/headline_convergence.py [--cases default,annular,...] [--replot]

For each case, the scene at its element size and at 0.8 times it (``solver.mesh_size``; the
rest of the scene as shipped) is built and rolled out, and the numbers ``jsnap simulate``
reports are taken from the rollout:

- the headline peak force (``jsnap._apps.simulate.peak_force``: each step's force counted up
  to the Theil-Sen line through it and the steps before it, ``PEAK_FORCE_STEPS`` = 9 in all)
  against the largest single step, and for the record the peaks of the 3-step running median
  and of the 5-step running mean;
- the bending strain (``jsnap._build.strain.bending_strain``, read in the wall of
  ``bending_wall``: the line fitted 1 to 3 walls from the singular edges, extrapolated to them,
  and the strain at least 1.5 walls from them; contacts left out) against the largest strain
  over the whole part and, for a preset, over its arm box, and the design guide's strain where
  it has one.

A case that cannot be built on this machine (its reduction needs more memory than it has) is
listed with the reason. The force histories are kept, so ``--replot`` redraws and re-tabulates
from the JSON. Writes benchmarks/results/headline_convergence.json and .png.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
import warnings
from pathlib import Path

import matplotlib
import numpy as np
from _common import code_version
from scipy.ndimage import median_filter

import jsnap
from jsnap._apps.simulate import (
    PEAK_FORCE_STEPS,
    arm_box,
    arm_elements,
    bending_wall,
    design_guide_strain,
    peak_force,
)
from jsnap._build.strain import bending_region, bending_strain, peak_strain

matplotlib.use("Agg")
import matplotlib.pyplot as plt

jsnap.configure_xla_cpu()

OUT = Path(__file__).parent / "results"
ROOT = Path(__file__).resolve().parents[1]
CASES = {
    "default": None,
    "two_hook_clip": "jsnap/scenes/two_hook_clip.toml",
    "cable_latch": "jsnap/scenes/cable_latch.toml",
    "own_connector": "examples/own_connector/scene.toml",
    "annular": "jsnap/scenes/annular.toml",
    "box_lid": "jsnap/scenes/box_lid.toml",
    "printed_hook": "examples/printed_hook/scene.toml",
}
FINER = 0.8


def run_case(name: str, path) -> dict:
    from jsnap._build.memory import BuildError

    base = jsnap.load_scene(None if path is None else ROOT / path)
    h0 = float(base["solver"]["mesh_size"])
    row = {"case": name, "scene": path or "default", "runs": []}
    for h in (h0, FINER * h0):
        scene = base.replace({"solver.mesh_size": h})
        t0 = time.perf_counter()
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                model = jsnap.build(scene)
        except (BuildError, MemoryError) as e:
            row["runs"].append({"mesh_size": h, "skipped": str(e)})
            print(f"{name} h={h:g}: skipped: {e}", flush=True)
            continue
        res = jsnap.rollout(model, keep_x=True)
        F, travel = np.asarray(res.insertion_force, float), np.asarray(res.travel, float)
        wall = bending_wall(scene)
        region = bending_region(model, wall)
        bend = bending_strain(model, res, wall=wall, region=region)
        part = peak_strain(model, res)
        arm = arm_box(scene["connector"])
        arm_peak = None
        if arm is not None:
            nodes, cells = np.asarray(model.mesh.nodes), np.asarray(model.mesh.cells)
            arm_peak = float(peak_strain(model, res, elements=arm_elements(nodes, cells, arm)).max_principal)
        run = {
            "mesh_size": h,
            "status": res.status(),
            "dof": int(model.n_dof),
            "elements": int(np.asarray(model.mesh.cells).shape[0]),
            "steps": int(F.size),
            **force_metrics(F, travel),
            "wall_mm": wall,
            "bending_strain": float(bend.max_principal),
            "bending_strain_at_edge": bool(bend.at_edge),
            "bending_strain_position_mm": [float(c) for c in bend.position],
            "bending_strain_travel_mm": float(travel[bend.step]) if bend.step >= 0 else None,
            "singular_edges": int(region.edges.shape[0]),
            "paths": int(region.root.shape[0]),
            "part_max_strain": float(part.max_principal),
            "part_max_strain_position_mm": [float(c) for c in part.position],
            "arm_box_strain": arm_peak,
            "design_guide_strain": design_guide_strain(scene),
            "seconds": time.perf_counter() - t0,
            "travel": travel.tolist(),
            "force": F.tolist(),
        }
        row["runs"].append(run)
        print(
            f"{name} h={h:g}: {run['status']}, {run['dof']} dof; peak force {run['peak_force_N']:.4f} N "
            f"(raw {run['raw_max_force_N']:.4f}); "
            f"bending strain {100 * bend.max_principal:.3f} % (part {100 * part.max_principal:.3f} %, guide "
            f"{run['design_guide_strain']}); {run['seconds']:.0f} s",
            flush=True,
        )
    return changes(row)


def force_metrics(F, travel) -> dict:
    """The headline peak force of a history and the other readings of it."""
    F, travel = np.asarray(F, float), np.asarray(travel, float)
    head, k = peak_force(F)
    raw = int(np.nanargmax(F))
    return {
        "peak_force_N": head,
        "travel_at_peak_force_mm": float(travel[k]),
        "raw_max_force_N": float(F[raw]),
        "travel_at_raw_max_mm": float(travel[raw]),
        "median3_peak_N": float(np.nanmax(median_filter(F, 3, mode="nearest"))),
        "mean5_peak_N": float(np.nanmax(np.convolve(F, np.ones(5) / 5, mode="valid"))),
    }


def changes(row: dict) -> dict:
    """The relative changes from the first mesh to the second, into ``row["change"]``."""
    done = [r for r in row["runs"] if "skipped" not in r]
    if len(done) == 2:
        a, b = done

        def change(key):
            return abs(b[key] / a[key] - 1)

        keys = ("peak_force_N", "raw_max_force_N", "median3_peak_N", "mean5_peak_N", "bending_strain")
        keys += ("part_max_strain",)
        row["change"] = {key: change(key) for key in keys}
        if a["arm_box_strain"] is not None:
            row["change"]["arm_box_strain"] = change("arm_box_strain")
    return row


def plot(rows, path: Path) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    names = [r["case"] for r in rows if "change" in r]
    x = np.arange(len(names))
    ch = {r["case"]: r["change"] for r in rows if "change" in r}
    for off, (key, label) in zip(
        (-0.3, -0.1, 0.1, 0.3),
        (
            ("peak_force_N", f"peak force ({PEAK_FORCE_STEPS}-step median)"),
            ("raw_max_force_N", "largest single step"),
            ("bending_strain", "bending strain"),
            ("part_max_strain", "whole-part max strain"),
        ),
        strict=True,
    ):
        axes[0].bar(x + off, [100 * ch[n][key] for n in names], 0.2, label=label)
    axes[0].axhline(3.0, color="k", lw=0.8, ls="--")
    axes[0].set_xticks(x, names, rotation=30, ha="right")
    axes[0].set_ylabel("change between the two meshes, %")
    axes[0].set_yscale("log")
    axes[0].legend(fontsize=8)
    for r in rows:
        done = [u for u in r["runs"] if "skipped" not in u]
        if not done:
            continue
        g = [100 * u["bending_strain"] for u in done]
        guide = done[0]["design_guide_strain"]
        axes[1].plot([r["case"]] * len(g), g, "o", color="C0")
        if guide is not None:
            axes[1].plot([r["case"]], [100 * guide], "k_", ms=20)
    axes[1].set_ylabel("bending strain, % (bar: design guide)")
    axes[1].tick_params(axis="x", rotation=30)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--replot", action="store_true")
    args = ap.parse_args()
    OUT.mkdir(exist_ok=True)
    out = OUT / "headline_convergence.json"
    if args.replot:
        data = json.loads(out.read_text())
        rows = data["rows"]
        for row in rows:  # the force readings again, from the kept histories
            for run in row["runs"]:
                if "force" in run:
                    run.update(force_metrics(run["force"], run["travel"]))
            changes(row)
        data["peak_force_steps"] = PEAK_FORCE_STEPS
        out.write_text(json.dumps(data, indent=1))
    else:
        old = {r["case"]: r for r in json.loads(out.read_text())["rows"]} if out.exists() else {}
        for name in args.cases.split(","):
            old[name] = run_case(name, CASES[name])
            rows = [old[n] for n in CASES if n in old]
            out.write_text(
                json.dumps(
                    {
                        "what": "peak force and bending strain at two meshes per preset and example",
                        "peak_force_steps": PEAK_FORCE_STEPS,
                        "finer": FINER,
                        "machine": platform.node(),
                        "code": code_version(),
                        "rows": rows,
                    },
                    indent=1,
                )
            )
    for r in rows:
        if "change" in r:
            print(r["case"], {k: f"{100 * v:.2f} %" for k, v in r["change"].items()})
    plot(rows, OUT / "headline_convergence.png")


if __name__ == "__main__":
    main()
