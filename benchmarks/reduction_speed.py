"""Full against reduced socket, side by side: step time against the full model's size, in a
``lax.scan`` rollout and stepping from Python one call at a time, and the reduction's build time.

    python benchmarks/reduction_speed.py [--quick]

For each P2 mesh (``solver.mesh_size``) the default scene is built with ``solver.method`` =
``full`` and ``reduced`` (default ``solver.hsv_tolerance``), and rolled out in float32
(``solver.dtype``, stated: the full model's default is float64 since the redesign) with two
contact configurations:

* ``default``: the scene's contact settings (64 slots, candidate lines every 1.0 mm across the
  width, up to 500 APGD iterations);
* ``light``: lines every 2.0 mm, 24 slots, up to 200 iterations of the SPG solver
  (``contact.solver = "spg"``) stopped at the 1e-4 residual (the scene's: 1e-6;
  benchmarks/contact_tolerance.py and docs/reduction.md measure what the settings cost in
  accuracy);
* ``light_apgd``: the same with the default APGD solver, at the ~1300-dof mesh only (the two
  solvers side by side);

and, for the reduced model only, ``floor``: the light settings with one APGD iteration.
It is not a usable setting (the contact is not solved); it bounds from above what a step costs
besides the contact solve. From above: with the contact unsolved, the motion of most steps
carries points that were not in the buffer into the plug, so the predict-correct pass solves
them again (189 of the 233 steps on 1344 dof, against none with the light settings), each a
second collision, contact operator and solve. Each row counts these steps (``second_solves``).
The socket's own work per step (free velocity, point displacements, contact operator, energy,
base wrench; no collision, no contact solve) is timed apart as well.

Timings: the PMI operator is prepared once, outside them; a rollout's rate is the median of
``REPEATS`` compiled runs spread over ``SPREAD_S`` seconds at least, after a first one (whose
excess over the median is reported as compile time; the fastest run is kept too; three runs
with ``--quick``); the per-call
rate steps a jitted ``step(state, control)`` through the same motion from a Python loop. The
reduced build is timed with an empty cache (and again from the cache). Writes
benchmarks/results/reduction_speed.{json,png} (``_quick`` with ``--quick``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _common import FLOAT32, FULL, TIGHT_ADMM, jitted_step, load_scene
from _common import LIGHT as LIGHT_CONTACT

import jsnap
from jsnap._build.model import build_model
from jsnap._core.util import cast_floats

# XLA's small-loop option, before the first JAX computation (the committed timings have it).
jsnap.configure_xla_cpu()

OUT = Path(__file__).parent / "results"
# Timed rollouts per row: at least the first, and more, up to the second, until SPREAD_S seconds
# have passed, so that a burst of the shared machine's load (a second or two) cannot take most of
# a fast row's rollouts (the median is reported). Measured: with five rollouts, the reduced
# 1344-dof light row once read a median of 170 µs per step and a fastest of 116.
REPEATS = (11, 201)
SPREAD_S = 3.0
QUICK_REPEATS, QUICK_SPREAD_S = (3, 3), 0.0  # --quick (CI): the script runs, no timing to quote
# The light contact settings: lines every 2.0 mm, 24 slots, the solve stopped at 200 iterations or
# the 1e-4 residual. With the scene's 1e-6 the capped solves of this scene end at a residual of
# ~4e-5 to 6e-5 (median, two runs; 2.5e-4 at most), so the hardest steps are solved to ~1e-4
# whatever the tolerance; the float64 force is as close to a tightly solved rollout at 1e-4 as at
# 1e-6, and 3e-4 moves the snap by a step (benchmarks/contact_tolerance.py, docs/reduction.md).
LIGHT = {**LIGHT_CONTACT, "contact.tolerance": 1e-4}
CONFIGS = {
    "default": {},
    "light": {**LIGHT, "contact.solver": "spg"},
    "light_apgd": LIGHT,
    "floor": {**LIGHT, "contact.iterations": 1},
}


def _build(scene):
    """``(model, build report, seconds)``."""
    t0 = time.perf_counter()
    model, report = build_model(scene)
    return model, report, time.perf_counter() - t0


def _tight_reference(mesh_size: float) -> np.ndarray:
    """The light settings' insertion force from the full model in float64 with the contact
    solved to 1e-10 (ADMM, ≤ 20000 iterations): what every row of this mesh converges to. The
    rows' distance from each other is dominated by the step in which the snap falls (float32
    round-off moves it by a step either way); this reference separates that from the solve."""
    scene = load_scene(  # TIGHT_ADMM's ADMM is an internal choice (with_internal)
        {
            "solver.mesh_size": mesh_size,
            **FULL,
            "solver.dtype": "float64",
            **LIGHT,
            **TIGHT_ADMM,
        }
    )
    return np.asarray(jsnap.rollout(jsnap.build(scene)).insertion_force, np.float64)


def _per_call_rate(model, prepared, controls) -> float:
    """Steps per second of a jitted step called once per step from Python (compile excluded)."""
    one, dyn, state0 = jitted_step(model, prepared)
    jax.block_until_ready(one(dyn, state0, controls[0]))
    best = np.inf
    for _ in range(2):
        s = state0
        t0 = time.perf_counter()
        for c in controls:
            s = one(dyn, s, c)
        jax.block_until_ready(s)
        best = min(best, time.perf_counter() - t0)
    return len(controls) / best


def _socket_us_per_step(model, prepared, n: int = 100) -> float:
    """Microseconds per step of the socket's own work (what ``step`` asks of it: free velocity,
    candidate and stencil displacements, the contact operator of ``capacity`` points, their
    velocity, energy and base wrench), without the collision and the contact solve."""
    dtype = jnp.dtype(model.dtype)
    m, p = cast_floats(model, dtype), cast_floats(prepared, dtype)
    sock, op, mat = m.part, p.op, p.params.material
    capacity = model.contact.capacity
    idx = jnp.arange(capacity) * (model.n_samples // capacity)
    force = jnp.full((capacity, 3), 1e-3, dtype)

    @jax.jit
    def loop(x0):
        def body(_, c):
            x, v = c
            vbar = sock.free_velocity(op, x, v)
            xn = sock.nodal(x)
            y = sock.sample_at(xn)
            st = sock.stencil_at(xn, idx)
            A, W = sock.contact_operator(op, idx)
            g = force * (1 + 0 * (jnp.sum(W) + jnp.sum(st) + jnp.sum(y)))
            vbar = vbar + jnp.einsum("cdn,cd->n", A, g)
            u = sock.point_at(sock.nodal(vbar), idx)
            x_new, v_new = x + op.dt * vbar, 2 * vbar - v
            e = sock.energy(op, x_new, v_new)
            f, _ = sock.base_wrench(mat, op.dt, x, v, v_new, vbar)
            return x_new + 0 * (e + f[0] + jnp.sum(u)), v_new

        return jax.lax.fori_loop(0, n, body, (x0, 0 * x0))

    x0 = jnp.zeros(model.n_dof, dtype)
    jax.block_until_ready(loop(x0))
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        jax.block_until_ready(loop(x0))
        best = min(best, time.perf_counter() - t0)
    return 1e6 * best / n


def run(mesh_size: float, method: str, config: str, quick: bool = False) -> dict:
    scene = load_scene({"solver.mesh_size": mesh_size, "solver.method": method, **FLOAT32, **CONFIGS[config]})
    model, report, build_s = _build(scene)
    row = {
        "mesh_size": mesh_size,
        "method": method,
        "config": config,
        "full_dof": model.full_dof,
        "dof": model.n_dof,
        "build_seconds": build_s,
    }
    if method == "reduced":
        red = report.reduction
        row["orders"] = list(model.part.orders)
        row["reduction_seconds"] = red["seconds"] if not red["cached"] else None
        row["cached"] = red["cached"]
    prepared = jsnap.prepare(model)
    t0 = time.perf_counter()
    res = jsnap.rollout(model, prepared=prepared)
    jax.block_until_ready(res.energy)
    first = time.perf_counter() - t0
    (least, most), spread = (QUICK_REPEATS, QUICK_SPREAD_S) if quick else (REPEATS, SPREAD_S)
    times, start = [], time.perf_counter()
    while len(times) < least or (time.perf_counter() - start < spread and len(times) < most):
        t0 = time.perf_counter()
        jax.block_until_ready(jsnap.rollout(model, prepared=prepared).energy)
        times.append(time.perf_counter() - t0)
    run_s = float(np.median(times))
    F = np.asarray(res.insertion_force, np.float64)
    controls = jnp.asarray(model.trajectory()[1:], model.dtype)
    row.update(
        steps=int(F.size),
        scan_steps_per_second=F.size / run_s,
        scan_us_per_step=1e6 * run_s / F.size,
        compile_seconds=first - run_s,
        scan_us_per_step_min=1e6 * min(times) / F.size,
        scan_rollouts=len(times),
        python_steps_per_second=_per_call_rate(model, prepared, controls),
        socket_us_per_step=_socket_us_per_step(model, prepared),
        peak_N=float(F.max()),
        iterations_mean=float(np.asarray(res.iterations).mean()),
        second_solves=int(np.asarray(res.corrected).sum()),
        max_overflow=int(np.asarray(res.overflow).max()),
        insertion_force=F.tolist(),
    )
    row["python_us_per_step"] = 1e6 / row["python_steps_per_second"]
    return row


def main(argv=None):
    # The per-call rate steps a jitted jsnap.step, which runs in JAX's 64-bit mode (see
    # _common.jitted_step), as every computation here did before the redesign.
    with jax.enable_x64(True):
        _main(argv)


def _main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one coarse mesh, light contact only")
    a = ap.parse_args(argv)
    meshes = [1.6] if a.quick else [2.0, 1.6, 1.2, 0.8]
    configs = ["light"] if a.quick else ["default", "light", "light_apgd"]
    stem = "reduction_speed_quick" if a.quick else "reduction_speed"
    load = [os.getloadavg()]
    rows = []
    with tempfile.TemporaryDirectory() as cache:
        os.environ["JSNAP_CACHE"] = cache  # time the reduction itself, then the cached load
        for h in meshes:
            # The default contact settings and APGD with the light ones at the ~1300-dof mesh only
            # (the 30-minute budget of `jsnap bench`); the light settings at every mesh for the
            # size sweep.
            for config in configs if h == 1.6 else ["light"]:
                for method in ("full", "reduced"):
                    rows.append(run(h, method, config, a.quick))
                    r = rows[-1]
                    if method == "reduced":
                        full = next(x for x in rows if x["mesh_size"] == h and x["config"] == config)
                        F0, F = np.asarray(full["insertion_force"]), np.asarray(r["insertion_force"])
                        r["rmse_vs_full_rel_peak"] = float(np.sqrt(np.mean((F - F0) ** 2)) / F0.max())
                        r["scan_speedup"] = r["scan_steps_per_second"] / full["scan_steps_per_second"]
                        r["python_speedup"] = r["python_steps_per_second"] / full["python_steps_per_second"]
                        r["socket_speedup"] = full["socket_us_per_step"] / r["socket_us_per_step"]
                    print({k: v for k, v in r.items() if k != "insertion_force"}, flush=True)
            if h == 1.6 and not a.quick:
                rows.append(run(h, "reduced", "floor"))
                print({k: v for k, v in rows[-1].items() if k != "insertion_force"}, flush=True)
                ref = _tight_reference(h)
                for r in rows:
                    if r["mesh_size"] == h and r["config"] in ("light", "light_apgd"):
                        F = np.asarray(r["insertion_force"])
                        r["rmse_vs_tight_full_rel_peak"] = float(np.sqrt(np.mean((F - ref) ** 2)) / ref.max())
            if not a.quick:  # the cached reduced model loads instead of being rebuilt
                _, _, t = _build(load_scene({"solver.mesh_size": h, "solver.method": "reduced", **FLOAT32}))
                for r in rows:
                    if r["mesh_size"] == h and r["method"] == "reduced":
                        r["cached_build_seconds"] = t
    load.append(os.getloadavg())
    lo, hi = min(a[0] for a in load), max(a[0] for a in load)
    machine = (
        f"{platform.machine()}, {os.cpu_count()} CPU cores, {jax.devices()[0].platform}, "
        f"load average {lo:.1f}-{hi:.1f}"
    )

    def pick(h, method, config):
        return next(r for r in rows if r["mesh_size"] == h and r["method"] == method and r["config"] == config)

    h_ref = 1.6  # the ~1300-dof mesh

    def side_by_side(config):
        """``{config}_scan_steps_per_second`` and ``_python_`` (full and reduced) and
        ``{config}_scan_speedup`` at the ~1300-dof mesh."""
        red, full = pick(h_ref, "reduced", config), pick(h_ref, "full", config)
        out = {
            f"{config}_{k}": {"full": full[k], "reduced": red[k]}
            for k in ("scan_steps_per_second", "python_steps_per_second")
        }
        out[f"{config}_scan_speedup"] = red["scan_speedup"]
        return out

    red, full = pick(h_ref, "reduced", "light"), pick(h_ref, "full", "light")
    headline = {
        "mesh_size": h_ref,
        "full_dof": full["full_dof"],
        "orders": red["orders"],
        **side_by_side("light"),
        "scan_speedup": red["scan_speedup"],
        "socket_speedup": red["socket_speedup"],
        "targets": {"scan_steps_per_second": 1e4, "python_steps_per_second": 2e3, "speedup": 10.0},
        "reduced_build_seconds": red["build_seconds"],
    }
    if not a.quick:  # the quick run (CI) measures neither the floor nor the default contact
        headline["floor_scan_steps_per_second"] = pick(h_ref, "reduced", "floor")["scan_steps_per_second"]
        headline.update(side_by_side("default"))
        headline.update(side_by_side("light_apgd"))
        headline["rmse_vs_full_rel_peak"] = {
            c: pick(h_ref, "reduced", c)["rmse_vs_full_rel_peak"] for c in ("light", "light_apgd", "default")
        }
        headline["rmse_vs_tight_full_rel_peak"] = {
            f"{m}_{c}": pick(h_ref, m, c)["rmse_vs_tight_full_rel_peak"]
            for m in ("full", "reduced")
            for c in ("light", "light_apgd")
        }
    OUT.mkdir(exist_ok=True)
    (OUT / f"{stem}.json").write_text(
        json.dumps(
            {
                "machine": machine,
                # 1/5/15-minute load averages at the start and the end: the machine is shared with
                # other jobs, so every timing here is an upper bound of the unloaded one.
                "load_average": {"start": list(load[0]), "end": list(load[1])},
                "shared_machine": True,
                "configs": CONFIGS,
                "headline": headline,
                "rows": rows,
            }
        )
    )

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.8), sharey=True)
    for ax, key, title in (
        (axes[0], "scan_us_per_step", "whole step, lax.scan rollout"),
        (axes[1], "python_us_per_step", "whole step, one jitted call from Python"),
        (axes[2], "socket_us_per_step", "the socket's own work per step (no contact solve)"),
    ):
        for method, color in (("full", "C3"), ("reduced", "C0")):
            for config, style in (("default", "--"), ("light", "-"), ("light_apgd", "-."), ("floor", ":")):
                pts = [r for r in rows if r["method"] == method and r["config"] == config]
                if not pts:
                    continue
                ax.loglog(
                    [r["full_dof"] for r in pts],
                    [r[key] for r in pts],
                    style,
                    color=color,
                    marker="o",
                    label=f"{method}, {config} contact" + (" (SPG)" if config == "light" else ""),
                )
        for rate, y in (("10 kHz", 100.0), ("2 kHz", 500.0)):
            ax.axhline(y, color="0.5", lw=0.7)
            ax.text(min(r["full_dof"] for r in rows), y * 1.08, rate, fontsize=8)
        ax.set_xlabel("full model free dofs (P2 mesh)")
        ax.set_title(title)
        ax.grid(alpha=0.3, which="both")
    axes[0].set_ylabel("time per step (µs)")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"Step time, full vs reduced socket (float32; {machine})", fontsize=9)
    fig.tight_layout()
    fig.savefig(OUT / f"{stem}.png", dpi=120)


if __name__ == "__main__":
    main()
