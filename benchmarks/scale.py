"""Large parts: the reduced model's build time, peak memory and orders, and its step rate,
against the full model's size.

    python benchmarks/scale.py [--quick]

The default hook is built with the default method (reduced) and contact settings at P2 meshes
from ``solver.mesh_size`` 0.8 (5742 free dofs) to 0.25 (118 008), and the design guide's worked
example hook (L = 19, h = 3.28 tapered to 1.64, b = 9.5, y = 2.4 mm, polycarbonate, the
other keys the default scene's) at the default 0.8 mm (57 900). Each part is built and run in a fresh process
with an empty cache, so that its peak resident memory (``ru_maxrss``) is its own: the build's,
read when the build returns, and the whole run's (build, JAX compilation and rollouts). The step rate is that of
``jsnap.rollout`` (a ``lax.scan``) of the default motion, compile excluded: the median of
repeated compiled rollouts (``REPEATS``, over ``SPREAD_S`` seconds at least), in the reduced
model's default dtype (float32) and in float64. Where the float32 rollout is flagged, the
float64 rate is the one quoted. The design-guide hook's peak insertion force is compared
with the design-guide formula (``jsnap._apps.simulate.design_guide_force``); its full model is
not built (about 154 GiB of dense matrices: the build refuses it). Each rollout's flags are
recorded (``status``). The contact buffer is sized as ``jsnap simulate`` sizes it: the default
64 slots, widened where a first rollout drops candidates (``contact_capacity``; the
design-guide hook has 10 candidate lines across its 9.5 mm width, the default hook 5).

The default hook is built a second time at every mesh with ``solver.load_patch = PATCH``: the
contact load cases spread over Gaussian patches instead of single points, which keeps the
contact segment's order from growing with the mesh (docs/reduction.md). Each such row records
its curve against the point-load model's on the same mesh (``against_point_loads``: the
peaks' ratio and the RMS differences over the rise and the whole motion, in fractions of the
peak), and the headline's ``load_patch`` entry checks the targets on its largest part.

Targets: a ~100k-dof part reduced in at most 5 minutes and 8 GB, stepping at 1 kHz or more.
``--quick`` (CI) runs one coarse mesh, a few rollouts, no timing to quote. Writes
benchmarks/results/scale.{json,png} (``_quick`` with ``--quick``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

OUT = Path(__file__).parent / "results"
MESHES = [0.8, 0.5, 0.4, 0.3, 0.25]
QUICK_MESHES = [2.0]
# The same meshes with the contact load cases spread over patches (``solver.load_patch``, mm):
# the order then stays flat in the mesh (docs/reduction.md, "Point loads or patch loads").
PATCH = 0.2
GUIDE = {
    "connector.length": 19.0,
    "connector.thickness": 3.28,
    "connector.tip_thickness": 1.64,
    "connector.width": 9.5,
    "connector.undercut": 2.4,
    "material.youngs_modulus": 2350.0,
    "material.poissons_ratio": 0.38,
    "material.density": 1.2e-9,
}
REPEATS, SPREAD_S = (5, 51), 3.0
# The default rollout dtype of the reduced model, and float64 beside it.
DTYPES = ("float32", "float64")
QUICK_REPEATS, QUICK_SPREAD_S = (2, 2), 0.0
TARGETS = {"full_dof": 1e5, "build_seconds": 300.0, "peak_rss_gb": 8.0, "steps_per_second": 1e3}
# A child's stdout line that carries its result.
_MARK = "SCALE_RESULT "


def _maxrss_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux: kilobytes


def child(name: str, mesh_size: float, quick: bool) -> dict:
    """Build and run one part in this (fresh) process; the caller set JSNAP_CACHE empty."""
    import jax

    import jsnap
    from jsnap._apps.simulate import design_guide_force, run_sizing_buffer
    from jsnap._build.model import build_model

    jsnap.configure_xla_cpu()  # before the first JAX computation, as the other benchmarks
    changes = {
        "solver.mesh_size": mesh_size,
        **(GUIDE if name == "design_guide_hook" else {}),
        **({"solver.load_patch": PATCH} if name == "default_hook_patch" else {}),
    }
    scene = jsnap.load_scene().replace(changes)
    t0 = time.perf_counter()
    model, report = build_model(scene, progress=True)
    build_s = time.perf_counter() - t0
    build_rss = _maxrss_bytes()
    red = report.reduction
    prepared = jsnap.prepare(model)
    row = {
        "part": name,
        "mesh_size": mesh_size,
        "full_dof": report.full_dof,
        "tets": report.tets,
        "contact_points": report.contact_points,
        "orders": list(model.part.orders),
        "dof": model.n_dof,
        "build_seconds": build_s,
        "reduction_seconds": red["seconds"],
        "reduction": {k: red[k] for k in ("interface_nodes", "interface_shapes", "contact_nodes") if k in red}
        | {"segment_dof": red.get("segment_dof"), "contact_load_cases": red.get("contact_load_cases")},
        "build_peak_rss_bytes": build_rss,
        "default_dtype": model.dtype,
    }
    (least, most), spread = (QUICK_REPEATS, QUICK_SPREAD_S) if quick else (REPEATS, SPREAD_S)
    # The contact buffer as `jsnap simulate` sizes it: the default 64 slots, widened where a
    # rollout drops candidates (the design-guide hook's 9.5 mm width).
    widened_from = None
    for dtype in DTYPES:
        clock = {}

        def run(model, dtype=dtype, clock=clock):
            t0 = time.perf_counter()
            res = jsnap.rollout(model, prepared=prepared, dtype=dtype)
            jax.block_until_ready(res.energy)
            clock["first"] = time.perf_counter() - t0
            return res

        model, res, wider_from = run_sizing_buffer(scene, model, run)
        widened_from = widened_from or wider_from
        first = clock["first"]
        times, start = [], time.perf_counter()
        while len(times) < least or (time.perf_counter() - start < spread and len(times) < most):
            t0 = time.perf_counter()
            jax.block_until_ready(jsnap.rollout(model, prepared=prepared, dtype=dtype).energy)
            times.append(time.perf_counter() - t0)
        run_s = float(np.median(times))
        F = np.asarray(res.insertion_force, np.float64)
        row[dtype] = {
            "steps": int(F.size),
            "scan_steps_per_second": F.size / run_s,
            "scan_us_per_step_min": 1e6 * min(times) / F.size,
            "scan_rollouts": len(times),
            "compile_seconds": first - run_s,
            "peak_N": float(F.max()) if np.isfinite(F).all() else None,
            "ok": bool(res.ok),
            "status": res.status() if not res.ok else "ok",
            # The curve, to compare point and patch loads on the same mesh.
            "insertion_force_N": [round(float(f), 6) for f in F],
        }
    row["contact_capacity"], row["contact_capacity_widened_from"] = model.contact.capacity, widened_from
    row["peak_rss_bytes"] = _maxrss_bytes()
    # The step rate quoted: the default dtype's, or float64's where the default one's rollout
    # is flagged (its steps then run on non-finite states).
    quoted = model.dtype if row[model.dtype]["ok"] else "float64"
    row["quoted_dtype"] = quoted
    row["scan_steps_per_second"] = row[quoted]["scan_steps_per_second"]
    row["peak_N"] = row[quoted]["peak_N"]
    if name == "design_guide_hook":
        row["design_guide_N"] = design_guide_force(scene)
        row["peak_over_guide"] = None if row["peak_N"] is None else row["peak_N"] / row["design_guide_N"]
    return row


def _against(patch: dict, point: dict) -> dict:
    """The patch-load model's curve against the point-load model's on the same mesh (both
    reduced to the same tolerance, in the quoted dtype): the peaks' ratio, and the RMS
    difference over the rise (up to the point-load model's peak) and over the whole motion, as
    fractions of that peak."""
    dtype = point["quoted_dtype"]
    a = np.asarray(patch[dtype]["insertion_force_N"])
    b = np.asarray(point[dtype]["insertion_force_N"])
    top = int(np.argmax(b))
    return {
        "dtype": dtype,
        "peak_ratio": float(a.max() / b.max()),
        "rmse_rise_of_peak": float(np.sqrt(np.mean((a[: top + 1] - b[: top + 1]) ** 2)) / b.max()),
        "rmse_of_peak": float(np.sqrt(np.mean((a - b) ** 2)) / b.max()),
    }


def _spawn(name: str, mesh_size: float, quick: bool) -> dict:
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, JSNAP_CACHE=cache)
        args = [sys.executable, __file__, "--child", name, str(mesh_size)] + (["--quick"] if quick else [])
        t0 = time.perf_counter()
        proc = subprocess.run(args, env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t0
    sys.stdout.write(proc.stdout.replace(_MARK, ""))
    if proc.returncode != 0:
        sys.stderr.write(proc.stderr)
        raise RuntimeError(f"{name} at mesh_size {mesh_size}: the child process failed ({proc.returncode})")
    line = next(x for x in reversed(proc.stdout.splitlines()) if x.startswith(_MARK))
    row = json.loads(line[len(_MARK) :])
    row["process_seconds"] = wall
    return row


def _plot(rows, path, machine, quick):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 4, figsize=(19, 6.4))
    for part, marker in (("default_hook", "o-"), ("default_hook_patch", "^--"), ("design_guide_hook", "s")):
        sel = sorted((r for r in rows if r["part"] == part), key=lambda r: r["full_dof"])
        if not sel:
            continue
        n = [r["full_dof"] for r in sel]
        label = part.replace("_patch", f", load_patch {PATCH:g} mm").replace("_", " ")
        ax[0].plot(n, [r["reduction_seconds"] for r in sel], marker, label=f"{label}: reduction")
        ax[0].plot(n, [r["build_seconds"] for r in sel], marker, alpha=0.5, label=f"{label}: whole build")
        ax[1].plot(n, [r["build_peak_rss_bytes"] / 2**30 for r in sel], marker, label=f"{label}: build")
        rss = [r["peak_rss_bytes"] / 2**30 for r in sel]
        ax[1].plot(n, rss, marker, alpha=0.5, label=f"{label}: with rollouts")
        ax[2].plot(n, [sum(r["orders"]) for r in sel], marker, label=label)
        for dtype, alpha in zip(DTYPES, (1.0, 0.5), strict=True):
            ok = [r for r in sel if r[dtype]["ok"]]
            ax[3].plot(
                [r["full_dof"] for r in ok],
                [r[dtype]["scan_steps_per_second"] for r in ok],
                marker,
                alpha=alpha,
                label=f"{label}, {dtype} (valid rollouts)",
            )
    for a, title, unit, target in (
        (ax[0], "build time", "s", TARGETS["build_seconds"]),
        (ax[1], "peak resident memory", "GiB", TARGETS["peak_rss_gb"] * 1e9 / 2**30),
        (ax[2], "reduced order (all segments)", "coordinates", None),
        (ax[3], "reduced rollout (lax.scan)", "steps/s", TARGETS["steps_per_second"]),
    ):
        a.set_xscale("log")
        a.set_yscale("log")
        a.set_xlabel("full model free dofs")
        a.set_ylabel(unit)
        a.set_title(title)
        if target is not None:
            a.axhline(target, color="k", ls="--", lw=0.8, label="target")
        a.grid(True, which="both", alpha=0.3)
        # Below the panel: six or seven curves' legend inside it would cover them.
        a.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16))
    fig.suptitle(f"jsnap: reduced models of large parts{' (quick)' if quick else ''}. {machine}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one coarse mesh, few rollouts (CI)")
    ap.add_argument("--child", nargs=2, metavar=("PART", "MESH_SIZE"), help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        row = child(a.child[0], float(a.child[1]), a.quick)
        print(_MARK + json.dumps(row), flush=True)
        return
    sys.path.insert(0, str(Path(__file__).parent))
    from _common import code_version

    stem = "scale_quick" if a.quick else "scale"
    meshes = QUICK_MESHES if a.quick else MESHES
    jobs = [(part, h) for part in ("default_hook", "default_hook_patch") for h in meshes]
    if not a.quick:
        jobs.append(("design_guide_hook", 0.8))
    load = [os.getloadavg()]
    rows = []
    for name, h in jobs:
        rows.append(_spawn(name, h, a.quick))
        print({k: v for k, v in rows[-1].items() if k not in ("reduction", *DTYPES)}, flush=True)
    load.append(os.getloadavg())
    lo, hi = min(x[0] for x in load), max(x[0] for x in load)
    machine = f"{platform.machine()}, {os.cpu_count()} CPU cores, cpu, load average {lo:.1f}-{hi:.1f}"
    default = [r for r in rows if r["part"] == "default_hook"]
    largest = max(default, key=lambda r: r["full_dof"])
    patched = {r["mesh_size"]: r for r in rows if r["part"] == "default_hook_patch"}
    for r in default:
        if r["mesh_size"] in patched:
            patched[r["mesh_size"]]["against_point_loads"] = _against(patched[r["mesh_size"]], r)
    headline = {
        "largest_full_dof": largest["full_dof"],
        "largest_orders": largest["orders"],
        "largest_reduction_seconds": largest["reduction_seconds"],
        "largest_build_seconds": largest["build_seconds"],
        "largest_build_peak_rss_gb": largest["build_peak_rss_bytes"] / 1e9,
        "largest_peak_rss_gb": largest["peak_rss_bytes"] / 1e9,
        "largest_scan_steps_per_second": largest["scan_steps_per_second"],
        "largest_quoted_dtype": largest["quoted_dtype"],
        "float32_ok": {str(r["full_dof"]): r["float32"]["ok"] for r in default},
        "targets": TARGETS,
    }
    headline["targets_met"] = {
        "build_seconds": largest["build_seconds"] <= TARGETS["build_seconds"],
        "peak_rss_gb": largest["build_peak_rss_bytes"] / 1e9 <= TARGETS["peak_rss_gb"],
        "steps_per_second": largest["scan_steps_per_second"] >= TARGETS["steps_per_second"],
    }
    if patched:
        big = patched[max(patched)] if a.quick else patched[largest["mesh_size"]]
        headline["load_patch"] = {
            "patch_mm": PATCH,
            "largest_full_dof": big["full_dof"],
            "largest_orders": big["orders"],
            "largest_build_seconds": big["build_seconds"],
            "largest_build_peak_rss_gb": big["build_peak_rss_bytes"] / 1e9,
            "largest_scan_steps_per_second": big["scan_steps_per_second"],
            "largest_quoted_dtype": big["quoted_dtype"],
            "largest_against_point_loads": big.get("against_point_loads"),
            "float32_ok": {str(r["full_dof"]): r["float32"]["ok"] for r in patched.values()},
            "targets_met": {
                "build_seconds": big["build_seconds"] <= TARGETS["build_seconds"],
                "peak_rss_gb": big["build_peak_rss_bytes"] / 1e9 <= TARGETS["peak_rss_gb"],
                "steps_per_second": big["scan_steps_per_second"] >= TARGETS["steps_per_second"],
            },
        }
    guide = [r for r in rows if r["part"] == "design_guide_hook"]
    if guide:
        g = guide[0]
        headline["design_guide_hook"] = {
            k: g[k]
            for k in (
                "full_dof", "orders", "build_seconds", "build_peak_rss_bytes", "peak_N", "design_guide_N",
                "peak_over_guide", "scan_steps_per_second", "quoted_dtype",
            )
        }  # fmt: skip
    OUT.mkdir(exist_ok=True)
    (OUT / f"{stem}.json").write_text(
        json.dumps(
            {
                "machine": machine,
                # The machine is shared with other jobs: every timing is an upper bound of the
                # unloaded one.
                "load_average": {"start": list(load[0]), "end": list(load[1])},
                "shared_machine": True,
                "code": code_version(),
                "headline": headline,
                "rows": rows,
            },
            indent=1,
        )
    )
    _plot(rows, OUT / f"{stem}.png", machine, a.quick)
    print(json.dumps(headline, indent=1))


if __name__ == "__main__":
    main()
