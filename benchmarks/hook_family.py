"""The shipped default method on a family of hooks nobody tuned it for.

    python benchmarks/hook_family.py [--hooks 12] [--seed 20261127]

Hooks drawn over the design-guide ranges of length, root thickness, taper, width, undercut,
lead and return angle and friction (``jsnap._geometry.cantilever.draw_hooks``: a Latin
hypercube, one P2 element across the thinnest feature), plus the hook that once broke the
float32 reduced model (L 12, h 1.4, b 5, y_u 0.9 mm, lead 35°, friction 0.4, 0.7 mm). For each
hook: the full model in float64 (the reference) and float32 (from the same factorisation: how
far rounding alone moves the full model's peak, i.e. how well posed the peak is), and the
default method (the reduced model) in float32, as shipped, and float64. Recorded: dofs, orders,
peaks, every rollout's status, the reduced peaks' error against the full float64 peak, and the
curves. tests/test_hook_family.py asserts the same on four of them. Writes
benchmarks/results/hook_family.{json,png}.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
from _common import code_version

import jsnap
from jsnap._geometry.cantilever import NEARBY_HOOK, draw_hooks

jsnap.configure_xla_cpu()

OUT = Path(__file__).resolve().parent / "results"


def _rollout(model, dtype, **kw):
    res = jsnap.rollout(model, dtype=dtype, **kw)
    return np.asarray(res.insertion_force, np.float64), res.status()


def run(case: dict) -> dict:
    scene = jsnap.load_scene().replace(case)
    t0 = time.perf_counter()
    full = jsnap.build(scene.replace({"solver.method": "full", "solver.dtype": "float64"}))
    prepared = jsnap.prepare(full)
    F64, s64 = _rollout(full, "float64", prepared=prepared)
    F32, s32 = _rollout(full, "float32", prepared=prepared)
    t1 = time.perf_counter()
    reduced = jsnap.build(scene)
    R32, r32 = _rollout(reduced, "float32")
    R64, r64 = _rollout(reduced, "float64")
    t2 = time.perf_counter()
    peak = float(F64.max())
    return {
        "case": case,
        "full_dof": int(full.n_dof),
        "reduced_dof": int(reduced.n_dof),
        "orders": list(reduced.part.orders),
        "full_peak_N": peak,
        "full_float32_spread": float(abs(F32.max() / peak - 1)),
        "reduced_float32_error": float(R32.max() / peak - 1),
        "reduced_float64_error": float(R64.max() / peak - 1),
        "status": {"full_float64": s64, "full_float32": s32, "reduced_float32": r32, "reduced_float64": r64},
        "finite": bool(np.all(np.isfinite(R32)) and np.all(np.isfinite(R64))),
        "seconds": {"full": t1 - t0, "reduced": t2 - t1},
        "force": {"full_float64": F64.tolist(), "reduced_float32": R32.tolist()},
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hooks", type=int, default=12, help="hooks drawn (the nearby hook is added)")
    ap.add_argument("--seed", type=int, default=20261127)
    ap.add_argument("--from-json", action="store_true", help="summarise and chart the saved rows again")
    args = ap.parse_args(argv)
    if args.from_json:
        saved = json.loads((OUT / "hook_family.json").read_text())
        return write(saved["rows"], saved["seed"], saved["machine"], saved["code"])
    rows = []
    for i, case in enumerate([*draw_hooks(args.seed, args.hooks), NEARBY_HOOK]):
        row = run(case)
        rows.append(row)
        print(
            f"hook {i}: {row['full_dof']} -> {row['reduced_dof']} dof, full {row['full_peak_N']:.3f} N "
            f"(float32 spread {100 * row['full_float32_spread']:.2f} %), reduced float32 "
            f"{100 * row['reduced_float32_error']:+.2f} %, "
            f"float64 {100 * row['reduced_float64_error']:+.2f} %, "
            f"status {sorted(set(row['status'].values()))}",
            flush=True,
        )
    machine = {"platform": platform.platform(), "cpus": os.cpu_count(), "load": os.getloadavg()}
    return write(rows, args.seed, machine, code_version())


def write(rows, seed, machine, code) -> int:
    errors = np.array([[r["reduced_float32_error"], r["reduced_float64_error"]] for r in rows])
    spread = np.array([r["full_float32_spread"] for r in rows])
    within = np.abs(errors) <= (0.03 + spread)[:, None]
    headline = {
        "hooks": len(rows),
        # The default method's rollouts; the full model's float32 one is a yardstick only (the
        # full model's default dtype is float64).
        "default_method_all_ok": all(
            r["status"][k] == "ok" for r in rows for k in ("reduced_float32", "reduced_float64")
        ),
        "full_float64_all_ok": all(r["status"]["full_float64"] == "ok" for r in rows),
        "full_float32_flagged": [i for i, r in enumerate(rows) if r["status"]["full_float32"] != "ok"],
        "all_finite": all(r["finite"] for r in rows),
        "within_3_percent": int(np.sum(np.all(np.abs(errors) <= 0.03, axis=1))),
        "within_3_percent_plus_spread": int(np.sum(np.all(within, axis=1))),
        "max_abs_error_float32": float(np.abs(errors[:, 0]).max()),
        "max_abs_error_float64": float(np.abs(errors[:, 1]).max()),
        "median_abs_error_float32": float(np.median(np.abs(errors[:, 0]))),
        "max_full_float32_spread": float(spread.max()),
        "reduced_dof_range": [min(r["reduced_dof"] for r in rows), max(r["reduced_dof"] for r in rows)],
    }
    data = {
        "headline": headline,
        "seed": seed,
        "rows": rows,
        "machine": machine,
        "code": code,
    }
    OUT.mkdir(exist_ok=True)
    (OUT / "hook_family.json").write_text(json.dumps(data, indent=1))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(12, 4.5))
    x = np.arange(len(rows))
    ax[0].bar(x - 0.2, 100 * errors[:, 0], 0.4, label="reduced float32 (shipped)")
    ax[0].bar(x + 0.2, 100 * errors[:, 1], 0.4, label="reduced float64")
    ax[0].plot(x, 100 * spread, "k_", ms=14, label="full float32 spread (how well posed)")
    ax[0].plot(x, -100 * spread, "k_", ms=14)
    for s in (-3, 3):
        ax[0].axhline(s, color="0.6", lw=0.8, ls="--")
    ax[0].set_xticks(x, [f"{i}\nµ {r['case']['contact.friction']:.2f}" for i, r in enumerate(rows)], fontsize=7)
    ax[0].set_ylabel("peak error vs full float64 (%)")
    ax[0].set_title("default method on drawn hooks (last: the nearby hook)", fontsize=9)
    ax[0].legend(fontsize=7)
    worst = int(np.argmax(np.abs(errors[:, 0])))
    for i, style in ((0, "-"), (worst, "-")):
        r = rows[i]
        (line,) = ax[1].plot(r["force"]["full_float64"], style, lw=1.0, label=f"hook {i}: full float64")
        ax[1].plot(
            r["force"]["reduced_float32"],
            "--",
            lw=1.0,
            color=line.get_color(),
            label=f"hook {i}: reduced float32",
        )
    ax[1].set_xlabel("step")
    ax[1].set_ylabel("insertion force (N)")
    ax[1].legend(fontsize=7)
    ax[1].set_title("a smooth hook and the worst one", fontsize=9)
    fig.tight_layout()
    fig.savefig(OUT / "hook_family.png", dpi=110)
    print(json.dumps(headline, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
