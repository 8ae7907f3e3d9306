"""The box lid preset (jsnap/scenes/box_lid.toml): its reduced model against its full model,
both against CalculiX and the design guide, the tilt's sequential engagement, and their speed
side by side.

    python benchmarks/box_lid.py

1. Accuracy, for the shipped tilted box (3 degrees) and the untilted one, frictionless and at
   mu = 0.3. The full model does not fit in memory on the shipped 0.8 mm mesh (36801 dof: about
   60 GiB of dense operators), so the reduced model is checked against it on a 1.2 mm mesh
   (the full model in float64, its contact solved by APGD to the default tolerance, 1e-6, with
   up to 5000 iterations; the reduced model in float32 as shipped): peak insertion force,
   travel at the peak, RMSE of the insertion force in % of the full model's peak over the
   whole motion and over the rise (up to the full model's largest force before the hooks first
   pull the box in: ``rise_end``). The same for the shipped mesh's reduced model at the other
   presets' contact sampling and point load cases (``_common.LID_DEFAULT_SAMPLING``). The
   shipped reduced model (0.8 mm, float32), that model and the 1.2 mm full model against
   CalculiX's linear-geometry curves of the same lid (jsnap/data/calculix-box_lid/), over the
   travel CalculiX covers, where it has the case.
   The reduction's tolerance: for the tilted box, the reduced model (float32) on the 1.2 mm
   mesh at several ``solver.hsv_tolerance`` values against the same full model, with each
   curve's peak after a 0.05 mm moving average (the tilted rise is a sawtooth: contact lines
   creep along the slanted edges point by point, and a single step's spike sets the raw peak).
2. The tilt: the travel at which each pair of hooks (-y, +y) first carries force and reaches
   its peak, against the delay spacing * tan(tilt) the box's slope predicts; the base's moment
   about x at the peak.
3. The design guide (untilted: four hooks deflected at once) against the full model's peak.
4. Speed: steps/s of the compiled rollout (median of the timed calls) of the reduced model and
   of the full model (float32 and float64) on the 1.2 mm mesh, and of the shipped reduced
   model, in one process, with the load average.
   The shipped model against the same lid at the other presets' contact sampling and point
   load cases (``_common.LID_DEFAULT_SAMPLING``), timed in interleaved rounds: what the scene's
   light contact settings buy. And the shipped model with the contact solve cut to the shipped
   problem sizes against the sizes without those only a 256-slot buffer gets
   (``jsnap._core.step._buckets``: 16, 24 and 48 slots), interleaved the same way.
5. Rate against the reduced order: the shipped mesh's reduced model (float32) at each of
   ``ORDER_TOLERANCES``, its coordinates and steps/s, and the least-squares line of the time a
   step takes against the coordinates. Its intercept is the part of the step no reduction
   removes (the contact queries of the candidate points, the solver's iterations, the slot
   bookkeeping): the fastest the lid could step with this contact at any order.

    python benchmarks/box_lid.py --speed-only   # 4 and 5 again, the accuracy rows kept

Writes benchmarks/results/box_lid.{json,png}.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import equinox as eqx
import jax
import numpy as np
from _common import (
    LID_DEFAULT_SAMPLING,
    calculix_row,
    curve_stats,
    load_scene,
    moving_average,
    plot_speed,
    recorded_problems,
    scan_timing,
    speed,
    timing_row,
    write_result,
)

import jsnap
from jsnap._apps.simulate import design_guide_force
from jsnap._core import step as step_module
from jsnap._core.contact import SPG, solve_admm, solve_apgd, solve_spg
from jsnap._geometry.scene import default_scene_path

jsnap.configure_xla_cpu()

OUT = Path(__file__).parent / "results"
SCENE = default_scene_path().parent / "box_lid.toml"
DATA = Path(jsnap.__file__).parent / "data" / "calculix-box_lid"


def _finest(stem: str) -> Path | None:
    """The CalculiX curve ``<stem>_m<level>_curve.csv`` of the finest mesh that ran, or None."""
    for level in (3, 2, 1):
        path = DATA / f"{stem}_m{level}_curve.csv"
        if path.is_file():
            return path
    return None


# (tilt, friction): the CalculiX curve of that case on the finest mesh CalculiX ran it on.
REFS = {
    (0.0, 0.0): _finest("lid_mu0_lin"),
    (0.0, 0.3): _finest("lid_mu03_lin"),
    (3.0, 0.0): _finest("lid_tilt3_mu0_lin"),
}
# The full model's contact: APGD to the default tolerance, 1e-6, with room to get there; the
# same candidate points as the scene's.
FULL_CONTACT = {"contact.solver": "apgd", "contact.iterations": 5000, "contact.tolerance": 1e-6}
# The finest mesh whose full model fits in this machine's memory (module docstring).
COARSE = {"solver.mesh_size": 1.2}
# solver.hsv_tolerance of the reduced models compared for the tilted box (the scene's is 3e-3).
TOLERANCES = (1e-2, 3e-3, 1e-3)
# solver.hsv_tolerance of the shipped mesh's reduced models timed for the rate against the order
# (1e-1 is far too coarse to use: it is there to pin the line's intercept).
ORDER_TOLERANCES = (1e-1, 1e-2, 3e-3, 1e-3)
# The moving average (steps: 0.05 mm at the scene's speed) of the smoothed peak.
WINDOW = 5


def smoothed_peak(F) -> float:
    """The largest ``WINDOW``-step moving average of ``F`` (over whole windows only)."""
    half = WINDOW // 2
    return float(moving_average(np.asarray(F, np.float64), WINDOW)[half : len(F) - half].max())


def pairs(model, res) -> dict:
    """Each pair of hooks' (-y, +y) push along the motion, its first travel and its peak, and
    the base's moment about x at the peak of the total."""
    travel = np.asarray(res.travel)
    rest = np.asarray(model.samples.rest)[np.asarray(res.contact_index)]
    push = -(np.asarray(res.contact_force)[..., 2] * np.asarray(res.contact_active))  # on the hooks, down
    out = {}
    for name, side in (("minus_y", rest[..., 1] < 0), ("plus_y", rest[..., 1] > 0)):
        F = np.where(side, push, 0.0).sum(axis=1)
        out[name] = {
            "first_contact_travel_mm": float(travel[np.argmax(F > 1e-6)]),
            "peak_N": float(F.max()),
            "travel_at_peak_mm": float(travel[np.argmax(F)]),
        }
    k = int(np.argmax(np.asarray(res.insertion_force)))
    out["base_moment_x_at_peak_Nmm"] = float(np.asarray(res.base_moment)[k, 0])
    return out


