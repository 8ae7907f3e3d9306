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
import functools
import math
import sys
from pathlib import Path

import make_deck as md
import numpy as np

sys.path.append(str(Path(__file__).resolve().parents[1]))  # benchmarks/calculix: ccx_common
import ccx_common as cc

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
    inputs = [DECKS / f"{name}.inp", DECKS / f"mesh_m{RUNS[name][0]}.inp"]
    return cc.run_ccx(name, inputs, work, wait, limit_s)


def block_distance(x, z, travel):
    """Signed distance (mm, negative inside) of the point (x, z) from the block's rounded section."""
    cz = md.Z_BLOCK - travel + md.BLOCK_H / 2
    return cc.rounded_rect_distance(x, z, 0.0, cz, md.GAP / 2, md.BLOCK_H / 2, md.BLOCK_FILLET)


def extract(name, work):
    """Write the run's curve; returns (rows kept, last converged travel). The curve stops at the
    snap: before the first increment in which the hook's land / retention-face edge (y = 0) has
    risen to the block's upper fillet (z above the block's top minus the fillet radius). From there
    the node-to-surface contact of the edge on the faceted fillet makes CalculiX stall or jump to
    a path that depends on the facets (see the README). It also stops before any increment in
    which a node of the hook's ramp, land or retention face (y = 0) lies more than PASS_THROUGH mm
    inside the block (the contact has let the block through the hook)."""
    level = RUNS[name][0]
    times, tot, disp = cc.parse_dat(work / f"{name}.dat", ("BLOCKN", "FIX", "SYMX"))
    mesh = DECKS / f"mesh_m{level}.inp"
    mon = cc.monitors_of(mesh)
    prof = cc.mesh_nodes(mesh, "PROF")
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


_r = functools.partial(cc.rounded, drop_negative_zero=False)  # the summary keeps -0.0


def summarise(names, work):
    rows = []
    for n in names:
        if not (work / f"{n}.dat").exists() or not (work / f"{n}.sta").exists():
            continue
        d, last = extract(n, work)
        level, mu, penalty, curve = RUNS[n]
        i = int(np.argmax(d[:, 2]))
        g, a = cc.smoothed(d[:, 1], d[:, 2], md.DTRAVEL)
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
        cc.solve_ccx(f"load_{tag}", [DECKS / f"load_{tag}.inp", DECKS / f"mesh_{tag}.inp"], work, wait)
        disp = cc.parse_dat_load(work / f"load_{tag}.dat")
        m = info["monitors"]
        edge, tip = disp[m["EDGE"]][0], disp[m["TIP"]][0]
        out.append([level, md.LEVELS[level]["fine"], info["clip_elements"], edge, tip])
        print(out[-1])
    with open(DATA / "lateral_load_check.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["mesh", "contact_size_mm", "clip_elements", "edge_ux_mm_per_N", "tip_ux_mm_per_N"])
        for r in out:
            w.writerow([*r[:3], f"{r[3] / md.LOAD_CHECK:.6f}", f"{r[4] / md.LOAD_CHECK:.6f}"])


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
