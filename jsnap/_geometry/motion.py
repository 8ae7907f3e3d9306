"""Motions of the rigid part: the desired pose over time (host side).

Units: mm, s.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["latching_stroke", "straight_insertion"]


def latching_stroke(plug_height: float, clearance: float, hook_height: float) -> float:
    """Travel along -z that latches the preset plug: its top passes 0.3 mm below the retention
    edge (``hook_height`` = z_top - L of the cantilever), mm."""
    return clearance + hook_height + plug_height + 0.3


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
