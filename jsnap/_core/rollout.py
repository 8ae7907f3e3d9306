"""Rollouts: a scene's whole motion from rest, one at a time or batched.

``rollout`` runs a ``lax.scan`` of :func:`jsnap._core.step._step` over the desired rigid-part
centres; ``rollout_batch`` is the same under ``jax.vmap`` over parameters, motions and start
positions. Both return a :class:`Result` whose every array has the step axis last but for the
per-step vectors (``(..., n)`` and ``(..., n, 3)``), with the batch axis first.
Units: mm, N, MPa, s, tonne.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jsnap._core import status
from jsnap._core.model import Model
from jsnap._core.params import FIELDS, Params
from jsnap._core.step import Prepared, State, StepOutput, _prepare, _step, init_state
from jsnap._core.util import cast_floats, x64

__all__ = ["Result", "SimulationError", "progress_chunk", "rollout", "rollout_batch"]

# Energy the deformable part may hold beyond the rigid part's work before the step is flagged,
# relative to the largest energy or work so far (float32 round-off of the energy's quadratic
# forms stays below 1e-4 of it on the shipped scenes; a failed contact solve creates far more).
ENERGY_RTOL = 1e-2

# A point of the deformable part deeper inside the rigid part than PENETRATION_DEPTH times the
# contact's resolution (the larger of its margin and its spacing) for more than PENETRATION_STEPS
# steps in a row is flagged. A snap's spring-in goes deeper for a step or two, and the contact
# pushes the point out; a point the contact lost stays in (docs/contact.md "Penetration").
PENETRATION_DEPTH = 4.0
PENETRATION_STEPS = 5


class SimulationError(RuntimeError):
    """A rollout's result is not the physics asked for (see :meth:`Result.check`)."""


class Result(StepOutput):
    """A rollout's history: every step's :class:`StepOutput` stacked, with the time, the travel
    and (on request) the coordinates. Per-step arrays have the step axis first (n = steps),
    after the batch axis of :func:`rollout_batch`.

    Attributes:
        t: (n,) time at the end of each step, s.
        travel: (n,) the rigid part's travel along the insertion axis (``model.axis``, -z for
            the presets) since t = 0, mm.
        insertion_force: (n,) force that pushes the rigid part along the insertion axis
            against the deformable part, N (positive while the part resists).
        lateral_force: (n,) x-component of the deformable part's force on the rigid part, N.
        base_force: (n, 3) reaction of the fixed base on the deformable part, N (what a force
            sensor under it reads; in statics it balances the contact force).
        base_moment: (n, 3) its moment about the base centroid, N mm.
        coupling_force: (n, 3) force of the drive on the rigid part, N (the haptic force under
            impedance control).
        coupling_moment: (n, 3) moment of the contact forces on the deformable part about the
            rigid part's centre, N mm: the torque the drive holds the rigid part's orientation
            against (the orientation follows its path under either drive).
        energy: (n,) the deformable part's energy 1/2 v'Mv + 1/2 x'Kx after the step, N mm.
        work: (n,) work of the rigid part on the deformable part during the step, N mm.
        friction_dissipation: (n,) energy the friction forces took from the two parts during
            the step, N mm (non-negative: maximal dissipation).
        normal_dissipation: (n,) energy the normal contact forces took during the step, N mm:
            zero where contacts persist with their gaps closed; an inelastic impact (a snap
            landing) takes a little; a contact held across a gap it does not touch takes energy
            step after step, the sign of a wrong contact normal (docs/contact.md "Energy").
            The midpoint rule's balance is exact: ``energy[k] - energy[k-1] = work[k] -
            friction_dissipation[k] - normal_dissipation[k]``, less what damping took (Rayleigh
            damping; a segmented part's interface dampers).
        penetration: (n,) how deep the deformable part's deepest contact point lies inside the
            rigid part at the start of the step, mm (0: none inside). The contact holds
            velocities, so a point that a step carried in stays there until the part moves it
            out: a snap's spring-in goes a few contact resolutions deep for a step or two; a run of
            more than ``PENETRATION_STEPS`` steps deeper than ``penetration_depth(model)`` is
            flagged ``DEEP_PENETRATION``.
        plug: (n, 3) the rigid part's centre, mm.
        plug_rotation: (n, 4) its orientation, a unit quaternion (w, x, y, z).
        contact_force: (n, C, 3) force of the rigid part on the deformable part at each slot, N.
        contact_point: (n, C, 3) slot positions, mm.
        contact_active: (n, C) bool, the slot holds a contact.
        contact_index: (n, C) candidate point of each slot (index into
            ``model.samples.rest``).
        overflow: (n,) candidates that did not fit in the buffer (0 = none dropped).
        residual: (n,) the contact solver's normalised KKT residual (of the second solve where
            ``corrected``).
        iterations: (n,) the contact solver's iterations (of the second solve where
            ``corrected``).
        corrected: (n,) bool, the step was solved a second time (predict-correct).
        flags: (n,) int32 bit mask of what went wrong in each step (``jsnap._core.status``):
            0 everywhere is a clean run; see :attr:`ok`, :meth:`status`, :meth:`check`.
        x: (n, dof) the deformable part's coordinates (None unless ``keep_x``): the
            displacement at the free dofs (mm) for the full model; modal or reduced coordinates
            otherwise, which ``model.part.free_displacement`` maps to the free dofs.
    """

    # The fields of every step (StepOutput's, stacked), and:
    t: jax.Array
    travel: jax.Array
    x: jax.Array | None

    @property
    def ok(self):
        """True where no step has an error flag (a bool per rollout of a batch)."""
        return jnp.all((self.flags & status.ERRORS) == 0, axis=-1)

    def status(self) -> str | list[str]:
        """``"ok"`` or a message naming the first step with an error (a list for a batch)."""
        flags = np.asarray(self.flags)
        if flags.ndim == 1:
            return status.describe(flags)
        return [status.describe(f) for f in flags.reshape(-1, flags.shape[-1])]

    def check(self) -> Result:
        """Return ``self``, or raise :class:`SimulationError` with :meth:`status`'s message."""
        flags = np.asarray(self.flags)
        for i, f in enumerate(flags.reshape(-1, flags.shape[-1])):
            message = status.describe(f)
            if message != "ok":
                where = f"rollout {i}: " if flags.ndim > 1 else ""
                raise SimulationError(where + message)
        return self


