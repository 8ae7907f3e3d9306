"""Pieces the benchmark scripts share (not a benchmark itself: `jsnap bench` runs only the
registered names). Scripts import it as ``from _common import ...`` (their folder is on
``sys.path`` when run as ``python benchmarks/NAME.py`` and under ``jsnap bench``).

The shipped scene's defaults are the reduced model and a per-method rollout dtype (float64 for
the full model, float32 for the reduced and segmented ones), and several keys are internal. The
benchmarks state what they measure instead of leaning on defaults: :data:`FULL` and :data:`FLOAT32` are the
choices the scene made when the committed results were taken (the full model, float32
rollouts), and :func:`load_scene` applies changes that may include internal keys.
"""

from __future__ import annotations

import json
import os
import subprocess
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jsnap
from jsnap._core.status import ERRORS, NOT_CONVERGED, describe
from jsnap._core.util import cast_floats
from jsnap._geometry.scene import Scene, with_internal

# The deformable part's model and the rollout precision of the shipped scene up to the redesign
# (its defaults then; now "reduced", and float64 for every method but the reduced one).
FULL = {"solver.method": "full"}
FLOAT32 = {"solver.dtype": "float32"}
# The light contact settings several benchmarks compare against the scene's: candidate lines
# every 2.0 mm across the width (default 1.0), 24 slots (64), at most 200 solver iterations (500).
# reduction_speed.py adds the SPG solver and the 1e-4 residual for its speed rows.
LIGHT = {"contact.width_spacing": 2.0, "contact.capacity": 24, "contact.iterations": 200}
# The box lid (jsnap/scenes/box_lid.toml) at the default contact sampling and point load cases,
# with a finer reduction tolerance: the shipped scene samples its contact more coarsely and
# reduces it by patch loads for a 1 kHz step (benchmarks/box_lid.py). The benchmarks that study a
# mechanism on the lid (patch loads, the hand-over, the snap's sensitivity, XLA's kernels) run it
# this way, the contact sampled as on every other preset.
LID_DEFAULT_SAMPLING = {
    "contact.width_spacing": 1.0,
    "contact.spacing": 0.02,
    "solver.load_patch": 0.0,
    "solver.hsv_tolerance": 1e-3,
}
# A contact solve tight enough to stand for the exact one: ADMM (it converges where APGD stalls
# on these problems) to the 1e-10 residual, at most 20000 iterations; run it in float64. ADMM is
# an internal choice of contact.solver: apply it with :func:`load_scene` or ``with_internal``.
TIGHT_ADMM = {"contact.solver": "admm", "contact.iterations": 20000, "contact.tolerance": 1e-10}


def load_scene(changes: dict | None = None, scene: Scene | None = None) -> Scene:
    """``scene`` (default: the shipped default scene) with ``changes``, which may set internal
    keys and choices (``jsnap._geometry.scene.with_internal``: ADMM and PGS, the modal form,
    the segmentation's and the contact's internal settings)."""
    scene = jsnap.load_scene() if scene is None else scene
    return with_internal(scene, changes or {})


def code_version() -> dict:
    """The commit the numbers were taken at, the library files modified in the working tree, and
    the ``XLA_FLAGS`` the process runs with (the scripts opt in to XLA's small-loop option with
    ``jsnap.configure_xla_cpu()``, as the committed results were measured)."""
    here = Path(__file__).resolve().parent

    def git(*args):
        try:
            return subprocess.run(["git", *args], capture_output=True, text=True, cwd=here).stdout
        except OSError:
            return ""

    return {
        "commit": git("rev-parse", "HEAD").strip(),
        "modified": git("status", "--porcelain", "--", "../jsnap").splitlines(),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
    }


