"""Batched throughput of the reduced model: ``jax.vmap`` of a rollout over a batch of scenes
that differ in Young's modulus, friction and the plug's lateral offset, in scene-steps per
second against the batch size.

    python benchmarks/throughput.py [--quick] [--admm | --spg] [--steps 20] [--max-batch 512]

The model is the paper's Model 4 on the ~1300-dof mesh of ``benchmarks/frequency.py``: the
default scene with P2 elements at ``solver.mesh_size`` 1.7 mm (1218 free dofs), segmented and
reduced (``solver.method = "reduced"``), neural SDF, float32. Lane ``i`` of a batch has its own
E (1800-2600 MPa), friction coefficient (0.1-0.5) and plug offset across the hook's width
(y, -0.4 to +0.4 mm: the 5 mm plug still spans the 4 mm hook, but the contact lines move against
the candidate points); the lanes of a batch of B are the first B of one fixed random draw of 512.

Batching: the script vmaps its own small rollout (``jsnap.rollout_batch`` batches the same way
but prepares each lane's operator inside the call; here the preparation stays outside the
timings, as in the committed results): ``jsnap.prepare`` is vmapped over a batched
:class:`jsnap.Params` (outside the timings, like the other benchmarks), and a ``lax.scan`` of
``jsnap.step`` over the first ``--steps`` steps of the scene's motion (contact from the second
step on) is vmapped over the prepared operators and the plug offsets, and jitted. Under
``vmap`` a lane's early exit saves nothing: the forward APGD solve (``contact.gradient =
"implicit"``, the default) is a ``lax.while_loop``, which batched runs until the slowest lane of
the batch converges or reaches the cap (``contact.iterations``, 500 by default), finished lanes
kept by selects; with ``"unrolled"`` (a ``lax.scan`` whose ``lax.cond`` freezes a converged
lane) every lane runs the whole cap. Every branch of the step's conds and switches (the
predict-correct pass, the solver size) runs too. So batching pays a price that a single scene
mostly avoids; the second series, ``contact.iterations = 100``, measures how much of it is the
iterations. A single scene without ``vmap`` (early exit working) is timed as the reference.

Timings: for every batch size the first call compiles and runs; the steady time is the median
of three further calls and the compile time is the first call minus it. The batch grows from 1
until ``--max-batch`` (every 4x), until a 4x larger batch gains less than 5 % (saturated; checked
from a batch of 16 on), or until a call would take more than ``--max-call`` seconds. CPU numbers and GPU
numbers are kept apart (``results[platform]``); a run on one platform keeps the other's, and
the top-level ``headline`` is the CPU one (a GPU's is also ``headline_gpu``).
``--admm`` or ``--spg`` (not run by ``jsnap bench``): a third series with ``contact.solver =
"admm"`` or ``"spg"`` (500 iterations), side by side with the two APGD ones in the same run;
its while loop runs to the slowest lane as APGD's does (docs/contact.md). Writes
``throughput_admm.{json,png}`` or ``throughput_spg.{json,png}``.
``--quick`` (CI): batches 1 and 4, 10 steps, the default series only, no saturation check.
Writes benchmarks/results/throughput{,_quick}.{json,png} (the chart of a GPU run as
throughput_gpu.png).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from _common import FLOAT32, code_version, load_scene

import jsnap
from jsnap._core.util import cast_floats

# XLA's small-loop option, before the first JAX computation (the committed timings have it).
jsnap.configure_xla_cpu()

OUT = Path(__file__).parent / "results"
SCENE = {
    "solver.element": "P2",
    "solver.mesh_size": 1.7,
    "solver.method": "reduced",
    "solver.sdf": "neural",
    **FLOAT32,
}
POOL = 512
NOTE = (
    "Under vmap a lane's early exit saves nothing: the forward APGD solve (contact.gradient = "
    "implicit, the default) is a lax.while_loop, which batched runs until the slowest lane "
    "converges or reaches contact.iterations (finished lanes kept by selects); with "
    "contact.gradient = unrolled (lax.scan with lax.cond freezes) every lane runs the whole cap. "
    "Every branch of the step's conds and switches (predict-correct pass, solver size) runs. "
    "The single_scene row is one scene jitted without vmap (early exit working)."
)
SERIES = {"default (500 iterations)": {}, "contact.iterations = 100": {"contact.iterations": 100}}
# The third series of --admm and --spg: the other contact solvers at the scene's settings.
EXTRA_SERIES = {
    "admm": {"ADMM (500 iterations)": {"contact.solver": "admm"}},
    "spg": {"SPG (500 iterations)": {"contact.solver": "spg"}},
}
E_RANGE, MU_RANGE, OFFSET_RANGE = (1800.0, 2600.0), (0.1, 0.5), (-0.4, 0.4)  # MPa, -, mm


def lanes(model, n: int, seed: int = 0):
    """Batched Params (n,) and plug offsets (n, 3) in mm: lane i of a fixed random draw (of
    POOL lanes, or of n where a GPU run asks for more)."""
    rng = np.random.default_rng(seed)
    pool = max(POOL, n)
    E = rng.uniform(*E_RANGE, pool)[:n]
    mu = rng.uniform(*MU_RANGE, pool)[:n]
    dx = rng.uniform(*OFFSET_RANGE, pool)[:n]
    p = model.params
    params = jsnap.Params(
        E=jnp.asarray(E),
        nu=jnp.full(n, p.nu),
        rho=jnp.full(n, p.rho),
        alpha=jnp.full(n, p.alpha),
        beta=jnp.full(n, p.beta),
        friction=jnp.asarray(mu),
    )
    offsets = np.zeros((n, 3))
    offsets[:, 1] = dx
    return params, offsets


def scene_rollout(model, n_steps: int):
    """``(f, dyn)``: ``f(dyn, prepared, offset)`` is a ``lax.scan`` of ``jsnap.step`` over the
    first ``n_steps`` steps of the scene's motion for one scene, its plug shifted by ``offset``
    (3,) mm; it returns the insertion force (N), solver iterations and residual, each (steps,).
    ``dyn`` is the model's arrays in the scene's dtype (passed as an argument, not baked into
    the compiled program); ``prepared`` must be cast to that dtype too."""
    dtype = jnp.dtype(model.dtype)
    dyn, static = eqx.partition(cast_floats(model, dtype), eqx.is_array)
    controls = jnp.asarray(model.trajectory()[1 : 1 + n_steps], dtype)
    state0 = jsnap.init_state(model, dtype)
    T = jnp.asarray(model.dt, dtype)

    def f(dyn, prepared, offset):
        m = eqx.combine(dyn, static)
        offset = offset.astype(dtype)
        start = state0.plug + offset
        # As in jsnap.rollout, the plug starts moving with the drive.
        s = eqx.tree_at(
            lambda s: (s.plug, s.target, s.plug_vel), state0, (start, start, (controls[0] - state0.plug) / T)
        )

        def body(s, c):
            s, out = jsnap.step(m, prepared, s, c + offset)
            return s, (out.insertion_force, out.iterations, out.residual)

        return jax.lax.scan(body, s, controls)[1]

    return f, dyn


def prepare_batch(model, params):
    """``jsnap.prepare`` vmapped over batched Params, cast to the scene's dtype."""
    prepared = jax.jit(jax.vmap(lambda p: jsnap.prepare(model, p)))(params)
    return cast_floats(prepared, jnp.dtype(model.dtype))


