"""Exact contact against rigid parts nobody tuned for (``benchmarks/_shapes.py``): a pin, a ball,
sharp and chamfered blocks, a wedge and a sleeve whose hole the arm passes through, each pressed
onto the default cantilever (the preset) and onto the own-connector example's hook (a part
from an STL file), straight and tilted, at default settings.

For every case the rigid part's signed distance is the default for a file, the candidate grid
(``GridMeshSDF``), and the same rollout is run twice more with the model's SDF swapped:

- ``brute``: the brute-force mesh distance at every point (``MeshSDF``, exact by construction,
  the independent reference): the grid's forces must equal it to round-off, its decisions the
  same at every step;
- ``bounded``: the former default, the brute-force distance at the 384 points nearest a box
  about the part and the box's distance elsewhere: where more points lie near the box (a pin's
  corners, a sleeve around the arm) its decisions differ.

Each row: status, peak insertion force, the largest force difference to ``brute`` over the run
(relative to the peak), the candidates per step whose side of the margin differs from the
exact distance's (recomputed from the rollout's own coordinates), steps/s of each SDF
(medians of interleaved rounds, with the load average) and, with ``--refine``, the peak with the
contact spacing halved and the element size at 0.75x. Writes ``results/rigid_family.json`` and
``.png``.

    python benchmarks/rigid_family.py [--quick] [--refine] [--rounds N]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _common import code_version, write_result
from _shapes import SHAPES, Hook, shape, with_distance

import jsnap
from jsnap._core.pose import quat_matrix
from jsnap._core.sdf import BoundedSDF, RoundedBoxSDF
from jsnap._core.util import cast_floats

HERE = Path(__file__).resolve().parent
EXAMPLE = HERE.parent / "examples" / "own_connector"
# The default cantilever's hook, and the example file's (the same section, its mesh's surface).
HOOK = Hook(h_tip=1.2, width=4.0, z_top=11.5, length=10.0, undercut=0.8)
# Tilted: turned 3 degrees about x and moved 0.2 mm aside on the way, as the example's motion.
TILT = (0.9996573249755573, 0.02617694830787315, 0.0, 0.0)


def scene_text(part: str, rigid_file: str, stroke: float, tilted: bool, speed: float = 10.0) -> str:
    """A scene file's text: the preset cantilever or the example hook, the rigid part from
    ``rigid_file``, a straight push at ``speed`` mm/s or a tilted one."""
    if part == "preset":
        head = (
            '[connector]\ntype = "cantilever"\nlength = 10.0\nthickness = 1.2\nwidth = 4.0\nundercut = 0.8\n'
            "lead_angle = 30.0\nreturn_angle = 90.0\nflat = 0.1144\n"
        )
    else:
        head = f'[part]\nmesh = "{EXAMPLE / "hook.stl"}"\nfixed_box = [[-1.0, -3.0, -0.01], [2.5, 3.0, 0.01]]\n'
    head += f'[rigid]\nmesh = "{rigid_file}"\n'
    head += "[material]\nyoungs_modulus = 2200.0\npoissons_ratio = 0.35\ndensity = 1.05e-9\n"
    head += "[contact]\nfriction = 0.3\n"
    if not tilted:
        return head + f"[motion]\ndirection = [0.0, 0.0, -1.0]\nspeed = {speed}\nstroke = {stroke}\n"
    t_end = stroke / speed
    q = ", ".join(map(str, TILT))
    return head + (
        "[motion]\nwaypoints = [\n"
        "  { t = 0.0, position = [0.0, 0.0, 0.0], rotation = [1.0, 0.0, 0.0, 0.0] },\n"
        f"  {{ t = {0.1 * t_end}, position = [0.0, 0.2, {-0.1 * stroke}], rotation = [{q}] }},\n"
        f"  {{ t = {t_end}, position = [0.0, 0.2, {-stroke}], rotation = [{q}] }},\n]\n"
    )


def case_scene(folder: Path, name: str, part: str, tilted: bool, changes: dict | None = None):
    """The scene of one case, its files written to ``folder``."""
    mesh, stroke = shape(name, HOOK)
    stl = folder / f"{name}.stl"
    mesh.export(stl)
    path = folder / f"{name}_{part}_{'tilted' if tilted else 'straight'}.toml"
    path.write_text(scene_text(part, str(stl), stroke, tilted))
    scene = jsnap.load_scene(path)
    return scene.replace(**{k.replace(".", "__"): v for k, v in (changes or {}).items()}) if changes else scene


def variants(model) -> dict:
    """The model with each of the three SDFs: the grid (as built), brute force, bounded (each
    within the edge rounding, if any)."""

    def bounded(grid):
        mesh = grid.mesh
        corners = np.abs(np.concatenate([np.asarray(mesh.a), np.asarray(mesh.b), np.asarray(mesh.c)]))
        return BoundedSDF(mesh, RoundedBoxSDF(jnp.asarray(corners.max(0)), jnp.asarray(0.0, jnp.float64)), 1e-3)

    return {
        "grid": model,
        "brute": dataclasses.replace(model, rigid=with_distance(model.rigid, lambda g: g.mesh)),
        "bounded": dataclasses.replace(model, rigid=with_distance(model.rigid, bounded)),
    }


def decision_mismatches(model, exact, res) -> np.ndarray:
    """(n,) candidate points per step whose side of the contact margin by ``model.rigid`` (as
    the step queries it) differs from the brute-force distance ``exact``'s, at the points where
    the rollout's coordinates (``res.x``) put them at the start of each step."""
    with jax.enable_x64(True):
        dtype = jnp.dtype(model.dtype)
        m = cast_floats(model, dtype)
        exact = cast_floats(exact, dtype)
        x = jnp.asarray(res.x, dtype)
        x0 = jnp.concatenate([jnp.zeros_like(x[:1]), x[:-1]])
        y = m.samples.rest + jax.vmap(lambda xi: m.part.sample_at(m.part.nodal(xi)))(x0)  # (n, P, 3)
        start = np.asarray(model.trajectory()[0])
        q0 = start[3:] if start.size == 7 else np.array([1.0, 0.0, 0.0, 0.0])
        quats = np.concatenate([q0[None], np.asarray(res.plug_rotation[:-1])])
        centre = np.concatenate([start[None, :3], np.asarray(res.plug[:-1])])
        rot = jax.vmap(quat_matrix)(jnp.asarray(quats, dtype))
        local = jnp.einsum("npi,nij->npj", y - jnp.asarray(centre, dtype)[:, None, :], rot)
        margin = model.contact.margin
        a = jax.lax.map(lambda q: m.rigid.scene_query(q, margin)[0], local)
        b = jax.lax.map(lambda q: exact(q)[0], local)
        return np.asarray(jnp.sum((a < margin) != (b < margin), axis=1))


