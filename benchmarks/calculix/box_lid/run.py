"""CalculiX reference for jsnap's `box_lid`: write the decks, run ccx, extract the curves.

    python benchmarks/calculix/box_lid/run.py all              # decks, every run, curves, summary
    python benchmarks/calculix/box_lid/run.py decks            # only (re)write the decks
    python benchmarks/calculix/box_lid/run.py run mu0_m2       # run (and extract) some runs
    python benchmarks/calculix/box_lid/run.py extract          # curves + summary from the .dat files

Decks (mesh_<tag>.inp, <run>.inp) go to this folder's `decks/`; ccx works in --work (scratch,
default /tmp/ccx_box_lid); curves and the summary go to jsnap/data/calculix-box_lid/. ccx runs
single-threaded (OMP_NUM_THREADS=1, CCX_NPROC_EQUATION_SOLVER=1) and, by default, waits while
another ccx process runs on the machine (--no-wait to skip). A run is stopped at a time limit, or
STOP_AFTER converged increments after its curve's end (see `curve`): from the hooks' release
on, ccx's increments follow the faceted fillet (see the README).

Forces (see make_deck.py for the models):
- untilted runs, the quarter x >= 0, y >= 0 holding one whole hook: insertion force = -4 RFz of
  the block (the force resisting its motion along -z, whole lid); lateral force per hook = RFx of
  the block (outwards on the hook; the hooks' lateral forces cancel on the block); base
  reaction = the clamped bottom face's (z: 4 RFz; x: 2 RFx under the half x > 0, the whole
  base's x and y reactions are zero by symmetry); midplane force = 2 RFx of the x = 0 symmetry
  face (the force the lid's left half exerts on its right half);
- the tilted run, the half x >= 0 holding the two right hooks (y = -4 and y = +4): insertion
  force = -2 RFz of the block, and of its nodes at y < 0 and y > 0 (the hook pairs at -y and +y);
  lateral force per hook = RFx of the block's nodes at y < 0 (y > 0); base reaction: 2 RFz,
  2 RFy, 2 RFx (under the half x > 0); base_Mx_Nmm = 2 sum(y RFz - z RFy) over the clamped face's
  nodes (z = -T), the moment of the base's reactions about the x axis through the origin.
"""

from __future__ import annotations

import argparse
import csv
import functools
import math
import re
import sys
from pathlib import Path

import make_deck as md
import numpy as np

sys.path.append(str(Path(__file__).resolve().parents[1]))  # benchmarks/calculix: ccx_common
import ccx_common as cc

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[2]
DATA = REPO / "jsnap" / "data" / "calculix-box_lid"
DECKS = HERE / "decks"

# name: (mesh level, mu, tilt deg, penalty N/mm^3, curve file); `all` runs them in this order
RUNS = {
    "mu0_m1": (1, 0.0, 0.0, md.PENALTY, "lid_mu0_lin_m1_curve.csv"),
    "mu0_m2": (2, 0.0, 0.0, md.PENALTY, "lid_mu0_lin_m2_curve.csv"),
    "mu03_m2": (2, 0.3, 0.0, md.PENALTY, "lid_mu03_lin_m2_curve.csv"),
    "tilt3_m1": (1, 0.0, md.TILT, md.PENALTY, "lid_tilt3_mu0_lin_m1_curve.csv"),
    "mu0_m3": (3, 0.0, 0.0, md.PENALTY, "lid_mu0_lin_m3_curve.csv"),
}
LIMIT_S = 1500  # s, a ccx run is stopped after this long (unless --limit) ...
RUN_LIMIT_S = {"tilt3_m1": 1800}  # ... or this long
STOP_AFTER = 3  # converged increments after the curve's end before ccx is stopped
PASS_THROUGH = 0.02  # mm: a hook node deeper than this inside the block ends the curve
DECIMALS = {"plug_travel_mm": 5, "base_Mx_Nmm": 5, "moment_mismatch_Nmm": 5, "hook_penetration_mm": 5}
DECIMALS |= {c: 4 for c in ("hook_rotation_deg", "hook_rotation_minus_y_deg", "hook_rotation_plus_y_deg")}

