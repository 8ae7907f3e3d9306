"""Stability at the control rate (the paper's Fig. 3): a St. Venant–Kirchhoff hook integrated by
linearised backward Euler, linearised implicit midpoint, Newton-implicit midpoint and velocity
Verlet, against linear PMI, for E from 2 GPa to 200 GPa, zero damping, dt = 1 ms.

The scenario is the snap's release: the default hook held pressed in by its undercut (0.8 mm
on the flat, static equilibrium of each model) and let go at rest; free vibration, no damping,
no load, so the exact energy is constant. Writes benchmarks/results/stability.json (config,
per-run summary table, energy histories) and stability.png (energy / E0 against time, one
panel per E). See docs/stability.md.

    python benchmarks/stability.py [--quick] [--steps N] [--mesh-size MM]

Full: 1.2 mm P1 mesh (420 free dofs), 400 steps, E in {2, 2.2, 20, 200} GPa: 2 minutes on a
shared 2-core machine (up to 8 when it is busy), nearly all of it Newton iterations.
--quick: 2 mm mesh (153 dofs), 50 steps, E = 200 GPa only, a smoke run for CI (seconds;
written to a temp dir unless --out). --replot redraws the PNG from the JSON.
"""

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np
import scipy.linalg as sl

matplotlib.use("Agg")
import matplotlib.pyplot as plt

import jsnap
from jsnap._build.nonlinear import snap_release
from jsnap._core import nonlinear as N
from jsnap._core.params import Material
from jsnap._geometry.scene import connector_geometry, load_scene

# XLA's small-loop option, before the first JAX computation (the committed results had it).
jsnap.configure_xla_cpu()

DT, NU, RHO = 1e-3, 0.35, 1.05e-9
STOP = 1e8  # a run whose energy exceeds STOP * E0 is stopped and counted as diverged
RTOL, MAX_ITER = 1e-10, 40  # Newton-implicit midpoint

LABELS = {
    "linear_pmi": "linear PMI (this project)",
    "newton_midpoint": "SVK, Newton-implicit midpoint",
    "linearised_midpoint": "SVK, linearised implicit midpoint",
    "linearised_euler": "SVK, linearised backward Euler",
    "verlet": "SVK, velocity Verlet (explicit)",
}
COLOURS = {
    "linear_pmi": "#1a9641",
    "newton_midpoint": "#2b83ba",
    "linearised_midpoint": "#fdae61",
    "linearised_euler": "#7b3294",
    "verlet": "#d7191c",
}
ORDER = ["linear_pmi", "newton_midpoint", "linearised_midpoint", "linearised_euler", "verlet"]


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{platform.node()} ({cpu}, jax {jax.__version__} {jax.default_backend()}, float64)"


def classify(ratio: np.ndarray) -> str:
    """diverged: energy NaN/overflow or > 10 E0; damped: ends > 10% below E0; conserved:
    within 1% throughout; otherwise 'not conserved' (bounded, but neither)."""
    if not np.all(np.isfinite(ratio)) or ratio.max() > 10.0:
        return "diverged"
    if ratio[-1] < 0.9:
        return "damped"
    if np.max(np.abs(ratio - 1.0)) <= 0.01:
        return "conserved"
    return "not conserved"


def first(mask: np.ndarray):
    return int(np.argmax(mask)) if mask.any() else None


def run_all(snap, Es, steps):
    model, probe = snap.model, jnp.asarray(snap.probe)
    n = model.n_free
    runs = []
    for E in Es:
        mat = Material.create(E, NU, RHO)
        for method in ORDER:
            u0 = jnp.asarray(snap.u_linear if method == "linear_pmi" else snap.u_svk)
            t0 = time.perf_counter()
            tr = N.simulate(method, model, mat, DT, u0, jnp.zeros(n), steps, probe, RTOL, MAX_ITER, STOP)
            tr = jax.tree_util.tree_map(np.asarray, tr)
            wall = time.perf_counter() - t0
            e = tr.energy
            r = e / e[0]
            fin = np.isfinite(r)
            failed = ~tr.converged & fin[1:]  # Newton failures before the run was stopped
            row = {
                "E_MPa": E,
                "method": method,
                "class": classify(r),
                "E0_Nmm": float(e[0]),
                "final_ratio": float(r[-1]) if fin[-1] else None,  # None: stopped (strict JSON)
                "max_ratio": float(np.nanmax(r)),
                "min_ratio": float(np.nanmin(r)),
                "max_abs_change": float(np.nanmax(np.abs(r - 1.0))),
                "stopped_at_step": first(~fin),
                "exceeded_10x_at_step": first(~(r <= 10.0)),
                "newton_failures": int(failed.sum()) if method == "newton_midpoint" else None,
                "first_newton_failure": first(failed) if method == "newton_midpoint" else None,
                "mean_newton_iterations": (
                    float(tr.iterations[fin[1:]].mean()) if method == "newton_midpoint" and fin[1] else None
                ),
                "max_abs_tip_mm": float(np.nanmax(np.abs(tr.probe))),
                "wall_s": wall,
            }
            hist = {
                "energy_ratio": [float(x) if np.isfinite(x) else None for x in r],
                "newton_failed_steps": (np.flatnonzero(failed) + 1).tolist(),
            }
            runs.append((row, hist))
            print(
                f"E={E:>8.0f} MPa {method:20s} {row['class']:13s} final={r[-1]:.3g} "
                f"max={row['max_ratio']:.3g} stop={row['stopped_at_step']} "
                f"newton_fail={row['newton_failures']} {wall:6.1f}s",
                flush=True,
            )
    return runs


