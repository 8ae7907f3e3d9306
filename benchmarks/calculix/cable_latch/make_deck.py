"""CalculiX deck for jsnap's `cable_latch` preset: mesh (gmsh) and .inp, independent of jsnap.

    python benchmarks/calculix/cable_latch/make_deck.py --mesh 2 --mu 0.3 --out /tmp/ccx_cable_latch

The flexible latch of a cable (LAN) plug: an arm hanging from a bridge at the top of the plug
body, a catch on its outer face; the jack's lip (a rigid block) comes down along the arm from its
root, pushes the catch in by the undercut and passes it. The section lies in the x-z plane and is
extruded over y. By symmetry only the half y >= 0 is modelled (uy = 0 on y = 0; the lip moves
along -z only, which respects the symmetry). Forces of the whole latch are twice the half's. The
plug body's back face x = -(GAP + T_BODY) is clamped.

Writes `mesh_m<level>.inp` (nodes, elements, sets, surfaces) and `<name>.inp` (material,
contact, step; includes the mesh). C3D8I hexahedra for the latch (incompatible modes, good in
bending); the rigid lip is meshed with C3D8 whose nodes all have prescribed displacements (a
rigid translation: its elements carry no strain, so the reaction on its nodes is the contact
force). Node-to-surface penalty contact (large sliding: re-paired in every iteration up to the 8th),
two pairs: the lip's bottom face and lower inner fillet (slave) against the catch's ramp; the
catch's land (slave, i.e. its two edges and the nodes between) against the lip's faces. The arm's
outer face (above and below the catch) is in no pair: it lies in the plane of the lip's inner face,
but the arm only moves away from it while the lip is on the catch, and after the snap it springs
back to that plane without load (zero clearance, zero force; run.py checks for overlap). Linear
geometry (no NLGEOM); static increments of lip travel.
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

# ---- named dimensions (mm), jsnap's cable_latch defaults ------------------------------------
L = 10.0  # arm length, from its free end (z = 0) up to its root (z = L)
H = 0.8  # arm thickness (x)
B = 3.2  # width (y)
CATCH_POS = 6.0  # from the root down to the catch's retention face
Y_U = 0.6  # undercut: the catch stands out of the arm's outer face (+x)
ALPHA = 30.0  # lead angle (deg, to the z axis)
FLAT = 0.3  # land length
GAP = 1.6  # between the arm's inner face x = 0 and the plug body
T_BODY = 3.0  # plug body thickness (x); its back face is clamped
T_BRIDGE = 2 * H  # bridge height over the gap, z in [L, L + T_BRIDGE]

# ---- rigid lip (the jack's) -----------------------------------------------------------------
LIP_T = 1.25 * Y_U  # lip thickness (x); its inner face in the plane of the arm's outer face
CLEARANCE = 0.02  # lip bottom above the catch's top at the start
LIP_H = 0.5  # lip height (z)
LIP_FILLET = 0.1  # edge radius (the x-z section's four corners)
LIP_OVERHANG = 0.5  # lip beyond the latch's width on each side in y
PASS = 0.3  # travel past the point where the lip's top reaches the retention face

# ---- material (ABS) and contact -------------------------------------------------------------
E_MOD = 2200.0  # MPa
NU = 0.35
PENALTY = 5.0e4  # N/mm^3, slope of the linear pressure-overclosure curve
SIGMA_INF = 0.02  # MPa, tension at large clearance (CalculiX's regularisation)
C0 = 0.1  # springs are generated up to a clearance of C0 * sqrt(slave node's area)
STICK_RATIO = 0.01  # stick slope = STICK_RATIO * PENALTY (N/mm^3), CalculiX's advice (1/100)
N_INC = 160  # nominal increments over the stroke; CalculiX may cut them, never enlarges them
LOAD_CHECK = 1.0  # N, lateral load (whole latch) of the stiffness check

# ---- derived geometry -----------------------------------------------------------------------
X_OUT = H  # arm outer face (the arm's inner face is x = 0)
X_LAND = H + Y_U  # catch land
Z_RET = L - CATCH_POS  # retention face (= 4.0)
Z_FLAT = Z_RET + FLAT  # land / ramp edge (= 4.3)
Z_TOP = Z_FLAT + Y_U / math.tan(math.radians(ALPHA))  # ramp meets the outer face (= 5.33923)
Z_BODY = L + T_BRIDGE  # top of the bridge and of the body (= 11.6)
X_BODY = -GAP  # body face towards the arm
X_BACK = -GAP - T_BODY  # body back face (clamped)
Z_LIP = Z_TOP + CLEARANCE  # lip bottom at the start
STROKE = CLEARANCE + (Z_TOP - Z_RET) + LIP_H + PASS  # lip top 0.3 mm below the retention face
DTRAVEL = STROKE / N_INC  # lip travel per nominal increment (mm)

# ---- mesh levels: size on the catch's contact faces (and the lip's inner side), distance over
# which it grows to the arm's bulk size, size at the root corners (the arm's (0, L) and (H, L),
# the body's (-GAP, L)), bulk size in the plug body, segments of each lip fillet, layers over
# y in [0, B/2]
LEVELS = {
    1: dict(fine=0.08, grow=0.6, bulk=0.2, root=0.05, body=0.4, fillet_seg=6, ny=3),
    2: dict(fine=0.04, grow=0.6, bulk=0.2, root=0.05, body=0.4, fillet_seg=8, ny=3),
    3: dict(fine=0.02, grow=0.6, bulk=0.2, root=0.05, body=0.4, fillet_seg=16, ny=3),
}


def latch_section(lv):
    """The latch's section (plug body + bridge + arm + catch), in (x, z), counter-clockwise.
    The outer face carries extra points at the root height z = L and the inner face at the
    retention face's height z = Z_RET (mesh nodes there for the monitors)."""
    pts = [
        (X_BACK, 0.0),
        (X_BODY, 0.0),
        (X_BODY, L),
        (0.0, L),
        (0.0, Z_RET),
        (0.0, 0.0),
        (X_OUT, 0.0),
        (X_OUT, Z_RET),
        (X_LAND, Z_RET),
        (X_LAND, Z_FLAT),
        (X_OUT, Z_TOP),
        (X_OUT, L),
        (X_OUT, Z_BODY),
        (X_BACK, Z_BODY),
    ]
    names = [
        "body_bottom",
        "body_face",  # towards the arm, across the gap
        "bridge_under",
        "inner_hi",
        "inner_lo",
        "arm_end",  # the latch's free end
        "outer_lo",  # below the catch
        "retention",
        "land",
        "ramp",
        "outer_hi",  # above the catch, up to the root height
        "outer_root",  # the bridge's outer face
        "top",
        "back",  # clamped
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
        roots = {"roots": [p[pts.index(q)] for q in ((0.0, L), (X_OUT, L), (X_BODY, L))]}
        return named, nseg, roots

    arm = ("inner_hi", "inner_lo", "outer_lo", "outer_hi", "outer_root", "arm_end")
    sizes = [
        (("ramp", "land", "retention"), fine, lv["grow"], lv["body"]),
        (("roots",), lv["root"], 1.0, lv["body"]),
        # the arm and the bridge at the bulk size, the plug body coarser away from them (the
        # sizes far from each refinement are the body's: the smallest of the three applies)
        (arm, lv["bulk"], 1.0, lv["body"]),
    ]
    return mesh_section(build, sizes)


def lip_section(lv):
    """The rigid lip's section x in [X_OUT, X_OUT + LIP_T] at its start position, in (x, z); its
    four corners rounded. The inner side x = X_OUT faces the arm."""
    r = LIP_FILLET
    x0, x1 = X_OUT, X_OUT + LIP_T
    z0, z1 = Z_LIP, Z_LIP + LIP_H
    fine = lv["fine"]

    def build(geo):
        p = {
            "a": geo.addPoint(x0 + r, z0, 0),
            "b": geo.addPoint(x1 - r, z0, 0),
            "cb": geo.addPoint(x1 - r, z0 + r, 0),
            "c": geo.addPoint(x1, z0 + r, 0),
            "d": geo.addPoint(x1, z1 - r, 0),
            "cd": geo.addPoint(x1 - r, z1 - r, 0),
            "e": geo.addPoint(x1 - r, z1, 0),
            "f": geo.addPoint(x0 + r, z1, 0),
            "cf": geo.addPoint(x0 + r, z1 - r, 0),
            "g": geo.addPoint(x0, z1 - r, 0),
            "h": geo.addPoint(x0, z0 + r, 0),
            "ch": geo.addPoint(x0 + r, z0 + r, 0),
        }
        c = {
            "bottom": geo.addLine(p["a"], p["b"]),
            "fillet_lo_out": geo.addCircleArc(p["b"], p["cb"], p["c"]),
            "outer": geo.addLine(p["c"], p["d"]),
            "fillet_hi_out": geo.addCircleArc(p["d"], p["cd"], p["e"]),
            "top": geo.addLine(p["e"], p["f"]),
            "fillet_hi": geo.addCircleArc(p["f"], p["cf"], p["g"]),
            "side": geo.addLine(p["g"], p["h"]),
            "fillet_lo": geo.addCircleArc(p["h"], p["ch"], p["a"]),
        }
        geo.addPlaneSurface([geo.addCurveLoop(list(c.values()))])
        nseg = {
            c["fillet_lo"]: lv["fillet_seg"],
            c["fillet_hi"]: lv["fillet_seg"],
            c["fillet_lo_out"]: 4,
            c["fillet_hi_out"]: 4,
            c["side"]: max(2, round((LIP_H - 2 * r) / fine)),
        }
        return {k: [v] for k, v in c.items()}, nseg, {}

    sizes = [(("fillet_lo", "side", "fillet_hi"), fine, 0.4, 0.1)]
    return mesh_section(build, sizes)


def write_mesh(lv, out, tag):
    """Write `mesh_<tag>.inp` for the mesh parameters `lv` (one of LEVELS)."""
    gmsh.initialize()
    gmsh.option.setNumber("General.Terminal", 0)
    try:
        cn, cq, ce = latch_section(lv)
        bn, bq, be = lip_section(lv)
    finally:
        gmsh.finalize()
    ys_latch = y_layers(lv["ny"], B / 2)
    ys_lip = np.append(ys_latch, B / 2 + LIP_OVERHANG)
    cxyz, cids, cconn, ceids, _ = extrude(cn, cq, ys_latch, 1, 1)
    bxyz, bids, bconn, beids, _ = extrude(bn, bq, ys_lip, len(cxyz) + 1, len(cconn) + 1)
    xyz = np.vstack([cxyz, bxyz])
    assert np.all(hex_volume_sign(lambda c: xyz[c - 1], cconn) > 0)
    assert np.all(hex_volume_sign(lambda c: xyz[c - 1], bconn) > 0)
    ncl, nbl = len(ys_latch) - 1, len(ys_lip) - 1
    tol = 1e-9

    fix = cids[np.abs(cxyz[:, 0] - X_BACK) < tol]
    symy = cids[(np.abs(cxyz[:, 1]) < tol) & (np.abs(cxyz[:, 0] - X_BACK) > tol)]

    def node_at(x, y, z):
        d = np.linalg.norm(cxyz - [x, y, z], axis=1)
        i = int(np.argmin(d))
        assert d[i] < 1e-9, (x, y, z)
        return int(cids[i])

    monitors = {
        "EDGE": node_at(X_LAND, 0.0, Z_RET),  # land / retention-face edge, mid-plane
        "LANDTOP": node_at(X_LAND, 0.0, Z_FLAT),  # ramp / land edge
        "INNER4": node_at(0.0, 0.0, Z_RET),  # arm's inner face at the retention face
        "OUTER4": node_at(X_OUT, 0.0, Z_RET),  # outer face at the same height
        "TIP": node_at(X_OUT, 0.0, 0.0),  # the arm's free end, outer corner
        "ROOTIN": node_at(0.0, 0.0, L),  # inner root corner
        "ROOTOUT": node_at(X_OUT, 0.0, L),  # outer face at the root height
    }

    catch_master = faces_on(ce["ramp"], cq, ncl, len(cq), 1)
    catch_slave = faces_on(ce["land"], cq, ncl, len(cq), 1)
    lip_master, lip_slave = [], []
    for n in ("bottom", "fillet_lo", "side", "fillet_hi", "top"):
        fs = faces_on(be[n], bq, nbl, len(bq), int(beids[0]))
        lip_master += fs
        # slave faces: those that meet the ramp, only within the latch's width (the last layer is
        # the overhang); the lip's inner side and upper fillet meet the catch's land edges: pair 2
        if n in ("bottom", "fillet_lo"):
            lip_slave += [f for f in fs if (f[0] - beids[0]) // len(bq) < ncl]

    land = np.unique([n for e in faces_on(ce["land"], cq, ncl, len(cq), 1) for n in face_nodes(cconn, e)])

    path = Path(out) / f"mesh_{tag}.inp"
    with open(path, "w") as f:
        f.write(f"** cable_latch half model, mesh {tag}: {lv}\n")
        f.write(f"** latch: {len(cconn)} C3D8I, lip: {len(bconn)} C3D8 (rigid, prescribed)\n")
        f.write("*NODE, NSET=NALL\n")
        for i, p in enumerate(xyz):
            f.write(f"{i + 1}, {p[0]:.9g}, {p[1]:.9g}, {p[2]:.9g}\n")
        for name, typ, conn, eids in (("LATCH", "C3D8I", cconn, ceids), ("LIP", "C3D8", bconn, beids)):
            f.write(f"*ELEMENT, TYPE={typ}, ELSET={name}\n")
            for e, c in zip(eids, conn, strict=True):
                f.write(f"{e}, " + ", ".join(str(int(v)) for v in c) + "\n")
        for name, ids in (("FIX", fix), ("SYMY", symy), ("LIPN", bids), ("LANDN", land)):
            f.write(f"*NSET, NSET={name}\n")
            write_ids(f, ids)
        f.write("*NSET, NSET=MON\n")
        write_ids(f, monitors.values())
        # the catch's ramp, land and retention face and the arm's outer face below it, at y = 0
        f.write("*NSET, NSET=PROF\n")
        prof = ("ramp", "land", "retention", "outer_lo")
        write_ids(f, sorted({1 + i for n in prof for e in ce[n] for i in e}))
        for name, n in monitors.items():
            f.write(f"*NSET, NSET={name}\n{n},\n")
        for name, faces in (
            ("CATCH_M", catch_master),
            ("CATCH_S", catch_slave),
            ("LIP_M", lip_master),
            ("LIP_S", lip_slave),
        ):
            f.write(f"*SURFACE, NAME={name}, TYPE=ELEMENT\n")
            for e, s in faces:
                f.write(f"{int(e)}, {s}\n")
    info = dict(
        latch_elements=len(cconn),
        latch_nodes=len(cxyz),
        lip_elements=len(bconn),
        nodes=len(xyz),
        land_nodes=len(land),
        monitors=monitors,
    )
    return path, info


def _head(tag, extra):
    return [
        f"** cable_latch half model (y >= 0), mesh {tag}; {extra}",
        f"*INCLUDE, INPUT=mesh_{tag}.inp",
        "*MATERIAL, NAME=ABS",
        "*ELASTIC",
        f"{E_MOD:g}, {NU:g}",
        "*SOLID SECTION, ELSET=LATCH, MATERIAL=ABS",
        "*SOLID SECTION, ELSET=LIP, MATERIAL=ABS",
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
        "LIP_S, CATCH_M",
        "*CONTACT PAIR, INTERACTION=SI, TYPE=NODE TO SURFACE",
        "CATCH_S, LIP_M",
        "*BOUNDARY",
        "FIX, 1, 3",
        "SYMY, 2, 2",
        "LIPN, 1, 2",
        "*STEP, INC=10000",
        "*STATIC",
        f"{dt:.8g}, 1.0, {dt * 1e-3:.8g}, {dt:.8g}",
        "*BOUNDARY",
        f"LIPN, 3, 3, {-STROKE:.8g}",
        "*NODE PRINT, NSET=LIPN, TOTALS=ONLY",
        "RF",
        "*NODE PRINT, NSET=FIX, TOTALS=ONLY",
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
    """Stiffness check without contact: a lateral force `force` on the whole latch (inwards, -x,
    as the lip pushes) spread evenly over the land's nodes of the half model (n_land of them); one
    linear solve."""
    lines = _head(tag, f"lateral load check, {force:g} N (whole latch) on the land")
    lines += [
        "*BOUNDARY",
        "FIX, 1, 3",
        "SYMY, 2, 2",
        "LIPN, 1, 3",
        "*STEP",
        "*STATIC",
        "*CLOAD",
        f"LANDN, 1, {-force / 2 / n_land:.10g}",
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
    ap.add_argument("--dtravel", type=float, default=DTRAVEL, help="lip travel per increment, mm")
    ap.add_argument("--name", default=None, help="deck name (default latch_m<level>_mu<mu>)")
    ap.add_argument("--load-check", action="store_true", help="the lateral-load stiffness deck instead")
    ap.add_argument("--out", default="/tmp/ccx_cable_latch", help="output folder")
    a = ap.parse_args()
    Path(a.out).mkdir(parents=True, exist_ok=True)
    tag = f"m{a.mesh}"
    mesh, info = write_mesh(LEVELS[a.mesh], a.out, tag)
    print(f"{mesh}: {info}")
    if a.load_check:
        deck = write_load_deck(a.name or f"load_{tag}", tag, a.out, info["land_nodes"])
    else:
        deck = write_deck(a.name or f"latch_{tag}_mu{a.mu:g}", tag, a.mu, a.penalty, a.out, a.dtravel)
    print(f"{deck}: stroke {STROKE:.4f} mm, catch top {Z_TOP:.4f} mm, lip bottom {Z_LIP:.4f} mm")


if __name__ == "__main__":
    main()