COLUMNS = [
    "time",
    "plug_travel_mm",
    "insertion_force_N",  # -4 RFz of the block: force resisting the motion, whole lid
    "lateral_force_per_hook_N",  # RFx of the block: outwards on each hook
    "net_lateral_force_N",  # on the block, all hooks: zero by symmetry
    "base_RFz_N",  # clamped bottom face, whole lid
    "base_RFx_half_N",  # clamped bottom face under one half (x > 0); whole base: zero by symmetry
    "midplane_Fx_N",  # through the lid's x = 0 section (left half on right half)
    "equilibrium_mismatch_N",  # max over x, y, z of |block + base + symmetry faces|, whole lid
    "edge_ux_mm",  # hook's land / retention-face edge, mid-width (y = 4)
    "edge_uz_mm",
    "tip_ux_mm",  # outer top corner of the arm, mid-width
    "hook_rotation_deg",  # from the inner and outer face points at z = L, mid-width
    "hook_penetration_mm",  # deepest ramp / land / retention-face node (y = 4) inside the block
]
COLUMNS_TILT = [
    "time",
    "plug_travel_mm",
    "insertion_force_N",  # -2 RFz of the block, whole lid
    "insertion_force_minus_y_N",  # the two hooks at y = -4 (block nodes at y < 0)
    "insertion_force_plus_y_N",  # the two hooks at y = +4
    "lateral_force_per_hook_minus_y_N",  # outwards on a hook at y = -4
    "lateral_force_per_hook_plus_y_N",  # outwards on a hook at y = +4
    "base_RFz_N",  # clamped bottom face, whole lid
    "base_RFy_N",
    "base_RFx_half_N",  # under one half (x > 0)
    "midplane_Fx_N",  # through the lid's x = 0 section
    "base_Mx_Nmm",  # moment of the clamped face's reactions about the x axis through the origin
    "equilibrium_mismatch_N",  # max over x, y, z of |block + base + symmetry face|, whole lid
    "moment_mismatch_Nmm",  # |base_Mx + the block's reactions' moment (at their positions)|
    "edge_ux_minus_y_mm",  # land / retention-face edge of the hook at y = -4, mid-width
    "edge_uz_minus_y_mm",
    "edge_ux_plus_y_mm",  # the same, hook at y = +4
    "edge_uz_plus_y_mm",
    "hook_rotation_minus_y_deg",
    "hook_rotation_plus_y_deg",
    "hook_penetration_mm",  # deepest ramp / land / retention-face node of both hooks (mid-width)
]


def tag_of(name):
    level, _, tilt, _, _ = RUNS[name]
    return f"m{level}" if tilt == 0 else f"half_m{level}_tilt{tilt:g}"


def write_decks(names):
    DECKS.mkdir(exist_ok=True)
    for level, tilt in sorted({(RUNS[n][0], RUNS[n][2]) for n in names}):
        tag = f"m{level}" if tilt == 0 else f"half_m{level}_tilt{tilt:g}"
        _, info = md.write_mesh(md.LEVELS[level], DECKS, tag, tilt)
        print(f"mesh_{tag}.inp: {info['lid_elements']} C3D8I, {info['nodes']} nodes")
    for n in names:
        level, mu, tilt, penalty, _ = RUNS[n]
        md.write_deck(n, tag_of(n), mu, penalty, DECKS, md.DTRAVEL, tilt)


def run_ccx(name, work, wait, limit_s):
    """Run ccx on decks/<name>.inp in `work`; stop it after `limit_s` seconds, or once STOP_AFTER
    converged increments have followed the curve's end (the .dat file keeps every increment
    converged so far)."""

    def stop():
        try:
            rows, end = curve(name, work)
        except (FileNotFoundError, KeyError, ValueError, IndexError, AttributeError):
            return None  # nothing converged yet, or the files half written
        if end < len(rows) - STOP_AFTER:
            return f"stopped: curve ended at {rows[max(end - 1, 0), 1]:.4f} mm"
        return None

    inputs = [DECKS / f"{name}.inp", DECKS / f"mesh_{tag_of(name)}.inp"]
    check_s = 60 if RUNS[name][2] else 20  # the tilted run's .dat is large
    return cc.run_ccx(name, inputs, work, wait, limit_s, stop=stop, check_s=check_s, fresh=True)


def node_forces(path, nset, times):
    """{time: (ids, forces (n, 3))} of a node set printed node by node (RF) in a .dat file."""
    txt = Path(path).read_text()
    out = {}
    for t, body in re.findall(rf"forces \(fx,fy,fz\) for set {nset} and time\s+(\S+)\n\n((?:.+\n)+)", txt):
        t = float(t)
        if t in out:  # the first print at a time (ccx repeats the last one when it gives up)
            continue
        rows = [r.split() for r in body.splitlines()]
        out[t] = (np.array([int(r[0]) for r in rows]), np.array([[cc._float(v) for v in r[1:4]] for r in rows]))
    return {t: out[t] for t in times}


def box_distance(p, tilt, travel):
    """Signed distance (mm, negative inside) of the world point p (3,) from the block's rounded
    section (its x-z section in its own frame; the hooks are far from its ends in y)."""
    xb, _, zb = md.to_box(p[None], tilt, travel)[0]
    return cc.rounded_rect_distance(xb, zb, 0.0, 0.0, md.GAP / 2, md.BOX_H / 2, md.BOX_FILLET)


