"""Scene files: TOML in, a validated, immutable :class:`Scene` out.

Every key is declared once in :data:`SCHEMA` with its type, unit, default (or required), range
and meaning; the scene reference in the docs is generated from it. Unknown keys, missing
required keys, wrong types, non-finite numbers, out-of-range values and combinations that make
the result meaningless raise :class:`SceneError`, whose message names the key (``section.key``)
and the value; doubtful values warn with :class:`SceneWarning`.

A few keys and choices are internal: they exist for the tests and benchmarks that show why they
are not the default (projected Gauss–Seidel, the modal form, the segmentation's settings...).
Scene files and :meth:`Scene.replace` reject them; :func:`with_internal` sets them.

Units: mm, N, MPa, s, tonne (density in t/mm^3), angles in degrees.
"""

from __future__ import annotations

import functools
import math
import tomllib
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np

from jsnap._geometry.cantilever import Cantilever
from jsnap._geometry.errors import SceneError, SceneWarning
from jsnap._geometry.motion import UNIT_TOLERANCE, read_pose_csv
from jsnap._geometry.part import PartError, part_thinnest_wall, part_wall_thickness
from jsnap._geometry.presets import connector_features, default_rigid, default_stroke, hook_of
from jsnap._geometry.size import (
    GEOMETRIC,
    MIN_ELEMENTS_ACROSS,
    REFERENCE_WALL,
    SIZED,
    elements_across,
    preset_ratio,
    size_of,
)

__all__ = [
    "MIN_STEPS",
    "SCHEMA",
    "Key",
    "Scene",
    "SceneError",
    "SceneWarning",
    "connector_geometry",
    "default_scene_path",
    "load_scene",
    "motion_duration",
    "motion_keyposes",
    "motion_stroke",
    "scene_file",
    "sdf_kind",
    "with_internal",
]


REQUIRED = object()
# The largest contact.friction accepted (see the key).
_MAX_FRICTION = 2.0


@dataclass(frozen=True)
class Key:
    """One scene key.

    Attributes:
        kind: float, int, bool or str.
        default: the value when the key is absent; ``REQUIRED`` for none; None for "derived"
            (see ``doc``).
        unit: e.g. ``"mm"``; ``""`` for dimensionless.
        lo, hi: numeric range (None: unbounded), ``lo_open``/``hi_open`` for open ends.
        choices: the allowed strings; ``internal_choices``: more, for tests and benchmarks only.
        internal: the key is not part of scene files (tests and benchmarks set it).
        doc: what it means.
    """

    kind: type
    default: Any = REQUIRED
    unit: str = ""
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    choices: tuple[str, ...] | None = None
    internal_choices: tuple[str, ...] = ()
    internal: bool = False
    doc: str = ""
    shape: str = ""

    def range_text(self) -> str:
        """The allowed values, as the scene reference shows them."""
        if self.kind is list:
            return self.shape
        if self.choices is not None:
            return " | ".join(f'"{c}"' for c in self.choices)
        if self.kind is bool:
            return "true | false"
        if self.lo is None and self.hi is None:
            return "any"
        if self.hi is None:
            return f"{'>' if self.lo_open else '>='} {self.lo:g}"
        if self.lo is None:
            return f"{'<' if self.hi_open else '<='} {self.hi:g}"
        return f"{'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}{')' if self.hi_open else ']'}"

    def check(self, v) -> str | None:
        """Why ``v`` is out of range, or None."""
        if self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo):
            return f"must be in {self.range_text()}" if self.hi is not None else f"must be {self.range_text()}"
        if self.hi is not None and (v >= self.hi if self.hi_open else v > self.hi):
            return f"must be in {self.range_text()}" if self.lo is not None else f"must be {self.range_text()}"
        return None


def _pos(unit, default=REQUIRED, doc="", **kw):
    return Key(float, default, unit, lo=0.0, lo_open=True, doc=doc, **kw)


def _nonneg(unit, default=REQUIRED, doc="", **kw):
    return Key(float, default, unit, lo=0.0, doc=doc, **kw)


def _numbers(value, shape: tuple[int, ...], name: str):
    """``value`` as nested lists of finite floats of ``shape``, or SceneError."""
    try:
        if isinstance(value, str | bool) or any(isinstance(v, bool | str) for v in np.ravel(value)):
            raise TypeError
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        arr = None
    if arr is None or arr.shape != shape:
        want = " x ".join(map(str, shape))
        raise SceneError(f"{name} = {value!r}: must be {want} numbers")
    if not np.all(np.isfinite(arr)):
        raise SceneError(f"{name} = {value!r}: must be finite")
    return arr.tolist()


def _parse_box(name, value):
    box = _numbers(value, (2, 3), name)
    if not all(a < b for a, b in zip(*box, strict=True)):
        raise SceneError(f"{name} = {value!r}: the first corner must be below the second in x, y and z")
    return box


def _parse_direction(name, value):
    d = _numbers(value, (3,), name)
    if math.hypot(*d) == 0:
        raise SceneError(f"{name} = {value!r}: must not be zero")
    return d


def _parse_rotation(name, value):
    """A unit quaternion (w, x, y, z), normalised; refused when zero or more than
    ``UNIT_TOLERANCE`` off unit length (as the waypoints' rotations)."""
    q = np.asarray(_numbers(value, (4,), name))
    norm = float(np.linalg.norm(q))
    if norm == 0:
        raise SceneError(f"{name} = {value!r}: must not be zero; [1, 0, 0, 0] is no rotation")
    if abs(norm - 1) > UNIT_TOLERANCE:
        raise SceneError(
            f"{name} = {value!r}: not a unit quaternion (|q| = {norm:.9g}); give (w, x, y, z) with "
            f"w^2 + x^2 + y^2 + z^2 = 1 (within {UNIT_TOLERANCE:g})"
        )
    return (q / norm).tolist()


def _parse_waypoints(name, value):
    if not isinstance(value, list) or not all(isinstance(w, Mapping) for w in value):
        raise SceneError(
            f"{name}: must be an array of tables {{ t = ..., position = [...], rotation = [...] }}"
        )
    out = []
    for i, w in enumerate(value):
        extra = set(w) - {"t", "position", "rotation"}
        if extra:
            raise SceneError(
                f"{name}[{i}]: unknown key(s) {', '.join(sorted(extra))}; takes t, position, rotation"
            )
        if "t" not in w or "position" not in w:
            raise SceneError(f"{name}[{i}]: needs t (s) and position (mm); rotation defaults to [1, 0, 0, 0]")
        t = _numbers(w["t"], (), f"{name}[{i}].t")
        pos = _numbers(w["position"], (3,), f"{name}[{i}].position")
        rot = _numbers(w.get("rotation", [1.0, 0.0, 0.0, 0.0]), (4,), f"{name}[{i}].rotation")
        out.append({"t": t, "position": pos, "rotation": rot})
    from jsnap._geometry.motion import check_poses

    check_poses([w["t"] for w in out], [w["position"] for w in out], [w["rotation"] for w in out], name)
    return out


