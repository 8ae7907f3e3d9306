"""Tip deflection of the straight reference arm (L=10, h=1.2, b=4 mm, 3 N tip load, ABS) for
P1 and P2 under refinement; writes benchmarks/results/fem_convergence.json.

    python benchmarks/fem_convergence.py [--quick]

Meshes up to ``DIRECT_MAX_DOF`` free dofs are solved by the library's sparse direct solve
(``jsnap._build.fem.solve_static``); the larger ones (the 0.2 mm P2 mesh, 160k dofs: the direct solve
took ~4 minutes and ~10 GB here) by conjugate gradients to a relative residual of 1e-12,
preconditioned by a two-level cycle: damped Jacobi smoothing and an exact coarse solve with the
P1 element on the same mesh (P2 -> P1 by dropping the edge nodes, P1 -> P2 by linear
interpolation; ~27 iterations on every mesh). The 0.3 mm P2 mesh is solved both ways; their
difference is recorded (``cg_check``).
"""

import argparse
import json
import platform
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from jsnap._build import fem as _fem
from jsnap._geometry.cantilever import mesh_box

L, H, B, P, E, NU = 10.0, 1.2, 4.0, 3.0, 2200.0, 0.35
DIRECT_MAX_DOF = 60_000
# The edges of a 10-node tetrahedron, in skfem's (= VTK's) order of its nodes 4..9.
_EDGES = [(0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3)]


def p1_prolongation(asm) -> sp.csr_matrix:
    """(n_dof, 3 n_vertices): P1 on the P2 mesh's vertices, interpolated to every P2 node (a
    vertex keeps its value, an edge node takes the mean of its edge's two vertices)."""
    cells = asm.cells
    nv = int(cells[:, :4].max()) + 1  # skfem numbers the vertices first
    rows, cols = [np.arange(nv)], [np.arange(nv)]
    for k, (a, b) in enumerate(_EDGES):
        for end in (a, b):
            rows.append(cells[:, 4 + k])
            cols.append(cells[:, end])
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    # Each (edge node, vertex) pair appears once per cell around the edge: keep it once.
    pairs = np.unique(np.stack([rows, cols], axis=1), axis=0)
    val = np.where(pairs[:, 0] < nv, 1.0, 0.5)
    Ps = sp.csr_matrix((val, (pairs[:, 0], pairs[:, 1])), shape=(asm.nodes.shape[0], nv))
    return sp.kron(Ps, sp.identity(3), format="csr")


def solve_cg(asm, f, rtol=1e-12, sweeps=2, omega=0.4):
    """K u = f on the free dofs by preconditioned CG (see the module docstring); (u, iterations)."""
    free = asm.free
    K = asm.stiffness(E, NU)[free][:, free].tocsr()
    Pv = p1_prolongation(asm)
    Pf = Pv[free][:, free[free < Pv.shape[1]]].tocsc()  # vertex dofs are numbered first
    coarse = spla.splu((Pf.T @ K @ Pf).tocsc())
    dinv = omega / K.diagonal()

    def cycle(r):
        x = dinv * r
        for _ in range(sweeps - 1):
            x += dinv * (r - K @ x)
        x += Pf @ coarse.solve(Pf.T @ (r - K @ x))
        for _ in range(sweeps):
            x += dinv * (r - K @ x)
        return x

    count = [0]
    x, info = spla.cg(
        K,
        f[free],
        M=spla.LinearOperator(K.shape, cycle),
        rtol=rtol,
        maxiter=1000,
        callback=lambda _: count.__setitem__(0, count[0] + 1),
    )
    if info != 0:
        raise RuntimeError(f"CG did not reach rtol {rtol} in 1000 iterations (info {info})")
    u = np.zeros(asm.n_dof)
    u[free] = x
    return u, count[0]


def tip(u, f):
    return float((u[0::3] * f[0::3]).sum() / f[0::3].sum())


def deflection(el, size, both=False):
    """(free dofs, tip deflection mm, how solved, CG check or None)."""
    asm = _fem.assemble(mesh_box(H, B, L, size), el)
    f = _fem.traction_load(asm, lambda x: np.isclose(x[2], L), [P / (H * B), 0, 0])
    if asm.free.size <= DIRECT_MAX_DOF or el != "P2":  # the two-level cycle is written for P2
        d = tip(_fem.solve_static(asm, E, NU, f), f)
        if not both:
            return asm.free.size, d, "direct", None
        u, its = solve_cg(asm, f)
        return (
            asm.free.size,
            d,
            "direct",
            {"cg_tip_mm": tip(u, f), "iterations": its, "rel_diff": tip(u, f) / d - 1},
        )
    u, its = solve_cg(asm, f)
    return asm.free.size, tip(u, f), f"CG, {its} iterations", None


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    a = ap.parse_args()
    sizes = [1.2, 0.6, 0.4] if a.quick else [1.2, 1.0, 0.8, 0.6, 0.4, 0.3, 0.2]
    rows = []
    cg_check = None
    for el in ("P1", "P2"):
        for s in sizes:
            dof, d, how, check = deflection(el, s, both=(el, s) == ("P2", 0.3))
            rows.append({"element": el, "size_mm": s, "free_dof": dof, "tip_deflection_mm": d, "solver": how})
            cg_check = cg_check or (check and {"element": el, "size_mm": s, **check})
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
        "cg_check": cg_check,
        "machine": platform.node(),
    }
    stem = "fem_convergence_quick" if a.quick else "fem_convergence"  # quick never overwrites full
    path = Path(__file__).parent / "results" / f"{stem}.json"
    path.write_text(json.dumps(out, indent=2))
    print(json.dumps({k: v for k, v in out.items() if k != "rows"}, indent=2))


if __name__ == "__main__":
    main()
