"""Neural SDF of the default plug: training time and accuracy against the exact mesh SDF.

Trains the default network (``NeuralSDFConfig()``: 3 → 64 → 64 → 64 → 1) on the default scene's
plug (the rounded block of ``jsnap._geometry.presets.default_rigid``, ``rounded_box_mesh``: 1.0 × 5.0 × 0.5 mm,
0.1 mm fillet, 5516 triangles) from scratch, timing it, and measures over points uniform in the
contact shell ``|φ| ≤ 0.2 mm``:

- the distance error against the exact triangle-mesh SDF (target: mean ≤ 0.01 mm) and, for
  information, against the analytic rounded box the mesh approximates;
- the angle between the network's normal ``∇φ/|∇φ|`` and the exact one (target: median ≤ 2°).

Writes ``benchmarks/results/sdf_accuracy.json`` and the error-field picture
``docs/img/neural_sdf_error.png``, and puts the weights in the cache (``$JSNAP_CACHE`` or
``~/.cache/jsnap``) under their key, where ``jsnap.build`` finds them. Exit status 1 if a target
is missed.

    python benchmarks/sdf_accuracy.py     # ~1-2 min on 2 CPU cores
"""

import argparse
import json
import os
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np

import jsnap
from jsnap._build.neural_sdf import NeuralSDFConfig, band_errors, cache_key, cache_path, save, summarise, train
from jsnap._build.sdf import mesh_sdf_from_trimesh
from jsnap._core.sdf import mesh_sdf_and_normal, neural_sdf_and_normal, rounded_box_sdf
from jsnap._geometry.presets import default_rigid

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.colors import LogNorm

# XLA's small-loop option, before the first JAX computation (the committed timings have it).
jsnap.configure_xla_cpu()

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
IMG = ROOT / "docs" / "img"
TARGET_MAE_MM = 0.01
TARGET_NORMAL_DEG = 2.0


def machine():
    proc = platform.processor() or platform.machine()
    dev = jax.devices()[0]
    return f"{platform.node()} ({proc}, {os.cpu_count()} cores, {dev.platform}: {dev.device_kind})"


def section(net, exact, axes, fixed, extent, n):
    """Errors on a planar grid: axes (i, j) vary over extent, the third coordinate = fixed."""
    (a0, a1), (b0, b1) = extent
    u, v = np.meshgrid(np.linspace(a0, a1, n[0]), np.linspace(b0, b1, n[1]))
    p = np.zeros((*u.shape, 3))
    p[..., axes[0]] = u
    p[..., axes[1]] = v
    k = 3 - axes[0] - axes[1]
    p[..., k] = fixed
    q = p.reshape(-1, 3)
    f, nr = (np.asarray(a) for a in mesh_sdf_and_normal(exact, q))
    g, gn = (np.asarray(a, np.float64) for a in neural_sdf_and_normal(net, jnp.asarray(q, jnp.float32)))
    ang = np.degrees(np.arccos(np.clip(np.sum(gn * nr, axis=1), -1, 1)))
    shape = u.shape
    return u, v, f.reshape(shape), (g - f).reshape(shape), ang.reshape(shape)


def main(argv=None):
    # The exact and analytic distances are evaluated in float64: jsnap's kernels called directly
    # run in JAX's 64-bit mode, which importing jsnap no longer switches on for the process.
    with jax.enable_x64(True):
        return _main(argv)


