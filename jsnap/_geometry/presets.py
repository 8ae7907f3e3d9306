"""Connector presets (``connector.type``): generators of the same things a user can give in
files — a deformable part (tetrahedra and its fixed region), a default rigid part and a default
straight motion along −z. After the geometry layer only the canonical cantilever is told
apart: it keeps its own contact sampling along its section (``jsnap._build.samples``).

* ``cantilever`` — the canonical hook (:class:`jsnap._geometry.cantilever.Cantilever`),
  structured tetrahedra;
* ``two_hook_clip`` — two cantilevers of that section, mirror images about ``x = 0`` with their
  hooks pointing inwards, their inner faces ``gap`` apart, rising from ``z = 0`` out of a base
  block ``base_thickness`` thick whose bottom face is fixed; the rigid part is a block exactly
  ``gap`` wide that squeezes between the hooks;
* ``box_lid`` — a lid with four hooks (the switch box of the paper's Fig. 1): a plate
  ``lid_thickness`` thick whose outer face is fixed (the robot's flat platen holds it), two
  pairs of the clip's arms standing on it, hooks inwards, ``gap`` apart across the box and
  ``spacing`` apart along it; the rigid part is the box's rim, a block ``gap`` wide, turned by
  ``tilt`` about the x axis so that the hooks at ``-y`` engage before those at ``+y``;
* ``cable_latch`` — the flexible latch of a cable plug (the LAN plug of the paper's Fig. 1): an
  arm hanging from a bridge at the top of the plug body, ``gap`` away from it, with a catch
  (the cantilever's hook section) ``catch_position`` below its root; the plug body's back face is
  fixed (the part the robot holds) and the jack's lip, a rigid block, comes down along the
  arm from its root: it pushes the catch in by the undercut and passes it, the latch springs
  back behind it. The contact moves away from the root as the lip travels, so the arm grows
  softer under it (a cantilever loaded at a travelling point, not at its tip).

* ``annular`` — a tube (bore ``radius``, wall ``thickness``) fixed at its end ``z = 0`` with an
  inward lip at its mouth (the cantilever's hook section turned about the tube's axis, its
  retention face ``length`` above the fixed end), snapped over a rigid bead (a cylinder of the
  bore's radius with rounded edges) pushed down the axis: caps, pens, bottle closures. The
  part is a ``sector`` (degrees) of the ring whose two cut faces slide on their planes
  (``TetMesh.sliding``): exact for the axisymmetric straight insertion, and the contact line it
  carries is ``sector / 360`` of the ring's, so the model stays small; its forces are the
  sector's (the whole ring's axial force is ``360 / sector`` times it). The sector is one
  element wide (its facets' sagitta a small fraction of the undercut, checked on load).

The clip, the lid, the latch and the annular snap are tet-meshed with gmsh (the mesher the
parts from files use) from their exact CAD solids, section polygons extruded over y (and
fused) or turned about z, finer along the hooks' (catch's, lip's) edges (see
:func:`_hook_size`). Units: mm, degrees.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from jsnap._geometry.cantilever import Cantilever, mesh_cantilever
from jsnap._geometry.mesh import TetMesh, check_quality
from jsnap._geometry.motion import latching_stroke
from jsnap._geometry.plug import Plug
from jsnap._geometry.size import OVERSHOOT, PLUG_DEPTH_MARGIN, preset_ratio

__all__ = [
    "PRESETS",
    "Preset",
    "annular_section",
    "annular_sliding",
    "box_lid_pieces",
    "box_lid_tilt",
    "clip_section",
    "connector_features",
    "default_rigid",
    "default_stroke",
    "generate",
    "hook_of",
    "latch_section",
    "latch_tip_deflection",
    "preset_volume",
]

PRESETS = (
    "cantilever",
    "two_hook_clip",
    "box_lid",
    "cable_latch",
    "annular",
)  # the keys of jsnap._geometry.scene.CONNECTORS


@dataclass(frozen=True, eq=False)
class Preset:
    """What a preset generates.

    Attributes:
        mesh: the deformable part (mm), its fixed region in ``base_nodes``.
        plug: the default rigid part (a block or, for the annular snap, a cylinder with rounded
            edges) and its start.
        stroke: the default travel along −z, mm: the rigid part passes 0.3 mm below the
            retention faces (it latches).
    """

    mesh: TetMesh
    plug: Plug | None
    stroke: float


def hook_of(c: Mapping) -> Cantilever:
    """The hook section of a preset's ``[connector]`` table (the cantilever's arm, each of the
    clip's arms; the latch's catch with the arm below it, its ``length`` the height of the
    retention face above the latch's free end; the annular snap's wall and lip, ``x`` the depth
    into the wall from the bore). Raises ``ValueError`` naming the key."""
    if "catch_position" in c:
        if not 0 < c["catch_position"] < c["length"]:
            raise ValueError(
                f"connector.catch_position = {c['catch_position']!r}: the catch's retention face must lie "
                f"on the arm, between its root and its free end: in (0, length) = (0, {c['length']:g}) mm"
            )
    return Cantilever(
        length=c["length"] - c["catch_position"] if "catch_position" in c else c["length"],
        thickness=c["thickness"],
        # The annular lip's width: its arc at the bore over the sector.
        width=c["width"] if "width" in c else c["radius"] * math.radians(c["sector"]),
        undercut=c["undercut"],
        lead_angle=c["lead_angle"],
        return_angle=c["return_angle"],
        flat=c["flat"],
        tip_thickness=c.get("tip_thickness"),
    )


def connector_features(kind: str, c: Mapping) -> dict[str, float]:
    """The preset's thin features (key -> mm) that the elements must resolve; checks the
    preset's own rules (``ValueError`` naming the key)."""
    hook = hook_of(c)
    if kind == "cantilever":
        return {
            "thickness": c["thickness"],
            "tip_thickness": hook.h_tip,
            "width": c["width"],
            "undercut": c["undercut"],
        }
    if kind == "two_hook_clip":
        if not c["gap"] > 2 * c["undercut"]:
            raise ValueError(
                f"connector.gap = {c['gap']!r}: the two hooks' lips would touch or overlap; the gap must be "
                f"more than twice connector.undercut ({2 * c['undercut']:g} mm)"
            )
        # The hooks' lips are meshed finer on their own (see generate).
        return {"thickness": c["thickness"], "width": c["width"], "base_thickness": c["base_thickness"]}
    if kind == "box_lid":
        if not c["gap"] > 2 * c["undercut"]:
            raise ValueError(
                f"connector.gap = {c['gap']!r}: facing hooks' lips would touch or overlap; the gap must be "
                f"more than twice connector.undercut ({2 * c['undercut']:g} mm)"
            )
        if not c["spacing"] > c["width"]:
            raise ValueError(
                f"connector.spacing = {c['spacing']!r}: the two hooks on a side would overlap; the spacing "
                f"of their centres must be more than connector.width ({c['width']:g} mm)"
            )
        return {"thickness": c["thickness"], "width": c["width"], "lid_thickness": c["lid_thickness"]}
    if kind == "cable_latch":
        if not hook.z_top < c["length"]:
            raise ValueError(
                f"connector.catch_position = {c['catch_position']!r}: the catch is "
                f"{hook.z_top - hook.length:g} mm tall (retention face, flat and lead ramp) and must end below "
                f"the arm's root: catch_position must be more than {hook.z_top - hook.length:g} mm"
            )
        tip = latch_tip_deflection(c)
        if not c["gap"] > tip:
            raise ValueError(
                f"connector.gap = {c['gap']!r}: pushed in by the undercut at the catch, the latch's free end "
                f"moves ~{tip:.3g} mm towards the plug body (beam theory) and would hit it, a contact jsnap "
                f"does not model; make the gap more than {tip:.3g} mm (or the catch nearer the free end)"
            )
        return {"thickness": c["thickness"], "width": c["width"], "gap": c["gap"]}
    if kind == "annular":
        if not c["undercut"] < c["radius"]:
            raise ValueError(
                f"connector.undercut = {c['undercut']!r}: the lip would close the bore (connector.radius = "
                f"{c['radius']:g} mm); it must be less than the radius"
            )
        return {"thickness": c["thickness"]}
    raise ValueError(f"connector.type = {kind!r}: must be one of {', '.join(PRESETS)}")


