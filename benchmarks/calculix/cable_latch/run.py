"""CalculiX reference for jsnap's `cable_latch`: write the decks, run ccx, extract the curves.

    python benchmarks/calculix/cable_latch/run.py all            # decks, every run, curves, summary
    python benchmarks/calculix/cable_latch/run.py decks          # only (re)write the decks
    python benchmarks/calculix/cable_latch/run.py run mu0_m3     # run (and extract) some runs
    python benchmarks/calculix/cable_latch/run.py extract        # curves + summary from the .dat files
    python benchmarks/calculix/cable_latch/run.py stiffness      # lateral-load check per mesh level

Decks (mesh_m<level>.inp, <run>.inp) go to this folder's `decks/`; ccx works in --work (scratch,
default /tmp/ccx_cable_latch); curves and the summary go to jsnap/data/calculix-cable_latch/.
ccx runs single-threaded (OMP_NUM_THREADS=1, CCX_NPROC_EQUATION_SOLVER=1) and, by default, waits
while another ccx process runs on the machine (--no-wait to skip). A run is stopped at a time limit
or once the catch has gone through the lip (see run_ccx): ccx's later increments are no physical
path.

The model is a half (y >= 0; see make_deck.py); the curves give the whole latch: insertion
force = -2 RFz of the lip (the force resisting its motion along -z); lateral force = 2 RFx of
the lip (the x force of the lip on the latch: negative, the lip pushes the catch towards the plug
body; jsnap's `lateral_force` is the latch's force on the rigid part, the opposite sign); base
reaction = the clamped back face's reaction (2 RFx, 2 RFz).
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
DATA = REPO / "jsnap" / "data" / "calculix-cable_latch"
DECKS = HERE / "decks"

# name: (mesh level, mu, penalty N/mm^3, curve file)
RUNS = {
    "mu0_m1": (1, 0.0, md.PENALTY, "latch_mu0_lin_m1_curve.csv"),
    "mu0_m2": (2, 0.0, md.PENALTY, "latch_mu0_lin_m2_curve.csv"),
    "mu0_m3": (3, 0.0, md.PENALTY, "latch_mu0_lin_curve.csv"),
    "mu03_m2": (2, 0.3, md.PENALTY, "latch_mu03_lin_m2_curve.csv"),
    "mu03_m3": (3, 0.3, md.PENALTY, "latch_mu03_lin_curve.csv"),
    "mu0_m2_K10": (2, 0.0, 10 * md.PENALTY, "latch_mu0_lin_m2_K10_curve.csv"),
}
LIMIT_S = 900  # s, a ccx run is stopped after this long (unless --limit) ...
RUN_LIMIT_S = {"mu0_m2_K10": 600}  # ... or this long: the penalty check crawls (cut increments)

COLUMNS = [
    "time",
    "plug_travel_mm",
    "insertion_force_N",  # -2 RFz of the lip: force resisting its motion along -z
    "lateral_force_N",  # 2 RFx of the lip: x force of the lip on the latch (negative: inwards)
    "base_RFx_N",  # clamped back face, whole latch
    "base_RFz_N",
    "equilibrium_mismatch_N",  # max over x, z of |lip + base reactions|, whole latch
    "edge_ux_mm",  # catch's land / retention-face edge, mid-width (y = 0)
    "edge_uz_mm",
    "landtop_ux_mm",  # catch's ramp / land edge, mid-width
    "landtop_uz_mm",
    "tip_ux_mm",  # the arm's free end, outer corner
    "catch_rotation_deg",  # from the arm's inner and outer face points at z = Z_RET
    "catch_penetration_mm",  # deepest catch / outer-face node (y = 0) inside the lip
]
PASS_THROUGH = 0.02  # mm: a catch node deeper than this inside the lip ends the curve
STOP_AFTER = 3  # converged increments after the catch went through the lip before ccx is stopped
LAND_MARGIN = 0.02  # mm: the land phase's ends left out of its means (contact changing faces)


def write_decks(names):
    DECKS.mkdir(exist_ok=True)
    for level in sorted({RUNS[n][0] for n in names}):
        _, info = md.write_mesh(md.LEVELS[level], DECKS, f"m{level}")
        print(f"mesh_m{level}.inp: {info['latch_elements']} C3D8I, {info['nodes']} nodes")
    for n in names:
        level, mu, penalty, _ = RUNS[n]
        md.write_deck(n, f"m{level}", mu, penalty, DECKS, md.DTRAVEL)


def run_ccx(name, work, wait, limit_s):
    """Run ccx on decks/<name>.inp in `work`; stop it after `limit_s` seconds, or once STOP_AFTER
    converged increments have followed the first one in which the catch lies inside the lip
    (the contact has let the lip through: the rest is not a physical path; the .dat file keeps
    every increment converged so far)."""

    def stop():
        at = _passed_through(name, work)
        return None if at is None else f"stopped: catch through the lip at {at:.4f} mm"

    inputs = [DECKS / f"{name}.inp", DECKS / f"mesh_m{RUNS[name][0]}.inp"]
    return cc.run_ccx(name, inputs, work, wait, limit_s, stop=stop, fresh=True)


def _passed_through(name, work):
    """Travel of the first converged increment with the catch inside the lip, once STOP_AFTER
    converged increments have followed it; else None (also while the files are half written)."""
    try:
        rows = curve(name, work)
    except (FileNotFoundError, KeyError, ValueError, IndexError, AttributeError):
        return None
    bad = np.nonzero(rows[:, 13] > PASS_THROUGH)[0]
    if len(bad) and len(rows) - bad[0] > STOP_AFTER:
        return rows[bad[0], 1]
    return None


def lip_distance(x, z, travel):
    """Signed distance (mm, negative inside) of the point (x, z) from the lip's rounded section."""
    cx = md.X_OUT + md.LIP_T / 2
    cz = md.Z_LIP - travel + md.LIP_H / 2
    return cc.rounded_rect_distance(x, z, cx, cz, md.LIP_T / 2, md.LIP_H / 2, md.LIP_FILLET)