def timed(model, prepared, rounds: int) -> list:
    times = []
    for _ in range(rounds):
        t0 = time.perf_counter()
        jax.block_until_ready(jsnap.rollout(model, prepared=prepared).energy)
        times.append(time.perf_counter() - t0)
    return times


def run_case(folder: Path, name: str, part: str, tilted: bool, rounds: int, refine: bool) -> dict:
    scene = case_scene(folder, name, part, tilted)
    t0 = time.perf_counter()
    model = jsnap.build(scene)
    build_s = time.perf_counter() - t0
    models = variants(model)
    prepared = jsnap.prepare(model)
    grid = getattr(model.rigid, "inner", model.rigid)
    row = {"build_s": build_s, "grid_row_length": int(grid.row_length), "points": int(model.n_samples)}
    results = {}
    for key, m in models.items():
        res = jsnap.rollout(m, prepared=prepared, keep_x=True)
        results[key] = res
        peak = float(np.max(res.insertion_force))
        row[key] = {
            "status": res.status(),
            "peak_insertion_force_N": peak,
            "decision_mismatches_max": int(decision_mismatches(m, models["brute"].rigid, res).max()),
        }
    ref = np.asarray(results["brute"].insertion_force)
    scale = max(float(np.max(np.abs(ref))), 1e-9)
    for key in models:
        row[key]["max_force_difference_rel"] = float(
            np.max(np.abs(np.asarray(results[key].insertion_force) - ref)) / scale
        )
    # Steps/s: interleaved rounds after one untimed run each (the rollouts above kept x, another
    # program), medians; none with --rounds 0.
    times = {key: [] for key in models}
    for r in range(rounds + 1 if rounds else 0):
        for key, m in models.items():
            t = timed(m, prepared, 1)
            times[key] += t if r else []
    steps = model.motion.shape[0] - 1
    for key in models if rounds else ():
        row[key]["steps_per_second"] = steps / float(np.median(times[key]))
    row["load_average"] = os.getloadavg()[0]
    if refine:
        fine = jsnap.build(
            scene.replace(
                contact__spacing=0.5 * float(scene["contact"]["spacing"]),
                solver__mesh_size=0.75 * float(scene["solver"]["mesh_size"]),
            )
        )
        res = jsnap.rollout(fine)
        row["refined"] = {"status": res.status(), "peak_insertion_force_N": float(np.max(res.insertion_force))}
        row["refined"]["peak_ratio"] = (
            row["refined"]["peak_insertion_force_N"] / row["grid"]["peak_insertion_force_N"]
        )
    return row