def _main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=50_000, help="evaluation points in the shell")
    ap.add_argument("--no-cache", action="store_true", help="do not store the weights in the cache")
    args = ap.parse_args(argv)

    scene = jsnap.load_scene()
    plug = default_rigid("cantilever", scene["connector"], scene["plug"])
    half, radius = plug.half, plug.radius
    mesh = plug.mesh()
    config = NeuralSDFConfig()
    load = os.getloadavg()

    # What `jsnap train-sdf --retrain` does: label, fit, and a 20k-point accuracy report.
    t0 = time.perf_counter()
    net, info = train(mesh, config, progress=True)
    t_total = time.perf_counter() - t0
    print(f"trained in {info['seconds']:.1f} s (labelling + fitting), {t_total:.1f} s with the report")

    band = config.band
    errors = band_errors(net, mesh, band=band, points=args.points, seed=2024)
    rep = summarise(errors, band)
    x, f = errors["x"], errors["phi"]
    box = np.asarray(rounded_box_sdf(x, half, radius))
    rep["mae_vs_analytic_box_mm"] = float(np.mean(np.abs(f + errors["error"] - box)))
    rep["mesh_vs_analytic_box_max_mm"] = float(np.max(np.abs(f - box)))
    err = np.abs(errors["error"])
    exact = mesh_sdf_from_trimesh(mesh)

    passed = rep["mae_mm"] <= TARGET_MAE_MM and rep["normal_median_deg"] <= TARGET_NORMAL_DEG
    out = dict(
        machine=machine(),
        load_average_at_start=load,
        jax=jax.__version__,
        plug=dict(half_extents_mm=list(map(float, half)), fillet_mm=float(radius), triangles=len(mesh.faces)),
        config=config.to_dict(),
        train_seconds=info["seconds"],
        train_seconds_with_report=t_total,
        final_loss_mm=float(np.mean(info["loss"][-100:])),
        accuracy=rep,
        targets=dict(mae_mm=TARGET_MAE_MM, normal_median_deg=TARGET_NORMAL_DEG, train_seconds=120.0),
        passed=bool(passed and t_total <= 120.0),
    )
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "sdf_accuracy.json").write_text(json.dumps(out, indent=1))
    print(json.dumps(rep, indent=1))
    if not args.no_cache:
        key = cache_key(mesh, config)
        extra = dict(report=info["report"], seconds=info["seconds"], final_loss=out["final_loss_mm"])
        path = save(net, cache_path(key), key=key, mesh_hash=info["mesh_hash"], config=config, extra=extra)
        print(f"weights cached in {path}")

    # Error field: the plug's thin section (x-z at y = 0), its plan (x-y at z = 0), normals.
    xz = section(net, exact, (0, 2), 0.0, ((-0.8, 0.8), (-0.55, 0.55)), (320, 220))
    xy = section(net, exact, (1, 0), 0.0, ((-2.85, 2.85), (-0.85, 0.85)), (570, 170))
    lim = 2 * TARGET_MAE_MM
    fig = plt.figure(figsize=(13, 8.5))
    gs = fig.add_gridspec(2, 3, height_ratios=[1, 1.05])
    panels = [
        (fig.add_subplot(gs[0, 0]), xz, "x (mm)", "z (mm)", "section y = 0: φ_net − φ_exact"),
        (fig.add_subplot(gs[0, 1:]), xy, "y (mm)", "x (mm)", "section z = 0: φ_net − φ_exact"),
    ]
    # Outside the contact shell |φ| > band (grey) the net is trained only loosely (far_weight).
    cmap_e = plt.get_cmap("RdBu_r").with_extremes(bad="0.82")
    cmap_a = plt.get_cmap("magma").with_extremes(bad="0.82")
    for ax, (u, v, f_, e_, _), xl, yl, title in panels:
        e_ = np.ma.masked_where(np.abs(f_) > band, e_)
        im = ax.pcolormesh(u, v, e_, cmap=cmap_e, vmin=-lim, vmax=lim, shading="auto")
        ax.contour(u, v, f_, levels=[0.0], colors="k", linewidths=1.0)
        ax.contour(u, v, f_, levels=[-band, band], colors="0.35", linewidths=0.7, linestyles="--")
        ax.set_aspect("equal")
        ax.set_xlabel(xl)
        ax.set_ylabel(yl)
        ax.set_title(title, fontsize=10)
        fig.colorbar(im, ax=ax, label="distance error (mm)", shrink=0.85)
    ax = fig.add_subplot(gs[1, 0])
    u, v, f_, _, ang = xz
    ang = np.ma.masked_where(np.abs(f_) > band, np.maximum(ang, 1e-2))
    im = ax.pcolormesh(u, v, ang, cmap=cmap_a, norm=LogNorm(1e-2, 90), shading="auto")
    ax.contour(u, v, f_, levels=[0.0], colors="w", linewidths=1.0)
    ax.contour(u, v, f_, levels=[-band, band], colors="0.7", linewidths=0.7, linestyles="--")
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("z (mm)")
    ax.set_title("section y = 0: normal error (degrees)", fontsize=10)
    fig.colorbar(im, ax=ax, label="angle (deg)", shrink=0.85)
    ax = fig.add_subplot(gs[1, 1])
    ax.hist(err, bins=np.logspace(-6, 0, 61), color="C0")
    ax.axvline(rep["mae_mm"], color="k", label=f"mean {rep['mae_mm'] * 1e3:.2f} µm")
    ax.axvline(TARGET_MAE_MM, color="C3", ls="--", label=f"target {TARGET_MAE_MM * 1e3:.0f} µm")
    ax.set_xscale("log")
    ax.set_xlabel(f"|φ_net − φ_exact| (mm), {len(err)} points with |φ| ≤ {band} mm")
    ax.set_ylabel("points")
    ax.legend(fontsize=8)
    ax = fig.add_subplot(gs[1, 2])
    ax.hist(errors["angle"], bins=np.logspace(-3, 2.3, 61), color="C1")
    ax.axvline(rep["normal_median_deg"], color="k", label=f"median {rep['normal_median_deg']:.2f}°")
    ax.axvline(TARGET_NORMAL_DEG, color="C3", ls="--", label=f"target {TARGET_NORMAL_DEG:.0f}°")
    ax.set_xscale("log")
    ax.set_xlabel("normal error (degrees), same points")
    ax.legend(fontsize=8)
    fig.suptitle(
        f"Neural SDF of the default plug ({len(mesh.faces)} triangles), {config.width}x{config.depth} "
        f"{config.activation}, trained in {t_total:.0f} s; black: surface, dashed: |φ| = {band} mm "
        f"(grey: outside the contact shell)\n"
        f"{machine()}",
        fontsize=10,
    )
    fig.tight_layout()
    IMG.mkdir(parents=True, exist_ok=True)
    fig.savefig(IMG / "neural_sdf_error.png", dpi=110)
    print(f"wrote {RESULTS / 'sdf_accuracy.json'} and {IMG / 'neural_sdf_error.png'}")
    return 0 if out["passed"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
