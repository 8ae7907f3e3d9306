"""Run the CalculiX reference for jsnap's `annular` preset and extract its curves.

    python benchmarks/calculix/annular/run.py list
    python benchmarks/calculix/annular/run.py run mu0 mu03 ...   # or: run all
    python benchmarks/calculix/annular/run.py summary

`run` writes each case's deck (make_deck.py) into /tmp/ccx_annular/<job>/, runs ccx there
single-threaded (waiting first until no other ccx process is running on the machine), reads the
.dat file and writes the curve to jsnap/data/calculix-annular/<csv>. `summary` reads the curves
back and writes summary.csv there (peaks, travel at the peak, equilibrium mismatch, run time).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import make_deck as md

REPO = Path(__file__).resolve().parents[3]
DATA = REPO / "jsnap" / "data" / "calculix-annular"
WORK = Path("/tmp/ccx_annular")

# case -> (csv file, make_deck options); the converged frictionless and mu = 0.3 runs first.
CASES = {
    "mu0": ("annular_mu0_lin_curve.csv", dict(level=3, mu=0.0)),
    "mu03": ("annular_mu03_lin_curve.csv", dict(level=3, mu=0.3)),
    "mu0_m1": ("annular_mu0_lin_m1_curve.csv", dict(level=1, mu=0.0)),
    "mu0_m2": ("annular_mu0_lin_m2_curve.csv", dict(level=2, mu=0.0)),
    "mu0_m4": ("annular_mu0_lin_m4_curve.csv", dict(level=4, mu=0.0)),
    "mu03_m2": ("annular_mu03_lin_m2_curve.csv", dict(level=2, mu=0.3)),
    # the stick slope (elastic slip before sliding) at 1 % (the runs above), 10 % and 0.1 % of
    # the penalty, on the level-1 mesh: how much of the mu = 0.3 force is CalculiX's elastic slip
    "mu03_m1": ("annular_mu03_lin_m1_curve.csv", dict(level=1, mu=0.3)),
    "mu03_m1_stick10": ("annular_mu03_lin_m1_stick10_curve.csv", dict(level=1, mu=0.3, stick=0.1)),
    "mu03_m1_stick01": ("annular_mu03_lin_m1_stick01_curve.csv", dict(level=1, mu=0.3, stick=0.001)),
    "mu0_k10": ("annular_mu0_lin_penalty10_curve.csv", dict(level=3, mu=0.0, penalty=10 * md.PENALTY)),
    # a 10x softer penalty: about 1-2 % low, but the static solver gets through the snap
    "mu0_k01": ("annular_mu0_lin_penalty0.1_curve.csv", dict(level=3, mu=0.0, penalty=0.1 * md.PENALTY)),
    # the full 360-degree model (24 hexahedra around) at the level-2 section, up to past the peak
    "mu0_full": (
        "annular_mu0_lin_full360_m2_curve.csv",
        dict(level=2, mu=0.0, full=24, approach=0.08, stroke=0.36),
    ),
}

HEADER = [
    "time",
    "plug_travel_mm",
    "insertion_force_N",
    "radial_force_N",
    "lateral_force_x_N",
    "lateral_force_y_N",
    "base_RFx_N",
    "base_RFy_N",
    "base_RFz_N",
    "lip_low_ur_mm",
    "lip_low_uz_mm",
    "lip_high_ur_mm",
    "mouth_ur_mm",
]

_EXP3 = re.compile(r"(\d)([+-]\d{3})$")
_BLOCK = re.compile(r"^\s*(total force|displacements) \(.*\) for set (\S+) and time\s+(\S+)")


def read_dat(path: Path) -> dict[float, dict[str, list[list[float]]]]:
    """{time: {set name: rows of numbers}} from a ccx .dat file (TOTALS=ONLY force rows have
    three numbers, displacement rows a node number and three)."""
    out: dict[float, dict[str, list[list[float]]]] = {}
    rows = None
    for line in path.read_text().splitlines():
        m = _BLOCK.match(line)
        if m:
            rows = out.setdefault(float(m.group(3)), {}).setdefault(m.group(2).upper(), [])
            continue
        if rows is None:
            continue
        parts = line.split()
        if not parts:
            if rows:  # the blank line after a block's rows ends it
                rows = None
            continue
        try:  # Fortran drops the E of three-digit exponents: 1.234567-105
            rows.append([float(_EXP3.sub(r"\1E\2", x)) for x in parts])
        except ValueError:
            rows = None
    return out


def curve(dat: Path, meta: dict) -> list[list[float]]:
    """The curve's rows (HEADER) from the .dat file of a job written by make_deck.build."""
    s = meta["scale"]
    t0 = meta["monitor_theta"]
    c0, s0 = math.cos(t0), math.sin(t0)
    mon = {k: int(v) for k, v in meta["monitors"].items()}
    rows = []
    amp_t, amp_v = np.asarray(meta.get("amplitude", [(0.0, 0.0), (1.0, 1.0)])).T
    for t, sets in sorted(read_dat(dat).items()):
        bead = np.asarray(sets["BEADN"][0])
        base = np.asarray(sets["BASE"][0])
        u = {int(r[0]): r[1:] for r in sets["MON"]}
        if meta["full"]:
            radial = sum(
                sets[f"BEADT{k}"][0][0] * math.cos(th) + sets[f"BEADT{k}"][0][1] * math.sin(th)
                for k, th in enumerate(meta["bead_thetas"])
            )
            lat = (-bead[0], -bead[1])
            base_xy = (base[0], base[1])
        else:  # the sector's net x force is hoop (symmetry-plane) load, not lateral: zero by symmetry
            radial = bead[0] * s
            lat, base_xy = (0.0, 0.0), (0.0, 0.0)

        def ur(key):
            v = u[mon[key]]
            return v[0] * c0 + v[1] * s0

        rows.append(
            [
                t,
                float(np.interp(t, amp_t, amp_v)) * meta["stroke"],
                -bead[2] * s,
                radial,
                lat[0],
                lat[1],
                base_xy[0],
                base_xy[1],
                base[2] * s,
                ur("lip_low"),
                u[mon["lip_low"]][2],
                ur("lip_high"),
                ur("mouth"),
            ]
        )
    return rows


