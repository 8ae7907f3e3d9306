"""Helpers shared by the CalculiX reference builders in this folder (two_hook_clip/, cable_latch/).

Not a reference itself: nothing here knows a part's geometry, dimensions, contact pairs or deck
text; those stay in each builder's make_deck.py and run.py. This module holds the generic pieces
both builders use:

- meshing (make_deck.py): a 2-D section in (x, z) meshed with quadrilaterals by gmsh
  (`mesh_section`), its extrusion over y into hexahedra in Abaqus node order (`y_layers`,
  `extrude`, `hex_volume_sign`), the hexahedra's faces on section edges (`faces_on`, `face_nodes`)
  and node lists in the .inp format (`write_ids`);
- running ccx single-threaded in a scratch folder (`run_ccx`, `solve_ccx`, `wait_for_other_ccx`);
- reading ccx's .dat output (`parse_dat`, `parse_dat_load`) and a mesh file's node sets
  (`mesh_nodes`, `monitors_of`);
- small pieces of post-processing (`rounded_rect_distance`, `smoothed`, `rounded`).

The builders' scripts are run as files (python benchmarks/calculix/<name>/run.py ...); each puts
this folder on sys.path to import this module.
"""

from __future__ import annotations

import math
import os
import re
import shutil
import subprocess
import time
from pathlib import Path

import gmsh
import numpy as np

# ---- meshing --------------------------------------------------------------------------------