def timed(fn, *args, runs: int = 3):
    """(outputs, first call seconds, median of ``runs`` further calls in seconds)."""
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return out, first, float(np.median(times))


def sweep(model, n_steps: int, batches, saturate: bool, max_call: float = np.inf) -> list[dict]:
    f, dyn = scene_rollout(model, n_steps)
    batched = jax.jit(jax.vmap(f, in_axes=(None, 0, 0)))
    rows, rates = [], []
    for B in batches:
        params, offsets = lanes(model, B)
        prepared = prepare_batch(model, params)
        (F, it, res), first, steady = timed(batched, dyn, prepared, jnp.asarray(offsets))
        rows.append(
            {
                "batch": B,
                "steps": n_steps,
                "seconds": steady,
                "compile_seconds": first - steady,
                "scene_steps_per_second": B * n_steps / steady,
                "us_per_scene_step": 1e6 * steady / (B * n_steps),
                "iterations_mean": float(np.mean(it)),
                "residual_max": float(np.max(res)),
                "peak_N_lanes": [float(x) for x in np.max(np.asarray(F), axis=1)[:8]],
                "insertion_force_lane0": np.asarray(F[0], np.float64).tolist(),
            }
        )
        print({k: v for k, v in rows[-1].items() if k != "insertion_force_lane0"}, flush=True)
        rates.append(rows[-1]["scene_steps_per_second"])
        flat = len(rates) >= 2 and rates[-1] < 1.05 * rates[-2]  # a 4x larger batch gained < 5 %
        if saturate and B >= 16 and flat:
            rows[-1]["stopped"] = "saturated"
            break
        if 2 * steady > max_call:  # the next batch would take too long per call
            rows[-1]["stopped"] = f"next call over {max_call:g} s"
            break
    return rows


