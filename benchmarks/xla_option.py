"""``jsnap.configure_xla_cpu()`` measured: the shipped default scene's step rate with and without
it, side by side (what the opt-in buys, and what a program that does not opt in forgoes). It
sets XLA's small-loop option and XLA's own kernels for every operation; the second matters on
the contact-heavy presets, not here (``benchmarks/xla_kernels.py`` measures it on every preset).

    python benchmarks/xla_option.py [--quick] [--rounds N]

The scene is ``jsnap.load_scene()`` as shipped: the reduced model, float32 rollout, P2 0.8 mm,
the scene's contact settings (64 slots, APGD, up to 500 iterations). XLA reads its flags once
per process, so every measurement is a fresh process (this script with ``--child``): it imports
jsnap, calls ``jsnap.configure_xla_cpu()`` right after (``with``) or not (``without``, the
option and the own-kernels flag also taken out of the ``XLA_FLAGS`` it inherits: ``jsnap bench``
runs with them), builds the scene (the reduced basis from the jsnap cache after the first
build), prepares it, rolls it out once (compile) and times ``REPEATS`` further ``jsnap.rollout``
calls (``lax.scan``); its rate is their median. ``ROUNDS`` rounds each run both, in alternating
order, so that the shared machine's load falls on both alike; the rates reported are the medians
over the rounds, the speedup their ratio (each round's own ratio is kept too, and the same ratio
of each process's fastest rollout, which a burst of load on the shared machine disturbs less),
and the 1-minute load average is recorded before and after every process. The option compiles
the contact solver's loops into one kernel each; it does not change what they compute. To show
it, the first round's two processes also roll the scene out in float64 after their timings
(``max |dF|`` over the peak: round-off), and every round compares the two float32 peaks (float32
round-off of another compilation can move the snap, the force's drop, by a step, so the curves'
largest difference is no measure of it).

``--quick`` (CI): the 2.0 mm mesh, one round, three timed rollouts, no float64 rollout. Writes
benchmarks/results/xla_option{,_quick}.{json,png}.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from _common import code_version

from jsnap._apps.xla import LIBRARY_FLAG, SMALL_LOOP_BYTES, SMALL_LOOP_OPTION, without_xla_cpu_flags

OUT = Path(__file__).parent / "results"
ROUNDS, REPEATS = 6, 15  # an even number of rounds: each option goes first in half of them
QUICK_ROUNDS, QUICK_REPEATS = 1, 3
QUICK_CHANGES = {"solver.mesh_size": 2.0}
OPTIONS = ("with", "without")


def child(option: str, quick: bool, float64: bool) -> dict:
    """One measurement in this (fresh) process; its JSON is the last line of stdout."""
    import jsnap

    # The opt-in exactly as a program makes it: right after importing jsnap, before any
    # computation. "without" leaves XLA's default (the parent took the option out of XLA_FLAGS).
    how = jsnap.configure_xla_cpu() if option == "with" else "not called"

    import jax

    from jsnap._build.model import build_model

    scene = jsnap.load_scene().replace(QUICK_CHANGES if quick else {})
    t0 = time.perf_counter()
    model, report = build_model(scene)
    build_s = time.perf_counter() - t0
    prepared = jsnap.prepare(model)
    t0 = time.perf_counter()
    res = jsnap.rollout(model, prepared=prepared)
    jax.block_until_ready(res.energy)
    first = time.perf_counter() - t0
    times = []
    for _ in range(QUICK_REPEATS if quick else REPEATS):
        t0 = time.perf_counter()
        jax.block_until_ready(jsnap.rollout(model, prepared=prepared).energy)
        times.append(time.perf_counter() - t0)
    run_s = float(np.median(times))
    F = np.asarray(res.insertion_force, np.float64)
    F64 = None
    if float64:  # after the timings: the same scene in float64 (compiled anew)
        F64 = np.asarray(jsnap.rollout(model, prepared=prepared, dtype="float64").insertion_force).tolist()
    dev = jax.devices()[0]
    return {
        "option": option,
        "configure_xla_cpu": how,
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "small_loop_option": SMALL_LOOP_OPTION in os.environ.get("XLA_FLAGS", ""),
        "own_kernels": LIBRARY_FLAG in os.environ.get("XLA_FLAGS", ""),
        "device": f"jax {dev.platform}" + (f" ({dev.device_kind})" if dev.device_kind != dev.platform else ""),
        "method": model.method,
        "dtype": model.dtype,
        "full_dof": model.full_dof,
        "dof": model.n_dof,
        "orders": list(model.part.orders),
        "reduction_cached": bool((report.reduction or {}).get("cached", False)),
        "build_seconds": build_s,
        "steps": int(F.size),
        "first_call_seconds": first,
        "compile_seconds": first - run_s,
        "run_seconds": times,
        "steps_per_second": F.size / run_s,
        "steps_per_second_best": F.size / min(times),
        "us_per_step": 1e6 * run_s / F.size,
        "peak_N": float(F.max()),
        "ok": bool(res.ok),
        "iterations_mean": float(np.asarray(res.iterations).mean()),
        "insertion_force": F.tolist(),
        "insertion_force_float64": F64,
    }


def measure(option: str, quick: bool, float64: bool) -> dict:
    """One fresh process for ``option``, with the load average around it."""
    env = dict(os.environ)
    flags = without_xla_cpu_flags(env.get("XLA_FLAGS", ""))
    if flags:
        env["XLA_FLAGS"] = flags
    else:
        env.pop("XLA_FLAGS", None)
    # A compiled program loaded from JAX's cache would hide the compile time (and jsnap bench
    # switches the cache off for its scripts anyway).
    env["JAX_ENABLE_COMPILATION_CACHE"] = "false"
    argv = [sys.executable, str(Path(__file__).resolve()), "--child", option]
    argv += (["--quick"] if quick else []) + (["--float64"] if float64 else [])
    load_before = os.getloadavg()[0]
    t0 = time.perf_counter()
    run = subprocess.run(argv, env=env, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    if run.returncode != 0:
        sys.stderr.write(run.stdout + run.stderr)
        raise RuntimeError(f"xla_option: the {option!r} process failed (exit {run.returncode})")
    row = json.loads(run.stdout.strip().splitlines()[-1])
    row.update(load_average_before=load_before, load_average_after=os.getloadavg()[0], process_seconds=wall)
    return row


def chart(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h = result["headline"]
    rounds = result["rounds"]
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 4.6), gridspec_kw={"width_ratios": [1.4, 1]})
    k = np.arange(1, len(rounds) + 1)
    for option, color in (("with", "C0"), ("without", "C3")):
        rates = [r[option]["steps_per_second"] for r in rounds]
        label = f"{option} configure_xla_cpu(): median {h[option]['steps_per_second']:.0f} steps/s"
        ax.plot(k, rates, "o-", color=color, label=label)
        ax.axhline(h[option]["steps_per_second"], color=color, ls=":", lw=1)
    ax.set_xticks(k)
    ax.set_xlabel("round (each: one fresh process per option, order alternating)")
    ax.set_ylabel(f"steady rollout rate (steps/s; median of {result['repeats']} rollouts)")
    ax.set_ylim(0, None)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    ax.set_title(f"{result['scene_label']}", fontsize=9)
    speed = [r["speedup"] for r in rounds]
    bx.bar(k, speed, color="C2")
    bx.axhline(h["speedup"], color="k", ls="--", lw=1, label=f"ratio of the medians: ×{h['speedup']:.2f}")
    bx.axhline(
        h["speedup_fastest_rollouts"],
        color="C1",
        ls=":",
        lw=1.2,
        label=f"of the fastest rollouts: ×{h['speedup_fastest_rollouts']:.2f}",
    )
    bx.axhline(1.0, color="0.5", lw=0.7)
    for i, r in enumerate(rounds):
        bx.text(k[i], speed[i], f"load {r['load_average']:.1f}", ha="center", va="bottom", fontsize=7)
    bx.set_xticks(k)
    bx.set_xlabel("round")
    bx.set_ylabel("speedup with the option (×, steps/s over steps/s)")
    bx.grid(alpha=0.3, axis="y")
    bx.legend(fontsize=8, loc="lower right")
    bx.set_title("per round (1-minute load average over its two processes)", fontsize=9)
    fig.suptitle(
        f"jsnap.configure_xla_cpu() ({SMALL_LOOP_OPTION}={SMALL_LOOP_BYTES}, XLA's own kernels) on the "
        f"shipped default scene\n"
        f"{result['machine']}",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="2.0 mm mesh, one round, three rollouts (CI)")
    ap.add_argument("--rounds", type=int, default=None, help=f"rounds (default {ROUNDS}, quick {QUICK_ROUNDS})")
    ap.add_argument("--child", choices=OPTIONS, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--float64", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        print(json.dumps(child(a.child, a.quick, a.float64)))
        return 0
    t_start = time.perf_counter()
    code = code_version()
    n_rounds = a.rounds or (QUICK_ROUNDS if a.quick else ROUNDS)
    rounds = []
    loads = [os.getloadavg()[0]]
    for i in range(n_rounds):
        order = OPTIONS if i % 2 == 0 else OPTIONS[::-1]
        rows = {option: measure(option, a.quick, float64=i == 0 and not a.quick) for option in order}
        forces = {option: rows[option].pop("insertion_force") for option in OPTIONS}
        forces64 = {option: rows[option].pop("insertion_force_float64") for option in OPTIONS}
        if i == 0:  # the first round's curves go into the JSON
            kept = {"float32": forces, "float64": forces64 if not a.quick else None}
        w, wo = rows["with"], rows["without"]
        load = [
            w["load_average_before"],
            w["load_average_after"],
            wo["load_average_before"],
            wo["load_average_after"],
        ]
        loads += load
        rounds.append(
            {
                "order": list(order),
                **rows,
                "speedup": w["steps_per_second"] / wo["steps_per_second"],
                "peak_rel_diff": w["peak_N"] / wo["peak_N"] - 1,
                "load_average": float(np.mean(load)),
            }
        )
        print(
            f"round {i + 1}: with {w['steps_per_second']:.0f} steps/s, without {wo['steps_per_second']:.0f} "
            f"steps/s (×{rounds[-1]['speedup']:.2f}), load {rounds[-1]['load_average']:.1f}",
            flush=True,
        )
    w, wo = rounds[0]["with"], rounds[0]["without"]
    if not (w["small_loop_option"] and not wo["small_loop_option"]):
        raise RuntimeError(
            f"xla_option: the processes did not run as asked: {w['xla_flags']!r}, {wo['xla_flags']!r}"
        )
    headline = {
        option: {
            "steps_per_second": float(np.median([r[option]["steps_per_second"] for r in rounds])),
            "us_per_step": float(np.median([r[option]["us_per_step"] for r in rounds])),
            "compile_seconds": float(np.median([r[option]["compile_seconds"] for r in rounds])),
        }
        for option in OPTIONS
    }
    headline["speedup"] = headline["with"]["steps_per_second"] / headline["without"]["steps_per_second"]
    headline["speedup_by_round"] = [r["speedup"] for r in rounds]
    # Less sensitive to the shared machine's bursts: each process's fastest rollout.
    best = {o: float(np.median([r[o]["steps_per_second_best"] for r in rounds])) for o in OPTIONS}
    headline["fastest_rollout_steps_per_second"] = best
    headline["speedup_fastest_rollouts"] = best["with"] / best["without"]
    headline["rounds"] = n_rounds
    headline["full_dof"], headline["dof"], headline["orders"] = w["full_dof"], w["dof"], w["orders"]
    headline["dtype"] = w["dtype"]
    headline["float32_peak_max_rel_diff"] = max(abs(r["peak_rel_diff"]) for r in rounds)
    if kept["float64"] is not None:
        F, F0 = (np.asarray(kept["float64"][option]) for option in OPTIONS)
        headline["float64_force_max_abs_diff_rel_peak"] = float(np.abs(F - F0).max() / np.abs(F0).max())
    headline["load_average_range"] = [min(loads), max(loads)]
    headline["quick"] = a.quick
    mesh = QUICK_CHANGES["solver.mesh_size"] if a.quick else 0.8
    result = {
        "benchmark": "xla_option",
        "machine": (
            f"{platform.machine()} {platform.system()}, {os.cpu_count()} CPU cores, {w['device']}, "
            f"load average {min(loads):.1f}-{max(loads):.1f}"
        ),
        "shared_machine": True,
        "code": code,
        "scene_label": (
            f"shipped default scene{' (quick: 2.0 mm mesh)' if a.quick else ''}: {w['method']} "
            f"{w['full_dof']} → {w['dof']} dof (P2 {mesh:g} mm), {w['dtype']}, {w['steps']} steps"
        ),
        "option": f"{SMALL_LOOP_OPTION}={SMALL_LOOP_BYTES}",
        "repeats": QUICK_REPEATS if a.quick else REPEATS,
        "headline": headline,
        "rounds": rounds,
        "forces_round_1": kept,
        "wall_seconds": time.perf_counter() - t_start,
    }
    stem = "xla_option_quick" if a.quick else "xla_option"
    OUT.mkdir(exist_ok=True)
    (OUT / f"{stem}.json").write_text(json.dumps(result, indent=1))
    chart(result, OUT / f"{stem}.png")
    print(json.dumps(headline, indent=1), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
