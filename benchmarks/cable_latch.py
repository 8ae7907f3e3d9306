"""The cable latch preset (jsnap/scenes/cable_latch.toml): its reduced model against its full
model, both against CalculiX and the design guide, and their speed side by side.

    python benchmarks/cable_latch.py

1. Accuracy, frictionless and at mu = 0.3: the full model (float64, its contact solved by APGD
   to the tolerance with up to 5000 iterations) and the shipped reduced model (float32): peak
   insertion force, travel at the peak, RMSE of the insertion force in % of the full model's
   peak over the whole motion and over the rise; both against CalculiX's linear-geometry curves
   of the same latch (jsnap/data/calculix-cable_latch/), over the travel CalculiX covers.
2. The design guide's cantilever loaded at the catch (mating force W = P (mu + tan a) /
   (1 - mu tan a), P = 3 E I y / l^3 with l from the root to the land's top; root strain) against
   the full model's peak force and the arm's peak strain, the gap split into measured factors:
   P against the lateral force while the lip's face holds the catch in by the whole undercut
   (on the land), for the latch with its root clamped (every node at z >= length fixed: beam
   theory against 3D FEM and the catch's own compliance: f_3d_beam) and as shipped (the bridge
   and the plug body give way: f_root); and the peak over that lateral force against
   (mu + tan a) / (1 - mu tan a) (f_ramp: the ramp meets the lip turned by the arm's slope,
   shallower, and the ramp's axial force acts off the arm's axis).
3. Speed: steps/s of the compiled rollout (median of the timed calls) of the shipped reduced
   model and of the full model (float32 and float64), in one process, with the load average.

Writes benchmarks/results/cable_latch.{json,png}.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from _common import calculix_row, curve_stats, load_scene, plot_curves, plot_speed, speed, write_result

import jsnap
from jsnap._apps.simulate import arm_box, arm_elements, design_guide_force, design_guide_strain
from jsnap._build.strain import scan
from jsnap._geometry.scene import default_scene_path

jsnap.configure_xla_cpu()

OUT = Path(__file__).parent / "results"
SCENE = default_scene_path().parent / "cable_latch.toml"
DATA = Path(jsnap.__file__).parent / "data" / "calculix-cable_latch"
# Friction: the CalculiX curve of each mu the accuracy part runs.
REFS = {0.0: DATA / "latch_mu0_lin_curve.csv", 0.3: DATA / "latch_mu03_lin_curve.csv"}
# The full model's contact: APGD to the scene's tolerance, with room to get there.
FULL_CONTACT = {"contact.solver": "apgd", "contact.iterations": 5000}


def arm_peak_strain(model, res, connector) -> float:
    """The largest principal strain over the run in the latch's arm (below its root, without
    the catch), dimensionless."""
    nodes, cells = np.asarray(model.mesh.nodes), np.asarray(model.mesh.cells)
    arm = arm_elements(nodes, cells, arm_box(connector))
    x = np.asarray(res.x)
    t = np.asarray(res.t, np.float64)
    peaks, _ = scan(model, x, t, float(model.params.E), float(model.params.nu), regions={"arm": arm})
    return float(peaks["arm"].max_principal)


def clamped_root(scene):
    """``jsnap.build(scene)`` of the latch with its root clamped: every node at z >= length fixed
    (the bridge and the body above the root) instead of the body's back face."""
    from jsnap._build import model as M
    from jsnap._geometry.mesh import TetMesh
    from jsnap._geometry.presets import Preset

    generate, L = M.generate, scene["connector"]["length"]

    def clamped(*args, **kw):
        p = generate(*args, **kw)
        root = np.flatnonzero(p.mesh.points[:, 2] >= L - 1e-9)
        return Preset(TetMesh(points=p.mesh.points, cells=p.mesh.cells, base_nodes=root), p.plug, p.stroke)

    M.generate = clamped
    try:
        return jsnap.build(scene)
    finally:
        M.generate = generate


def land_force(res, scene) -> float:
    """The lateral force on the lip while the catch's land is held in by the lip's flat inner
    face (every contact on it, away from its rounded edges), N: the median over those steps."""
    c, p = scene["connector"], scene["plug"]
    active, points = np.asarray(res.contact_active), np.asarray(res.contact_point)
    forces, lip_z = np.asarray(res.contact_force), np.asarray(res.plug)[:, 2]
    fx = []
    for k in range(active.shape[0]):
        a = active[k]
        z, x = points[k, a, 2], points[k, a, 0]
        on_face = (np.abs(z - lip_z[k]) < 0.5 * p["height"] - p["fillet"] - 0.02) & (
            np.abs(x - c["thickness"]) < 0.03
        )
        if a.any() and on_face.all():
            fx.append(-float(forces[k, a, 0].sum()))
    return float(np.median(fx)) if fx else float("nan")


