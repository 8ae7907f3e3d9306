"""CalculiX deck for jsnap's `two_hook_clip` preset: mesh (gmsh) and .inp, independent of jsnap.

    python benchmarks/calculix/two_hook_clip/make_deck.py --mesh 2 --mu 0.3 --out /tmp/ccx_two_hook_clip

Two cantilever snap hooks facing each other on a base block; a rigid block is pressed down
between them. The section lies in the x-z plane and is extruded over y. By symmetry only the
quarter x >= 0, y >= 0 is modelled: ux = 0 on the base's x = 0 face, uy = 0 on y = 0 (the
block moves along -z only, which respects both symmetries). Forces of the full clip are four
times the quarter's.

Writes `mesh_m<level>.inp` (nodes, elements, sets, surfaces) and `<name>.inp` (material,
contact, step; includes the mesh). C3D8I hexahedra for the clip (incompatible modes, good in
bending); the rigid block is meshed with C3D8 whose nodes all have prescribed displacements (a
rigid translation: its elements carry no strain, so the reaction on its nodes is the contact
force). Node-to-surface penalty contact (large sliding: re-paired in every iteration up to the 8th),
two pairs: the block's bottom face and lower fillet (slave) against the hook's ramp; the hook's land
(slave, i.e. its two edges) against the block's faces. Linear geometry (no NLGEOM); static
increments of block travel.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import gmsh
import numpy as np

sys.path.append(str(Path(__file__).resolve().parents[1]))  # benchmarks/calculix: ccx_common
from ccx_common import extrude, face_nodes, faces_on, hex_volume_sign, mesh_section, write_ids, y_layers

# ---- named dimensions (mm), jsnap's two_hook_clip defaults ---------------------------------
L = 10.0  # arm length to the retention face
H = 1.2  # arm thickness (x)
B = 4.0  # width (y)
Y_U = 0.8  # undercut: hook protrusion towards x = 0
ALPHA = 30.0  # lead angle (deg, to the z axis)
FLAT = 0.1144  # land length
GAP = 4.0  # clear distance between the arms' inner faces
T_B = 2.0  # base thickness
MARGIN = 1.0  # base beyond the arms' outer faces

# ---- rigid block ----------------------------------------------------------------------------
CLEARANCE = 0.02  # block bottom above the hook top at the start
BLOCK_H = 0.5  # block height (z)
BLOCK_FILLET = 0.1  # edge radius (the x-z section's corners at x = +-GAP/2)
BLOCK_OVERHANG = 0.5  # block beyond the clip's width on each side in y
PASS = 0.3  # travel past the point where the block's top reaches the retention face

# ---- material (ABS) and contact -------------------------------------------------------------
E_MOD = 2200.0  # MPa
NU = 0.35
PENALTY = 5.0e4  # N/mm^3, slope of the linear pressure-overclosure curve
SIGMA_INF = 0.02  # MPa, tension at large clearance (CalculiX's regularisation)
C0 = 0.1  # springs are generated up to a clearance of C0 * sqrt(slave node's area)
STICK_RATIO = 0.01  # stick slope = STICK_RATIO * PENALTY (N/mm^3), CalculiX's advice (1/100)
DTRAVEL = 0.0145  # block travel per increment (mm); CalculiX may cut it, never raises it
LOAD_CHECK = 1.0  # N per hook, lateral load of the stiffness check

# ---- derived geometry -----------------------------------------------------------------------
X_IN = GAP / 2  # arm inner face
X_OUT = GAP / 2 + H  # arm outer face
X_TIP = X_IN - Y_U  # hook land
X_BASE = X_OUT + MARGIN  # base end
Z_TOP = L + FLAT + Y_U / math.tan(math.radians(ALPHA))  # hook top (= 11.5)
Z_BLOCK = Z_TOP + CLEARANCE  # block bottom at the start
STROKE = CLEARANCE + (Z_TOP - L) + BLOCK_H + PASS  # block top 0.3 mm below the retention face

# ---- mesh levels: size on the hook's contact faces (and the block's side), distance over which
# it grows to the bulk size, size at the arm's root corners, segments of each block fillet, layers
# over y in [0, B/2]
LEVELS = {
    1: dict(fine=0.08, grow=0.6, bulk=0.2, root=0.05, fillet_seg=6, ny=3),
    2: dict(fine=0.04, grow=0.6, bulk=0.2, root=0.05, fillet_seg=8, ny=3),
    3: dict(fine=0.02, grow=0.6, bulk=0.2, root=0.05, fillet_seg=16, ny=3),
}


def clip_section(lv):
    """The clip's half section x >= 0 (base + arm + hook), in (x, z)."""
    pts = [
        (0.0, -T_B),
        (X_BASE, -T_B),
        (X_BASE, 0.0),
        (X_OUT, 0.0),
        (X_OUT, L),
        (X_OUT, Z_TOP),
        (X_IN, Z_TOP),
        (X_TIP, L + FLAT),
        (X_TIP, L),
        (X_IN, L),
        (X_IN, 0.0),
        (0.0, 0.0),
    ]
    names = [
        "bottom",
        "base_end",
        "base_top_out",
        "outer_lo",
        "outer_hi",
        "top",
        "ramp",
        "land",
        "retention",
        "inner",
        "base_top_in",
        "symx",
    ]
    fine = lv["fine"]

    def build(geo):
        p = [geo.addPoint(x, z, 0) for x, z in pts]
        c = [geo.addLine(p[i], p[(i + 1) % len(p)]) for i in range(len(p))]
        geo.addPlaneSurface([geo.addCurveLoop(c)])
        named = {n: [t] for n, t in zip(names, c, strict=True)}
        nseg = {}
        for n in ("ramp", "land", "retention"):
            a, b = pts[names.index(n)], pts[(names.index(n) + 1) % len(pts)]
            nseg[named[n][0]] = max(2, round(math.dist(a, b) / fine))
        return named, nseg, {}

    sizes = [
        (("ramp", "land", "retention"), fine, lv["grow"], lv["bulk"]),
        (("base_top_out", "base_top_in"), lv["root"], 1.0, lv["bulk"]),
    ]
    return mesh_section(build, sizes)