def mesh_section(build, sizes):
    """Mesh a 2-D section with quadrilaterals (gmsh must be initialised). `build(geo)` adds
    points/curves/surface to gmsh's geo kernel and returns {name: [curve tags]}, {curve tag:
    number of segments} and {name: [point tags]} (refinement points; may be empty); `sizes` is a
    list of (curve or point names, size near them, distance of the growth, size far away).
    Returns nodes (n, 2) in (x, z), quads (m, 4) 0-based and counter-clockwise, {name: [(a, b)
    node pairs]} of the named curves."""
    gmsh.model.add("section")
    geo = gmsh.model.geo
    named, nseg, points = build(geo)
    geo.synchronize()
    for tag, n in nseg.items():
        gmsh.model.mesh.setTransfiniteCurve(tag, (n + 1) // 2 + 1)  # n rounded up to even
    fields = []
    for names, s_near, d_grow, s_far in sizes:
        unknown = set(names) - set(named) - set(points)
        if unknown:
            raise KeyError(f"refinement of unknown curves or points {sorted(unknown)}")
        f_d = gmsh.model.mesh.field.add("Distance")
        curves = [t for n in names if n in named for t in named[n]]
        pts = [t for n in names if n in points for t in points[n]]
        if curves:
            gmsh.model.mesh.field.setNumbers(f_d, "CurvesList", curves)
        if pts:
            gmsh.model.mesh.field.setNumbers(f_d, "PointsList", pts)
        gmsh.model.mesh.field.setNumber(f_d, "Sampling", 200)
        f_t = gmsh.model.mesh.field.add("Threshold")
        gmsh.model.mesh.field.setNumber(f_t, "InField", f_d)
        gmsh.model.mesh.field.setNumber(f_t, "SizeMin", 2 * s_near)
        gmsh.model.mesh.field.setNumber(f_t, "SizeMax", 2 * s_far)
        gmsh.model.mesh.field.setNumber(f_t, "DistMin", s_near)
        gmsh.model.mesh.field.setNumber(f_t, "DistMax", d_grow)
        fields.append(f_t)
    f_min = gmsh.model.mesh.field.add("Min")
    gmsh.model.mesh.field.setNumbers(f_min, "FieldsList", fields)
    gmsh.model.mesh.field.setAsBackgroundMesh(f_min)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    gmsh.option.setNumber("Mesh.Algorithm", 8)  # frontal-Delaunay for quads
    gmsh.option.setNumber("Mesh.RecombineAll", 1)
    gmsh.option.setNumber("Mesh.RecombinationAlgorithm", 1)  # blossom
    # blossom may leave a few triangles: split every element into quadrilaterals instead (halves
    # the sizes, which are therefore doubled above)
    gmsh.option.setNumber("Mesh.SubdivisionAlgorithm", 1)
    gmsh.model.mesh.generate(2)
    gmsh.model.mesh.optimize("Laplace2D")

    tags, coords, _ = gmsh.model.mesh.getNodes()
    index = {int(t): i for i, t in enumerate(tags)}
    nodes = coords.reshape(-1, 3)[:, :2].copy()
    quads = []
    for etype, _, enodes in zip(*gmsh.model.mesh.getElements(2), strict=True):
        if etype != 3:
            raise RuntimeError(f"non-quadrilateral element type {etype} in the section mesh")
        quads.append(np.array([index[int(t)] for t in enodes]).reshape(-1, 4))
    quads = np.vstack(quads)
    edges = {}
    for name, curves in named.items():
        pairs = []
        for c in curves:
            for etype, _, enodes in zip(*gmsh.model.mesh.getElements(1, c), strict=True):
                assert etype == 1
                e = np.array([index[int(t)] for t in enodes]).reshape(-1, 2)
                pairs += [tuple(p) for p in e]
        edges[name] = pairs
    gmsh.model.remove()
    # drop unused nodes (geometry points not on the mesh), renumber
    used = np.unique(quads)
    remap = -np.ones(len(nodes), int)
    remap[used] = np.arange(len(used))
    nodes = nodes[used]
    quads = remap[quads]
    edges = {k: [(remap[a], remap[b]) for a, b in v] for k, v in edges.items()}
    # counter-clockwise in (x, z)
    p = nodes[quads]
    area2 = np.sum(p[:, :, 0] * np.roll(p[:, :, 1], -1, 1) - np.roll(p[:, :, 0], -1, 1) * p[:, :, 1], 1)
    quads[area2 < 0] = quads[area2 < 0][:, ::-1]
    return nodes, quads, edges


def y_layers(n, y1):
    """n layers over [0, y1], graded towards y1 (the free edge; ratio 0.8 per layer)."""
    w = 0.8 ** np.arange(n)
    return np.concatenate([[0.0], np.cumsum(w) / w.sum() * y1])


def extrude(nodes2, quads, ys, first_node, first_elem):
    """Hexahedra from the section: node (i, k) is section node i at ys[k]."""
    n2, nl = len(nodes2), len(ys) - 1
    xyz = np.zeros((n2 * len(ys), 3))
    for k, y in enumerate(ys):
        xyz[k * n2 : (k + 1) * n2] = np.column_stack([nodes2[:, 0], np.full(n2, y), nodes2[:, 1]])
    ids = first_node + np.arange(len(xyz))
    hexes = []
    for k in range(nl):
        lo, hi = quads + k * n2, quads + (k + 1) * n2
        # CCW in (x, z) has normal -y; Abaqus wants nodes 1-4 with the normal towards 5-8 (+y):
        # reverse the order of the bottom and top faces
        hexes.append(np.hstack([lo[:, ::-1], hi[:, ::-1]]))
    hexes = np.vstack(hexes)
    conn = ids[hexes]
    eids = first_elem + np.arange(len(conn))
    return xyz, ids, conn, eids, n2


def hex_volume_sign(xyz_of, conn):
    """Per hexahedron, (n1n2 x n1n4) . n1n5: positive in Abaqus node order."""
    p = xyz_of(conn)
    a, b, d, e = p[:, 0], p[:, 1], p[:, 3], p[:, 4]
    return np.einsum("ij,ij->i", np.cross(b - a, d - a), e - a)


def faces_on(edges, quads, nl, n2q, first_elem):
    """(element id, face label) of the extruded faces on the section edges `edges`."""
    # after reversal, hex nodes 1-4 = quad nodes (3, 2, 1, 0); Abaqus faces of the quad edges:
    # S3 = nodes 1-2 -> quad edge (3, 2); S4 = 2-3 -> (2, 1); S5 = 3-4 -> (1, 0); S6 = 4-1 -> (0, 3)
    edge_face = {}
    for qi, q in enumerate(quads):
        for (i, j), s in zip(((3, 2), (2, 1), (1, 0), (0, 3)), ("S3", "S4", "S5", "S6"), strict=True):
            edge_face[frozenset((q[i], q[j]))] = (qi, s)
    out = []
    for k in range(nl):
        for a, b in edges:
            qi, s = edge_face[frozenset((a, b))]
            out.append((first_elem + k * n2q + qi, s))
    return out


_FACE_NODES = {"S3": (0, 1, 5, 4), "S4": (1, 2, 6, 5), "S5": (2, 3, 7, 6), "S6": (3, 0, 4, 7)}


def face_nodes(conn, face):
    """Node ids of a face (element id, label) from faces_on; conn's row e - 1 is element e."""
    e, s = face
    return conn[e - 1][list(_FACE_NODES[s])]


def write_ids(f, ids, per_line=16):
    """Ids `per_line` to a line, each line ending with a comma (a *NSET's data lines)."""
    ids = list(ids)
    for i in range(0, len(ids), per_line):
        f.write(", ".join(str(int(v)) for v in ids[i : i + per_line]) + ",\n")


# ---- running ccx ----------------------------------------------------------------------------


def wait_for_other_ccx():
    """Wait while another ccx process runs on the machine (needs pgrep; without it, no wait)."""
    if shutil.which("pgrep") is None:
        return
    while subprocess.run(["pgrep", "-x", "ccx"], capture_output=True).returncode == 0:
        time.sleep(2)


def _stage(inputs, work):
    """Copy the input files into `work`; returns the environment of a single-threaded ccx run."""
    work.mkdir(parents=True, exist_ok=True)
    for f in inputs:
        shutil.copy(f, work / Path(f).name)
    return dict(os.environ, OMP_NUM_THREADS="1", CCX_NPROC_EQUATION_SOLVER="1")


def run_ccx(name, inputs, work, wait, limit_s, *, stop=None, check_s=20, fresh=False):
    """Run `ccx -i <name>` in `work` after copying the files `inputs` (the deck and the mesh it
    includes) there; ccx's output goes to <name>.log. It is stopped after `limit_s` seconds, or
    when `stop()` (if given; called every `check_s` seconds, first at the start) returns a note
    instead of None; the .dat file keeps every increment converged so far. `fresh`: remove an
    earlier run's <name>.dat and <name>.sta first (so that `stop` cannot read them). Writes
    "<wall seconds> <note>" to <name>.wall and returns the wall time."""
    env = _stage(inputs, work)
    if fresh:
        for f in (f"{name}.dat", f"{name}.sta"):
            (work / f).unlink(missing_ok=True)
    if wait:
        wait_for_other_ccx()
    t0 = time.time()
    note = None
    checked = 0.0
    with open(work / f"{name}.log", "w") as log:
        proc = subprocess.Popen(["ccx", "-i", name], cwd=work, env=env, stdout=log, stderr=subprocess.STDOUT)
        while proc.poll() is None:
            if time.time() - t0 > limit_s:
                note = "stopped at the time limit"
            elif stop is not None and time.time() - checked > check_s:
                checked = time.time()
                note = stop()
            if note:
                proc.terminate()
                proc.wait()
                break
            time.sleep(2)
    wall = time.time() - t0
    note = note or f"ccx rc {proc.returncode}"
    (work / f"{name}.wall").write_text(f"{wall:.1f} {note}\n")
    print(f"{name}: {note}, {wall:.0f} s")
    return wall


def solve_ccx(name, inputs, work, wait):
    """One short ccx run (`ccx -i <name>` in `work`, after copying `inputs` there), output
    discarded; raises if ccx fails."""
    env = _stage(inputs, work)
    if wait:
        wait_for_other_ccx()
    subprocess.run(["ccx", "-i", name], cwd=work, env=env, capture_output=True, check=True)


# ---- reading ccx's output and the mesh files --------------------------------------------------


def _float(v):
    """Fortran E format drops the E of three-digit exponents (-4.130105-101)."""
    try:
        return float(v)
    except ValueError:
        return float(re.sub(r"(\d)([+-]\d+)$", r"\1E\2", v))


def _vec(fields):
    return np.array([_float(v) for v in fields])


def parse_dat(path, sets):
    """Per output time of a .dat file: the total RF of node sets printed with TOTALS=ONLY and the
    displacements of the node sets printed node by node. Returns (times, {set: {time: RF}},
    {time: {node: u}}); times are those at which every set in `sets` has its total and some
    displacements are printed, and, if the run's .sta file exists, only converged increments."""
    txt = Path(path).read_text()
    totals, disp, seen = {}, {}, set()
    for s, t, fx, fy, fz in re.findall(
        r"total force \(fx,fy,fz\) for set (\w+) and time\s+(\S+)\s+(\S+)\s+(\S+)\s+(\S+)", txt
    ):
        totals.setdefault(s, {}).setdefault(float(t), _vec([fx, fy, fz]))
    for s, t, body in re.findall(
        r"displacements \(vx,vy,vz\) for set (\w+) and time\s+(\S+)\n\n((?:.+\n)+)", txt
    ):
        if (s, t) not in seen:  # the first print at a time (ccx repeats the last one when it gives up)
            seen.add((s, t))
            disp.setdefault(float(t), {}).update(
                {int(r.split()[0]): _vec(r.split()[1:4]) for r in body.splitlines()}
            )
    common = set(disp)
    for s in sets:
        common &= set(totals[s])
    times = sorted(common)
    sta = Path(path).with_suffix(".sta")
    if sta.exists():  # converged increments only
        done = [float(r.split()[-3]) for r in sta.read_text().splitlines()[2:] if r.split()[2].isdigit()]
        times = [t for t in times if any(abs(t - d) < 1e-5 for d in done)]
    return times, totals, disp


def parse_dat_load(path):
    """{node: u} of the set MON in a one-increment (linear) run's .dat file."""
    txt = Path(path).read_text()
    body = re.search(r"displacements \(vx,vy,vz\) for set MON and time\s+\S+\n\n((?:.+\n)+)", txt).group(1)
    return {int(r.split()[0]): _vec(r.split()[1:4]) for r in body.splitlines()}


def mesh_nodes_xyz(mesh_path, nset):
    """{node: (x, y, z) array} of a node set of a mesh file (mesh_m<level>.inp)."""
    txt = Path(mesh_path).read_text()
    body = re.search(rf"\*NSET, NSET={nset}\n((?:[\d, ]+\n)+)", txt).group(1)
    ids = {int(v) for v in body.replace("\n", "").split(",") if v.strip()}
    nodes = re.search(r"\*NODE, NSET=NALL\n((?:.+\n)+?)\*", txt).group(1)
    out = {}
    for r in nodes.splitlines():
        n, x, y, z = r.split(",")
        if int(n) in ids:
            out[int(n)] = np.array([float(x), float(y), float(z)])
    return out


def mesh_nodes(mesh_path, nset):
    """{node: (x, z)} of a node set of a mesh file (mesh_m<level>.inp)."""
    return {n: (float(p[0]), float(p[2])) for n, p in mesh_nodes_xyz(mesh_path, nset).items()}


def monitors_of(mesh_path):
    """Node numbers of the monitor points (from the mesh file's single-node sets)."""
    txt = Path(mesh_path).read_text()
    return {k: int(v) for k, v in re.findall(r"\*NSET, NSET=(\w+)\n(\d+),\n", txt)}


# ---- post-processing ------------------------------------------------------------------------


def rounded_rect_distance(x, z, cx, cz, half_w, half_h, r):
    """Signed distance (negative inside) of the point (x, z) from a rectangle centred at (cx, cz),
    half sizes half_w (x) and half_h (z), its corners rounded with radius r."""
    qx = abs(x - cx) - (half_w - r)
    qz = abs(z - cz) - (half_h - r)
    return math.hypot(max(qx, 0.0), max(qz, 0.0)) + min(max(qx, qz), 0.0) - r


def smoothed(travel, force, step):
    """The force on a uniform travel grid (spacing `step`, the nominal increment), averaged over 5
    grid points (a window of 5 increments: the zig-zag of node-to-surface contact averages out)."""
    grid = np.arange(travel[0], travel[-1] + 1e-9, step)
    return grid, np.convolve(np.interp(grid, travel, force), np.ones(5) / 5, mode="same")


def rounded(v, n, *, drop_negative_zero):
    """float(v) rounded to n decimals; with drop_negative_zero, -0.0 becomes 0.0."""
    r = round(float(v), n)
    return r + 0.0 if drop_negative_zero else r