def curve(name, work):
    """Rows (one per converged increment, the COLUMNS) of a run's .dat file."""
    level = RUNS[name][0]
    times, tot, disp = cc.parse_dat(work / f"{name}.dat", ("LIPN", "FIX"))
    mesh = DECKS / f"mesh_m{level}.inp"
    mon = cc.monitors_of(mesh)
    prof = cc.mesh_nodes(mesh, "PROF")
    rows = []
    for t in times:
        b, f = tot["LIPN"][t], tot["FIX"][t]
        u = disp[t]
        e, lt, ti, ui, uo = (u[mon[k]] for k in ("EDGE", "LANDTOP", "TIP", "INNER4", "OUTER4"))
        rot = math.degrees(math.atan2(ui[2] - uo[2], md.H + uo[0] - ui[0]))
        mism = 2 * max(abs(b[0] + f[0]), abs(b[2] + f[2]))
        travel = t * md.STROKE
        pen = -min(lip_distance(x + u[n][0], z + u[n][2], travel) for n, (x, z) in prof.items())
        forces = [-2 * b[2], 2 * b[0], 2 * f[0], 2 * f[2], mism]
        rows.append([t, travel, *forces, e[0], e[2], lt[0], lt[2], ti[0], rot, pen])
    return np.array(rows)


def extract(name, work):
    """Write the run's curve; returns (rows kept, last converged travel). The curve keeps every
    converged increment up to the first one in which a node of the catch's ramp, land or
    retention face or of the arm's outer face below the catch (y = 0) lies more than
    PASS_THROUGH mm inside the lip (the contact has let the lip through the catch; the outer face
    is in no contact pair)."""
    rows = curve(name, work)
    bad = np.nonzero(rows[:, 13] > PASS_THROUGH)[0]
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


_r = functools.partial(cc.rounded, drop_negative_zero=True)  # no -0.0 in the summary


def land_means(d):
    """Mean insertion and lateral force while the lip's flat inner side slides over the catch's
    land: the land's upper edge (deformed, y = 0) level with the side, LAND_MARGIN mm inside its
    ends (nan if the curve has no such increment)."""
    lo = md.Z_LIP - d[:, 1] + md.LIP_FILLET  # the side's ends
    hi = lo + md.LIP_H - 2 * md.LIP_FILLET
    z = md.Z_FLAT + d[:, 10]
    m = (z > lo + LAND_MARGIN) & (z < hi - LAND_MARGIN)
    if not m.any():
        return math.nan, math.nan
    return d[m, 2].mean(), d[m, 3].mean()


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
        land_f, land_lat = land_means(d)
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
                lateral_at_peak_N=_r(d[i, 3], 4),
                max_abs_lateral_N=_r(np.abs(d[:, 3]).max(), 4),
                land_mean_insertion_N=_r(land_f, 4),
                land_mean_lateral_N=_r(land_lat, 4),
                base_RFz_at_peak_N=_r(d[i, 5], 4),
                edge_ux_at_peak_mm=_r(d[i, 7], 4),
                landtop_ux_at_peak_mm=_r(d[i, 9], 4),
                catch_rotation_at_peak_deg=_r(d[i, 12], 3),
                max_equilibrium_mismatch_N=f"{d[:, 6].max():.2e}",
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
    """Lateral load (1 N on the whole latch, on the land, -x, no lip) per mesh level: land edge
    and free-end deflection."""
    out = []
    for level in sorted(md.LEVELS):
        tag = f"m{level}"
        _, info = md.write_mesh(md.LEVELS[level], DECKS, tag)
        md.write_load_deck(f"load_{tag}", tag, DECKS, info["land_nodes"])
        cc.solve_ccx(f"load_{tag}", [DECKS / f"load_{tag}.inp", DECKS / f"mesh_{tag}.inp"], work, wait)
        disp = cc.parse_dat_load(work / f"load_{tag}.dat")
        m = info["monitors"]
        edge, top, tip = disp[m["EDGE"]][0], disp[m["LANDTOP"]][0], disp[m["TIP"]][0]
        out.append([level, md.LEVELS[level]["fine"], info["latch_elements"], edge, top, tip])
        print(out[-1])
    DATA.mkdir(parents=True, exist_ok=True)
    with open(DATA / "lateral_load_check.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        per_n = ["edge_ux_mm_per_N", "landtop_ux_mm_per_N", "tip_ux_mm_per_N"]
        w.writerow(["mesh", "contact_size_mm", "latch_elements", *per_n])
        for r in out:
            w.writerow([*r[:3], *(f"{v / md.LOAD_CHECK:.6f}" for v in r[3:])])


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["all", "decks", "run", "extract", "stiffness"])
    ap.add_argument("names", nargs="*", help=f"runs (default: all of {list(RUNS)})")
    ap.add_argument("--work", type=Path, default=Path("/tmp/ccx_cable_latch"))
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
    if a.what == "stiffness":
        stiffness(a.work, not a.no_wait)


if __name__ == "__main__":
    main()