def _check_controls(controls, batched: bool = False):
    """``controls`` must be (steps, 3) centres or (steps, 7) poses (or with a leading batch
    axis), steps >= 1, finite and with unit quaternions (checked when not traced). Returns them
    as a host array when concrete, else as they are."""
    if not isinstance(controls, jax.core.Tracer):
        controls = np.asarray(controls)
    want = 3 if batched else 2
    if controls.ndim != want or controls.shape[-1] not in (3, 7) or controls.shape[-2] < 1:
        shape = "(B, steps, 3 or 7)" if batched else "(steps, 3 or 7)"
        raise ValueError(
            f"controls must be {shape} desired rigid-part centres, mm (and unit quaternions w, x, y, z), "
            f"with steps >= 1; got shape {controls.shape}"
        )
    if isinstance(controls, np.ndarray) and controls.shape[-1] == 7:
        off = np.abs(np.linalg.norm(controls[..., 3:], axis=-1) - 1) > 1e-6
        if off.any():
            i = tuple(int(k) for k in np.unravel_index(int(np.argmax(off)), off.shape))
            raise ValueError(
                f"controls: the quaternion of row {i[0] if len(i) == 1 else i} is not of unit norm"
            )
    if isinstance(controls, np.ndarray):
        bad = ~np.isfinite(controls).all(axis=-1)
        if bad.any():
            i = tuple(int(k) for k in np.unravel_index(int(np.argmax(bad)), bad.shape))
            row = i[0] if len(i) == 1 else i  # (rollout, row) for a batch
            raise ValueError(f"controls must be finite; row {row} is {controls[i]}")
    return controls