def frequencies(snap):
    """Lowest and highest angular frequency (rad/s) of the linear model at E = 1 MPa."""
    asm = snap.asm
    K = asm.stiffness(1.0, NU)[asm.free][:, asm.free].toarray()
    M = RHO * asm.M1[asm.free][:, asm.free].toarray()
    w2 = sl.eigh(K, M, eigvals_only=True)
    return float(np.sqrt(w2[0])), float(np.sqrt(w2[-1]))


def verdict(row, ratio) -> str:
    what = row["class"]
    if what == "diverged":
        k, stop = row["exceeded_10x_at_step"], row["stopped_at_step"]
        what += f" (> 10 E0 at step {k}" if k is not None else " ("
        what += f", stopped at {stop})" if stop is not None else ")"
    elif what == "conserved":
        what += f" (|E/E0 - 1| ≤ {row['max_abs_change']:.0e})"
    elif what == "damped":
        k = first(ratio < 1e-6)
        what += (
            f" (E < 1e-6 E0 from step {k})" if k is not None else f" ({row['final_ratio']:.2g} E0 at the end)"
        )
    if row["newton_failures"]:
        what += f"; Newton failures: {row['newton_failures']}"
    return what


def plot(out, path):
    """Energy / E0 against time, log-log (step 1 onwards), one panel per E."""
    Es, steps = out["config"]["moduli_MPa"], out["config"]["steps"]
    fig, axes = plt.subplots(len(Es), 1, figsize=(13, 2.7 * len(Es)), sharex=True, squeeze=False)
    fig.subplots_adjust(left=0.07, right=0.62, top=1 - 0.75 / (2.7 * len(Es)), bottom=0.6 / (2.7 * len(Es)))
    t = np.arange(steps + 1) * DT * 1e3
    lo, hi = 1e-6, 1e9
    for ax, E in zip(axes[:, 0], Es, strict=True):
        ax.axhline(10.0, color="0.45", lw=0.8, ls=":")
        ax.axhline(0.9, color="0.45", lw=0.8, ls=":")
        rows = [row for row in out["summary"] if row["E_MPa"] == E]
        for i, row in enumerate(rows):
            m, c = row["method"], COLOURS[row["method"]]
            r = np.array([np.nan if x is None else x for x in row["energy_ratio"]])
            pmi = m == "linear_pmi"
            ax.plot(
                t[1:], np.clip(r[1:], 0.1 * lo, None), color=c, lw=3 if pmi else 1.3, zorder=3 if pmi else 2
            )
            if row["stopped_at_step"] is not None:  # where it blew up, on the top edge
                ax.plot(t[row["stopped_at_step"]], hi, "x", color=c, ms=11, mew=2.8, zorder=5, clip_on=False)
            bad = np.array(row["newton_failed_steps"] or [], dtype=int)
            if bad.size:
                bad = bad[np.isfinite(r[bad])]
                ax.plot(t[bad], r[bad], "o", mfc="none", color=c, ms=5, zorder=4)
            short = LABELS[m].split(",")[-1].strip()
            ax.text(
                1.015,
                0.96 - 0.2 * i,
                f"{short}: {verdict(row, r)}",
                transform=ax.transAxes,
                color=c,
                fontsize=8.5,
                va="top",
                ha="left",
                fontweight="bold" if pmi else "normal",
            )
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlim(t[1], t[-1])
        ax.set_ylim(lo, hi)
        ax.set_ylabel("energy / E0")
        ax.set_title(f"E = {E / 1000:g} GPa", loc="right", fontsize=11, fontweight="bold")
        ax.grid(True, which="major", alpha=0.3)
    axes[-1, 0].set_xlabel("time after release, ms (dt = 1 ms: one point per step)")
    handles = [plt.Line2D([], [], color=COLOURS[m], lw=3 if m == "linear_pmi" else 1.5) for m in ORDER]
    labels = [LABELS[m] for m in ORDER]
    handles += [
        plt.Line2D([], [], color="k", marker="x", ls="none", ms=9, mew=2),
        plt.Line2D([], [], color="k", marker="o", mfc="none", ls="none", ms=5),
        plt.Line2D([], [], color="0.45", lw=0.8, ls=":"),
    ]
    labels += [
        f"run stopped: energy > {STOP:.0e} E0 or NaN",
        f"Newton did not converge ({MAX_ITER} iterations)",
        "10 E0 (diverged) and 0.9 E0 (damped)",
    ]
    fig.legend(
        handles, labels, loc="upper left", ncol=4, fontsize=8.5, bbox_to_anchor=(0.07, 1.0), frameon=False
    )
    fig.suptitle(out["title"], fontsize=10.5, x=0.07, ha="left", y=1.0 + 0.35 / (2.7 * len(Es)))
    fig.savefig(path, dpi=130, bbox_inches="tight")
    plt.close(fig)