def _area(section: np.ndarray) -> float:
    """Area of a counter-clockwise polygon (k, 2), mm² (shoelace)."""
    x, z = section[:, 0], section[:, 1]
    return 0.5 * float(np.sum(x * np.roll(z, -1) - np.roll(x, -1) * z))


def preset_volume(kind: str, c: Mapping) -> float:
    """The exact volume of the preset's deformable part, mm³, from its ``[connector]`` table
    (validated), without meshing it: its section polygons' areas times their extrusion, or (the
    annular sector) its section turned about z by ``sector`` (Pappus: the section's first moment
    about the axis times the angle)."""
    if kind == "cantilever":
        return hook_of(c).volume()
    if kind == "two_hook_clip":
        return _area(clip_section(c)) * c["width"]
    if kind == "box_lid":  # the plate and the arms standing on it meet on a face, never overlap
        return sum(_area(section) * (y1 - y0) for section, y0, y1 in box_lid_pieces(c))
    if kind == "cable_latch":
        return _area(latch_section(c)) * c["width"]
    if kind == "annular":
        p = annular_section(c)
        r, z, r1, z1 = p[:, 0], p[:, 1], np.roll(p[:, 0], -1), np.roll(p[:, 1], -1)
        return float(np.sum((r + r1) * (r * z1 - r1 * z)) / 6.0) * math.radians(c["sector"])
    raise ValueError(f"connector.type = {kind!r}: must be one of {', '.join(PRESETS)}")