_PARSERS = {
    "part.fixed_box": _parse_box,
    "motion.direction": _parse_direction,
    "motion.waypoints": _parse_waypoints,
    "rigid.position": lambda name, value: _numbers(value, (3,), name),
    "rigid.rotation": _parse_rotation,
}


# The length unit of a part file's coordinates ([part] and [rigid]).
_UNITS = Key(str, "mm", choices=("mm", "m", "in"), doc="length unit of the file's coordinates")


def _hook_keys(arm: str, bending: str) -> dict[str, Key]:
    """The keys of a hook section (the cantilever's, the clip's arms', the annular lip's)."""
    return {
        "length": _pos("mm", doc=f"L, {arm} length from the fixed root (z = 0) to the retention face"),
        "thickness": _pos("mm", doc=f"h, {arm} thickness at the root ({bending})"),
        "undercut": _pos("mm", doc="y_u, how far the hook protrudes beyond the face it stands on"),
        "lead_angle": Key(
            float, REQUIRED, "deg", 0.0, 90.0, True, True, doc="alpha, lead ramp to the insertion axis"
        ),
        "return_angle": Key(
            float,
            REQUIRED,
            "deg",
            0.0,
            90.0,
            True,
            False,
            doc="alpha', retention face (90 = square, permanent)",
        ),
        "flat": _nonneg("mm", doc="land between the retention face and the lead ramp"),
    }


def _angle_keys(lead: str, ret: str) -> dict[str, Key]:
    """A preset's lead and return angles with defaults (30 and 90 degrees), ``lead`` and
    ``ret`` their docs."""
    return {
        "lead_angle": Key(float, 30.0, "deg", 0.0, 90.0, True, True, doc=lead),
        "return_angle": Key(float, 90.0, "deg", 0.0, 90.0, True, False, doc=ret),
    }


def _ordered(keys: dict[str, Key], order: str) -> dict[str, Key]:
    return {k: keys[k] for k in order.split()}


# The keys of each connector preset (connector.type); SCHEMA["connector"] holds only the type.
CONNECTORS: dict[str, dict[str, Key]] = {
    "cantilever": _ordered(
        {
            **_hook_keys("arm", "the bending direction x"),
            "tip_thickness": _pos(
                "mm", None, "h_tip, arm thickness at z = L (tapered arm); default: thickness"
            ),
            "width": _pos("mm", doc="b, arm width (y)"),
        },
        "length thickness tip_thickness width undercut lead_angle return_angle flat",
    ),
    "two_hook_clip": _ordered(
        {
            **_hook_keys("arm", "x"),
            "width": _pos("mm", doc="b, width of the arms and the base (y)"),
            "gap": _pos("mm", 4.0, "distance between the arms' inner faces (x), the rigid block's width"),
            "base_thickness": _pos(
                "mm", 2.0, "the base block's thickness under the arms (its bottom face is fixed)"
            ),
            "base_margin": _nonneg(
                "mm", 1.0, "how far the base block reaches beyond the arms' outer faces (x)"
            ),
        },
        "length thickness width undercut lead_angle return_angle flat gap base_thickness base_margin",
    ),
    "box_lid": _ordered(
        {
            **_hook_keys("arm", "x"),
            "width": _pos("mm", doc="b, width of each arm (y)"),
            "gap": _pos("mm", 8.0, "distance between facing arms' inner faces (x): the box's width"),
            "spacing": _pos("mm", 8.0, "distance between the centres of the two arms on a side (y)"),
            "lid_thickness": _pos(
                "mm", 1.5, "the lid plate's thickness under the arms (its outer face is fixed)"
            ),
            "lid_margin": _nonneg("mm", 1.0, "how far the lid reaches beyond the arms (x and y)"),
            "tilt": Key(
                float,
                3.0,
                "deg",
                0.0,
                10.0,
                False,
                False,
                doc="the box's tilt about the x axis: its -y end comes down first, so the hooks at -y "
                "engage before those at +y",
            ),
        },
        "length thickness width undercut lead_angle return_angle flat gap spacing lid_thickness lid_margin "
        "tilt",
    ),
    "cable_latch": _ordered(
        {
            "length": _pos("mm", 10.0, "L, latch arm length from its free end (z = 0) up to its root (z = L)"),
            "thickness": _pos("mm", 0.8, "h, latch arm thickness (x, the bending direction)"),
            "width": _pos("mm", 3.2, "b, width of the latch and the plug body (y)"),
            "catch_position": _pos(
                "mm", 6.0, "distance from the latch's root down to the catch's retention face"
            ),
            "undercut": _pos("mm", 0.6, "y_u, how far the catch protrudes beyond the arm's outer face (x)"),
            **_angle_keys(
                "alpha, the catch's lead ramp to the motion",
                "alpha', the catch's retention face (90 = square: the plug stays in until pressed)",
            ),
            "flat": _nonneg("mm", 0.3, "the catch's land between its retention face and lead ramp"),
            "gap": _pos("mm", 1.6, "clearance between the arm's inner face and the plug body (x)"),
            "body_thickness": _pos("mm", 3.0, "the plug body's thickness (x); its back face is fixed"),
        },
        "length thickness width catch_position undercut lead_angle return_angle flat gap body_thickness",
    ),
    "annular": _ordered(
        {
            "length": _pos("mm", 4.0, "L, from the tube's fixed end (z = 0) up to the lip's retention face"),
            "thickness": _pos("mm", 1.0, "h, the tube's wall thickness (radial)"),
            "undercut": _pos("mm", 0.12, "y_u, how far the lip reaches into the bore (radial)"),
            **_angle_keys(
                "alpha, the lip's lead ramp to the axis",
                "alpha', the lip's retention face (90 = square: the bead stays in)",
            ),
            "flat": _nonneg("mm", 0.1, "the lip's land between its retention face and lead ramp"),
            "radius": _pos("mm", 3.0, "R, the bore's radius (and the rigid bead's)"),
            "sector": Key(
                float,
                2.0,
                "deg",
                0.0,
                90.0,
                True,
                False,
                doc="the part modelled, a sector of the ring one element wide: its cut faces slide on their "
                "planes (exact for the straight insertion along the axis); its forces are the sector's, the "
                "whole ring's axial force is 360 / sector times it. Its facets are chords of the ring: their "
                "sagitta radius (1 - cos(sector / 2)) may be at most 2 % of the undercut",
            ),
        },
        "length thickness radius undercut lead_angle return_angle flat sector",
    ),
}

