"""A part in a long housing: the shipped example ``examples/printed_hook`` (a three-prong hook
whose two barbed prongs slide about 30 mm along the walls of a housing's through-hole before
they snap out) at its default settings.

Measures, from an empty cache: ``jsnap simulate``'s wall time and peak memory (``/usr/bin/time
-v``), its status, the contact candidates and the reduced orders; the insertion force curve
against friction on the barbs' normal force (the plateau while they slide) and against the
prongs' deflection force (a Timoshenko cantilever pushed in by the interference); and the
forces at twice the Young's modulus (the same model, ``params.replace(E=2E)``), whose ratio to
the scene's should be 2, and without friction, where the walls' normal forces have no
component along the insertion and the plateau should vanish.
Writes ``benchmarks/results/long_housing.{json,png}``.

    python benchmarks/long_housing.py
"""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import code_version, write_result

import jsnap
from jsnap._build.model import with_capacity

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "examples" / "printed_hook"
OUT = Path(__file__).resolve().parent / "results" / "long_housing.json"
sys.path.insert(0, str(EXAMPLE))
import make_files  # noqa: E402  (the example's drawing: its dimensions)


def _timed_simulate(cache: Path, out: Path) -> dict:
    """``jsnap simulate`` of the example under ``/usr/bin/time -v`` with an empty cache."""
    env = dict(os.environ, JSNAP_CACHE=str(cache))
    cli = [sys.executable, "-m", "jsnap._apps.cli", "simulate", str(EXAMPLE / "scene.toml")]
    cmd = ["/usr/bin/time", "-v", *cli]
    t0 = time.perf_counter()
    run = subprocess.run([*cmd, "--out", str(out)], env=env, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    rss = re.search(r"Maximum resident set size \(kbytes\): (\d+)", run.stderr)
    built = re.search(r"built in ([0-9.]+) s", run.stdout + run.stderr)
    return dict(
        returncode=run.returncode,
        wall_s=wall,
        build_s=float(built.group(1)) if built else None,
        peak_rss_GB=int(rss.group(1)) * 1024 / 1e9 if rss else None,
        log=[ln for ln in (run.stdout + run.stderr).splitlines() if ln.startswith("jsnap")][-20:],
    )


def _beam_force() -> float:
    """Each prong's normal force at the land for the interference: a Timoshenko cantilever from
    the base's top face (z = 0) to the land's middle, N."""
    h, s = make_files.HOOK, make_files.HOUSING
    scene = jsnap.load_scene(EXAMPLE / "scene.toml")
    E, nu = scene["material"]["youngs_modulus"], scene["material"]["poissons_ratio"]
    t, b = h["thickness"], h["width"]
    L = make_files.retention_z(h) + 0.5 * h["land"]
    compliance = L**3 / (3 * E * b * t**3 / 12) + L / (5 / 6 * E / (2 * (1 + nu)) * b * t)
    return (h["undercut"] - s["clearance"]) / compliance


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        cache = Path(tmp) / "cache"
        run = _timed_simulate(cache, Path(tmp) / "out")
        summary = json.loads((Path(tmp) / "out" / "summary.json").read_text())
        os.environ["JSNAP_CACHE"] = str(cache)  # the model just built, loaded
        scene = jsnap.load_scene(EXAMPLE / "scene.toml")
        # As many contact slots as the CLI's run settled on (it widens an overflowing buffer).
        model = with_capacity(jsnap.build(scene), summary["contact_capacity"])
        E = scene["material"]["youngs_modulus"]
        res = jsnap.rollout(model)
        res2 = jsnap.rollout(model, model.params.replace(E=2 * E))
        res0 = jsnap.rollout(model, model.params.replace(friction=0.0))
    h, s = make_files.HOOK, make_files.HOUSING
    mu = scene["contact"]["friction"]
    F, F2 = np.asarray(res.insertion_force), np.asarray(res2.insertion_force)
    travel = np.asarray(res.travel)
    normal = np.sum(np.abs(np.asarray(res.contact_force)[..., 0]), axis=1)
    ramp = h["undercut"] / math.tan(math.radians(h["lead_angle"]))
    plateau = (travel > s["start_gap"] + ramp + 1.0) & (travel < s["start_gap"] + s["thickness"] - 1.0)
    on = F > 0.2 * F.max()
    beam = _beam_force()
    out = dict(
        what="examples/printed_hook at its default settings: build and run from an empty cache; the "
        "insertion force against friction on the barbs' normal force and the prongs' deflection; E and 2E",
        version=code_version(),
        simulate=run,
        status=summary.get("status"),
        dof=summary.get("dof"),
        full_dof=summary.get("full_dof"),
        reduced_orders=summary.get("reduced_orders"),
        contact_points=int(model.samples.rest.shape[0]),
        peak_force_N=float(F.max()),
        plateau_force_N=float(np.median(F[plateau])),
        plateau_normal_force_N=float(np.median(normal[plateau])),
        friction_times_normal_N=float(mu * np.median(normal[plateau])),
        beam_normal_force_per_prong_N=beam,
        normal_force_per_prong_over_beam=float(0.5 * np.median(normal[plateau]) / beam),
        final_force_N=float(F[-1]),
        latched=bool(abs(F[-1]) < 0.02 * F.max()),
        status_2E=res2.status(),
        force_ratio_2E_median=float(np.median(F2[on] / F[on])),
        force_ratio_2E_peak=float(F2.max() / F.max()),
        force_ratio_2E_plateau=float(np.median(F2[plateau]) / np.median(F[plateau])),
        status_frictionless=res0.status(),
        plateau_force_frictionless_N=float(np.median(np.asarray(res0.insertion_force)[plateau])),
        plateau_force_max_N=float(F[plateau].max()),
        plateau_force_frictionless_max_N=float(np.asarray(res0.insertion_force)[plateau].max()),
        curve=dict(
            travel=travel[::10].tolist(),
            force=F[::10].tolist(),
            force_2E=F2[::10].tolist(),
            force_frictionless=np.asarray(res0.insertion_force)[::10].tolist(),
            normal=normal[::10].tolist(),
        ),
    )
    write_result(out, OUT)
    _plot(out, OUT.with_suffix(".png"))
    print(json.dumps({k: v for k, v in out.items() if k not in ("curve", "version")}, indent=1))


def _plot(out: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = out["curve"]
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(c["travel"], c["force"], label="E (ABS, 2200 MPa)")
    ax.plot(c["travel"], np.asarray(c["force_2E"]) / 2, "--", label="2E, force / 2")
    ax.plot(c["travel"], c["force_frictionless"], lw=0.8, label="frictionless")
    ax.axhline(out["friction_times_normal_N"], color="grey", lw=0.8, label="μ × barbs' normal force (plateau)")
    ax.set_xlabel("travel, mm")
    ax.set_ylabel("insertion force, N")
    run = out["simulate"]
    ax.set_title(
        f"printed hook in a long housing: built and run in {run['wall_s']:.0f} s, "
        f"peak {run['peak_rss_GB']:.1f} GB",
        fontsize=9,
    )
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    main()
