"""The scene-file reference (``docs/scene-reference.md``), generated from the scene schema.

Every scene key is declared once, in :data:`jsnap._geometry.scene.SCHEMA`; :func:`render` turns
its user-visible keys (not the internal ones, nor the internal choices) into Markdown: an
introduction (format, units, errors, the rules that involve several keys) and one table per
section. The documentation's page is this function's output, committed, and a test checks that
it is up to date::

    python -m jsnap._apps.scene_reference > docs/scene-reference.md
"""

from __future__ import annotations

import math
import tomllib

from jsnap._geometry import scene as _scene
from jsnap._geometry.scene import CONNECTORS, REQUIRED, SCHEMA, Key, default_scene_path
from jsnap._geometry.size import (
    BAND,
    GEOMETRIC,
    MIN_ELEMENTS_ACROSS,
    REFERENCE_THICKNESS,
    REFERENCE_WALL,
    SIZED,
    WALL_ANGLE,
)

__all__ = ["render"]

COMMAND = "python -m jsnap._apps.scene_reference > docs/scene-reference.md"

# What each section describes (the schema itself says what each key means).
_SECTIONS = {
    "connector": "The deformable part: a connector preset, chosen by `type`, each with its own keys "
    "(below). Every preset generates what a user could give in files (a tet mesh with its fixed "
    "region, a rigid part, a straight motion along -z); shipped scenes: `jsnap/scenes/<type>.toml` "
    "(`default.toml` for the cantilever).",
    "part": "The deformable part from a file, instead of [connector] (see "
    "[your own connector](own-connector.md)): tetrahedra, or a closed surface that jsnap tet-meshes "
    "with gmsh at solver.mesh_size; its fixed region a named group of the file or a box. Paths are "
    "relative to the scene file.",
    "rigid": "The rigid part from a file, instead of [plug]: a closed surface whose coordinates are "
    "its pose at t = 0 in the frame of the fixed base, or are placed there by `rigid.rotation` (about "
    "the file's volume centroid) and then `rigid.position`; its frame's origin is its volume centroid. "
    'Its signed distance is the exact mesh distance (solver.sdf = "mesh", the default here) or a '
    'network trained once and cached ("neural").',
    "material": "The deformable part's linear elastic material and its Rayleigh damping "
    "(D = rayleigh_alpha M + rayleigh_beta K).",
    "contact": "Frictional contact between the parts and its solver.",
    "plug": "The preset rigid part: a block with rounded edges, sized from the connector.",
    "motion": "How the rigid part moves: a straight insertion (along -z from just above the hook "
    "for the preset plug, or along motion.direction), or a path of poses (motion.waypoints or a "
    "motion.trajectory CSV file) that also turns it. The orientation follows the path under either "
    "control; impedance control couples the position.",
    "solver": "The numerical model: time step, the deformable part's model and elements, the "
    "rigid part's signed distance, precision.",
}

