"""Strain and stress outputs: what they add to ``jsnap simulate``, and the shipped hook's peak
strain against the snap-fit design guide and under mesh refinement.

    python benchmarks/strain.py [--quick]

1. Cost (timed). On the shipped scene (reduced model) the output step of ``jsnap simulate``
   with strain (``write_series``: every step's strain at every element's vertices, the peaks,
   the ParaView series with each element's largest principal strain and von Mises stress)
   against the same series of the displacement alone. Each repetition starts with
   ``jax.clear_caches()``, so that the one compilation of the part's displacement map is
   counted as in a command-line run; the two alternate, medians, with the load average.
2. The shipped hook against the guide. The guide's strain ``1.5 h y / L^2`` (a tip force at
   z = L deflecting a beam by the undercut y) against (a) beam theory on the simulated load,
   ``6 |M_y| / (E b h^2)`` (bending) and ``- F_z / (E b h)`` (axial) at the root from the
   rollout's base wrench, and (b) the finite-element peak over the arm (every element below
   z = L, every step) and over the whole part. Reduced and full models, mesh 0.8 and 0.6 mm.
3. A straight cantilever under a tip load (static): the strain on the mid-span section against
   beam theory (converges) and the peak at the clamped root (does not: the rigid clamp's edges
   are singular), for 2, 3, 4 (and 6) P2 elements through the thickness.

Writes benchmarks/results/strain.json and strain.png (strain_quick.* with --quick).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import statistics
import tempfile
import time
import warnings
from pathlib import Path

import jax
import matplotlib
import numpy as np
from _common import code_version, load_scene

import jsnap
from jsnap._apps.simulate import design_guide_strain, write_series
from jsnap._build import fem
from jsnap._build.strain import StrainOperator, max_principal, scan
from jsnap._geometry.cantilever import mesh_box
from jsnap._geometry.mesh import write_vtu_series

matplotlib.use("Agg")
import matplotlib.pyplot as plt

jsnap.configure_xla_cpu()

OUT = Path(__file__).parent / "results"
# (method, mesh size in mm) of the full run's comparison with the guide.
RUNS = [("reduced", 0.8), ("full", 0.8), ("reduced", 0.6), ("full", 0.6)]


def series_displacement_only(model, res, out: Path, frames: int = 100) -> Path:
    """The ParaView series of the displacement alone (``write_series`` without the strain)."""
    nodes, cells, free = (np.asarray(a) for a in (model.mesh.nodes, model.mesh.cells, model.mesh.free))
    every = max(1, res.x.shape[0] // frames)
    with jax.enable_x64(True):
        x = jax.numpy.asarray(res.x[::every], jax.numpy.float64)
        disp_free = np.asarray(jax.vmap(model.part.free_displacement)(x))
    disp = np.zeros((disp_free.shape[0], nodes.size))
    disp[:, free] = disp_free
    return write_vtu_series(
        out / "vtu", "socket", nodes, cells, disp.reshape(-1, nodes.shape[0], 3), np.asarray(res.t)[::every]
    )


_RUNS: dict = {}


def run(scene):
    """The built model and its rollout (with coordinates), once per scene."""
    key = json.dumps(scene.to_dict(), sort_keys=True, default=str)
    if key not in _RUNS:
        model = jsnap.build(scene)
        _RUNS[key] = model, jsnap.rollout(model, keep_x=True)
    return _RUNS[key]


def cost(scene, reps: int) -> dict:
    model, res = run(scene)
    L = scene["connector"]["length"]
    variants = {
        "displacement_only": lambda out: series_displacement_only(model, res, out),
        "with_strain": lambda out: write_series(model, res, out, L),
    }
    times = {k: [] for k in variants}
    scan_times = []
    x, t = np.asarray(res.x), np.asarray(res.t)
    for rep in range(reps):
        order = list(variants) if rep % 2 == 0 else list(variants)[::-1]
        for name in order:
            with tempfile.TemporaryDirectory() as tmp:
                jax.clear_caches()
                t0 = time.perf_counter()
                variants[name](Path(tmp))
                times[name].append(time.perf_counter() - t0)
        jax.clear_caches()
        t0 = time.perf_counter()
        scan(model, x, t, float(model.params.E), float(model.params.nu))
        scan_times.append(time.perf_counter() - t0)
    med = {k: statistics.median(v) for k, v in times.items()}
    return {
        "scene": "shipped scene" if scene.source == jsnap.load_scene().source else scene.source,
        "method": model.method,
        "full_dof": model.full_dof,
        "dof": model.n_dof,
        "elements": int(model.mesh.cells.shape[0]),
        "steps": int(x.shape[0]),
        "reps": reps,
        "seconds": times,
        "median_seconds": med,
        "added_seconds": med["with_strain"] - med["displacement_only"],
        "ratio": med["with_strain"] / med["displacement_only"],
        "scan_median_seconds": statistics.median(scan_times),
        "load_average_after": os.getloadavg(),
    }


def guide_comparison(scene, runs) -> list[dict]:
    c, mat = scene["connector"], scene["material"]
    L, h, b, E = c["length"], c["thickness"], c["width"], mat["youngs_modulus"]
    guide = design_guide_strain(scene)
    rows = []
    for method, size in runs:
        t0 = time.perf_counter()
        model, res = run(scene.replace({"solver.method": method, "solver.mesh_size": size}))
        nodes, cells = np.asarray(model.mesh.nodes), np.asarray(model.mesh.cells)
        arm = np.all(nodes[cells[:, :4], 2] <= L * (1 + 1e-12), axis=1)
        peaks, _ = scan(
            model,
            np.asarray(res.x),
            np.asarray(res.t),
            float(model.params.E),
            float(model.params.nu),
            regions={"part": None, "arm": arm},
        )
        M_y, F_z = np.asarray(res.base_moment)[:, 1], np.asarray(res.base_force)[:, 2]
        bending = 6.0 * np.abs(M_y) / (E * b * h**2)
        axial = -F_z / (E * b * h)
        beam = bending + axial
        k = int(np.nanargmax(beam))
        a, p = peaks["arm"], peaks["part"]
        travel = np.asarray(res.travel)
        rows.append(
            {
                "method": method,
                "mesh_size_mm": size,
                "full_dof": model.full_dof,
                "dof": model.n_dof,
                "status": res.status(),
                "guide_strain": guide,
                "beam_root_strain": float(beam[k]),
                "beam_root_bending_strain": float(bending[k]),
                "beam_root_axial_strain": float(axial[k]),
                "beam_step": k,
                "beam_travel_mm": float(travel[k]),
                "arm_peak_strain": a.max_principal,
                "arm_peak_step": a.step,
                "arm_peak_travel_mm": float(travel[a.step]),
                "arm_peak_position_mm": a.position.tolist(),
                "arm_peak_von_mises_MPa": a.von_mises,
                "part_peak_strain": p.max_principal,
                "part_peak_step": p.step,
                "part_peak_travel_mm": float(travel[p.step]),
                "part_peak_position_mm": p.position.tolist(),
                "part_peak_von_mises_MPa": p.von_mises,
                "beam_over_guide": float(beam[k]) / guide,
                "arm_peak_over_beam": a.max_principal / float(beam[k]),
                "arm_peak_over_guide": a.max_principal / guide,
                "part_peak_over_guide": p.max_principal / guide,
                "seconds": time.perf_counter() - t0,
                "_curves": {
                    "travel": travel,
                    "arm": a.history,
                    "part": p.history,
                    "beam": beam,
                },
            }
        )
        print(f"{method} {size} mm: {json.dumps({k: v for k, v in rows[-1].items() if k != '_curves'})}")
    return rows


def cantilever(divisions_list) -> list[dict]:
    """Square 1.2 mm arm, 8 mm long, clamped at z = 0, a 1 N tip shear along x."""
    E, nu, h, L, P = 2200.0, 0.35, 1.2, 8.0, 1.0
    I = h**4 / 12.0
    rows = []
    for div in divisions_list:
        t0 = time.perf_counter()
        asm = fem.assemble(mesh_box(h, h, L, divisions=div), "P2")
        f = fem.traction_load(asm, lambda x: np.isclose(x[2], L), [P / h**2, 0.0, 0.0])
        u = fem.solve_static(asm, E, nu, f).reshape(-1, 3)
        eps = StrainOperator.from_mesh(asm.nodes, asm.cells).strain(u)
        X = asm.nodes[asm.cells[:, :4]]
        on = np.isclose(X[..., 2], L / 2)
        surface = P * (L / 2) * (h / 2) / (E * I)
        exact = -P * (L / 2) * (X[..., 0] - h / 2) / (E * I)
        mp = max_principal(eps)
        root = P * L * (h / 2) / (E * I)
        rows.append(
            {
                "divisions": list(div),
                "elements_through_thickness": div[0],
                "dof": asm.n_dof,
                "midspan_max_error_rel": float(np.max(np.abs(eps[..., 2, 2] - exact)[on]) / surface),
                "peak_over_beam_root": float(mp.max() / root),
                "peak_position_mm": X[np.unravel_index(np.argmax(mp), mp.shape)].tolist(),
                "seconds": time.perf_counter() - t0,
            }
        )
        print(f"cantilever {div}: {rows[-1]}")
    for a, b in itertools.pairwise(rows):
        b["midspan_order"] = float(
            np.log(a["midspan_max_error_rel"] / b["midspan_max_error_rel"])
            / np.log(b["elements_through_thickness"] / a["elements_through_thickness"])
        )
    return rows


def plot(rows, path: Path, title: str) -> None:
    fig, ax = plt.subplots(figsize=(8, 4.8))
    for r in rows:
        c = r["_curves"]
        label = f"{r['method']} {r['mesh_size_mm']} mm"
        ax.plot(c["travel"], 100 * c["arm"], lw=1.4, label=f"FEM peak in the arm, {label}")
        if r["method"] == "full":
            ax.plot(c["travel"], 100 * c["part"], lw=0.8, ls=":", label=f"FEM peak over the part, {label}")
    r0 = rows[0]
    ax.plot(r0["_curves"]["travel"], 100 * r0["_curves"]["beam"], "k-", lw=0.8, alpha=0.6,
            label="beam theory at the root, simulated base wrench")  # fmt: skip
    ax.axhline(100 * r0["guide_strain"], color="k", ls="--", lw=0.8, label="design guide 1.5 h y / L²")
    ax.set_xlabel("travel of the rigid part (mm)")
    ax.set_ylabel("largest principal strain (%)")
    top = max(np.nanmax(r["_curves"]["arm"]) for r in rows)
    ax.set_ylim(0, 100 * top * 1.5)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    warnings.simplefilter("ignore", jsnap.SceneWarning)
    scene = load_scene()
    if args.quick:
        cheap = scene.replace({"solver.method": "full", "solver.mesh_size": 1.5, "motion.speed": 40.0})
        out = {
            "cost": cost(cheap, reps=1),
            "guide": guide_comparison(cheap, [("full", 1.5)]),
            "cantilever": cantilever([(2, 2, 14), (3, 3, 20)]),
        }
    else:
        out = {
            "cost": cost(scene, reps=5),
            "guide": guide_comparison(scene, RUNS),
            "cantilever": cantilever([(2, 2, 14), (3, 3, 20), (4, 4, 28), (6, 6, 40)]),
        }
    stem = "strain_quick" if args.quick else "strain"
    machine = f"{platform.machine()}, {os.cpu_count()} CPUs, {platform.system()}"
    plot(out["guide"], OUT / f"{stem}.png", f"jsnap: largest principal strain of the shipped hook ({machine})")
    for r in out["guide"]:
        r.pop("_curves")
    c, g = out["cost"], {(r["method"], r["mesh_size_mm"]): r for r in out["guide"]}
    first = out["guide"][0]
    headline = {
        "cost_median_seconds": c["median_seconds"],
        "cost_added_seconds": c["added_seconds"],
        "cost_ratio": c["ratio"],
        "guide_strain": first["guide_strain"],
        "beam_over_guide": first["beam_over_guide"],
        "arm_peak_over_guide": {f"{m} {s}": r["arm_peak_over_guide"] for (m, s), r in g.items()},
        "part_peak_over_guide": {f"{m} {s}": r["part_peak_over_guide"] for (m, s), r in g.items()},
        "cantilever_midspan_error": {
            r["elements_through_thickness"]: r["midspan_max_error_rel"] for r in out["cantilever"]
        },
        "cantilever_root_peak_over_beam": {
            r["elements_through_thickness"]: r["peak_over_beam_root"] for r in out["cantilever"]
        },
    }
    result = {
        "headline": headline,
        **out,
        "machine": machine,
        "code": code_version(),
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "quick": args.quick,
    }
    OUT.mkdir(exist_ok=True)
    (OUT / f"{stem}.json").write_text(json.dumps(result, indent=2, default=float) + "\n")
    print(json.dumps(headline, indent=2, default=float))


if __name__ == "__main__":
    main()