def wait_for_other_ccx(poll: float = 0.5) -> None:
    """Block while any ccx process runs on this machine (it has two cores shared with others);
    check twice before going ahead."""

    def busy() -> bool:
        return subprocess.run(["pgrep", "-x", "ccx"], capture_output=True).returncode == 0

    while True:
        while busy():
            time.sleep(poll)
        time.sleep(0.3)
        if not busy():
            return


def run_case(case: str, *, keep: bool = False) -> None:
    csv_name, opts = CASES[case]
    job = f"ann_{case}"
    work = WORK / job
    _, meta = md.build(job, work, **opts)
    env = dict(os.environ, OMP_NUM_THREADS="1", CCX_NPROC_EQUATION_SOLVER="1")
    wait_for_other_ccx()
    t0 = time.time()
    with (work / f"{job}.log").open("w") as log:
        proc = subprocess.run(["ccx", "-i", job], cwd=work, env=env, stdout=log, stderr=subprocess.STDOUT)
    rc = proc.returncode
    wall = time.time() - t0
    rows = curve(work / f"{job}.dat", meta)
    DATA.mkdir(parents=True, exist_ok=True)
    with (DATA / csv_name).open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(HEADER)
        for r in rows:
            w.writerow([f"{r[0]:.6f}", f"{r[1]:.6f}"] + [f"{x:.6g}" for x in r[2:]])
    meta.update(rc=rc, wall_s=round(wall, 1), increments=len(rows), csv=csv_name, case=case)
    meta["last_travel"] = rows[-1][1] if rows else 0.0
    runs = _runs()
    runs[case] = meta
    (WORK / "runs.json").write_text(json.dumps(runs, indent=1))
    travel = meta["last_travel"]
    print(f"{case}: rc {rc}, {len(rows)} increments to travel {travel:.4f} mm, {wall:.0f} s -> {csv_name}")


def _runs() -> dict:
    p = WORK / "runs.json"
    return json.loads(p.read_text()) if p.exists() else {}


def smooth(y: np.ndarray, n: int = 5) -> np.ndarray:
    """Centred n-point moving average (shorter at the ends)."""
    h = n // 2
    return np.array([y[max(0, i - h) : i + h + 1].mean() for i in range(len(y))])


def summary() -> None:
    runs = _runs()
    lines = []
    for case, (csv_name, opts) in CASES.items():
        p = DATA / csv_name
        if not p.exists():
            continue
        d = np.genfromtxt(p, delimiter=",", names=True)
        f, x = d["insertion_force_N"], d["plug_travel_mm"]
        k = int(np.argmax(f))
        fs = smooth(f)
        ks = int(np.argmax(fs))
        mismatch = np.max(np.abs(d["base_RFz_N"] - f))
        meta = runs.get(case, {})

        def at(column, travel, d=d, x=x):
            """Interpolated value at a travel (None beyond the curve's end)."""
            return round(float(np.interp(travel, x, d[column])), 3) if travel <= x[-1] else None

        lines.append(
            dict(
                case=case,
                csv=csv_name,
                mesh_level=opts["level"],
                lip_element_mm=md.LEVELS[opts["level"]]["fine"],
                mu=opts.get("mu", 0.0),
                penalty=opts.get("penalty", md.PENALTY),
                stick_ratio=opts.get("stick", md.STICK_RATIO) if opts.get("mu", 0.0) else None,
                model="full 360" if opts.get("full") else f"{md.THETA_S:g}-deg sector",
                peak_force_N=round(float(f[k]), 3),
                travel_at_peak_mm=round(float(x[k]), 4),
                peak_smoothed_N=round(float(fs[ks]), 3),
                travel_at_smoothed_peak_mm=round(float(x[ks]), 4),
                radial_force_at_peak_N=round(float(d["radial_force_N"][k]), 2),
                min_force_N=round(float(np.min(f)), 3),
                force_at_0p15_N=at("insertion_force_N", 0.15),
                force_at_0p20_N=at("insertion_force_N", 0.20),
                force_at_0p25_N=at("insertion_force_N", 0.25),
                radial_at_0p25_N=at("radial_force_N", 0.25),
                radial_at_0p50_N=at("radial_force_N", 0.50),
                last_travel_mm=round(float(x[-1]), 4),
                max_equilibrium_mismatch_N=float(f"{mismatch:.3g}"),
                increments=len(f),
                wall_s=meta.get("wall_s"),
                nodes=meta.get("n_nodes"),
            )
        )
    if not lines:
        print("no curves yet")
        return
    with (DATA / "summary.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(lines[0]))
        w.writeheader()
        w.writerows(lines)
    for r in lines:
        print(r)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    sub.add_parser("list", help="list the cases")
    r = sub.add_parser("run", help="run cases ('all' for every case)")
    r.add_argument("cases", nargs="+")
    sub.add_parser("summary", help="peaks and checks of the curves written so far")
    a = ap.parse_args(argv)
    if a.cmd == "list":
        for case, (csv_name, opts) in CASES.items():
            print(f"{case:10s} {csv_name:38s} {opts}")
    elif a.cmd == "run":
        cases = list(CASES) if a.cases == ["all"] else a.cases
        for case in cases:
            run_case(case)
        summary()
    else:
        summary()


if __name__ == "__main__":
    main()