def tolerance_sweep(coarse, red_model, Fr, travel, Ff) -> dict:
    """The reduced model (float32) of ``coarse`` at each of ``TOLERANCES`` against the full
    model's curve ``Ff``; ``red_model`` (its curve ``Fr``) is the scene's own tolerance."""
    rows = {}
    for tol in TOLERANCES:
        if tol == coarse["solver"]["hsv_tolerance"]:
            model, F = red_model, Fr
        else:
            model = jsnap.build(coarse.replace({"solver.hsv_tolerance": tol}))
            F = np.asarray(jsnap.rollout(model).insertion_force)
        rows[f"{tol:g}"] = {
            "orders": [int(o) for o in model.part.orders],
            **curve_stats(F, travel, Ff),
            "smoothed_peak_N": smoothed_peak(F),
        }
        print(f"  hsv_tolerance {tol:g}:", rows[f"{tol:g}"], flush=True)
    return rows


def interleaved(scenes: dict, rounds: int, label: str) -> dict:
    """Steps/s of each scene's model (name -> scene), reduced, float32: every model compiled
    first, then timed in ``rounds`` rounds, one rollout of each per round, so that the machine's
    load drifts over all of them alike; the median per model, with its orders, and the first
    rollout's result (``"result"``, for the caller's own figures; not JSON)."""
    built = {}
    for key, scene in scenes.items():
        model = jsnap.build(scene)
        built[key] = compiled(model, jsnap.prepare(model))
    return interleaved_models(built, rounds, label)


# The step's problem sizes as shipped (compiled() swaps the step's for a while).
SHIPPED_SIZES = step_module._buckets


def compiled(model, prepared, sizes=None) -> tuple:
    """``(model, prepared, first result, first call's seconds)``: the model's rollout compiled
    by a first call, with the contact solve's problem sizes ``sizes`` (a function of the
    capacity; ``jsnap._core.step._buckets`` as shipped when None) while it is traced."""
    step_module._buckets = sizes or SHIPPED_SIZES
    try:
        res, first, _ = scan_timing(model, prepared, 1)
    finally:
        step_module._buckets = SHIPPED_SIZES
    return model, prepared, res, first


