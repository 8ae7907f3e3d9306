"""CalculiX reference for jsnap's `two_hook_clip`: write the decks, run ccx, extract the curves.

    python benchmarks/calculix/two_hook_clip/run.py all            # decks, every run, curves, summary
    python benchmarks/calculix/two_hook_clip/run.py decks          # only (re)write the decks
    python benchmarks/calculix/two_hook_clip/run.py run mu0_m3     # run (and extract) some runs
    python benchmarks/calculix/two_hook_clip/run.py extract        # curves + summary from the .dat files
    python benchmarks/calculix/two_hook_clip/run.py stiffness      # lateral-load check per mesh level

Decks (mesh_m<level>.inp, <run>.inp) go to this folder's `decks/`; ccx works in --work (scratch,
default /tmp/ccx_two_hook_clip); curves and the summary go to jsnap/data/calculix-two_hook_clip/.
ccx runs single-threaded (OMP_NUM_THREADS=1, CCX_NPROC_EQUATION_SOLVER=1) and, by default, waits
while another ccx process runs on the machine (--no-wait to skip).

The model is a quarter (x >= 0, y >= 0; see make_deck.py); the curves give the full clip:
insertion force = -4 RFz of the block; lateral force per hook = 2 RFx of the block (outwards on
the hook; the two hooks' lateral forces cancel on the block); base reaction = the fixed bottom
face's reaction (z: 4 RFz; x: 2 RFx under one half, the whole base's x reaction is zero by
symmetry); midplane force = 2 RFx of the x = 0 symmetry face (the force the base's left half
exerts on the right half).
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import make_deck as md
import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[2]
DATA = REPO / "jsnap" / "data" / "calculix-two_hook_clip"
DECKS = HERE / "decks"

# name: (mesh level, mu, penalty N/mm^3, curve file)
RUNS = {
    "mu0_m1": (1, 0.0, md.PENALTY, "clip_mu0_lin_m1_curve.csv"),
    "mu0_m2": (2, 0.0, md.PENALTY, "clip_mu0_lin_m2_curve.csv"),
    "mu0_m3": (3, 0.0, md.PENALTY, "clip_mu0_lin_curve.csv"),
    "mu03_m2": (2, 0.3, md.PENALTY, "clip_mu03_lin_curve.csv"),
    "mu0_m2_K10": (2, 0.0, 10 * md.PENALTY, "clip_mu0_lin_m2_K10_curve.csv"),
}

COLUMNS = [
    "time",
    "plug_travel_mm",
    "insertion_force_N",  # -4 RFz of the block: force resisting the motion
    "lateral_force_per_hook_N",  # 2 RFx of the block: outwards on each hook
    "net_lateral_force_N",  # on the block, both hooks: zero by symmetry
    "base_RFz_N",  # fixed bottom face, whole clip
    "base_RFx_half_N",  # fixed bottom face under one half (x > 0); whole base: zero by symmetry
    "midplane_Fx_N",  # through the base's x = 0 section (left half on right half)
    "equilibrium_mismatch_N",  # max over x, z of |block + base (+ midplane) reactions|, whole clip
    "edge_ux_mm",  # hook's land / retention-face edge, mid-width (y = 0)
    "edge_uz_mm",
    "tip_ux_mm",  # outer top corner of the arm
    "hook_rotation_deg",  # from the inner and outer face points at z = L
    "hook_penetration_mm",  # deepest ramp / land / retention-face node (y = 0) inside the block
]
PASS_THROUGH = 0.02  # mm: a hook edge deeper than this inside the block ends the curve


def wait_for_other_ccx():
    if shutil.which("pgrep") is None:
        return
    while subprocess.run(["pgrep", "-x", "ccx"], capture_output=True).returncode == 0:
        time.sleep(2)


def write_decks(names):
    DECKS.mkdir(exist_ok=True)
    for level in sorted({RUNS[n][0] for n in names}):
        _, info = md.write_mesh(md.LEVELS[level], DECKS, f"m{level}")
        print(f"mesh_m{level}.inp: {info['clip_elements']} C3D8I, {info['nodes']} nodes")
    for n in names:
        level, mu, penalty, _ = RUNS[n]
        md.write_deck(n, f"m{level}", mu, penalty, DECKS, md.DTRAVEL)


def run_ccx(name, work, wait, limit_s):
    """Run ccx on decks/<name>.inp in `work`; stop it after `limit_s` seconds (the .dat file
    keeps every increment converged so far)."""
    work.mkdir(parents=True, exist_ok=True)
    level = RUNS[name][0]
    for f in (f"{name}.inp", f"mesh_m{level}.inp"):
        shutil.copy(DECKS / f, work / f)
    env = dict(os.environ, OMP_NUM_THREADS="1", CCX_NPROC_EQUATION_SOLVER="1")
    if wait:
        wait_for_other_ccx()
    t0 = time.time()
    stopped = False
    with open(work / f"{name}.log", "w") as log:
        proc = subprocess.Popen(["ccx", "-i", name], cwd=work, env=env, stdout=log, stderr=subprocess.STDOUT)
        while proc.poll() is None:
            if time.time() - t0 > limit_s:
                proc.terminate()
                proc.wait()
                stopped = True
                break
            time.sleep(2)
    wall = time.time() - t0
    note = "stopped at the time limit" if stopped else f"ccx rc {proc.returncode}"
    (work / f"{name}.wall").write_text(f"{wall:.1f} {note}\n")
    print(f"{name}: {note}, {wall:.0f} s")
    return wall


def _float(v):
    """Fortran E format drops the E of three-digit exponents (-4.130105-101)."""
    try:
        return float(v)
    except ValueError:
        return float(re.sub(r"(\d)([+-]\d+)$", r"\1E\2", v))


def _vec(fields):
    return np.array([_float(v) for v in fields])


def parse_dat(path):
    """Per output time: total RF of BLOCKN, FIX, SYMX and the displacements of MON and PROF."""
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
    times = sorted(set(totals["BLOCKN"]) & set(totals["FIX"]) & set(totals["SYMX"]) & set(disp))
    sta = Path(path).with_suffix(".sta")
    if sta.exists():  # converged increments only
        done = [float(r.split()[-3]) for r in sta.read_text().splitlines()[2:] if r.split()[2].isdigit()]
        times = [t for t in times if any(abs(t - d) < 1e-5 for d in done)]
    return times, totals, disp


def mesh_nodes(level, nset):
    """{node: (x, z)} of a node set of mesh_m<level>.inp."""
    txt = (DECKS / f"mesh_m{level}.inp").read_text()
    body = re.search(rf"\*NSET, NSET={nset}\n((?:[\d, ]+\n)+)", txt).group(1)
    ids = {int(v) for v in body.replace("\n", "").split(",") if v.strip()}
    nodes = re.search(r"\*NODE, NSET=NALL\n((?:.+\n)+?)\*", txt).group(1)
    out = {}
    for r in nodes.splitlines():
        n, x, _, z = r.split(",")
        if int(n) in ids:
            out[int(n)] = (float(x), float(z))
    return out


def block_distance(x, z, travel):
    """Signed distance (mm, negative inside) of the point (x, z) from the block's rounded section."""
    r = md.BLOCK_FILLET
    cz = md.Z_BLOCK - travel + md.BLOCK_H / 2
    qx = abs(x) - (md.GAP / 2 - r)
    qz = abs(z - cz) - (md.BLOCK_H / 2 - r)
    return math.hypot(max(qx, 0.0), max(qz, 0.0)) + min(max(qx, qz), 0.0) - r


