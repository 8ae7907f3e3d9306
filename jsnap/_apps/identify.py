"""Parameter identification: fit E, friction, damping (and a time shift / plug offset) of a scene
to a measured insertion-force history.

    meas = jsnap.load_measurement("forces.csv")       # time (s) and force (N) columns
    fit = jsnap.identify(model, meas, fit=("E", "friction"))
    fit.values, fit.std_errors                          # MPa, -, 1/s, s, s, mm
    fit.plot("fit.png")

The measured history is resampled onto the simulation's output times ``t_k = k dt`` (linear
interpolation when it is sampled at most as fast as the simulation; the average over each step's
window when faster, which also averages the noise down). Then

    loss(θ) = ½ mean_k ([G (F_sim(θ) − F_meas)]_k / s)²,     s = max |F_meas|

is minimised, with ``G`` a Gaussian smoothing over a few steps (``smooth``: it spreads the
one-step jumps that contact events make in the simulated history, see :func:`smoothing_filter`).

- Variables: logarithms of the positive parameters (E, friction, alpha, beta: positive by
  construction); the time shift and the plug offset in units of a step's duration and travel.
- Seed: a global start from forward rollouts only: E by its closed-form force scale (the force
  is proportional to E at fixed friction), friction on a log grid over a factor 4 either way
  of its start (:func:`_seed`).
- Optimiser: L-BFGS (``optax.scale_by_lbfgs``) with Armijo backtracking and a cap on the step,
  in variables whitened by the Gauss–Newton metric ``JᵀJ`` (E and friction both scale the
  force, so the valley is long and narrow; whitened, the first step is the Gauss–Newton step).
- Gradients: ``jax.grad`` of the whole rollout, through contact (implicit differentiation of the
  contact solve, ``jsnap._core.contact.implicit``).
- Uncertainty: the Gauss–Newton (Laplace) covariance from ``J = ∂F/∂θ`` (forward mode, one
  pass per parameter) and the residual variance σ², in its sandwich form for the smoothed
  residuals; standard errors in the parameters' own units by the delta method. They assume
  independent noise: model error that is correlated in time makes them optimistic.

Units: mm, N, MPa, s, tonne.
"""

from __future__ import annotations

import csv
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from jsnap._core.model import Model
from jsnap._core.params import Params
from jsnap._core.rollout import rollout
from jsnap._core.util import x64

__all__ = ["FIT_PARAMETERS", "FitResult", "Measurement", "MeasurementError", "identify", "load_measurement"]

# What can be fitted, in the parameters' own units.
FIT_PARAMETERS = {
    "E": "MPa",
    "friction": "",
    "alpha": "1/s",
    "beta": "s",
    "time_shift": "s",
    "plug_offset": "mm",
}
_POSITIVE = ("E", "friction", "alpha", "beta")
# Starting values of positive parameters that are 0 in the scene (a log cannot start at 0).
_ZERO_START = {"alpha": 1.0, "beta": 1e-6, "friction": 0.1}

# Accepted column names (lower case, spaces as underscores) and the factor to s / N.
_TIME_COLUMNS = {"t_s": 1.0, "time_s": 1.0, "time": 1.0, "t": 1.0, "t_ms": 1e-3, "time_ms": 1e-3}
_FORCE_COLUMNS = {
    "insertion_force_n": 1.0,
    "insertion_force": 1.0,
    "force_n": 1.0,
    "force": 1.0,
    "f_n": 1.0,
    "f": 1.0,
    "fz_n": 1.0,
    "insertion_force_mn": 1e-3,
    "force_mn": 1e-3,
    "insertion_force_kn": 1e3,
    "force_kn": 1e3,
}
# A measured scale this many times off the simulated one is a unit error, not a parameter
# error (the fit starts within a factor of a few of the truth).
_UNIT_FACTOR = 20.0


class MeasurementError(ValueError):
    """Measured force data that cannot be used; the message names the file, column and rows."""


@dataclass(frozen=True)
class Measurement:
    """A measured insertion-force history.

    Attributes:
        t: (m,) strictly increasing times, s (t = 0 when the plug starts moving).
        force: (m,) insertion force, N (positive while the socket resists the plug).
        source: where it came from (file name), for messages.
        columns: the (time, force) column names used.
    """

    t: np.ndarray
    force: np.ndarray
    source: str = "<array>"
    columns: tuple[str, str] = ("t_s", "insertion_force_N")

    def __post_init__(self):
        t = np.asarray(self.t, dtype=float)
        f = np.asarray(self.force, dtype=float)
        where = f"{self.source}"
        if t.ndim != 1 or f.shape != t.shape:
            raise MeasurementError(
                f"{where}: time and force must be 1-D of one length, got {t.shape} and {f.shape}"
            )
        if t.size < 4:
            raise MeasurementError(f"{where}: {t.size} samples; at least 4 are needed")
        for name, a in ((self.columns[0], t), (self.columns[1], f)):
            bad = np.flatnonzero(~np.isfinite(a))
            if bad.size:
                rows = ", ".join(str(i + 1) for i in bad[:5]) + (" ..." if bad.size > 5 else "")
                raise MeasurementError(
                    f"{where}: column {name!r} has {bad.size} NaN/inf value(s) (data rows {rows}); "
                    "remove or fill them"
                )
        back = np.flatnonzero(np.diff(t) <= 0)
        if back.size:
            i = back[0]
            raise MeasurementError(
                f"{where}: time column {self.columns[0]!r} is not strictly increasing: data row {i + 2} "
                f"has t = {t[i + 1]:g} after t = {t[i]:g} ({back.size} such place(s)); sort the samples and "
                "drop duplicates"
            )
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "force", f)


