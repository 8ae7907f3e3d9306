"""Physical parameters: traced, differentiable, batchable scalars, and their validity.

Units: mm, N, MPa, s, tonne (density in t/mm^3).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["FIELDS", "Material", "Params", "lame", "params_valid"]


def lame(E, nu):
    """Lamé parameters ``(lambda, mu)`` in MPa from Young's modulus ``E`` (MPa) and Poisson's
    ratio ``nu``. Works on floats, NumPy and JAX arrays alike."""
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    mu = E / (2.0 * (1.0 + nu))
    return lam, mu


class Material(eqx.Module):
    """Material parameters, each a scalar array.

    Attributes:
        E: Young's modulus, MPa.   nu: Poisson's ratio.   rho: density, t/mm^3.
        alpha: Rayleigh mass-proportional damping, 1/s.
        beta: Rayleigh stiffness-proportional damping, s.
    """

    E: jax.Array
    nu: jax.Array
    rho: jax.Array
    alpha: jax.Array
    beta: jax.Array

    @classmethod
    def create(cls, E, nu, rho, alpha=0.0, beta=0.0) -> Material:
        return cls(*(jnp.asarray(v, jnp.float64) for v in (E, nu, rho, alpha, beta)))


# Field -> (lower bound, lower bound open?, upper bound): the range each parameter must lie in.
FIELDS = {
    "E": (0.0, True, None),
    "nu": (-1.0, True, 0.5),
    "rho": (0.0, True, None),
    "alpha": (0.0, False, None),
    "beta": (0.0, False, None),
    "friction": (0.0, False, None),
}


class Params(eqx.Module):
    """Physical parameters of a scene, each a scalar array (or a batch of them, for
    :func:`jsnap.rollout_batch`): traced, differentiable, batchable.

    Attributes:
        E: Young's modulus, MPa.
        nu: Poisson's ratio, in (-1, 0.5).
        rho: density, t/mm^3.
        alpha: Rayleigh mass damping, 1/s.
        beta: Rayleigh stiffness damping, s.
        friction: Coulomb coefficient between the rigid part and the deformable part.
    """

    E: jax.Array
    nu: jax.Array
    rho: jax.Array
    alpha: jax.Array
    beta: jax.Array
    friction: jax.Array

    @classmethod
    def create(cls, E, nu, rho, alpha=0.0, beta=0.0, friction=0.0) -> Params:
        """Parameters from numbers or arrays (stored as float64)."""
        with jax.enable_x64(True):
            vals = (E, nu, rho, alpha, beta, friction)
            return cls(*(jnp.asarray(v, jnp.float64) for v in vals))

    @property
    def material(self) -> Material:
        return Material(self.E, self.nu, self.rho, self.alpha, self.beta)

    def replace(self, **kw) -> Params:
        """A copy with some fields replaced, e.g. ``params.replace(E=2500.0)``."""
        for k in kw:
            if k not in FIELDS:
                raise TypeError(f"Params has no field {k!r}; its fields are {', '.join(FIELDS)}")
        return Params(**{**{f: getattr(self, f) for f in FIELDS}, **kw})

    def check(self) -> None:
        """Raise ValueError naming the first field that is not finite or out of its range
        (fields that are traced are skipped: under ``jit`` and ``vmap`` the result is flagged
        instead, see :func:`params_valid`)."""
        for name, (lo, lo_open, hi) in FIELDS.items():
            v = getattr(self, name)
            if isinstance(v, jax.core.Tracer):
                continue
            v = np.asarray(v)
            if not np.all(np.isfinite(v)):
                raise ValueError(f"Params.{name} must be finite, got {v}")
            bad = (v <= lo) if lo_open else (v < lo)
            if hi is not None:
                bad = bad | (v >= hi)
            if np.any(bad):
                rng = f"in ({lo}, {hi})" if hi is not None else (f"> {lo}" if lo_open else f">= {lo}")
                raise ValueError(f"Params.{name} must be {rng}, got {v}")


def params_valid(params: Params) -> jax.Array:
    """Bool array (the parameters' batch shape): every field finite and within its range."""
    ok = jnp.asarray(True)
    for name, (lo, lo_open, hi) in FIELDS.items():
        v = jnp.asarray(getattr(params, name))
        good = jnp.isfinite(v) & ((v > lo) if lo_open else (v >= lo))
        if hi is not None:
            good = good & (v < hi)
        ok = ok & good
    return ok