SCHEMA: dict[str, dict[str, Key]] = {
    "connector": {
        "type": Key(
            str,
            choices=tuple(CONNECTORS),
            doc="connector preset: the canonical cantilever hook, two hooks facing each other on a "
            "base block (two_hook_clip), a lid with four hooks pressed onto a box (box_lid), a "
            "cable plug's latch (cable_latch), or a tube with an inward lip snapped over a bead (annular)",
        ),
    },
    "part": {
        "mesh": Key(
            str,
            doc="the deformable part, instead of [connector]: tetrahedra in any meshio format, or a closed "
            "surface (STL/OBJ/PLY) tet-meshed at solver.mesh_size; relative to the scene file",
        ),
        "units": _UNITS,
        "fixed": Key(
            str, None, doc="fixed region: a named group of the file (point set, cell set, mask, physical group)"
        ),
        "fixed_box": Key(
            list,
            None,
            "mm",
            doc="fixed region: the nodes inside this box are fixed",
            shape="[[x0, y0, z0], [x1, y1, z1]]",
        ),
    },
    "rigid": {
        "mesh": Key(
            str,
            doc="the rigid part, instead of the preset plug: a closed surface (STL/OBJ/PLY), its coordinates "
            "its pose at t = 0 in the frame of the fixed base (placed by rigid.rotation and rigid.position); "
            "relative to the scene file",
        ),
        "units": _UNITS,
        "position": Key(
            list,
            [0.0, 0.0, 0.0],
            "mm",
            doc="the rigid part's start position: a translation of the file's coordinates (after "
            "rigid.rotation) in the frame of the fixed base; its frame's origin, the volume centroid at "
            "t = 0, is the file's centroid plus this",
            shape="[x, y, z]",
        ),
        "rotation": Key(
            list,
            [1.0, 0.0, 0.0, 0.0],
            "",
            doc="the rigid part's start orientation: a unit quaternion (w, x, y, z) that turns the file's "
            "coordinates about their volume centroid (before rigid.position). Normalised when its length "
            "is 1 within 1e-6 (as the waypoints' rotations), refused when farther off or zero. The motion's "
            "rotations turn the part from this pose",
            shape="[w, x, y, z]",
        ),
    },
    "material": {
        "youngs_modulus": _pos("MPa", doc="E, Young's modulus"),
        "poissons_ratio": Key(float, REQUIRED, "", -1.0, 0.5, True, True, doc="nu, Poisson's ratio"),
        "density": _pos("t/mm^3", doc="rho, density (ABS: 1.05e-9)"),
        "rayleigh_alpha": _nonneg("1/s", 0.0, "mass-proportional Rayleigh damping"),
        "rayleigh_beta": _nonneg("s", 0.0, "stiffness-proportional Rayleigh damping"),
    },
    "contact": {
        # Snap-fit design guides list dry Coulomb friction of 0.1-0.7 for plastics on steel and up
        # to about twice that for a plastic on itself; above 2 the tangential force would be twice
        # the normal force, which no such pair gives (a percentage or an angle given by mistake).
        "friction": Key(
            float, 0.3, "", 0.0, _MAX_FRICTION, doc="Coulomb friction coefficient between the parts"
        ),
        "capacity": Key(
            int,
            64,
            "",
            1,
            doc="contact buffer slots: the most points in contact in one step (at most the number of "
            "candidate points is used); left at its default, jsnap simulate runs a rollout that dropped "
            "candidates again with a buffer that holds them",
        ),
        "stabilisation": Key(
            float,
            0.0,
            "",
            0.0,
            1.0,
            doc="fraction of a point's penetration into the rigid part removed per step. 0: the contact "
            "holds velocities only, which is passive; where contact slides around the rigid part's rounded "
            "edge for many steps (the annular lip) the linearised gap drifts inward, and a fraction of it "
            "removed per step stops the drift; 0.1 pushes out a point the contact lost deep inside the rigid "
            "part (flagged DEEP_PENETRATION); pushing points out does work, which the "
            "rollout's energy check flags where it is too much",
        ),
        "width_spacing": _pos("mm", 1.0, "spacing of the contact candidate lines across the connector's width"),
        "solver": Key(
            str,
            "apgd",
            choices=("apgd", "spg"),
            internal_choices=("admm", "pgs"),
            doc="cone-complementarity solver: accelerated projected gradient (robust) or spectral "
            "projected gradient (fewer iterations, faster)",
        ),
        "iterations": Key(int, 500, "", 1, doc="iteration cap per contact solve"),
        "tolerance": _pos("", 1e-6, "normalised KKT residual the contact solve stops at"),
        "spacing": _pos(
            "mm",
            0.02,
            "spacing of the contact candidate points along each line (across the contact line); "
            "coarser is faster and rougher: each point is one more collision query and one more "
            "nearly dependent row for the solver (docs/contact.md)",
        ),
        "margin": _nonneg("mm", 0.02, "distance below which a point is a contact candidate", internal=True),
        "compliance": _nonneg("mm/N", 0.0, "contact regularisation per point", internal=True),
        "sampling": Key(
            str,
            "auto",
            choices=("auto", "surface"),
            internal=True,
            doc="contact candidates: the canonical cantilever's own (its section outline) or the general "
            "surface sampling (every other part's)",
        ),
        "gradient": Key(
            str,
            "implicit",
            choices=("implicit", "unrolled"),
            internal=True,
            doc="how jax.grad goes through the contact solve",
        ),
        "hand_over": Key(
            str,
            "auto",
            choices=("auto", "on", "off"),
            internal=True,
            doc="face points beside an edge that the rigid part presses leave their contact to the edge: "
            "with the general surface sampling (auto), always or never",
        ),
    },
    "plug": {
        "fillet": _nonneg("mm", 0.1, "edge radius of the preset rigid part (a rounded block)"),
        "thickness": _pos("mm", None, "x extent; default 1.25 undercut"),
        "width": _pos("mm", None, "y extent; default connector width + 1 mm × wall ratio"),
        "height": _pos("mm", 0.5, "z extent"),
        "clearance": _nonneg("mm", 0.02, "start gap above the hook's top", internal=True),
    },
    "motion": {
        "direction": Key(
            list,
            None,
            "",
            doc="straight insertion direction (normalised); default [0, 0, -1]",
            shape="[x, y, z]",
        ),
        "speed": _pos("mm/s", 10.0, "insertion speed along motion.direction"),
        "stroke": _pos(
            "mm",
            None,
            "travel; default (preset plug): the rigid part latches 0.3 mm × wall ratio below the hook",
        ),
        "withdraw": Key(bool, False, doc="return to the start after the stroke"),
        "waypoints": Key(
            list,
            None,
            "s, mm",
            doc="instead of a straight insertion: poses { t, position (relative to the start), rotation "
            "(unit quaternion w, x, y, z about the rigid part's centroid) }, interpolated linearly and by "
            "slerp",
            shape="[{ t = 0.0, position = [0, 0, 0], rotation = [1, 0, 0, 0] }, ...]",
        ),
        "trajectory": Key(
            str,
            None,
            doc="instead of a straight insertion: a CSV file of poses t, x, y, z, qw, qx, qy, qz "
            "(as waypoints)",
        ),
        "control": Key(
            str,
            "position",
            choices=("position", "impedance"),
            doc="the rigid part follows its path exactly (position) or through a virtual spring-damper "
            "(impedance, the haptic case)",
        ),
        "coupling_stiffness": _pos("N/mm", 200.0, "virtual coupling stiffness (impedance control)"),
        "coupling_damping": _nonneg("N s/mm", 2.0, "virtual coupling damping (impedance control)"),
        "plug_mass": _pos("t", 1e-5, "the rigid part's mass (impedance control)"),
    },
    "solver": {
        "dt": _pos("s", 1e-3, "time step"),
        "method": Key(
            str,
            "reduced",
            choices=("reduced", "full", "segmented"),
            internal_choices=("modal",),
            doc="the deformable part's model: passive balanced reduction (real time), the full FEM "
            "reference, or the segmented full model (the paper's Model 3)",
        ),
        "element": Key(
            str, "P2", choices=("P2", "P1"), doc="quadratic or linear tetrahedra (P1 locks in bending)"
        ),
        "mesh_size": _pos("mm", 0.8, "element size"),
        "sdf": Key(
            str,
            None,
            choices=("analytic", "mesh", "neural"),
            doc="the rigid part's signed distance: exact formula (preset plug), exact triangle mesh, or "
            "trained "
            "network; default analytic for the preset plug, mesh for a [rigid] file",
        ),
        "dtype": Key(
            str,
            None,
            choices=("float32", "float64"),
            doc="rollout precision; default float32 for the reduced model (its float32 peak force is "
            "within 1 % of float64's) and float64 for the full and segmented ones (more than 1 % off: "
            "benchmarks/precision.py)",
        ),
        "hsv_tolerance": Key(
            float,
            1e-2,
            "",
            0.0,
            1.0,
            True,
            True,
            doc=(
                "reduced: keep Hankel singular values above this fraction of the whole part's, and every "
                "contact load's static compliance to within it"
            ),
        ),
        "subspace_modes": Key(
            int, 30, "", 1, internal=True, doc="reduced: lowest modes per segment balanced over"
        ),
        "segment_margin": _nonneg("mm", 1.0, "contact segment grown by this", internal=True),
        "load_patch": _nonneg(
            "mm",
            0.0,
            "reduced: the contact load cases spread over a Gaussian patch of this standard deviation "
            "(0: each candidate point's own); a patch keeps the contact segment's order from growing "
            "with the mesh, at some cost after snaps (docs/reduction.md)",
        ),
        "segments": Key(int, 1, "", 1, internal=True, doc="number of non-contact segments"),
        "interface_stiffness": _pos("N/mm", 1e6, "segmented: k_c joining the segments' copies", internal=True),
        "interface_damping": _nonneg("N s/mm", None, "segmented: b_c; default k_c dt / 2", internal=True),
    },
}