def _find_column(header: list[str], accepted: dict, given: str | None, what: str, source: str):
    norm = [h.strip().lower().replace(" ", "_") for h in header]
    if given is not None:
        key = given.strip().lower().replace(" ", "_")
        if key not in norm:
            raise MeasurementError(f"{source}: no column {given!r} (columns: {', '.join(header)})")
        return norm.index(key), accepted.get(key, 1.0), header[norm.index(key)]
    for name, factor in accepted.items():
        if name in norm:
            return norm.index(name), factor, header[norm.index(name)]
    raise MeasurementError(
        f"{source}: missing {what} column: none of {', '.join(header) or '(no header)'} is one of "
        f"{', '.join(accepted)} (or name it with time_column= / force_column=, --time-column / --force-column)"
    )


def load_measurement(path, *, time_column: str | None = None, force_column: str | None = None) -> Measurement:
    """Read a measured force history from a CSV file with a header row.

    Time columns recognised: ``t_s``, ``time_s``, ``time``, ``t`` (seconds), ``t_ms``,
    ``time_ms`` (milliseconds, converted). Force: ``insertion_force_N``, ``force_N``, ``force``,
    ``F``, ``Fz_N`` (newtons), ``*_mN``, ``*_kN`` (converted). Case and spaces do not matter.
    The ``forces.csv`` of ``jsnap simulate`` is accepted as is.

    Raises:
        MeasurementError: missing file or columns, non-numeric, NaN or non-monotonic values.
    """
    path = Path(path)
    if not path.is_file():
        raise MeasurementError(f"measured force file {str(path)!r} does not exist")
    with open(path, newline="") as fh:
        rows = [r for r in csv.reader(fh) if r and not r[0].lstrip().startswith("#")]
    if not rows:
        raise MeasurementError(f"{path}: empty file")
    header = [h.strip() for h in rows[0]]
    if all(_is_number(h) for h in header):
        raise MeasurementError(
            f"{path}: no header row (the first line is numbers); name the columns, e.g. 't_s,insertion_force_N'"
        )
    it, ft, tname = _find_column(header, _TIME_COLUMNS, time_column, "time", str(path))
    iF, fF, fname = _find_column(header, _FORCE_COLUMNS, force_column, "force", str(path))
    t, f = [], []
    for k, r in enumerate(rows[1:], start=2):
        if len(r) <= max(it, iF):
            raise MeasurementError(
                f"{path}: line {k} has {len(r)} fields, fewer than the header's {len(header)}"
            )
        vals = []
        for col, name in ((it, tname), (iF, fname)):
            s = r[col].strip()
            try:
                vals.append(float(s) if s else math.nan)
            except ValueError:
                raise MeasurementError(f"{path}: line {k}, column {name!r}: {s!r} is not a number") from None
        t.append(vals[0] * ft)
        f.append(vals[1] * fF)
    return Measurement(np.array(t), np.array(f), str(path), (tname, fname))


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def _window_average(t, f, a, b):
    """Average over [a, b] (arrays) of the piecewise-linear interpolant of (t, f)."""
    h = np.diff(t)
    I = np.concatenate([[0.0], np.cumsum(0.5 * h * (f[1:] + f[:-1]))])

    def integral(x):
        j = np.clip(np.searchsorted(t, x, side="right") - 1, 0, t.size - 2)
        d = x - t[j]
        return I[j] + f[j] * d + (f[j + 1] - f[j]) * d * d / (2 * h[j])

    return (integral(b) - integral(a)) / (b - a)


def resample(meas: Measurement, t_sim: np.ndarray, dt: float):
    """The measured force at the simulation's output times.

    Returns ``(force, mask)``, each (n,): the resampled force (N) and which times the
    measurement covers. Linear interpolation if the measurement is sampled at most as fast as
    the simulation (median spacing ≥ dt/2), else the mean over each step's window
    ``[t_k − dt/2, t_k + dt/2]`` (anti-aliasing: it also averages the noise).
    """
    t, f = meas.t, meas.force
    fast = np.median(np.diff(t)) < 0.5 * dt
    half = 0.5 * dt if fast else 0.0
    mask = (t_sim - half >= t[0] - 1e-12 * dt) & (t_sim + half <= t[-1] + 1e-12 * dt)
    ts = np.clip(t_sim, t[0] + half, t[-1] - half)
    out = _window_average(t, f, ts - half, ts + half) if fast else np.interp(ts, t, f)
    return np.where(mask, out, 0.0), mask