def _check_jumps(model: Model, controls, plug_start, batched: bool = False) -> None:
    """Refuse concrete ``controls`` (from :func:`_check_controls`) whose rigid part moves farther
    in one step (from its start to the first row, or from a row to the next; its centre, plus its
    turn times its distance to the nearest contact candidate) than the deformable part's smallest
    extent: a part that jumps its own size between two contact checks passes through it (the
    force is nonsense, and nothing else flags it). Traced arrays are not checked."""
    leaves = [controls, model.mesh.nodes, model.motion, model.samples.rest]
    if plug_start is not None:
        leaves.append(plug_start)
    if any(isinstance(a, jax.core.Tracer) for a in leaves):
        return
    # Inside a user's jit the model's properties (jnp slices of concrete leaves) would trace.
    with jax.ensure_compile_time_eval():
        _refuse_jumps(model, controls, plug_start, batched)


def _refuse_jumps(model: Model, controls, plug_start, batched: bool) -> None:
    c = np.asarray(controls, np.float64).reshape(-1, *np.shape(controls)[-2:])  # (B, steps, 3 | 7)
    start = np.asarray(model.plug_start if plug_start is None else plug_start, np.float64).reshape(-1, 3)
    start = np.broadcast_to(start, (c.shape[0], 3))
    jump = np.linalg.norm(np.diff(np.concatenate([start[:, None], c[..., :3]], axis=1), axis=1), axis=-1)
    if c.shape[-1] == 7:
        q0 = np.broadcast_to(np.asarray(model.rotation_start, np.float64), (c.shape[0], 4))
        q = np.concatenate([q0[:, None], c[..., 3:]], axis=1)
        turn = 2.0 * np.arccos(np.clip(np.abs(np.sum(q[:, 1:] * q[:, :-1], axis=-1)), 0.0, 1.0))
        lever = float(np.min(np.linalg.norm(np.asarray(model.samples.rest) - start[0], axis=1)))
        jump = jump + turn * lever
    size = float(np.min(np.ptp(np.asarray(model.mesh.nodes), axis=0)))
    if not jump.max() > size:
        return
    b, k = (int(i) for i in np.unravel_index(int(np.argmax(jump)), jump.shape))
    where = f"rollout {b}, " if batched else ""
    rows = f"from row {k - 1} to row {k}" if k else "from its start (plug_start) to row 0"
    resolution = max(float(model.contact.margin), float(model.samples.spacing))
    raise ValueError(
        f"controls: the rigid part jumps {jump[b, k]:.4g} mm in one step ({where}{rows}), more than the "
        f"deformable part's smallest extent ({size:.3g} mm): it would pass through the part between two "
        f"contact checks; give one row per time step of the model (dt = {model.dt:g} s), moving at most "
        f"about {resolution:g} mm (the contact's resolution) from one row to the next"
    )


def _dtype(model: Model, dtype):
    dtype = jnp.dtype(dtype or model.dtype)
    if dtype not in (jnp.float32, jnp.float64):
        raise ValueError(f"dtype must be 'float32' or 'float64', got {dtype.name!r}")
    return dtype


def _start(model: Model, prepared: Prepared, controls, plug_start, dtype) -> State:
    """The state at rest; the rigid part moves with its drive from the first step (no start-up
    transient in a virtual coupling)."""
    state = init_state(model, dtype, plug_start)
    vel = (controls[0, :3] - state.plug) / jnp.asarray(model.dt, dtype)
    return eqx.tree_at(lambda s: s.plug_vel, state, vel)


def _scan(model: Model, prepared: Prepared, state: State, controls, keep_x: bool):
    # Checkpointed: reverse mode keeps only each step's state and recomputes the step (its
    # contact problems) on the way back; forward runs are unaffected.
    @jax.checkpoint
    def body(s, c):
        s, out = _step(model, prepared, s, c)
        return s, (out, s.x if keep_x else None)

    return jax.lax.scan(body, state, controls)


def _run(model: Model, prepared: Prepared, controls, plug_start, keep_x: bool):
    """One rollout in the controls' dtype (model and prepared cast to it), outputs stacked."""
    dtype = controls.dtype
    model, prepared = cast_floats(model, dtype), cast_floats(prepared, dtype)
    state = _start(model, prepared, controls, plug_start, dtype)
    _, (out, xs) = _scan(model, prepared, state, controls, keep_x)
    return out, xs, state.plug


