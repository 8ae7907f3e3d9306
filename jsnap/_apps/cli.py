"""Command line: ``jsnap simulate [SCENE.toml] [--out DIR] [--json]``, ``jsnap train-sdf [MESH]``,
``jsnap fit SCENE.toml MEASURED.csv [--fit E,friction,...] [--out DIR] [--json]``, ``jsnap bench``,
``jsnap cache [--clear [FOLDER ...]] [--json]``.

``simulate``, ``train-sdf`` and ``fit`` keep JAX's compiled programs in the jsnap cache, so that
a scene's second run skips most of its compilation (see the README's "Caches"; off with
JSNAP_XLA_CACHE=0)."""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np


def design_guide_force(scene) -> float:
    """Snap-fit design-guide mating force W = P (mu + tan a) / (1 - mu tan a), N.

    P = b h^2 E eps / (6 L) with eps = 1.5 h y / L^2 (constant arm) or h y / (1.09 L^2) (arm
    tapered to h/2); a beam-theory estimate (see docs/validation.md for how far it is off).
    """
    c, m = scene["connector"], scene["material"]
    L, h, b, y = c["length"], c["thickness"], c["width"], c["undercut"]
    h_tip = c["tip_thickness"] or h
    eps = y * h / (1.09 * L**2) if abs(h_tip - h / 2) < 1e-9 else 1.5 * h * y / L**2
    P = b * h**2 * m["youngs_modulus"] * eps / (6 * L)
    mu, ta = scene["contact"]["friction"], math.tan(math.radians(c["lead_angle"]))
    return P * (mu + ta) / (1 - mu * ta)


