"""``jsnap simulate``: run a scene, write what a user looks at, and say honestly how it went.

Outputs in the ``--out`` folder (checked before anything is built):

- ``forces.csv``: per step, time, travel, insertion force, the base wrench (force and moment),
  the drive's wrench (force and moment), the rigid part's pose (centre and unit quaternion),
  the energy, the step's work and what friction and the normal forces took, how deep the
  deformable part went into the rigid part, and the step's status flags;
- ``forces.png``: the force curves against travel and time;
- ``vtu/socket.pvd`` with ``socket_*.vtu``: the deformed part for ParaView, with each element's
  largest principal strain and von Mises stress (cell data);
- ``summary.json``: the strict-JSON summary (also printed with ``--json``), with the peak strain
  and stress of the whole run (every step; over the whole part, and over the arm below the hook,
  whose bending strain is the design guide's: ``jsnap._build.strain``).

Timings are apart: ``build_seconds`` (mesh, assembly, reduction, the parameter-dependent
operator), ``compile_seconds`` (XLA), and ``steps_per_second`` of the compiled rollout alone.
A run whose contact buffer was left at its default size (``contact.capacity``) and dropped
candidates is run again with a buffer that holds them (a warning says which capacity to set).
A run whose result carries an error flag (non-finite values, energy created, dropped contacts,
invalid parameters, a point lost deep inside the rigid part) writes its outputs, says what
happened at which step, and exits with 1.
"""

from __future__ import annotations

import json
import math
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

__all__ = [
    "NORMAL_DISSIPATION_LIMIT", "PEAK_FORCE_STEPS", "OutputError", "bending_wall", "check_out_dir",
    "design_guide_force", "design_guide_strain", "energy_to_peak", "peak_force", "run_sizing_buffer",
    "simulate",
]  # fmt: skip


class OutputError(ValueError):
    """The output folder cannot be used (the message names it and why)."""