def jitted_step(model, prepared):
    """``(one, dyn, state0)``: ``one(dyn, state, control) -> next state``, the jitted
    ``jsnap.step`` called once per step from Python (the interactive case), in the model's
    rollout dtype (``model.dtype``); the model and operator are cast once, here.

    Call it in JAX's 64-bit mode (``with jax.enable_x64(True):``, as the scripts that use it run
    their whole measurement): jsnap enters that mode only while the step is traced, and JAX
    lowers a program the caller jits in the caller's mode, where the step's 64-bit indices do
    not lower."""
    if not jax.config.jax_enable_x64:
        raise RuntimeError("jitted_step: call it inside `with jax.enable_x64(True):` (see its docstring)")
    dtype = jnp.dtype(model.dtype)
    dyn, static = eqx.partition((cast_floats(model, dtype), cast_floats(prepared, dtype)), eqx.is_array)

    @jax.jit
    def one(dyn, state, control):
        m, p = eqx.combine(dyn, static)
        return jsnap.step(m, p, state, control)[0]

    return one, dyn, jsnap.init_state(model, dtype)


def two_step_compile_seconds(model, prepared) -> float:
    """Compile time of ``jsnap.rollout`` for ``model``, measured as the first call of a two-step
    rollout (the same scan body, compiled anew for that length): lets a slow rollout be run once."""
    t0 = time.perf_counter()
    jax.block_until_ready(jsnap.rollout(model, prepared=prepared, controls=model.trajectory()[1:3]).energy)
    return time.perf_counter() - t0


def scan_timing(model, prepared, runs: int, controls=None):
    """``(result of the first call, its seconds, the seconds of each further call)`` of
    ``jsnap.rollout``. With ``runs = 0`` (a slow rollout, run once) the one entry is the first
    call less the compile time, measured by :func:`two_step_compile_seconds`."""
    t0 = time.perf_counter()
    res = jsnap.rollout(model, prepared=prepared, controls=controls)
    jax.block_until_ready(res.energy)
    first = time.perf_counter() - t0
    if runs == 0:
        return res, first, [first - two_step_compile_seconds(model, prepared)]
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        jax.block_until_ready(jsnap.rollout(model, prepared=prepared, controls=controls).energy)
        times.append(time.perf_counter() - t0)
    return res, first, times


def moving_average(F, window: int) -> np.ndarray:
    """The centred ``window``-point moving average of ``F``, the same length (the ends
    averaged over the points there are)."""
    k = np.ones(window)
    return np.convolve(F, k, "same") / np.convolve(np.ones_like(F), k, "same")


def run_status(res) -> str:
    """``"ok"``, or what went wrong in a rollout (its error flags and the solver's warnings)."""
    return describe(np.asarray(res.flags), ERRORS | NOT_CONVERGED)


def curve_stats(F, travel, ref_F, rise_end: int | None = None):
    """Peak, its travel, and the RMS difference from ``ref_F`` (the same travels) in % of its
    peak over the whole motion and over the rise (up to ``ref_F``'s peak: after a snap the hooks
    ring against the rigid part's sides, which are exactly where their faces rest). Or up to the
    step ``rise_end``, where a single step of that ringing is ``ref_F``'s largest force: then
    both differences are in % of ``ref_F``'s peak on the rise."""
    k = int(np.argmax(F))
    rise = (int(np.argmax(ref_F)) if rise_end is None else int(rise_end)) + 1
    peak = ref_F[:rise].max()
    rmse = float(np.sqrt(np.mean((F - ref_F) ** 2)) / peak)
    rmse_rise = float(np.sqrt(np.mean((F[:rise] - ref_F[:rise]) ** 2)) / peak)
    return {
        "peak_N": float(F[k]),
        "travel_at_peak_mm": float(travel[k]),
        "rmse_of_full_peak": rmse,
        "rmse_rise_of_full_peak": rmse_rise,
    }