def _plot(res, out: Path, guide: float, title: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    travel = np.asarray(res.travel)
    t = np.asarray(res.t) * 1e3
    fig, ax = plt.subplots(1, 2, figsize=(12, 4.5))
    for a, xv, xl in ((ax[0], travel, "plug travel along -z (mm)"), (ax[1], t, "time (ms)")):
        a.plot(xv, np.asarray(res.insertion_force), label="insertion force (N)", lw=1.6)
        a.plot(
            xv,
            np.linalg.norm(np.asarray(res.base_force), axis=1),
            label="|base force| (N)",
            lw=1.0,
            alpha=0.8,
        )
        a.plot(
            xv,
            np.asarray(res.lateral_force),
            label="lateral force on plug, x (N)",
            lw=1.0,
            alpha=0.8,
        )
        a.axhline(guide, color="k", ls="--", lw=0.8, label=f"design-guide mating force {guide:.2f} N")
        a.axhline(0, color="0.6", lw=0.5)
        a.set_xlabel(xl)
        a.set_ylabel("force (N)")
        a.grid(alpha=0.3)
    F = np.asarray(res.insertion_force)
    k, j = int(F.argmax()), int(F.argmin())
    marks = [(k, f"peak {F[k]:.2f} N at {travel[k]:.2f} mm", (8, 10), "left")]
    if F[j] < -0.05 * F[k] and j > k:
        marks.append((j, f"snap: hook pulls\nthe plug in, {F[j]:.2f} N", (10, 0), "left"))
    for i, text, offset, ha in marks:
        ax[0].annotate(
            text,
            (travel[i], F[i]),
            xytext=offset,
            textcoords="offset points",
            fontsize=8,
            ha=ha,
            va="center",
            arrowprops=dict(arrowstyle="-", lw=0.6),
        )
    ax[0].axvspan(0, travel[k], color="C0", alpha=0.04, lw=0)
    ax[0].text(0.5 * travel[k], 0.97, "ramp", transform=ax[0].get_xaxis_transform(), ha="center", fontsize=8)
    ax[0].legend(fontsize=8, loc="lower left")
    fig.suptitle(title)
    fig.tight_layout()
    path = out / "forces.png"
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def simulate(args) -> int:
    import jax

    import jsnap
    from jsnap._geometry.cantilever import write_vtu_series

    t0 = time.perf_counter()
    scene = jsnap.load_scene(args.scene)
    if args.method:
        scene = scene.replace({"solver.method": args.method})
    quiet = args.json
    model = jsnap.build(scene, progress=not quiet)
    t_build = time.perf_counter() - t0
    prepared = jsnap.prepare(model)
    res = jsnap.rollout(model, keep_x=True, progress=True, prepared=prepared)  # bar on stderr
    jax.block_until_ready(res.energy)
    t_total = time.perf_counter() - t0
    # Steady-state stepping rate, compile excluded: re-run a few chunks of the size the progress
    # run compiled (cached), rather than the whole motion again.
    from jsnap._core.step import progress_chunk

    n = model.n_steps
    chunk = progress_chunk(n)
    controls = model.trajectory()[1 : 1 + chunk]
    reps = max(1, min(5, n // chunk))
    t1 = time.perf_counter()
    for _ in range(reps):
        jax.block_until_ready(jsnap.rollout(model, controls=controls, keep_x=True, prepared=prepared).energy)
    t_run = (time.perf_counter() - t1) / (reps * chunk) * n

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    F = np.asarray(res.insertion_force)
    base = np.asarray(res.base_force)
    cols = np.column_stack(
        [
            np.asarray(res.t),
            np.asarray(res.travel),
            F,
            np.asarray(res.lateral_force),
            base,
            np.asarray(res.base_moment),
            np.asarray(res.coupling_force),
            np.asarray(res.energy),
        ]
    )
    header = (
        "t_s,travel_mm,insertion_force_N,lateral_force_N,base_fx_N,base_fy_N,base_fz_N,"
        "base_mx_Nmm,base_my_Nmm,base_mz_Nmm,coupling_fx_N,coupling_fy_N,coupling_fz_N,"
        "energy_Nmm"
    )
    np.savetxt(out / "forces.csv", cols, delimiter=",", header=header, comments="", fmt="%.8g")
    guide = design_guide_force(scene)
    _plot(
        res,
        out,
        guide,
        f"jsnap: {Path(scene.source).name}, {scene['solver']['element']}, "
        f"{model.n_dof} dof, dt = {model.dt * 1e3:g} ms",
    )
    asm = model.host.assembly
    disp = np.zeros((F.size, asm.n_dof))
    disp[:, model.host.free] = np.asarray(jax.vmap(model.socket.free_displacement)(res.x))
    every = max(1, F.size // 100)
    pvd = write_vtu_series(
        out / "vtu",
        "socket",
        asm.nodes,
        asm.cells,
        disp[::every].reshape(-1, asm.nodes.shape[0], 3),
        np.asarray(res.t)[::every],
    )
    warnings = []
    if int(np.max(np.asarray(res.overflow))) > 0:
        warnings.append(
            f"contact buffer overflowed (up to {int(np.max(res.overflow))} candidate "
            "points dropped): raise contact.capacity"
        )
    bad = np.asarray(res.residual) > 100 * scene["contact"]["tolerance"]
    if bad.any():
        warnings.append(f"contact solver did not converge in {int(bad.sum())} steps: raise contact.iterations")
    summary = {
        "scene": scene.source,
        "steps": int(F.size),
        "dt": model.dt,
        "method": model.method,
        "element": scene["solver"]["element"],
        "dof": model.n_dof,
        "full_dof": int(model.host.free.size),
        "reduced_orders": list(getattr(model.socket, "orders", ())),  # per segment, contact first
        "contact_points": model.n_samples,
        "steps_per_second": F.size / t_run,
        "build_seconds": t_build,
        "total_seconds": t_total,
        "peak_insertion_force_N": float(F.max()),
        "travel_at_peak_mm": float(np.asarray(res.travel)[F.argmax()]),
        "peak_base_force_N": float(np.linalg.norm(base, axis=1).max()),
        "design_guide_mating_force_N": guide,
        "min_insertion_force_N": float(F.min()),
        "max_contact_overflow": int(np.max(np.asarray(res.overflow))),
        "max_solver_residual": float(np.max(np.asarray(res.residual))),
        "outputs": {
            "csv": str(out / "forces.csv"),
            "png": str(out / "forces.png"),
            "pvd": str(pvd),
        },
        "warnings": warnings,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    if args.json:
        print(json.dumps(summary))
    else:
        for w in warnings:
            print(f"jsnap: warning: {w}", file=sys.stderr)
        print(
            f"jsnap: {F.size} steps, peak insertion force {F.max():.3f} N at "
            f"{summary['travel_at_peak_mm']:.3f} mm (design guide {guide:.3f} N); "
            f"{summary['steps_per_second']:.0f} steps/s; wrote {out}/"
        )
    return 0


# NeuralSDFConfig fields settable from `jsnap train-sdf`.
_SDF_SETTINGS = {
    "width": int,
    "depth": int,
    "activation": str,
    "steps": int,
    "batch": int,
    "samples": int,
    "seed": int,
}


def train_sdf(args) -> int:
    """``jsnap train-sdf [MESH]``: train (or load from the cache) the neural SDF of a plug."""
    from jsnap._build import neural_sdf as nsdf

    try:
        settings = {k: getattr(args, k) for k in _SDF_SETTINGS if getattr(args, k) is not None}
        config = nsdf.NeuralSDFConfig(**settings)
        if args.mesh is None:
            import jsnap
            from jsnap._build.model import _plug_geometry
            from jsnap._geometry.scene import connector_geometry
            from jsnap._core.sdf import rounded_box_mesh

            scene = jsnap.load_scene(args.scene)
            half, radius, _ = _plug_geometry(scene, connector_geometry(scene))
            mesh = rounded_box_mesh(half, radius)
            what = f"the plug of {scene.source}"
        else:
            mesh = nsdf.load_mesh(args.mesh)
            what = args.mesh
        net, info = nsdf.load_or_train(mesh, config, progress=not args.json, retrain=args.retrain)
    except (ValueError, FileNotFoundError) as err:
        print(f"jsnap: error: {err}", file=sys.stderr)
        return 2
    if args.out:
        nsdf.save(
            net,
            args.out,
            key=info["key"],
            mesh_hash=info["mesh_hash"],
            config=config,
            extra=dict(report=info["report"], seconds=info["seconds"]),
        )
    r = info["report"]
    summary = dict(
        mesh=what,
        triangles=len(mesh.faces),
        cached=info["cached"],
        train_seconds=info["seconds"],
        weights=str(info["path"]),
        out=args.out,
        architecture=config.architecture,
        accuracy=r,
    )
    if args.json:
        print(json.dumps(summary))
        return 0
    how = "loaded from the cache" if info["cached"] else f"trained in {info['seconds']:.1f} s"
    print(f"jsnap: neural SDF of {what} ({len(mesh.faces)} triangles): {how}")
    print(f"  weights: {info['path']}" + (f" (copied to {args.out})" if args.out else ""))
    if r:
        print(
            f"  accuracy vs the exact mesh SDF over |phi| <= {r['band_mm']:g} mm ({r['points']} points): "
            f"mean |error| {r['mae_mm']:.2e} mm (p95 {r['p95_mm']:.2e}, max {r['max_mm']:.2e}); "
            f"normal error median {r['normal_median_deg']:.2f} deg (p95 {r['normal_p95_deg']:.1f})"
        )
    return 0


def _size(n: int) -> str:
    return f"{n / 1e6:.1f} MB" if n >= 1e5 else f"{n / 1e3:.0f} kB"


def cache_command(args) -> int:
    """``jsnap cache [--clear [FOLDER ...]] [--json]``: what the cache holds; remove it."""
    from jsnap._build import cache as _cache

    if args.clear is not None:
        try:
            removed = _cache.clear(args.clear or None)
        except ValueError as err:
            print(f"jsnap: error: {err}", file=sys.stderr)
            return 2
        if args.json:
            print(json.dumps({"cache": str(_cache.cache_dir()), "removed_bytes": removed}))
        else:
            for kind, n in removed.items():
                print(f"jsnap cache: removed {kind} ({_size(n)})")
        return 0
    use = _cache.usage()
    if args.json:
        print(json.dumps({"cache": str(_cache.cache_dir()), "folders": use}))
        return 0
    print(f"jsnap cache: {_cache.cache_dir()} ($JSNAP_CACHE or ~/.cache/jsnap)")
    for kind, u in use.items():
        what = _cache.KINDS[kind]
        print(f"  {kind:11s} {u['files']:5d} files {_size(u['bytes']):>9s}  {what}")
    print(f"  total {_size(sum(u['bytes'] for u in use.values())):>27s}")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="jsnap", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    sim = sub.add_parser("simulate", help="run a scene (default: the shipped default scene)")
    sim.add_argument("scene", nargs="?", default=None, help="scene TOML file")
    sim.add_argument("--method", choices=["full", "modal", "segmented", "reduced"], default=None)
    sim.add_argument("--out", default="jsnap-out", help="output directory (default jsnap-out)")
    sim.add_argument("--json", action="store_true", help="print a JSON summary to stdout")
    tr = sub.add_parser("train-sdf", help="train the neural SDF of a plug mesh (cached)")
    tr.add_argument("mesh", nargs="?", default=None, help="closed STL/OBJ/PLY, mm (default: the scene's plug)")
    tr.add_argument("--scene", default=None, help="scene whose plug to use when no MESH (default scene)")
    tr.add_argument("--out", default=None, help="also write the weights to this .npz file")
    tr.add_argument("--retrain", action="store_true", help="train even if cached weights exist")
    tr.add_argument("--json", action="store_true", help="print a JSON summary to stdout")
    for name, kind in _SDF_SETTINGS.items():
        tr.add_argument(f"--{name}", type=kind, default=None, help="training setting (see docs/neural_sdf.md)")
    bench = sub.add_parser("bench", help="run benchmarks/ scripts and regenerate benchmarks/README.md")
    bench.add_argument("names", nargs="*", help="benchmarks to run (default: all; see --list)")
    bench.add_argument("--quick", action="store_true", help="the quick variants (CI: a few minutes)")
    bench.add_argument(
        "--jobs",
        type=int,
        default=None,
        help="processes for the quick scripts (default 2), for the untimed ones of a full run (default 1)",
    )
    bench.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    fit = sub.add_parser("fit", help="fit E, friction, damping to a measured force history (CSV)")
    fit.add_argument("scene", help="scene TOML file (its parameters are the starting point)")
    fit.add_argument("measured", help="CSV: a time (t_s, time) and a force (insertion_force_N, force) column")
    fit.add_argument(
        "--fit", default="E,friction", help="comma-separated: E,friction,alpha,beta,time_shift,plug_offset"
    )
    fit.add_argument(
        "--init", default=None, help="starting values overriding the scene's: E=1100,friction=0.15"
    )
    fit.add_argument("--max-iters", type=int, default=30, help="L-BFGS iterations at most (default 30)")
    fit.add_argument("--smooth", type=float, default=3.0, help="Gaussian smoothing of both histories, steps")
    fit.add_argument("--time-column", default=None, help="name of the time column (s) if not a standard one")
    fit.add_argument("--force-column", default=None, help="name of the force column (N) if not a standard one")
    fit.add_argument("--out", default="jsnap-fit", help="output directory (default jsnap-fit)")
    fit.add_argument("--json", action="store_true", help="print a JSON summary to stdout")
    cache = sub.add_parser("cache", help="show what the jsnap cache holds; --clear removes it")
    cache.add_argument(
        "--clear",
        nargs="*",
        metavar="FOLDER",
        default=None,
        help="remove the cached files (of the given folders only: neural_sdf, reduced, xla)",
    )
    cache.add_argument("--json", action="store_true", help="print a JSON summary to stdout")
    args = parser.parse_args(argv)
    if args.command == "cache":
        return cache_command(args)
    if args.command in ("simulate", "train-sdf", "fit"):
        from jsnap._build.cache import use_compilation_cache

        use_compilation_cache()
    if args.command == "train-sdf":
        return train_sdf(args)
    if args.command == "fit":
        from jsnap._apps.identify import fit_command

        return fit_command(args)
    if args.command == "bench":
        from jsnap._apps import bench as _bench

        try:
            return _bench.main(args.names, args.quick, args.list, args.jobs)
        except FileNotFoundError as err:
            print(f"jsnap: error: {err}", file=sys.stderr)
            return 2
    from jsnap._geometry.scene import SceneError

    try:
        return simulate(args)
    except (SceneError, FileNotFoundError) as err:
        print(f"jsnap: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