# Beyond this contact.friction warns: above what the design guides list for any plastic pair.
_HIGH_FRICTION = 1.5
# What to do when a key is out of its range, where the range alone does not say it.
_RANGE_HINTS = {
    "contact.friction": "dry Coulomb friction of plastics is 0.1-0.7 on steel and up to about twice that "
    "on themselves; give the coefficient itself (0.3, not 30 %, not an angle)",
}
# The rigid part may move at most this many contact resolutions (the larger of contact.spacing
# and contact.margin) per step unwarned. A point is a contact candidate within the margin of the
# rigid part, and candidates lie a spacing apart: a part that moves farther in one step reaches
# points the step's contact did not hold, which the predict-correct pass catches a step late, so
# the force wanders. The default scene's peak force (reduced, float32; 5.103 N at 0.5 resolutions
# per step, dt 1 ms): -0.7 % at 1 (dt 2 ms), +3.7 % at 1.5, +2.1 % at 2, +9.8 % at 5 (dt 10 ms).
_MAX_STEP_TRAVEL = 1.0
# A motion shorter than this many steps is refused: the contact events of a snap (ramp, flat,
# release) each need several steps to be resolved at all.
MIN_STEPS = 20
# Elements more than this many times the thinnest feature leave it unresolved altogether.
_COARSEST = 4.0
# The annular lip's hoop strain (undercut / bore radius) beyond which a linear model is
# meaningless (design guides allow a few percent).
_MAX_HOOP_STRAIN = 0.1
# The annular sector's facets stand inside the ring by their sagitta: at most this fraction of
# the undercut (2 % changes the radial force by as much).
_MAX_SAGITTA = 0.02
# Tip deflection over arm length beyond which a linear (small-rotation) model is meaningless:
# the tip would turn by ~1.5 y_u / L rad (0.375 rad, 21 degrees).
_MAX_DEFLECTION_RATIO = 0.25


def _coerce(name: str, spec: Key, value: Any, internal: bool) -> Any:
    """Check type, finiteness, choices and range of one value; return it normalised."""
    if value is None and spec.default is None:
        return None
    if spec.kind is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise SceneError(f"{name} = {value!r}: must be a number")
        value = float(value)
        if not math.isfinite(value):
            raise SceneError(f"{name} = {value!r}: must be finite")
    elif spec.kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise SceneError(f"{name} = {value!r}: must be an integer")
    elif spec.kind is bool:
        if not isinstance(value, bool):
            raise SceneError(f"{name} = {value!r}: must be true or false")
    elif spec.kind is str and not isinstance(value, str):
        raise SceneError(f"{name} = {value!r}: must be a string")
    elif spec.kind is list:
        return _PARSERS[name](name, value)
    if spec.choices is not None:
        allowed = spec.choices + (spec.internal_choices if internal else ())
        if value not in allowed:
            raise SceneError(f"{name} = {value!r}: must be one of {', '.join(spec.choices)}")
    if spec.kind in (float, int):
        problem = spec.check(value)
        if problem:
            hint = f": {_RANGE_HINTS[name]}" if name in _RANGE_HINTS else ""
            raise SceneError(f"{name} = {value!r}: {problem}{hint}")
    return value