# --------------------------------------------------------------------------------------------
# Sections and their meshes
# --------------------------------------------------------------------------------------------


def _mirror_hook(hook: Cantilever, inner: float) -> np.ndarray:
    """The right arm's section (x, z) of the clip, counter-clockwise from its outer root
    corner: the cantilever's polygon with x -> inner + h - x (its hook on the inner face)."""
    p = hook.section()  # (0,0) (h,0) (h_tip,L) (ret) (flat end) (h_tip,z_top) (0,z_top)
    x = inner + hook.thickness - p[:, 0]
    q = np.stack([x, p[:, 1]], axis=1)
    # Mirroring reverses the orientation: walk it backwards from (inner + h, 0).
    return q[[0, 6, 5, 4, 3, 2, 1]]


def clip_section(c: Mapping) -> np.ndarray:
    """(k, 2) section polygon (x, z) of the two-hook clip, counter-clockwise, mm."""
    hook = hook_of(c)
    a, h, m, tb = 0.5 * c["gap"], c["thickness"], c["base_margin"], c["base_thickness"]
    X = a + h + m
    right = _mirror_hook(hook, a)  # (a+h,0) (a+h,zt) (a,zt) (flat end) (ret) (a,L) (a,0)
    left = right[::-1] * [-1.0, 1.0]  # (-a,0) (-a,L) ... (-a-h,zt) (-a-h,0)
    return np.concatenate([[[-X, -tb], [X, -tb], [X, 0.0]], right, left, [[-X, 0.0]]])


def box_lid_pieces(c: Mapping) -> list[tuple[np.ndarray, float, float]]:
    """The box lid as sections (x, z), counter-clockwise, each extruded over ``y in [y0, y1]``:
    ``[(section, y0, y1), ...]``, mm. The lid plate ``x in [-X, X]``, ``y in [-Y, Y]``,
    ``z in [-lid_thickness, 0]`` and four arms of the clip's section standing on it, their inner
    faces at ``x = +-gap/2``, centred at ``y = +-spacing/2``."""
    hook = hook_of(c)
    a, h, b, m = 0.5 * c["gap"], c["thickness"], c["width"], c["lid_margin"]
    X, Y, T = a + h + m, 0.5 * c["spacing"] + 0.5 * b + m, c["lid_thickness"]
    plate = np.array([[-X, -T], [X, -T], [X, 0.0], [-X, 0.0]])
    right = _mirror_hook(hook, a)
    left = right[::-1] * [-1.0, 1.0]
    arms = [
        (arm, yc - 0.5 * b, yc + 0.5 * b)
        for yc in (-0.5 * c["spacing"], 0.5 * c["spacing"])
        for arm in (right, left)
    ]
    return [(plate, -Y, Y), *arms]


def box_lid_tilt(c: Mapping) -> np.ndarray:
    """The box's orientation, a unit quaternion (w, x, y, z): turned by ``tilt`` about the x
    axis, so that its -y end comes down first."""
    half = 0.5 * np.radians(c["tilt"])
    return np.array([np.cos(half), np.sin(half), 0.0, 0.0])


