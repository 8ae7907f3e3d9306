"""Small numerical helpers shared by the kernels."""

import jax.numpy as jnp


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
