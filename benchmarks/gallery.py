"""The preset gallery: every connector preset jsnap ships, run as its shipped scene.

    python benchmarks/gallery.py [--presets annular,...]

For every preset of ``jsnap._geometry.presets.PRESETS`` (the cantilever's scene is
``jsnap/scenes/default.toml``, every other preset ``p``'s ``jsnap/scenes/<p>.toml``), with the
scene as it is (its default method, the reduced model, rolled out in float32):

1. the reduced orders, the full model's dof and the steps/s of the compiled rollout (median of
   3 timed calls after the compiling one, ``_common.scan_timing``);
2. a rollout with the coordinates kept: the peak insertion force and where it occurs, the peak
   strain of the whole run (``jsnap.peak_strain``), and a figure
   ``docs/img/gallery_<preset>.png``: the deformed surface at the peak-force step coloured by
   each element's largest principal strain (with the rigid part's outline), and the insertion
   force against travel;
3. the insertion force for the materials of :data:`MATERIALS` (E and nu passed as parameters
   to the same reduced model; the scene's friction kept). Where a material's Poisson ratio
   differs from the scene's, the scene is also rebuilt with that material (a basis reduced at
   it) and the two peaks are compared (``basis_check``).

Writes benchmarks/results/gallery.json, docs/img/gallery_<preset>.png for every preset and
docs/img/gallery_materials.png (every preset's force for every material on one chart, the
counterpart of the paper's Fig. 5). ``--presets`` reruns some presets and keeps the other rows
(each row carries its date and commit); the materials chart is then kept as it was.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
from _common import code_version, kept_rows, presets_option, previous_result, scan_timing, stamped

import jsnap
from jsnap._apps.simulate import ring_copies
from jsnap._build.strain import _nodal_displacement
from jsnap._core.sdf import RoundedCylinderSDF
from jsnap._geometry.mesh import TetMesh
from jsnap._geometry.presets import PRESETS
from jsnap._geometry.scene import default_scene_path

# XLA's small-loop option, before the first JAX computation (the committed results have it).
jsnap.configure_xla_cpu()

ROOT = Path(__file__).resolve().parent
OUT = ROOT / "results"
IMG = ROOT.parent / "docs" / "img"
RUNS = 3  # timed rollouts after the compiling one; their median gives steps/s

# The materials of the materials chart: Young's modulus (MPa) and Poisson's ratio at room
# temperature, short-term (the modulus a snap-fit design calculation uses for the one quick
# deflection of an assembly), unfilled injection-moulding grades. ABS is the shipped scenes'
# own material (and the CalculiX reference's, jsnap/data/calculix-cantilever). PC and POM are
# typical values for general-purpose grades (Covestro Makrolon 2405: tensile modulus 2400 MPa;
# a POM copolymer such as BASF Ultraform N2320: 2700-2900 MPa); their Poisson ratios are the
# usual handbook values. A grade's own datasheet (and the secant modulus at the design strain,
# as the Bayer/Covestro "Snap-Fit Joints for Plastics" guide uses) is what a design should take.
MATERIALS = {
    "ABS": {"youngs_modulus": 2200.0, "poissons_ratio": 0.35},
    "PC": {"youngs_modulus": 2400.0, "poissons_ratio": 0.38},
    "POM": {"youngs_modulus": 2800.0, "poissons_ratio": 0.35},
}
MATERIALS_SOURCE = (
    "typical room-temperature short-term values of unfilled grades: ABS as in the shipped scenes; "
    "PC as Covestro Makrolon 2405's tensile modulus (2400 MPa); POM a copolymer's (BASF Ultraform "
    "N2320 class, 2700-2900 MPa); Poisson's ratios the usual handbook values"
)


def scene_of(preset: str):
    """The shipped scene of ``preset`` and its path."""
    path = default_scene_path()
    if preset != "cantilever":
        path = path.parent / f"{preset}.toml"
    return jsnap.load_scene(path), path


def magnification(u: np.ndarray, nodes: np.ndarray) -> float:
    """1, unless the largest displacement is under 2 % of the part's size: then the power of
    ten (or 2 or 5 times one) that brings it to about 5 %."""
    size = float(np.max(np.ptp(nodes, axis=0)))
    umax = float(np.max(np.linalg.norm(u, axis=1)))
    if umax <= 0 or umax >= 0.02 * size:
        return 1.0
    want = 0.05 * size / umax
    return float(max(f * 10**e for e in range(0, 6) for f in (1, 2, 5) if f * 10**e <= want))


def box_edges(centre, quat, half) -> list[np.ndarray]:
    """The 12 edges (each (2, 3)) of a box of half extents ``half`` at ``centre``, turned by
    the unit quaternion ``quat`` (w, x, y, z)."""
    w, x, y, z = quat
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    corners = centre + (signs * half) @ R.T
    edges = []
    for i in range(8):
        for j in range(i + 1, 8):
            if np.sum(signs[i] != signs[j]) == 1:
                edges.append(corners[[i, j]])
    return edges


def bead_profile(centre, half) -> list[np.ndarray]:
    """The annular bead's outline in the plane y = 0 near the sector (x > 0): its side at
    x = radius and 0.3 mm of its two end faces, as (2, 3) segments."""
    R, h = half[0], half[2]
    c = np.asarray(centre, np.float64)
    x, z = np.array([1.0, 0, 0]), np.array([0, 0, 1.0])
    bottom, top = c - h * z, c + h * z
    return [
        np.array([bottom + (R - 0.3) * x, bottom + R * x]),
        np.array([bottom + R * x, top + R * x]),
        np.array([top + (R - 0.3) * x, top + R * x]),
    ]


def run_preset(preset: str) -> tuple[dict, dict]:
    """One preset's numbers (for the JSON) and what its figure needs."""
    scene, path = scene_of(preset)
    model = jsnap.build(scene)
    if model.dtype != "float32":
        print(f"  {preset}: the scene rolls out in {model.dtype}, not float32", flush=True)
    prepared = jsnap.prepare(model)
    load_before = os.getloadavg()
    res_t, first, times = scan_timing(model, prepared, RUNS)
    load_after = os.getloadavg()
    steps = model.motion.shape[0] - 1
    res = jsnap.rollout(model, keep_x=True)
    F, travel = np.asarray(res.insertion_force), np.asarray(res.travel)
    k = int(np.argmax(F))
    strain_k = jsnap.strain(model, res, steps=[k]).max_principal[0].max(axis=-1)  # (m,)
    u_k = _nodal_displacement(model, np.asarray(res.x)[[k]])[0]  # (N, 3) mm
    peak = jsnap.peak_strain(model, res)
    rigid = model.rigid
    half = getattr(rigid, "half", None)
    figure = {
        "nodes": np.asarray(model.mesh.nodes),
        "cells4": np.asarray(model.mesh.cells)[:, :4],
        "u": u_k,
        "strain": strain_k,
        "travel": travel,
        "F": F,
        "k": k,
        "rigid_edges": None
        if half is None
        else bead_profile(np.asarray(res.plug)[k], np.asarray(half))
        if isinstance(rigid, RoundedCylinderSDF)
        else box_edges(np.asarray(res.plug)[k], np.asarray(res.plug_rotation)[k], np.asarray(half)),
    }
    copies = ring_copies(scene)
    row = {
        "scene": str(path.relative_to(ROOT.parent)) if path.is_relative_to(ROOT.parent) else path.name,
        "method": model.method,
        "element": model.element,
        "dtype": model.dtype,
        "steps": steps,
        "dt_s": model.dt,
        "friction": float(model.params.friction),
        "youngs_modulus_MPa": float(model.params.E),
        "poissons_ratio": float(model.params.nu),
        "orders": [int(o) for o in model.part.orders],
        "coordinates": int(model.n_dof),
        "full_dof": int(model.full_dof),
        "status": res.status(),
        "peak_insertion_force_N": float(F[k]),
        "travel_at_peak_mm": float(travel[k]),
        # The annular preset models a sector: its whole ring's force is this many times more.
        "ring_copies": copies,
        "peak_step": k,
        "peak_strain": float(peak.max_principal),
        "peak_strain_step": int(peak.step),
        "peak_strain_travel_mm": float(travel[peak.step]),
        "peak_strain_position_mm": [float(c) for c in peak.position],
        "peak_von_mises_MPa": float(peak.von_mises),
        "strain_at_peak_force_step": float(np.max(strain_k)),
        "max_displacement_at_peak_force_mm": float(np.max(np.linalg.norm(u_k, axis=1))),
        "steps_per_second": steps / float(np.median(times)),
        "first_call_seconds": first,
        "timed_seconds": times,
        "load_average": [list(load_before), list(load_after)],
        # The timed rollout (no coordinates kept) against the one drawn (coordinates kept).
        "keep_x_force_max_abs_diff_N": float(np.max(np.abs(np.asarray(res_t.insertion_force) - F))),
    }
    row["materials"], figure["materials"] = materials(model, scene, row)
    return row, figure