def latch_section(c: Mapping) -> np.ndarray:
    """(12, 2) section polygon (x, z) of the cable latch, counter-clockwise, mm: the arm
    ``x in [0, h]`` from its free end ``z = 0`` up to its root ``z = length``, the catch on its
    outer face, a bridge ``2 h`` tall over the gap to the plug body
    ``x in [-gap - body_thickness, -gap]``, ``z in [0, length + 2 h]``."""
    hook = hook_of(c)
    h, L, g, T = c["thickness"], c["length"], c["gap"], c["body_thickness"]
    top = L + 2.0 * h
    catch = hook.section()[2:6]  # (h, z_r) (h + y_u, z_ret) (h + y_u, z_flat_end) (h, z_top)
    return np.concatenate(
        [[[-g - T, 0.0], [-g, 0.0], [-g, L], [0.0, L], [0.0, 0.0], [h, 0.0]], catch, [[h, top], [-g - T, top]]]
    )


def annular_section(c: Mapping) -> np.ndarray:
    """(7, 2) section (r, z) of the annular snap's tube wall and lip, counter-clockwise from the
    bore at the fixed end, mm: the wall ``r in [radius, radius + thickness]``, the lip reaching
    ``undercut`` into the bore at its mouth."""
    sec = _mirror_hook(hook_of(c), c["radius"])  # (R+h,0) (R+h,zt) (R,zt) (flat end) (ret) (R,L) (R,0)
    return sec[[6, 0, 1, 2, 3, 4, 5]]


def annular_sliding(points: np.ndarray, sector: float) -> tuple:
    """The two cut faces of an annular sector (``sector`` degrees centred on +x) as sliding
    planes ``((nodes, unit normal), ...)`` for :class:`TetMesh`."""
    tol = 1e-9 * float(np.linalg.norm(np.ptp(points, axis=0)))
    planes = []
    for phi in (-0.5 * math.radians(sector), 0.5 * math.radians(sector)):
        normal = np.array([-math.sin(phi), math.cos(phi), 0.0])
        planes.append((np.flatnonzero(np.abs(points @ normal) <= tol), normal))
    return tuple(planes)


def latch_tip_deflection(c: Mapping) -> float:
    """How far the latch's free end moves when the catch is pushed in by the undercut, mm:
    a cantilever of length ``length`` loaded at distance ``l`` from its root (the top of the
    catch's flat), ``y (3 L - l) / (2 l)`` for the deflection ``y`` there."""
    hook = hook_of(c)
    L = c["length"]
    arm = L - hook.z_flat_end
    return c["undercut"] * (3.0 * L - arm) / (2.0 * arm)