def calculix_row(path, travel, models):
    """Each model's (name -> insertion force at ``travel``) peak over the CalculiX curve's at
    ``path`` and their RMS difference in % of CalculiX's peak, over the travel the CalculiX curve
    covers and over its rise (up to 0.05 mm before its peak: the snap's steep drop, a few
    hundredths of a mm earlier or later, dominates the whole)."""
    d = np.genfromtxt(path, delimiter=",", names=True)
    ref_travel, ref_F = d["plug_travel_mm"], d["insertion_force_N"]
    window = travel <= ref_travel.max()
    row = {
        "reference": str(path.relative_to(Path(jsnap.__file__).parent)),
        "peak_N": float(ref_F.max()),
        "travel_at_peak_mm": float(ref_travel[np.argmax(ref_F)]),
        "travel_covered_mm": float(ref_travel.max()),
    }
    rise = travel <= ref_travel[np.argmax(ref_F)] - 0.05
    for name, F in models.items():
        interp = np.interp(travel, ref_travel, ref_F)
        row[name] = {
            "peak_over_reference": float(F[window].max() / ref_F.max()),
            "rms_difference_of_reference_peak": float(
                np.sqrt(np.mean((F[window] - interp[window]) ** 2)) / ref_F.max()
            ),
            "rms_rise_of_reference_peak": float(np.sqrt(np.mean((F[rise] - interp[rise]) ** 2)) / ref_F.max()),
        }
    return row


def plot_curves(ax, curves, refs) -> dict:
    """On ``ax``: for each friction ``mu`` of ``curves`` (mu -> (travel, full, reduced)), the
    full model's insertion force, the reduced model's (dashed) and the CalculiX curve at
    ``refs[mu]`` (dots, where the file exists), in one colour per mu. Returns mu -> colour."""
    colours = {}
    for mu, (travel, Ff, Fr) in curves.items():
        line = ax.plot(travel, Ff, label=f"full float64, mu {mu:g}")[0]
        colours[mu] = line.get_color()
        ax.plot(travel, Fr, "--", color=colours[mu], label=f"reduced float32 (shipped), mu {mu:g}")
        if refs[mu].is_file():
            d = np.genfromtxt(refs[mu], delimiter=",", names=True)
            label = f"CalculiX, mu {mu:g}"
            ax.plot(d["plug_travel_mm"], d["insertion_force_N"], ".", color=colours[mu], ms=3, label=label)
    return colours


def timing_row(model, runs: int) -> dict:
    """Steps/s of ``model``'s compiled rollout: the first call and the median of ``runs`` more,
    with the load average."""
    prepared = jsnap.prepare(model)
    _, first, times = scan_timing(model, prepared, runs)
    steps = model.motion.shape[0] - 1
    return {
        "dof": int(model.n_dof),
        "steps": steps,
        "first_call_s": first,
        "median_s": float(np.median(times)),
        "steps_per_second": steps / float(np.median(times)),
        "load_average": os.getloadavg()[0],
    }


def speed(scene, runs: int, full_runs: int | None = None) -> dict:
    """Steps/s of the compiled rollout (:func:`timing_row`): the shipped reduced model (float32)
    and the full model in float32 and float64, built from ``scene`` and timed in this process one
    after the other (``runs`` timed calls each after the first, ``full_runs`` for the full model:
    default ``runs``)."""
    rows = {}
    for name, changes in (
        ("reduced_float32", {}),
        ("full_float32", {"solver.method": "full", "solver.dtype": "float32"}),
        ("full_float64", {"solver.method": "full", "solver.dtype": "float64"}),
    ):
        model = jsnap.build(load_scene(changes, scene))
        rows[name] = timing_row(model, runs if name.startswith("reduced") or full_runs is None else full_runs)
        print(name, rows[name], flush=True)
    return rows


