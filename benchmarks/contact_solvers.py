"""APGD against ADMM and SPG (``contact.solver``) in whole rollouts: iterations, steps stopped
at the cap, time per step, and the force's distance from a tightly solved rollout.

    python benchmarks/contact_solvers.py

The 1344-dof reduced scene (P2 1.6 mm, float32) with reduction_speed.py's ``light`` and
``default`` contact settings, each solved by APGD, ADMM and SPG. All six models are built and
compiled first; then ``ROUNDS`` rounds each time every model (the median of ``REPEATS``
rollouts in a ``lax.scan``, and one pass stepping from Python), so that the solvers are
measured side by side on the same machine state. Each rollout's insertion force is compared
with the same model rolled out in float64 with APGD solved to 1e-10 (≤ 20000 iterations): the
curve the solve converges to. First, the contact problems of each configuration's APGD rollout
are recorded as solved (float32, warm starts included; a ``jax.debug.callback``) and solved
again in float64 to the 1e-6 residual by each solver: iterations without the cap, and how far
each solution's total normal force is from APGD's. Writes
benchmarks/results/contact_solvers.{json,png}.
"""

from __future__ import annotations

import json
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _common import FLOAT32, LIGHT, code_version, jitted_step, load_scene, recorded_problems

import jsnap
from jsnap._core.contact import APGD, solve_admm, solve_apgd, solve_spg

# XLA's small-loop option, before the first JAX computation (the committed timings have it).
jsnap.configure_xla_cpu()

OUT = Path(__file__).parent / "results"
MESH = 1.6
CONFIGS = {
    "light": LIGHT,
    "default": {},
}
SOLVE = {"apgd": solve_apgd, "admm": solve_admm, "spg": solve_spg}  # APGD first: the reference
SOLVERS = tuple(SOLVE)
TIGHT = {"contact.iterations": 20000, "contact.tolerance": 1e-10, "solver.dtype": "float64"}
ROUNDS, REPEATS = 5, 5


def _scene(config, changes):
    """The reduced scene of ``config`` in float32 with ``changes`` (ADMM is an internal choice
    of contact.solver: the scene is made with ``with_internal``)."""
    base = {"solver.mesh_size": MESH, "solver.method": "reduced", **FLOAT32, **CONFIGS[config]}
    return load_scene({**base, **changes})


def recorded_solves(config, tol=1e-6, cap=20000):
    """The APGD rollout's contact problems, solved again in float64 by each solver."""
    recs = [
        [np.asarray(x, np.float64) for x in r] for r in recorded_problems(jsnap.build(_scene(config, {})), APGD)
    ]
    out = {"solves": len(recs), "tolerance": tol, "cap": cap}
    totals = {}
    for name, solve in SOLVE.items():
        f = jax.jit(
            lambda W, q, mu, mask, g0, solve=solve: solve(
                W, q, mu, mask, max_iters=cap, tol=tol, gamma0=g0, differentiable=False
            )
        )
        its, tot = [], []
        for W, q, mu, mask, g0 in recs:
            sol = f(W, q, mu, mask.astype(bool), g0)
            its.append(int(sol.iterations))
            tot.append(float(np.asarray(sol.gamma)[:, 0].sum()))
        its = np.asarray(its)
        out[name] = {
            "mean": float(its.mean()),
            "median": float(np.median(its)),
            "max": int(its.max()),
            "capped": int((its >= cap).sum()),
        }
        totals[name] = np.asarray(tot)
    scale = np.maximum(np.abs(totals["apgd"]), 1e-12)
    out["max_total_normal_force_rel_diff"] = {
        name: float(np.max(np.abs(totals[name] - totals["apgd"]) / scale)) for name in SOLVERS[1:]
    }
    print(config, out, flush=True)
    return out


def _scan_seconds(model, prepared):
    times = []
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        jax.block_until_ready(jsnap.rollout(model, prepared=prepared).energy)
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def _call_seconds(one, dyn, state0, controls):
    s = state0
    t0 = time.perf_counter()
    for c in controls:
        s = one(dyn, s, c)
    jax.block_until_ready(s)
    return time.perf_counter() - t0


def main():
    # The per-call rate steps a jitted jsnap.step from Python, which runs in JAX's 64-bit mode
    # (see _common.jitted_step), as every computation here did before the redesign.
    with jax.enable_x64(True):
        _main()


