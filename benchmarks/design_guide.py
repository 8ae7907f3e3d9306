"""Peak insertion force of the full model against the snap-fit design guide, with the gap
decomposed into measured factors.

    python benchmarks/design_guide.py [--quick]

For each scene the full linear model (P2, float64) is run; at the peak the contact forces are
taken from the rollout and loaded statically on the same FEM model, split into their lateral (x)
and axial (z) parts. With W_guide = P (mu + tan a)/(1 - mu tan a) and the simulated peak W_sim,

    W_sim / W_guide = f_beam * f_3d * f_axial * f_angle        (exact up to the y-forces)

- f_beam = P_EB / P: Euler-Bernoulli on the actual arm and hook profile, loaded at the contact's
  height and deflected as much as the simulation deflects it there, against the guide's P (tip
  load at z = L, deflection = undercut);
- f_3d = P_FEM / P_EB: the 3D FEM lateral force for that deflection against Euler-Bernoulli
  (shear, the fully clamped root, Poisson stiffening);
- f_axial = F_x / P_FEM: the ramp force's axial component bends the arm back (its moment about
  the arm's axis opposes the lateral force's), so more lateral force is needed;
- f_angle = g(a_eff) / g(a): the hook has rotated at the peak, so the ramp meets the plug at
  a_eff instead of a (a_eff from the simulated F_z / F_x and mu).

Writes benchmarks/results/design_guide.{json,md,png}.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import time
from pathlib import Path

import numpy as np
import scipy.sparse.linalg as spla
from _common import FULL, load_scene

import jsnap
from jsnap._apps.simulate import design_guide_force
from jsnap._build.fem import assemble
from jsnap._geometry.cantilever import mesh_cantilever
from jsnap._geometry.scene import connector_geometry

# XLA's small-loop option, before the first JAX computation (the committed results had it).
jsnap.configure_xla_cpu()

OUT = Path(__file__).parent / "results"

SCENES = [
    ("default hook, mu 0", {"contact.friction": 0.0}),
    ("default hook, mu 0.3", {}),
    ("tapered to h/2, mu 0.3", {"connector.tip_thickness": 0.6}),
    ("shallow undercut 0.4 mm, mu 0.3", {"connector.undercut": 0.4}),
    ("lead angle 45 deg, mu 0.2", {"connector.lead_angle": 45.0, "contact.friction": 0.2}),
    ("thick arm h 1.6 mm, mu 0.3", {"connector.thickness": 1.6, "connector.tip_thickness": 1.6}),
]


def _g(alpha_rad, mu):
    t = math.tan(alpha_rad)
    return (mu + t) / (1 - mu * t)


def _eb_compliance(geom, z_c, E):
    """Lateral compliance (mm/N) at height z_c of the arm + hook profile, Euler-Bernoulli."""
    s = np.linspace(0.0, z_c, 4001)
    h = np.where(
        s <= geom.length,
        geom.thickness + (geom.h_tip - geom.thickness) * s / geom.length,
        np.where(
            s <= geom.length + geom.flat,
            geom.h_tip + geom.undercut,
            geom.h_tip + geom.undercut * (geom.z_top - s) / (geom.z_top - geom.length - geom.flat),
        ),
    )
    EI = E * geom.width * h**3 / 12
    return float(np.trapezoid((z_c - s) ** 2 / EI, s))


def analyse(name, changes, mesh_size):
    scene = load_scene({"solver.mesh_size": mesh_size, **FULL, **changes})
    model = jsnap.build(scene)
    t0 = time.perf_counter()
    res = jsnap.rollout(model, dtype="float64", keep_x=True)
    F = np.asarray(res.insertion_force)
    run_s = time.perf_counter() - t0
    k = int(F.argmax())
    act = np.asarray(res.contact_active[k])
    idx = np.asarray(res.contact_index[k])[act]
    G = np.asarray(res.contact_force[k])[act]  # (c, 3) on the hook, N
    part = model.part  # the full model: free-node indices and shape functions of the points
    nodes = np.asarray(part.sample_nodes)[idx]
    w = np.asarray(part.sample_weights)[idx]
    n = model.n_dof

    def load(g):  # J' g
        f = np.zeros(n)
        for c in range(len(idx)):
            for j in range(nodes.shape[1]):
                f[3 * nodes[c, j] : 3 * nodes[c, j] + 3] += w[c, j] * g[c]
        return f

    def deflection(u):  # lateral displacement at the contact, weighted by the lateral force
        ux = np.einsum("ck,ck->c", w, u.reshape(-1, 3)[nodes][..., 0])
        return float((ux * G[:, 0]).sum() / G[:, 0].sum())

    p = scene["material"]
    # The model holds no assembly: the same one, rebuilt from the scene's mesh.
    geom = connector_geometry(scene)
    asm = assemble(mesh_cantilever(geom, scene["solver"]["mesh_size"]), scene["solver"]["element"])
    free = asm.free
    assert free.size == n and np.array_equal(free, np.asarray(model.mesh.free))
    K = asm.stiffness(p["youngs_modulus"], p["poissons_ratio"])[free][:, free].tocsc()
    solve = spla.factorized(K)
    d_sim = deflection(np.asarray(res.x[k]))
    gx, gz = G * [1, 0, 0], G * [0, 0, 1]
    d_lat, d_ax = deflection(solve(load(gx))), deflection(solve(load(gz)))
    d_static = deflection(solve(load(G)))

    rest = np.asarray(model.samples.rest)[idx]
    z_c = float((rest[:, 2] * np.abs(G).sum(1)).sum() / np.abs(G).sum())
    Fx, Fz = -G[:, 0].sum(), -G[:, 2].sum()  # on the plug's side: both positive
    mu = scene["contact"]["friction"]
    alpha = math.radians(scene["connector"]["lead_angle"])
    r = Fz / Fx
    a_eff = math.atan((r - mu) / (1 + mu * r))
    W_guide = design_guide_force(scene)
    P_guide = W_guide / _g(alpha, mu)
    P_eb = abs(d_sim) / _eb_compliance(geom, z_c, p["youngs_modulus"])
    P_fem = Fx * d_sim / d_lat
    row = {
        "scene": name,
        "changes": changes,
        "free_dof": n,
        "friction": mu,
        "guide_P_N": P_guide,
        "guide_W_N": W_guide,
        "sim_peak_N": float(F[k]),
        "travel_at_peak_mm": float(res.travel[k]),
        "ratio": float(F[k]) / W_guide,
        "lateral_at_peak_N": float(Fx),
        "contact_height_mm": z_c,
        "deflection_at_contact_mm": -d_sim,
        "undercut_mm": geom.undercut,
        "f_beam": P_eb / P_guide,
        "f_3d": P_fem / P_eb,
        "f_axial": d_lat / (d_lat + d_ax),
        "f_angle": _g(a_eff, mu) / _g(alpha, mu),
        "hook_rotation_deg": math.degrees(a_eff - alpha),
        "quasi_static_check": d_static / d_sim,
        "rollout_seconds": run_s,
    }
    row["product"] = row["f_beam"] * row["f_3d"] * row["f_axial"] * row["f_angle"]
    return row


def _markdown(rows):
    head = (
        "| scene | guide W (N) | jsnap peak (N) | ratio | f_beam | f_3d | f_axial | f_angle (rotation) "
        "| product |\n|---|---|---|---|---|---|---|---|---|\n"
    )
    body = "".join(
        f"| {r['scene']} | {r['guide_W_N']:.2f} | {r['sim_peak_N']:.2f} | {r['ratio']:.2f} "
        f"| {r['f_beam']:.3f} | {r['f_3d']:.3f} | {r['f_axial']:.3f} "
        f"| {r['f_angle']:.3f} ({r['hook_rotation_deg']:.1f}°) | {r['product']:.2f} |\n"
        for r in rows
    )
    return head + body


def _plot(rows, path, machine):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = ["f_beam", "f_3d", "f_axial", "f_angle"]
    fig, ax = plt.subplots(figsize=(11, 4.5))
    xs = np.arange(len(rows))
    width = 0.15
    for i, key in enumerate(keys):
        ax.bar(xs + (i - 2) * width, [r[key] for r in rows], width, label=key)
    ax.bar(xs + 2 * width, [r["ratio"] for r in rows], width, color="k", label="jsnap peak / guide W")
    ax.axhline(1, color="0.5", lw=0.8)
    ax.set_xticks(xs, [r["scene"] for r in rows], rotation=15, ha="right", fontsize=8)
    ax.set_ylabel("factor (dimensionless)")
    ax.set_title(f"Peak insertion force against the design guide, factors measured ({machine})")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="coarse mesh, two scenes")
    a = ap.parse_args(argv)
    mesh = 1.2 if a.quick else 0.8
    scenes = SCENES[:2] if a.quick else SCENES
    rows = []
    for name, changes in scenes:
        rows.append(analyse(name, changes, mesh))
        print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in rows[-1].items()}, flush=True)
    OUT.mkdir(exist_ok=True)
    machine = f"{platform.machine()}, {platform.processor() or platform.system()}"
    stem = "design_guide_quick" if a.quick else "design_guide"
    (OUT / f"{stem}.json").write_text(
        json.dumps({"machine": machine, "mesh_size_mm": mesh, "rows": rows}, indent=2)
    )
    (OUT / f"{stem}.md").write_text(_markdown(rows))
    _plot(rows, OUT / f"{stem}.png", machine)
    print(_markdown(rows))


if __name__ == "__main__":
    main()
