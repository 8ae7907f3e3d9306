"""How the rigid part follows its desired pose: position control or impedance control.

Both are PMI on the rigid part: over a step its midpoint velocity is
``vbar_p = vp_free - s_p * F`` with ``F`` the sum of the contact forces on the deformable part
(N) and ``s_p`` its mobility (mm/(N s)); position control moves it kinematically (``s_p = 0``).
Units: mm, N, s, tonne.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp

__all__ = ["AbstractDrive", "ImpedanceDrive", "PositionDrive"]


class AbstractDrive(eqx.Module):
    """The rigid part's drive."""

    @abc.abstractmethod
    def free(self, plug, plug_vel, target, control, dt):
        """``(vp_free, s_p)``: the midpoint velocity (3,) without contact, mm/s, and the
        mobility (scalar) of the rigid part over the step from its state, the last desired
        centre ``target`` and the next one ``control`` (3,), mm."""

    @abc.abstractmethod
    def finish(self, plug, target, control, vbar_p, total, dt):
        """``(plug_new, coupling)``: the centre at the end of the step (3,) and the force of the
        drive on the rigid part (3,), N, given its midpoint velocity ``vbar_p`` and the total
        contact force ``total`` (3,) on the deformable part."""


class PositionDrive(AbstractDrive):
    """The rigid part moves exactly as commanded; the drive's force is the contact force."""

    def free(self, plug, plug_vel, target, control, dt):
        return (control - target) / dt, jnp.zeros((), plug.dtype)

    def finish(self, plug, target, control, vbar_p, total, dt):
        return control, total


class ImpedanceDrive(AbstractDrive):
    """A virtual spring-damper between the desired pose and the rigid part (the haptic case:
    the coupling force is what a haptic device renders).

    Attributes:
        stiffness: N/mm.   damping: N s/mm.   mass: the rigid part's mass, t.
    """

    stiffness: jax.Array
    damping: jax.Array
    mass: jax.Array

    def free(self, plug, plug_vel, target, control, dt):
        k, b, m = self.stiffness, self.damping, self.mass
        s_p = 1.0 / (2 * m / dt + b + 0.5 * dt * k)
        v_des = (control - target) / dt
        mid_target = 0.5 * (control + target)
        return s_p * (2 * m / dt * plug_vel + k * (mid_target - plug) + b * v_des), s_p

    def finish(self, plug, target, control, vbar_p, total, dt):
        xbar_p = plug + 0.5 * dt * vbar_p
        v_des = (control - target) / dt
        coupling = self.stiffness * (0.5 * (control + target) - xbar_p) + self.damping * (v_des - vbar_p)
        return plug + dt * vbar_p, coupling