def guide_gap(scene, full_model, full) -> dict:
    """The design guide's force against the full model's, split into measured factors (module
    docstring, item 2)."""
    c, m = scene["connector"], scene["material"]
    mu, a = scene["contact"]["friction"], np.radians(c["lead_angle"])
    g = (mu + np.tan(a)) / (1 - mu * np.tan(a))
    W = design_guide_force(scene)
    P = W / g
    clamped = jsnap.rollout(
        clamped_root(load_scene({"solver.method": "full", **FULL_CONTACT}, scene)), dtype="float64"
    )
    P_clamped, P_shipped = land_force(clamped, scene), land_force(full, scene)
    W_shipped = float(np.asarray(full.insertion_force).max())
    return {
        "guide_mating_force_N": W,
        "guide_lateral_force_N": P,
        "clamped_root_lateral_on_land_N": P_clamped,
        "shipped_lateral_on_land_N": P_shipped,
        "clamped_root_peak_N": float(np.asarray(clamped.insertion_force).max()),
        "shipped_peak_N": W_shipped,
        "f_3d_beam": P_clamped / P,
        "f_root": P_shipped / P_clamped,
        "f_ramp": W_shipped / P_shipped / g,
        "youngs_modulus_MPa": m["youngs_modulus"],
    }


def main(argv=None) -> int:
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args(argv)
    base = jsnap.load_scene(SCENE)
    out = {"scene": str(SCENE.name), "mesh_size": base["solver"]["mesh_size"], "accuracy": {}}
    curves = {}
    for mu in (0.0, 0.3):
        scene = base.replace({"contact.friction": mu})
        full_model = jsnap.build(load_scene({"solver.method": "full", **FULL_CONTACT}, scene))
        full = jsnap.rollout(full_model, dtype="float64", keep_x=True)
        red_model = jsnap.build(scene)
        red = jsnap.rollout(red_model)
        travel = np.asarray(full.travel)
        Ff, Fr = np.asarray(full.insertion_force), np.asarray(red.insertion_force)
        curves[mu] = (travel, Ff, Fr)
        acc = out["accuracy"][f"mu {mu:g}"] = {
            "full_dof": full_model.full_dof,
            "reduced_orders": list(red_model.part.orders),
            "full_float64": {**curve_stats(Ff, travel, Ff), "ok": bool(full.ok)},
            "reduced_float32": {**curve_stats(Fr, travel, Ff), "ok": bool(red.ok)},
            "design_guide": {
                **guide_gap(scene, full_model, full),
                "root_strain": design_guide_strain(scene),
                "full_arm_peak_strain": arm_peak_strain(full_model, full, scene["connector"]),
            },
            "curves": {"travel_mm": travel.tolist(), "full_N": Ff.tolist(), "reduced_N": Fr.tolist()},
        }
        if REFS[mu].is_file():
            acc["calculix"] = calculix_row(REFS[mu], travel, {"full_float64": Ff, "reduced_float32": Fr})
        print(f"mu {mu:g}:", json.dumps({k: v for k, v in acc.items() if k != "curves"}), flush=True)
    out["speed"] = speed(base, 5)
    write_result(out, OUT / "cable_latch.json")
    plot(out, curves)
    return 0


def plot(out, curves):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(13, 4.8), gridspec_kw={"width_ratios": [2, 1]})
    colours = plot_curves(ax[0], curves, REFS)
    for mu, colour in colours.items():
        guide = out["accuracy"][f"mu {mu:g}"]["design_guide"]["guide_mating_force_N"]
        ax[0].axhline(guide, color=colour, ls=":", lw=0.8, label=f"design guide, mu {mu:g}")
    ax[0].axhline(0, color="0.6", lw=0.5)
    ax[0].set(
        xlabel="travel of the lip (mm)", ylabel="insertion force (N)", title="cable latch: insertion force"
    )
    ax[0].legend(fontsize=7)
    plot_speed(ax[1], out["speed"])
    fig.tight_layout()
    fig.savefig(OUT / "cable_latch.png", dpi=110)


if __name__ == "__main__":
    raise SystemExit(main())