def monitors_of(level):
    """Node numbers of the monitor points (from the mesh file's single-node sets)."""
    txt = (DECKS / f"mesh_m{level}.inp").read_text()
    return {k: int(v) for k, v in re.findall(r"\*NSET, NSET=(\w+)\n(\d+),\n", txt)}


def extract(name, work):
    """Write the run's curve; returns (rows kept, last converged travel). The curve stops at the
    snap: before the first increment in which the hook's land / retention-face edge (y = 0) has
    risen to the block's upper fillet (z above the block's top minus the fillet radius). From there
    the node-to-surface contact of the edge on the faceted fillet makes CalculiX stall or jump to
    a path that depends on the facets (see the README). It also stops before any increment in
    which a node of the hook's ramp, land or retention face (y = 0) lies more than PASS_THROUGH mm
    inside the block (the contact has let the block through the hook)."""
    level = RUNS[name][0]
    times, tot, disp = parse_dat(work / f"{name}.dat")
    mon = monitors_of(level)
    prof = mesh_nodes(level, "PROF")
    rows = []
    for t in times:
        b, f, s = tot["BLOCKN"][t], tot["FIX"][t], tot["SYMX"][t]
        u = disp[t]
        e, ti, ui, uo = u[mon["EDGE"]], u[mon["TIP"]], u[mon["INNER10"]], u[mon["OUTER10"]]
        rot = math.degrees(math.atan2(ui[2] - uo[2], md.H + uo[0] - ui[0]))
        mism = max(4 * abs(b[2] + f[2]), 2 * abs(b[0] + f[0] + s[0]))
        travel = t * md.STROKE
        pen = -min(block_distance(x + u[n][0], z + u[n][2], travel) for n, (x, z) in prof.items())
        snap = md.L + e[2] - (md.Z_BLOCK - travel + md.BLOCK_H - md.BLOCK_FILLET)
        forces = [-4 * b[2], 2 * b[0], 0.0, 4 * f[2], 2 * f[0], 2 * s[0], mism]
        rows.append([t, travel, *forces, e[0], e[2], ti[0], rot, pen, snap])
    rows = np.array(rows)
    bad = np.nonzero((rows[:, 13] > PASS_THROUGH) | (rows[:, 14] > 0))[0]
    kept = rows[: bad[0]] if len(bad) else rows
    DATA.mkdir(parents=True, exist_ok=True)
    with open(DATA / RUNS[name][3], "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(COLUMNS)
        for r in kept:
            w.writerow(
                [f"{r[0]:.6f}", f"{r[1]:.5f}", *(f"{v:.6f}" for v in r[2:12]), f"{r[12]:.4f}", f"{r[13]:.5f}"]
            )
    return kept, rows[-1, 1]


def _r(v, n):
    return round(float(v), n)


def smoothed(travel, force):
    """The force on a uniform travel grid (DTRAVEL, the nominal increment), averaged over 5 grid
    points (a window of 5 increments: the zig-zag of node-to-surface contact averages out)."""
    grid = np.arange(travel[0], travel[-1] + 1e-9, md.DTRAVEL)
    return grid, np.convolve(np.interp(grid, travel, force), np.ones(5) / 5, mode="same")


def summarise(names, work):
    rows = []
    for n in names:
        if not (work / f"{n}.dat").exists() or not (work / f"{n}.sta").exists():
            continue
        d, last = extract(n, work)
        level, mu, penalty, curve = RUNS[n]
        i = int(np.argmax(d[:, 2]))
        g, a = smoothed(d[:, 1], d[:, 2])
        j = int(np.argmax(a[2:-2])) + 2
        wall = (work / f"{n}.wall").read_text().strip() if (work / f"{n}.wall").exists() else ""
        rows.append(
            dict(
                run=n,
                curve=curve,
                mesh=level,
                contact_size_mm=md.LEVELS[level]["fine"],
                mu=mu,
                penalty_N_per_mm3=penalty,
                increments=len(d),
                last_converged_travel_mm=_r(last, 4),
                curve_end_travel_mm=_r(d[-1, 1], 4),
                peak_insertion_N=_r(d[i, 2], 4),
                travel_at_peak_mm=_r(d[i, 1], 4),
                peak_5pt_avg_N=_r(a[j], 4),
                travel_at_5pt_peak_mm=_r(g[j], 4),
                lateral_per_hook_at_peak_N=_r(d[i, 3], 4),
                max_lateral_per_hook_N=_r(d[:, 3].max(), 4),
                base_RFz_at_peak_N=_r(d[i, 5], 4),
                edge_ux_at_peak_mm=_r(d[i, 9], 4),
                hook_rotation_at_peak_deg=_r(d[i, 12], 3),
                max_equilibrium_mismatch_N=f"{d[:, 8].max():.2e}",
                ccx_wall_s_and_exit=wall,
            )
        )
    if rows:
        with open(DATA / "summary.csv", "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
        for r in rows:
            print(r)


def stiffness(work, wait):
    """Lateral load (1 N per hook on the land, no block) per mesh level: edge and tip deflection."""
    out = []
    for level in sorted(md.LEVELS):
        tag = f"m{level}"
        _, info = md.write_mesh(md.LEVELS[level], DECKS, tag)
        md.write_load_deck(f"load_{tag}", tag, DECKS, info["land_nodes"])
        for f in (f"load_{tag}.inp", f"mesh_{tag}.inp"):
            shutil.copy(DECKS / f, work / f)
        env = dict(os.environ, OMP_NUM_THREADS="1", CCX_NPROC_EQUATION_SOLVER="1")
        if wait:
            wait_for_other_ccx()
        subprocess.run(["ccx", "-i", f"load_{tag}"], cwd=work, env=env, capture_output=True, check=True)
        disp = parse_dat_load(work / f"load_{tag}.dat")
        m = info["monitors"]
        edge, tip = disp[m["EDGE"]][0], disp[m["TIP"]][0]
        out.append([level, md.LEVELS[level]["fine"], info["clip_elements"], edge, tip])
        print(out[-1])
    with open(DATA / "lateral_load_check.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["mesh", "contact_size_mm", "clip_elements", "edge_ux_mm_per_N", "tip_ux_mm_per_N"])
        for r in out:
            w.writerow([*r[:3], f"{r[3] / md.LOAD_CHECK:.6f}", f"{r[4] / md.LOAD_CHECK:.6f}"])


def parse_dat_load(path):
    txt = Path(path).read_text()
    body = re.search(r"displacements \(vx,vy,vz\) for set MON and time\s+\S+\n\n((?:.+\n)+)", txt).group(1)
    return {int(r.split()[0]): _vec(r.split()[1:4]) for r in body.splitlines()}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["all", "decks", "run", "extract", "stiffness"])
    ap.add_argument("names", nargs="*", help=f"runs (default: all of {list(RUNS)})")
    ap.add_argument("--work", type=Path, default=Path("/tmp/ccx_two_hook_clip"))
    ap.add_argument("--no-wait", action="store_true", help="do not wait for other ccx processes")
    ap.add_argument("--limit", type=float, default=900, help="stop a ccx run after this many seconds")
    a = ap.parse_args()
    names = a.names or list(RUNS)
    unknown = set(names) - set(RUNS)
    if unknown:
        sys.exit(f"unknown runs {sorted(unknown)}; known: {list(RUNS)}")
    a.work.mkdir(parents=True, exist_ok=True)
    if a.what in ("all", "decks", "run"):
        write_decks(names)
    if a.what in ("all", "run"):
        for n in names:
            run_ccx(n, a.work, not a.no_wait, a.limit)
    if a.what in ("all", "run", "extract"):
        summarise(list(RUNS), a.work)
    if a.what == "stiffness":
        stiffness(a.work, not a.no_wait)


if __name__ == "__main__":
    main()
