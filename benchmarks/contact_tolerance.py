"""What the contact solve's stopping tolerance buys and costs on the light contact settings: step
time, iterations and the force's distance from a tightly solved rollout, over ``contact.tolerance``.

    python benchmarks/contact_tolerance.py

The 1344-dof reduced scene (P2 1.6 mm) with reduction_speed.py's light contact settings (lines
every 2.0 mm, 24 slots, SPG capped at 200 iterations), ``contact.tolerance`` from 1e-6 (the
scene default) to 1e-3. For each tolerance:

* float32 (the scene's dtype): time per step in a ``lax.scan`` rollout, the median of
  ``REPEATS`` rollouts in each of ``ROUNDS`` rounds that time every tolerance in turn (side by
  side on the same machine state; the median of the rounds' medians is reported), iterations per
  step, steps stopped at the cap, steps solved twice (predict-correct);
* float64: the same rollout's insertion force against the reduced model's own tightly solved
  rollout (float64, ADMM to 1e-10, ≤ 20000 iterations): RMSE and largest error, both relative to
  the reference's peak, and the step of the largest. Float64 keeps float32 round-off out of the
  comparison (it moves the step in which the snap falls, whatever the tolerance);
* the residual the 1e-6 rollout's capped solves end at: what the cap leaves of the tolerance.

Writes benchmarks/results/contact_tolerance.{json,png}.
"""

from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path

import jax
import numpy as np
from _common import FLOAT32, LIGHT, TIGHT_ADMM, code_version, load_scene

import jsnap

# XLA's small-loop option, before the first JAX computation (the committed timings have it).
jsnap.configure_xla_cpu()

OUT = Path(__file__).parent / "results"
SCENE = {"solver.mesh_size": 1.6, "solver.method": "reduced", **FLOAT32, **LIGHT, "contact.solver": "spg"}
TOLERANCES = (1e-6, 3e-6, 1e-5, 3e-5, 1e-4, 3e-4, 1e-3)
ROUNDS, REPEATS = 5, 7


def _model(changes):
    """The scene with ``changes``; TIGHT_ADMM's ADMM is an internal choice (``with_internal``)."""
    return jsnap.build(load_scene({**SCENE, **changes}))


def main():
    load = [os.getloadavg()]
    ref = np.asarray(jsnap.rollout(_model({**TIGHT_ADMM, "solver.dtype": "float64"})).insertion_force)
    peak = float(ref.max())
    rows, runs = [], []
    for tol in TOLERANCES:
        model = _model({"contact.tolerance": tol})
        prepared = jsnap.prepare(model)
        res = jsnap.rollout(model, prepared=prepared)  # compiles
        it = np.asarray(res.iterations)
        r64 = jsnap.rollout(_model({"contact.tolerance": tol, "solver.dtype": "float64"}))
        err = np.asarray(r64.insertion_force) - ref
        row = {
            "tolerance": tol,
            "iterations_mean": float(it.mean()),
            "capped": int((it >= model.contact.solver.max_iters).sum()),
            "second_solves": int(np.asarray(res.corrected).sum()),
            "peak_N": float(np.asarray(res.insertion_force).max()),
            "float64_iterations_mean": float(np.asarray(r64.iterations).mean()),
            "float64_rmse_rel_peak": float(np.sqrt(np.mean(err**2)) / peak),
            "float64_max_error_rel_peak": float(np.abs(err).max() / peak),
            "float64_max_error_step": int(np.abs(err).argmax()),
            "float64_peak_N": float(np.asarray(r64.insertion_force).max()),
        }
        if tol == TOLERANCES[0]:
            capped = it >= model.contact.solver.max_iters
            resid = np.asarray(res.residual)[capped]
            row["capped_residual"] = {"median": float(np.median(resid)), "max": float(resid.max())}
        rows.append(row)
        runs.append((model, prepared, []))
        print({k: v for k, v in row.items()}, flush=True)

    for _ in range(ROUNDS):  # every tolerance in turn, each round
        for model, prepared, medians in runs:
            times = []
            for _ in range(REPEATS):
                t0 = time.perf_counter()
                jax.block_until_ready(jsnap.rollout(model, prepared=prepared).energy)
                times.append(time.perf_counter() - t0)
            medians.append(float(np.median(times)))
    n = len(model.trajectory()) - 1
    for row, (_, _, medians) in zip(rows, runs, strict=True):
        row["scan_us_per_step"] = 1e6 * float(np.median(medians)) / n
        row["scan_us_per_step_rounds"] = [1e6 * t / n for t in medians]
        row["scan_steps_per_second"] = 1e6 / row["scan_us_per_step"]
        print(row["tolerance"], f"{row['scan_us_per_step']:.1f} us per step", flush=True)
    load.append(os.getloadavg())
    lo, hi = min(a[0] for a in load), max(a[0] for a in load)
    OUT.mkdir(exist_ok=True)
    (OUT / "contact_tolerance.json").write_text(
        json.dumps(
            {
                "machine": f"{platform.machine()}, {os.cpu_count()} CPU cores, {jax.devices()[0].platform}, "
                f"load average {lo:.1f}-{hi:.1f}",
                "shared_machine": True,
                "code": code_version(),
                "scene": SCENE,
                "reference": {**TIGHT_ADMM, "solver.dtype": "float64", "peak_N": peak},
                "rounds": ROUNDS,
                "repeats": REPEATS,
                "headline": {
                    f"{r['tolerance']:.0e}": {
                        "us_per_step": r["scan_us_per_step"],
                        "iterations": r["iterations_mean"],
                        "rmse_rel_peak": r["float64_rmse_rel_peak"],
                    }
                    for r in rows
                },
                "rows": rows,
            }
        )
    )

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tol = [r["tolerance"] for r in rows]
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4.5))
    a.semilogx(tol, [r["scan_us_per_step"] for r in rows], "o-", color="C0", label="µs per step (float32 scan)")
    a.axhline(100.0, color="0.5", lw=0.7)
    a.text(tol[0], 101.0, "10 kHz", fontsize=8)
    a.set_xlabel("contact.tolerance")
    a.set_ylabel("time per step (µs)")
    a2 = a.twinx()
    a2.semilogx(tol, [r["iterations_mean"] for r in rows], "s--", color="C1", label="iterations per step")
    a2.set_ylabel("mean solver iterations per step", color="C1")
    a.set_title("cost (1344-dof reduced scene, light contact, SPG ≤ 200 iterations)")
    a.grid(alpha=0.3, which="both")
    b.loglog(tol, [100 * r["float64_rmse_rel_peak"] for r in rows], "o-", label="RMSE")
    worst = [100 * r["float64_max_error_rel_peak"] for r in rows]
    b.loglog(tol, worst, "s--", label="largest error (one step)")
    b.set_xlabel("contact.tolerance")
    b.set_ylabel("insertion force error, % of peak")
    b.set_title("float64 rollout vs the same model solved to 1e-10")
    b.grid(alpha=0.3, which="both")
    b.legend()
    fig.tight_layout()
    fig.savefig(OUT / "contact_tolerance.png", dpi=120)


if __name__ == "__main__":
    main()