def released(p, tilt, travel):
    """Whether the deformed hook edge p (3,) has risen to the block's upper fillet (in the
    block's frame, above its top minus the fillet radius): the hook's release."""
    return md.to_box(p[None], tilt, travel)[0, 2] > md.BOX_H / 2 - md.BOX_FILLET


def _rotation(u, mon, k):
    ui, uo = u[mon[f"INNER10{k}"]], u[mon[f"OUTER10{k}"]]
    return math.degrees(math.atan2(ui[2] - uo[2], md.H + uo[0] - ui[0]))


def curve(name, work):
    """Rows (one per converged increment, COLUMNS or COLUMNS_TILT) of a run's .dat file and the
    number of rows of its curve: up to the first increment in which the hooks have released (the
    last hook, for the tilted run: its land / retention-face edge, mid-width, risen to the block's
    upper fillet) or a hook node (ramp, land, retention face, mid-width) lies more than
    PASS_THROUGH mm inside the block (the contact has let the block through)."""
    _, _, tilt, _, _ = RUNS[name]
    mesh = DECKS / f"mesh_{tag_of(name)}.inp"
    mon = cc.monitors_of(mesh)
    dat = work / f"{name}.dat"
    hooks = ("M", "P") if tilt else ("",)
    prof = {k: cc.mesh_nodes(mesh, f"PROF{k}") for k in hooks}
    hook_y = {"M": -md.Y_MID, "P": md.Y_MID, "": md.Y_MID}
    if tilt:
        times, tot, disp = cc.parse_dat(dat, ("BLOCKN", "FIX", "SYMX", "BLOCKNM", "BLOCKNP"))
        fix_xyz, blk_xyz = cc.mesh_nodes_xyz(mesh, "FIX"), cc.mesh_nodes_xyz(mesh, "BLOCKC")
        fix_f, blk_f = node_forces(dat, "FIX", times), node_forces(dat, "BLOCKC", times)
    else:
        times, tot, disp = cc.parse_dat(dat, ("BLOCKN", "FIX", "SYMX", "SYMY"))
    rows, ends = [], []
    for t in times:
        travel = t * md.stroke(tilt)
        u = disp[t]
        b, f, s = tot["BLOCKN"][t], tot["FIX"][t], tot["SYMX"][t]
        pen = -min(
            box_distance(np.array([x, hook_y[k], z]) + u[n], tilt, travel)
            for k in hooks
            for n, (x, z) in prof[k].items()
        )
        edge = {k: u[mon[f"EDGE{k}"]] for k in hooks}
        rel = {k: released(np.array([md.X_TIP, hook_y[k], md.L]) + edge[k], tilt, travel) for k in hooks}
        ends.append(pen > PASS_THROUGH or rel[hooks[-1]])
        if tilt:
            bm, bp = tot["BLOCKNM"][t], tot["BLOCKNP"][t]
            ids, rf = fix_f[t]
            p = np.array([fix_xyz[i] for i in ids])
            mx_base = 2 * np.sum(p[:, 1] * rf[:, 2] - p[:, 2] * rf[:, 1])
            ids, rf = blk_f[t]
            p = np.array([blk_xyz[i] for i in ids]) - [0.0, 0.0, travel]
            mx_block = 2 * np.sum(p[:, 1] * rf[:, 2] - p[:, 2] * rf[:, 1])
            mism = 2 * max(abs(b[0] + f[0] + s[0]), abs(b[1] + f[1]), abs(b[2] + f[2]))
            forces = [-2 * b[2], -2 * bm[2], -2 * bp[2], bm[0], bp[0], 2 * f[2], 2 * f[1], 2 * f[0], 2 * s[0]]
            rot = [_rotation(u, mon, k) for k in hooks]
            em, ep = edge["M"], edge["P"]
            edges = [em[0], em[2], ep[0], ep[2]]
            rows.append([t, travel, *forces, mx_base, mism, abs(mx_base + mx_block), *edges, *rot, pen])
        else:
            sy = tot["SYMY"][t]
            e, ti = edge[""], u[mon["TIP"]]
            mism = max(4 * abs(b[2] + f[2]), 2 * abs(b[0] + f[0] + s[0]), 4 * abs(b[1] + f[1] + sy[1]))
            forces = [-4 * b[2], b[0], 0.0, 4 * f[2], 2 * f[0], 2 * s[0], mism]
            rows.append([t, travel, *forces, e[0], e[2], ti[0], _rotation(u, mon, ""), pen])
    ends = np.nonzero(ends)[0]
    rows = np.array(rows)
    return rows, int(ends[0]) if len(ends) else len(rows)