@dataclass
class FitResult:
    """Outcome of :func:`identify`.

    Attributes:
        names: fitted parameters, in order.
        values: fitted values, in the parameters' units (FIT_PARAMETERS).
        initial: starting values, same units.
        std_errors: Gauss–Newton (Laplace) standard errors, same units (``inf`` if a parameter
            does not affect the force).
        correlation: (p, p) correlation matrix of the estimates.
        params: the fitted :class:`Params` (other fields as in the scene).
        t: (n,) simulation output times, s.
        mask: (n,) bool, the times covered by the measurement.
        measured: (n,) the measurement resampled onto ``t``, N.
        fitted: (n,) the fitted model's force, N.
        start: (n,) the initial model's force, N.
        rms_residual: RMS of measured minus fitted force over the covered times, N.
        noise_estimate: the residual's standard deviation σ, N.
        loss_history: loss after each iteration.
        iterations: optimiser iterations.
        evaluations: differentiated rollouts (gradients and Jacobians).
        seconds: wall time (compilation included).
        converged: the step fell below ``xtol`` (not just ``max_iters`` reached).
        source: where the measurement came from (its file).
        seeded: values after the seed search (None without it).
        rollouts: the seed search's forward rollouts.
    """

    names: tuple[str, ...]
    values: dict
    initial: dict
    std_errors: dict
    correlation: np.ndarray
    params: Params
    t: np.ndarray
    mask: np.ndarray
    measured: np.ndarray
    fitted: np.ndarray
    start: np.ndarray
    rms_residual: float
    noise_estimate: float
    loss_history: list = field(default_factory=list)
    iterations: int = 0
    evaluations: int = 0
    seconds: float = 0.0
    converged: bool = False
    source: str = ""
    seeded: dict | None = None
    rollouts: int = 0

    def to_dict(self) -> dict:
        """JSON-serialisable summary."""
        return {
            "measured": self.source,
            "fit": list(self.names),
            "values": {k: float(v) for k, v in self.values.items()},
            "initial": {k: float(v) for k, v in self.initial.items()},
            "std_errors": {k: float(v) for k, v in self.std_errors.items()},
            "relative_std_errors": {
                k: (float(self.std_errors[k] / abs(v)) if v != 0 else None) for k, v in self.values.items()
            },
            "units": {k: FIT_PARAMETERS[k] for k in self.names},
            "correlation": np.asarray(self.correlation).tolist(),
            "rms_residual_N": self.rms_residual,
            "noise_estimate_N": self.noise_estimate,
            "samples": int(self.mask.sum()),
            "iterations": self.iterations,
            "gradient_evaluations": self.evaluations,
            "converged": self.converged,
            "seeded": self.seeded,
            "seed_rollouts": self.rollouts,
            "seconds": self.seconds,
            "loss_history": [float(v) for v in self.loss_history],
        }

    def summary(self) -> str:
        lines = []
        for k in self.names:
            u = FIT_PARAMETERS[k]
            v, se, v0 = self.values[k], self.std_errors[k], self.initial[k]
            rel = f" ({100 * se / abs(v):.2g} %)" if v != 0 and np.isfinite(se) else ""
            lines.append(f"  {k:12s} = {v:.6g} ± {se:.2g}{rel} {u}   (start {v0:.6g})")
        lines.append(
            f"  rms residual {self.rms_residual:.4g} N over {int(self.mask.sum())} samples; "
            f"{self.iterations} iterations, {self.evaluations} derivative evaluations, {self.seconds:.1f} s"
            + ("" if self.converged else " (not converged: max_iters reached)")
        )
        return "\n".join(lines)

    def plot(self, path, title: str | None = None) -> Path:
        """PNG of measured vs fitted (and initial) force over time."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        m = self.mask
        t = self.t[m] * 1e3
        fig, ax = plt.subplots(2, 1, figsize=(8, 6), sharex=True, gridspec_kw={"height_ratios": [3, 1]})
        ax[0].plot(t, self.measured[m], ".", ms=3, color="0.4", label="measured (resampled)")
        ax[0].plot(t, self.start[m], "--", lw=1.0, color="tab:orange", label="model at the start")
        ax[0].plot(t, self.fitted[m], lw=1.6, color="tab:blue", label="fitted model")
        ax[0].set_ylabel("insertion force (N)")
        ax[0].grid(alpha=0.3)
        ax[0].legend(fontsize=8)
        fitted = ", ".join(f"{k} = {self.values[k]:.4g} ± {self.std_errors[k]:.2g}" for k in self.names)
        ax[0].set_title(title or f"jsnap fit: {fitted}", fontsize=9)
        ax[1].plot(t, self.measured[m] - self.fitted[m], ".", ms=3, color="tab:red")
        ax[1].axhline(0, color="0.5", lw=0.6)
        ax[1].set_ylabel("residual (N)")
        ax[1].set_xlabel("time (ms)")
        ax[1].grid(alpha=0.3)
        fig.tight_layout()
        path = Path(path)
        fig.savefig(path, dpi=120)
        plt.close(fig)
        return path

    def write(self, out) -> dict:
        """Write fit.json, fit.csv and fit.png to the directory ``out``; returns the paths."""
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        d = self.to_dict()
        paths = {"json": str(out / "fit.json"), "csv": str(out / "fit.csv"), "png": str(out / "fit.png")}
        d["outputs"] = paths
        (out / "fit.json").write_text(json.dumps(d, indent=2))
        m = self.mask
        np.savetxt(
            out / "fit.csv",
            np.column_stack([self.t[m], self.measured[m], self.fitted[m], self.start[m]]),
            delimiter=",",
            header="t_s,measured_N,fitted_N,initial_N",
            comments="",
            fmt="%.8g",
        )
        self.plot(out / "fit.png")
        return d


class _Problem(eqx.Module):
    """The model's insertion force as a function of the fit variables θ (a pytree leaf)."""

    model: Model
    base: Params
    t_table: jax.Array  # (K,) s, the scene's desired plug z over time
    z_table: jax.Array  # (K,) mm
    xy: jax.Array  # (2,) plug centre x, y, mm
    names: tuple[str, ...] = eqx.field(static=True)
    n_steps: int = eqx.field(static=True)
    dt: float = eqx.field(static=True)
    step_travel: float = eqx.field(static=True)

    def unpack(self, theta):
        """θ -> dict of parameter values (parameters' units)."""
        out = {}
        for i, k in enumerate(self.names):
            if k in _POSITIVE:
                out[k] = jnp.exp(theta[i])
            elif k == "time_shift":
                out[k] = theta[i] * self.dt
            else:
                out[k] = theta[i] * self.step_travel
        return out

    def force(self, theta):
        vals = self.unpack(theta)
        params = self.base.replace(**{k: v for k, v in vals.items() if k in _POSITIVE})
        shift = vals.get("time_shift", 0.0)
        offset = vals.get("plug_offset", 0.0)
        t = (jnp.arange(self.n_steps) + 1) * self.dt
        z = jnp.interp(t - shift, self.t_table, self.z_table) + offset
        controls = jnp.concatenate([jnp.broadcast_to(self.xy, (self.n_steps, 2)), z[:, None]], axis=1)
        start = self.model.plug_start
        if "plug_offset" in vals:
            start = start.at[2].add(offset)
        return rollout(self.model, params, controls=controls, plug_start=start, dtype="float64").insertion_force