# What each connector preset is (its keys say what each dimension means).
_CONNECTORS = {
    "cantilever": "The canonical cantilever snap hook. Coordinates in mm: the arm spans x in "
    "[0, thickness] (x is the bending direction), y in [-width/2, width/2] and z from its fixed "
    "root face z = 0 to the retention face at z = length; the hook protrudes by the undercut in +x "
    "beyond the arm's outer face, and the rigid part (a block whose face lies in the plane of the "
    "arm's outer face at the tip) comes down along -z.",
    "two_hook_clip": "Two cantilevers of the section above, mirror images about x = 0, hooks "
    "pointing inwards, their inner faces `gap` apart, rising from z = 0 out of a base block "
    "`base_thickness` thick (its bottom face z = -base_thickness is fixed) that reaches "
    "`base_margin` beyond the arms' outer faces; arms and base are `width` wide. The rigid part is "
    "a block exactly `gap` wide pushed down between the hooks: both hooks are squeezed apart at "
    "once. Meshed with gmsh at `solver.mesh_size`, along the hooks' edges at the smaller of that "
    "and 2.5 undercuts.",
    "box_lid": "A lid with four snap hooks pressed onto a box (a switch box): a plate "
    "`lid_thickness` thick, z in [-lid_thickness, 0], whose outer face is fixed (the robot's flat "
    "platen holds it), and four arms of the clip's section standing on it, hooks pointing inwards: "
    "two pairs facing each other across the box, their inner faces `gap` apart (x), the two arms "
    "of a side `spacing` apart between their centres (y); the plate reaches `lid_margin` beyond "
    "the arms. The rigid part is the box's rim, a block `gap` wide and spacing + width + 1 deep, "
    "turned by `tilt` about the x axis and pushed straight down along -z: the hooks at -y engage "
    "first, those at +y spacing tan(tilt) mm of travel later; the default stroke latches all four. "
    "Meshed with gmsh like the clip (the plate and arms fused into one part).",
    "cable_latch": "The flexible latch of a cable plug (a LAN plug), on the plug: the latch arm "
    "spans x in [0, thickness] and z from its free end z = 0 up to its root z = length, where a "
    "bridge 2 thickness tall joins it over a `gap` to the plug body x in "
    "[-gap - body_thickness, -gap], z in [0, length + 2 thickness]; latch and body are `width` "
    "wide. The catch (the cantilever's hook section: undercut, lead and return angles, flat) stands "
    "on the arm's outer face, its retention face `catch_position` below the root. The body's back "
    "face x = -(gap + body_thickness) is fixed (the part the robot holds). The rigid part is the "
    "jack's lip, a block whose inner face lies in the plane of the arm's outer face, coming down "
    "along -z from above the catch: it pushes the catch in by the undercut, passes it, and the "
    "latch springs back behind it (the plug is moved into the jack; jsnap moves the jack relative "
    "to the plug). The latch's free end must not reach the body: `gap` must exceed its "
    "beam-theory swing. Meshed with gmsh like the clip, finer along the catch's edges.",
    "annular": "A tube with an inward lip at its mouth snapped over a rigid bead (a cap, a pen, a "
    "bottle closure): the wall r in [radius, radius + thickness] from its fixed end z = 0 up to "
    "its top, the lip (the cantilever's hook section turned about the z axis: undercut, lead and "
    "return angles, flat) reaching `undercut` into the bore, its retention face `length` above "
    "the fixed end. The rigid part is a bead, a cylinder of the bore's radius `plug.height` tall "
    "with its edges rounded by `plug.fillet`, pushed down the axis through the lip. jsnap models "
    "a `sector` of the ring one element wide whose two cut faces slide on their planes (exact for "
    "this axisymmetric insertion, so the sector's contact line and model stay small); its forces "
    "are the sector's, the whole ring's axial force is 360 / sector times it (the summary's "
    "`ring_copies`). Another motion or rigid part would break the symmetry and is refused. "
    "Meshed with gmsh, finer along the lip's edges.",
}

_TYPES = {float: "number", int: "integer", bool: "boolean", str: "string", list: "array"}


def _number(v: float | int) -> str:
    """A number as TOML writes it, in its shortest form: ``1e-5``, ``0.3``, ``10.0``, ``64``."""
    if isinstance(v, int):
        return str(v)
    text = f"{v:.12g}"
    if "e" in text:
        mantissa, exponent = text.split("e")
        return f"{mantissa}e{int(exponent)}"
    return text if "." in text else text + ".0"


def _value(v) -> str:
    if isinstance(v, list):
        return f"`[{', '.join(_number(x) for x in v)}]`"
    if isinstance(v, bool):
        return f"`{'true' if v else 'false'}`"
    if isinstance(v, str):
        return f'`"{v}"`'
    return f"`{_number(v)}`"


def _split_doc(doc: str) -> tuple[str, str]:
    """``(meaning, how the default is derived)`` from a doc of the form "meaning; default: how"."""
    for marker in ("; default: ", "; default "):
        if marker in doc:
            meaning, derived = doc.split(marker, 1)
            return meaning, derived
    return doc, ""


def _allowed(spec: Key) -> str:
    if spec.choices is not None:
        return ", ".join(_value(c) for c in spec.choices)
    if spec.kind is bool:
        return "`true`, `false`"
    return f"`{spec.range_text()}`"


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def _row(section: str, key: str, spec: Key) -> str:
    meaning, derived = _split_doc(spec.doc)
    dotted = f"{section}.{key}"
    if spec.default is REQUIRED:
        default = "required"
    elif spec.default is None:
        default = f"derived: {derived}" if derived else "derived"
    elif dotted in GEOMETRIC:
        default = f"{_value(GEOMETRIC[dotted])} × wall ratio"
    elif dotted in SIZED:
        default = f"{_value(SIZED[dotted])} × size"
    else:
        default = _value(spec.default)
    unit = spec.unit or ("–" if spec.kind in (float, int) else "")
    cells = [f"`{key}`", _TYPES[spec.kind], unit, default, _allowed(spec), meaning]
    return "| " + " | ".join(_cell(c) for c in cells) + " |"