def materials(model, scene, row) -> tuple[dict, dict]:
    """The insertion force of each material of :data:`MATERIALS` on ``model`` (E, nu as
    parameters, the scene's friction and density), and a rebuilt model's where nu differs."""
    out, curves = {}, {}
    for name, m in MATERIALS.items():
        E, nu = m["youngs_modulus"], m["poissons_ratio"]
        res = jsnap.rollout(model, model.params.replace(E=E, nu=nu))
        F = np.asarray(res.insertion_force)
        k = int(np.argmax(F))
        entry = out[name] = {
            "peak_insertion_force_N": float(F[k]),
            "travel_at_peak_mm": float(np.asarray(res.travel)[k]),
            "status": res.status(),
        }
        curves[name] = (np.asarray(res.travel), F)
        if nu != row["poissons_ratio"]:
            rebuilt = jsnap.build(scene.replace({"material.youngs_modulus": E, "material.poissons_ratio": nu}))
            Fr = np.asarray(jsnap.rollout(rebuilt).insertion_force)
            entry["basis_check"] = {
                "rebuilt_orders": [int(o) for o in rebuilt.part.orders],
                "rebuilt_peak_insertion_force_N": float(Fr.max()),
                "peak_rel_diff": float(F[k] / Fr.max() - 1),
                "rms_diff_of_peak": float(np.sqrt(np.mean((F - Fr) ** 2)) / Fr.max()),
            }
        print(f"  {name}: {json.dumps(entry)}", flush=True)
    return out, curves


