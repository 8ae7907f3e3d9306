"""Contact solvers on the symmetric squeeze: APGD vs projected Gauss–Seidel.

A light rigid plug squeezed between two stiff latches (``symmetric_squeeze_problem``: 4
contacts per hook, μ = 0.3, dt = 1 ms) at several plug-to-hook mobility ratios, i.e. several
condition numbers of the Delassus matrix W. For each ratio and solver it records:

- the residual (``kkt_residual``) after every iteration / sweep, up to ``--iters``;
- iterations to ``--tol`` (or "not converged at N");
- the force error at that stop against a tight reference solve (max |Δγ| / max |γ|);
- wall time per solve at ``--tol`` (median of ``--repeats`` after ``.lower().compile()``).

Writes ``benchmarks/results/contact_squeeze.json`` and ``contact_squeeze.png``.

    python benchmarks/contact_squeeze.py            # ~30 s on 2 CPU cores
    python benchmarks/contact_squeeze.py --quick    # two ratios, shorter runs
"""

import argparse
import functools
import json
import platform
import time
from pathlib import Path

import jax
import matplotlib
import numpy as np

import jsnap
from jsnap._core.contact import solve_apgd, solve_pgs, symmetric_squeeze_problem

matplotlib.use("Agg")
import matplotlib.pyplot as plt

# XLA's small-loop option, before the first JAX computation (the committed timings have it).
jsnap.configure_xla_cpu()

RESULTS = Path(__file__).resolve().parent / "results"
SOLVERS = {"APGD": solve_apgd, "PGS": solve_pgs}


def machine():
    proc = platform.processor() or platform.machine()
    dev = jax.devices()[0]
    return f"{platform.node()} ({proc}, {dev.platform}: {dev.device_kind})"


def median_time(fn, args, repeats):
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def main(argv=None):
    # The problems and solves are float64: jsnap's kernels called directly run in JAX's 64-bit
    # mode, which importing jsnap no longer switches on for the whole process.
    with jax.enable_x64(True):
        _main(argv)


def _main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="two ratios, fewer iterations")
    ap.add_argument("--ratios", type=float, nargs="*", default=None, help="mobility ratios")
    ap.add_argument("--iters", type=int, default=None, help="iteration cap (both solvers)")
    ap.add_argument("--tol", type=float, default=1e-6)
    ap.add_argument("--repeats", type=int, default=None)
    ap.add_argument("--per-side", type=int, default=4, help="contacts per hook")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    STEM = "contact_squeeze_quick" if args.quick else "contact_squeeze"  # quick runs never overwrite full ones
    ratios = args.ratios or ([1e2, 1e3] if args.quick else [1e1, 1e2, 1e3, 1e4])
    iters = args.iters or (2000 if args.quick else 5000)
    repeats = args.repeats or (3 if args.quick else 7)

    problems = [symmetric_squeeze_problem(args.per_side, r, 0.3) for r in ratios]
    shape_args = (problems[0].W, problems[0].q, problems[0].mu, problems[0].mask)

    # One compiled function per solver and purpose; the problems share shapes, so ratios reuse
    # it. The traced run goes on to a tiny tol to draw the whole curve; the timed run stops at
    # --tol; the reference run is a tight, long APGD solve.
    compiled = {}
    compile_s = {}
    for name, solver in SOLVERS.items():
        t = time.perf_counter()
        trace_fn = jax.jit(functools.partial(solver, max_iters=iters, tol=1e-13, return_trace=True))
        solve_fn = jax.jit(functools.partial(solver, max_iters=iters, tol=args.tol))
        compiled[name] = (
            trace_fn.lower(*shape_args).compile(),
            solve_fn.lower(*shape_args).compile(),
        )
        compile_s[name] = time.perf_counter() - t
    reference = jax.jit(functools.partial(solve_apgd, max_iters=50000, tol=1e-13))

    records = []
    full_traces = {}
    for P in problems:
        pargs = (P.W, P.q, P.mu, P.mask)
        ref = np.asarray(reference(*pargs).gamma)
        rec = {
            "mobility_ratio": P.mobility_ratio,
            "condition_number": P.condition,
            "plug_mass_g": P.plug_mass * 1e6,
            "contacts": int(P.mask.sum()),
            "solvers": {},
        }
        for name in SOLVERS:
            traced, timed = compiled[name]
            _, trace = traced(*pargs)
            trace = np.asarray(trace)
            sol = timed(*pargs)
            its = int(sol.iterations)
            t = median_time(timed, pargs, repeats)
            err = np.abs(np.asarray(sol.gamma) - ref).max() / np.abs(ref).max()
            keep = np.unique(np.geomspace(1, len(trace), 300).astype(int)) - 1
            full_traces[(P.mobility_ratio, name)] = trace
            rec["solvers"][name] = {
                "converged": bool(sol.converged),
                "iterations_to_tol": its if bool(sol.converged) else f"not converged at {its}",
                "residual_at_stop": float(sol.residual),
                "force_rel_error_at_stop": float(err),
                "solve_ms_median": 1e3 * t,
                "us_per_iteration": 1e6 * t / max(its, 1),
                # From the trace (the curve's solve runs to 1e-13): first iteration at or below.
                "iterations_to": {
                    f"{lvl:g}": (int(np.argmax(trace <= lvl)) + 1 if (trace <= lvl).any() else None)
                    for lvl in (1e-4, 1e-6, 1e-8, 1e-10)
                },
                # Subsampled (log-spaced iterations) to keep the JSON small; the plot uses all.
                "trace_iterations": [int(i) + 1 for i in keep],
                "trace_residual": [float(f"{trace[i]:.4g}") for i in keep],
            }
            print(
                f"ratio {P.mobility_ratio:8.0f}  cond {P.condition:9.3g}  {name:4s}  "
                f"{rec['solvers'][name]['iterations_to_tol']!s:>22}  "
                f"r {float(sol.residual):.2e}  force err {err:.1e}  {1e3 * t:8.3f} ms"
            )
        records.append(rec)

    out = {
        "benchmark": "contact_squeeze",
        "machine": machine(),
        "jax": jax.__version__,
        "dtype": "float64",
        "tol": args.tol,
        "iteration_cap": iters,
        "repeats": repeats,
        "compile_s": compile_s,
        "residual": "kkt_residual: natural map, step 1/L, relative to the force scale",
        "problems": records,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{STEM}.json").write_text(json.dumps(out, indent=1))

    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    colors = plt.cm.viridis(np.linspace(0, 0.85, len(records)))
    for rec, c in zip(records, colors, strict=True):
        for name, ls in (("APGD", "-"), ("PGS", "--")):
            tr = full_traces[(rec["mobility_ratio"], name)]
            ratio, cond = rec["mobility_ratio"], rec["condition_number"]
            label = f"{name}, mobility ratio {ratio:.0e} (cond {cond:.1e})"
            ax.semilogy(np.arange(1, len(tr) + 1), np.maximum(tr, 1e-16), ls, color=c, label=label)
    ax.axhline(args.tol, color="k", lw=0.8, ls=":", label=f"tol = {args.tol:g}")
    ax.set_xlabel("iteration (APGD) / sweep (PGS)")
    ax.set_ylabel("KKT residual (natural map, dimensionless)")
    ax.set_title(
        f"Symmetric squeeze, {records[0]['contacts']} contacts, μ = 0.3, float64\n{machine()}",
        fontsize=9,
    )
    ax.legend(fontsize=7, loc="upper right")
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(args.out / f"{STEM}.png", dpi=130)
    print(f"wrote {args.out / (STEM + '.json')} and {STEM}.png")


if __name__ == "__main__":
    main()
