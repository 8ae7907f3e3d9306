"""What the face points' hand-over of contact to the edges costs in steps/s, and what it changes
in the force, on every part sampled by the general surface sampling.

    python benchmarks/hand_over_cost.py [--runs 5]

The hand-over (``jsnap._core.collision.contact_normal``, docs/contact.md "Normals") queries the
rigid part's signed distance a second time per contact slot and step: one spacing along each
face point's sampling line. It applies to surface-sampled parts only (``Samples.hand_over``):
the two-hook clip, the box lid, the cable latch and parts from files (here the pipe clip of
``tests/data/pipe_clip``, whose rigid pin is an STL with an exact mesh distance). For each, the
shipped default model (reduced, float32, the scene's friction) is built once and rolled out
with the hand-over and without it (the internal key ``contact.hand_over = "off"``, which skips
the second query; the same reduced model, from the cache), the two timed calls alternating so
that both see the same machine load; steps/s is the median of ``--runs`` calls of each after
the compiling one. Recorded per part:
steps/s both ways and their ratio, the peak insertion force both ways, and the load average.
Writes benchmarks/results/hand_over_cost.{json,png}.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import jax
import numpy as np
from _common import LID_DEFAULT_SAMPLING, code_version

import jsnap
from jsnap._geometry.scene import with_internal

jsnap.configure_xla_cpu()

HERE = Path(__file__).resolve().parent
OUT = HERE / "results"
OFF = {"contact.hand_over": "off"}
SCENES = Path(jsnap.__file__).resolve().parent / "scenes"
PARTS = {
    "two_hook_clip": SCENES / "two_hook_clip.toml",
    "box_lid": SCENES / "box_lid.toml",
    "cable_latch": SCENES / "cable_latch.toml",
    "pipe_clip": HERE.parent / "tests" / "data" / "pipe_clip" / "scene.toml",
}
# The box lid at the contact sampling of the other parts (_common.LID_DEFAULT_SAMPLING).
CHANGES = {"box_lid": LID_DEFAULT_SAMPLING}


def timed(model, prepared) -> float:
    t0 = time.perf_counter()
    jax.block_until_ready(jsnap.rollout(model, prepared=prepared).energy)
    return time.perf_counter() - t0


def run_part(name: str, scene: Path, runs: int) -> dict:
    base = jsnap.load_scene(scene).replace(CHANGES.get(name, {}))
    model = jsnap.build(base)
    if not model.samples.hand_over:
        raise RuntimeError(f"{name}: not sampled by the general surface sampling (no hand-over to measure)")
    prepared = jsnap.prepare(model)
    variants = {"hand_over": model, "no_hand_over": jsnap.build(with_internal(base, OFF))}
    peaks, times = {}, {k: [] for k in variants}
    for key, m in variants.items():
        res = jsnap.rollout(m, prepared=prepared)  # compiles
        peaks[key] = float(np.max(np.asarray(res.insertion_force)))
    for _ in range(runs):
        for key, m in variants.items():
            times[key].append(timed(m, prepared))
    steps = model.motion.shape[0] - 1
    rate = {k: steps / float(np.median(v)) for k, v in times.items()}
    row = {
        "full_dof": int(model.full_dof),
        "capacity": int(model.contact.capacity),
        "steps": steps,
        "steps_per_second": rate,
        "cost_ratio": rate["no_hand_over"] / rate["hand_over"],
        "timed_seconds": times,
        "peak_N": peaks,
        "peak_change": peaks["hand_over"] / peaks["no_hand_over"] - 1.0,
        "load_average": os.getloadavg()[0],
    }
    print(
        f"{name}: {rate['hand_over']:.0f} steps/s with the hand-over, {rate['no_hand_over']:.0f} without "
        f"(x{row['cost_ratio']:.2f}); peak {peaks['hand_over']:.4g} / {peaks['no_hand_over']:.4g} N; "
        f"load {row['load_average']:.2f}",
        flush=True,
    )
    return row


def plot(rows: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(rows)
    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(7, 3.6))
    for k, (key, label) in enumerate((("hand_over", "with hand-over (shipped)"), ("no_hand_over", "without"))):
        ax.bar(x + (k - 0.5) * 0.38, [rows[n]["steps_per_second"][key] for n in names], 0.38, label=label)
    for i, n in enumerate(names):
        ax.text(i, rows[n]["steps_per_second"]["no_hand_over"], f"x{rows[n]['cost_ratio']:.2f}", ha="center",
                va="bottom", fontsize=8)  # fmt: skip
    ax.set_xticks(x, names)
    ax.set_ylabel("steps/s (reduced, float32, one scene)")
    ax.set_title("Cost of the second SDF query of the face points' hand-over")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5, help="timed calls of each variant (median)")
    args = parser.parse_args(argv)
    load_start = os.getloadavg()[0]
    rows = {name: run_part(name, scene, args.runs) for name, scene in PARTS.items()}
    out = {
        "what": "steps/s of the shipped default model with and without the face points' hand-over",
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, {jax.default_backend()}",
        "load_average_start": load_start,
        "load_average_end": os.getloadavg()[0],
        "code": code_version(),
        "runs": args.runs,
        "parts": rows,
    }
    OUT.mkdir(exist_ok=True)
    (OUT / "hand_over_cost.json").write_text(json.dumps(out, indent=2) + "\n")
    plot(rows, OUT / "hand_over_cost.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