@dataclass(frozen=True)
class Scene:
    """A validated scene: ``scene["material"]["youngs_modulus"]`` or ``scene.get(...)``.

    Attributes:
        sections: read-only mapping ``section -> key -> value`` with every default filled in.
        source: where the scene came from (a path, or ``"<dict>"``).
        given: the ``"section.key"`` names that the file (or mapping) and later ``replace``
            calls set, as against the defaults filled in (see :meth:`is_set`).
        size: the part's size, which scales the contact's resolution defaults (the keys of
            ``jsnap._geometry.size.SIZED`` not given are their value there times it); it follows
            the wall ratio (a preset's ``connector.thickness`` over the shipped preset's, a part
            file's wall over the shipped hook's 1.2 mm), which scales the geometric defaults
            (``GEOMETRIC``) itself (``jsnap._geometry.size``).
    """

    sections: Mapping[str, Mapping[str, Any]]
    source: str = field(default="<dict>", compare=False)
    given: frozenset[str] = field(default=frozenset(), compare=False)
    size: float = 1.0

    def __getitem__(self, section: str) -> Mapping[str, Any]:
        return self.sections[section]

    def get(self, dotted: str) -> Any:
        """Value of ``"section.key"``."""
        section, key = _split(dotted)
        return self.sections[section][key]

    def is_set(self, dotted: str) -> bool:
        """Whether ``"section.key"`` was given (by the scene's file or mapping, or by
        :meth:`replace`) rather than left at its default; an application may size what the user
        left to it (``jsnap simulate`` widens a default contact buffer that overflowed)."""
        _split(dotted)
        return dotted in self.given

    def replace(self, changes: Mapping[str, Any] | None = None, **kw: Any) -> Scene:
        """A new, re-validated scene with ``{"section.key": value}`` changes applied.

        Keyword form: ``scene.replace(solver__mesh_size=0.3)``.
        """
        return self._replace(changes, kw, internal=False)

    def _replace(self, changes, kw, internal: bool) -> Scene:
        changes = dict(changes or {})
        changes.update({k.replace("__", "."): v for k, v in kw.items()})
        raw = {s: dict(v) for s, v in self.sections.items()}
        for dotted, value in changes.items():
            section, key = _split(dotted)
            if section not in raw:
                raise SceneError(f"unknown section [{section}] in {dotted!r}")
            raw[section][key] = value
        return Scene._validate(raw, self.source, internal=internal, given=set(changes), before=self.given)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """Plain nested dict (defaults included), e.g. for JSON summaries."""
        return {s: dict(v) for s, v in self.sections.items()}

    @classmethod
    def from_dict(cls, raw: Mapping[str, Any], source: str = "<dict>") -> Scene:
        """Validate a nested mapping (as parsed from TOML) into a :class:`Scene`."""
        return cls._validate(raw, source, internal=False, given=None)

    @classmethod
    def _validate(cls, raw, source, *, internal: bool, given, before: frozenset[str] = frozenset()) -> Scene:
        """``given``: the dotted keys set by the caller (None: every key present in ``raw``);
        internal keys among them are refused unless ``internal``. ``before``: the keys an
        earlier scene had set, kept in the new one's ``given``."""
        if not isinstance(raw, Mapping):
            raise SceneError(f"a scene must be a table of sections, got {type(raw).__name__}")
        for section in raw:
            if section not in SCHEMA:
                raise SceneError(f"unknown section [{section}]; expected one of {', '.join(SCHEMA)}")
        sections: dict[str, Mapping[str, Any]] = {}
        absent = _absent_sections(raw)
        for section, keys in SCHEMA.items():
            if section in absent:
                sections[section] = MappingProxyType({})
                continue
            supplied = raw.get(section, {})
            if not isinstance(supplied, Mapping):
                raise SceneError(f"[{section}] must be a table, got {supplied!r}")
            if section == "connector":
                keys = _connector_keys(supplied, internal or not (given is None or "connector.type" in given))
            visible = [k for k, spec in keys.items() if not spec.internal]
            for key in supplied:
                spec = keys.get(key)
                set_here = given is None or f"{section}.{key}" in given
                if spec is None or (spec.internal and set_here and not internal):
                    raise SceneError(
                        f"unknown key {section}.{key} = {supplied[key]!r}; "
                        f"[{section}] takes {', '.join(visible)}"
                    )
            values = {}
            for key, spec in keys.items():
                name = f"{section}.{key}"
                set_here = given is None or name in given
                if key in supplied:
                    values[key] = _coerce(name, spec, supplied[key], internal or not set_here)
                elif spec.default is REQUIRED:
                    raise SceneError(f"{name} is required but missing ({spec.doc})")
                else:  # a list default copied: no scene shares it
                    values[key] = list(spec.default) if isinstance(spec.default, list) else spec.default
            sections[section] = MappingProxyType(values)
        if given is None:
            given = {f"{s}.{k}" for s, table in raw.items() if isinstance(table, Mapping) for k in table}
        given = frozenset(before | set(given))
        scene = cls(MappingProxyType(sections), source, given)
        _check_files(scene)
        scene = _sized(scene)
        _check_consistency(scene)
        _check_part_elements(scene)
        return scene


def _sized(scene: Scene) -> Scene:
    """``scene`` with its size, and the keys of ``GEOMETRIC`` and ``SIZED`` it did not give at
    its wall ratio and its size (``jsnap._geometry.size``)."""
    c = scene["connector"]
    if c:
        ratio = preset_ratio(c)
    else:
        try:
            ratio = part_wall_thickness(scene_file(scene, "part.mesh"), scene["part"]["units"]) / REFERENCE_WALL
        except PartError:
            ratio = 1.0  # a file that cannot be used: jsnap.build says why
    size = size_of(ratio)
    sections = {k: dict(v) for k, v in scene.sections.items()}
    for table, scale in ((GEOMETRIC, ratio), (SIZED, size)):
        for dotted, value in table.items():
            section, key = _split(dotted)
            if key in sections[section] and not scene.is_set(dotted):
                sections[section][key] = value * scale
    frozen = MappingProxyType({k: MappingProxyType(v) for k, v in sections.items()})
    return Scene(frozen, scene.source, scene.given, size)


