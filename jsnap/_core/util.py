"""Small numerical helpers shared by the kernels, and jsnap's scoped 64-bit mode."""

import functools

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["cast_floats", "safe_norm", "x64"]


def safe_norm(x, axis=-1, keepdims=False, eps=1e-30):
    """Euclidean norm whose gradient is zero (not NaN) where ``x`` is zero.

    Args:
        x: array (..., d).
        axis: reduction axis.
        keepdims: keep the reduced axis.
        eps: squared-norm threshold below which the norm is taken as 0.
    """
    sq = jnp.sum(x * x, axis=axis, keepdims=keepdims)
    ok = sq > eps
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0)


def x64(fn):
    """Run ``fn`` with JAX's 64-bit types enabled for its own duration only.

    jsnap precomputes in float64 (assembly, the PMI operator's inverse, reductions) and rolls out
    in the precision asked for. ``jax_enable_x64`` is a setting of the whole process; rather than
    switching it on at import (which would change every other JAX program in the process, an RL
    policy's for one), each public entry point enters ``jax.enable_x64(True)`` around its own
    work. Arrays jsnap returns keep their dtype (float32 by default).

    A JAX transformation of the user's (``jit``, ``grad``, ``vmap``) compiles its program after
    jsnap's function has returned, outside that scope: calls traced by one must therefore run
    with 64-bit mode on around the transformation (``with jax.enable_x64(True): jax.jit(f)(x)``),
    and are refused with that advice otherwise.
    """

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        if not jax.config.jax_enable_x64 and any(
            isinstance(a, jax.core.Tracer) for a in jax.tree_util.tree_leaves((args, kwargs))
        ):
            # JAX lowers a transformed program after the transformation returns, so a scope
            # opened here would be closed by then, and the float64 parts of jsnap's program would
            # be lowered in 32-bit mode (which fails, or worse, rounds them).
            raise RuntimeError(
                f"jsnap.{fn.__name__} is being traced by a JAX transformation (jit, grad, vmap, ...) "
                "started outside JAX's 64-bit mode. jsnap precomputes in float64, so run the "
                "transformation inside `with jax.enable_x64(True):` (only that block is affected), "
                "or enable 64-bit mode for the process (jax.config.update('jax_enable_x64', True))"
            )
        with jax.enable_x64(True):
            return fn(*args, **kwargs)

    return wrapped


def cast_floats(tree, dtype):
    """``tree`` with every floating array leaf cast to ``dtype`` (other leaves unchanged)."""

    def f(a):
        if isinstance(a, jax.Array | np.ndarray) and jnp.issubdtype(a.dtype, jnp.floating):
            return a.astype(dtype)
        return a

    return jax.tree_util.tree_map(f, tree)
