"""One part, two files, under refinement: the shipped hook given as a tet mesh with a named
fixed group and as a closed STL surface that jsnap tet-meshes with gmsh. Their force curves
must agree within the mesh difference, which must shrink as the mesh is refined.

    python benchmarks/own_parts.py [--sizes 1.0 0.8 0.6 0.5]

For each element size h: the default hook's structured P2 mesh at h is written as an Abaqus
``.inp`` file with its root face as the node set "root" (the *tet* path), and its boundary at
the coarsest size as an STL (the *STL* path: the same surface, meshed by gmsh at h, fixed by a
box around z = 0). The rigid part is the preset plug as an STL, pushed straight down by the
default stroke. Both run the reduced model in float64 (its peak is within 0.5 % of the full
model's on the default hook; the full model's dense inverse does not fit at the finest sizes).
Recorded per size: free dofs, peaks, the STL peak's relative difference from the tet one, and
the RMSE between the curves relative to the tet peak. Writes
benchmarks/results/own_parts.{json,png}.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import meshio
import numpy as np
import trimesh
from _common import code_version

import jsnap
from jsnap._geometry.cantilever import mesh_cantilever
from jsnap._geometry.presets import default_rigid
from jsnap._geometry.scene import connector_geometry, motion_stroke

jsnap.configure_xla_cpu()

OUT = Path(__file__).resolve().parent / "results"
MATERIAL = {"youngs_modulus": 2200.0, "poissons_ratio": 0.35, "density": 1.05e-9}
ROOT_BOX = [[-1.0, -3.0, -0.01], [2.5, 3.0, 0.01]]


def run(part: dict, folder: Path, size: float, stroke: float):
    scene = jsnap.Scene.from_dict(
        {
            "part": part,
            "rigid": {"mesh": str(folder / "plug.stl")},
            "material": MATERIAL,
            "motion": {"stroke": stroke},
            "solver": {"mesh_size": size, "dtype": "float64"},
        }
    )
    t0 = time.perf_counter()
    model = jsnap.build(scene, progress=True)
    seconds = time.perf_counter() - t0
    res = jsnap.rollout(model)
    return model, np.asarray(res.insertion_force), res.status(), seconds


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=float, nargs="+", default=[1.0, 0.8, 0.6, 0.5])
    args = ap.parse_args(argv)
    preset = jsnap.load_scene()
    geom = connector_geometry(preset)
    stroke = motion_stroke(preset)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        plug = default_rigid("cantilever", preset["connector"], preset["plug"])
        surface = plug.mesh()
        surface.apply_translation(plug.start)
        surface.export(folder / "plug.stl")
        coarse = mesh_cantilever(geom, max(args.sizes))
        trimesh.Trimesh(coarse.points, coarse.boundary_faces()).export(folder / "hook.stl")
        for size in args.sizes:
            mesh = mesh_cantilever(geom, size)
            inp = folder / f"hook_{size:g}.inp"
            meshio.write(
                inp, meshio.Mesh(mesh.points, [("tetra", mesh.cells)], point_sets={"root": mesh.base_nodes})
            )
            m_tet, f_tet, s_tet, t_tet = run({"mesh": str(inp), "fixed": "root"}, folder, size, stroke)
            part = {"mesh": str(folder / "hook.stl"), "fixed_box": ROOT_BOX}
            m_stl, f_stl, s_stl, t_stl = run(part, folder, size, stroke)
            n = min(f_tet.size, f_stl.size)
            row = {
                "mesh_size": size,
                "tet_full_dof": m_tet.full_dof,
                "stl_full_dof": m_stl.full_dof,
                "tet_peak_N": float(f_tet.max()),
                "stl_peak_N": float(f_stl.max()),
                "stl_vs_tet_peak": float(f_stl.max() / f_tet.max() - 1),
                "rmse_rel_peak": float(np.sqrt(np.mean((f_stl[:n] - f_tet[:n]) ** 2)) / f_tet.max()),
                "status": [s_tet, s_stl],
                "build_seconds": [t_tet, t_stl],
                "tet_force": f_tet.tolist(),
                "stl_force": f_stl.tolist(),
            }
            rows.append(row)
            print(
                f"h = {size:g} mm: tet {row['tet_full_dof']} dof {row['tet_peak_N']:.4f} N, STL "
                f"{row['stl_full_dof']} dof {row['stl_peak_N']:.4f} N ({100 * row['stl_vs_tet_peak']:+.2f} %)",
                flush=True,
            )
    diffs = [abs(r["stl_vs_tet_peak"]) for r in rows]
    headline = {
        "sizes": [r["mesh_size"] for r in rows],
        "stl_vs_tet_peak": [r["stl_vs_tet_peak"] for r in rows],
        "rmse_rel_peak": [r["rmse_rel_peak"] for r in rows],
        "finest_within": diffs[-1],
        "all_ok": all(s == "ok" for r in rows for s in r["status"]),
    }
    data = {
        "headline": headline,
        "rows": rows,
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "load": os.getloadavg()},
        "code": code_version(),
    }
    OUT.mkdir(exist_ok=True)
    (OUT / "own_parts.json").write_text(json.dumps(data, indent=1))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    for r in rows:
        (line,) = ax[0].plot(r["tet_force"], lw=1.2, label=f"tet file, h = {r['mesh_size']:g}")
        ax[0].plot(
            r["stl_force"], lw=1.0, ls="--", color=line.get_color(), label=f"STL, h = {r['mesh_size']:g}"
        )
    ax[0].set_xlabel("step")
    ax[0].set_ylabel("insertion force (N)")
    ax[0].legend(fontsize=7)
    ax[1].plot(headline["sizes"], np.abs(headline["stl_vs_tet_peak"]) * 100, "o-", label="|peak difference|")
    ax[1].plot(headline["sizes"], np.array(headline["rmse_rel_peak"]) * 100, "s-", label="curve RMSE / peak")
    ax[1].set_xlabel("element size h (mm)")
    ax[1].set_ylabel("STL path against tet file (%)")
    ax[1].invert_xaxis()
    ax[1].legend()
    fig.suptitle("The default hook from a tet file and from an STL, under refinement (reduced, float64)")
    fig.tight_layout()
    fig.savefig(OUT / "own_parts.png", dpi=110)
    return 0 if headline["all_ok"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
