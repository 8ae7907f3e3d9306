"""CalculiX deck for jsnap's `box_lid` preset: mesh (gmsh) and .inp, independent of jsnap.

    python benchmarks/calculix/box_lid/make_deck.py --mesh 2 --mu 0.3 --out /tmp/ccx_box_lid
    python benchmarks/calculix/box_lid/make_deck.py --mesh 1 --tilt 3 --out /tmp/ccx_box_lid

A lid (the deformable part) with four snap hooks, held flat underneath, and the box's rim (a
rigid block) pressed down between the hooks. The lid plate x in [-X, X], y in [-Y, Y],
z in [-T, 0]; its bottom face z = -T is clamped. Each hook is the two_hook_clip's arm section
(x in [a, a + h], a = gap / 2, the hook protruding inwards to a - y_u) standing on the plate's top
face, b wide in y and centred at y = +-spacing / 2; the left pair is the right pair mirrored about
x = 0. The section (x, z) of plate + right arm is meshed with quadrilaterals and extruded over y
into hexahedra; where there is no hook (|y| < spacing / 2 - b / 2 and beyond its outer edge) only
the plate's quadrilaterals are extruded (one conforming section mesh everywhere).

Two models:

- untilted (tilt 0): the quarter x >= 0, y >= 0, with ux = 0 on the plate's x = 0 face and
  uy = 0 on its y = 0 face; it holds ONE whole hook (y in [2, 6]) and a quarter of the plate. The
  block moves along -z only, which respects both symmetries. Forces of the whole lid are four
  times the quarter's (the lateral force of one hook is the quarter's own);
- tilted (tilt > 0): the box turned by `tilt` about the x axis through its centre (right-handed:
  its -y end lower, so the hooks at -y engage first), moved straight along -z. The y symmetry is
  gone, the x symmetry stays: the half x >= 0 with both right hooks (y = -4 and y = +4), ux = 0
  on x = 0. Forces of the whole lid are twice the half's.

Writes `mesh_<tag>.inp` (nodes, elements, sets, surfaces) and `<name>.inp` (material, contact,
step; includes the mesh). C3D8I hexahedra for the lid (incompatible modes, good in bending); the
rigid block is meshed with C3D8 whose nodes all have prescribed displacements (a rigid
translation: no strain, so the reaction on its nodes is the contact force). Node-to-surface
penalty contact as in the two_hook_clip reference: the block's bottom face and lower fillet
(slave, within the hooks' widths) against the hooks' ramps; the hooks' lands (slave, their two
edges) against the block's faces. Linear geometry (no NLGEOM); static increments of block travel.
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

# ---- named dimensions (mm), jsnap's box_lid defaults ----------------------------------------
L = 10.0  # arm length to the retention face
H = 1.2  # arm thickness (x)
B = 4.0  # hook width (y)
Y_U = 0.8  # undercut: hook protrusion towards x = 0
ALPHA = 30.0  # lead angle (deg, to the z axis)
FLAT = 0.1144  # land length
GAP = 8.0  # clear distance between the arms' inner faces (x)
SPACING = 8.0  # distance between the hooks' centres along y
T_LID = 1.5  # lid plate thickness
MARGIN = 1.0  # plate beyond the arms' outer faces (x) and the hooks' outer edges (y)

# ---- the box's rim: a rigid rounded block ----------------------------------------------------
CLEARANCE = 0.02  # its lowest point above the hooks' tops at the start
BOX_H = 0.5  # height (z)
BOX_FILLET = 0.1  # edge radius
BOX_OVERHANG = 0.5  # beyond the hooks' outer edges in y (depth 2 * 6.5 = 13)
PASS = 0.3  # its top ends this far below the retention faces (at the far hooks' far edge)
TILT = 3.0  # deg, the tilted run's rotation about the x axis
# tilted box only: its rows of nodes over the hooks' edges (y = +-2, +-6) lie this far inside the
# hooks' width (mm), its bottom face's nodes there. A first try had the bottom face's nodes on the
# edges (the lower fillet's, turned by the tilt, within 0.003 mm of them): ccx cut its increments
# when the tilted contact line reached the -y hooks' last edge (y = -2) and gave up when it
# reached the +y hooks' (y = 6), at 0.65 mm of travel. With the inset it passed both.
EDGE_INSET = 0.02

# ---- material (ABS) and contact (as the two_hook_clip reference) -------------------------------
E_MOD = 2200.0  # MPa
NU = 0.35
PENALTY = 5.0e4  # N/mm^3, slope of the linear pressure-overclosure curve
SIGMA_INF = 0.02  # MPa, tension at large clearance (CalculiX's regularisation)
C0 = 0.1  # springs are generated up to a clearance of C0 * sqrt(slave node's area)
STICK_RATIO = 0.01  # stick slope = STICK_RATIO * PENALTY (N/mm^3), CalculiX's advice (1/100)
DTRAVEL = 0.0145  # block travel per increment (mm); CalculiX may cut it, never raises it

# ---- derived geometry -----------------------------------------------------------------------
X_IN = GAP / 2  # arm inner face (4.0)
X_OUT = X_IN + H  # arm outer face (5.2)
X_TIP = X_IN - Y_U  # hook land (3.2)
X_LID = X_OUT + MARGIN  # plate end (6.2)
Y_LO = SPACING / 2 - B / 2  # hook's inner edge (2.0)
Y_HI = SPACING / 2 + B / 2  # hook's outer edge (6.0)
Y_MID = SPACING / 2  # hook's centre (4.0)
Y_LID = Y_HI + MARGIN  # plate end (7.0)
Y_BOX = Y_HI + BOX_OVERHANG  # box half depth (6.5)
Z_TOP = L + FLAT + Y_U / math.tan(math.radians(ALPHA))  # hook top (= 11.5)


def box_start(tilt):
    """z of the box's centre at the start: its lowest point (on the -y bottom edge's fillet when
    tilted) CLEARANCE above the hooks' tops."""
    c, s = math.cos(math.radians(tilt)), math.sin(math.radians(tilt))
    below = (BOX_H / 2 - BOX_FILLET) * c + (Y_BOX - BOX_FILLET) * s + BOX_FILLET
    return Z_TOP + CLEARANCE + below


