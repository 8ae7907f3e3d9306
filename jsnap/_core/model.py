"""The built scene as a pytree: what the kernels read.

A :class:`Model` is made once on the host (``jsnap.build``) and holds only arrays and static
choices: the deformable part (:mod:`jsnap._core.parts`), its contact candidate points, the rigid
part's signed distance (:mod:`jsnap._core.sdf`), how the rigid part is driven
(:mod:`jsnap._core.drive`), the contact solver (:mod:`jsnap._core.contact`), the physical
parameters and the scene's motion. Components are types chosen at build time; a field is traced
if and only if it is an array. Units: mm, N, MPa, s, tonne.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jsnap._core.contact import AbstractContactSolver
from jsnap._core.drive import AbstractDrive
from jsnap._core.params import Params
from jsnap._core.parts import AbstractPart, FullPart, ModalPart, ReducedPart, SegmentedPart
from jsnap._core.sdf import AbstractSDF
from jsnap._core.util import cast_floats

__all__ = ["ContactSettings", "MeshArrays", "Model", "Samples"]


class Samples(eqx.Module):
    """Contact candidate points on the deformable part's surface.

    Attributes:
        rest: (P, 3) rest positions, mm.
        stencil: (P, 8, 3) rest positions of each point's normal stencils, mm: the deformed
            normals of its side and (at a corner) of the other side are
            ``cross(s3 - s2, s1 - s0)`` and ``cross(s7 - s6, s5 - s4)``.
        corner: (P,) bool, point on a convex edge (normal: the rigid part's, within the cone of
            the two sides' normals).
        group: (P,) int, one group per line of points (a section side at one width position);
            order: (P,) int, the point's place along its line.
        n_groups: number of lines (static).
        line: (P, 3) unit direction of each point's line (rest), from its first point to its
            last (zero for a line of one point).
        reach: (P, 2) rest distances along it from the point back to its line's first point
            and on to its last, mm.
        spacing: distance between neighbouring points along a line, mm (static).
        hand_over: a face point beside an edge that the rigid part presses leaves its contact
            to the edge (static; the general surface sampling; see
            :func:`jsnap._core.collision.contact_normal`).
    """

    rest: jax.Array
    stencil: jax.Array
    corner: jax.Array
    group: jax.Array
    order: jax.Array
    line: jax.Array
    reach: jax.Array
    n_groups: int = eqx.field(static=True)
    spacing: float = eqx.field(static=True)
    hand_over: bool = eqx.field(static=True)


class ContactSettings(eqx.Module):
    """How contact is detected and solved.

    Attributes:
        solver: the cone-complementarity solver (its type is the algorithm).
        capacity: contact buffer slots (static): the most points in contact at once.
        margin: distance below which a point is a contact candidate, mm (static).
        compliance: contact regularisation per point, mm/N (static).
        stabilisation: the fraction of a point's penetration into the rigid part that a step
            removes (static; 0: none, the contact holds velocities only).
    """

    solver: AbstractContactSolver
    capacity: int = eqx.field(static=True)
    margin: float = eqx.field(static=True)
    compliance: float = eqx.field(static=True)
    stabilisation: float = eqx.field(static=True, default=0.0)


class MeshArrays(eqx.Module):
    """The deformable part's mesh, for outputs (ParaView series, strain); unused by the step.

    Attributes:
        nodes: (N, 3) node positions, mm (P2: vertices, then edge midpoints).
        cells: (M, 4) or (M, 10) node indices (P2 in scikit-fem's order).
        free: (n_free,) free dofs of the 3N nodal vector (``3 node + component``).
    """

    nodes: jax.Array
    cells: jax.Array
    free: jax.Array


_METHODS = {FullPart: "full", ModalPart: "modal", SegmentedPart: "segmented", ReducedPart: "reduced"}


class Model(eqx.Module):
    """A built scene.

    Attributes:
        part: the deformable part's linear model (full, modal, segmented or reduced).
        samples: contact candidate points on it.
        rigid: the rigid part's signed distance, in its own frame.
        drive: how the rigid part follows its desired pose (position or impedance control).
        contact: detection and solver settings.
        params: the scene's physical parameters (the default of ``rollout``).
        motion: (n + 1, 3) the scene's desired rigid-part centres at t_k = k dt, mm (row 0:
            the start pose); (n + 1, 7) with the orientation as a unit quaternion (w, x, y, z)
            in the last four columns when the rigid part turns.
        mesh: the deformable part's mesh (outputs only).
        dt: time step, s (static).
        dtype: default rollout precision, ``"float32"`` or ``"float64"`` (static).
        axis: (3,) unit insertion axis: the insertion force is the contact force along it.
    """

    part: AbstractPart
    samples: Samples
    rigid: AbstractSDF
    drive: AbstractDrive
    contact: ContactSettings
    params: Params
    motion: jax.Array
    mesh: MeshArrays
    dt: float = eqx.field(static=True)
    dtype: str = eqx.field(static=True)
    axis: jax.Array = eqx.field(default_factory=lambda: np.array([0.0, 0.0, -1.0]))

    @property
    def rotates(self) -> bool:
        """The scene's motion turns the rigid part (its poses hold quaternions)."""
        return self.motion.shape[-1] == 7

    @property
    def method(self) -> str:
        """Which model of the deformable part this is (``"full"``, ``"modal"``, ``"segmented"`` or
        ``"reduced"``)."""
        return _METHODS[type(self.part)]

    @property
    def n_dof(self) -> int:
        """Coordinates of the deformable part's state (free dofs, or modal / reduced ones)."""
        return self.part.n_dof

    @property
    def full_dof(self) -> int:
        """Free dofs of the full mesh."""
        return int(self.mesh.free.shape[0])

    @property
    def element(self) -> str:
        """``"P1"`` or ``"P2"``."""
        return "P1" if self.mesh.cells.shape[1] == 4 else "P2"

    @property
    def n_steps(self) -> int:
        """Steps of the scene's motion."""
        return self.motion.shape[0] - 1

    @property
    def n_samples(self) -> int:
        return self.samples.rest.shape[0]

    @property
    def plug_start(self) -> jax.Array:
        """(3,) the rigid part's centre at t = 0, mm."""
        return self.motion[0, :3]

    @property
    def rotation_start(self) -> jax.Array:
        """(4,) the rigid part's orientation at t = 0, a unit quaternion (w, x, y, z)."""
        if self.rotates:
            return self.motion[0, 3:]
        return jnp.array([1.0, 0.0, 0.0, 0.0], self.motion.dtype)

    def trajectory(self) -> np.ndarray:
        """(n_steps + 1, 3) desired rigid-part centres at t_k = k dt, mm, or (n_steps + 1, 7)
        poses with their quaternions when the rigid part turns (host copy)."""
        return np.asarray(self.motion)

    def astype(self, dtype) -> Model:
        """The model with every floating array in ``dtype`` (rollouts cast it themselves)."""
        return dataclasses.replace(cast_floats(self, dtype), dtype=str(np.dtype(dtype)))
