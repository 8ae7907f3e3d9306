"""CalculiX deck for jsnap's `annular` preset: mesh and .inp from the named dimensions, independent of jsnap.

    python benchmarks/calculix/annular/make_deck.py --mesh 3 --mu 0.3 --out /tmp/ccx_annular

A tube (bore radius R, wall H) fixed at z = 0 with an inward lip at its mouth; a rigid bead (a
cylinder of radius R, 0.5 mm tall, edges rounded with radius 0.1 mm) is pushed down the axis
through the lip. The section (r, z):

    (R + H, 0) (R + H, Z_TOP) (R, Z_TOP) (R - Y_U, L + FLAT) (R - Y_U, L) (R, L) (R, 0)

is meshed with structured quadrilaterals (fine at the lip, graded into the wall) and turned about
the z axis:

* sector model (default): one layer of C3D8I hexahedra over a THETA_S-degree sector, its two
  side planes held by symmetry (no circumferential displacement, an *EQUATION per node). The
  deformation is axisymmetric, so this is the axisymmetric solution; forces are scaled by
  360 / THETA_S to the full ring.
* full model (``--full N``): the whole 360 degrees in N hexahedra around, no symmetry conditions
  (a check of the sector model).

The bead is a thin band of C3D8 elements under its surface (bottom face, both rounded edges,
side, top face) whose nodes all have prescribed displacements (a rigid translation: no strain,
so the reaction on its nodes is the contact force). Node-to-surface penalty contact: the lip's
lead ramp, land and retention face and the bore below it (slave) against the bead's surface
(master). In the sector model the bead extends one slice beyond the sector on each side, so
that the slave nodes on the symmetry planes lie inside the master surface, not on its edge
(CalculiX loses a penetrating node that projects onto a master surface's free edge). Linear
geometry (no NLGEOM); static increments of bead travel.

Writes ``<name>.inp`` (mesh, material, contact, step) and ``<name>.json`` (what run.py needs to
read the results: scale factor, node sets, the case's parameters).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

# ---- named dimensions (mm, degrees), jsnap's annular defaults --------------------------------
R = 3.0  # bore radius (= bead radius)
H = 1.0  # wall thickness
L = 4.0  # from the fixed end z = 0 to the lip's retention face
Y_U = 0.12  # undercut: the lip's protrusion into the bore
ALPHA = 30.0  # lead angle (the ramp's angle to the z axis)
RETURN_ANGLE = 90.0  # retention face square to the axis (the only value this generator builds)
FLAT = 0.1  # land length

# ---- rigid bead -------------------------------------------------------------------------------
BEAD_H = 0.5  # bead height
FILLET = 0.1  # radius of the bead's rounded circular edges
CLEARANCE = 0.02  # bead bottom above the tube's top at the start
PASS = 0.3  # travel past the point where the bead's top reaches the retention face
BEAD_BAND = 0.3  # the bead's bottom and top faces are modelled for r in [R - BEAD_BAND, R]
BEAD_SKIN = 0.04  # thickness of the band of rigid elements under the bead's surface

# ---- material (ABS) and contact ---------------------------------------------------------------
E_MOD = 2200.0  # MPa
NU = 0.35
PENALTY = 2.0e6  # N/mm^3, slope of the linear pressure-overclosure curve (~900 E)
SIGMA_INF = 0.03  # MPa, tension at large clearance (CalculiX's regularisation; its default E/70000)
STICK_RATIO = 0.01  # stick slope = STICK_RATIO * PENALTY (CalculiX's advice: ~1/100)

# ---- derived geometry -------------------------------------------------------------------------
Z_TOP = L + FLAT + Y_U / math.tan(math.radians(ALPHA))  # tube top (4.307846)
Z_BEAD = Z_TOP + CLEARANCE  # bead bottom at the start
STROKE = CLEARANCE + (Z_TOP - L) + BEAD_H + PASS  # bead top 0.3 mm below the retention face (1.127846)
BORE_CONTACT = 1.0  # the bore is a contact face for z in [L - BORE_CONTACT, L]
THETA_S = 1.0  # sector angle (deg)

# ---- mesh levels: element size at the lip (mm) and segments on each rounded edge of the bead ---
LEVELS = {
    1: dict(fine=0.04, fillet_seg=64),
    2: dict(fine=0.02, fillet_seg=64),
    3: dict(fine=0.01, fillet_seg=64),
    4: dict(fine=0.005, fillet_seg=64),
}
GROWTH = 1.15  # element growth away from the lip
SIZE_MAX_Z = 0.2  # largest element along the tube
SIZE_MAX_R = H / 6  # largest element through the wall


def graded(length: float, first: float, growth: float, largest: float) -> np.ndarray:
    """Coordinates 0 .. length, the first step `first`, growing by `growth` up to `largest`
    (all steps scaled slightly so that they add up to `length`)."""
    steps, total, h = [], 0.0, first
    while total < length - 1e-9 * length:
        steps.append(h)
        total += h
        h = min(h * growth, largest)
    steps = np.asarray(steps) * (length / total)
    return np.concatenate([[0.0], np.cumsum(steps)])


def tube_section(fine: float):
    """Structured quads of the tube's (r, z) section. Returns nodes (n, 2), quads (m, 4) and
    {name: [(a, b) boundary node pairs]} for the contact faces, and the base and monitor nodes."""
    r_wall = R + graded(H, fine, GROWTH * 1.05, SIZE_MAX_R)
    z_low = L - graded(L, fine, GROWTH, SIZE_MAX_Z)[::-1]  # 0 .. L, fine at L
    nz = math.ceil((Z_TOP - L) / fine - 1e-9)  # divisions over the lip's height
    # Divisions along the ramp: twice as fine as elsewhere, the ramp's nodes (slaves) sliding on
    # the bead's rounded edge decide how smooth the force is.
    m = math.ceil(2 * Y_U / math.sin(math.radians(ALPHA)) / fine - 1e-9)
    z_wall = np.concatenate([z_low, L + (Z_TOP - L) * np.arange(1, nz + 1) / nz])
    jl = len(z_low) - 1  # row of z = L
    nr, nzw = len(r_wall), len(z_wall)
    pts = [(r, z) for z in z_wall for r in r_wall]

    def w(i, j):
        return j * nr + i

    quads = [
        (w(i, j), w(i + 1, j), w(i + 1, j + 1), w(i, j + 1)) for j in range(nzw - 1) for i in range(nr - 1)
    ]
    # Lip: bilinear patch (u across, from r = R inwards; v along z), its u = 0 edge the wall's bore.
    p00, p10 = np.array([R, L]), np.array([R - Y_U, L])
    p11, p01 = np.array([R - Y_U, L + FLAT]), np.array([R, Z_TOP])
    lip = {}
    for b in range(nz + 1):
        lip[0, b] = w(0, jl + b)
        for a in range(1, m + 1):
            u, v = a / m, b / nz
            p = (1 - u) * (1 - v) * p00 + u * (1 - v) * p10 + u * v * p11 + (1 - u) * v * p01
            lip[a, b] = len(pts)
            pts.append((float(p[0]), float(p[1])))
    quads += [(lip[a, b], lip[a + 1, b], lip[a + 1, b + 1], lip[a, b + 1]) for b in range(nz) for a in range(m)]
    z_bore = L - BORE_CONTACT - 1e-9
    edges = {
        "bore": [(w(0, j), w(0, j + 1)) for j in range(jl) if z_wall[j] >= z_bore],
        "ret": [(lip[a, 0], lip[a + 1, 0]) for a in range(m)],
        "land": [(lip[m, b], lip[m, b + 1]) for b in range(nz)],
        "ramp": [(lip[a, nz], lip[a + 1, nz]) for a in range(m)],
    }
    monitors = {
        "lip_low": lip[m, 0],  # (R - Y_U, L): the land's lower corner
        "lip_high": lip[m, nz],  # (R - Y_U, L + FLAT): the land's upper corner
        "mouth": w(nr - 1, nzw - 1),  # (R + H, Z_TOP): the tube's outer top corner
    }
    base = [w(i, 0) for i in range(nr)]
    return np.asarray(pts), np.asarray(quads), edges, base, monitors


def bead_section(fillet_seg: int, fine: float):
    """Quads of a thin band under the bead's surface (r, z), bead bottom at z = Z_BEAD. Returns
    nodes, quads and {name: [(a, b) outer-surface node pairs]}."""
    rho, z0, zt = FILLET, Z_BEAD, Z_BEAD + BEAD_H
    n_face = max(4, math.ceil((BEAD_BAND - rho) / max(fine, 0.02)))
    n_side = max(4, math.ceil((BEAD_H - 2 * rho) / max(fine, 0.02)))
    prof, normal, label = [], [], []  # outer points, inward normals, label of the segment after

    def add(p, n, lab):
        prof.append(p)
        normal.append(n)
        label.append(lab)

    for k in range(n_face):  # bottom face, r from R - BEAD_BAND to R - rho
        add((R - BEAD_BAND + (BEAD_BAND - rho) * k / n_face, z0), (0.0, 1.0), "bottom")
    for k in range(fillet_seg):  # lower rounded edge
        phi = -0.5 * math.pi + 0.5 * math.pi * k / fillet_seg
        c, s = math.cos(phi), math.sin(phi)
        add((R - rho + rho * c, z0 + rho + rho * s), (-c, -s), "fillet_low")
    for k in range(n_side):  # side
        add((R, z0 + rho + (BEAD_H - 2 * rho) * k / n_side), (-1.0, 0.0), "side")
    for k in range(fillet_seg):  # upper rounded edge
        phi = 0.5 * math.pi * k / fillet_seg
        c, s = math.cos(phi), math.sin(phi)
        add((R - rho + rho * c, zt - rho + rho * s), (-c, -s), "fillet_high")
    for k in range(n_face + 1):  # top face, r from R - rho to R - BEAD_BAND
        add((R - rho - (BEAD_BAND - rho) * k / n_face, zt), (0.0, -1.0), "top")
    outer = np.asarray(prof)
    inner = outer + BEAD_SKIN * np.asarray(normal)
    n = len(outer)
    pts = np.concatenate([outer, inner])
    quads = np.asarray([(k, k + 1, n + k + 1, n + k) for k in range(n - 1)])
    edges: dict[str, list] = {}
    for k in range(n - 1):
        edges.setdefault(label[k], []).append((k, k + 1))
    return pts, quads, edges


def orient(pts: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """Quads ordered clockwise in the (r, z) plane: turned about +z (theta increasing), their
    first face (nodes 1-4 at the lower angle) then faces the element's other four nodes."""
    p = pts[quads]
    area = 0.5 * np.sum(
        p[:, :, 0] * np.roll(p[:, :, 1], -1, 1) - np.roll(p[:, :, 0], -1, 1) * p[:, :, 1], axis=1
    )
    return np.where((area > 0)[:, None], quads[:, ::-1], quads)