def _deep_runs(penetration, depth):
    """(..., n) bool: the steps of each run of more than ``PENETRATION_STEPS`` consecutive steps
    whose ``penetration`` (..., n) exceeds ``depth`` (mm), the whole run from its first step."""
    n = penetration.shape[-1]
    axis = penetration.ndim - 1
    k = jnp.arange(n)
    deep = penetration > depth
    last_shallow = jax.lax.cummax(jnp.where(deep, -1, k), axis=axis)  # at or before each step
    next_shallow = jax.lax.cummin(jnp.where(deep, n, k), axis=axis, reverse=True)  # at or after it
    return deep & (next_shallow - last_shallow - 1 > PENETRATION_STEPS)


def contact_resolution(model: Model) -> float:
    """The contact's resolution, mm: the larger of its margin and its candidate spacing."""
    return max(float(model.contact.margin), float(model.samples.spacing))


def penetration_depth(model: Model) -> float:
    """The depth (mm) beyond which a point's penetration into the rigid part is deep:
    ``PENETRATION_DEPTH`` contact resolutions (:func:`contact_resolution`)."""
    return PENETRATION_DEPTH * contact_resolution(model)


def _result(out: StepOutput, xs, start, valid, model: Model) -> Result:
    """Stack a rollout's outputs into a :class:`Result`: flag energy creation and lasting deep
    penetration over the whole history and, for invalid parameters, make every floating output
    NaN."""
    dtype = out.energy.dtype
    axis = model.axis.astype(dtype)
    work = jnp.cumsum(out.work, axis=-1)
    scale = jax.lax.cummax(jnp.maximum(jnp.abs(out.energy), jnp.abs(work)), axis=out.energy.ndim - 1)
    created = out.energy - work > ENERGY_RTOL * scale + jnp.finfo(dtype).tiny
    deep = _deep_runs(out.penetration, penetration_depth(model))
    flags = (
        out.flags
        | jnp.where(created, status.ENERGY_CREATED, 0).astype(jnp.int32)
        | jnp.where(deep, status.DEEP_PENETRATION, 0).astype(jnp.int32)
    )
    n = out.energy.shape[-1]

    def nan_if_invalid(a):
        if a is None or not jnp.issubdtype(a.dtype, jnp.floating):
            return a
        v = jnp.reshape(valid, valid.shape + (1,) * (a.ndim - valid.ndim))
        return jnp.where(v, a, jnp.nan)

    res = Result(
        t=(jnp.arange(n) + 1) * jnp.asarray(model.dt, dtype),
        travel=jnp.sum((out.plug - start[..., None, :]) * axis, axis=-1),
        insertion_force=out.insertion_force,
        lateral_force=out.lateral_force,
        base_force=out.base_force,
        base_moment=out.base_moment,
        coupling_force=out.coupling_force,
        coupling_moment=out.coupling_moment,
        energy=out.energy,
        work=out.work,
        friction_dissipation=out.friction_dissipation,
        normal_dissipation=out.normal_dissipation,
        penetration=out.penetration,
        plug=out.plug,
        plug_rotation=out.plug_rotation,
        contact_force=out.contact_force,
        contact_point=out.contact_point,
        contact_active=out.contact_active,
        contact_index=out.contact_index,
        overflow=out.overflow,
        residual=out.residual,
        iterations=out.iterations,
        corrected=out.corrected,
        flags=flags,
        x=xs,
    )
    return _nan_fields(res, nan_if_invalid)


_FLOAT_FIELDS = (
    "travel", "insertion_force", "lateral_force", "base_force", "base_moment", "coupling_force",
    "coupling_moment", "energy", "work", "friction_dissipation", "normal_dissipation", "penetration", "plug",
    "plug_rotation", "contact_force", "contact_point", "residual", "x",
)  # fmt: skip


def _nan_fields(res: Result, f) -> Result:
    fields = [k for k in _FLOAT_FIELDS if getattr(res, k) is not None]
    return eqx.tree_at(lambda r: [getattr(r, k) for k in fields], res, [f(getattr(res, k)) for k in fields])