class _Objective(eqx.Module):
    """Normalised least-squares loss of a :class:`_Problem` against the resampled data."""

    prob: _Problem
    target: jax.Array  # (n,) N
    filter: jax.Array  # (n, n) smoothing G over the covered steps (zero rows elsewhere)
    scale: jax.Array  # () N
    count: jax.Array  # () samples covered

    def loss(self, theta):
        """The loss and, as auxiliary output, the model's force (n,)."""
        F = self.prob.force(theta)
        r = self.filter @ (F - self.target) / self.scale
        return 0.5 * jnp.sum(r * r) / self.count, F


def smoothing_filter(mask: np.ndarray, width: float) -> np.ndarray:
    """(n, n) Gaussian smoothing of standard deviation ``width`` steps over the covered steps
    (``mask``), each row normalised over them; rows of uncovered steps are zero. ``width = 0``:
    the identity on the covered steps.

    Why: the simulated force changes discontinuously with the parameters where a contact event
    (the snap off the hook, a contact moving to the next row of sample points) moves to the next
    time step; the jump is one sample wide. Comparing band-limited histories turns those jumps
    into small, spread changes (their squared size falls ~3.5 × width), so the loss is smooth
    enough for a gradient method, and the noise is averaged too.
    """
    n = mask.size
    if width <= 0:
        return np.diag(mask.astype(float))
    k = np.arange(n)
    G = np.exp(-0.5 * ((k[:, None] - k[None, :]) / width) ** 2) * mask[None, :]
    G[np.abs(k[:, None] - k[None, :]) > 4 * width] = 0.0
    G /= np.maximum(G.sum(axis=1, keepdims=True), 1e-300)
    return G * mask[:, None]


@eqx.filter_jit
def _evaluate(obj: _Objective, theta):
    """((loss, force), gradient, Jacobian of the force (n, p)), all from one forward-mode pass.

    Forward mode (p tangents, batched) rather than reverse: with the few parameters a fit has,
    it runs as fast as ``jax.value_and_grad`` (0.54 s both, reduced P2 0.9 mm, 255 steps, p = 2)
    and compiles in about half the time (7.9 s against 13.8 s); and one program serves the
    line search, the Gauss–Newton metric and the standard errors, so a fit compiles it once.
    """
    J, F = jax.jacfwd(lambda th: (obj.prob.force(th),) * 2, has_aux=True)(theta)
    r = obj.filter @ (F - obj.target) / obj.scale
    loss = 0.5 * jnp.sum(r * r) / obj.count
    grad = J.T @ (obj.filter.T @ r) / (obj.scale * obj.count)
    return (loss, F), grad, J


# L-BFGS iterations on E alone before the joint fit when there is no seed search (see identify).
_SCALE_ITERS = 4
# The seed search tries friction at these factors of its starting value (a factor 4 either way;
# 12 points, 29 % apart: the grid does not contain the factors 1/2 and 2 of the benchmarks).
_SEED_FACTORS = np.geomspace(0.25, 4.0, 12)
# Finer grids around the best friction after the coarse one (each a third of the spacing).
_SEED_REFINE = 2


@eqx.filter_jit
def _force(prob: _Problem, theta):
    return prob.force(theta)