def recorded_problems(model, solver_class, active_only: bool = False) -> list:
    """The cone problems ``(W, q, mu, mask, gamma0)`` of ``model``'s rollout as its contact
    solver (of type ``solver_class``) received them: device arrays in the rollout's dtype, one
    per solve, warm starts included (a ``jax.debug.callback``). ``active_only``: only the solves
    with an active slot (the steps without contact solve an empty problem)."""
    if not isinstance(model.contact.solver, solver_class):
        name = type(model.contact.solver).__name__
        raise ValueError(f"the model solves its contact by {name}, not {solver_class.__name__}")
    recs = []
    original = solver_class.algorithm

    def keep(*a):
        if not active_only or np.asarray(a[3]).any():
            recs.append(tuple(jnp.asarray(x) for x in a))

    def recorded(W, q, mu, mask, *, max_iters, tol, gamma0=None, **kw):
        sol = original(W, q, mu, mask, max_iters=max_iters, tol=tol, gamma0=gamma0, **kw)
        jax.debug.callback(keep, W, q, mu, mask, gamma0)
        return sol

    # The algorithm is the solver component's class attribute, looked up when the step is
    # traced: a model compiled before would hit the jit cache and skip it.
    jax.clear_caches()
    solver_class.algorithm = staticmethod(recorded)
    try:
        jax.block_until_ready(jsnap.rollout(model).energy)
    finally:
        solver_class.algorithm = staticmethod(original)
        # The same model later hits the jit cache: without this it would be timed with the
        # callback in its program (measured: 2x slower per step, and no compile).
        jax.clear_caches()
    return recs


def write_result(out: dict, path: Path) -> None:
    """``out`` as JSON at ``path``, stamped with the load average, the CPUs, the date and the
    code version."""
    out["load_average_after"] = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    out["cpus"] = os.cpu_count()
    out["date"] = time.strftime("%Y-%m-%d %H:%M")
    out["code"] = code_version()
    path.parent.mkdir(exist_ok=True)
    path.write_text(json.dumps(out, indent=1) + "\n")


def presets_option(parser, known, argv, option: str = "presets") -> list[str]:
    """The names that ``--presets`` (or ``--<option>``) gives (comma-separated; default: all
    of ``known``); an unknown name is a parser error naming it."""
    parser.add_argument(f"--{option}", default=",".join(known), help="comma-separated; default: all")
    names = getattr(parser.parse_args(argv), option).split(",")
    unknown = sorted(set(names) - set(known))
    if unknown:
        parser.error(f"--{option}: unknown {', '.join(unknown)} (known: {', '.join(known)})")
    return names


def previous_result(path: Path, rerun, known) -> dict:
    """The result at ``path`` when only some of ``known`` are rerun (its other rows are kept);
    empty for a run of all of them or when there is none."""
    if set(rerun) == set(known) or not path.exists():
        return {}
    return json.loads(path.read_text())


def kept_rows(previous: dict, rerun, known) -> dict:
    """The rows (``["presets"]``) of :func:`previous_result` for the presets not rerun; each
    carries its own date and commit (:func:`stamped`)."""
    rows = previous.get("presets", {})
    return {p: r for p, r in rows.items() if p in known and p not in rerun}


def stamped(row: dict) -> dict:
    """``row`` with the date and the commit it was measured at."""
    return row | {"date": time.strftime("%Y-%m-%d %H:%M"), "commit": code_version()["commit"]}


def plot_speed(ax, rows: dict) -> None:
    """On ``ax``: the steps/s of each timing row (name -> :func:`timing_row`) as bars on a log
    scale, against 1 kHz, titled with the first row's load average."""
    names = list(rows)
    ax.bar(names, [rows[n]["steps_per_second"] for n in names])
    ax.axhline(1000, color="k", ls="--", lw=0.8, label="1 kHz")
    ax.set_yscale("log")
    ax.set(
        ylabel="steps/s (compiled rollout)", title=f"speed, load average {rows[names[0]]['load_average']:.1f}"
    )
    labels = [n.replace("_float", "\nfloat") + f"\n{rows[n]['dof']} dof" for n in names]
    ax.set_xticks(range(len(names)), labels, fontsize=7)
    ax.legend(fontsize=8)