def stroke(tilt):
    """Block travel: its top passes PASS below the retention faces at y = Y_HI (the far edge of
    the hooks it reaches last; every hook for tilt 0)."""
    c, s = math.cos(math.radians(tilt)), math.sin(math.radians(tilt))
    along = (Y_HI + BOX_H / 2 * s) / c  # the top face's point over y = Y_HI, in the box's frame
    return box_start(tilt) + along * s + BOX_H / 2 * c - (L - PASS)


def to_world(p, tilt):
    """Points (n, 3) of the box's own frame (centre at the origin) at their start position."""
    c, s = math.cos(math.radians(tilt)), math.sin(math.radians(tilt))
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    return np.column_stack([x, c * y - s * z, s * y + c * z + box_start(tilt)])


def to_box(p, tilt, travel):
    """Points (n, 3) of the world in the box's own frame after `travel` along -z."""
    c, s = math.cos(math.radians(tilt)), math.sin(math.radians(tilt))
    x, y, z = p[:, 0], p[:, 1], p[:, 2] - box_start(tilt) + travel
    return np.column_stack([x, c * y + s * z, -s * y + c * z])


# ---- mesh levels: size on the hooks' contact faces (and the block's side), the distance over
# which it grows to the arm's size, the arm's size, size at the arm's root corners, the plate's
# size away from the arm, segments of each block fillet, layers over the hook's half width, over
# the plate between the hooks (y in [0, Y_LO]) and beyond them
LEVELS = {
    1: dict(fine=0.08, grow=0.6, bulk=0.2, root=0.05, lid=0.5, fillet_seg=6, ny=3, ny_in=2, ny_out=1),
    2: dict(fine=0.04, grow=0.6, bulk=0.2, root=0.05, lid=0.5, fillet_seg=8, ny=3, ny_in=2, ny_out=1),
    3: dict(fine=0.02, grow=0.6, bulk=0.2, root=0.05, lid=0.5, fillet_seg=16, ny=3, ny_in=2, ny_out=1),
}
ROOT_GROW = 1.0  # the root size grows to the arm's size over this distance (as the clip's)
ARM_GROW = 3.0  # the arm's size grows to the plate's over this distance from the arm's faces


def _reach(s_near, s_far, d_bulk, s_bulk):
    """Distance at which a size growing linearly from s_near (at distance s_near) through s_bulk
    (at d_bulk) reaches s_far: the growth of the clip's mesh, continued up to the plate's size."""
    return s_near + (s_far - s_near) * (d_bulk - s_near) / (s_bulk - s_near)