def block_section(lv):
    """The rigid block's half section x in [0, GAP/2] at its start position, in (x, z)."""
    r = BLOCK_FILLET
    z0, z1 = Z_BLOCK, Z_BLOCK + BLOCK_H
    fine = lv["fine"]

    def build(geo):
        p = {
            "a": geo.addPoint(0.0, z0, 0),
            "b": geo.addPoint(X_IN - r, z0, 0),
            "cb": geo.addPoint(X_IN - r, z0 + r, 0),
            "c": geo.addPoint(X_IN, z0 + r, 0),
            "d": geo.addPoint(X_IN, z1 - r, 0),
            "cd": geo.addPoint(X_IN - r, z1 - r, 0),
            "e": geo.addPoint(X_IN - r, z1, 0),
            "f": geo.addPoint(0.0, z1, 0),
        }
        c = {
            "bottom": geo.addLine(p["a"], p["b"]),
            "fillet_lo": geo.addCircleArc(p["b"], p["cb"], p["c"]),
            "side": geo.addLine(p["c"], p["d"]),
            "fillet_hi": geo.addCircleArc(p["d"], p["cd"], p["e"]),
            "top": geo.addLine(p["e"], p["f"]),
            "symx": geo.addLine(p["f"], p["a"]),
        }
        geo.addPlaneSurface([geo.addCurveLoop(list(c.values()))])
        nseg = {
            c["fillet_lo"]: lv["fillet_seg"],
            c["fillet_hi"]: lv["fillet_seg"],
            c["side"]: max(2, round((BLOCK_H - 2 * r) / fine)),
        }
        return {k: [v] for k, v in c.items()}, nseg, {}

    sizes = [(("fillet_lo", "side", "fillet_hi"), fine, 0.6, 0.25)]
    return mesh_section(build, sizes)


