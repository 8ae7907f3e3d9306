"""How deep the deformable part goes into the rigid part, on every shipped scene, against the
limit of the ``DEEP_PENETRATION`` flag.

    python benchmarks/penetration.py [--parts box_lid,...]

The contact holds velocities (``contact.stabilisation = 0`` on every scene but the annular
snap), so a point that a step carries into the rigid part stays there until the part moves it
out. A snap's spring-in goes a few contact resolutions deep for a step or two; a point the
contact lost stays deep, and the rollout flags it (more than ``PENETRATION_STEPS`` steps in a
row deeper than ``PENETRATION_DEPTH`` resolutions, the resolution being the larger of the
contact's margin and spacing). This measures the margin between the two on the scenes that
ship: the five presets, the pipe clip of ``tests/data`` and the own-connector example, each
frictionless and at friction 0.3, rolled out as ``jsnap simulate`` runs them (the scene's
model and precision; a default buffer that dropped candidates widened). And the case the flag
is for: the shipped hook as STL files ten times its size (``part_size.py``'s, float64), whose
lip the contact loses in the snap at friction 0.3, at its time step (10 ms) and at half of it.

Recorded per case: the resolution (mm), the deepest penetration (in resolutions) and its step,
the longest run of steps deeper than 2 resolutions and deeper than the limit, the status, and
the history. ``--parts`` reruns some cases and keeps the other rows of the committed result,
each with the date and commit it was measured at. Writes benchmarks/results/penetration.{json,png}.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
from _common import presets_option, previous_result, run_status, stamped, write_result
from part_size import files_scene, write_files

import jsnap
from jsnap._apps.simulate import run_sizing_buffer
from jsnap._core.rollout import PENETRATION_DEPTH, PENETRATION_STEPS, contact_resolution

jsnap.configure_xla_cpu()

HERE = Path(__file__).resolve().parent
OUT = HERE / "results"
SCENES = Path(jsnap.__file__).resolve().parent / "scenes"
PARTS = {
    "default": SCENES / "default.toml",
    "two_hook_clip": SCENES / "two_hook_clip.toml",
    "box_lid": SCENES / "box_lid.toml",
    "annular": SCENES / "annular.toml",
    "cable_latch": SCENES / "cable_latch.toml",
    "pipe_clip": HERE.parent / "tests" / "data" / "pipe_clip" / "scene.toml",
    "own_connector": HERE.parent / "examples" / "own_connector" / "scene.toml",
}
FRICTIONS = (0.0, 0.3)
# The file hook ten times the shipped one's size, at its own time step and at half of it.
FILE_HOOK = {"file_hook_10x": {}, "file_hook_10x_half_dt": {"solver.dt": 5e-3}}


def longest_run(deep: np.ndarray) -> int:
    """The most consecutive True entries of ``deep``."""
    best = cur = 0
    for d in deep:
        cur = cur + 1 if d else 0
        best = max(best, cur)
    return best


def measure(name: str, scene: jsnap.Scene) -> dict:
    """One scene at each friction: its depths in contact resolutions and its status."""
    model = jsnap.build(scene)
    resolution = contact_resolution(model)
    row = {"resolution_mm": resolution, "dtype": model.dtype, "dt": model.dt}
    for mu in FRICTIONS:
        _, res, _ = run_sizing_buffer(scene, model, lambda m: jsnap.rollout(m, m.params.replace(friction=mu)))
        depth = np.asarray(res.penetration, float) / resolution
        row[f"mu{mu}"] = r = {
            "deepest_resolutions": float(depth.max()),
            "deepest_step": int(depth.argmax()),
            "longest_run_deeper_than_2": longest_run(depth > 2),
            "longest_run_deeper_than_limit": longest_run(depth > PENETRATION_DEPTH),
            "status": run_status(res),
            "depth_resolutions": depth.tolist(),
        }
        print(
            f"{name}, mu {mu:g}: deepest "
            f"{r['deepest_resolutions']:.2f} resolutions at step {r['deepest_step'] + 1}, longest run beyond "
            f"the limit {r['longest_run_deeper_than_limit']} steps; {r['status']}",
            flush=True,
        )
    return row


def main(argv=None) -> int:
    known = [*PARTS, *FILE_HOOK]
    parts = presets_option(argparse.ArgumentParser(description=__doc__.splitlines()[0]), known, argv, "parts")
    before = previous_result(OUT / "penetration.json", parts, known).get("parts", {})
    rows = {}
    for name in known:
        if name not in parts:
            rows[name] = before[name]
        elif name in PARTS:
            rows[name] = stamped(measure(name, jsnap.load_scene(PARTS[name])))
    if set(parts) & set(FILE_HOOK):
        with tempfile.TemporaryDirectory() as tmp:
            d = Path(tmp)
            write_files(d, [10.0])
            for name, changes in FILE_HOOK.items():
                if name in parts:
                    rows[name] = stamped(measure(name, files_scene(d, 10.0).replace(changes)))
    out = {"limit_resolutions": PENETRATION_DEPTH, "limit_steps": PENETRATION_STEPS, "parts": rows}
    write_result(out, OUT / "penetration.json")
    plot(out)
    return 0


def plot(out: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, len(FRICTIONS), figsize=(12, 4.5), sharey=True)
    for a, mu in zip(ax, FRICTIONS, strict=True):
        for name, r in out["parts"].items():
            depth = r[f"mu{mu}"]["depth_resolutions"]
            # Against the fraction of the motion: the half time step's run has twice the steps.
            a.plot(np.linspace(0, 1, len(depth)), depth, lw=1, label=name)
        a.axhline(out["limit_resolutions"], color="k", ls="--", lw=1, label="DEEP_PENETRATION depth")
        a.set_title(f"friction {mu:g}: deepest point inside the rigid part")
        a.set_ylim(0, 9)
        a.set_xlabel("fraction of the motion")
    ax[0].set_ylabel("depth / contact resolution (max of margin, spacing)")
    ax[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(OUT / "penetration.png", dpi=120)


if __name__ == "__main__":
    raise SystemExit(main())
