"""The annular snap's force against the density of its contact candidates.

    python benchmarks/annular_spacing.py

The lip's lead ramp is 0.24 mm long and its land 0.1 mm: at the scene's candidate spacing
along the section outline (``contact.spacing``, 0.02 mm) a dozen points lie on the ramp, and
the contact line between the bead's rounded edge and the ramp steps from one to the next as
the bead comes down. So the insertion force is a sawtooth, and CalculiX's curve of the same
snap (node-to-surface contact on its 0.01 mm mesh at the lip) is one too. This sweeps the
spacing, frictionless, with the rest of the shipped scene kept:

- the full model (float64): candidate points, raw peak and its travel, the peak of the 0.05 mm
  moving average, and that average at 0.15, 0.20 and 0.25 mm of travel over CalculiX's
  (averaged the same way on the same travels), and the flags the rollout raised;
- the shipped reduced model (float32) at the same spacing: its peak over the full model's and
  its RMSE over the rise in % of the full model's peak;
- the full model again with ``contact.hand_over = "on"`` (the preset's turned sampling keeps
  every face point's contact): its peak and flags. Where the flags come from: a face point of
  the tube's top beside the bead's rounded edge, which would hold it across a sideways gap
  along the top's normal, and the stabilisation's push-out (``stabilisation_0`` below: the
  same with ``contact.stabilisation = 0``).

Writes benchmarks/results/annular_spacing.{json,png}.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from _common import curve_stats, load_scene, moving_average, run_status, write_result
from annular import REFS, SCENE

import jsnap
from jsnap._apps.simulate import ring_copies

jsnap.configure_xla_cpu()

OUT = Path(__file__).parent / "results"
SPACINGS = (0.04, 0.03, 0.025, 0.02, 0.015, 0.01)
TRAVELS = (0.15, 0.20, 0.25)
WINDOW = 5  # steps: 0.05 mm at the scene's 10 mm/s and 1 ms


def full_model_scene(scene):
    """``scene``'s full model in float64."""
    return load_scene({"solver.method": "full", "solver.dtype": "float64"}, scene)


def main() -> int:
    base = jsnap.load_scene(SCENE).replace({"contact.friction": 0.0})
    shipped = base["contact"]["spacing"]
    copies = ring_copies(base)
    d = np.genfromtxt(REFS[0.0][0], delimiter=",", names=True)
    rows, curves = [], {}
    for spacing in SPACINGS:
        scene = load_scene({"contact.spacing": spacing}, base)
        full_model = jsnap.build(full_model_scene(scene))
        full = jsnap.rollout(full_model)
        red = jsnap.rollout(jsnap.build(scene))
        travel = np.asarray(full.travel)
        Ff = copies * np.asarray(full.insertion_force, np.float64)
        Fr = copies * np.asarray(red.insertion_force, np.float64)
        ref = moving_average(np.interp(travel, d["plug_travel_mm"], d["insertion_force_N"]), WINDOW)
        avg = moving_average(Ff, WINDOW)
        stats = curve_stats(Fr, travel, Ff)
        row = {
            "spacing_mm": spacing,
            "contact_points": int(full_model.n_samples),
            "full_float64": {
                "peak_N": float(Ff.max()),
                "travel_at_peak_mm": float(travel[np.argmax(Ff)]),
                "averaged_peak_N": float(avg.max()),
                "averaged_over_calculix": [
                    float(np.interp(t, travel, avg) / np.interp(t, travel, ref)) for t in TRAVELS
                ],
                "flags": run_status(full),
            },
            "reduced_float32": {
                "peak_over_full": stats["peak_N"] / float(Ff.max()),
                "rmse_rise_of_full_peak": stats["rmse_rise_of_full_peak"],
                "flags": run_status(red),
            },
        }
        for key, changes in (
            ("hand_over_on", {"contact.hand_over": "on"}),
            ("stabilisation_0", {"contact.stabilisation": 0.0}),
        ):
            res = jsnap.rollout(jsnap.build(load_scene(changes, full_model_scene(scene))))
            F = copies * np.asarray(res.insertion_force, np.float64)
            row[key] = {
                "peak_N": float(F.max()),
                "least_before_peak_N": float(F[: int(np.argmax(F)) + 1].min()),
                "flags": run_status(res),
            }
        row["full_float64"]["least_before_peak_N"] = float(Ff[: int(np.argmax(Ff)) + 1].min())
        rows.append(row)
        curves[spacing] = (travel, Ff)
        print(row, flush=True)
    out = {
        "scene": SCENE.name,
        "friction": 0.0,
        "shipped_spacing_mm": shipped,
        "calculix": REFS[0.0][0].name,
        "calculix_averaged_peak_N": float(ref.max()),
        "travels_mm": list(TRAVELS),
        "window_steps": WINDOW,
        "rows": rows,
    }
    write_result(out, OUT / "annular_spacing.json")
    plot(out, curves, d)
    return 0


def plot(out, curves, d):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(12, 4.5))
    ax[0].plot(d["plug_travel_mm"], d["insertion_force_N"], "k.", ms=3, label="CalculiX, 0.01 mm at the lip")
    for spacing, (travel, F) in curves.items():
        ax[0].plot(travel, F, lw=0.8, label=f"full model, spacing {spacing:g} mm")
    ax[0].set(
        xlabel="travel of the bead (mm)",
        ylabel="insertion force, whole ring (N)",
        title="annular snap, frictionless",
        xlim=(0.05, 0.4),
        ylim=(-50, 220),
    )
    s = [r["spacing_mm"] for r in out["rows"]]
    for k, t in enumerate(out["travels_mm"]):
        ratio = [r["full_float64"]["averaged_over_calculix"][k] for r in out["rows"]]
        ax[1].plot(s, ratio, "o-", label=f"{t:g} mm")
    peak = [r["full_float64"]["averaged_peak_N"] / out["calculix_averaged_peak_N"] for r in out["rows"]]
    ax[1].plot(s, peak, "ks--", label="averaged peak")
    flagged = [r["spacing_mm"] for r in out["rows"] if r["full_float64"]["flags"] != "ok"]
    ax[1].plot(flagged, [0.7] * len(flagged), "rx", label="rollout flagged (energy gained)")
    ax[1].axhspan(0.95, 1.05, color="0.9", label="within 5 %")
    ax[1].axvline(0.02, color="0.5", lw=0.6)
    ax[1].set(
        xlabel="contact.spacing (mm); the scene's 0.02",
        ylabel="jsnap / CalculiX, both averaged over 0.05 mm",
        title="the rise settles, the force near the peak does not",
    )
    for a in ax:
        a.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(OUT / "annular_spacing.png", dpi=110)


if __name__ == "__main__":
    raise SystemExit(main())
