"""Tip deflection of the straight reference arm (L=10, h=1.2, b=4 mm, 3 N tip load, ABS) for
P1 and P2 under refinement; writes benchmarks/results/fem_convergence.json.

    python benchmarks/fem_convergence.py [--quick]

The 0.2 mm P2 mesh takes ~4 minutes and ~10 GB on a 2-core machine (sparse direct solve).
"""

import argparse
import json
import platform
from pathlib import Path

import numpy as np

from jsnap import _fem
from jsnap._geometry import mesh_box

L, H, B, P, E, NU = 10.0, 1.2, 4.0, 3.0, 2200.0, 0.35


def deflection(el, size):
    asm = _fem.assemble(mesh_box(H, B, L, size), el)
    f = _fem.traction_load(asm, lambda x: np.isclose(x[2], L), [P / (H * B), 0, 0])
    u = _fem.solve_static(asm, E, NU, f)
    return asm.free.size, float((u[0::3] * f[0::3]).sum() / f[0::3].sum())


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    a = ap.parse_args()
    sizes = [1.2, 0.6, 0.4] if a.quick else [1.2, 1.0, 0.8, 0.6, 0.4, 0.3, 0.2]
    rows = []
    for el in ("P1", "P2"):
        for s in sizes:
            dof, d = deflection(el, s)
            rows.append({"element": el, "size_mm": s, "free_dof": dof, "tip_deflection_mm": d})
            print(rows[-1], flush=True)
    I, G = B * H**3 / 12, E / (2 * (1 + NU))
    eb = P * L**3 / (3 * E * I)
    tim = eb + P * L / (10 * (1 + NU) / (12 + 11 * NU) * G * B * H)
    p2 = [r for r in rows if r["element"] == "P2"][-3:]
    d = np.array([r["tip_deflection_mm"] for r in p2])
    h = np.array([r["size_mm"] for r in p2])
    from scipy.optimize import brentq

    ratio = (d[1] - d[0]) / (d[2] - d[1])
    order = brentq(lambda q: (h[0] ** q - h[1] ** q) / (h[1] ** q - h[2] ** q) - ratio, 0.3, 6)
    conv = d[2] + (d[2] - d[1]) / ((h[1] / h[2]) ** order - 1)
    out = {
        "rows": rows,
        "euler_bernoulli_mm": eb,
        "timoshenko_mm": tim,
        "richardson_mm": conv,
        "observed_order": order,
        "calculix_converged_mm": 0.7695,
        "machine": platform.node(),
    }
    stem = "fem_convergence_quick" if a.quick else "fem_convergence"  # quick never overwrites full
    path = Path(__file__).parent / "results" / f"{stem}.json"
    path.write_text(json.dumps(out, indent=2))
    print(json.dumps({k: v for k, v in out.items() if k != "rows"}, indent=2))


if __name__ == "__main__":
    main()