def interleaved_models(built: dict, rounds: int, label: str) -> dict:
    """:func:`interleaved` for models :func:`compiled` already (name -> its tuple)."""
    times = {key: [] for key in built}
    for _ in range(rounds):
        for key, (model, prepared, _, _) in built.items():
            times[key] += scan_timing(model, prepared, 1)[2]
    rows = {}
    for key, (model, _, res, first) in built.items():
        steps = model.motion.shape[0] - 1
        median = float(np.median(times[key]))
        rows[key] = {
            "orders": [int(o) for o in model.part.orders],
            "dof": int(model.n_dof),
            "steps": steps,
            "first_call_s": first,
            "median_s": median,
            "steps_per_second": steps / median,
        }
        print(f"  {label} {key}:", rows[key], flush=True)
        rows[key]["result"] = (model, res)
    return rows


def rate_against_order(base, rounds: int = 5) -> dict:
    """Steps/s of the shipped mesh's reduced model (float32) at each of ``ORDER_TOLERANCES``
    (:func:`interleaved`) and the line ``seconds per step = intercept + slope x coordinates``
    through them."""
    scenes = {f"{tol:g}": base.replace({"solver.hsv_tolerance": tol}) for tol in ORDER_TOLERANCES}
    rows = interleaved(scenes, rounds, "hsv_tolerance")
    for row in rows.values():
        row.pop("result")
    r = np.array([row["dof"] for row in rows.values()], dtype=float)
    t = np.array([1.0 / row["steps_per_second"] for row in rows.values()])
    slope, intercept = np.polyfit(r, t, 1)
    return {
        "rows": rows,
        "rounds": rounds,
        "load_average": os.getloadavg()[0],
        "us_per_step_at_no_coordinates": 1e6 * float(intercept),
        "us_per_step_per_coordinate": 1e6 * float(slope),
        "steps_per_second_at_no_coordinates": 1.0 / float(intercept),
    }


def light_against_default(base, rounds: int = 7) -> dict:
    """Steps/s of the shipped model (its light contact sampling and patch loads) and of the
    same lid at the other presets' contact sampling (``LID_DEFAULT_SAMPLING``), on the shipped
    mesh (:func:`interleaved`); with each one's candidate points, contact iterations and peak."""
    rows = interleaved({"shipped": base, "default_sampling": base.replace(LID_DEFAULT_SAMPLING)}, rounds, "")
    for row in rows.values():
        model, res = row.pop("result")
        row |= {
            "candidate_points": int(model.samples.rest.shape[0]),
            "mean_iterations": float(np.mean(np.asarray(res.iterations))),
            "most_active_slots": int(np.asarray(res.contact_active).sum(axis=1).max()),
            "peak_N": float(np.max(np.asarray(res.insertion_force))),
            "ok": bool(res.ok),
        }
    rows["speedup"] = rows["shipped"]["steps_per_second"] / rows["default_sampling"]["steps_per_second"]
    return {"rows": rows, "rounds": rounds, "load_average": os.getloadavg()[0]}


def _without_fine_sizes(capacity: int) -> tuple[int, ...]:
    """The problem sizes less those that only a buffer of 256 slots or more gets (a sixteenth,
    three thirty-seconds and three sixteenths of it): the lid's 32, 64, 128 and 256 instead of
    16, 24, 32, 48, 64, 128 and 256."""
    return tuple(k for k in SHIPPED_SIZES(capacity) if k not in step_module._fine_buckets(capacity))


class _SameSolver(SPG):
    """The scene's solver under another name: a model holding it is another compiled rollout
    (jit's cache tells models apart by their types), so two can be compiled with different
    problem sizes and then timed in alternation."""


def problem_sizes(base, rounds: int = 7) -> dict:
    """Steps/s of the shipped model with its contact solve cut to the shipped problem sizes and
    to those without the sizes a 256-slot buffer gets beyond the smaller buffers' rule
    (``_without_fine_sizes``), in interleaved rounds (:func:`interleaved_models`): what they buy.
    The same forces but for the round-off of another summation order."""
    model = jsnap.build(base)
    prepared = jsnap.prepare(model)
    s = model.contact.solver
    coarse_model = eqx.tree_at(
        lambda m: m.contact.solver, model, _SameSolver(max_iters=s.max_iters, tol=s.tol, implicit=s.implicit)
    )
    built = {
        "shipped": compiled(model, prepared),
        "without_fine_sizes": compiled(coarse_model, prepared, _without_fine_sizes),
    }
    rows = interleaved_models(built, rounds, "problem sizes")
    for key, sizes in (("shipped", SHIPPED_SIZES), ("without_fine_sizes", _without_fine_sizes)):
        row = rows[key]
        model, res = row.pop("result")
        row |= {
            "problem_sizes": list(sizes(model.contact.capacity)),
            "mean_iterations": float(np.mean(np.asarray(res.iterations))),
            "peak_N": float(np.max(np.asarray(res.insertion_force))),
            "ok": bool(res.ok),
        }
    rows["speedup"] = rows["shipped"]["steps_per_second"] / rows["without_fine_sizes"]["steps_per_second"]
    return {"rows": rows, "rounds": rounds, "load_average": os.getloadavg()[0]}