def _seed(obj: _Objective, theta, names, progress: bool):
    """A global start for the local fit, from forward rollouts only.

    Quasi-static linear elasticity with a kinematic plug makes the contact forces proportional
    to E at a fixed friction coefficient (the displacements are set by the geometry; inertia
    and damping break it only slightly), so the best E for a given history is a closed-form
    scale ``s = <G F, G F_meas> / <G F, G F>``. When friction is fitted too, the loss profiled
    over friction (E eliminated by that scale) is minimised by grid search: a log grid
    ``_SEED_FACTORS`` × its start (29 % apart), then ``_SEED_REFINE`` finer grids around the
    best point (9 %, 3 % apart); 20 forward rollouts in all.

    Why: the loss is not convex in friction. A hook pushed with high friction sticks and slips,
    its force history is rough and its gradients are dominated by the discrete contact sequence
    (docs/differentiation.md), and E and friction trade along a long valley (both scale the
    force). From a start far off, a gradient method can stall there; the grid puts the local fit
    in the right valley, and the local fit (L-BFGS with exact gradients) does the rest.

    Returns ``(theta, rollouts, seeded values or None)``.
    """
    i_E = names.index("E") if "E" in names else None
    i_mu = names.index("friction") if "friction" in names else None
    if i_E is None and i_mu is None:
        return theta, 0, None
    G = np.asarray(obj.filter)
    target = G @ np.asarray(obj.target)
    scale2 = float(obj.scale) ** 2 * float(obj.count)

    def profiled(th):
        """(θ with E at its best scale, loss) for the friction in θ."""
        GF = G @ np.asarray(_force(obj.prob, th))
        if i_E is not None:
            s = float(GF @ target) / float(GF @ GF) if float(GF @ GF) > 0 else 0.0
            if not (math.isfinite(s) and s > 0):
                return th, math.inf
            th = th.at[i_E].add(math.log(s))
            GF = s * GF
        r = GF - target
        loss = 0.5 * float(r @ r) / scale2
        return th, (loss if math.isfinite(loss) else math.inf)

    if i_mu is None:
        best, _ = profiled(theta)
        rollouts = 1
    else:
        # The coarse grid, then two finer ones around the best point so far (spacing /3 each:
        # ~29 %, ~9 %, ~3 %); the local fit polishes the last few per cent.
        grids = [np.log(_SEED_FACTORS)]
        step = float(np.log(_SEED_FACTORS[1] / _SEED_FACTORS[0]))
        for _ in range(_SEED_REFINE):
            step /= 3
            grids.append(step * np.array([-2.0, -1.0, 1.0, 2.0]))
        bar = None
        if progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=sum(len(g) for g in grids), desc="jsnap fit: seed", unit="rollout", leave=False)
        best, best_loss, rollouts, centre = theta, math.inf, 0, theta
        for shifts in grids:
            for d in shifts:
                th, loss = profiled(centre.at[i_mu].add(float(d)))
                rollouts += 1
                if bar is not None:
                    bar.update(1)
                if loss < best_loss:
                    best, best_loss = th, loss
            centre = best
        if bar is not None:
            bar.close()
    values = {k: float(v) for k, v in obj.prob.unpack(best).items()}
    return best, rollouts, values


class _Run:
    """The optimiser's state across stages: L-BFGS (optax) in Gauss–Newton-whitened variables,
    Armijo backtracking, a cap on the step, and the counts and history it reports."""

    def __init__(self, obj: _Objective, mask, theta, bar, max_step: float, xtol: float):
        self.obj, self.mask, self.bar = obj, mask, bar
        # The current point's loss, force, gradient and force Jacobian (one _evaluate call).
        (self.value, self.force), self.grad, self.jac = _evaluate(obj, theta)
        self.max_step, self.xtol = max_step, xtol
        self.history = [float(self.value)]
        self.evaluations = 1
        self.iterations = 0
        self.converged = False

    def _metric(self, theta, free):
        """P (p, q): θ = θ_start + P φ whitens the Gauss–Newton metric over the free variables
        (at the current point, whose Jacobian the last evaluation gave)."""
        J = (np.asarray(self.obj.filter) @ np.asarray(self.jac))[self.mask][:, free] / float(self.obj.scale)
        H = J.T @ J / float(self.obj.count)
        d = np.diag(H)
        seen = d > 1e-12 * max(float(d.max()), 1e-300)
        # A little Levenberg damping; a parameter the force does not see gets a unit scale.
        H = H + np.diag(np.where(seen, 1e-3 * d, 1.0))
        P = np.zeros((theta.shape[0], len(free)))
        P[free] = np.linalg.inv(np.linalg.cholesky(H)).T
        return jnp.asarray(P)

    def minimise(self, theta, free: list[int], iters: int):
        """Up to ``iters`` iterations over the variables ``free``; returns θ."""
        self.converged = False
        if iters <= 0:
            return theta
        P = self._metric(theta, free)
        start = theta
        phi = jnp.zeros(len(free))
        grad = P.T @ self.grad
        opt = optax.scale_by_lbfgs()
        state = opt.init(phi)
        for _ in range(iters):
            # optax's L-BFGS transform returns the preconditioned gradient H g (optax.lbfgs then
            # scales it by -lr); -H g is the descent direction.
            scaled, state = opt.update(grad, state, phi)
            direction = -scaled
            slope = float(jnp.vdot(grad, direction))
            if not slope < 0:  # curvature pair rejected: steepest descent in the whitened metric
                direction, slope = -grad, float(-jnp.vdot(grad, grad))
            # No variable moves more than max_step in one iteration (a trust region in θ).
            longest = float(jnp.max(jnp.abs(P @ direction)))
            step = min(1.0, self.max_step / longest) if longest > 0 else 1.0
            accepted = False
            for _ in range(12):
                cand = phi + step * direction
                (v_new, F_new), g_new, J_new = _evaluate(self.obj, start + P @ cand)
                self.evaluations += 1
                if np.isfinite(float(v_new)) and float(v_new) <= float(self.value) + 1e-4 * step * slope:
                    accepted = True
                    break
                step *= 0.3
            if not accepted:  # no decrease along a descent direction: at the noise floor
                self.converged = True
                break
            change = float(jnp.max(jnp.abs(P @ (cand - phi))))
            phi, self.value, self.grad = cand, v_new, g_new
            self.force, self.jac = F_new, J_new
            grad = P.T @ g_new
            self.iterations += 1
            self.history.append(float(v_new))
            if self.bar is not None:
                vals = self.obj.prob.unpack(start + P @ phi)
                post = {k: f"{float(v):.4g}" for k, v in vals.items()} | {"loss": f"{float(v_new):.3g}"}
                self.bar.set_postfix(post)
                self.bar.update(1)
            if change < self.xtol:
                self.converged = True
                break
        return start + P @ phi