@eqx.filter_jit
def _whole(model: Model, prepared: Prepared, controls, plug_start, keep_x):
    """``rollout`` without progress: the casts, the scan and the result in one compiled call."""
    out, xs, start = _run(model, prepared, controls, plug_start, keep_x)
    return _result(out, xs, start, prepared.valid, model)


def progress_chunk(n_steps: int) -> int:
    """Steps per compiled chunk when ``rollout`` shows progress (20 updates)."""
    return max(1, math.ceil(n_steps / 20))


@eqx.filter_jit
def _chunk(model: Model, prepared: Prepared, state: State, controls, keep_x):
    model, prepared = cast_floats(model, controls.dtype), cast_floats(prepared, controls.dtype)
    return _scan(model, prepared, state, controls, keep_x)


@eqx.filter_jit
def _finish(out, xs, start, valid, model):
    return _result(out, xs, start, valid, model)


def _with_progress(model, prepared, controls, plug_start, keep_x):
    """The rollout in chunks of :func:`progress_chunk` steps, with a progress bar on stderr."""
    from tqdm.auto import tqdm

    dtype = controls.dtype
    state = _start(cast_floats(model, dtype), cast_floats(prepared, dtype), controls, plug_start, dtype)
    start = state.plug
    chunk = progress_chunk(controls.shape[0])
    outs, xs_all = [], []
    with tqdm(total=controls.shape[0], unit="step", desc="jsnap rollout") as bar:
        for i in range(0, controls.shape[0], chunk):
            c = controls[i : i + chunk]
            n_real = c.shape[0]
            if n_real < chunk:  # pad the tail: one compiled chunk size
                c = jnp.concatenate([c, jnp.repeat(c[-1:], chunk - n_real, 0)])
            state_next, (out, xs) = _chunk(model, prepared, state, c, keep_x)
            if n_real < chunk:
                out = jax.tree_util.tree_map(lambda a: a[:n_real], out)
                xs = None if xs is None else xs[:n_real]
            state = state_next
            outs.append(out)
            xs_all.append(xs)
            bar.update(n_real)
    out = jax.tree_util.tree_map(lambda *a: jnp.concatenate(a), *outs)
    xs = None if not keep_x else jnp.concatenate(xs_all)
    return _finish(out, xs, start, prepared.valid, model)


@x64
def rollout(
    model: Model,
    params: Params | None = None,
    *,
    controls=None,
    plug_start=None,
    dtype=None,
    keep_x: bool = False,
    progress: bool = False,
    prepared: Prepared | None = None,
) -> Result:
    """Run the scene's motion (or ``controls``) from rest and return the history.

    Args:
        model: ``jsnap.build(scene)``.
        params: physical parameters (default: the scene's); differentiable.
        controls: (steps, 3) desired rigid-part centres at the end of each step, mm, or
            (steps, 7) poses with a unit quaternion (w, x, y, z) each (default: the scene's
            motion, ``model.trajectory()[1:]``).
        plug_start: (3,) the rigid part's centre at t = 0, mm (default: the scene's).
        dtype: rollout precision, ``"float32"`` or ``"float64"`` (default: the scene's).
        keep_x: also return the deformable part's coordinates (``Result.x``).
        progress: show a progress bar (runs the scan in chunks; not for use under ``jit``).
        prepared: ``prepare(model, params)`` computed once and reused (it factorises the PMI
            operator, ~n^3 for the full model); give it or ``params``, not both.

    Returns:
        A :class:`Result`. Parameters that are traced (under ``jit``, ``vmap``, ``grad``) and
        invalid, non-finite steps, energy creation and dropped contacts are flagged in
        ``Result.flags`` (:attr:`Result.ok`, :meth:`Result.check`), never silently replaced.

    Raises:
        ValueError: controls not (steps, 3) or not finite, a dtype other than float32/float64,
            both ``params`` and ``prepared``, or (when not traced) parameter values that are not
            finite or out of range.
    """
    dtype = _dtype(model, dtype)
    if controls is not None:  # before anything is prepared or compiled
        controls = _check_controls(controls)
        _check_jumps(model, controls, plug_start)
    if prepared is None:
        params = model.params if params is None else params
        params.check()
        prepared = _prepare(model, params)
    elif params is not None and params is not prepared.params:
        # Silently ignoring params would be a wrong answer (and a zero gradient under jax.grad).
        raise ValueError(
            "rollout got both params and prepared: prepared = prepare(model, params) holds the "
            "parameters it was made from; pass one of them"
        )
    controls = jnp.asarray(model.motion[1:] if controls is None else controls, dtype)
    plug_start = jnp.asarray(model.plug_start if plug_start is None else plug_start, dtype)
    if plug_start.shape != (3,):
        raise ValueError(
            f"plug_start must be (3,), the rigid part's centre in mm; got shape {plug_start.shape}"
        )
    if progress:
        return _with_progress(model, prepared, controls, plug_start, keep_x)
    return _whole(model, prepared, controls, plug_start, keep_x)