def _minimal_example() -> str:
    """The required keys, with the shipped default scene's values, as TOML."""
    shipped = tomllib.loads(default_scene_path().read_text())
    lines = []
    for section, keys in SCHEMA.items():
        if section == "connector" and section in shipped:
            keys = {**keys, **CONNECTORS[shipped[section]["type"]]}
        required = [k for k, spec in keys.items() if spec.default is REQUIRED and not spec.internal]
        if not required or section not in shipped:  # the optional sections of parts from files
            continue
        if lines:
            lines.append("")
        lines.append(f"[{section}]")
        for key in required:
            value = shipped[section][key]
            text = f'"{value}"' if isinstance(value, str) else _number(value)
            lines.append(f"{key} = {text}")
    return "\n".join(lines)


def _rules() -> list[str]:
    """The checks of ``_check_consistency`` (and of the connector's own validation), in words."""
    deflection = _scene._MAX_DEFLECTION_RATIO
    return [
        "**The connector must be a hook that can be built.** `connector.tip_thickness` may be at "
        "most 4 times `connector.thickness`; angles so close to 0 degrees that the hook would be "
        "infinitely tall, or a `connector.lead_angle` so close to 90 degrees that the lead ramp "
        "vanishes, are refused.",
        f"**The deflection must stay small.** `connector.undercut` may be at most {deflection:g} "
        "times `connector.length`: the arm bends its tip by the undercut, and beyond that the tip "
        f"would turn by more than ~{math.degrees(1.5 * deflection):.0f} degrees, outside the small "
        "strains and rotations of a linear model and of any plastic snap-fit.",
        "**The rigid part's fillet must fit.** `plug.fillet` may be at most half the plug's smallest "
        "side (`plug.thickness`, `plug.width`, `plug.height`, with their derived defaults).",
        f"**The motion must take at least {_scene.MIN_STEPS} time steps.** The stroke (given, or the "
        "derived latching stroke) divided by `motion.speed`, twice that with `motion.withdraw`, "
        f"divided by `solver.dt`: the contact events of a snap (ramp, flat, release) each need "
        "several steps. The error gives the largest `solver.dt` that works.",
        "**A step must not carry the rigid part through the part.** The farthest any point of the rigid "
        "part moves in one step (`motion.speed` times `solver.dt`, or a path's largest step: its centre's "
        "displacement plus its turn times its radius) may be at most the part's wall (`connector.thickness`, "
        "or a part file's measured wall); a `SceneWarning` says when it is more than "
        f"{_scene._MAX_STEP_TRAVEL:g} contact resolution (the larger of `contact.spacing` and "
        "`contact.margin`), where contact is found a step late and the force is off, and gives the "
        "`solver.dt` that resolves it.",
        f"**Friction must be a dry plastic's.** `contact.friction` may be at most {_scene._MAX_FRICTION:g}; "
        f"a `SceneWarning` says when it is above {_scene._HIGH_FRICTION:g}, more than the design guides "
        "list for any plastic pair.",
        "**The parts are presets or files, one of each.** `[part]` replaces `[connector]` and "
        "needs `[rigid]` (the preset plug is sized from the connector); `[rigid]` replaces `[plug]`. "
        '`[part]` takes exactly one of `part.fixed` and `part.fixed_box`; `solver.sdf = "analytic"` '
        "is the preset plug's formula and is refused with a `[rigid]` file, which also needs "
        "`motion.stroke` for a straight insertion. The files named must exist (paths relative to the "
        "scene file).",
        "**The motion is straight or a path.** `motion.waypoints` and `motion.trajectory` exclude "
        "each other and the straight insertion's `direction`, `stroke` and `withdraw`; poses start at "
        "t = 0, their times increase and their rotations are unit quaternions (within 1e-6). The "
        "insertion axis (the direction of `insertion_force`) is `motion.direction`, or the direction "
        "of a path's largest displacement from its start.",
        "**The elements must resolve the connector.** `solver.mesh_size` may be at most "
        f"{_scene._COARSEST:g} times the thinnest feature of the connector (the smallest of its "
        "`thickness`, `tip_thickness`, `width` and `undercut`; for the two-hook clip, whose hooks are "
        "meshed finer on their own, of `thickness`, `width` and `base_thickness`), and a "
        "`SceneWarning` says when it is larger than that feature itself (less than one element "
        "across it: a coarse, stiff model). For a part from a file a `SceneWarning` says when the "
        "element size, given or derived, spans its thinnest wall with fewer than "
        f"{MIN_ELEMENTS_ACROSS['P2']} P2 or {MIN_ELEMENTS_ACROSS['P1']} P1 elements (gmsh divides a "
        "wall's edges t long into ceil(t / solver.mesh_size) elements: for P2, elements no larger than "
        "the wall), and suggests a size.",
    ]