def similar_scene(scene: Scene, k: float, changes: Mapping[str, Any] | None = None) -> Scene:
    """The dynamically similar scene: every length ``scene`` gives (a key in mm) times ``k``,
    every time (in s) times ``k`` and every rate (in 1/s) over it, then ``changes``. Its masses
    go as ``k^3``, accelerations as ``1/k`` and stiffnesses as ``k``: every force is ``k^2``
    times the original's, step for step, if nothing in jsnap hides a length. A preset's scene
    only (a part file's coordinates and waypoints are not scaled)."""
    if not scene["connector"] or scene["motion"]["waypoints"] is not None or scene["motion"]["trajectory"]:
        raise ValueError("similar_scene scales a preset's scene with a straight motion only")
    out = {}
    for dotted in scene.given:
        section, key = _split(dotted)
        table = CONNECTORS[scene["connector"]["type"]] if section == "connector" else SCHEMA[section]
        spec, value = table.get(key), scene.get(dotted)
        factor = {"mm": k, "s": k, "1/s": 1 / k}.get(spec.unit if spec else None)
        if factor is not None and isinstance(value, float):
            out[dotted] = value * factor
    return scene.replace({**out, **(changes or {})})


def _connector_keys(supplied: Mapping[str, Any], internal: bool) -> dict[str, Key]:
    """The keys of the [connector] table of the type it names."""
    spec = SCHEMA["connector"]["type"]
    if "type" not in supplied:
        raise SceneError(f"connector.type is required but missing ({spec.doc})")
    kind = _coerce("connector.type", spec, supplied["type"], internal)
    return {"type": spec, **CONNECTORS[kind]}


# Sections that may be left out: the user's parts replace the presets.
_OPTIONAL = ("part", "rigid")


def _absent_sections(raw: Mapping[str, Any]) -> set[str]:
    """The sections this scene leaves out: [part] and [rigid] unless given; [connector] when
    [part] is given and [plug] when [rigid] is (and then they must not be)."""
    absent = {s for s in _OPTIONAL if not raw.get(s)}
    if "part" not in absent:
        if raw.get("connector"):
            raise SceneError("[part] and [connector] both given: the deformable part is one or the other")
        absent.add("connector")
        if "rigid" in absent:
            raise SceneError("[part] needs [rigid]: the preset plug is sized from a [connector]")
    if "rigid" not in absent:
        if raw.get("plug"):
            raise SceneError("[rigid] and [plug] both given: the rigid part is one or the other")
        absent.add("plug")
    return absent


def with_internal(scene: Scene, changes: Mapping[str, Any]) -> Scene:
    """``scene.replace(changes)`` that may also set internal keys and choices (for tests and
    benchmarks: the solvers, models and settings that are not offered to users)."""
    return scene._replace(changes, {}, internal=True)


def _split(dotted: str) -> tuple[str, str]:
    parts = dotted.split(".")
    if len(parts) != 2:
        raise SceneError(f"expected 'section.key', got {dotted!r}")
    return parts[0], parts[1]


def connector_geometry(scene: Scene) -> Cantilever:
    """The hook section of the scene's connector preset (the cantilever's arm, the clip's arms,
    the annular snap's wall and lip) as a :class:`jsnap._geometry.cantilever.Cantilever`
    (validated)."""
    return hook_of(scene["connector"])


def motion_stroke(scene: Scene) -> float:
    """The stroke of the scene's straight motion, mm (``motion.stroke`` or, for the preset plug,
    the latching default)."""
    stroke = scene["motion"]["stroke"]
    if stroke is not None:
        return stroke
    p, c = scene["plug"], scene["connector"]
    return default_stroke(c["type"], c, p, default_rigid(c["type"], c, p))


def sdf_kind(scene: Scene) -> str:
    """``solver.sdf``, or its default: analytic for the preset plug, mesh for a [rigid] file."""
    return scene["solver"]["sdf"] or ("mesh" if scene["rigid"] else "analytic")


def scene_file(scene: Scene, dotted: str) -> Path:
    """The file a scene key names, relative to the scene file's folder (absolute paths as they
    are; scenes made in Python: relative to the working directory)."""
    path = Path(scene.get(dotted)).expanduser()
    if not path.is_absolute() and scene.source not in ("<dict>", ""):
        path = Path(scene.source).parent / path
    return path


def motion_keyposes(scene: Scene):
    """``(t, position, rotation)`` of a waypoint or CSV motion, or None for a straight one."""
    m = scene["motion"]
    if m["waypoints"] is not None:
        w = m["waypoints"]
        return tuple(np.array([p[k] for p in w], np.float64) for k in ("t", "position", "rotation"))
    if m["trajectory"] is not None:
        return read_pose_csv(scene_file(scene, "motion.trajectory"))
    return None


def motion_duration(scene: Scene) -> tuple[float, str]:
    """The motion's duration, s, and how it was set (for messages)."""
    m = scene["motion"]
    keys = motion_keyposes(scene)
    if keys is not None:
        return float(keys[0][-1]), f"its last pose at t = {keys[0][-1]:g} s"
    stroke = motion_stroke(scene)
    duration = stroke / m["speed"] * (2 if m["withdraw"] else 1)
    return duration, f"{stroke:g} mm at {m['speed']:g} mm/s, {duration:g} s"


def _check_files(scene: Scene) -> None:
    """The motion's keys fit together; the files a scene names exist."""
    m = scene["motion"]
    given = [k for k in ("waypoints", "trajectory") if m[k] is not None]
    if len(given) > 1:
        raise SceneError("motion.waypoints and motion.trajectory both given: the motion is one or the other")
    if given:
        straight = [k for k in ("direction", "stroke") if m[k] is not None] + (
            ["withdraw"] if m["withdraw"] else []
        )
        if straight:
            raise SceneError(
                f"motion.{straight[0]} is for a straight insertion, but motion.{given[0]} is given: "
                "the motion is one or the other"
            )
    rigid, part = scene["rigid"], scene["part"]
    sdf = scene["solver"]["sdf"]
    if rigid and sdf == "analytic":
        raise SceneError(
            "solver.sdf = 'analytic' is the preset plug's formula; a [rigid] file needs 'mesh' or 'neural'"
        )
    if rigid and not given and m["stroke"] is None:
        raise SceneError(
            "motion.stroke is required with a [rigid] file (the latching default is the preset plug's)"
        )
    if part and (part["fixed"] is None) == (part["fixed_box"] is None):
        raise SceneError("[part] needs exactly one of part.fixed (a group in the file) and part.fixed_box")
    for dotted in ("part.mesh", "rigid.mesh", "motion.trajectory"):
        section, key = _split(dotted)
        if scene[section] and scene[section][key] is not None:
            path = scene_file(scene, dotted)
            if not path.is_file():
                raise SceneError(f"{dotted} = {scene[section][key]!r}: no such file ({path})")


