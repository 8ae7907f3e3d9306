"""The tilted box lid's reduced model against its full model, in rollouts that differ only by
round-off.

    python benchmarks/box_lid_roundoff.py

The tilted rise is a sawtooth (benchmarks/box_lid.py): the box's slanted edges meet the hooks'
lips one candidate point after another, and with friction each point sticks or slips. Which it
does at a given step can turn on the last bits of a force, so the curve's distance from the
full model's moves with round-off alone. This measures that spread on the 1.2 mm mesh, at
mu = 0.3 (the scene's friction): one reduced model (the scene's hsv_tolerance), rolled out in
float32 and in float64, each with the contact solve cut to the scene's problem sizes
(``jsnap._core.step._buckets``) and without the eighth of the buffer among them (the same
problem, its Delassus matrix summed in another order). Every curve is compared with the full
model's (float64, APGD to the tolerance) from ``results/box_lid.json``: RMSE over the rise and
over the whole motion in % of the full model's peak, and the peak.

Writes benchmarks/results/box_lid_roundoff.{json,png}.
"""

from __future__ import annotations

import json
from pathlib import Path

import jax
import numpy as np
from _common import curve_stats, load_scene, write_result
from box_lid import COARSE, SCENE

import jsnap
from jsnap._core import step as step_module

jsnap.configure_xla_cpu()

OUT = Path(__file__).parent / "results"
CASE = "tilt 3 mu 0.3"


SHIPPED = step_module._buckets


def without_eighth(capacity: int) -> tuple[int, ...]:
    """The scene's problem sizes less the eighth of the buffer (the 256-slot lid: 16, 24, 48,
    64, 128 and 256 slots instead of 16, 24, 32, 48, 64, 128 and 256)."""
    return tuple(k for k in SHIPPED(capacity) if k != capacity // 8 or k == capacity)


def main() -> int:
    acc = json.loads((OUT / "box_lid.json").read_text())["accuracy"][CASE]
    travel, F_full = (np.asarray(acc["curves"][k]) for k in ("travel_mm", "full_N"))
    model = jsnap.build(load_scene(COARSE, jsnap.load_scene(SCENE)))
    C = model.contact.capacity
    rows, curves = {}, {}
    for sizes_name, sizes in (("shipped", SHIPPED), ("no eighth", without_eighth)):
        step_module._buckets = sizes
        jax.clear_caches()  # the step is traced anew with these sizes
        try:
            for dtype in ("float32", "float64"):
                F = np.asarray(jsnap.rollout(model, dtype=dtype).insertion_force)
                key = f"{dtype}, sizes {sizes_name}"
                rows[key] = {"problem_sizes": list(sizes(C)), **curve_stats(F, travel, F_full)}
                curves[key] = F
                print(key, rows[key], flush=True)
        finally:
            step_module._buckets = SHIPPED
    rise = [r["rmse_rise_of_full_peak"] for r in rows.values()]
    out = {
        "case": CASE,
        "mesh_size": COARSE["solver.mesh_size"],
        "orders": [int(o) for o in model.part.orders],
        "full_peak_N": float(F_full.max()),
        "rows": rows,
        "rmse_rise_range": [min(rise), max(rise)],
    }
    write_result(out, OUT / "box_lid_roundoff.json")
    plot(travel, F_full, curves)
    return 0


def plot(travel, F_full, curves):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(12, 4.5))
    rise = int(np.argmax(F_full)) + 1
    ax[0].plot(travel, F_full, "k", lw=1.5, label="full float64")
    for key, F in curves.items():
        ax[0].plot(travel, F, lw=0.8, label=f"reduced {key}")
        off = 100 * (F[:rise] - F_full[:rise]) / F_full.max()
        ax[1].plot(travel[:rise], off, lw=0.8, label=f"reduced {key}")
    ax[0].set(xlabel="travel of the box (mm)", ylabel="insertion force (N)", title=f"box lid, 1.2 mm, {CASE}")
    ax[1].axhline(0, color="0.6", lw=0.5)
    ax[1].set(
        xlabel="travel of the box (mm)",
        ylabel="reduced - full, % of the full model's peak",
        title="over the rise: round-off only between the reduced curves",
    )
    for a in ax:
        a.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(OUT / "box_lid_roundoff.png", dpi=110)


if __name__ == "__main__":
    raise SystemExit(main())