def single(model, n_steps: int) -> dict:
    """One scene (lane 0), jitted without vmap: the solver's early exit works."""
    f, dyn = scene_rollout(model, n_steps)
    params, offsets = lanes(model, 1)
    prepared = jax.tree_util.tree_map(lambda a: a[0], prepare_batch(model, params))
    (F, it, _), first, steady = timed(jax.jit(f), dyn, prepared, jnp.asarray(offsets[0]))
    return {
        "batch": 1,
        "vmap": False,
        "steps": n_steps,
        "seconds": steady,
        "compile_seconds": first - steady,
        "scene_steps_per_second": n_steps / steady,
        "iterations_mean": float(np.mean(it)),
        "insertion_force_lane0": np.asarray(F, np.float64).tolist(),
    }


def machine(load) -> str:
    d = jax.devices()[0]
    return (
        f"{platform.machine()} {platform.system()}, {os.cpu_count()} CPU cores, jax {d.platform} "
        f"({d.device_kind}), load average {min(load):.1f}-{max(load):.1f}"
    )


def chart(result, title, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(13, 4.8))
    for (name, rows), color in zip(result["series"].items(), ("C0", "C1", "C3"), strict=False):
        B = [r["batch"] for r in rows]
        ax.loglog(B, [r["scene_steps_per_second"] for r in rows], "o-", color=color, label=f"vmap, {name}")
        bx.semilogx(B, [r["compile_seconds"] for r in rows], "o-", color=color, label=name)
    ref = result.get("single_scene")
    if ref:
        ax.axhline(ref["scene_steps_per_second"], color="C2", ls="--", label="one scene, no vmap (early exit)")
    ax.set_xscale("log", base=2)
    bx.set_xscale("log", base=2)
    ax.set_xlabel("batch size (scenes)")
    ax.set_ylabel("throughput (scene-steps/s)")
    ax.set_title("steady state, median of 3 calls", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    bx.set_xlabel("batch size (scenes)")
    bx.set_ylabel("compile time (s)")
    bx.set_title("compile time: first call minus a steady call", fontsize=10)
    bx.grid(alpha=0.3, which="both")
    bx.legend(fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _lane0_rmse(rows, ref_rows) -> float:
    """RMSE of lane 0's insertion force (batch 1) against the reference series', over its peak."""
    F = np.asarray(rows[0]["insertion_force_lane0"])
    F0 = np.asarray(ref_rows[0]["insertion_force_lane0"])
    return float(np.sqrt(np.mean((F - F0) ** 2)) / max(np.abs(F0).max(), 1e-12))


def main(argv=None):
    # The script jits and vmaps jsnap.step and jsnap.prepare in its own programs, which JAX
    # lowers in the caller's mode: 64-bit, as every computation here ran before the redesign
    # (importing jsnap no longer switches it on for the whole process).
    with jax.enable_x64(True):
        _main(argv)


def _main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="batches 1 and 4, 10 steps, default series only")
    ap.add_argument("--steps", type=int, default=20, help="steps of the motion per rollout")
    ap.add_argument("--max-batch", type=int, default=POOL)
    ap.add_argument("--max-call", type=float, default=30.0, help="seconds a timed call may take")
    ap.add_argument("--admm", action="store_true", help="a third series with the ADMM contact solver")
    ap.add_argument("--spg", action="store_true", help="a third series with the SPG contact solver")
    a = ap.parse_args(argv)
    if a.admm and a.spg:
        ap.error("--admm and --spg are alternatives: one extra series per run")
    extra = "admm" if a.admm else "spg" if a.spg else None
    if a.quick and extra:
        ap.error(f"--{extra} is a full run's extra series; it has no quick variant")
    t_start = time.perf_counter()
    code = code_version()  # the code as imported, before anyone commits during the run
    n_steps = 10 if a.quick else a.steps
    if a.quick:
        batches, series = [1, 4], dict(list(SERIES.items())[:1])
    else:
        # Every 4x (each batch size is a compile): the 30-minute budget of `jsnap bench`.
        batches = [4**k for k in range(10) if 4**k <= a.max_batch]
        series = {**SERIES, **(EXTRA_SERIES[extra] if extra else {})}
    load = [os.getloadavg()[0]]
    result = {"series": {}}
    for name, changes in series.items():
        model = jsnap.build(load_scene({**SCENE, **changes}))  # ADMM: an internal choice
        result["series"][name] = sweep(model, n_steps, batches, saturate=not a.quick, max_call=a.max_call)
        load.append(os.getloadavg()[0])
        if not changes:
            result["full_dof"], result["dof"] = model.full_dof, model.n_dof
            result["orders"] = [int(k) for k in model.part.orders]
            if not a.quick:
                result["single_scene"] = single(model, n_steps)
                print({k: v for k, v in result["single_scene"].items() if k != "insertion_force_lane0"})
    load.append(os.getloadavg()[0])
    dev = jax.devices()[0]
    result["machine"] = machine(load)
    result["device"] = f"{dev.platform} ({dev.device_kind})"

    names = list(result["series"])
    main_rows = result["series"][names[0]]
    best = max(main_rows, key=lambda r: r["scene_steps_per_second"])
    headline = {
        "device": result["device"],
        "full_dof": result["full_dof"],
        "dof": result["dof"],
        "steps": n_steps,
        "batch_1_scene_steps_per_second": main_rows[0]["scene_steps_per_second"],
        "best_batch": best["batch"],
        "best_scene_steps_per_second": best["scene_steps_per_second"],
        "max_batch": main_rows[-1]["batch"],
    }
    if "single_scene" in result:
        headline["single_scene_no_vmap_steps_per_second"] = result["single_scene"]["scene_steps_per_second"]
    if len(names) > 1:
        alt = result["series"][names[1]]
        best_alt = max(alt, key=lambda r: r["scene_steps_per_second"])
        headline["iterations_100_best_batch"] = best_alt["batch"]
        headline["iterations_100_best_scene_steps_per_second"] = best_alt["scene_steps_per_second"]
        # What the lower cap costs in accuracy on lane 0 (same parameters in both series).
        headline["iterations_100_force_rmse_rel_peak_lane0"] = _lane0_rmse(alt, main_rows)
    if extra:
        name = next(iter(EXTRA_SERIES[extra]))
        rows = result["series"][name]
        best_x = max(rows, key=lambda r: r["scene_steps_per_second"])
        headline.update(
            {
                f"{extra}_batch_1_scene_steps_per_second": rows[0]["scene_steps_per_second"],
                f"{extra}_best_batch": best_x["batch"],
                f"{extra}_best_scene_steps_per_second": best_x["scene_steps_per_second"],
                f"{extra}_iterations_mean_at_best": best_x["iterations_mean"],
                "apgd_iterations_mean_at_best": best["iterations_mean"],
                f"{extra}_force_rmse_rel_peak_lane0": _lane0_rmse(rows, main_rows),
            }
        )
        common = {r["batch"]: r for r in main_rows}
        headline[f"{extra}_speedup_by_batch"] = {
            str(r["batch"]): r["scene_steps_per_second"] / common[r["batch"]]["scene_steps_per_second"]
            for r in rows
            if r["batch"] in common
        }
    result["headline"] = headline
    result["wall_seconds"] = time.perf_counter() - t_start

    stem = "throughput_quick" if a.quick else f"throughput_{extra}" if extra else "throughput"
    OUT.mkdir(exist_ok=True)
    path = OUT / f"{stem}.json"
    results = {}
    if path.is_file():  # keep the other platforms' numbers
        try:
            results = json.loads(path.read_text()).get("results", {})
        except (json.JSONDecodeError, AttributeError):
            results = {}
    result["code"] = code
    results[dev.platform] = result
    # The top-level headline is the CPU one (this project's machine) when there is one; each
    # platform's own headline stays in results[platform] and a GPU's is also "headline_gpu".
    top = results.get("cpu", result)["headline"]
    doc = {
        "what": "batched rollout throughput of the reduced model (jax.vmap over scenes)",
        "scene": SCENE,
        "lanes": {"E_MPa": E_RANGE, "friction": MU_RANGE, "plug_offset_y_mm": OFFSET_RANGE, "pool": POOL},
        "note": NOTE,
        "headline": top,
        **({"headline_gpu": results["gpu"]["headline"]} if "gpu" in results else {}),
        "results": results,
    }
    path.write_text(json.dumps(doc, indent=1))
    title = (
        f"Batched throughput, Model 4 (reduced {result['full_dof']} → {result['dof']} dof, neural SDF, "
        f"float32), {n_steps} steps of the insertion per rollout\n"
        f"device: {result['device']}; {result['machine']}"
    )
    # The chart of the platform that ran (a GPU's beside the CPU's, not over it).
    chart(result, title, OUT / f"{stem}{'' if dev.platform == 'cpu' else '_' + dev.platform}.png")
    print(f"wrote {path} in {result['wall_seconds']:.0f} s", flush=True)


if __name__ == "__main__":
    main()