def _check_annular(scene: Scene) -> None:
    """The annular snap's own rules: a hoop strain a linear model can carry; a sector of the
    ring only under the motion its symmetry holds for (its preset bead straight down the axis)."""
    c, m = scene["connector"], scene["motion"]
    if c["undercut"] > _MAX_HOOP_STRAIN * c["radius"]:
        raise SceneError(
            f"connector.undercut = {c['undercut']!r}: the lip must stretch to the bore's radius "
            f"{c['radius']:g} mm, a hoop strain of {100 * c['undercut'] / c['radius']:.0f} % (more than "
            f"{100 * _MAX_HOOP_STRAIN:g} %), far beyond jsnap's linear model and any plastic snap-fit; use a "
            "smaller undercut"
        )
    for key in ("thickness", "width"):
        if scene["plug"] and scene["plug"][key] is not None:
            raise SceneError(
                f"plug.{key} = {scene['plug'][key]!r}: the annular preset's rigid part is a bead of the bore's "
                "radius (connector.radius); plug.thickness and plug.width size the other presets' block"
            )
    sagitta = c["radius"] * (1 - math.cos(math.radians(0.5 * c["sector"])))
    if sagitta > _MAX_SAGITTA * c["undercut"]:
        widest = 2 * math.degrees(math.acos(1 - _MAX_SAGITTA * c["undercut"] / c["radius"]))
        raise SceneError(
            f"connector.sector = {c['sector']!r}: the sector's facets, chords of the ring, would stand "
            f"{1e3 * sagitta:.2g} um inside it, {100 * sagitta / c['undercut']:.2g} % of connector.undercut "
            f"(the force follows the undercut); use connector.sector <= {widest:.3g} degrees"
        )
    axial = m["direction"] is None or np.allclose(
        np.asarray(m["direction"]) / np.linalg.norm(m["direction"]), [0, 0, -1]
    )
    moved = [k for k in ("waypoints", "trajectory") if m[k] is not None]
    if scene["rigid"] or moved or not axial:
        what = "a [rigid] file" if scene["rigid"] else f"motion.{moved[0]}" if moved else "motion.direction"
        raise SceneError(
            f"connector.sector = {c['sector']!r}: a sector of the ring is exact only for the preset bead "
            f"pushed straight down the axis, and {what} breaks that symmetry (jsnap does not model the whole "
            "ring)"
        )


@functools.lru_cache(maxsize=32)
def _rigid_file_radius(path: str, size: int, mtime_ns: int, units: str) -> float:
    """The largest distance of a [rigid] file's surface from its centroid, mm (0: unreadable,
    the build says why)."""
    from jsnap._geometry.part import load_rigid

    try:
        return float(np.linalg.norm(load_rigid(path, units=units).half))
    except PartError:
        return 0.0


def _rigid_radius(scene: Scene) -> float:
    """How far the rigid part's surface reaches from the centre its rotations turn about, mm."""
    if not scene["rigid"]:
        c, p = scene["connector"], scene["plug"]
        return float(np.linalg.norm(default_rigid(c["type"], c, p).half))
    path = scene_file(scene, "rigid.mesh")
    stat = path.stat()
    return _rigid_file_radius(str(path.resolve()), stat.st_size, stat.st_mtime_ns, scene["rigid"]["units"])


def _part_wall(scene: Scene) -> tuple[float, str] | None:
    """The deformable part's wall, mm, and where it comes from (None: a file that cannot be read)."""
    c = scene["connector"]
    if c:
        if c.get("tip_thickness") is not None and c["tip_thickness"] < c["thickness"]:
            return float(c["tip_thickness"]), f"connector.tip_thickness = {c['tip_thickness']:g} mm"
        return float(c["thickness"]), f"connector.thickness = {c['thickness']:g} mm"
    try:
        wall = part_wall_thickness(scene_file(scene, "part.mesh"), scene["part"]["units"])
    except PartError:
        return None
    return wall, f"{wall:.3g} mm, measured on part.mesh"


def _round_down(x: float) -> float:
    """``x`` rounded down to two significant digits (a limit that still holds once rounded)."""
    unit = 10.0 ** (math.floor(math.log10(x)) - 1)
    return math.floor(x / unit * (1 + 1e-9)) * unit


def _check_step_travel(scene: Scene) -> None:
    """The rigid part's travel in one step (the farthest any point of it moves: its centre's
    displacement plus its turn times its radius) against the part's wall (an error: it would
    pass through the wall between two contact checks) and the contact's resolution (a warning,
    naming the time step that resolves it)."""
    s, m, ct = scene["solver"], scene["motion"], scene["contact"]
    dt = s["dt"]
    keys = motion_keyposes(scene)
    if keys is None:
        travel, at = m["speed"] * dt, 0
        what, times = f"motion.speed = {m['speed']:g} mm/s", None
    else:
        from jsnap._geometry.motion import sample_poses

        poses = sample_poses(*keys, np.zeros(3), dt)
        dq = np.abs(np.sum(poses[1:, 3:] * poses[:-1, 3:], axis=1))
        turn = 2.0 * np.arccos(np.clip(dq, -1.0, 1.0))
        steps = np.linalg.norm(np.diff(poses[:, :3], axis=0), axis=1)
        if np.any(turn > 0):
            steps = steps + turn * _rigid_radius(scene)
        at = int(np.argmax(steps))
        travel = float(steps[at])
        key = "motion.waypoints" if m["waypoints"] is not None else f"motion.trajectory = {m['trajectory']!r}"
        what, times = key, (at * dt, (at + 1) * dt)
    when = f" between t = {times[0]:.6g} and {times[1]:.6g} s" if times else ""
    wall = _part_wall(scene)
    resolution = max(ct["spacing"], ct["margin"])
    if wall is not None and travel > wall[0]:
        n = math.ceil(travel / (_MAX_STEP_TRAVEL * resolution))
        raise SceneError(
            f"{what}: the rigid part moves {travel:.4g} mm in one step of solver.dt = {dt:g} s{when}, more "
            f"than the part's wall ({wall[1]}): it would pass through the part between two contact checks; "
            f"give that move at least {n} steps ({n * dt:.3g} s at this solver.dt: a step per {resolution:g} "
            "mm, the contact's resolution), or check the motion's times and units"
        )
    if travel > _MAX_STEP_TRAVEL * resolution * (1 + 1e-9):  # equal but for rounding is not larger
        fine = dt * _MAX_STEP_TRAVEL * resolution / travel
        warnings.warn(
            f"solver.dt = {dt!r}: the rigid part moves {travel:.3g} mm per step ({what}{when}), "
            f"{travel / resolution:.3g} times the contact's resolution ({resolution:g} mm, the larger of "
            "contact.spacing and contact.margin): contact is found a step late and the force is off (the "
            f"default scene's peak by +9.8 % at solver.dt = 0.01); use solver.dt <= {_round_down(fine):g} s",
            SceneWarning,
            stacklevel=5,
        )


