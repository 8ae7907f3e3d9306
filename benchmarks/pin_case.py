"""A cylindrical pin pressed onto a tapered hook, both given as STL files, at default settings
and refined: the user's case of docs/own-connector.md followed literally.

The hook is the default cantilever with its tip thinned to 0.8 mm, exported as a surface (as a
CAD tool would); the pin is a 48-sided cylinder of radius 1 mm across the hook, 0.02 mm above
it, its axis over the tip's outer face. Four runs: the defaults, then the element size and the
contact spacing refined together (0.75x and 0.5x of each, and the element size at 0.5x with the
spacing at 0.25x). Each row: status, peak insertion force, the peak's ratio to the finest run's,
the contact points, the dofs, build and run times. Writes ``results/pin_case.json`` and ``.png``.

    python benchmarks/pin_case.py [--quick]

``--quick``: the defaults and the first refinement only.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh
from _common import code_version, write_result

import jsnap
from jsnap._geometry.cantilever import mesh_cantilever
from jsnap._geometry.scene import connector_geometry

HERE = Path(__file__).resolve().parent
# (element size, contact spacing) as multiples of the defaults.
LADDER = ((1.0, 1.0), (0.75, 0.5), (0.5, 0.5), (0.5, 0.25))


def write_files(folder: Path) -> Path:
    """The hook and pin STLs and the scene file (the own-connector page's form) in ``folder``."""
    geom = connector_geometry(jsnap.load_scene().replace(connector__tip_thickness=0.8))
    hook = mesh_cantilever(geom, 0.6)
    trimesh.Trimesh(hook.points, hook.boundary_faces()).export(folder / "taper_hook.stl")
    radius = 1.0
    pin = trimesh.creation.cylinder(radius=radius, height=6.0, sections=48)
    pin.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    pin.apply_translation([0.8 + radius, 0.0, geom.z_top + 0.02 + radius])
    pin.export(folder / "pin.stl")
    path = folder / "pin.toml"
    path.write_text(
        '[part]\nmesh = "taper_hook.stl"\nfixed_box = [[-1.0, -3.0, -0.01], [2.5, 3.0, 0.01]]\n'
        '[rigid]\nmesh = "pin.stl"\n'
        "[material]\nyoungs_modulus = 2200.0\npoissons_ratio = 0.35\ndensity = 1.05e-9\n"
        "[contact]\nfriction = 0.3\n"
        "[motion]\ndirection = [0.0, 0.0, -1.0]\nstroke = 3.0\n"
    )
    return path


def run(scene, size: float, spacing: float) -> dict:
    scene = scene.replace(
        solver__mesh_size=size * float(scene["solver"]["mesh_size"]),
        contact__spacing=spacing * float(scene["contact"]["spacing"]),
    )
    t0 = time.perf_counter()
    model = jsnap.build(scene)
    build_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = jsnap.rollout(model)
    force = np.asarray(res.insertion_force)
    return {
        "mesh_size_mm": float(scene["solver"]["mesh_size"]),
        "contact_spacing_mm": float(scene["contact"]["spacing"]),
        "status": res.status(),
        "peak_insertion_force_N": float(force.max()),
        "travel_mm": np.asarray(res.travel).tolist(),
        "insertion_force_N": force.tolist(),
        "contact_points": int(model.n_samples),
        "dof": int(model.n_dof),
        "build_s": build_s,
        "run_s": time.perf_counter() - t0,
        "load_average": os.getloadavg()[0],
    }


def plot(out: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.2))
    for row in out["runs"]:
        label = f"h = {row['mesh_size_mm']:.3g} mm, spacing {row['contact_spacing_mm']:.3g} mm: {row['status']}"
        ax.plot(row["travel_mm"], row["insertion_force_N"], label=label, lw=1.2)
    ax.set_xlabel("travel (mm)")
    ax.set_ylabel("insertion force (N)")
    ax.set_title("Cylindrical pin on a tapered hook (STL files), defaults and refined")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the defaults and the first refinement")
    args = ap.parse_args(argv)
    jsnap.configure_xla_cpu()
    out = {"code": code_version(), "runs": []}
    with tempfile.TemporaryDirectory() as tmp:
        scene = jsnap.load_scene(write_files(Path(tmp)))
        for size, spacing in LADDER[:2] if args.quick else LADDER:
            row = run(scene, size, spacing)
            out["runs"].append(row)
            print({k: v for k, v in row.items() if not isinstance(v, list)}, flush=True)
    finest = out["runs"][-1]["peak_insertion_force_N"]
    for row in out["runs"]:
        row["peak_ratio_to_finest"] = row["peak_insertion_force_N"] / finest
    out["defaults_within_3_percent_of_finest"] = abs(out["runs"][0]["peak_ratio_to_finest"] - 1) <= 0.03
    name = "pin_case_quick" if args.quick else "pin_case"
    write_result(out, HERE / "results" / f"{name}.json")
    plot(out, HERE / "results" / f"{name}.png")


if __name__ == "__main__":
    sys.exit(main())
