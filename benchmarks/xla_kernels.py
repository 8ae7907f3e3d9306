"""XLA:CPU's library kernels measured: every preset's step rate with XLA's YNNPACK fusions (its
default) and with XLA's own kernels for every operation (``jsnap.configure_xla_cpu()``), side by
side in fresh processes.

    python benchmarks/xla_kernels.py [--quick] [--rounds N]

XLA:CPU hands some operations to the YNNPACK library: matrix products and reductions, each
then a library call on the runtime's thread pool. A contact step is hundreds of such operations
on small arrays (the 1822 candidate points' signed distances reduced over their three
coordinates, a 96 x 138 by 138 x 96 Delassus product), where a library call costs more than the
arithmetic. ``--xla_cpu_experimental_ynn_fusion_type=`` (an empty list) keeps every operation
in XLA's own kernels.

Every measurement is a fresh process (XLA reads its flags once per process), this script with
``--child``: ``library`` sets XLA's small-loop option only
(``jsnap._apps.xla.with_small_loop_option``; XLA keeps its default library fusions), ``own``
calls ``jsnap.configure_xla_cpu()``. Each process builds every case (the reduced bases from the
jsnap cache), rolls each out once (compile) and times ``REPEATS`` further rollouts
(``lax.scan``); its rate is their median. The cases: each shipped preset's scene as shipped
(reduced model, float32) and a batch of ``BATCH`` default-scene rollouts
(``jsnap.rollout_batch``, scene-steps/s). ``ROUNDS`` rounds each run both options, the order
alternating, so that the shared machine's load falls on both alike; the rates reported are
medians over the rounds, the speedup their ratio. Both options compute the same forces but for
round-off: each case's peak under both is recorded.

``--quick`` (CI): the default scene and the two-hook clip at a 2.0 mm mesh, one round, three
timed rollouts, no batch. Writes benchmarks/results/xla_kernels{,_quick}.{json,png}.
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
from _common import LID_DEFAULT_SAMPLING, code_version, write_result

from jsnap._apps.xla import with_small_loop_option, without_xla_cpu_flags
from jsnap._geometry.scene import default_scene_path

OUT = Path(__file__).parent / "results"
SCENES = default_scene_path().parent
ROUNDS, REPEATS, BATCH = 3, 5, 32
QUICK_ROUNDS, QUICK_REPEATS = 1, 3
PRESETS = ("default", "two_hook_clip", "box_lid", "annular", "cable_latch")
QUICK_PRESETS = ("default", "two_hook_clip")
OPTIONS = ("library", "own")


def _cases(quick: bool) -> list[tuple[str, str, dict, int]]:
    """(name, scene file, changes, batch) of every case measured."""
    changes = {"solver.mesh_size": 2.0} if quick else {}
    # The box lid at the other presets' contact sampling (_common.LID_DEFAULT_SAMPLING).
    own = {"box_lid": LID_DEFAULT_SAMPLING}
    cases = [
        (p, str(SCENES / f"{p}.toml"), {**own.get(p, {}), **changes}, 0)
        for p in (QUICK_PRESETS if quick else PRESETS)
    ]
    if not quick:
        cases.append((f"default x{BATCH}", str(SCENES / "default.toml"), {}, BATCH))
    return cases


def child(option: str, quick: bool) -> dict:
    """One measurement of every case in this (fresh) process; its JSON is the last line."""
    import jsnap

    how = jsnap.configure_xla_cpu() if option == "own" else "not called"

    import jax
    import jax.numpy as jnp

    rows = {}
    for name, path, changes, batch in _cases(quick):
        model = jsnap.build(jsnap.load_scene(path).replace(changes))
        prepared = jsnap.prepare(model)

        if batch:
            params = model.params.replace(E=jnp.linspace(0.9, 1.1, batch) * model.params.E)

            def run():
                return jsnap.rollout_batch(model, params)

        else:

            def run():
                return jsnap.rollout(model, prepared=prepared)

        res = run()
        jax.block_until_ready(res.energy)
        times = []
        for _ in range(QUICK_REPEATS if quick else REPEATS):
            t0 = time.perf_counter()
            jax.block_until_ready(run().energy)
            times.append(time.perf_counter() - t0)
        F = np.asarray(res.insertion_force, np.float64)
        steps = F.size
        rows[name] = {
            "full_dof": model.full_dof,
            "dof": int(model.n_dof),
            "method": model.method,
            "batch": batch,
            "scene_steps": steps,
            "run_seconds": times,
            "steps_per_second": steps / float(np.median(times)),
            "peak_N": float(F.max()),
            "ok": bool(np.all(np.asarray(res.ok))),
        }
    return {
        "option": option,
        "configure_xla_cpu": how,
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "cases": rows,
    }


def measure(option: str, quick: bool) -> dict:
    """One fresh process for ``option``, with the load average around it."""
    env = dict(os.environ)
    flags = without_xla_cpu_flags(env.get("XLA_FLAGS", ""))
    if option == "library":
        flags = with_small_loop_option(flags)
    if flags:
        env["XLA_FLAGS"] = flags
    else:
        env.pop("XLA_FLAGS", None)
    env["JAX_ENABLE_COMPILATION_CACHE"] = "false"
    argv = [sys.executable, str(Path(__file__).resolve()), "--child", option] + (["--quick"] if quick else [])
    load_before = os.getloadavg()[0]
    t0 = time.perf_counter()
    run = subprocess.run(argv, env=env, capture_output=True, text=True, check=False)
    if run.returncode != 0:
        sys.stderr.write(run.stdout + run.stderr)
        raise RuntimeError(f"xla_kernels: the {option!r} process failed (exit {run.returncode})")
    row = json.loads(run.stdout.strip().splitlines()[-1])
    row.update(load_average_before=load_before, load_average_after=os.getloadavg()[0])
    row["process_seconds"] = time.perf_counter() - t0
    return row


def headline(rounds: list[dict], names: list[str]) -> dict:
    out = {}
    for name in names:
        rate = {o: float(np.median([r[o]["cases"][name]["steps_per_second"] for r in rounds])) for o in OPTIONS}
        peaks = {o: [r[o]["cases"][name]["peak_N"] for r in rounds] for o in OPTIONS}
        first = rounds[0]["library"]["cases"][name]
        out[name] = {
            "full_dof": first["full_dof"],
            "dof": first["dof"],
            "method": first["method"],
            "batch": first["batch"],
            "library_steps_per_second": rate["library"],
            "own_steps_per_second": rate["own"],
            "speedup": rate["own"] / rate["library"],
            "speedup_per_round": [
                r["own"]["cases"][name]["steps_per_second"] / r["library"]["cases"][name]["steps_per_second"]
                for r in rounds
            ],
            "peak_N": {o: float(np.median(peaks[o])) for o in OPTIONS},
            "peak_rel_diff": abs(np.median(peaks["own"]) / np.median(peaks["library"]) - 1.0),
            "ok": all(r[o]["cases"][name]["ok"] for r in rounds for o in OPTIONS),
        }
    return out


def chart(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h = result["headline"]
    names = list(h)
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 4.6), gridspec_kw={"width_ratios": [1.5, 1]})
    x = np.arange(len(names))
    for k, (option, color, label) in enumerate(
        (
            ("library", "C3", "YNNPACK fusions (XLA's default)"),
            ("own", "C0", "XLA's own kernels (configure_xla_cpu)"),
        )
    ):
        rates = [h[n][f"{option}_steps_per_second"] for n in names]
        ax.bar(x + (k - 0.5) * 0.4, rates, 0.4, color=color, label=label)
    ax.axhline(1000, color="0.4", ls=":", lw=1)
    ax.set_yscale("log")
    ax.set_xticks(x)
    ax.set_xticklabels(names, rotation=20, fontsize=8)
    ax.set_ylabel("steps/s (scene-steps/s for the batch; median over rounds)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="y")
    for i, n in enumerate(names):
        sp = h[n]["speedup_per_round"]
        bx.plot([i] * len(sp), sp, "o", color="0.5", ms=4)
        bx.plot(i, h[n]["speedup"], "D", color="C2", ms=7)
    bx.axhline(1.0, color="0.4", lw=0.8)
    bx.set_xticks(x)
    bx.set_xticklabels(names, rotation=20, fontsize=8)
    bx.set_ylabel("own / library (diamond: ratio of medians; dots: rounds)")
    bx.grid(alpha=0.3, axis="y")
    fig.suptitle(
        f"XLA:CPU's library fusions against its own kernels, {result['rounds_run']} rounds in fresh "
        f"processes\n{result['machine']}",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--rounds", type=int, default=None)
    ap.add_argument("--child", choices=OPTIONS, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(child(args.child, args.quick)))
        return
    n_rounds = args.rounds or (QUICK_ROUNDS if args.quick else ROUNDS)
    rounds = []
    for i in range(n_rounds):
        order = OPTIONS if i % 2 == 0 else OPTIONS[::-1]
        r = {o: measure(o, args.quick) for o in order}
        rounds.append(r)
        pairs = {n: (r["library"]["cases"][n], r["own"]["cases"][n]) for n in r["library"]["cases"]}
        line = ", ".join(
            f"{n} {a['steps_per_second']:.0f} -> {b['steps_per_second']:.0f}" for n, (a, b) in pairs.items()
        )
        print(f"round {i + 1}: {line}", flush=True)
    names = list(rounds[0]["library"]["cases"])
    loads = [r[o][k] for r in rounds for o in OPTIONS for k in ("load_average_before", "load_average_after")]
    result = {
        "quick": args.quick,
        "rounds_run": n_rounds,
        "repeats": QUICK_REPEATS if args.quick else REPEATS,
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, load average "
        f"{min(loads):.1f}-{max(loads):.1f}",
        "load_average_range": [min(loads), max(loads)],
        "headline": headline(rounds, names),
        "rounds": rounds,
        "code": code_version(),
    }
    stem = "xla_kernels_quick" if args.quick else "xla_kernels"
    write_result(result, OUT / f"{stem}.json")
    chart(result, OUT / f"{stem}.png")
    for n, v in result["headline"].items():
        a, b = v["library_steps_per_second"], v["own_steps_per_second"]
        print(f"{n}: {a:.0f} -> {b:.0f} steps/s (x{v['speedup']:.2f})")


if __name__ == "__main__":
    main()