def machine() -> str:
    return f"{platform.machine()} {platform.system()}, {os.cpu_count()} CPU cores"


def plot_preset(preset: str, row: dict, fig_data: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import cm, colors
    from matplotlib.ticker import MaxNLocator
    from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

    nodes, u = fig_data["nodes"], fig_data["u"]
    faces, owner = TetMesh(nodes, fig_data["cells4"], np.zeros(0, np.int64)).boundary_faces(owners=True)
    scale = magnification(u, nodes)
    xyz = nodes + scale * u
    verts = xyz[faces]
    pct = 100 * fig_data["strain"][owner]
    norm = colors.Normalize(vmin=0.0, vmax=max(float(pct.max()), 1e-9))
    cmap = plt.get_cmap("viridis")

    fig = plt.figure(figsize=(13, 6))
    # Fixed places (tight_layout does not know a 3D axes' labels): the part, its colorbar, the curve.
    ax = fig.add_axes((0.0, 0.13, 0.45, 0.74), projection="3d")
    ax.add_collection3d(
        Poly3DCollection(verts, facecolors=cmap(norm(pct)), edgecolors=(0, 0, 0, 0.15), linewidths=0.1)
    )
    pts = [xyz]
    if fig_data["rigid_edges"] is not None:
        edges = fig_data["rigid_edges"]
        ax.add_collection3d(Line3DCollection(edges, colors="tab:red", linewidths=1.2))
        pts.append(np.concatenate(edges))
    pts = np.concatenate(pts)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    ax.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), zlim=(lo[2], hi[2]))
    ax.set_box_aspect(np.maximum(hi - lo, 1e-6))
    ax.view_init(elev=18, azim=-62)
    ax.set(xlabel="x (mm)", ylabel="y (mm)", zlabel="z (mm)")
    ax.tick_params(labelsize=7)
    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_locator(MaxNLocator(4))
    sm = cm.ScalarMappable(norm=norm, cmap=cmap)
    cax = fig.add_axes((0.45, 0.22, 0.012, 0.5))
    fig.colorbar(sm, cax=cax, label="largest principal strain (%)")
    ax.set_title(
        f"deformed at the peak force (step {fig_data['k'] + 1}, travel {row['travel_at_peak_mm']:.2f} mm), "
        f"displacement ×{scale:g}\nfaces coloured by their element's largest principal strain; "
        "rigid part's outline in red",
        fontsize=9,
    )

    ax2 = fig.add_axes((0.58, 0.1, 0.4, 0.76))
    ax2.plot(fig_data["travel"], fig_data["F"], color="tab:blue")
    ax2.plot(row["travel_at_peak_mm"], row["peak_insertion_force_N"], "o", color="tab:red")
    ax2.annotate(
        f"peak {row['peak_insertion_force_N']:.2f} N at {row['travel_at_peak_mm']:.2f} mm",
        (row["travel_at_peak_mm"], row["peak_insertion_force_N"]),
        xytext=(8, -4),
        textcoords="offset points",
        fontsize=9,
    )
    ax2.axhline(0, color="k", lw=0.5)
    ax2.set(xlabel="travel (mm)", ylabel="insertion force (N)", title="insertion force")
    ax2.grid(alpha=0.3)
    orders = " + ".join(map(str, row["orders"]))
    text = (
        f"{row['method']} model: {orders} = {row['coordinates']} coordinates\n"
        f"full model: {row['full_dof']} dof ({row['element']})\n"
        f"{row['steps_per_second']:.0f} steps/s ({row['dtype']}, "
        f"{row['steps']} steps of {1e3 * row['dt_s']:g} ms)\n"
        f"peak strain {100 * row['peak_strain']:.2f} % (whole run)\n"
        f"E {row['youngs_modulus_MPa']:g} MPa, ν {row['poissons_ratio']:g}, μ {row['friction']:g}"
    )
    ax2.text(
        0.02, 0.03, text, transform=ax2.transAxes, ha="left", va="bottom", fontsize=8.5,
        bbox={"boxstyle": "round", "fc": "white", "ec": "0.7"},
    )  # fmt: skip
    load = row["load_average"][1][0]
    fig.suptitle(
        f"{preset} ({row['scene']}): {orders} of {row['full_dof']} dof, {row['steps_per_second']:.0f} steps/s "
        f"({machine()}, load average {load:.1f})",
        fontsize=11,
    )
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _sector(row: dict) -> str:
    copies = row.get("ring_copies")
    return "" if copies is None else f" (a 1/{copies:g} sector of the ring)"