def _main():
    solves = {config: recorded_solves(config) for config in CONFIGS}
    runs = {}
    for config in CONFIGS:
        ref = jsnap.rollout(jsnap.build(_scene(config, TIGHT)))
        F_ref = np.asarray(ref.insertion_force, np.float64)
        for solver in SOLVERS:
            model = jsnap.build(_scene(config, {"contact.solver": solver}))
            prepared = jsnap.prepare(model)
            t0 = time.perf_counter()
            res = jsnap.rollout(model, prepared=prepared)
            jax.block_until_ready(res.energy)
            first = time.perf_counter() - t0
            controls = jnp.asarray(model.trajectory()[1:], model.dtype)
            one, dyn, state0 = jitted_step(model, prepared)
            _call_seconds(one, dyn, state0, controls)  # a whole pass: every compile happens here
            F = np.asarray(res.insertion_force, np.float64)
            it = np.asarray(res.iterations)
            runs[(config, solver)] = dict(
                model=model,
                prepared=prepared,
                call=(one, dyn, state0, controls),
                row={
                    "config": config,
                    "solver": solver,
                    "dof": model.n_dof,
                    "full_dof": model.full_dof,
                    "steps": int(F.size),
                    "first_call_seconds": first,
                    "iterations_mean": float(it.mean()),
                    "iterations_per_step": it.tolist(),
                    "capped_steps": int((it >= model.contact.solver.max_iters).sum()),
                    "contact_steps": int((it > 0).sum()),
                    "peak_N": float(F.max()),
                    "ref_peak_N": float(F_ref.max()),
                    "rmse_vs_tight_rel": float(np.sqrt(np.mean((F - F_ref) ** 2)) / F_ref.max()),
                    "scan_us_per_step": [],
                    "python_us_per_step": [],
                },
            )
            print(config, solver, "compiled", flush=True)
    for r in range(ROUNDS):
        for (config, solver), run in runs.items():
            row = run["row"]
            row["scan_us_per_step"].append(1e6 * _scan_seconds(run["model"], run["prepared"]) / row["steps"])
            row["python_us_per_step"].append(1e6 * _call_seconds(*run["call"]) / row["steps"])
            print(r, config, solver, row["scan_us_per_step"][-1], row["python_us_per_step"][-1], flush=True)
    rows = [run["row"] for run in runs.values()]
    by = {(row["config"], row["solver"]): row for row in rows}
    headline = {}
    for config in CONFIGS:
        a = by[(config, "apgd")]
        headline[config] = {"contact_steps": a["contact_steps"]}
        for solver in SOLVERS:
            d = by[(config, solver)]
            med = {k: (np.median(a[k]), np.median(d[k])) for k in ("scan_us_per_step", "python_us_per_step")}
            headline[config][solver] = {
                # APGD's time over this solver's (medians): > 1 is faster than APGD
                "scan_speedup": float(med["scan_us_per_step"][0] / med["scan_us_per_step"][1]),
                "python_speedup": float(med["python_us_per_step"][0] / med["python_us_per_step"][1]),
                "scan_us_per_step": float(med["scan_us_per_step"][1]),
                "iterations": d["iterations_mean"],
                "capped": d["capped_steps"],
                "rmse": d["rmse_vs_tight_rel"],
            }
    machine = f"{platform.machine()}, {platform.processor() or platform.system()}, {jax.devices()[0].platform}"
    result = {
        "code": code_version(),
        "machine": machine,
        "mesh_size": MESH,
        "configs": CONFIGS,
        "tight": TIGHT,
        "rounds": ROUNDS,
        "repeats": REPEATS,
        "headline": headline,
        "recorded_solves": solves,
        "rows": rows,
    }
    OUT.mkdir(exist_ok=True)
    (OUT / "contact_solvers.json").write_text(json.dumps(result, indent=1))
    plot(result, OUT / "contact_solvers.png")
    print(json.dumps(headline, indent=1))


def plot(result, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["rows"]
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    labels, colors = [], {"apgd": "tab:blue", "admm": "tab:orange", "spg": "tab:green"}
    k = len(SOLVERS)
    for i, row in enumerate(rows):
        for j, key in enumerate(("scan_us_per_step", "python_us_per_step")):
            x = (k + 1) * (i // k) + (i % k) + 0.4 * j - 0.2
            v = row[key]
            ax.bar(x, np.median(v), 0.4, color=colors[row["solver"]], alpha=1.0 if j == 0 else 0.5)
            ax.plot([x] * len(v), v, "k.", ms=3)
        labels.append(((k + 1) * (i // k) + (i % k), f"{row['config']}\n{row['solver']}"))
    ax.set_xticks([p for p, _ in labels], [t for _, t in labels])
    ax.set_ylabel("µs per step")
    ax.set_title(
        f"reduced {rows[0]['full_dof']}-dof scene, float32\n"
        "solid: lax.scan rollout, pale: one Python call per step"
    )
    for row in rows:
        if row["config"] == "default":
            it = np.asarray(row["iterations_per_step"])
            ax2.plot(
                it,
                color=colors[row["solver"]],
                lw=1,
                label=f"{row['solver']} (mean {row['iterations_mean']:.0f})",
            )
    cap = next(r for r in rows if r["config"] == "default")
    ax2.axhline(np.max(cap["iterations_per_step"]), color="gray", ls=":", lw=1)
    ax2.set_xlabel("step")
    ax2.set_ylabel("solver iterations")
    ax2.set_title("default contact settings: iterations per step (cap dotted)")
    ax2.legend()
    fig.suptitle(f"APGD, ADMM and SPG, side by side; {result['machine']}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
