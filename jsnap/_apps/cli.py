"""Command line: ``jsnap simulate [SCENE.toml] [--method ...] [--out DIR] [--json]``,
``jsnap fit SCENE.toml MEASURED.csv [--fit E,friction,...] [--out DIR] [--json]``,
``jsnap train-sdf [MESH]``, ``jsnap bench``, ``jsnap cache [--clear [FOLDER ...]] [--json]``.

The command line owns its process, so it makes the process-wide settings a library leaves to
its program: XLA:CPU's small-loop option (``jsnap.configure_xla_cpu``) and, for ``simulate``,
``fit`` and ``train-sdf``, JAX's compilation cache in the jsnap cache, so that a scene's second
run loads its compiled programs (off with JSNAP_XLA_CACHE=0). Exit codes: 0 done, 1 the run's
result is flagged (its message says what and at which step), 2 bad input (the message names
it)."""

from __future__ import annotations

import argparse
import json
import sys

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
            from jsnap._geometry.part import load_rigid
            from jsnap._geometry.presets import default_rigid
            from jsnap._geometry.scene import scene_file

            scene = jsnap.load_scene(args.scene)
            if scene["rigid"]:  # placed as the build places it, so that the cache key is the build's
                r = scene["rigid"]
                path = scene_file(scene, "rigid.mesh")
                mesh = load_rigid(path, units=r["units"], position=r["position"], rotation=r["rotation"]).mesh
            else:
                c = scene["connector"]
                mesh = default_rigid(c["type"], c, scene["plug"]).mesh()
            what = f"the rigid part of {scene.source}"
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
    sim.add_argument(
        "--method",
        choices=["reduced", "full", "segmented"],
        default=None,
        help="the deformable part's model (default: the scene's, reduced for the shipped scene)",
    )
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
    from jsnap._apps.xla import _backend_started, configure_xla_cpu

    if not _backend_started():  # called in a process that already computed (tests): leave it
        configure_xla_cpu()
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
    from jsnap._apps.simulate import OutputError, simulate
    from jsnap._geometry.scene import SceneError

    try:
        return simulate(args)
    except (SceneError, OutputError, FileNotFoundError) as err:
        print(f"jsnap: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