def lid_section(lv):
    """The lid's section x >= 0 (plate + right arm + hook), in (x, z): two surfaces, the plate
    and the arm, sharing the arm's root line z = 0, x in [X_IN, X_OUT]."""
    plate = [(0.0, -T_LID), (X_LID, -T_LID), (X_LID, 0.0), (X_OUT, 0.0), (X_IN, 0.0), (0.0, 0.0)]
    plate_names = ["bottom", "plate_end", "plate_top_out", "root", "plate_top_in", "symx"]
    arm = [(X_OUT, 0.0), (X_OUT, L), (X_OUT, Z_TOP), (X_IN, Z_TOP), (X_TIP, L + FLAT), (X_TIP, L), (X_IN, L)]
    arm_names = ["outer_lo", "outer_hi", "top", "ramp", "land", "retention", "inner"]  # + root, back
    fine = lv["fine"]

    def build(geo):
        pp = [geo.addPoint(x, z, 0) for x, z in plate]
        pc = [geo.addLine(pp[i], pp[(i + 1) % len(pp)]) for i in range(len(pp))]
        ap = [pp[3]] + [geo.addPoint(x, z, 0) for x, z in arm[1:]] + [pp[4]]
        ac = [geo.addLine(ap[i], ap[i + 1]) for i in range(len(arm))]
        geo.addPlaneSurface([geo.addCurveLoop(pc)])
        geo.addPlaneSurface([geo.addCurveLoop([*ac, -pc[3]])])
        named = {n: [t] for n, t in zip(plate_names + arm_names, pc + ac, strict=True)}
        nseg = {}
        for i, n in enumerate(arm_names):
            if n in ("ramp", "land", "retention"):
                a, b = arm[i], arm[i + 1]
                nseg[named[n][0]] = max(2, round(math.dist(a, b) / fine))
        return named, nseg, {"roots": [pp[3], pp[4]]}

    s_lid = lv["lid"]
    sizes = [
        (("ramp", "land", "retention"), fine, _reach(fine, s_lid, lv["grow"], lv["bulk"]), s_lid),
        (("inner", "outer_lo", "outer_hi", "top"), lv["bulk"], ARM_GROW, s_lid),
        (("roots",), lv["root"], _reach(lv["root"], s_lid, ROOT_GROW, lv["bulk"]), s_lid),
    ]
    return mesh_section(build, sizes)


def box_section(lv):
    """The block's half section x in [0, GAP / 2] in its own frame (centre at the origin), (x, z)."""
    r, hz = BOX_FILLET, BOX_H / 2
    fine = lv["fine"]

    def build(geo):
        p = {
            "a": geo.addPoint(0.0, -hz, 0),
            "b": geo.addPoint(X_IN - r, -hz, 0),
            "cb": geo.addPoint(X_IN - r, -hz + r, 0),
            "c": geo.addPoint(X_IN, -hz + r, 0),
            "d": geo.addPoint(X_IN, hz - r, 0),
            "cd": geo.addPoint(X_IN - r, hz - r, 0),
            "e": geo.addPoint(X_IN - r, hz, 0),
            "f": geo.addPoint(0.0, hz, 0),
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
            c["side"]: max(2, round((BOX_H - 2 * r) / fine)),
        }
        return {k: [v] for k, v in c.items()}, nseg, {}

    sizes = [(("fillet_lo", "side", "fillet_hi"), fine, 0.6, 0.25)]
    return mesh_section(build, sizes)


def lid_levels(lv, half):
    """y levels of the lid's extrusion and, per layer, whether it holds a hook (y in [Y_LO, Y_HI]).
    The quarter's: y in [0, Y_LID]; the half's: its mirror image about y = 0 added."""
    edge = y_layers(lv["ny"], B / 2)  # graded towards the hook's edges
    hook = np.concatenate([Y_MID - edge[::-1], Y_MID + edge[1:]])
    inner = y_layers(lv["ny_in"], Y_LO)  # graded towards the hook
    outer = np.sort(Y_LID - y_layers(lv["ny_out"], MARGIN))  # graded towards the hook
    ys = np.concatenate([inner, hook[1:], outer[1:]])
    has_hook = (ys[:-1] >= Y_LO - 1e-9) & (ys[1:] <= Y_HI + 1e-9)
    if half:
        ys = np.concatenate([-ys[::-1], ys[1:]])
        has_hook = np.concatenate([has_hook[::-1], has_hook])
    return ys, has_hook