def render() -> str:
    """The scene reference as Markdown (the text of ``docs/scene-reference.md``)."""
    out = [
        "# Scene reference",
        "",
        f"<!-- Generated from the scene schema (jsnap/_geometry/scene.py) by `{COMMAND}`; "
        "do not edit by hand. -->",
        "",
        "A scene is a TOML file: one table per section below, each holding the section's keys. "
        "`jsnap.load_scene(path)` reads and validates one (`jsnap.load_scene()` with no path: the "
        "shipped default scene, `jsnap/scenes/default.toml`), `jsnap simulate SCENE.toml` runs it, "
        'and `scene.replace({"section.key": value})` changes keys of a loaded scene, validated '
        "in the same way.",
        "",
        "Units everywhere: mm, N, MPa, s, tonne (density in t/mm³); angles in degrees. A key that "
        "is absent takes its default; a default marked *derived* is computed from other keys as "
        "its entry says.",
        "",
        "Defaults that are lengths follow the part's size. The *wall ratio* is the part's wall "
        "thickness over the shipped part's: a preset's `connector.thickness` over its shipped "
        f"scene's ({', '.join(f'{k} {v:g} mm' for k, v in REFERENCE_THICKNESS.items())}), a part "
        "file's measured wall thickness (its thinnest wall: the least of its thicknesses along the "
        f"inward normals, across to a face within {WALL_ANGLE:g} degrees of facing back) over the "
        f"shipped hook's {REFERENCE_WALL:g} mm. A default marked *× wall ratio* "
        "(the element size, the preset rigid part's shape) is its value times the wall ratio. A "
        "default marked *× size* (the contact's resolution) is its value times the part's *size*: "
        f"1 while the wall ratio is within a factor {BAND:g} of 1, where these defaults hold as they "
        f"are, and beyond that the wall ratio over the band's edge (ratio / {BAND:g} above, "
        f"ratio × {BAND:g} below). `scene.size` holds it; a key given in the scene keeps its value "
        "([parts of any size](guide.md#parts-of-any-size)).",
        "",
        "A scene needs only the required keys; with the shipped default scene's values:",
        "",
        "```toml",
        _minimal_example(),
        "```",
        "",
        "## Validation",
        "",
        "A scene is checked completely when it is loaded, before anything is built. Each of these "
        "is an error (`jsnap.SceneError`) whose message names the key (`section.key`) and the "
        "value:",
        "",
        "- an unknown section or key (the message lists the keys the section takes), or a "
        "missing required key;",
        "- a value of the wrong type (an integer is accepted where a number is expected, not "
        "the other way round), a number that is not finite, a number outside the key's range "
        "or a string that is not one of its choices.",
        "",
        "These rules involve several keys:",
        "",
        *[f"- {rule}" for rule in _rules()],
    ]
    for section, keys in SCHEMA.items():
        visible = [(k, spec) for k, spec in keys.items() if not spec.internal]
        if not visible:
            continue
        out += ["", f"## [{section}]", ""]
        if section in _SECTIONS:
            out += [_SECTIONS[section], ""]
        out += _table(section, visible)
        if section == "connector":
            for kind, kind_keys in CONNECTORS.items():
                out += ["", f'### type = "{kind}"', "", _CONNECTORS[kind], ""]
                out += _table(section, [(k, spec) for k, spec in kind_keys.items() if not spec.internal])
    return "\n".join(out) + "\n"


def _table(section: str, keys: list[tuple[str, Key]]) -> list[str]:
    return [
        "| key | type | unit | default | allowed | meaning |",
        "|---|---|---|---|---|---|",
        *[_row(section, k, spec) for k, spec in keys],
    ]


if __name__ == "__main__":
    import sys

    sys.stdout.write(render())