def write_mesh(lv, out, tag):
    """Write `mesh_<tag>.inp` for the mesh parameters `lv` (one of LEVELS)."""
    gmsh.initialize()
    gmsh.option.setNumber("General.Terminal", 0)
    try:
        cn, cq, ce = clip_section(lv)
        bn, bq, be = block_section(lv)
    finally:
        gmsh.finalize()
    ys_clip = y_layers(lv["ny"], B / 2)
    ys_block = np.append(ys_clip, B / 2 + BLOCK_OVERHANG)
    cxyz, cids, cconn, ceids, _ = extrude(cn, cq, ys_clip, 1, 1)
    bxyz, bids, bconn, beids, _ = extrude(bn, bq, ys_block, len(cxyz) + 1, len(cconn) + 1)
    xyz = np.vstack([cxyz, bxyz])
    assert np.all(hex_volume_sign(lambda c: xyz[c - 1], cconn) > 0)
    assert np.all(hex_volume_sign(lambda c: xyz[c - 1], bconn) > 0)
    ncl, nbl = len(ys_clip) - 1, len(ys_block) - 1
    tol = 1e-9

    def cset(mask):
        return cids[mask(cxyz)]

    fix = cset(lambda p: np.abs(p[:, 2] + T_B) < tol)
    symx = cset(lambda p: (np.abs(p[:, 0]) < tol) & (np.abs(p[:, 2] + T_B) > tol))
    symy = cset(lambda p: (np.abs(p[:, 1]) < tol) & (np.abs(p[:, 2] + T_B) > tol))

    def node_at(x, y, z):
        d = np.linalg.norm(cxyz - [x, y, z], axis=1)
        i = int(np.argmin(d))
        assert d[i] < 1e-9, (x, y, z)
        return int(cids[i])

    monitors = {
        "EDGE": node_at(X_TIP, 0.0, L),  # land / retention-face edge, mid-plane
        "LANDTOP": node_at(X_TIP, 0.0, L + FLAT),  # ramp / land edge
        "INNER10": node_at(X_IN, 0.0, L),  # inner face at the retention face
        "OUTER10": node_at(X_OUT, 0.0, L),  # outer face at the same height
        "TIP": node_at(X_OUT, 0.0, Z_TOP),  # outer top corner
        "ROOTIN": node_at(X_IN, 0.0, 0.0),  # inner root corner
    }

    hook_master = faces_on(ce["ramp"], cq, ncl, len(cq), 1)
    hook_slave = faces_on(ce["land"], cq, ncl, len(cq), 1)
    block_master, block_slave = [], []
    for n in ("bottom", "fillet_lo", "side", "fillet_hi", "top"):
        fs = faces_on(be[n], bq, nbl, len(bq), int(beids[0]))
        block_master += fs
        # slave faces: those that meet the ramp, only within the clip's width (the last layer is
        # the overhang); the block's side and top fillet meet the hook's land edges: pair 2
        if n in ("bottom", "fillet_lo"):
            block_slave += [f for f in fs if (f[0] - beids[0]) // len(bq) < ncl]

    land = np.unique([n for e in faces_on(ce["land"], cq, ncl, len(cq), 1) for n in face_nodes(cconn, e)])

    path = Path(out) / f"mesh_{tag}.inp"
    with open(path, "w") as f:
        f.write(f"** two_hook_clip quarter model, mesh {tag}: {lv}\n")
        f.write(f"** clip: {len(cconn)} C3D8I, block: {len(bconn)} C3D8 (rigid, prescribed)\n")
        f.write("*NODE, NSET=NALL\n")
        for i, p in enumerate(xyz):
            f.write(f"{i + 1}, {p[0]:.9g}, {p[1]:.9g}, {p[2]:.9g}\n")
        for name, typ, conn, eids in (("CLIP", "C3D8I", cconn, ceids), ("BLOCK", "C3D8", bconn, beids)):
            f.write(f"*ELEMENT, TYPE={typ}, ELSET={name}\n")
            for e, c in zip(eids, conn, strict=True):
                f.write(f"{e}, " + ", ".join(str(int(v)) for v in c) + "\n")
        for name, ids in (("FIX", fix), ("SYMX", symx), ("SYMY", symy), ("BLOCKN", bids), ("LANDN", land)):
            f.write(f"*NSET, NSET={name}\n")
            write_ids(f, ids)
        f.write("*NSET, NSET=MON\n")
        write_ids(f, monitors.values())
        f.write("*NSET, NSET=PROF\n")  # the hook's ramp, land and retention face at y = 0
        write_ids(f, sorted({1 + i for n in ("ramp", "land", "retention") for e in ce[n] for i in e}))
        for name, n in monitors.items():
            f.write(f"*NSET, NSET={name}\n{n},\n")
        for name, faces in (
            ("HOOK_M", hook_master),
            ("HOOK_S", hook_slave),
            ("BLOCK_M", block_master),
            ("BLOCK_S", block_slave),
        ):
            f.write(f"*SURFACE, NAME={name}, TYPE=ELEMENT\n")
            for e, s in faces:
                f.write(f"{int(e)}, {s}\n")
    info = dict(
        clip_elements=len(cconn),
        clip_nodes=len(cxyz),
        block_elements=len(bconn),
        nodes=len(xyz),
        land_nodes=len(land),
        monitors=monitors,
    )
    return path, info


def _head(tag, extra):
    return [
        f"** two_hook_clip quarter model (x >= 0, y >= 0), mesh {tag}; {extra}",
        f"*INCLUDE, INPUT=mesh_{tag}.inp",
        "*MATERIAL, NAME=ABS",
        "*ELASTIC",
        f"{E_MOD:g}, {NU:g}",
        "*SOLID SECTION, ELSET=CLIP, MATERIAL=ABS",
        "*SOLID SECTION, ELSET=BLOCK, MATERIAL=ABS",
    ]


def write_deck(name, tag, mu, penalty, out, dtravel):
    """The insertion deck `<name>.inp`, including mesh_<tag>.inp (written next to it)."""
    dt = dtravel / STROKE
    lines = _head(tag, f"mu = {mu:g}, penalty {penalty:g} N/mm^3, {dtravel:g} mm per increment")
    lines += [
        "*SURFACE INTERACTION, NAME=SI",
        "*SURFACE BEHAVIOR, PRESSURE-OVERCLOSURE=LINEAR",
        f"{penalty:g}, {SIGMA_INF:g}, {C0:g}",
    ]
    if mu > 0:
        lines += ["*FRICTION", f"{mu:g}, {STICK_RATIO * penalty:g}"]
    lines += [
        "*CONTACT PAIR, INTERACTION=SI, TYPE=NODE TO SURFACE",
        "BLOCK_S, HOOK_M",
        "*CONTACT PAIR, INTERACTION=SI, TYPE=NODE TO SURFACE",
        "HOOK_S, BLOCK_M",
        "*BOUNDARY",
        "FIX, 1, 3",
        "SYMX, 1, 1",
        "SYMY, 2, 2",
        "BLOCKN, 1, 2",
        "*STEP, INC=10000",
        "*STATIC",
        f"{dt:.8g}, 1.0, {dt * 1e-3:.8g}, {dt:.8g}",
        "*BOUNDARY",
        f"BLOCKN, 3, 3, {-STROKE:.8g}",
        "*NODE PRINT, NSET=BLOCKN, TOTALS=ONLY",
        "RF",
        "*NODE PRINT, NSET=FIX, TOTALS=ONLY",
        "RF",
        "*NODE PRINT, NSET=SYMX, TOTALS=ONLY",
        "RF",
        "*NODE PRINT, NSET=MON",
        "U",
        "*NODE PRINT, NSET=PROF",
        "U",
        "*NODE FILE, NSET=SYMY",
        "U",
        "*END STEP",
    ]
    path = Path(out) / f"{name}.inp"
    path.write_text("\n".join(lines) + "\n")
    return path


def write_load_deck(name, tag, out, n_land, force=LOAD_CHECK):
    """Stiffness check without contact: a lateral force `force` per hook (outwards, +x) spread
    evenly over the land's nodes of the quarter model (n_land of them); one linear solve."""
    lines = _head(tag, f"lateral load check, {force:g} N per hook on the land")
    lines += [
        "*BOUNDARY",
        "FIX, 1, 3",
        "SYMX, 1, 1",
        "SYMY, 2, 2",
        "BLOCKN, 1, 3",
        "*STEP",
        "*STATIC",
        "*CLOAD",
        f"LANDN, 1, {force / 2 / n_land:.10g}",
        "*NODE PRINT, NSET=MON",
        "U",
        "*NODE PRINT, NSET=FIX, TOTALS=ONLY",
        "RF",
        "*END STEP",
    ]
    path = Path(out) / f"{name}.inp"
    path.write_text("\n".join(lines) + "\n")
    return path


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mesh", type=int, default=2, choices=sorted(LEVELS), help="refinement level")
    ap.add_argument("--mu", type=float, default=0.0, help="friction coefficient")
    ap.add_argument("--penalty", type=float, default=PENALTY, help="contact slope, N/mm^3")
    ap.add_argument("--dtravel", type=float, default=DTRAVEL, help="block travel per increment, mm")
    ap.add_argument("--name", default=None, help="deck name (default clip_m<level>_mu<mu>)")
    ap.add_argument("--load-check", action="store_true", help="the lateral-load stiffness deck instead")
    ap.add_argument("--out", default="/tmp/ccx_two_hook_clip", help="output folder")
    a = ap.parse_args()
    Path(a.out).mkdir(parents=True, exist_ok=True)
    tag = f"m{a.mesh}"
    mesh, info = write_mesh(LEVELS[a.mesh], a.out, tag)
    print(f"{mesh}: {info}")
    if a.load_check:
        deck = write_load_deck(a.name or f"load_{tag}", tag, a.out, info["land_nodes"])
    else:
        deck = write_deck(a.name or f"clip_{tag}_mu{a.mu:g}", tag, a.mu, a.penalty, a.out, a.dtravel)
    print(f"{deck}: stroke {STROKE:.4f} mm, z_top {Z_TOP:.4f} mm")


if __name__ == "__main__":
    main()