def plot(out: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = list(out["cases"])
    rows = [out["cases"][c] for c in cases]
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(max(8, 0.6 * len(cases)), 8), sharex=True)
    x = np.arange(len(cases))
    timed = all("steps_per_second" in r["grid"] for r in rows)
    for k, (key, colour) in enumerate((("grid", "C0"), ("brute", "C2"), ("bounded", "C3"))):
        at = x + (k - 1) * 0.27
        a1.bar(at, [r[key]["decision_mismatches_max"] for r in rows], 0.27, color=colour, label=key)
        if timed:
            a2.bar(at, [r[key]["steps_per_second"] for r in rows], 0.27, color=colour, label=key)
    if timed:
        a2.set_ylabel("steps/s (median)")
    else:  # a full run: how far each grid peak moves under refinement
        change = [100 * (r["refined"]["peak_ratio"] - 1) if "refined" in r else np.nan for r in rows]
        a2.bar(x, change, 0.5, color="C0")
        for level in (-3, 3):
            a2.axhline(level, color="k", lw=0.8, ls="--")
        a2.set_ylabel("peak change under refinement (%)\n(half the spacing, 0.75x elements)")
    a1.set_ylabel("most candidates per step decided\nagainst the exact distance")
    a2.set_xticks(x, cases, rotation=60, ha="right", fontsize=8)
    a1.legend()
    a1.set_title(f"Rigid parts nobody tuned for, default settings (CPU, {os.cpu_count()} cores)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def _interleaved() -> list:
    """Every (shape, part, tilt) once, ordered so that each run of four cases covers the four
    (part, tilt) pairs with different shapes: a run stopped part-way has measured all of them."""
    pairs = [(p, t) for p in ("preset", "file") for t in (False, True)]
    n = len(SHAPES)
    return [(SHAPES[k % n], *pairs[(k + k // n) % len(pairs)]) for k in range(n * len(pairs))]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the pin and the sleeve on the preset, straight")
    ap.add_argument(
        "--refine", action="store_true", help="also the peak at half the contact spacing, 0.75x elements"
    )
    ap.add_argument("--rounds", type=int, default=5, help="interleaved timing rounds (0: no timings)")
    args = ap.parse_args(argv)
    jsnap.configure_xla_cpu()
    cases = [(n, "preset", False) for n in ("cylinder", "sleeve")] if args.quick else _interleaved()
    out = {"code": code_version(), "cases": {}}
    stem = "rigid_family_quick" if args.quick else "rigid_family"
    with tempfile.TemporaryDirectory() as tmp:
        for name, part, tilted in cases:
            key = f"{name}/{part}/{'tilted' if tilted else 'straight'}"
            out["cases"][key] = row = run_case(Path(tmp), name, part, tilted, args.rounds, args.refine)
            print(
                key,
                {
                    k: (
                        v
                        if not isinstance(v, dict)
                        else {kk: (round(vv, 4) if isinstance(vv, float) else vv) for kk, vv in v.items()}
                    )
                    for k, v in row.items()
                },
                flush=True,
            )
            # Written after every case: a long run stopped part-way keeps what it measured.
            out["complete"] = len(out["cases"]) == len(cases)
            write_result(out, HERE / "results" / f"{stem}.json")
    plot(out, HERE / "results" / f"{stem}.png")


if __name__ == "__main__":
    sys.exit(main())
