"""Motions of the rigid part: the desired pose over time (host side).

Units: mm, s.
"""

from __future__ import annotations

import math

import numpy as np

from jsnap._geometry.errors import SceneError

__all__ = [
    "UNIT_TOLERANCE",
    "MotionError",
    "check_poses",
    "latching_stroke",
    "quat_matrix",
    "quat_multiply",
    "read_pose_csv",
    "sample_poses",
    "straight_insertion",
    "straight_poses",
]


def latching_stroke(plug_height: float, clearance: float, hook_height: float, overshoot: float = 0.3) -> float:
    """Travel along -z that latches the preset plug: its top passes ``overshoot`` below the
    retention edge (``hook_height`` = z_top - L of the cantilever), mm."""
    return clearance + hook_height + plug_height + overshoot


def straight_insertion(start, speed: float, stroke: float, withdraw: bool, dt: float) -> np.ndarray:
    """(n + 1, 3) desired centres at t_k = k dt of a straight insertion along -z at ``speed``
    (mm/s) over ``stroke`` (mm) from ``start`` (3,), and back up when ``withdraw``; n covers
    the whole motion."""
    duration = stroke / speed * (2 if withdraw else 1)
    n_steps = math.ceil(duration / dt - 1e-9)
    t = np.arange(n_steps + 1) * dt
    t_in = stroke / speed
    travel = np.where(t <= t_in, speed * t, stroke)
    if withdraw:
        travel = np.where(t > t_in, np.maximum(stroke - speed * (t - t_in), 0), travel)
    out = np.tile(np.asarray(start, dtype=np.float64), (t.size, 1))
    out[:, 2] -= travel
    return out


# A pose's rotation is a unit quaternion if its length is 1 within this (a quaternion written
# out to 7 digits or more).
UNIT_TOLERANCE = 1e-6


class MotionError(SceneError):
    """A motion that cannot be used; the message names the key or file (and the row)."""


def quat_multiply(a, b) -> np.ndarray:
    """Hamilton product of quaternions (w, x, y, z), broadcasting over leading axes."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a, np.float64), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, np.float64), -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_matrix(q) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4) (w, x, y, z)."""
    w, x, y, z = np.moveaxis(np.asarray(q, np.float64), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def _slerp(q0, q1, s) -> np.ndarray:
    """Spherical linear interpolation between unit quaternions q0, q1 (4,) at fractions s (k,)."""
    d = float(np.dot(q0, q1))
    if d < 0:  # the shorter arc
        q1, d = -q1, -d
    if d > 1 - 1e-12:
        q = q0[None] + s[:, None] * (q1 - q0)[None]
        return q / np.linalg.norm(q, axis=1, keepdims=True)
    theta = np.arccos(d)
    return (np.sin((1 - s) * theta)[:, None] * q0 + np.sin(s * theta)[:, None] * q1) / np.sin(theta)


def check_poses(t, position, rotation, where: str) -> None:
    """Times strictly increasing from 0, finite positions, unit quaternions; raises
    :class:`MotionError` naming ``where`` and the row."""
    t, position, rotation = (np.asarray(a, np.float64) for a in (t, position, rotation))
    if t.ndim != 1 or t.size < 2:
        raise MotionError(f"{where}: at least two poses are needed, got {t.size}")
    if position.shape != (t.size, 3) or rotation.shape != (t.size, 4):
        raise MotionError(f"{where}: each pose needs a position (3 numbers) and a rotation (4 numbers)")
    bad = ~(np.isfinite(t) & np.all(np.isfinite(position), 1) & np.all(np.isfinite(rotation), 1))
    if bad.any():
        raise MotionError(f"{where}: pose {int(np.flatnonzero(bad)[0])} is not finite")
    if t[0] != 0.0:
        raise MotionError(f"{where}: the first pose must be at t = 0, got t = {t[0]:g} s")
    step = np.flatnonzero(np.diff(t) <= 0)
    if step.size:
        i = int(step[0]) + 1
        raise MotionError(
            f"{where}: time must increase, but pose {i} has t = {t[i]:g} s after t = {t[i - 1]:g} s"
        )
    norm = np.linalg.norm(rotation, axis=1)
    off = np.flatnonzero(np.abs(norm - 1) > UNIT_TOLERANCE)
    if off.size:
        i = int(off[0])
        raise MotionError(
            f"{where}: the rotation of pose {i} is not a unit quaternion (|q| = {norm[i]:.9g}); "
            "give (w, x, y, z) with w^2 + x^2 + y^2 + z^2 = 1"
        )


def sample_poses(t, position, rotation, start, dt: float) -> np.ndarray:
    """(n + 1, 7) poses [centre (3), quaternion (w, x, y, z)] at t_k = k dt, k = 0..n covering
    ``t[-1]``, from key poses: ``position`` (m, 3) relative to ``start`` (3,) and ``rotation``
    (m, 4) about the centre, interpolated linearly and by slerp (held after the last)."""
    t, position, rotation = (np.asarray(a, np.float64) for a in (t, position, rotation))
    n_steps = math.ceil(t[-1] / dt - 1e-9)
    tk = np.minimum(np.arange(n_steps + 1) * dt, t[-1])
    seg = np.clip(np.searchsorted(t, tk, side="right") - 1, 0, t.size - 2)
    s = (tk - t[seg]) / (t[seg + 1] - t[seg])
    pos = position[seg] + s[:, None] * (position[seg + 1] - position[seg])
    quat = np.empty((tk.size, 4))
    for i in range(t.size - 1):
        here = seg == i
        if here.any():
            quat[here] = _slerp(rotation[i], rotation[i + 1], s[here])
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    return np.concatenate([np.asarray(start, np.float64)[None] + pos, quat], axis=1)


def straight_poses(start, direction, speed: float, stroke: float, withdraw: bool, dt: float) -> np.ndarray:
    """(n + 1, 7) poses of a straight insertion along the unit ``direction`` (no rotation)."""
    d = np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    along = straight_insertion(np.zeros(3), speed, stroke, withdraw, dt)[:, 2]  # -travel
    pos = np.asarray(start, np.float64)[None] - along[:, None] * d[None]
    return np.concatenate([pos, np.tile([1.0, 0, 0, 0], (pos.shape[0], 1))], axis=1)


def read_pose_csv(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(t, position, rotation)`` from a CSV file with columns t, x, y, z, qw, qx, qy, qz (a
    header row naming them is allowed); checked like waypoints."""
    from pathlib import Path

    path = Path(path)
    where = f"motion.trajectory = {str(path)!r}"
    if not path.is_file():
        raise MotionError(f"{where}: no such file")
    lines = [ln for ln in path.read_text().splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    rows = []
    for i, line in enumerate(lines):
        fields = [f.strip() for f in line.split(",")]
        try:
            rows.append([float(f) for f in fields])
        except ValueError:
            if i == 0:  # a header
                continue
            raise MotionError(f"{where}: line {i + 1} is not 8 numbers: {line!r}") from None
        if len(fields) != 8:
            raise MotionError(
                f"{where}: line {i + 1} has {len(fields)} columns, expected t, x, y, z, qw, qx, qy, qz"
            )
    data = np.array(rows, np.float64).reshape(-1, 8)
    check_poses(data[:, 0], data[:, 1:4], data[:, 4:], where)
    return data[:, 0], data[:, 1:4], data[:, 4:]