def revolve(pts, quads, thetas, periodic, node0, elem0):
    """Nodes (r cos t, r sin t, z) for each angle and hexahedra between consecutive angles.
    Returns node ids (n_angles, n_pts), coordinates, element ids (n_slices, n_quads), connectivity."""
    na = len(thetas)
    nid = node0 + np.arange(na * len(pts)).reshape(na, len(pts))
    xyz = np.concatenate(
        [np.column_stack([pts[:, 0] * math.cos(t), pts[:, 0] * math.sin(t), pts[:, 1]]) for t in thetas]
    )
    nslice = na if periodic else na - 1
    eid = elem0 + np.arange(nslice * len(quads)).reshape(nslice, len(quads))
    conn = []
    for s in range(nslice):
        lo, hi = nid[s], nid[(s + 1) % na]
        conn.append(np.column_stack([lo[quads], hi[quads]]))
    return nid, xyz, eid, np.concatenate(conn)


def faces(quads: np.ndarray, pairs) -> list[tuple[int, int]]:
    """(quad index, C3D8 face number) of the faces built on section edges `pairs`: the edge
    (n1, n2) of a quad gives face S3, (n2, n3) S4, (n3, n4) S5, (n4, n1) S6."""
    where = {}
    for q, quad in enumerate(quads):
        for k in range(4):
            where[frozenset((int(quad[k]), int(quad[(k + 1) % 4])))] = (q, 3 + k)
    return [where[frozenset((int(a), int(b)))] for a, b in pairs]