def _check_consistency(scene: Scene) -> None:
    """Checks that involve several keys: geometry that cannot be built or cannot be modelled,
    plug sizes, a motion too short for the time step, elements too coarse for the features."""
    c = scene["connector"]
    if c:
        try:
            features = connector_features(c["type"], c)  # the hook section's checks (hook_of) first
        except ValueError as err:
            raise SceneError(str(err)) from None
        if c["type"] == "annular":
            _check_annular(scene)
        elif c["undercut"] > _MAX_DEFLECTION_RATIO * c["length"]:
            raise SceneError(
                f"connector.undercut = {c['undercut']!r}: the arm must bend its tip {c['undercut']:g} mm on a "
                f"{c['length']:g} mm length (more than {_MAX_DEFLECTION_RATIO:g} of it): the tip would turn by "
                f"~{math.degrees(1.5 * c['undercut'] / c['length']):.0f} degrees, far beyond the small strains "
                "and rotations of jsnap's linear model and of any plastic snap-fit; use a longer arm or a "
                "smaller undercut"
            )
    if not scene["rigid"]:
        p = scene["plug"]
        rigid = default_rigid(c["type"], c, p)
        half = float(np.min(rigid.half))
        if p["fillet"] > half:
            raise SceneError(
                f"plug.fillet = {p['fillet']!r}: must be <= half the plug's smallest side ({half:g} mm)"
            )
    ct = scene["contact"]
    if ct["solver"] == "spg" and ct["gradient"] == "unrolled":
        raise SceneError(
            "contact.gradient = 'unrolled' with contact.solver = 'spg': SPG's spectral steps reach "
            "past 2/||W||, so the unrolled iteration's derivative does not settle on the solution's"
        )
    s = scene["solver"]
    duration, how = motion_duration(scene)
    steps = duration / s["dt"]
    if steps < MIN_STEPS:
        raise SceneError(
            f"solver.dt = {s['dt']!r}: the motion ({how}) would take {steps:.3g} steps; at least "
            f"{MIN_STEPS} are needed to resolve the contact: use solver.dt <= {duration / MIN_STEPS:.3g} s"
        )
    if ct["friction"] > _HIGH_FRICTION:
        warnings.warn(
            f"contact.friction = {ct['friction']!r} is above {_HIGH_FRICTION:g}, beyond the dry friction of "
            "plastics (0.1-0.7 on steel, up to about twice that on themselves): the parts would stick where "
            "a snap-fit slides; check the value",
            SceneWarning,
            stacklevel=4,
        )
    _check_step_travel(scene)
    if not c:
        return
    name, thinnest = min(features.items(), key=lambda kv: kv[1])
    if s["mesh_size"] > _COARSEST * thinnest:
        raise SceneError(
            f"solver.mesh_size = {s['mesh_size']!r}: elements more than {_COARSEST:g} times connector.{name} "
            f"= {thinnest:g} mm, the thinnest feature, leave it unresolved; use solver.mesh_size <= "
            f"{thinnest:g} mm"
        )
    if s["mesh_size"] > thinnest * (1 + 1e-9):  # equal but for rounding is not larger
        warnings.warn(
            f"solver.mesh_size = {s['mesh_size']!r} is larger than connector.{name} = {thinnest:g} mm, the "
            "thinnest feature: fewer than one element across it (a coarse, stiff model)",
            SceneWarning,
            stacklevel=4,
        )


def _check_part_elements(scene: Scene) -> None:
    """A part from a file: warn when the element size, given or derived, puts fewer than
    ``MIN_ELEMENTS_ACROSS`` elements across its thinnest wall (the wall the default follows)."""
    if not scene["part"]:
        return
    try:
        wall, where = part_thinnest_wall(scene_file(scene, "part.mesh"), scene["part"]["units"])
    except PartError:
        return  # a file that cannot be used: jsnap.build says why
    s = scene["solver"]
    need = MIN_ELEMENTS_ACROSS[s["element"]]
    across = elements_across(wall, s["mesh_size"])
    if across < need:
        how = "" if scene.is_set("solver.mesh_size") else " (its default)"
        at = ", ".join(f"{x:.3g}" for x in where)
        warnings.warn(
            f"solver.mesh_size = {s['mesh_size']:.4g}{how} spans the thinnest wall of part.mesh "
            f"({wall:.3g} mm, measured from ({at}) mm) with {across} element(s), fewer than {need} for "
            f"{s['element']} elements: a coarse, stiff model of the walls that bend; use solver.mesh_size <= "
            f"{wall / (need - 0.5):.3g}",
            SceneWarning,
            stacklevel=4,
        )


def load_scene(path: str | Path | None = None) -> Scene:
    """Load and validate a scene TOML file (``None``: the shipped default scene).

    Raises:
        SceneError: unknown or missing keys, wrong types, impossible values (naming the key).
        FileNotFoundError: the file does not exist.
    """
    if path is None:
        path = default_scene_path()
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise FileNotFoundError(f"scene file not found: {path}") from None
    except (IsADirectoryError, PermissionError, UnicodeDecodeError) as err:
        raise SceneError(f"{path}: cannot read the scene file ({type(err).__name__})") from None
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise SceneError(f"{path}: not valid TOML: {err}") from None
    try:
        return Scene.from_dict(raw, source=str(path))
    except SceneError as err:
        raise SceneError(f"{path}: {err}") from None


def default_scene_path() -> Path:
    """Path of the shipped default scene (the reference hook of the CalculiX comparison)."""
    return Path(str(resources.files("jsnap") / "scenes" / "default.toml"))
