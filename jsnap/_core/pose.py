"""Rigid-body rotations as unit quaternions (w, x, y, z), for the rigid part's pose."""

from __future__ import annotations

import jax.numpy as jnp

from jsnap._core.util import safe_norm

__all__ = ["angular_velocity", "quat_matrix"]


def quat_matrix(q):
    """(3, 3) rotation matrix of the unit quaternion ``q`` (4,)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    return jnp.stack(
        [
            jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)]),
            jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)]),
            jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]),
        ]
    )


def angular_velocity(q0, q1, dt):
    """(3,) constant angular velocity (rad/s, world axes) that turns ``q0`` into ``q1`` over
    ``dt``: the rotation vector of ``q1 q0^-1`` (the shorter way round) over ``dt``."""
    w0, v0 = q0[0], q0[1:]
    w1, v1 = q1[0], q1[1:]
    # q1 * conj(q0)
    w = w1 * w0 + jnp.dot(v1, v0)
    v = -w1 * v0 + w0 * v1 - jnp.cross(v1, v0)
    sign = jnp.where(w < 0, -1.0, 1.0).astype(w.dtype)
    w, v = sign * w, sign * v
    s = safe_norm(v)
    angle = 2 * jnp.arctan2(s, w)
    # angle / sin(angle / 2) -> 2 as the angle -> 0
    scale = jnp.where(s > 1e-12, angle / jnp.where(s > 1e-12, s, 1.0), 2.0 / jnp.maximum(w, 1e-30))
    return scale * v / dt
