"""Write the example's two STL files (mm): a printed three-prong snap hook (the deformable part)
and the housing it snaps into (the rigid part), drawn as a CAD user would, with sharp edges.

The hook: a base block 34 x 12 x 6 mm (its bottom face z = -6 is the fixed region) carrying
three prongs 6 mm thick (x) and 7 mm wide (y) that rise 40 mm from its top face z = 0, 4 mm
apart. The two outer prongs carry barbs on their outer faces: an undercut of 1.5 mm, a square
retention face at z = 36.4, a 1 mm land and a 30 degree lead ramp that returns to the prong's
face at its top, z = 40. The middle prong is a plain guide.

The housing: a plate 42 x 20 mm, 30 mm thick (z), with a rectangular through-hole 26.6 x 9 mm,
0.3 mm wider on each side than the outer prongs' faces, and 1.2 mm narrower than their barbs.
At t = 0 its lower face is 1 mm above the prongs' tips (z = 41). Pushed down along -z, the hole
meets the barbs' ramps, presses both barbs in by 1.2 mm and slides along their lands for about
31 mm, until its upper face passes the retention faces and the barbs snap out over it.

Run from this folder (or pass another folder, and sizes, to :func:`write`):

    python make_files.py
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

# The hook's and the housing's dimensions, mm (see the module docstring).
HOOK = dict(
    length=40.0,  # the prongs' height above the base, barbs included
    thickness=6.0,  # x, the bending direction of the outer prongs
    width=7.0,  # y
    gap=4.0,  # between neighbouring prongs
    undercut=1.5,
    land=1.0,
    lead_angle=30.0,  # degrees from the insertion direction
    base_thickness=6.0,
    base_margin=4.0,  # the base reaches this far beyond the outer prongs in x, 2.5 mm in y
)
HOUSING = dict(
    thickness=30.0,  # along z: the length the barbs slide in the hole
    clearance=0.3,  # between the hole's wall and the outer prongs' faces (x)
    side_clearance=2.0,  # between the hole's wall and the prongs' sides (y)
    wall=4.0,  # the plate beyond the hole (x), 5.5 mm in y
    start_gap=1.0,  # its lower face above the prongs' tips at t = 0
)


def prong_outline(x0: float, x1: float, h: dict, barb: int) -> list[tuple[float, float]]:
    """The x-z outline of one prong from x0 to x1 (mm), counter-clockwise; ``barb`` +1 puts a
    barb on its face at x1, -1 on its face at x0, 0 none."""
    L, u, land = h["length"], h["undercut"], h["land"]
    ramp = u / math.tan(math.radians(h["lead_angle"]))
    z_ret = L - ramp - land
    if barb > 0:
        return [(x0, 0.0), (x1, 0.0), (x1, z_ret), (x1 + u, z_ret), (x1 + u, z_ret + land), (x1, L), (x0, L)]
    if barb < 0:
        return [(x0, 0.0), (x1, 0.0), (x1, L), (x0, L), (x0 - u, z_ret + land), (x0 - u, z_ret), (x0, z_ret)]
    return [(x0, 0.0), (x1, 0.0), (x1, L), (x0, L)]


def retention_z(h: dict = HOOK) -> float:
    """z of the barbs' retention faces, mm."""
    return h["length"] - h["undercut"] / math.tan(math.radians(h["lead_angle"])) - h["land"]


def outer_face(h: dict = HOOK) -> float:
    """x of the right prong's outer face (the left one's is its negative), mm."""
    return 1.5 * h["thickness"] + h["gap"]


def _extruded(gmsh, outline, y0: float, width: float) -> int:
    """An OCC volume: the x-z polygon ``outline`` extruded over y in [y0, y0 + width]."""
    occ = gmsh.model.occ
    pts = [occ.addPoint(x, y0, z) for x, z in outline]
    lines = [occ.addLine(pts[i], pts[(i + 1) % len(pts)]) for i in range(len(pts))]
    face = occ.addPlaneSurface([occ.addCurveLoop(lines)])
    out = occ.extrude([(2, face)], 0.0, width, 0.0)
    return next(tag for dim, tag in out if dim == 3)


# Longest triangle edge of the STL files, mm: as a CAD export's "maximum edge length". An STL
# of the fewest triangles (a face with holes in a handful of slivers) is one that gmsh cannot
# split into pieces it can remesh ("Wrong topology of boundary mesh for parametrization").
STL_EDGE = 2.0


def _write_stl(gmsh, path: Path) -> None:
    """Triangulate the current model's surfaces (edges at most :data:`STL_EDGE`) and write them
    as one binary STL."""
    gmsh.option.setNumber("Mesh.MeshSizeMin", 0.0)
    gmsh.option.setNumber("Mesh.MeshSizeMax", STL_EDGE)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    gmsh.option.setNumber("Mesh.Binary", 1)
    gmsh.option.setNumber("Mesh.StlOneSolidPerSurface", 0)
    gmsh.model.mesh.generate(2)
    gmsh.write(str(path))


def write(folder, hook: dict | None = None, housing: dict | None = None) -> tuple[Path, Path]:
    """Write ``hook.stl`` and ``housing.stl`` into ``folder`` (mm); ``hook`` and ``housing``
    override entries of :data:`HOOK` and :data:`HOUSING`. Returns the two paths."""
    import gmsh

    h, s = {**HOOK, **(hook or {})}, {**HOUSING, **(housing or {})}
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    t, b = h["thickness"], h["width"]
    xo = outer_face(h)
    initialized = gmsh.isInitialized()
    if not initialized:
        gmsh.initialize(["-noenv"], readConfigFiles=False)
    gmsh.option.setNumber("General.Terminal", 0)
    try:
        gmsh.model.add("hook")
        occ = gmsh.model.occ
        bx, by = xo + h["base_margin"], b / 2 + 2.5
        base = occ.addBox(-bx, -by, -h["base_thickness"], 2 * bx, 2 * by, h["base_thickness"])
        prongs = [
            _extruded(gmsh, prong_outline(-xo, -xo + t, h, -1), -b / 2, b),
            _extruded(gmsh, prong_outline(-t / 2, t / 2, h, 0), -b / 2, b),
            _extruded(gmsh, prong_outline(xo - t, xo, h, +1), -b / 2, b),
        ]
        occ.fuse([(3, base)], [(3, p) for p in prongs])
        occ.synchronize()
        hook_path = folder / "hook.stl"
        _write_stl(gmsh, hook_path)
        gmsh.model.remove()

        gmsh.model.add("housing")
        occ = gmsh.model.occ
        hx, hy = xo + s["clearance"], b / 2 + s["side_clearance"]
        px, py = hx + s["wall"], hy + s["wall"] + 1.5
        z0, T = h["length"] + s["start_gap"], s["thickness"]
        plate = occ.addBox(-px, -py, z0, 2 * px, 2 * py, T)
        hole = occ.addBox(-hx, -hy, z0 - 1.0, 2 * hx, 2 * hy, T + 2.0)
        occ.cut([(3, plate)], [(3, hole)])
        occ.synchronize()
        housing_path = folder / "housing.stl"
        _write_stl(gmsh, housing_path)
        gmsh.model.remove()
    finally:
        if not initialized:
            gmsh.finalize()
    return hook_path, housing_path


if __name__ == "__main__":
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).parent
    paths = write(out)
    print("wrote " + " and ".join(str(p) for p in paths))