def box_levels(ys_lid, has_hook, tilt):
    """The block's y levels in its own frame and, per layer, whether it lies over a hook: the
    lid's hook levels (so that, once turned by `tilt`, its bottom face's nodes lie over them),
    BOX_OVERHANG beyond the hooks' edges on either side."""
    hook_levels = np.unique(np.concatenate([ys_lid[:-1][has_hook], ys_lid[1:][has_hook]]))
    extra = [Y_HI + BOX_OVERHANG, Y_LO - BOX_OVERHANG]
    if hook_levels.min() < 0:
        extra += [-v for v in extra]
    world = np.unique(np.concatenate([hook_levels, extra]))
    c, sn = math.cos(math.radians(tilt)), math.sin(math.radians(tilt))
    inset = world.copy()
    if tilt != 0.0:  # the rows over the hooks' edges EDGE_INSET inside them (see EDGE_INSET)
        for e in (Y_LO, Y_HI):
            for sgn in (1.0, -1.0):
                at = np.isclose(world, sgn * e)
                inset[at] -= sgn * EDGE_INSET * (1.0 if e == Y_HI else -1.0)
    ys = (inset - BOX_H / 2 * sn) / c  # bottom face (z = -BOX_H / 2) over the world level
    ys[np.isclose(world, Y_BOX)] = Y_BOX  # the box's ends where they are
    ys[np.isclose(world, -Y_BOX)] = -Y_BOX
    mid = 0.5 * (world[:-1] + world[1:])
    over = np.array([np.any((m > ys_lid[:-1][has_hook]) & (m < ys_lid[1:][has_hook])) for m in mid])
    return ys, over