def write_lines(f, items, per_line=8):
    items = list(items)
    for k in range(0, len(items), per_line):
        f.write(", ".join(str(x) for x in items[k : k + per_line]) + "\n")


def build(
    name: str,
    out: Path,
    *,
    level: int,
    mu: float = 0.0,
    penalty: float = PENALTY,
    stick: float = STICK_RATIO,
    full: int = 0,
    dtravel: float = 0.01,
    stroke: float = STROKE,
    approach: float = 0.0,
    fillet_seg: int | None = None,
    theta_s: float = THETA_S,
):
    """Write ``out/<name>.inp`` and ``out/<name>.json``. ``full``: hexahedra around a 360-degree
    model (0: the sector model); ``approach``: travel covered by the first increment (before
    contact), the rest in increments of ``dtravel``. Returns the deck's path and the metadata."""
    lev = dict(LEVELS[level])
    if fillet_seg:
        lev["fillet_seg"] = fillet_seg
    tp, tq, tedges, base, monitors = tube_section(lev["fine"])
    bp, bq, bedges = bead_section(lev["fillet_seg"], lev["fine"])
    tq, bq = orient(tp, tq), orient(bp, bq)
    if full:
        thetas_t = 2 * math.pi * np.arange(full) / full
        thetas_b, periodic, scale = thetas_t, True, 1.0
    else:
        h = math.radians(theta_s) / 2
        thetas_t = np.array([-h, h])
        thetas_b = np.array([-3 * h, -h, h, 3 * h])  # one slice more on each side
        periodic, scale = False, 360.0 / theta_s
    tn, txyz, te, tconn = revolve(tp, tq, thetas_t, periodic, 1, 1)
    bn, bxyz, be, bconn = revolve(bp, bq, thetas_b, periodic, int(tn.max()) + 1, int(te.max()) + 1)

    out.mkdir(parents=True, exist_ok=True)
    inp = out / f"{name}.inp"
    with inp.open("w") as f:
        f.write(f"*HEADING\njsnap annular preset, CalculiX reference: {name}\n")
        f.write("*NODE, NSET=NALL\n")
        for ids, xyz in ((tn.ravel(), txyz), (bn.ravel(), bxyz)):
            for i, (x, y, z) in zip(ids, xyz, strict=True):
                f.write(f"{i}, {x:.12g}, {y:.12g}, {z:.12g}\n")
        blocks = (("C3D8I", "TUBE", te.ravel(), tconn), ("C3D8", "BEAD", be.ravel(), bconn))
        for typ, eset, eids, conn in blocks:
            f.write(f"*ELEMENT, TYPE={typ}, ELSET={eset}\n")
            for e, c in zip(eids, conn, strict=True):
                f.write(f"{e}, " + ", ".join(str(int(x)) for x in c) + "\n")
        f.write("*NSET, NSET=BASE\n")
        write_lines(f, sorted(int(x) for x in tn[:, base].ravel()))
        f.write("*NSET, NSET=BEADN\n")
        write_lines(f, sorted(int(x) for x in bn.ravel()))
        if full:  # the bead's nodes per angle, for the radial force
            for k in range(full):
                f.write(f"*NSET, NSET=BEADT{k}\n")
                write_lines(f, sorted(int(x) for x in bn[k]))
        monitor_ids = {key: int(tn[0, v]) for key, v in monitors.items()}
        f.write("*NSET, NSET=MON\n")
        write_lines(f, sorted(monitor_ids.values()))

        def surface(sname, quads, pairs, eids, slices):
            f.write(f"*SURFACE, NAME={sname}, TYPE=ELEMENT\n")
            for q, face in faces(quads, pairs):
                for s in slices:
                    f.write(f"{int(eids[s, q])}, S{face}\n")

        all_t = range(te.shape[0])
        all_b = range(be.shape[0])
        surface("S_LIP", tq, tedges["ramp"] + tedges["land"] + tedges["ret"] + tedges["bore"], te, all_t)
        bead_all = [e for k in ("bottom", "fillet_low", "side", "fillet_high", "top") for e in bedges[k]]
        surface("M_BEAD", bq, bead_all, be, all_b)

        f.write(f"*MATERIAL, NAME=ABS\n*ELASTIC\n{E_MOD}, {NU}\n")
        f.write(f"*MATERIAL, NAME=STIFF\n*ELASTIC\n{1000 * E_MOD}, 0.3\n")
        f.write("*SOLID SECTION, ELSET=TUBE, MATERIAL=ABS\n*SOLID SECTION, ELSET=BEAD, MATERIAL=STIFF\n")
        if not full:  # symmetry: no circumferential displacement on the side planes
            f.write("*EQUATION\n")
            fixed = set(int(x) for x in tn[:, base].ravel())
            for s, t in enumerate(thetas_t):
                for i in tn[s]:
                    if int(i) not in fixed:
                        f.write(f"2\n{int(i)}, 2, 1.0, {int(i)}, 1, {-math.tan(t):.15g}\n")
        f.write("*SURFACE INTERACTION, NAME=SI\n*SURFACE BEHAVIOR, PRESSURE-OVERCLOSURE=LINEAR\n")
        f.write(f"{penalty:g}, {SIGMA_INF:g}\n")
        if mu > 0:
            f.write(f"*FRICTION\n{mu:g}, {stick * penalty:g}\n")
        f.write("*CONTACT PAIR, INTERACTION=SI, TYPE=NODE TO SURFACE\nS_LIP, M_BEAD\n")
        # step time t in [0, 1]; travel = stroke * amplitude(t), fixed increments dt
        dt = dtravel / (stroke - approach + dtravel) if approach > 0 else dtravel / stroke
        amp = [(0.0, 0.0), (dt, approach / stroke), (1.0, 1.0)] if approach > 0 else [(0.0, 0.0), (1.0, 1.0)]
        f.write("*AMPLITUDE, NAME=TRAVEL\n" + ", ".join(f"{t:.12g}, {v:.12g}" for t, v in amp) + "\n")
        f.write("*STEP, INC=100000\n*STATIC\n")
        f.write(f"{dt:.9g}, 1.0, {dt * 1e-2:.9g}, {dt:.9g}\n")
        f.write("*BOUNDARY\nBASE, 1, 3\nBEADN, 1, 2\n")
        f.write(f"*BOUNDARY, AMPLITUDE=TRAVEL\nBEADN, 3, 3, {-stroke:.9g}\n")
        f.write("*NODE PRINT, NSET=BEADN, TOTALS=ONLY\nRF\n*NODE PRINT, NSET=BASE, TOTALS=ONLY\nRF\n")
        if full:
            for k in range(full):
                f.write(f"*NODE PRINT, NSET=BEADT{k}, TOTALS=ONLY\nRF\n")
        f.write("*NODE PRINT, NSET=MON\nU\n*END STEP\n")

    meta = dict(
        name=name,
        level=level,
        fine=lev["fine"],
        fillet_seg=lev["fillet_seg"],
        mu=mu,
        penalty=penalty,
        stick=stick,
        full=full,
        theta_s=None if full else theta_s,
        scale=scale,
        dtravel=dtravel,
        stroke=stroke,
        amplitude=amp,
        monitors=monitor_ids,
        monitor_theta=float(thetas_t[0]),
        bead_thetas=[float(t) for t in thetas_b] if full else None,
        n_nodes=int(tn.size + bn.size),
        n_tube_elements=int(te.size),
        n_bead_elements=int(be.size),
        n_section_quads=len(tq),
    )
    (out / f"{name}.json").write_text(json.dumps(meta, indent=1))
    return inp, meta


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mesh", type=int, default=3, choices=sorted(LEVELS), help="refinement level")
    ap.add_argument("--mu", type=float, default=0.0, help="Coulomb friction coefficient")
    ap.add_argument("--penalty", type=float, default=PENALTY, help="contact penalty slope, N/mm^3")
    ap.add_argument("--stick", type=float, default=STICK_RATIO, help="stick slope over the penalty slope")
    ap.add_argument("--full", type=int, default=0, help="full 360-degree model with this many hexahedra around")
    ap.add_argument("--dtravel", type=float, default=0.01, help="bead travel per increment, mm")
    ap.add_argument("--stroke", type=float, default=STROKE, help="total bead travel, mm")
    ap.add_argument("--approach", type=float, default=0.0, help="travel in the first increment, mm")
    ap.add_argument("--fillet-seg", type=int, default=None, help="segments on each rounded edge of the bead")
    ap.add_argument("--theta", type=float, default=THETA_S, help="sector angle, degrees")
    ap.add_argument("--name", default=None, help="job name (default from the options)")
    ap.add_argument("--out", type=Path, default=Path("/tmp/ccx_annular"), help="output folder")
    a = ap.parse_args(argv)
    name = a.name or f"ann_m{a.mesh}_mu{a.mu:g}" + (f"_full{a.full}" if a.full else "")
    inp, meta = build(
        name,
        a.out,
        level=a.mesh,
        mu=a.mu,
        penalty=a.penalty,
        stick=a.stick,
        full=a.full,
        dtravel=a.dtravel,
        stroke=a.stroke,
        approach=a.approach,
        fillet_seg=a.fillet_seg,
        theta_s=a.theta,
    )
    n_t, n_b = meta["n_tube_elements"], meta["n_bead_elements"]
    print(f"{inp}: {meta['n_nodes']} nodes, {n_t} tube + {n_b} bead elements")


if __name__ == "__main__":
    main()
