"""Accuracy of the segmented and reduced sockets against the full model on the same mesh.

    python benchmarks/reduction_accuracy.py [--quick]

The full model is stated (``solver.method = "full"``): the shipped scene defaults to the reduced
one since the redesign. Every rollout names its dtype.

1. Segmented (no reduction) as the interface stiffness k_c grows, ~1300-dof P2 mesh (1.6 mm):
   insertion-force RMSE against the full model (both float64) and the largest relative error
   of the static normal compliance at the contact candidate points.
2. Reduced against full, on the default mesh (0.8 mm, 5742 free dofs) and the ~1300-dof mesh,
   for three Hankel-singular-value tolerances: orders per segment (interface shapes, balanced
   and static-correction states), build time, force RMSE in float64, and in float32 (the
   scene's dtype) against the float64 full model, beside the full model's own float32 error and
   its change for E x (1 + 1e-3) (``full_stiffer_1e3``: how sharp the snap is, a tiny stiffness
   change moves it by a step).
3. The light contact configuration of benchmarks/reduction_speed.py against the default one.

RMSEs are relative to the full model's peak insertion force. Writes
benchmarks/results/reduction_accuracy.{json,png} (``_quick`` with ``--quick``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
from pathlib import Path

import jax
import numpy as np
import scipy.linalg as sla
from _common import FULL, LIGHT, load_scene

import jsnap
from jsnap._build import reduce as R
from jsnap._build.fem import assemble
from jsnap._build.model import build_model
from jsnap._core.params import lame
from jsnap._geometry.cantilever import mesh_cantilever
from jsnap._geometry.scene import connector_geometry

# XLA's small-loop option, before the first JAX computation (the committed results had it).
jsnap.configure_xla_cpu()

OUT = Path(__file__).parent / "results"


_PREPARED: dict = {}  # the PMI operator per model at its own parameters (float64 and float32 runs share it)


def _force(model, dtype="float64", params=None):
    if params is None:
        if id(model) not in _PREPARED:
            _PREPARED.clear()  # one model at a time: the default mesh's operator is 264 MB
            _PREPARED[id(model)] = (model, jsnap.prepare(model))
        res = jsnap.rollout(model, prepared=_PREPARED[id(model)][1], dtype=dtype)
    else:
        res = jsnap.rollout(model, params, dtype=dtype)
    return np.asarray(res.insertion_force, np.float64)


def _rmse(F, F0):
    return float(np.sqrt(np.mean((F - F0) ** 2)) / np.abs(F0).max())


def _normals(model):
    s = np.asarray(model.samples.stencil)
    n = np.cross(s[:, 3] - s[:, 2], s[:, 1] - s[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def full_normal_compliance(model, scene) -> np.ndarray:
    """(P,) static compliance of the full model along each candidate point's normal, mm/N."""
    # The model holds no assembly: the same one, rebuilt from the scene's mesh.
    s = scene["solver"]
    asm = assemble(mesh_cantilever(connector_geometry(scene), s["mesh_size"]), s["element"])
    lam, mu = lame(float(model.params.E), float(model.params.nu))
    f = asm.free
    assert np.array_equal(f, np.asarray(model.mesh.free))
    K = (lam * asm.K_lam + mu * asm.K_mu)[f][:, f]
    s = model.part
    nodes, w = np.asarray(s.sample_nodes), np.asarray(s.sample_weights)
    loads = np.zeros((f.size, nodes.shape[0]))
    n = _normals(model)
    for k in range(nodes.shape[1]):
        for a in range(3):
            np.add.at(loads, (3 * nodes[:, k] + a, np.arange(nodes.shape[0])), w[:, k] * n[:, a])
    lu = R._factor(K)
    return np.einsum("np,np->p", loads, lu.solve(loads))


def socket_normal_compliance(model) -> np.ndarray:
    s = model.part
    with jax.enable_x64(True):  # the part's blocks are float64
        K = np.asarray(s.stiffness(model.params.material))
    node_rows = np.asarray(s.node_rows)[np.asarray(s.sample_nodes)]
    rows = np.einsum("pk,pkdr->pdr", np.asarray(s.sample_weights), node_rows)
    rows = np.einsum("pdr,pd->pr", rows, _normals(model))
    return np.einsum("pr,rp->p", rows, sla.solve(K, rows.T, assume_a="pos"))


def coupling_table(h, kcs):
    scene = load_scene({"solver.mesh_size": h, **FULL})
    full = jsnap.build(scene)
    F0 = _force(full)
    c0 = full_normal_compliance(full, scene)
    rows = []
    for kc in kcs:
        # solver.interface_stiffness is an internal key (with_internal)
        seg = jsnap.build(load_scene({"solver.method": "segmented", "solver.interface_stiffness": kc}, scene))
        F = _force(seg)
        c = socket_normal_compliance(seg)
        rows.append(
            dict(
                interface_stiffness=kc,
                rmse_rel_peak=_rmse(F, F0),
                max_error_rel_peak=float(np.abs(F - F0).max() / np.abs(F0).max()),
                compliance_max_rel_error=float(np.max(np.abs(c / c0 - 1))),
            )
        )
        print(rows[-1], flush=True)
    return dict(mesh_size=h, full_dof=int(full.n_dof), segment_dof=list(seg.part.orders), rows=rows)


