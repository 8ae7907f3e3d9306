"""Parts of other sizes: the shipped hook scaled from 1/16 to 16 times, as a preset and as files,
against dimensional analysis.

    python benchmarks/part_size.py

Scaling every length of a scene by k and every time by k (the time step; the speed unchanged)
scales every force by k^2, step for step (masses go as k^3, accelerations as 1/k, stiffnesses
as k). jsnap's defaults that are lengths follow the part (``jsnap._geometry.size``): the
geometric ones (element size, rigid part) with the wall ratio, the contact's resolution with the
part's size, 1 within a factor 2 of the shipped walls and proportional beyond. So hooks 8 and 16
times the shipped one are the same discrete problem, and across the band the contact is
sampled at another density per wall.

Two families, each frictionless and at friction 0.3, in float64 with the default (reduced)
model:

1. ``preset``: the shipped default scene with every length and time it gives times k (its
   0.8 mm mesh, its plug's fillet, its time step), k = 1/16, 1/8, 1/4, 1, 4, 8, 16;
2. ``files``: the shipped hook and its plug written to STL files (float32 vertices, as a CAD
   export) ten times smaller and larger, tet-meshed by gmsh at 0.8 k mm, the stroke 2.3 k mm and
   the time step 1 ms k.

Each is rolled out as ``jsnap simulate`` runs it: where the default contact buffer dropped
candidates, again with a buffer that holds them. A rollout flagged ``DEEP_PENETRATION`` is run
again with the remedy its message names, ``contact.stabilisation = 0.1`` (``*_stabilised``).
Recorded per case: the part's size, the
contact candidates, the model's coordinates, the buffer used, the rollout's status (its flags
by name), the peak insertion force over k^2 and its ratio to k = 1, and the largest
difference of the force history over k^2 from the k = 1 one (and, for 16, from 8) in % of the
peak.
Writes benchmarks/results/part_size.{json,png}.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import trimesh
from _common import run_status, write_result

import jsnap
from jsnap._apps.simulate import run_sizing_buffer
from jsnap._geometry.cantilever import mesh_cantilever
from jsnap._geometry.presets import default_rigid
from jsnap._geometry.scene import connector_geometry, similar_scene

jsnap.configure_xla_cpu()

OUT = Path(__file__).resolve().parent / "results"
PRESET_SCALES = (1 / 16, 1 / 8, 1 / 4, 1.0, 4.0, 8.0, 16.0)
FILE_SCALES = (0.1, 1.0, 10.0)
FRICTIONS = (0.0, 0.3)
# What a run flagged DEEP_PENETRATION is run again with: a tenth of a penetration removed per step.
REMEDY = {"contact.stabilisation": 0.1}
REMEDY_LABEL = "stabilisation 0.1 (rerun of a flagged run)"


def run(scene: jsnap.Scene, k: float) -> dict:
    """One size: its model built once, rolled out at each friction as ``jsnap simulate`` runs it
    (a default contact buffer that dropped candidates is widened and the run repeated)."""
    model = jsnap.build(scene)
    row = {
        "k": k,
        "size": scene.size,
        "mesh_size_mm": scene.get("solver.mesh_size"),
        "contact_spacing_mm": scene.get("contact.spacing"),
        "width_spacing_mm": scene.get("contact.width_spacing"),
        "contact_points": model.n_samples,
        "dof": model.n_dof,
    }
    for mu in FRICTIONS:
        used, res, widened_from = run_sizing_buffer(
            scene, model, lambda m: jsnap.rollout(m, m.params.replace(friction=mu))
        )
        row[f"force_mu{mu}"] = (np.asarray(res.insertion_force) / k**2).tolist()
        row[f"status_mu{mu}"] = run_status(res)
        row[f"capacity_mu{mu}"] = int(used.contact.capacity)
        row[f"widened_from_mu{mu}"] = widened_from
        row[f"max_penetration_mm_mu{mu}"] = float(np.max(np.asarray(res.penetration)))
        if np.any(np.asarray(res.flags) & jsnap.Flag.DEEP_PENETRATION):
            again = scene.replace(REMEDY)
            _, res2, _ = run_sizing_buffer(
                again, jsnap.build(again), lambda m: jsnap.rollout(m, m.params.replace(friction=mu))
            )
            row[f"force_mu{mu}_stabilised"] = (np.asarray(res2.insertion_force) / k**2).tolist()
            row[f"status_mu{mu}_stabilised"] = run_status(res2)
    print(f"k = {k:g}: size {scene.size:g}, {model.n_samples} points, {model.n_dof} coordinates", flush=True)
    return row


def compare(rows: list[dict]) -> None:
    ref = next(r for r in rows if r["k"] == 1.0)
    by_k = {r["k"]: r for r in rows}
    for r in rows:
        for mu in FRICTIONS:
            F, F1 = np.asarray(r[f"force_mu{mu}"]), np.asarray(ref[f"force_mu{mu}"])
            r[f"peak_mu{mu}"] = float(F.max())
            r[f"peak_ratio_mu{mu}"] = float(F.max() / F1.max())
            if f"force_mu{mu}_stabilised" in r:
                r[f"peak_ratio_mu{mu}_stabilised"] = float(max(r[f"force_mu{mu}_stabilised"]) / F1.max())
            n = min(F.size, F1.size)
            r[f"max_difference_pct_mu{mu}"] = float(100 * np.max(np.abs(F[:n] - F1[:n])) / F1.max())
            twin = by_k.get(r["k"] / 2) if r["k"] > 2 else by_k.get(2 * r["k"]) if r["k"] < 0.5 else None
            if twin is not None:
                G = np.asarray(twin[f"force_mu{mu}"])
                r[f"max_difference_pct_to_k{twin['k']:g}_mu{mu}"] = float(100 * np.max(np.abs(F - G)) / G.max())


def files_scene(d: Path, k: float) -> jsnap.Scene:
    raw = {
        "part": {
            "mesh": str(d / f"hook{k}.stl"),
            "fixed_box": [[-k, -3 * k, -0.01 * k], [2.5 * k, 3 * k, 0.01 * k]],
        },
        "rigid": {"mesh": str(d / f"plug{k}.stl")},
        "material": {"youngs_modulus": 2200.0, "poissons_ratio": 0.35, "density": 1.05e-9},
        "motion": {"stroke": 2.3 * k, "speed": 10.0},
        "solver": {"mesh_size": 0.8 * k, "dt": 1e-3 * k, "dtype": "float64"},
    }
    return jsnap.Scene.from_dict(raw)


def write_files(d: Path, scales) -> None:
    """The shipped hook (its 0.8 mm mesh's surface) and its plug as STL files in ``d``, every
    length times each of ``scales`` (``hook{k}.stl``, ``plug{k}.stl``; float32 vertices)."""
    scene = jsnap.load_scene()
    mesh = mesh_cantilever(connector_geometry(scene), 0.8)
    plug = default_rigid("cantilever", scene["connector"], scene["plug"])
    plug_mesh = plug.mesh()
    plug_mesh.apply_translation(plug.start)
    for k in scales:
        trimesh.Trimesh(mesh.points * k, mesh.boundary_faces()).export(d / f"hook{k}.stl")
        p = plug_mesh.copy()
        p.apply_scale(k)
        p.export(d / f"plug{k}.stl")


def main() -> int:
    base = jsnap.load_scene().replace({"solver.dtype": "float64"})
    preset = [run(similar_scene(base, k), k) for k in PRESET_SCALES]
    compare(preset)
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        write_files(d, FILE_SCALES)
        files = [run(files_scene(d, k), k) for k in FILE_SCALES]
    compare(files)
    out = {"preset": preset, "files": files}
    write_result(out, OUT / "part_size.json")
    plot(out)
    return 0


def plot(out: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    for i, family in enumerate(("preset", "files")):
        rows = out[family]
        for mu, style in zip(FRICTIONS, ("-", "--"), strict=True):
            for r in rows:
                F = np.asarray(r[f"force_mu{mu}"])
                ax[i].plot(np.arange(F.size), F, style, lw=1, label=f"k = {r['k']:g}, mu = {mu:g}")
                if f"force_mu{mu}_stabilised" in r:
                    G = np.asarray(r[f"force_mu{mu}_stabilised"])
                    ax[i].plot(
                        np.arange(G.size), G, ":", lw=1.5, label=f"k = {r['k']:g}, mu = {mu:g}, {REMEDY_LABEL}"
                    )
        ax[i].set_title(f"{family}: insertion force / k^2 (every length and time x k)")
        ax[i].set_xlabel("step")
        # Cut at 1.6 times the k = 1 extremes: a run whose force runs away would flatten the rest.
        ref = next(r for r in rows if r["k"] == 1.0)
        ax[i].set_ylim(
            1.6 * min(min(ref[f"force_mu{mu}"]) for mu in FRICTIONS),
            1.6 * max(max(ref[f"force_mu{mu}"]) for mu in FRICTIONS),
        )
        ax[i].set_ylabel("N")
        ax[i].legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(OUT / "part_size.png", dpi=120)


if __name__ == "__main__":
    raise SystemExit(main())