def extract(name, work):
    """Write the run's curve (the rows before its end, see `curve`); returns (rows kept, last
    converged travel)."""
    rows, end = curve(name, work)
    kept = rows[:end]
    tilt = RUNS[name][2]
    cols = COLUMNS_TILT if tilt else COLUMNS
    DATA.mkdir(parents=True, exist_ok=True)
    with open(DATA / RUNS[name][4], "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for r in kept:
            w.writerow([f"{v:.{DECIMALS.get(c, 6)}f}" for c, v in zip(cols, r, strict=True)])
    return kept, rows[-1, 1]


_r = functools.partial(cc.rounded, drop_negative_zero=True)  # no -0.0 in the summary


def summarise(names, work):
    rows = []
    for n in names:
        if not (work / f"{n}.dat").exists() or not (work / f"{n}.sta").exists():
            continue
        d, last = extract(n, work)
        level, mu, tilt, penalty, curve_file = RUNS[n]
        i = int(np.argmax(d[:, 2]))
        g, a = cc.smoothed(d[:, 1], d[:, 2], md.DTRAVEL)
        j = int(np.argmax(a[2:-2])) + 2
        wall = (work / f"{n}.wall").read_text().strip() if (work / f"{n}.wall").exists() else ""
        row = dict(
            run=n,
            curve=curve_file,
            model="half" if tilt else "quarter",
            mesh=level,
            contact_size_mm=md.LEVELS[level]["fine"],
            mu=mu,
            tilt_deg=tilt,
            penalty_N_per_mm3=penalty,
            stroke_mm=_r(md.stroke(tilt), 4),
            increments=len(d),
            last_converged_travel_mm=_r(last, 4),
            curve_end_travel_mm=_r(d[-1, 1], 4),
            peak_insertion_N=_r(d[i, 2], 4),
            travel_at_peak_mm=_r(d[i, 1], 4),
            peak_5pt_avg_N=_r(a[j], 4),
            travel_at_5pt_peak_mm=_r(g[j], 4),
        )
        if tilt:
            im, ip = int(np.argmax(d[:, 3])), int(np.argmax(d[:, 4]))
            row |= dict(
                lateral_per_hook_at_peak_N=f"{_r(d[i, 5], 4)} / {_r(d[i, 6], 4)}",  # -y / +y
                base_RFz_at_peak_N=_r(d[i, 7], 4),
                base_Mx_at_peak_Nmm=_r(d[i, 11], 4),
                max_abs_base_Mx_Nmm=_r(np.abs(d[:, 11]).max(), 4),
                peak_minus_y_pair_N=_r(d[im, 3], 4),
                travel_at_minus_y_peak_mm=_r(d[im, 1], 4),
                peak_plus_y_pair_N=_r(d[ip, 4], 4),
                travel_at_plus_y_peak_mm=_r(d[ip, 1], 4),
                hook_rotation_at_peak_deg=f"{_r(d[i, 18], 3)} / {_r(d[i, 19], 3)}",
                max_equilibrium_mismatch_N=f"{d[:, 12].max():.2e}",
                max_moment_mismatch_Nmm=f"{d[:, 13].max():.2e}",
            )
        else:
            row |= dict(
                lateral_per_hook_at_peak_N=_r(d[i, 3], 4),
                base_RFz_at_peak_N=_r(d[i, 5], 4),
                base_Mx_at_peak_Nmm=0.0,  # zero by symmetry
                max_abs_base_Mx_Nmm=0.0,
                peak_minus_y_pair_N="",
                travel_at_minus_y_peak_mm="",
                peak_plus_y_pair_N="",
                travel_at_plus_y_peak_mm="",
                hook_rotation_at_peak_deg=_r(d[i, 12], 3),
                max_equilibrium_mismatch_N=f"{d[:, 8].max():.2e}",
                max_moment_mismatch_Nmm="",
            )
        row["ccx_wall_s_and_exit"] = wall
        rows.append(row)
    if rows:
        with open(DATA / "summary.csv", "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
        for r in rows:
            print(r)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["all", "decks", "run", "extract"])
    ap.add_argument("names", nargs="*", help=f"runs (default: all of {list(RUNS)})")
    ap.add_argument("--work", type=Path, default=Path("/tmp/ccx_box_lid"))
    ap.add_argument("--no-wait", action="store_true", help="do not wait for other ccx processes")
    ap.add_argument("--limit", type=float, default=None, help="stop a ccx run after this many seconds")
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
            run_ccx(n, a.work, not a.no_wait, a.limit or RUN_LIMIT_S.get(n, LIMIT_S))
    if a.what in ("all", "run", "extract"):
        summarise(list(RUNS), a.work)


if __name__ == "__main__":
    main()