def reduction_table(h, tols, float32=True):
    """Reduced against full at mesh ``h`` for each tolerance; ``float32=False`` (the quick run)
    skips the float32 rollouts (two more compiled programs)."""
    scene = load_scene({"solver.mesh_size": h, **FULL})
    full = jsnap.build(scene)
    F64 = _force(full)
    F32 = _force(full, "float32") if float32 else None
    Fe = _force(full, params=full.params.replace(E=float(full.params.E) * (1 + 1e-3)))
    c0 = full_normal_compliance(full, scene)
    out = dict(
        mesh_size=h,
        full_dof=int(full.n_dof),
        full_peak_N=float(F64.max()),
        full_float32_rmse_rel_peak=_rmse(F32, F64) if float32 else None,
        full_stiffer_1e3_rmse_rel_peak=_rmse(Fe, F64),
        insertion_force_full=F64.tolist(),
        travel=(np.arange(1, F64.size + 1) * full.dt * scene["motion"]["speed"]).tolist(),
        rows=[],
    )
    print({k: v for k, v in out.items() if k not in ("insertion_force_full", "travel", "rows")}, flush=True)
    for tol in tols:
        red, report = build_model(load_scene({"solver.method": "reduced", "solver.hsv_tolerance": tol}, scene))
        info = report.reduction
        F = _force(red)
        c = socket_normal_compliance(red)
        row = dict(
            hsv_tolerance=tol,
            orders=list(red.part.orders),
            segments=[{k: v for k, v in s.items() if k != "hsv"} for s in info["segments"]],
            interface_shapes=info["interface_shapes"],
            build_seconds=info["seconds"],
            rmse_rel_peak_float64=_rmse(F, F64),
            rmse_rel_peak_float32=_rmse(_force(red, "float32"), F64) if float32 else None,
            peak_N=float(F.max()),
            compliance_max_rel_error=float(np.max(np.abs(c / c0 - 1))),
            hsv_contact_segment=info["segments"][0]["hsv"][:40],
            insertion_force=F.tolist(),
        )
        out["rows"].append(row)
        print({k: v for k, v in row.items() if k not in ("insertion_force", "hsv_contact_segment")}, flush=True)
    return out


def light_contact(h, F0):
    """The light contact settings against the default ones (``F0``: the full model's force)."""
    scene = load_scene({"solver.mesh_size": h, **FULL})
    light = jsnap.build(load_scene(LIGHT, scene))
    red_light = jsnap.build(load_scene({**LIGHT, "solver.method": "reduced"}, scene))
    out = dict(
        mesh_size=h,
        full_light_vs_full_default=_rmse(_force(light), F0),
        reduced_light_vs_full_default=_rmse(_force(red_light), F0),
        reduced_light_float32_vs_full_default=_rmse(_force(red_light, "float32"), F0),
        reduced_light_orders=list(red_light.part.orders),
    )
    print(out, flush=True)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--quick", action="store_true", help="CI smoke run: 780-dof mesh, one k_c, one tolerance, float64 only"
    )
    a = ap.parse_args(argv)
    stem = "reduction_accuracy_quick" if a.quick else "reduction_accuracy"
    kcs = [1e8] if a.quick else [1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e10]
    with tempfile.TemporaryDirectory() as cache:
        os.environ["JSNAP_CACHE"] = cache
        result = dict(coupling=coupling_table(2.0 if a.quick else 1.6, kcs), reduction=[], light=[])
        for h in [2.0] if a.quick else [0.8, 1.6]:
            result["reduction"].append(
                reduction_table(h, [1e-2] if a.quick else [3e-2, 1e-2, 3e-3], float32=not a.quick)
            )
            if not a.quick:
                result["light"].append(
                    light_contact(h, np.asarray(result["reduction"][-1]["insertion_force_full"]))
                )
    result["machine"] = f"{platform.machine()}, {os.cpu_count()} CPU cores, {jax.devices()[0].platform}"
    default = [r for t in result["reduction"] for r in t["rows"] if r["hsv_tolerance"] == 1e-2]
    result["headline"] = {
        f"{t['full_dof']} dof": {
            "orders": r["orders"],
            "rmse_float64": round(r["rmse_rel_peak_float64"], 4),
            "rmse_float32": r["rmse_rel_peak_float32"] and round(r["rmse_rel_peak_float32"], 4),
        }
        for t, r in zip(result["reduction"], default, strict=True)
    }
    OUT.mkdir(exist_ok=True)
    (OUT / f"{stem}.json").write_text(json.dumps(result))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tables = result["reduction"]
    fig, axes = plt.subplots(1, len(tables) + 1, figsize=(6 * (len(tables) + 1), 4.5))
    for ax, t in zip(axes, tables, strict=False):
        ax.plot(t["travel"], t["insertion_force_full"], "k", lw=2, label=f"full, {t['full_dof']} dof")
        for r in t["rows"]:
            ax.plot(
                t["travel"],
                r["insertion_force"],
                lw=1,
                label=f"reduced, tol {r['hsv_tolerance']:g}: {' + '.join(map(str, r['orders']))} "
                f"(RMSE {100 * r['rmse_rel_peak_float64']:.2f} %)",
            )
        ax.set_xlabel("plug travel (mm)")
        ax.set_ylabel("insertion force (N)")
        ax.set_title(f"P2 mesh {t['mesh_size']} mm (float64)", fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    c = result["coupling"]["rows"]
    ax = axes[-1]
    kc = [r["interface_stiffness"] for r in c]
    ax.loglog(kc, [r["rmse_rel_peak"] for r in c], "o-", label="force RMSE / peak")
    ax.loglog(
        kc,
        [r["compliance_max_rel_error"] for r in c],
        "s--",
        label="max rel. error, normal compliance",
    )
    ax.axhline(1e-3, color="0.5", lw=0.7)
    ax.set_xlabel("interface stiffness k_c (N/mm)")
    ax.set_title(f"segmented vs full, {result['coupling']['full_dof']} dof (float64)", fontsize=9)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.suptitle(f"Reduction accuracy ({result['machine']})", fontsize=9)
    fig.tight_layout()
    fig.savefig(OUT / f"{stem}.png", dpi=120)


if __name__ == "__main__":
    main()