def _problem(model: Model, base: Params, names, n_steps: int) -> _Problem:
    traj = np.asarray(model.trajectory())
    if (
        traj.shape[1] != 3
        or np.ptp(traj[:, :2], axis=0).max() > 0
        or np.any(np.asarray(model.axis) != [0, 0, -1])
    ):
        # The motion is rebuilt from its z column here (the time shift and the path offset move
        # it along z): a turning or slanted path would be replaced by another one.
        raise ValueError(
            "identification takes a straight insertion along -z (the presets' motion); this model's "
            "rigid part turns or moves along another direction"
        )
    t_tab = np.arange(traj.shape[0]) * model.dt
    return _Problem(
        model=model,
        base=base,
        t_table=jnp.asarray(t_tab),
        z_table=jnp.asarray(traj[:, 2]),
        xy=jnp.asarray(traj[0, :2]),
        names=tuple(names),
        n_steps=n_steps,
        dt=model.dt,
        step_travel=float(abs(traj[1, 2] - traj[0, 2])),
    )


def _check_time_scale(meas: Measurement, duration: float):
    """Time-unit errors, judged against the duration of the scene's motion (s)."""
    tname = meas.columns[0]
    span = meas.t[-1] - meas.t[0]
    if span > _UNIT_FACTOR * duration:
        hint = " — is it in ms?" if 200 < span / duration < 5000 else ""
        raise MeasurementError(
            f"{meas.source}: time column {tname!r} spans {span:g} s but the scene's motion lasts "
            f"{duration:g} s (a factor {span / duration:.3g}){hint}; give time in s (or name the column t_ms)"
        )
    if span < duration / _UNIT_FACTOR:
        raise MeasurementError(
            f"{meas.source}: time column {tname!r} spans only {span:g} s, the scene's motion {duration:g} s "
            f"(a factor {duration / span:.3g} shorter); give time in seconds"
        )
    if meas.t[0] >= duration:
        raise MeasurementError(
            f"{meas.source}: time column {tname!r} starts at {meas.t[0]:g} s, after the scene's motion ends "
            f"({duration:g} s); time must count from the start of the motion"
        )


def _check_force_scale(meas: Measurement, sim_peak: float, measured_peak: float):
    """Force-unit errors, judged against the model's peak force at the starting parameters (N)."""
    fname = meas.columns[1]
    if sim_peak <= 0:
        raise MeasurementError("the model gives no insertion force at the starting parameters: nothing to fit")
    ratio = measured_peak / sim_peak
    if ratio > _UNIT_FACTOR or ratio < 1 / _UNIT_FACTOR:
        hint = ""
        if 200 < ratio < 5000:
            hint = " — is it in mN? (name the column force_mN)"
        elif 1 / 5000 < ratio < 1 / 200:
            hint = " — is it in kN? (name the column force_kN)"
        raise MeasurementError(
            f"{meas.source}: force column {fname!r} peaks at {measured_peak:.4g} but the model gives "
            f"{sim_peak:.4g} N at the starting parameters (a factor {ratio:.3g}){hint}; give force in N"
        )


# The model's force counts where it is at least this fraction of its peak: where the rigid part
# presses the part, the measured force must point the same way.
_SIGN_FLOOR = 0.2


def _check_force_sign(meas: Measurement, t: np.ndarray, sim: np.ndarray, measured: np.ndarray):
    """Sign-convention errors: where the model pushes back (its insertion force positive and
    large), the measured force must be mostly positive too. A measurement that is mostly negative
    there is the same history with the opposite sign (a load cell that reads compression as
    negative, a force on the rigid part rather than on the socket): no E or friction fits it, and
    the fit would return the smallest force it can make instead of an error."""
    sim, measured, t = (np.asarray(a, np.float64) for a in (sim, measured, t))
    pushing = sim >= _SIGN_FLOOR * float(np.max(sim, initial=0.0))
    if float(np.max(sim, initial=0.0)) <= 0 or pushing.sum() < 4:
        return
    against = float(np.mean(measured[pushing] < 0))
    if against > 0.5 and float(np.dot(sim, measured)) < 0:
        fname = meas.columns[1]
        raise MeasurementError(
            f"{meas.source}: force column {fname!r} is negative at {100 * against:.0f} % of the times "
            f"where the model's insertion force is positive (t = {t[pushing][0]:g} to {t[pushing][-1]:g} s, "
            f"the rigid part pressing into the part; measured median there {np.median(measured[pushing]):.4g} "
            "N): jsnap's insertion force is positive while the part resists the rigid part; negate the "
            "column (F = -F) and fit again"
        )


