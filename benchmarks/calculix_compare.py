"""jsnap's full linear model against CalculiX on the default hook (refs: jsnap/data/calculix-cantilever).

    python benchmarks/calculix_compare.py [--quick]

Runs the default scene with the full P2 model in float64: frictionless (against CalculiX's
linear-geometry, frictionless curve: the like-for-like reference) and with mu = 0.3 (CalculiX
has it only with nonlinear geometry: context, not a like-for-like check); the frictionless case
also with a nearly sharp plug (fillet 0.02 mm; CalculiX's plug has sharp corners), and with
every other method of the frictionless case: segmented and reduced sockets, P1 elements, the
neural and the exact-mesh plug SDF; and the frictionless linear model against CalculiX's
*nonlinear*-geometry frictionless curve (the linear model's own geometric error). Reports the
peak (raw and 5-point average, as the reference README does), the travel at the peak and the
RMS difference of the insertion and lateral force over the reference's travel range.

Writes benchmarks/results/calculix_compare.{json,png}.
"""

from __future__ import annotations

import argparse
import json
import platform
from pathlib import Path

import numpy as np
from _common import FULL, load_scene

import jsnap

# XLA's small-loop option, before the first JAX computation (the committed results had it).
jsnap.configure_xla_cpu()

OUT = Path(__file__).parent / "results"
REF = Path(jsnap.__file__).parent / "data" / "calculix-cantilever"

LIN, NLGEOM_MU03 = "snap_mu0_lin_curve.csv", "snap_mu03_nlgeom_curve.csv"
NLGEOM_MU0 = "snap_mu0_nlgeom_curve.csv"
MU0 = {"contact.friction": 0.0}
RUNS = [
    ("jsnap full P2, mu 0", MU0, LIN),
    ("jsnap full P2, mu 0, fillet 0.02", {**MU0, "plug.fillet": 0.02}, LIN),
    ("jsnap full P2, mu 0.3", {}, NLGEOM_MU03),
    ("jsnap segmented P2, mu 0", {**MU0, "solver.method": "segmented"}, LIN),
    ("jsnap reduced P2, mu 0", {**MU0, "solver.method": "reduced"}, LIN),
    ("jsnap full P1, mu 0", {**MU0, "solver.element": "P1"}, LIN),
    ("jsnap full P2, mu 0, neural SDF", {**MU0, "solver.sdf": "neural"}, LIN),
    ("jsnap full P2, mu 0, mesh SDF", {**MU0, "solver.sdf": "mesh"}, LIN),
    ("jsnap full P2, mu 0 (linear) vs CalculiX nonlinear geometry", MU0, NLGEOM_MU0),
]


def load_ref(name):
    d = np.genfromtxt(REF / name, delimiter=",", skip_header=1)
    return d[:, 1], d[:, 2], d[:, 3]  # travel mm, insertion force N, lateral force N


def avg5(F):
    return np.convolve(F, np.ones(5) / 5, mode="same")


_CURVES: dict = {}  # simulated curves by scene: a run compared with two references is simulated once


def compare(label, changes, ref_name, mesh):
    # The full model unless a run names another (the shipped scene's default is now "reduced").
    scene = load_scene({"solver.mesh_size": mesh, **FULL, **changes})
    key = json.dumps(scene.to_dict(), sort_keys=True, default=str)
    if key not in _CURVES:
        res = jsnap.rollout(jsnap.build(scene), dtype="float64")
        _CURVES[key] = {k: np.asarray(getattr(res, a)).tolist() for k, a in CURVE.items()}
    curve = _CURVES[key]
    return {"run": label, "reference": ref_name, "changes": changes, **metrics(curve, ref_name), "curve": curve}


CURVE = {"travel": "travel", "insertion": "insertion_force", "lateral": "lateral_force"}


def metrics(curve, ref_name):
    """Peak (raw, 5-point average), travel at peak, and RMS differences: over the reference's
    whole travel range, and over the rise (up to 0.05 mm before the reference's peak), where a
    small shift of the steep post-peak drop does not dominate."""
    tr, F, lat = (np.asarray(curve[k]) for k in ("travel", "insertion", "lateral"))
    rt, rF, rlat = load_ref(ref_name)
    Fi, lati = np.interp(rt, tr, F), np.interp(rt, tr, lat)
    k, kr = int(F.argmax()), int(rF.argmax())
    rise = rt <= rt[kr] - 0.05
    return {
        "peak_N": float(F[k]),
        "peak_avg5_N": float(avg5(F).max()),
        "travel_at_peak_mm": float(tr[k]),
        "lateral_at_peak_N": float(lat[k]),
        "ref_peak_N": float(rF[kr]),
        "ref_peak_avg5_N": float(avg5(rF).max()),
        "ref_travel_at_peak_mm": float(rt[kr]),
        "ref_lateral_at_peak_N": float(rlat[kr]),
        "peak_ratio": float(F[k] / rF[kr]),
        "rms_insertion_N": float(np.sqrt(np.mean((Fi - rF) ** 2))),
        "rms_lateral_N": float(np.sqrt(np.mean((lati - rlat) ** 2))),
        "rms_insertion_rise_N": float(np.sqrt(np.mean((Fi - rF)[rise] ** 2))),
        "rms_lateral_rise_N": float(np.sqrt(np.mean((lati - rlat)[rise] ** 2))),
    }


def plot(rows, path, machine):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(13, 4.8), sharex=True)
    refs = sorted({r["reference"] for r in rows})
    for name, ls in zip(refs, ["k--", "k:", "k-."], strict=False):
        rt, rF, rlat = load_ref(name)
        ax[0].plot(rt, rF, ls, lw=1.2, label=f"CalculiX {name.replace('_curve.csv', '')}")
        ax[1].plot(rt, rlat, ls, lw=1.2)
    for r in rows:
        c = r["curve"]
        ax[0].plot(c["travel"], c["insertion"], lw=1.2, label=r["run"])
        ax[1].plot(c["travel"], c["lateral"], lw=1.2)
    ax[0].set_ylabel("insertion force on the plug, -z (N)")
    ax[1].set_ylabel("lateral force on the plug, x (N)")
    for a in ax:
        a.set_xlabel("plug travel (mm)")
        a.grid(alpha=0.3)
        a.set_xlim(0, 2.1)
    ax[0].legend(fontsize=8)
    fig.suptitle(f"Default hook: jsnap (linear FEM) against CalculiX ({machine})", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="coarse mesh (1.2 mm), frictionless only")
    ap.add_argument("--replot", action="store_true", help="recompute metrics and plot from the saved JSON")
    a = ap.parse_args(argv)
    OUT.mkdir(exist_ok=True)
    stem = "calculix_compare_quick" if a.quick else "calculix_compare"
    machine = f"{platform.machine()}, {platform.processor() or platform.system()}"
    mesh = 1.2 if a.quick else 0.8
    if a.replot:
        saved = json.loads((OUT / f"{stem}.json").read_text())
        machine, mesh = saved["machine"], saved["mesh_size_mm"]
        rows = [{**r, **metrics(r["curve"], r["reference"])} for r in saved["rows"]]
    else:
        rows = [compare(*r, mesh) for r in (RUNS[:1] if a.quick else RUNS)]
    for r in rows:
        print({k: v for k, v in r.items() if k != "curve"}, flush=True)
    (OUT / f"{stem}.json").write_text(json.dumps({"machine": machine, "mesh_size_mm": mesh, "rows": rows}))
    plot(rows, OUT / f"{stem}.png", machine)


if __name__ == "__main__":
    main()