def _gmsh_mesh(pieces, *, size: float, fine: float, fine_box, turn: float | None = None) -> tuple:
    """Tetrahedra (points (n, 3), cells (m, 4)) of the union of section polygons (x, z)
    extruded over y: ``pieces`` = [(section (k, 2), y0, y1), ...]; or, with ``turn`` (degrees,
    less than 180), of the one section (r, z) turned about the z axis by that angle, centred on
    +x. Elements of ``size``, ``fine`` on the edges that lie in ``fine_box`` = ((x0, z0),
    (x1, z1)) (the hooks), growing to ``size`` within ``2 size`` of them."""
    import gmsh

    initialised = gmsh.isInitialized()
    if not initialised:
        gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("jsnap-preset")
        occ = gmsh.model.occ
        solids = []
        for section, y0, y1 in pieces:
            pts = [occ.addPoint(x, y0, z) for x, z in section]
            lines = [occ.addLine(pts[i], pts[(i + 1) % len(pts)]) for i in range(len(pts))]
            face = occ.addPlaneSurface([occ.addCurveLoop(lines)])
            if turn is None:
                solids += [e for e in occ.extrude([(2, face)], 0.0, y1 - y0, 0.0) if e[0] == 3]
            else:
                angle = math.radians(turn)
                solids += [e for e in occ.revolve([(2, face)], 0, 0, 0, 0, 0, 1, angle) if e[0] == 3]
                occ.rotate(solids[-1:], 0, 0, 0, 0, 0, 1, -0.5 * angle)
        if len(solids) > 1:
            # One solid whose pieces share their nodes where they touch.
            occ.fuse(solids[:1], solids[1:])
        occ.synchronize()
        big = 10.0 * max(float(np.max(np.abs(np.asarray(p[0])))) + abs(p[1]) + abs(p[2]) for p in pieces) + 10.0
        eps = 1e-6 * big
        (x0, z0), (x1, z1) = np.clip(np.asarray(fine_box, np.float64), -big, big)
        hooks = gmsh.model.getEntitiesInBoundingBox(x0 - eps, -big, z0 - eps, x1 + eps, big, z1 + eps, dim=1)
        field = gmsh.model.mesh.field
        dist = field.add("Distance")
        field.setNumbers(dist, "CurvesList", [tag for _, tag in hooks])
        field.setNumber(dist, "Sampling", 50)
        grade = field.add("Threshold")
        field.setNumber(grade, "InField", dist)
        for name, v in (("SizeMin", fine), ("SizeMax", size), ("DistMin", 0.0), ("DistMax", 2.0 * size)):
            field.setNumber(grade, name, v)
        field.setAsBackgroundMesh(grade)
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
        gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
        gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
        gmsh.option.setNumber("Mesh.Optimize", 1)
        gmsh.model.mesh.generate(3)
        tags, coords, _ = gmsh.model.mesh.getNodes()
        etypes, _, enodes = gmsh.model.mesh.getElements(3)
    finally:
        gmsh.model.remove()
        if not initialised:
            gmsh.finalize()
    index = np.zeros(int(tags.max()) + 1, np.int64)
    index[tags.astype(np.int64)] = np.arange(tags.size)
    cells = index[np.asarray(enodes[list(etypes).index(4)], np.int64).reshape(-1, 4)]
    points = coords.reshape(-1, 3)
    used = np.unique(cells)
    renumber = -np.ones(points.shape[0], np.int64)
    renumber[used] = np.arange(used.size)
    return points[used], renumber[cells]


def _fixed_below(points: np.ndarray, value: float, axis: int) -> np.ndarray:
    tol = 1e-9 * float(np.linalg.norm(np.ptp(points, axis=0)))
    return np.flatnonzero(points[:, axis] <= value + tol)


def _finish(points, cells, fixed: float, axis: int = 2, sliding: tuple = ()) -> TetMesh:
    """The mesh with positive volumes, its fixed region the nodes at ``points[:, axis] <= fixed``
    and its ``sliding`` planes."""
    vol = np.einsum(
        "ij,ij->i",
        np.cross(points[cells[:, 1]] - points[cells[:, 0]], points[cells[:, 2]] - points[cells[:, 0]]),
        points[cells[:, 3]] - points[cells[:, 0]],
    )
    cells = np.where((vol < 0)[:, None], cells[:, [0, 2, 1, 3]], cells)
    check_quality(points, cells, min_quality=0.02)
    return TetMesh(points, cells, _fixed_below(points, fixed, axis), sliding)


def _hook_size(hook: Cantilever, size: float) -> float:
    """Element size along the hooks' edges: about one P2 element across the hook's section
    (2.5 undercuts; the mesh still follows its edges exactly), never above ``size``. A full
    hook of elements the undercut's size would multiply the part's dof several times over."""
    return min(size, max(2.5 * hook.undercut, hook.flat))


# --------------------------------------------------------------------------------------------
# The presets
# --------------------------------------------------------------------------------------------