# Section 6: the solvers the recorded problems are solved again by (SPG is the scene's).
SOLVE = {"spg": solve_spg, "apgd": solve_apgd, "admm": solve_admm}


def solve_alone(model, rounds: int = 5) -> dict:
    """Section 6 of the module docstring: per solver, the median over ``rounds`` of the seconds
    to solve every recorded problem of ``model``'s rollout, per rollout step."""
    recs = recorded_problems(model, SPG, active_only=True)
    steps = model.motion.shape[0] - 1
    cap, tol = model.contact.solver.max_iters, model.contact.solver.tol

    def timed_loop(f):
        for size in {r[0].shape[0] for r in recs}:  # compile every problem size first
            jax.block_until_ready(f(*next(r for r in recs if r[0].shape[0] == size)))
        times = []
        for _ in range(rounds):
            t0 = time.perf_counter()
            outs = [f(*r) for r in recs]
            jax.block_until_ready(outs)
            times.append(time.perf_counter() - t0)
        return float(np.median(times)), outs

    empty, _ = timed_loop(jax.jit(lambda W, q, mu, mask, g0: q[0] + W[0, 0]))
    out = {
        "solves": len(recs),
        "steps": steps,
        "tolerance": tol,
        "iteration_cap": cap,
        "rounds": rounds,
        "call_overhead_us_per_step": 1e6 * empty / steps,
    }
    for name, solve in SOLVE.items():
        f = jax.jit(
            lambda W, q, mu, mask, g0, solve=solve: solve(
                W, q, mu, mask, max_iters=cap, tol=tol, gamma0=g0, differentiable=False
            )
        )
        seconds, sols = timed_loop(f)
        its = np.array([int(s.iterations) for s in sols])
        out[name] = {
            "us_per_step": 1e6 * seconds / steps,
            "us_per_step_less_call_overhead": 1e6 * (seconds - empty) / steps,
            "mean_iterations": float(its.mean()),
            "capped": int((its >= cap).sum()),
            "max_residual": float(max(float(s.residual) for s in sols)),
        }
        print(f"  solve alone, {name}:", out[name], flush=True)
    out["load_average"] = os.getloadavg()[0]
    return out


def rise_end(F_full) -> int:
    """The step of the full model's largest force before it first pulls the box in (a force
    below -5 % of its peak: the hooks springing back behind the box's edge after a snap). The
    ringing after the snaps can put a single step above the rise's peak (the untilted,
    frictionless lid's full model: 12.5 N at 2.0 mm, against 8.8 N on the rise)."""
    pull = np.flatnonzero(F_full < -0.05 * F_full.max())
    return int(np.argmax(F_full[: pull[0] if pull.size else F_full.size]))


def model_stats(acc: dict) -> None:
    """The models' rows of ``acc`` (peak, RMS differences from the full model over the whole
    motion and over the rise, up to :func:`rise_end`) from its curves; each row's ``ok`` kept."""
    curves = acc["curves"]
    travel, Ff = np.asarray(curves["travel_mm"]), np.asarray(curves["full_N"])
    end = rise_end(Ff)
    acc["rise_end_travel_mm"] = float(travel[end])
    for row, key in (
        ("full_float64_1.2mm", "full_N"),
        ("reduced_float32_1.2mm", "reduced_N"),
        ("shipped_float32", "shipped_N"),
        ("default_sampling_float32", "default_sampling_N"),
    ):
        ok = acc[row]["ok"]
        acc[row] = {**curve_stats(np.asarray(curves[key]), travel, Ff, end), "ok": ok}