def plot_materials(rows: dict, curves: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    styles = ["-", "--", ":", "-."]
    how = ", ".join(sorted({f"{r['method']} model, {r['dtype']}" for r in rows.values()}))
    fig, ax = plt.subplots(figsize=(13, 5.2))
    for i, (preset, by_material) in enumerate(curves.items()):
        color = f"C{i}"
        for j, (name, (travel, F)) in enumerate(by_material.items()):
            m = MATERIALS[name]
            ax.plot(
                travel,
                F,
                styles[j % len(styles)],
                color=color,
                lw=1.3,
                label=f"{preset}{_sector(rows[preset])}, {name} (E {m['youngs_modulus']:g} MPa, "
                f"ν {m['poissons_ratio']:g}): "
                f"peak {rows[preset]['materials'][name]['peak_insertion_force_N']:.2f} N",
            )
    ax.axhline(0, color="k", lw=0.5)
    ax.set(
        xlabel="travel (mm)",
        ylabel="insertion force (N)",
        title=f"Insertion force of every preset for {len(MATERIALS)} materials ({how}; each scene's friction)",
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # beside the curves, not on them
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    presets = presets_option(ap, PRESETS, argv)
    IMG.mkdir(parents=True, exist_ok=True)
    OUT.mkdir(exist_ok=True)
    path = OUT / "gallery.json"
    partial = set(presets) != set(PRESETS)
    # The materials chart needs every preset's curves, so a partial rerun keeps it as it was.
    before = previous_result(path, presets, PRESETS)
    rows = kept_rows(before, presets, PRESETS)
    curves = {}
    for preset in presets:
        print(f"{preset} ...", flush=True)
        row, fig_data = run_preset(preset)
        curves[preset] = fig_data["materials"]
        figure = IMG / f"gallery_{preset}.png"
        plot_preset(preset, row, fig_data, figure)
        rows[preset] = row = stamped(row | {"figure": str(figure.relative_to(ROOT.parent))})
        print(f"{preset}: {json.dumps({k: v for k, v in row.items() if k != 'materials'})}", flush=True)
    rows = {p: rows[p] for p in PRESETS if p in rows}
    if partial:
        figure_date = before.get("materials_figure_date", before.get("date"))
        print(f"materials chart kept (drawn {figure_date}): it is redrawn by a run of every preset", flush=True)
    else:
        plot_materials(rows, curves, IMG / "gallery_materials.png")
        figure_date = time.strftime("%Y-%m-%d %H:%M")
    out = {
        "benchmark": "gallery",
        "presets": rows,
        "materials": MATERIALS,
        "materials_source": MATERIALS_SOURCE,
        "materials_figure": str((IMG / "gallery_materials.png").relative_to(ROOT.parent)),
        "materials_figure_date": figure_date,
        "machine": machine(),
        "cpus": os.cpu_count(),
        "load_average_after": list(os.getloadavg()),
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "code": code_version(),
    }
    path.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