def default_rigid(kind: str, c: Mapping, plug: Mapping) -> Plug:
    """The preset's default rigid part from its ``[connector]`` and ``[plug]`` tables: a block
    with rounded edges (cantilever: its face ``x = h_tip`` in the plane of the arm's outer face at
    the tip, so it pushes the hook by the full undercut; clip: exactly ``gap`` wide, centred,
    pushing both hooks; latch: like the cantilever, the jack's lip with its face in the plane of
    the arm's outer face; annular: a cylinder of the bore's radius on the axis),
    ``plug.clearance`` above the hook's (catch's, lip's) top."""
    hook = hook_of(c)
    if kind == "annular":
        half = np.array([c["radius"], c["radius"], 0.5 * plug["height"]])
        start = [0.0, 0.0, hook.z_top + plug["clearance"] + half[2]]
        return Plug(half, plug["fillet"], start, shape="cylinder")
    if kind in ("cantilever", "cable_latch"):
        thick = plug["thickness"] or 1.25 * hook.undercut
        x = hook.h_tip + 0.5 * thick
    else:
        thick, x = plug["thickness"] or c["gap"], 0.0
    depth = hook.width + (c["spacing"] if kind == "box_lid" else 0.0) + PLUG_DEPTH_MARGIN * preset_ratio(c)
    half = np.array([thick, plug["width"] or depth, plug["height"]]) / 2
    if kind != "box_lid":
        return Plug(half, plug["fillet"], [x, 0.0, hook.z_top + plug["clearance"] + half[2]])
    # The tilted box's lowest point (on its -y bottom edge's fillet) `clearance` above the hooks.
    r, (ct, st) = plug["fillet"], (np.cos(np.radians(c["tilt"])), np.sin(np.radians(c["tilt"])))
    below = (half[2] - r) * ct + (half[1] - r) * st + r
    return Plug(half, r, [x, 0.0, hook.z_top + plug["clearance"] + below], rotation=box_lid_tilt(c))


def default_stroke(kind: str, c: Mapping, plug: Mapping, rigid: Plug) -> float:
    """The preset's default travel along -z, mm: the rigid part ``rigid`` (its default) latches
    every hook, its top passing 0.3 mm (times the wall ratio) below the retention faces (for the
    box lid, its tilted top face at the far edge of the hooks it reaches last)."""
    hook = hook_of(c)
    if kind != "box_lid":
        return latching_stroke(
            plug["height"], plug["clearance"], hook.z_top - hook.length, OVERSHOOT * preset_ratio(c)
        )
    th = np.radians(c["tilt"])
    y_far = 0.5 * (c["spacing"] + c["width"])
    along = (y_far + rigid.half[2] * np.sin(th)) / np.cos(th)  # in the box's own frame
    top = rigid.start[2] + along * np.sin(th) + rigid.half[2] * np.cos(th)
    return float(top - (c["length"] - OVERSHOOT * preset_ratio(c)))


def generate(kind: str, c: Mapping, plug: Mapping, mesh_size: float) -> Preset:
    """The deformable part, default rigid part and default stroke of preset ``kind`` from its
    ``[connector]`` and ``[plug]`` tables (validated scene values), meshed at ``mesh_size``.
    Without a ``[plug]`` table (the scene's rigid part is a file) there is no default rigid part
    or stroke: both are None."""
    hook = hook_of(c)
    rigid = default_rigid(kind, c, plug) if plug else None
    stroke = default_stroke(kind, c, plug, rigid) if plug else None
    if kind == "cantilever":
        return Preset(mesh_cantilever(hook, mesh_size), rigid, stroke)
    fine = _hook_size(hook, mesh_size)
    above_root = ((-np.inf, hook.length), (np.inf, np.inf))  # the hooks' (lip's) edges
    if kind == "two_hook_clip":
        half = 0.5 * hook.width
        points, cells = _gmsh_mesh(
            [(clip_section(c), -half, half)], size=mesh_size, fine=fine, fine_box=above_root
        )
        return Preset(_finish(points, cells, -c["base_thickness"]), rigid, stroke)
    if kind == "box_lid":
        points, cells = _gmsh_mesh(box_lid_pieces(c), size=mesh_size, fine=fine, fine_box=above_root)
        return Preset(_finish(points, cells, -c["lid_thickness"]), rigid, stroke)
    if kind == "cable_latch":
        # Finer on the catch's edges only (the arm's outer face continues above and below it).
        box = ((hook.thickness, hook.length), (np.inf, hook.z_top))
        half = 0.5 * hook.width
        points, cells = _gmsh_mesh([(latch_section(c), -half, half)], size=mesh_size, fine=fine, fine_box=box)
        return Preset(_finish(points, cells, -c["gap"] - c["body_thickness"], axis=0), rigid, stroke)
    if kind == "annular":
        pieces = [(annular_section(c), 0.0, 0.0)]  # turned, not extruded: no y extent
        points, cells = _gmsh_mesh(pieces, size=mesh_size, fine=fine, fine_box=above_root, turn=c["sector"])
        return Preset(_finish(points, cells, 0.0, sliding=annular_sliding(points, c["sector"])), rigid, stroke)
    raise ValueError(f"connector.type = {kind!r}: must be one of {', '.join(PRESETS)}")