@x64
def identify(
    model: Model,
    measured: Measurement | str | Path,
    *,
    fit=("E", "friction"),
    initial: dict | None = None,
    max_iters: int = 30,
    xtol: float = 1e-4,
    max_step: float = 0.5,
    smooth: float = 3.0,
    seed: bool = True,
    progress: bool = True,
) -> FitResult:
    """Fit parameters of ``model`` to a measured insertion-force history.

    Args:
        model: ``jsnap.build(scene)``; the scene's parameters are the starting point (and the
            values of the parameters not fitted).
        measured: a :class:`Measurement` or a CSV path (see :func:`load_measurement`), time in
            s from the start of the motion, force in N. Samples beyond the scene's motion keep
            the plug at its final position.
        fit: names from ``FIT_PARAMETERS``: ``E`` (MPa), ``friction``, ``alpha`` (1/s),
            ``beta`` (s), ``time_shift`` (s, the measurement lags the motion by this),
            ``plug_offset`` (mm along +z, the plug's actual path is offset by this).
        initial: starting values overriding the scene's (parameters' units); a positive
            parameter that is 0 in the scene starts at ``_ZERO_START``.
        max_iters: L-BFGS iterations at most.
        max_step: no fit variable moves more than this in one iteration (a factor e^0.5 =
            1.65 for the positive parameters; 0.5 steps' time or travel for shift/offset).
        smooth: compare the histories smoothed by a Gaussian of this standard deviation, in
            simulation steps (see :func:`smoothing_filter`; 0: raw samples).
        xtol: stop when no fit variable (log of a positive parameter; shift/offset in steps)
            changes by more than this in an iteration.
        seed: start the local fit from a global seed search (forward rollouts only): E by its
            closed-form force scale and, when fitted, friction on a log grid over a factor 4
            either way of its start (:func:`_seed`). Without it, E is fitted alone for a few
            iterations first.
        progress: show a tqdm progress bar.

    Returns:
        :class:`FitResult`.

    Raises:
        MeasurementError: unusable data (see :func:`load_measurement`), units obviously off, or
            a force of the opposite sign to the model's.
        ValueError: unknown parameter names or non-positive starting values.
    """
    t0 = time.perf_counter()
    names = tuple(dict.fromkeys(fit))
    bad = [k for k in names if k not in FIT_PARAMETERS]
    if bad or not names:
        raise ValueError(
            f"fit: unknown parameter(s) {bad or '(none given)'}; choose from {', '.join(FIT_PARAMETERS)}"
        )
    meas = measured if isinstance(measured, Measurement) else load_measurement(measured)
    initial = dict(initial or {})
    unknown = [k for k in initial if k not in FIT_PARAMETERS]
    if unknown:
        raise ValueError(f"initial: unknown parameter(s) {unknown}; choose from {', '.join(FIT_PARAMETERS)}")
    start = {}
    for k in names:
        if k in _POSITIVE:
            v = float(initial.get(k, float(getattr(model.params, k))))
            if k not in initial and v == 0:
                v = _ZERO_START[k]
            if not v > 0:
                raise ValueError(f"initial {k} = {v:g}: must be > 0 (it is fitted as a logarithm)")
        else:
            v = float(initial.get(k, 0.0))
        start[k] = v
    base = model.params.replace(**{k: v for k, v in initial.items() if k in _POSITIVE and k not in names})

    dt = model.dt
    _check_time_scale(meas, model.n_steps * dt)
    n_steps = max(1, math.floor(meas.t[-1] / dt + 1e-9))
    t_sim = (np.arange(n_steps) + 1) * dt
    F_meas, mask = resample(meas, t_sim, dt)
    if mask.sum() < 4:
        raise MeasurementError(
            f"{meas.source}: only {int(mask.sum())} of the simulation's output times ({dt:g} s apart) lie "
            f"within the measurement's time range [{meas.t[0]:g}, {meas.t[-1]:g}] s"
        )
    prob = _problem(model, base, names, n_steps)
    theta0 = np.array(
        [
            math.log(start[k]) if k in _POSITIVE else start[k] / (dt if k == "time_shift" else prob.step_travel)
            for k in names
        ]
    )
    G = smoothing_filter(mask, smooth)
    obj = _Objective(
        prob,
        jnp.asarray(F_meas),
        jnp.asarray(G),
        jnp.asarray(float(np.max(np.abs(F_meas[mask])))),
        jnp.asarray(float(mask.sum())),
    )

    theta = jnp.asarray(theta0)
    F0 = np.asarray(_force(prob, theta))
    _check_force_scale(meas, float(np.max(np.abs(F0[mask]))), float(np.max(np.abs(F_meas[mask]))))
    _check_force_sign(meas, t_sim[mask], F0[mask], F_meas[mask])
    seeded, n_seed = None, 0
    if seed:
        theta, n_seed, seeded = _seed(obj, theta, names, progress)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=max_iters, desc="jsnap fit", unit="it")
    run = _Run(obj, mask, theta, bar, max_step, xtol)
    # Without a seed: the force scale first, E alone (a few iterations), then everything. E and
    # friction both scale the force (F ≈ E w(μ) on the ramp); fitted together from far off, the
    # first steps trade one for the other along that valley, and may carry friction into the
    # stick-slip regime where the force history is rough (docs/differentiation.md).
    if "E" in names and len(names) > 1 and seeded is None:
        theta = run.minimise(theta, [names.index("E")], min(_SCALE_ITERS, max_iters))
    theta = run.minimise(theta, list(range(len(names))), max_iters - run.iterations)
    if bar is not None:
        bar.close()
    history, evaluations, converged, it = run.history, run.evaluations, run.converged, run.iterations

    # Gauss–Newton / Laplace covariance from the residuals' Jacobian (forward mode). The fit
    # minimises |G (F(θ) − F_meas)|², so for white noise of variance σ² (estimated from the raw
    # residuals: model error counts as noise) the linearised estimator's covariance is the
    # sandwich σ² A⁻¹ J_Gᵀ G Gᵀ J_G A⁻¹, A = J_Gᵀ J_G, J_G = G J (= σ² A⁻¹ without smoothing).
    F_fit, J = run.force, run.jac  # at the final point
    F_fit = np.asarray(F_fit)
    Gm = G[mask][:, mask]
    J = np.asarray(J)[mask]
    JG = Gm @ J
    r = (F_fit - F_meas)[mask]
    m, p = r.size, len(names)
    sigma2 = float(r @ r) / max(m - p, 1)
    vals = {k: float(v) for k, v in prob.unpack(theta).items()}
    # d value / d theta: value for logs, the scale for shift/offset.
    dv = np.array(
        [vals[k] if k in _POSITIVE else (dt if k == "time_shift" else prob.step_travel) for k in names]
    )
    JtJ = JG.T @ JG
    B = JG.T @ Gm
    B = B @ B.T
    try:
        Ainv = np.linalg.inv(JtJ)
        cov_theta = sigma2 * Ainv @ B @ Ainv
        if not np.all(np.isfinite(cov_theta)) or np.any(np.diag(cov_theta) < 0):
            raise np.linalg.LinAlgError
    except np.linalg.LinAlgError:
        Ainv = np.linalg.pinv(JtJ)
        cov_theta = sigma2 * Ainv @ B @ Ainv
        cov_theta[np.diag(JtJ) <= 0] = np.inf
    cov = cov_theta * np.outer(dv, dv)
    se = np.sqrt(np.abs(np.diag(cov)))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(se, se)
    fitted_params = base.replace(**{k: vals[k] for k in names if k in _POSITIVE})
    return FitResult(
        names=names,
        values=vals,
        initial=start,
        std_errors={k: float(s) for k, s in zip(names, se, strict=True)},
        correlation=corr,
        params=fitted_params,
        t=t_sim,
        mask=mask,
        measured=F_meas,
        fitted=F_fit,
        start=F0,
        rms_residual=float(np.sqrt(np.mean(r * r))),
        noise_estimate=math.sqrt(sigma2),
        loss_history=history,
        iterations=it,
        evaluations=evaluations,
        seeded=seeded,
        rollouts=n_seed,
        seconds=time.perf_counter() - t0,
        converged=converged,
        source=meas.source,
    )


