"""Identification of E and friction from a noisy measured insertion force.

    python benchmarks/identify.py [--quick]

The "measurement" comes from a finer *full* model (P2 0.8 mm, the default scene's mesh) at the
true parameters (ABS, E = 2200 MPa, μ = 0.3), pushed at 20 mm/s and sampled at its 1 kHz steps,
plus independent Gaussian noise of 5 % of the peak force on every sample. The fitted model is
the *reduced* model (``solver.method = "reduced"``, passive balanced reduction) on a different,
coarser mesh (P2 0.9 mm). Each fit starts a factor 2 away from the truth in both parameters
(all four corners: E/2 or 2E with μ/2 or 2μ) and runs ``jsnap.identify`` (a seed search by
forward rollouts, then L-BFGS on log-parameters; Gauss–Newton standard errors); its wall time
includes compilation, not the reduced model's build (a cached, one-off cost, reported apart).
The starts with 2μ = 0.6 lie in this hook's stick–slip regime, where the force history is rough
(docs/differentiation.md).

``--quick`` (keeps the script from rotting; it shows nothing about accuracy): the truth is the
fitted model itself (reduced P2 1.5 mm, so its rollout compiles once), the first 60 ms, one
start, at most 4 iterations.
Writes benchmarks/results/identify{,_quick}.{json,png}.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import jax
import numpy as np

import jsnap

# XLA's small-loop option, before the first JAX computation (the committed timings have it).
jsnap.configure_xla_cpu()

OUT = Path(__file__).parent / "results"
TRUE = {"E": 2200.0, "friction": 0.3}
NOISE = 0.05  # of the peak force, per sample
SPEED = 20.0  # mm/s


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="coarser meshes, one start")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    truth_mesh = 1.5 if a.quick else 0.8
    max_iters = 4 if a.quick else 30
    # (fitted model's mesh, start factors on E and friction)
    plan = [(1.5, 0.5, 0.5)] if a.quick else [(0.9, fe, fm) for fe in (0.5, 2.0) for fm in (0.5, 2.0)]
    common = {"solver.dtype": "float64", "motion.speed": SPEED}

    t0 = time.perf_counter()
    truth_scene = jsnap.load_scene().replace(
        {**common, "solver.mesh_size": truth_mesh, "solver.method": "reduced" if a.quick else "full"}
    )
    truth = jsnap.build(truth_scene)
    res = jsnap.rollout(truth, controls=truth.trajectory()[1:61] if a.quick else None)
    F_true = np.asarray(res.insertion_force)
    t = np.asarray(res.t)
    t_truth = time.perf_counter() - t0
    rng = np.random.default_rng(a.seed)
    sigma = NOISE * F_true.max()
    F_meas = F_true + sigma * rng.normal(size=F_true.size)
    print(
        f"truth: {truth_scene.get('solver.method')} P2 {truth_mesh} mm, {truth.n_dof} dof, "
        f"peak {F_true.max():.3f} N",
        flush=True,
    )

    models = {}
    for fit_mesh in sorted({p[0] for p in plan}):
        t0 = time.perf_counter()
        scene = jsnap.load_scene().replace({**common, "solver.mesh_size": fit_mesh, "solver.method": "reduced"})
        model = jsnap.build(scene)
        t_build = time.perf_counter() - t0
        # The discretisation gap alone: the fitted model at the true parameters against the truth.
        F_gap = np.asarray(
            jsnap.rollout(model, controls=model.trajectory()[1 : F_true.size + 1]).insertion_force
        )
        gap = float(np.sqrt(np.mean((F_gap - F_true) ** 2)))
        models[fit_mesh] = (model, t_build, gap)
        print(f"fit model: reduced, P2 {fit_mesh} mm, {model.n_dof} states, build {t_build:.1f} s", flush=True)

    meas = jsnap.Measurement(t, F_meas, "synthetic (finer full model + 5 % noise)")
    runs = []
    for fit_mesh, fe, fm in plan:
        model, t_build, gap = models[fit_mesh]
        init = {"E": fe * TRUE["E"], "friction": fm * TRUE["friction"]}
        fit = jsnap.identify(
            model, meas, fit=("E", "friction"), initial=init, max_iters=max_iters, progress=True
        )
        d = fit.to_dict()
        d["fit_model"] = {
            "model": f"reduced, P2 {fit_mesh} mm",
            "states": model.n_dof,
            "build_seconds": t_build,
            "gap_rms_N_at_true_parameters": gap,
        }
        d["start_factors"] = {"E": fe, "friction": fm}
        d["error"] = {k: d["values"][k] / TRUE[k] - 1 for k in TRUE}
        d["within_3_percent"] = all(abs(v) < 0.03 for v in d["error"].values())
        d["fitted_force"] = fit.fitted.tolist()
        d["start_force"] = fit.start.tolist()
        runs.append(d)
        print(fit.summary(), flush=True)
        print({k: f"{100 * v:+.2f} %" for k, v in d["error"].items()}, flush=True)

    load = ", ".join(f"{v:.1f}" for v in os.getloadavg())
    machine = f"{platform.machine()}, {os.cpu_count()} cores, {jax.devices()[0].platform}, load average {load}"
    errors = {k: max(abs(r["error"][k]) for r in runs) for k in TRUE}
    seconds = [r["seconds"] for r in runs]
    result = {
        "machine": machine,
        "headline": {
            "starts": len(runs),
            "all_within_3_percent": all(r["within_3_percent"] for r in runs),
            "max_abs_error": errors,
            "seconds_median": float(np.median(seconds)),
            "seconds_max": float(np.max(seconds)),
            "fit_model": runs[0]["fit_model"]["model"],
        },
        "truth": {
            "model": f"{truth_scene.get('solver.method')} P2 {truth_mesh} mm",
            "dof": truth.n_dof,
            **TRUE,
            "seconds": t_truth,
        },
        "speed_mm_s": SPEED,
        "noise": {"relative_to_peak": NOISE, "sigma_N": sigma, "seed": a.seed},
        "t": t.tolist(),
        "measured": F_meas.tolist(),
        "truth_force": F_true.tolist(),
        "runs": runs,
    }
    stem = "identify_quick" if a.quick else "identify"
    OUT.mkdir(exist_ok=True)
    (OUT / f"{stem}.json").write_text(json.dumps(result, indent=1))
    plot(result, OUT / f"{stem}.png")


def _label(r):
    f = r["start_factors"]
    return f"{r['fit_model']['model']}, start E×{f['E']:g}, μ×{f['friction']:g}"


def plot(result, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.asarray(result["t"]) * 1e3
    fig, ax = plt.subplots(1, 2, figsize=(14, 5.2), gridspec_kw={"width_ratios": [3, 2]})
    ax[0].plot(t, result["measured"], ".", ms=3, color="0.55", label="measured: finer full model + 5 % noise")
    truth = result["truth"]["model"]
    ax[0].plot(t, result["truth_force"], lw=1.0, color="k", label=f"truth ({truth}), no noise")
    r0 = result["runs"][0]
    ax[0].plot(t, r0["start_force"], "--", lw=1.0, color="tab:orange", label=f"start: {_label(r0)}")
    ax[0].plot(t, r0["fitted_force"], lw=1.6, color="tab:blue", label="fitted")
    ax[0].set_xlabel("time (ms)")
    ax[0].set_ylabel("insertion force (N)")
    ax[0].grid(alpha=0.3)
    ax[0].legend(fontsize=8)
    lines = []
    for r in result["runs"]:
        ax[1].semilogy(np.arange(len(r["loss_history"])), r["loss_history"], "o-", ms=3, label=_label(r))
        v, se, e = r["values"], r["std_errors"], r["error"]
        lines.append(
            f"{_label(r)}: E = {v['E']:.0f} ± {se['E']:.0f} MPa ({100 * e['E']:+.1f} %), "
            f"μ = {v['friction']:.3f} ± {se['friction']:.3f} ({100 * e['friction']:+.1f} %), "
            f"{r['seconds']:.0f} s"
        )
    ax[1].set_xlabel("L-BFGS iteration")
    ax[1].set_ylabel("loss (smoothed, normalised)")
    ax[1].grid(alpha=0.3)
    ax[1].legend(fontsize=7)
    fig.suptitle(
        f"jsnap.identify: E and μ from a noisy insertion force (truth E = 2200 MPa, μ = 0.3) — "
        f"{result['machine']}\n" + "\n".join(lines),
        fontsize=8,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