def _batch_size(params: Params | None, controls, plug_start) -> int:
    sizes = {}
    if params is not None:
        for name in FIELDS:
            shape = jnp.shape(getattr(params, name))
            if len(shape) > 1:
                raise ValueError(f"params.{name} must be a scalar or a (B,) batch, got shape {shape}")
            if shape:
                sizes[f"params.{name}"] = shape[0]
    if controls is not None:
        sizes["controls"] = controls.shape[0]
    if plug_start is not None:
        sizes["plug_start"] = plug_start.shape[0]
    if not sizes:
        raise ValueError(
            "rollout_batch: nothing is batched; give params, controls or plug_start with a leading batch axis"
        )
    if len(set(sizes.values())) > 1:
        raise ValueError(f"rollout_batch: batch sizes differ: {sizes}")
    return next(iter(sizes.values()))


@x64
def rollout_batch(
    model: Model,
    params: Params | None = None,
    *,
    controls=None,
    plug_start=None,
    dtype=None,
    keep_x: bool = False,
) -> Result:
    """Many rollouts of one model at once (``jax.vmap``): each with its own parameters, motion
    and start position.

    Args:
        model: ``jsnap.build(scene)``.
        params: :class:`Params` whose fields are scalars (shared) or (B,) arrays (one per
            rollout), e.g. ``model.params.replace(E=jnp.array([2000., 2200., 2400.]))``.
        controls: (B, steps, 3) desired rigid-part centres (or (B, steps, 7) poses) per
            rollout, mm (default: the scene's motion for all).
        plug_start: (B, 3) start centres, mm (default: the scene's for all).
        dtype, keep_x: as for :func:`rollout`.

    Returns:
        A :class:`Result` whose arrays have the batch axis first. It equals a loop of
        :func:`rollout` over the batch, but for invalid parameters: a rollout whose parameters
        are NaN or out of range is flagged (``Result.ok`` False for it, its outputs NaN) while
        the others run, where :func:`rollout` raises.

    Raises:
        ValueError: nothing batched, batch sizes that differ, or what :func:`rollout` raises.
    """
    dtype = _dtype(model, dtype)
    params = model.params if params is None else params
    if controls is not None:
        controls = _check_controls(controls, batched=True)
        _check_jumps(model, controls, plug_start, batched=True)
        controls = jnp.asarray(controls, dtype)
    if plug_start is not None:
        plug_start = jnp.asarray(plug_start, dtype)
        if plug_start.ndim != 2 or plug_start.shape[1] != 3:
            raise ValueError(f"plug_start must be (B, 3) start centres, mm; got shape {plug_start.shape}")
    B = _batch_size(params, controls, plug_start)
    params = Params(**{k: jnp.broadcast_to(jnp.asarray(getattr(params, k)), (B,)) for k in FIELDS})
    if controls is None:
        controls = jnp.broadcast_to(jnp.asarray(model.motion[1:], dtype), (B, *model.motion[1:].shape))
    if plug_start is None:
        plug_start = jnp.broadcast_to(jnp.asarray(model.plug_start, dtype), (B, 3))
    return _batched(model, params, controls, plug_start, keep_x)


@eqx.filter_jit
def _batched(model: Model, params: Params, controls, plug_start, keep_x):
    def one(p, c, s):
        prepared = _prepare(model, p)
        out, xs, start = _run(model, prepared, c, s, keep_x)
        return _result(out, xs, start, prepared.valid, model)

    return jax.vmap(one)(params, controls, plug_start)