def _parse_init(text: str | None) -> dict:
    out = {}
    for item in filter(None, (s.strip() for s in (text or "").split(","))):
        key, sep, val = item.partition("=")
        if not sep:
            raise ValueError(f"--init: {item!r} is not NAME=VALUE")
        try:
            out[key.strip()] = float(val)
        except ValueError:
            raise ValueError(f"--init: {key.strip()} = {val!r} is not a number") from None
    return out


def fit_command(args) -> int:
    """``jsnap fit SCENE.toml MEASURED.csv [--fit ...] [--init ...] [--out DIR] [--json]``."""
    import sys

    from jsnap._build.model import build
    from jsnap._geometry.scene import SceneError, load_scene

    try:
        names = [s.strip() for s in args.fit.split(",") if s.strip()]
        initial = _parse_init(args.init)
        meas = load_measurement(args.measured, time_column=args.time_column, force_column=args.force_column)
        scene = load_scene(args.scene)
        model = build(scene, progress=not args.json)
        quiet = args.json
        fit = identify(
            model,
            meas,
            fit=names,
            initial=initial,
            max_iters=args.max_iters,
            smooth=args.smooth,
            progress=not quiet,
        )
    except (MeasurementError, SceneError, ValueError, FileNotFoundError) as err:
        print(f"jsnap: error: {err}", file=sys.stderr)
        return 2
    summary = fit.write(args.out)
    summary["scene"] = scene.source
    Path(summary["outputs"]["json"]).write_text(json.dumps(summary, indent=2))
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"jsnap: fit of {', '.join(fit.names)} to {meas.source}:")
        print(fit.summary())
        print(f"  wrote {args.out}/fit.json, fit.csv, fit.png")
    return 0