def main():
    # The integrators run in float64 on arrays made here: jsnap's kernels called directly run in
    # JAX's 64-bit mode, which importing jsnap no longer switches on for the whole process.
    with jax.enable_x64(True):
        _main()


def _main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="2 mm mesh, 50 steps, 200 GPa only (CI)")
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--mesh-size", type=float, default=None, help="mm")
    ap.add_argument("--out", type=Path, default=None, help="default results/ (full), a temp dir (quick)")
    ap.add_argument("--replot", action="store_true", help="redraw the PNG from the JSON in --out")
    a = ap.parse_args()
    if a.out is None:  # a CI smoke run must not overwrite the committed full results
        a.out = Path(tempfile.gettempdir()) / "jsnap-bench" if a.quick else Path(__file__).parent / "results"
    steps = a.steps or (50 if a.quick else 400)
    size = a.mesh_size or (2.0 if a.quick else 1.2)
    Es = [200000.0] if a.quick else [2000.0, 2200.0, 20000.0, 200000.0]
    if a.replot:
        plot(json.loads((a.out / "stability.json").read_text()), a.out / "stability.png")
        return

    t0 = time.perf_counter()
    snap = snap_release(connector_geometry(load_scene()), size, "P1", NU)
    w1, wmax = frequencies(snap)
    build_s = time.perf_counter() - t0
    print(f"{snap.model.n_free} free dofs, SVK/linear load ratio {snap.load_ratio:.4f}, build {build_s:.1f}s")

    runs = run_all(snap, Es, steps)
    mach = machine()
    out = {
        "machine": mach,
        "title": (
            f"Snap release, zero damping, dt = 1 ms: energy of each integrator "
            f"(default hook, P1, {snap.model.n_free} dof, {steps} steps)\n{mach}"
        ),
        "config": {
            "dt_s": DT,
            "steps": steps,
            "moduli_MPa": Es,
            "poissons_ratio": NU,
            "density_t_per_mm3": RHO,
            "damping": 0.0,
            "element": "P1",
            "mesh_size_mm": size,
            "free_dof": snap.model.n_free,
            "initial_flat_deflection_mm": float(snap.probe @ snap.u_svk),
            "svk_over_linear_load": snap.load_ratio,
            "newton_rtol": RTOL,
            "newton_max_iter": MAX_ITER,
            "stop_ratio": STOP,
            "classes": {
                "diverged": "energy NaN/overflow or > 10 E0 at some step",
                "damped": "final energy < 0.9 E0",
                "conserved": "|E/E0 - 1| <= 0.01 at every step",
                "not conserved": "none of the above",
            },
        },
        "frequencies": [
            {
                "E_MPa": E,
                "omega_1_rad_s": w1 * np.sqrt(E),
                "omega_max_rad_s": wmax * np.sqrt(E),
                "T_omega_1": DT * w1 * np.sqrt(E),
                "T_omega_max": DT * wmax * np.sqrt(E),
                "verlet_dt_limit_s": 2.0 / (wmax * np.sqrt(E)),
            }
            for E in Es
        ],
        "table": {
            f"{E / 1000:g} GPa": {row["method"]: row["class"] for row, _ in runs if row["E_MPa"] == E}
            for E in Es
        },
        "summary": [{**row, **hist} for row, hist in runs],
        "build_s": build_s,
        "total_s": time.perf_counter() - t0,
    }
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "stability.json").write_text(json.dumps(out, indent=1))
    plot(out, a.out / "stability.png")
    print(json.dumps(out["table"], indent=1))


if __name__ == "__main__":
    main()