def compare(acc: dict, tilt: float, mu: float) -> None:
    """``acc["calculix"]``: the case's curves against CalculiX's, where CalculiX ran the case."""
    ref = REFS.get((tilt, mu))
    if ref is not None:
        travel, Ff, Fs, Fd = (
            np.asarray(acc["curves"][k]) for k in ("travel_mm", "full_N", "shipped_N", "default_sampling_N")
        )
        models = {"full_float64_1.2mm": Ff, "shipped_float32": Fs, "default_sampling_float32": Fd}
        acc["calculix"] = calculix_row(ref, travel, models)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--compare-only",
        action="store_true",
        help="only compare the curves in results/box_lid.json with each other and with the CalculiX curves "
        "now there; replot",
    )
    parser.add_argument(
        "--speed-only",
        action="store_true",
        help="only time the models again (speed, rate against order); keep the accuracy rows",
    )
    args = parser.parse_args(argv)
    if args.speed_only:
        out = json.loads((OUT / "box_lid.json").read_text())
        out.pop("code", None)
        base = jsnap.load_scene(SCENE)
        out["speed"] = timed(base)
        write_result(out, OUT / "box_lid.json")
        plot(out, _curves(out))
        return 0
    if args.compare_only:
        out = json.loads((OUT / "box_lid.json").read_text())
        for key, acc in out["accuracy"].items():
            model_stats(acc)
            compare(acc, float(key.split()[1]), float(key.split()[3]))
        curves = _curves(out)
        (OUT / "box_lid.json").write_text(json.dumps(out, indent=1) + "\n")
        plot(out, curves)
        return 0
    base = jsnap.load_scene(SCENE)
    c = base["connector"]
    out = {"scene": str(SCENE.name), "mesh_size": base["solver"]["mesh_size"], "accuracy": {}}
    curves = {}
    for tilt in (c["tilt"], 0.0):
        for mu in (0.0, 0.3):
            scene = base.replace({"connector.tilt": tilt, "contact.friction": mu})
            coarse = load_scene(COARSE, scene)
            full_model = jsnap.build(load_scene({"solver.method": "full", **FULL_CONTACT}, coarse))
            full = jsnap.rollout(full_model, dtype="float64")
            red_model = jsnap.build(coarse)
            red = jsnap.rollout(red_model)
            shipped_model = jsnap.build(scene)
            shipped = jsnap.rollout(shipped_model)
            dense = jsnap.rollout(jsnap.build(scene.replace(LID_DEFAULT_SAMPLING)))
            travel = np.asarray(full.travel)
            Ff, Fr, Fs, Fd = (np.asarray(r.insertion_force) for r in (full, red, shipped, dense))
            curves[tilt, mu] = (travel, Ff, Fr, Fs)
            acc = out["accuracy"][f"tilt {tilt:g} mu {mu:g}"] = {
                "full_dof_1.2mm": full_model.full_dof,
                "full_dof_shipped": shipped_model.full_dof,
                "reduced_orders_1.2mm": list(red_model.part.orders),
                "reduced_orders_shipped": list(shipped_model.part.orders),
                "full_float64_1.2mm": {"ok": bool(full.ok)},
                "reduced_float32_1.2mm": {"ok": bool(red.ok)},
                "shipped_float32": {"ok": bool(shipped.ok)},
                "default_sampling_float32": {"ok": bool(dense.ok)},
                "pairs_full_1.2mm": pairs(full_model, full),
                "pairs_shipped": pairs(shipped_model, shipped),
                "curves": {
                    "travel_mm": travel.tolist(),
                    "full_N": Ff.tolist(),
                    "reduced_N": Fr.tolist(),
                    "shipped_N": Fs.tolist(),
                    "default_sampling_N": Fd.tolist(),
                },
            }
            model_stats(acc)  # the models' rows from their curves
            if tilt:
                acc["predicted_delay_mm"] = c["spacing"] * float(np.tan(np.radians(tilt)))
                acc["hsv_tolerance"] = tolerance_sweep(coarse, red_model, Fr, travel, Ff)
                acc["smoothed_peak_N"] = {
                    "full_float64_1.2mm": smoothed_peak(Ff),
                    "shipped_float32": smoothed_peak(Fs),
                }
            else:
                acc["design_guide_mating_force_N"] = design_guide_force(scene)
            compare(acc, tilt, mu)
            print(
                f"tilt {tilt:g} mu {mu:g}:",
                json.dumps({k: v for k, v in acc.items() if k != "curves"}),
                flush=True,
            )
    out["speed"] = timed(base)
    write_result(out, OUT / "box_lid.json")
    plot(out, curves)
    return 0