def write_mesh(lv, out, tag, tilt=0.0):
    """Write `mesh_<tag>.inp` for the mesh parameters `lv` (one of LEVELS): the quarter model
    for tilt 0, else the half model with the block turned by `tilt` degrees."""
    half = tilt != 0.0
    gmsh.initialize()
    gmsh.option.setNumber("General.Terminal", 0)
    try:
        cn, cq, ce = lid_section(lv)
        bn, bq, be = box_section(lv)
    finally:
        gmsh.finalize()
    nq = len(cq)
    is_plate = cn[cq].mean(axis=1)[:, 1] < 0.0
    ys_lid, has_hook = lid_levels(lv, half)
    nl = len(ys_lid) - 1
    # the full extrusion, then only the plate's hexahedra in the layers without a hook
    fxyz, _, fconn, _, _ = extrude(cn, cq, ys_lid, 1, 1)
    layer, quad = np.divmod(np.arange(nl * nq), nq)
    keep = has_hook[layer] | is_plate[quad]
    new_elem = np.zeros(len(keep) + 1, int)  # old element id -> new (0: dropped)
    new_elem[1:][keep] = np.arange(1, keep.sum() + 1)
    used = np.unique(fconn[keep])
    new_node = np.zeros(len(fxyz) + 1, int)
    new_node[used] = np.arange(1, len(used) + 1)
    cxyz = fxyz[used - 1]
    cids = np.arange(1, len(cxyz) + 1)
    cconn = new_node[fconn[keep]]
    ceids = np.arange(1, len(cconn) + 1)

    def lid_faces(name):
        return [(int(new_elem[e]), s) for e, s in faces_on(ce[name], cq, nl, nq, 1) if new_elem[e]]

    ys_box, over = box_levels(ys_lid, has_hook, tilt)
    bxyz, bids, bconn, beids, _ = extrude(bn, bq, ys_box, len(cxyz) + 1, len(cconn) + 1)
    bxyz = to_world(bxyz, tilt)
    xyz = np.vstack([cxyz, bxyz])
    assert np.all(hex_volume_sign(lambda c: xyz[c - 1], cconn) > 0)
    assert np.all(hex_volume_sign(lambda c: xyz[c - 1], bconn) > 0)
    nbl = len(ys_box) - 1
    tol = 1e-9

    def cset(mask):
        return cids[mask(cxyz)]

    fix = cset(lambda p: np.abs(p[:, 2] + T_LID) < tol)
    symx = cset(lambda p: (np.abs(p[:, 0]) < tol) & (np.abs(p[:, 2] + T_LID) > tol))
    symy = cset(lambda p: (np.abs(p[:, 1]) < tol) & (np.abs(p[:, 2] + T_LID) > tol))

    def node_at(x, y, z):
        d = np.linalg.norm(cxyz - [x, y, z], axis=1)
        i = int(np.argmin(d))
        assert d[i] < 1e-9, (x, y, z)
        return int(cids[i])

    hooks = {"M": -Y_MID, "P": Y_MID} if half else {"": Y_MID}
    monitors = {}
    for k, y in hooks.items():
        monitors |= {
            f"EDGE{k}": node_at(X_TIP, y, L),  # land / retention-face edge, mid-width
            f"LANDTOP{k}": node_at(X_TIP, y, L + FLAT),  # ramp / land edge
            f"INNER10{k}": node_at(X_IN, y, L),  # inner face at the retention face
            f"OUTER10{k}": node_at(X_OUT, y, L),  # outer face at the same height
            f"TIP{k}": node_at(X_OUT, y, Z_TOP),  # outer top corner
            f"ROOTIN{k}": node_at(X_IN, y, 0.0),  # inner root corner
        }
    prof = {}  # the hook's ramp, land and retention face at its mid-width
    for k, y in hooks.items():
        sec = {i for n in ("ramp", "land", "retention") for e in ce[n] for i in e}
        prof[f"PROF{k}"] = sorted(node_at(cn[i, 0], y, cn[i, 1]) for i in sec)

    hook_master = lid_faces("ramp")
    hook_slave = lid_faces("land")
    land = np.unique([n for e in hook_slave for n in face_nodes(cconn, e)])
    block_master, block_slave = [], []
    for n in ("bottom", "fillet_lo", "side", "fillet_hi", "top"):
        fs = faces_on(be[n], bq, nbl, len(bq), int(beids[0]))
        block_master += fs
        # slave faces: those that meet the ramps, only over the hooks' widths; the block's side
        # and top fillet meet the hooks' land edges: pair 2
        if n in ("bottom", "fillet_lo"):
            block_slave += [f for f in fs if over[(f[0] - beids[0]) // len(bq)]]
    bconn_of = np.zeros((int(beids[-1]), 8), int)
    bconn_of[beids - 1] = bconn
    block_surf = np.unique([n for e in block_master for n in face_nodes(bconn_of, e)])

    sets = {"FIX": fix, "SYMX": symx}
    if not half:
        sets["SYMY"] = symy
    sets |= {"BLOCKN": bids, "BLOCKC": block_surf, "LANDN": land}
    if half:
        sets |= {"BLOCKNM": bids[bxyz[:, 1] < 0], "BLOCKNP": bids[bxyz[:, 1] > 0]}
    model = f"half model (x >= 0), box tilted {tilt:g} deg" if half else "quarter model (x >= 0, y >= 0)"
    path = Path(out) / f"mesh_{tag}.inp"
    with open(path, "w") as f:
        f.write(f"** box_lid {model}, mesh {tag}: {lv}\n")
        f.write(f"** lid: {len(cconn)} C3D8I, block: {len(bconn)} C3D8 (rigid, prescribed)\n")
        f.write("*NODE, NSET=NALL\n")
        for i, p in enumerate(xyz):
            f.write(f"{i + 1}, {p[0]:.9g}, {p[1]:.9g}, {p[2]:.9g}\n")
        for name, typ, conn, eids in (("LID", "C3D8I", cconn, ceids), ("BLOCK", "C3D8", bconn, beids)):
            f.write(f"*ELEMENT, TYPE={typ}, ELSET={name}\n")
            for e, c in zip(eids, conn, strict=True):
                f.write(f"{e}, " + ", ".join(str(int(v)) for v in c) + "\n")
        for name, ids in sets.items():
            f.write(f"*NSET, NSET={name}\n")
            write_ids(f, ids)
        f.write("*NSET, NSET=MON\n")
        write_ids(f, monitors.values())
        for name, ids in prof.items():
            f.write(f"*NSET, NSET={name}\n")
            write_ids(f, ids)
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
        lid_elements=len(cconn),
        lid_nodes=len(cxyz),
        section_quads=nq,
        block_elements=len(bconn),
        nodes=len(xyz),
        land_nodes=len(land),
        monitors=monitors,
    )
    return path, info


def write_deck(name, tag, mu, penalty, out, dtravel, tilt=0.0):
    """The insertion deck `<name>.inp`, including mesh_<tag>.inp (written next to it)."""
    half = tilt != 0.0
    s = stroke(tilt)
    dt = dtravel / s
    model = f"half model (x >= 0), box tilted {tilt:g} deg" if half else "quarter model (x >= 0, y >= 0)"
    lines = [
        f"** box_lid {model}, mesh {tag}; mu = {mu:g}, penalty {penalty:g} N/mm^3, "
        f"{dtravel:g} mm per increment, stroke {s:.6g} mm",
        f"*INCLUDE, INPUT=mesh_{tag}.inp",
        "*MATERIAL, NAME=ABS",
        "*ELASTIC",
        f"{E_MOD:g}, {NU:g}",
        "*SOLID SECTION, ELSET=LID, MATERIAL=ABS",
        "*SOLID SECTION, ELSET=BLOCK, MATERIAL=ABS",
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
    ]
    if not half:
        lines += ["SYMY, 2, 2"]
    lines += [
        "BLOCKN, 1, 2",
        "*STEP, INC=10000",
        "*STATIC",
        f"{dt:.8g}, 1.0, {dt * 1e-3:.8g}, {dt:.8g}",
        "*BOUNDARY",
        f"BLOCKN, 3, 3, {-s:.8g}",
        "*NODE PRINT, NSET=BLOCKN, TOTALS=ONLY",
        "RF",
        "*NODE PRINT, NSET=SYMX, TOTALS=ONLY",
        "RF",
    ]
    if half:  # per node: the base's moment and the block's (equilibrium check); per hook pair
        lines += [
            "*NODE PRINT, NSET=FIX, TOTALS=YES",
            "RF",
            "*NODE PRINT, NSET=BLOCKC",
            "RF",
            "*NODE PRINT, NSET=BLOCKNM, TOTALS=ONLY",
            "RF",
            "*NODE PRINT, NSET=BLOCKNP, TOTALS=ONLY",
            "RF",
            "*NODE PRINT, NSET=PROFM",
            "U",
            "*NODE PRINT, NSET=PROFP",
            "U",
        ]
    else:
        lines += [
            "*NODE PRINT, NSET=FIX, TOTALS=ONLY",
            "RF",
            "*NODE PRINT, NSET=SYMY, TOTALS=ONLY",
            "RF",
            "*NODE PRINT, NSET=PROF",
            "U",
        ]
    lines += ["*NODE PRINT, NSET=MON", "U", "*END STEP"]
    path = Path(out) / f"{name}.inp"
    path.write_text("\n".join(lines) + "\n")
    return path


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mesh", type=int, default=2, choices=sorted(LEVELS), help="refinement level")
    ap.add_argument("--mu", type=float, default=0.0, help="friction coefficient")
    ap.add_argument("--tilt", type=float, default=0.0, help="box tilt about x (deg); > 0: half model")
    ap.add_argument("--penalty", type=float, default=PENALTY, help="contact slope, N/mm^3")
    ap.add_argument("--dtravel", type=float, default=DTRAVEL, help="block travel per increment, mm")
    ap.add_argument("--name", default=None, help="deck name (default lid_m<level>_mu<mu>[_tilt<tilt>])")
    ap.add_argument("--out", default="/tmp/ccx_box_lid", help="output folder")
    a = ap.parse_args()
    Path(a.out).mkdir(parents=True, exist_ok=True)
    tag = f"m{a.mesh}" if a.tilt == 0 else f"half_m{a.mesh}_tilt{a.tilt:g}"
    mesh, info = write_mesh(LEVELS[a.mesh], a.out, tag, a.tilt)
    print(f"{mesh}: {info}")
    name = a.name or f"lid_m{a.mesh}_mu{a.mu:g}" + (f"_tilt{a.tilt:g}" if a.tilt else "")
    deck = write_deck(name, tag, a.mu, a.penalty, a.out, a.dtravel, a.tilt)
    print(f"{deck}: stroke {stroke(a.tilt):.4f} mm, z_top {Z_TOP:.4f} mm")


if __name__ == "__main__":
    main()