def check_out_dir(out) -> Path:
    """The output folder, created if needed and checked writable, before any work is done.

    Raises:
        OutputError: ``out`` is a file, lies under a file, or cannot be written.
    """
    path = Path(out)
    if path.exists() and not path.is_dir():
        raise OutputError(f"--out {out}: exists and is not a folder")
    for parent in path.parents:
        if parent.exists() and not parent.is_dir():
            raise OutputError(f"--out {out}: {parent} is a file, not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path, prefix=".jsnap-write-check"):
            pass
    except OSError as err:
        raise OutputError(f"--out {out}: cannot write there ({err.strerror or type(err).__name__})") from None
    return path


# Presets made of cantilever hooks with a rigid root, and how many hooks the rigid part deflects
# (the design guide's beam formulas hold per hook; the box lid's four at once when untilted).
_HOOKS = {"cantilever": 1, "two_hook_clip": 2, "box_lid": 4, "cable_latch": 1}


def _lever(scene) -> float:
    """The design guide's cantilever length, mm: the arm's length for the hooks; for the latch,
    loaded part-way along its arm, the distance from its root to the top of the catch's flat
    (where the lip first pushes it in by the whole undercut)."""
    c = scene["connector"]
    if c["type"] == "cable_latch":
        from jsnap._geometry.scene import connector_geometry

        return c["length"] - connector_geometry(scene).z_flat_end
    return c["length"]


def ring_copies(scene) -> float | None:
    """How many of the modelled sectors make the whole ring (360 / connector.sector) for the
    annular preset, else None."""
    c = scene["connector"]
    return 360.0 / c["sector"] if c and c["type"] == "annular" else None


def _annular_guide_force(c, E: float, nu: float, mu: float) -> float:
    """The design guide's mating force of an annular snap (an elastic hub on a rigid shaft, the
    joint near the hub's end), the whole ring's, N: W = P (mu + tan a) / (1 - mu tan a),
    P = y d E X_N, X_N = 0.62 sqrt((k - 1) / (k + 1)) / ((k^2 + 1) / (k^2 - 1) + nu),
    k = d_o / d; y = 2 y_u the diametral undercut, d = 2 R, d_o = 2 (R + h)."""
    y, d, k = 2 * c["undercut"], 2 * c["radius"], (c["radius"] + c["thickness"]) / c["radius"]
    X = 0.62 * math.sqrt((k - 1) / (k + 1)) / ((k**2 + 1) / (k**2 - 1) + nu)
    ta = math.tan(math.radians(c["lead_angle"]))
    return y * d * E * X * (mu + ta) / (1 - mu * ta)


def design_guide_strain(scene) -> float | None:
    """Snap-fit design-guide strain at the root when the hook is deflected by the undercut:
    eps = 1.5 h y / L^2 (constant arm) or h y / (1.09 L^2) (arm tapered to h/2), dimensionless
    (None for a part from a file). For the cable latch L is the catch's distance from the root;
    for the annular snap the guide's hoop strain y / d = undercut / radius (y = 2 y_u the
    diametral undercut, d = 2 R).

    Beam theory for a deflection y of a cantilever of length L and root thickness h at its
    load: no stress concentration at the root, the root clamped.
    """
    c = scene["connector"]
    if c and c["type"] == "annular":
        return c["undercut"] / c["radius"]
    if not c or c["type"] not in _HOOKS:
        return None
    L, h, y = _lever(scene), c["thickness"], c["undercut"]
    h_tip = c.get("tip_thickness") or h
    return y * h / (1.09 * L**2) if abs(h_tip - h / 2) < 1e-9 else 1.5 * h * y / L**2


def design_guide_force(scene) -> float | None:
    """Snap-fit design-guide mating force W = P (mu + tan a) / (1 - mu tan a), N, of the
    hook presets, the sum over the hooks (None for a part from a file).

    P = b h^2 E eps / (6 L) with eps from :func:`design_guide_strain`; a beam-theory estimate
    (see the validation page for how far it is off). For the annular snap, the ring's force
    (:func:`_annular_guide_force`) over :func:`ring_copies`: the modelled sector's share.
    """
    c, m = scene["connector"], scene["material"]
    if c and c["type"] == "annular":
        W = _annular_guide_force(c, m["youngs_modulus"], m["poissons_ratio"], scene["contact"]["friction"])
        return W / ring_copies(scene)
    if not c or c["type"] not in _HOOKS:
        return None
    L, h, b = _lever(scene), c["thickness"], c["width"]
    eps = design_guide_strain(scene)
    P = b * h**2 * m["youngs_modulus"] * eps / (6 * L)
    mu, ta = scene["contact"]["friction"], math.tan(math.radians(c["lead_angle"]))
    return _HOOKS[c["type"]] * P * (mu + ta) / (1 - mu * ta)


# The headline peak force counts each step's force up to the robust straight line (Theil-Sen:
# the median of the pairwise slopes, then the median intercept) through it and the steps before
# it, this many in all. The force of a point contact has one- and two-step outliers of either
# sign where the set of active contact points changes (a point lets go for a step and comes
# back, or enters deep and is pushed out within a step: an impulse put into one step and taken
# back in the next); they change with the mesh where the curve does not. The line ignores up to
# two of nine steps, and on a curve that is smooth over nine steps it runs through the step,
# so the peak of a rising branch before a snap is kept as it is.
PEAK_FORCE_STEPS = 9


def peak_force(force) -> tuple[float, int]:
    """The headline peak insertion force of a force history (n,), N, and its step: the largest
    over the steps ``k`` of ``min(F[k], line_k(k))``, ``line_k`` the Theil-Sen line through the
    :data:`PEAK_FORCE_STEPS` steps up to ``k`` (fewer for the first steps; the steps whose
    force is not finite left out; at least three finite, or all a shorter history has). NaN, -1
    where no step is finite."""
    F = np.asarray(force, dtype=np.float64)
    W = PEAK_FORCE_STEPS
    padded = np.concatenate([np.full(W - 1, np.nan), np.where(np.isfinite(F), F, np.nan)])
    y = np.lib.stride_tricks.sliding_window_view(padded, W)  # (n, W): the steps up to k
    i, j = np.triu_indices(W, 1)
    x = np.arange(W, dtype=np.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # windows without a finite pair
        slope = np.nanmedian((y[:, j] - y[:, i]) / (j - i), axis=1)
        end = np.nanmedian(y - slope[:, None] * x, axis=1) + slope * (W - 1)
    enough = np.isfinite(y).sum(axis=1) >= min(3, int(np.isfinite(F).sum()))
    value = np.where(enough & np.isfinite(F), np.fmin(F, end), np.nan)
    if not np.isfinite(value).any():
        return math.nan, -1
    k = int(np.nanargmax(value))
    return float(value[k]), k


def bending_wall(scene) -> float:
    """The wall thickness the bending strain is read in, mm (:func:`jsnap._build.strain.bending_strain`):
    a preset's ``connector.thickness``; a part file's thinnest wall."""
    c = scene["connector"]
    if c:
        return float(c["thickness"])
    from jsnap._geometry.part import part_thinnest_wall
    from jsnap._geometry.scene import scene_file

    return float(part_thinnest_wall(scene_file(scene, "part.mesh"), scene["part"]["units"])[0])


def _finite(x):
    """A float for strict JSON: None where not finite."""
    x = float(x)
    return x if math.isfinite(x) else None


# Share of the rigid part's work up to the peak force that the normal contact forces may take
# before a run is warned. Measured (float64): the shipped presets and the pipe clip of
# tests/data take at most 1.7 % frictionless and 1.8 % at friction 0.3; the pipe clip whose face
# points held its pin across a gap (without the hand-over of docs/contact.md "Normals") took 73 %
# frictionless (docs/contact.md "Energy").
NORMAL_DISSIPATION_LIMIT = 0.05


def energy_to_peak(res) -> tuple[dict, str | None]:
    """The energy budget of one rollout up to its peak insertion force, N mm: the rigid part's
    work, the deformable part's energy, and what friction and the normal contact forces took
    (``jsnap.Result.friction_dissipation``, ``normal_dissipation``); with a warning (or None)
    when the normal forces took more than :data:`NORMAL_DISSIPATION_LIMIT` of the work.

    Up to the peak the rigid part slides over the deformable one and nothing lands on it, so
    the normal forces of a contact whose gap stays closed take no energy; a contact that holds
    a point across a gap takes energy step after step (docs/contact.md "Energy"). A warning is
    a reason to check the run frictionless (energy against work) and at half the time step.
    """
    F = np.asarray(res.insertion_force, np.float64)
    if not np.isfinite(F).any():
        return {}, None
    k = int(np.nanargmax(F)) + 1
    parts = (res.work, res.friction_dissipation, res.normal_dissipation)
    work, friction, normal = (float(np.sum(np.asarray(a, np.float64)[:k])) for a in parts)
    budget = {
        "work_Nmm": _finite(work),
        "energy_Nmm": _finite(np.asarray(res.energy, np.float64)[k - 1]),
        "friction_dissipation_Nmm": _finite(friction),
        "normal_dissipation_Nmm": _finite(normal),
    }
    if not (work > 0 and normal > NORMAL_DISSIPATION_LIMIT * work):
        return budget, None
    return budget, (
        f"the normal contact forces took {100 * normal / work:.1f} % of the rigid part's work before the peak "
        f"force (more than {100 * NORMAL_DISSIPATION_LIMIT:g} %): contacts held points across a gap, so forces "
        "may be too high; check the run frictionless (energy against work) and at half solver.dt "
        "(docs/own-connector.md)"
    )


def plot_forces(res, out: Path, guide: float | None, title: str) -> Path:
    """``forces.png``: insertion, base and lateral force against travel and time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    travel = np.asarray(res.travel)
    t = np.asarray(res.t) * 1e3
    F = np.asarray(res.insertion_force)
    fig, ax = plt.subplots(1, 2, figsize=(12, 4.5))
    for a, xv, xl in (
        (ax[0], travel, "travel of the rigid part along its insertion axis (mm)"),
        (ax[1], t, "time (ms)"),
    ):
        a.plot(xv, F, label="insertion force (N)", lw=1.6)
        a.plot(
            xv, np.linalg.norm(np.asarray(res.base_force), axis=1), label="|base force| (N)", lw=1.0, alpha=0.8
        )
        a.plot(
            xv, np.asarray(res.lateral_force), label="lateral force on the rigid part, x (N)", lw=1.0, alpha=0.8
        )
        if guide is not None:
            a.axhline(guide, color="k", ls="--", lw=0.8, label=f"design-guide mating force {guide:.2f} N")
        a.axhline(0, color="0.6", lw=0.5)
        a.set_xlabel(xl)
        a.set_ylabel("force (N)")
        a.grid(alpha=0.3)
    if np.isfinite(F).any():
        k = int(np.nanargmax(F))
        ax[0].annotate(
            f"peak {F[k]:.2f} N at {travel[k]:.2f} mm",
            (travel[k], F[k]),
            xytext=(8, 10),
            textcoords="offset points",
            fontsize=8,
            arrowprops=dict(arrowstyle="-", lw=0.6),
        )
    ax[0].legend(fontsize=8, loc="lower left")
    fig.suptitle(title)
    fig.tight_layout()
    path = out / "forces.png"
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def write_forces_csv(res, path: Path) -> Path:
    """``forces.csv``: one row per step (see the module docstring for the columns)."""
    cols = np.column_stack(
        [
            np.asarray(res.t),
            np.asarray(res.travel),
            np.asarray(res.insertion_force),
            np.asarray(res.lateral_force),
            np.asarray(res.base_force),
            np.asarray(res.base_moment),
            np.asarray(res.coupling_force),
            np.asarray(res.coupling_moment),
            np.asarray(res.plug),
            np.asarray(res.plug_rotation),
            np.asarray(res.energy),
            np.asarray(res.work),
            np.asarray(res.friction_dissipation),
            np.asarray(res.normal_dissipation),
            np.asarray(res.penetration),
            np.asarray(res.flags),
        ]
    )
    header = (
        "t_s,travel_mm,insertion_force_N,lateral_force_N,base_fx_N,base_fy_N,base_fz_N,"
        "base_mx_Nmm,base_my_Nmm,base_mz_Nmm,coupling_fx_N,coupling_fy_N,coupling_fz_N,"
        "coupling_mx_Nmm,coupling_my_Nmm,coupling_mz_Nmm,rigid_x_mm,rigid_y_mm,rigid_z_mm,"
        "rigid_qw,rigid_qx,rigid_qy,rigid_qz,energy_Nmm,work_Nmm,friction_dissipation_Nmm,"
        "normal_dissipation_Nmm,penetration_mm,flags"
    )
    np.savetxt(path, cols, delimiter=",", header=header, comments="", fmt="%.8g")
    return path


def arm_box(connector) -> tuple[float, float] | None:
    """``(x_max, z_max)`` of the preset's bending arm, mm: its elements are those with every
    vertex at ``z <= z_max`` and ``x <= x_max`` (below the hook, or for the cable latch below its
    root and inside its outer face, without the catch); None for a part from a file."""
    if not connector:
        return None
    if connector["type"] == "cable_latch":
        return connector["thickness"], connector["length"]
    return math.inf, connector["length"]


def arm_elements(nodes: np.ndarray, cells: np.ndarray, arm: tuple[float, float] | float) -> np.ndarray:
    """(m,) bool: the elements with every vertex at ``x <= x_max`` and ``z <= z_max`` for
    ``arm = (x_max, z_max)`` mm (see :func:`arm_box`; a number is ``z_max``)."""
    x_max, z_max = (math.inf, arm) if np.isscalar(arm) else arm
    vert = nodes[cells[:, :4]]
    tol = 1e-12 * float(np.linalg.norm(np.ptp(nodes, axis=0)))
    return np.all((vert[..., 2] <= z_max + tol) & (vert[..., 0] <= x_max + tol), axis=1)


def write_series(
    model, res, out: Path, arm: tuple[float, float] | float | None, frames: int = 100, bending=None
):
    """The strain of every step and the deformed part at about ``frames`` times as a ParaView
    series (``vtu/socket.pvd``, with each element's largest principal strain and von Mises
    stress as cell data). Returns ``(pvd path, {"part": PeakStrain, "arm": PeakStrain})``:
    the peaks of the whole run over every element and over the arm's (every vertex at
    ``x <= x_max`` and ``z <= z_max`` for ``arm = (x_max, z_max)`` mm, see :func:`arm_box`; a
    number is ``z_max``; no "arm" for ``arm = None``, a part from a file), and with a
    ``bending`` region (:func:`jsnap._build.strain.bending_region`) ``"bending"``: the
    :class:`jsnap._build.strain.BendingStrain` read there, the rollout's contacts left out."""
    from jsnap._build.strain import scan
    from jsnap._geometry.mesh import write_vtu_series

    x = np.asarray(res.x)
    keep = np.arange(0, x.shape[0], max(1, x.shape[0] // frames))
    E, nu = float(model.params.E), float(model.params.nu)
    nodes, cells = np.asarray(model.mesh.nodes), np.asarray(model.mesh.cells)
    regions = {"part": None}
    if arm is not None:
        regions["arm"] = arm_elements(nodes, cells, arm)
    t = np.asarray(res.t, dtype=np.float64)
    contacts = None if bending is None else (np.asarray(res.contact_index), np.asarray(res.contact_active))
    peaks, kept = scan(model, x, t, E, nu, keep=keep, regions=regions, bending=bending, contacts=contacts)
    cell_data = {"max_principal_strain": kept["max_principal"], "von_mises_stress_MPa": kept["von_mises"]}
    pvd = write_vtu_series(
        out / "vtu",
        "socket",
        nodes,
        cells,
        kept["displacement"],
        t[keep],
        cell_data=cell_data,
    )
    return pvd, peaks


def _strain_fields(prefix: str, peak, res) -> dict:
    """The summary's fields of one :class:`jsnap.PeakStrain` (None where no step is finite, or
    for no peak: the arm of a part from a file)."""
    if peak is None:
        names = ("peak_strain", "peak_strain_step", "peak_strain_time_s", "peak_strain_travel_mm")
        return {f"{prefix}{k}": None for k in (*names, "peak_strain_position_mm", "peak_von_mises_MPa")}
    k = peak.step if peak.step >= 0 else None
    return {
        f"{prefix}peak_strain": _finite(peak.max_principal) if k is not None else None,
        f"{prefix}peak_strain_step": k,
        f"{prefix}peak_strain_time_s": _finite(peak.time) if k is not None else None,
        f"{prefix}peak_strain_travel_mm": _finite(np.asarray(res.travel)[k]) if k is not None else None,
        f"{prefix}peak_strain_position_mm": [_finite(c) for c in peak.position] if k is not None else None,
        f"{prefix}peak_von_mises_MPa": _finite(peak.von_mises) if peak.von_mises_step >= 0 else None,
    }


def _bending_fields(bend) -> dict:
    """How the summary's bending strain was found (:class:`jsnap._build.strain.BendingStrain`)."""
    found = None
    if bend.step >= 0:
        found = "extrapolated to a singular edge" if bend.at_edge else "read away from the singular edges"
    region = bend.region
    return {
        "bending_strain_found": found,
        "bending_wall_mm": _finite(bend.wall),
        "bending_singular_edges": int(region.edges.shape[0]),
        "bending_paths": int(region.root.shape[0]),
        "bending_strain_readout_mm": [_finite(d) for d in bend.readout_distance] if bend.at_edge else None,
        "bending_strain_readout": [_finite(v) for v in bend.readout] if bend.at_edge else None,
    }


def _say(quiet: bool, message: str) -> None:
    if not quiet:
        print(message, file=sys.stderr, flush=True)


def _wider_buffer(scene, model, res) -> int | None:
    """The contact buffer to run again with, or None: where a step dropped candidates and the
    scene left ``contact.capacity`` at its default, the power of two that holds the most
    candidates a step had, and at least twice the slots (at most the candidate points). The
    default is sized for one narrow hook; a wide or many-hooked part can need more, and the
    buffer's size is fixed before compiling (as JAX-MD's neighbour lists, rebuilt larger when
    they overflow). A capacity the scene sets is kept: its overflow is reported as an error."""
    capacity = model.contact.capacity
    most = int(np.max(np.asarray(res.overflow), initial=0))
    if scene.is_set("contact.capacity") or capacity >= model.n_samples or most <= 0:
        return None
    return min(max(2 * capacity, 1 << (capacity + most - 1).bit_length()), model.n_samples)


def run_sizing_buffer(scene, model, run, say=None):
    """``run(model)`` (a rollout that returns its :class:`jsnap.Result`), run again with the
    :func:`_wider_buffer` while it asks for one; ``say(message)`` is told of each rerun.

    Returns ``(model, result, widened_from)``: the model of the last run, its result, and the
    default capacity the first run overflowed (None: it was not repeated)."""
    from jsnap._build.model import with_capacity

    widened_from = None
    while True:
        res = run(model)
        wider = _wider_buffer(scene, model, res)
        if wider is None:
            return model, res, widened_from
        if say is not None:
            say(
                f"jsnap: {int(np.count_nonzero(np.asarray(res.overflow)))} steps had more contact candidates "
                f"than the {model.contact.capacity} slots of the default contact.capacity; running again "
                f"with {wider} slots ..."
            )
        widened_from = widened_from or model.contact.capacity
        model = with_capacity(model, wider)


def simulate(args) -> int:
    """The ``simulate`` command (see the module docstring); returns the exit code."""
    import jax

    from jsnap._build.model import build_model
    from jsnap._core.rollout import _check_controls, _whole, contact_resolution
    from jsnap._core.step import prepare
    from jsnap._geometry.scene import load_scene

    quiet = args.json
    out = check_out_dir(args.out)
    t0 = time.perf_counter()
    scene = load_scene(args.scene)
    if args.method:
        scene = scene.replace({"solver.method": args.method})
    model, report = build_model(scene, progress=not quiet)
    with jax.enable_x64(True):
        prepared = prepare(model)
        jax.block_until_ready(prepared.op)
        dtype = jax.numpy.dtype(model.dtype)
        controls = jax.numpy.asarray(_check_controls(np.asarray(model.motion[1:])), dtype)
        start = jax.numpy.asarray(model.plug_start, dtype)
        t_build = time.perf_counter() - t0
        _say(quiet, f"jsnap: built in {t_build:.1f} s; compiling the rollout ({model.n_steps} steps) ...")
        times = {}

        def run(model):
            t1 = time.perf_counter()
            compiled = _whole.lower(model, prepared, controls, start, True).compile()
            times["compile"] = time.perf_counter() - t1
            _say(quiet, f"jsnap: compiled in {times['compile']:.1f} s; running ...")
            t2 = time.perf_counter()
            res = compiled(model, prepared, controls, start, True)
            jax.block_until_ready(res.energy)
            times["run"] = time.perf_counter() - t2
            return res

        model, res, widened_from = run_sizing_buffer(scene, model, run, lambda m: _say(quiet, m))
        t_compile, t_run = times["compile"], times["run"]
    status = res.status()
    F = np.asarray(res.insertion_force)
    base = np.asarray(res.base_force)
    guide = design_guide_force(scene)
    csv = write_forces_csv(res, out / "forces.csv")
    name = Path(scene.source).name
    title = f"jsnap: {name}, {model.method} {model.element}, {model.n_dof} dof, dt = {model.dt * 1e3:g} ms"
    png = plot_forces(res, out, guide, title)
    t3 = time.perf_counter()
    from jsnap._build.strain import bending_region

    wall = bending_wall(scene)
    pvd, peaks = write_series(model, res, out, arm_box(scene["connector"]), bending=bending_region(model, wall))
    t_strain = time.perf_counter() - t3
    warnings = []
    if widened_from is not None:
        warnings.append(
            f"the default contact.capacity ({widened_from} slots) dropped contact candidates, so the rollout "
            f"was run again with {model.contact.capacity}; set contact.capacity = {model.contact.capacity} in "
            "the scene to skip the first run"
        )
    residual = np.asarray(res.residual)
    loose = residual > 100 * scene["contact"]["tolerance"]
    if loose.any():
        warnings.append(
            f"the contact solve stopped above 100x contact.tolerance in {int(loose.sum())} of {F.size} steps "
            "(raise contact.iterations for a tighter solve)"
        )
    pen = np.asarray(res.penetration)
    budget, lost = energy_to_peak(res)
    if lost is not None:
        warnings.append(lost)
    peak = int(np.nanargmax(F)) if np.isfinite(F).any() else 0
    headline, at_headline = peak_force(F)
    reduction = report.reduction or {}
    summary = {
        "scene": scene.source,
        "status": status,
        "steps": int(F.size),
        "dt": model.dt,
        "method": model.method,
        "element": model.element,
        "dtype": model.dtype,
        "dof": model.n_dof,
        "full_dof": model.full_dof,
        "reduced_orders": list(getattr(model.part, "orders", ())),
        "contact_points": model.n_samples,
        "steps_per_second": F.size / t_run,
        "real_time_factor": F.size * model.dt / t_run,
        "build_seconds": t_build,
        "compile_seconds": t_compile,
        "run_seconds": t_run,
        "reduction_cached": reduction.get("cached"),
        # The headline peak force: each step's force up to the robust line through it and the
        # peak_force_steps - 1 steps before it (peak_force).
        "peak_force_N": _finite(headline),
        "travel_at_peak_force_mm": _finite(np.asarray(res.travel)[at_headline]) if at_headline >= 0 else None,
        "peak_force_steps": PEAK_FORCE_STEPS,
        # The largest single step's force: a diagnostic (a one-step contact impulse shows here).
        "peak_insertion_force_N": _finite(np.nanmax(F)) if np.isfinite(F).any() else None,
        "travel_at_peak_mm": _finite(np.asarray(res.travel)[peak]),
        "peak_base_force_N": _finite(np.nanmax(np.linalg.norm(base, axis=1)))
        if np.isfinite(base).any()
        else None,
        "min_insertion_force_N": _finite(np.nanmin(F)) if np.isfinite(F).any() else None,
        "design_guide_mating_force_N": guide,
        # The annular preset models a sector: the whole ring's forces are this many times its.
        "ring_copies": ring_copies(scene),
        "insertion_axis": np.asarray(model.axis).tolist(),
        "peak_base_moment_Nmm": _finite(np.nanmax(np.linalg.norm(np.asarray(res.base_moment), axis=1)))
        if np.isfinite(np.asarray(res.base_moment)).any()
        else None,
        # The headline strain: in the bending region, away from the singular edges and the
        # contacts (jsnap._build.strain.bending_strain), and how it was found.
        **_strain_fields("bending_", peaks["bending"], res),
        **_bending_fields(peaks["bending"]),
        # Diagnostics: the largest strain over the whole part (at a singular edge or a contact
        # where there is one) and over a preset's arm box.
        **_strain_fields("", peaks["part"], res),
        **_strain_fields("arm_", peaks.get("arm"), res),
        "design_guide_strain": design_guide_strain(scene),
        "strain_seconds": t_strain,
        "max_contact_overflow": int(np.max(np.asarray(res.overflow))),
        "contact_capacity": model.contact.capacity,
        # The default capacity the first run overflowed (None: the run was not repeated).
        "contact_capacity_widened_from": widened_from,
        "max_solver_residual": _finite(np.nanmax(residual)) if np.isfinite(residual).any() else None,
        # The deepest any contact point went into the rigid part, mm, and that in contact
        # resolutions (Result.penetration; DEEP_PENETRATION flags a run deeper than
        # PENETRATION_DEPTH of them).
        "max_penetration_mm": _finite(np.nanmax(pen)) if np.isfinite(pen).any() else None,
        "max_penetration_resolutions": _finite(np.nanmax(pen) / contact_resolution(model))
        if np.isfinite(pen).any()
        else None,
        # Up to the peak insertion force, N mm (energy_to_peak).
        "energy_to_peak": budget,
        "outputs": {"csv": str(csv), "png": str(png), "pvd": str(pvd)},
        "warnings": warnings,
    }
    text = json.dumps(summary, allow_nan=False)
    (out / "summary.json").write_text(json.dumps(summary, indent=2, allow_nan=False))
    if args.json:
        print(text)
    else:
        for w in warnings:
            print(f"jsnap: warning: {w}", file=sys.stderr)
        if summary["peak_force_N"] is not None:
            peak, at = summary["peak_force_N"], summary["travel_at_peak_force_mm"]
            rate, real = summary["steps_per_second"], summary["real_time_factor"]
            copies = summary["ring_copies"]
            ring = "" if copies is None else f" (a 1/{copies:g} sector: the whole ring's {copies * peak:.1f} N)"
            print(
                f"jsnap: {F.size} steps ({model.method} model, {model.n_dof} dof), peak insertion force "
                f"{peak:.3f} N at {at:.3f} mm{'' if guide is None else f' (design guide {guide:.3f} N)'}"
                f"{ring} (each step up to the robust line through its last {PEAK_FORCE_STEPS}; largest step "
                f"{summary['peak_insertion_force_N']:.3f} N); "
                f"{rate:.0f} steps/s "
                f"({real:.1f}x real time); build {t_build:.1f} s, compile {t_compile:.1f} s; wrote {out}/"
            )
        how = {
            "extrapolated to a singular edge": "extrapolated to a sharp edge from 1-3 walls out",
            "read away from the singular edges": "away from the sharp edges",
        }.get(summary["bending_strain_found"], "")
        for prefix, what in (
            ("bending_", f"in the bending region ({how}, wall {summary['bending_wall_mm']:.3g} mm)"),
            ("arm_", "in the arm box (diagnostic)"),
            ("", "over the part (diagnostic: singular at sharp edges and contacts)"),
        ):
            if summary[f"{prefix}peak_strain"] is None:
                continue
            eps, where = summary[f"{prefix}peak_strain"], summary[f"{prefix}peak_strain_position_mm"]
            guide_eps = ""
            if prefix == "bending_" and summary["design_guide_strain"] is not None:
                guide_eps = f" (design guide {100 * summary['design_guide_strain']:.3f} %)"
            print(
                f"jsnap: peak strain {what} {100 * eps:.3f} %{guide_eps}, largest principal, at travel "
                f"{summary[f'{prefix}peak_strain_travel_mm']:.3f} mm, (x, y, z) = ({where[0]:.2f}, "
                f"{where[1]:.2f}, {where[2]:.2f}) mm; von Mises stress up to "
                f"{summary[f'{prefix}peak_von_mises_MPa']:.1f} MPa"
            )
    if status != "ok":
        print(f"jsnap: error: {status}", file=sys.stderr)
        return 1
    return 0