def timed(base) -> dict:
    """Section 4 and 5 of the module docstring: the speed rows, in one process."""
    rows = speed(load_scene(COARSE, base), 5, full_runs=1)
    shipped = jsnap.build(base)
    rows["shipped_reduced_float32"] = timing_row(shipped, 5)
    rows["light_against_default"] = light_against_default(base)
    rows["problem_sizes"] = problem_sizes(base)
    rows["rate_against_order"] = rate_against_order(base)
    rows["solve_alone"] = solve_alone(shipped)
    return rows


def _curves(out) -> dict:
    """{(tilt, mu): (travel, full, reduced, shipped)} from a result's accuracy rows."""
    curves = {}
    for key, acc in out["accuracy"].items():
        tilt, mu = float(key.split()[1]), float(key.split()[3])
        curves[tilt, mu] = tuple(
            np.asarray(acc["curves"][k]) for k in ("travel_mm", "full_N", "reduced_N", "shipped_N")
        )
    return curves


def plot(out, curves):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 4, figsize=(21, 4.8), gridspec_kw={"width_ratios": [2, 2, 1, 1.3]})
    for a, tilt in zip(ax[:2], sorted({t for t, _ in curves}, reverse=True), strict=True):
        for mu in (0.0, 0.3):
            travel, Ff, Fr, Fs = curves[tilt, mu]
            colour = a.plot(travel, Fs, label=f"shipped: reduced float32, 0.8 mm, mu {mu:g}")[0].get_color()
            a.plot(travel, Ff, "--", color=colour, lw=1.0, label=f"full float64, 1.2 mm, mu {mu:g}")
            a.plot(travel, Fr, ":", color=colour, lw=1.0, label=f"reduced float32, 1.2 mm, mu {mu:g}")
            ref = REFS.get((tilt, mu))
            if ref is not None:
                d = np.genfromtxt(ref, delimiter=",", names=True)
                a.plot(
                    d["plug_travel_mm"],
                    d["insertion_force_N"],
                    ".",
                    color=colour,
                    ms=3,
                    label=f"CalculiX, mu {mu:g}",
                )
        if tilt:
            acc = out["accuracy"][f"tilt {tilt:g} mu 0"]["pairs_shipped"]
            for side, ls in (("minus_y", ":"), ("plus_y", "-.")):
                a.axvline(
                    acc[side]["first_contact_travel_mm"],
                    color="0.5",
                    ls=ls,
                    lw=0.8,
                    label=f"{side} pair's first contact",
                )
        else:
            guide = out["accuracy"]["tilt 0 mu 0"]["design_guide_mating_force_N"]
            a.axhline(guide, color="C0", ls=":", lw=0.8, label="design guide, mu 0 (four hooks)")
        a.axhline(0, color="0.6", lw=0.5)
        a.set(
            xlabel="travel of the box (mm)",
            ylabel="insertion force (N)",
            title=f"box lid, box tilted {tilt:g} deg",
        )
        a.legend(fontsize=7)
    skip = ("rate_against_order", "solve_alone", "light_against_default", "problem_sizes")
    plot_speed(ax[2], {k: v for k, v in out["speed"].items() if k not in skip})
    order = out["speed"].get("rate_against_order")
    if order is not None:
        r = np.array([row["dof"] for row in order["rows"].values()])
        us = np.array([1e6 / row["steps_per_second"] for row in order["rows"].values()])
        ax[3].plot(r, us, "o", label="shipped mesh, reduced float32")
        for tol, x, y in zip(order["rows"], r, us, strict=True):
            ax[3].annotate(f"hsv {tol}", (x, y), fontsize=7, xytext=(4, -10), textcoords="offset points")
        grid = np.linspace(0, r.max(), 50)
        ax[3].plot(
            grid,
            order["us_per_step_at_no_coordinates"] + order["us_per_step_per_coordinate"] * grid,
            "--",
            lw=0.8,
            label="least-squares line",
        )
        ax[3].axhline(1000, color="k", ls="--", lw=0.8, label="1 kHz")
        alone = out["speed"].get("solve_alone")
        for name, ls in (("spg", "-"), ("admm", ":")) if alone else ():
            us = alone[name]["us_per_step_less_call_overhead"]
            label = f"contact solve alone ({name.upper()}): {us:.0f} us"
            ax[3].axhline(us, color="C3", ls=ls, lw=0.8, label=label)
        ax[3].set(
            xlim=(0, None),
            ylim=(0, None),
            xlabel="reduced coordinates",
            ylabel="us per step (compiled rollout)",
            title="box lid: step time against the reduced order",
        )
        ax[3].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(OUT / "box_lid.png", dpi=110)


if __name__ == "__main__":
    raise SystemExit(main())
