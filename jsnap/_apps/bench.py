"""``jsnap bench [NAME ...] [--quick [--jobs N]] [--list]``: run the benchmark scripts and
regenerate the table in ``benchmarks/README.md`` from their results.

Each benchmark is a script ``benchmarks/<name>.py`` that writes ``benchmarks/results/<stem>.json``
(and PNG charts); each runs in its own process in a full run. A full run first runs the untimed
scripts (results that are accuracies only: ``Bench.timed`` false), ``N`` at a time with
``--jobs N`` (default 1), then the timed ones one at a time, each alone on the machine, so
that their timings are undisturbed. ``--quick`` runs the scripts' quick variants (the tests run
three of them on every run and all of them with ``pytest --xslow``, so the benchmarks never
rot): smoke runs whose time is mostly XLA compilation, so they run in
``N`` worker processes (default: 2, or the CPU count if lower), each running scripts in-process
one after another, and are compiled with ``QUICK_XLA_FLAGS``; their timings are not headline
numbers.

XLA's small-loop option (``jsnap.configure_xla_cpu``): the timing scripts opt in themselves, as a
program does, before their first computation. ``jsnap`` opts its own process in, so a full run's
scripts inherit the option; the quick workers start with it (``QUICK_XLA_FLAGS``), since their
scripts share processes and XLA reads its flags once per process.

The benchmarks live in the source tree, not in the installed package: run ``jsnap bench`` from
a checkout (or set ``JSNAP_BENCHMARKS`` to the folder).
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from jsnap._apps.xla import _EXTRA, SMALL_LOOP_BYTES, SMALL_LOOP_OPTION, xla_cpu_flags


@dataclass(frozen=True)
class Bench:
    name: str
    what: str
    quick: bool  # the script has a --quick variant
    summary: object  # (result dict) -> str, the headline
    # Its results include timings (steps/s, compile, build or fit times): a full run gives it the
    # machine to itself. Untimed ones (accuracy only) run side by side, before the timed ones.
    timed: bool = True
    script: str = ""  # benchmarks/<script>.py (default: the name)
    args: tuple = ()  # arguments of a full run

    @property
    def file(self) -> str:
        return f"{self.script or self.name}.py"


def _fmt(x, p=3):
    return f"{x:.{p}g}"


def _calculix(d):
    rows = {r["run"]: r for r in d["rows"]}
    r = rows.get("jsnap full P2, mu 0") or d["rows"][0]
    out = f"peak {r['peak_N']:.3f} N vs CalculiX {r['ref_peak_N']:.3f} N (×{r['peak_ratio']:.3f})"
    sharp = rows.get("jsnap full P2, mu 0, fillet 0.02")
    if sharp:
        rel = 100 * sharp["rms_insertion_rise_N"] / sharp["ref_peak_N"]
        out += f"; sharp plug: RMS on the rise {rel:.1f} % of peak"
    others = [
        r["peak_ratio"]
        for k, r in rows.items()
        if k.startswith(("jsnap segmented", "jsnap reduced")) or "SDF" in k
    ]
    if others:
        out += f"; segmented, reduced, neural/mesh SDF ×{min(others):.3f}–{max(others):.3f}"
    for key, what in (
        ("jsnap full P1, mu 0", "P1"),
        ("vs CalculiX nonlinear geometry", "linear vs nonlinear geometry"),
    ):
        hit = [r for k, r in rows.items() if k == key or k.endswith(key)]
        if hit:
            out += f"; {what} ×{hit[0]['peak_ratio']:.2f}"
    return out


def _design_guide(d):
    ratios = [r["ratio"] for r in d["rows"]]
    ax = [r["f_axial"] for r in d["rows"]]
    ang = [r["f_angle"] for r in d["rows"]]
    return (
        f"{len(ratios)} hooks: jsnap/guide {min(ratios):.2f}–{max(ratios):.2f}; axial-moment factor "
        f"{min(ax):.2f}–{max(ax):.2f}, hook-rotation factor {min(ang):.2f}–{max(ang):.2f}"
    )


def _strain(d):
    h = d["headline"]
    arm = ", ".join(f"{k} mm ×{v:.3f}" for k, v in h["arm_peak_over_guide"].items())
    part = ", ".join(f"{k} mm ×{v:.2f}" for k, v in h["part_peak_over_guide"].items())
    root = ", ".join(f"{k}: ×{v:.2f}" for k, v in h["cantilever_root_peak_over_beam"].items())
    med = h["cost_median_seconds"]
    return (
        f"shipped hook, largest principal strain against the guide's {100 * h['guide_strain']:.2f} %: "
        f"beam theory on the simulated root load ×{h['beam_over_guide']:.3f}; FEM peak in the arm {arm}; "
        f"over the whole part {part} (the hook's edge under contact, where resolved); clamped "
        f"cantilever root peak over beam theory by elements through the thickness {root} (singular); "
        f"simulate's output step {med['displacement_only']:.2f} → {med['with_strain']:.2f} s with "
        f"the strain (load average {d['cost']['load_average_after'][0]:.1f})"
    )


def _sdf_speed(d):
    h = d["headline"]
    return (
        f"1024 points: exact mesh {h['exact_mesh_ms']:.1f} ms, neural {h['neural_ms']:.2f} ms "
        f"(×{h['speedup']:.0f})"
    )


def _sdf_accuracy(d):
    a = d["accuracy"]
    return (
        f"mean abs. error {a['mae_mm'] * 1e3:.2f} µm within {a['band_mm']} mm, median normal error "
        f"{a['normal_median_deg']:.2f}°, training {d['train_seconds']:.0f} s"
    )


def _own_parts(d):
    h = d["headline"]
    diffs = ", ".join(
        f"h {size:g}: {100 * dp:+.2f} %" for size, dp in zip(h["sizes"], h["stl_vs_tet_peak"], strict=True)
    )
    return f"STL path against the tet file, peak: {diffs}"


def _part_size(d):
    rows = []
    for family, cases in (("preset", d["preset"]), ("files", d["files"])):
        runs = [(c["k"], mu, c[f"peak_ratio_mu{mu}"], c[f"status_mu{mu}"]) for c in cases for mu in (0.0, 0.3)]
        good = [r for _, _, r, _ in runs if abs(r - 1) <= 0.05]
        span = f"{cases[0]['k']:g}..{cases[-1]['k']:g}"
        text = f"{family} k = {span}: peak / k^2 {min(good):.3f}-{max(good):.3f} of k = 1"
        again = {(c["k"], mu): c.get(f"peak_ratio_mu{mu}_stabilised") for c in cases for mu in (0.0, 0.3)}
        off = [
            f"k = {k:g}, mu {mu:g}: x{r:.3g} ({'flagged' if s != 'ok' else 'unflagged'}"
            + (f"; with contact.stabilisation 0.1 x{again[k, mu]:.3f})" if again[k, mu] is not None else ")")
            for k, mu, r, s in runs
            if abs(r - 1) > 0.05
        ]
        flagged = sorted({f"{k:g}" for k, _, r, s in runs if s != "ok" and abs(r - 1) <= 0.05})
        if flagged:
            text += f" (flagged: k = {', '.join(flagged)})"
        if off:
            text += "; off by more than 5 %: " + ", ".join(off)
        rows.append(text)
    return "; ".join(rows)


def _penetration(d):
    rows = ", ".join(
        f"{name} {max(r[f'mu{mu}']['deepest_resolutions'] for mu in (0.0, 0.3)):.2f}"
        f" ({max(r[f'mu{mu}']['longest_run_deeper_than_limit'] for mu in (0.0, 0.3))})"
        for name, r in d["parts"].items()
    )
    return (
        f"deepest point inside the rigid part, in contact resolutions (longest run of steps beyond the "
        f"DEEP_PENETRATION depth of {d['limit_resolutions']:g}; flagged above {d['limit_steps']}), mu 0 and "
        f"0.3: {rows}"
    )


def _hand_over_cost(d):
    rows = ", ".join(
        f"{name} {r['steps_per_second']['hand_over']:.0f} (x{r['cost_ratio']:.2f})"
        for name, r in d["parts"].items()
    )
    return f"steps/s with the hand-over (without it over with it): {rows}"


def _hook_family(d):
    h = d["headline"]
    return (
        f"default method on {h['hooks']} hooks nobody tuned it for: peak within 3 % of the full float64 "
        f"model's on {h['within_3_percent']}, within 3 % + the full model's own float32 spread on "
        f"{h['within_3_percent_plus_spread']}; largest error float32 {100 * h['max_abs_error_float32']:.2f} %, "
        f"median {100 * h['median_abs_error_float32']:.2f} %; "
        f"every rollout of it ok: {h['default_method_all_ok']}"
    )


def _two_hook_clip(d):
    acc = d["accuracy"]["mu 0.3"]
    red = acc["reduced_float32"]
    runs = {k: v["scene_cap"] for k, v in d["solvers"].items()}
    shipped = runs["SPG"]
    rmse = 100 * red["rmse_of_full_peak"]
    conv = ", ".join(f"{k} {v['steps_in_contact'] - v['steps_not_converged']}" for k, v in runs.items())
    text = (
        f"two-hook clip, mu 0.3: reduced float32 peak {red['peak_N']:.3g} N, RMSE {rmse:.2f} % of the full "
        f"model's peak; squeeze, steps converged of {shipped['steps_in_contact']} at the "
        f"{shipped['iteration_cap']}-iteration cap: {conv}; SPG {shipped['steps_per_second']:.0f} steps/s"
    )
    ccx = d.get("accuracy", {}).get("mu 0", {}).get("calculix")
    if ccx:
        text += f"; full mu 0 peak {ccx['full_float64']['peak_over_reference']:.3f} x CalculiX's"
    return text


def _box_lid(d):
    acc = d["accuracy"]
    tilted = next(v for k, v in acc.items() if not k.startswith("tilt 0 ") and k.endswith("mu 0.3"))
    red = tilted["reduced_float32_1.2mm"]
    pairs = tilted["pairs_shipped"]
    delay = pairs["plus_y"]["first_contact_travel_mm"] - pairs["minus_y"]["first_contact_travel_mm"]
    rate = d["speed"]["shipped_reduced_float32"]["steps_per_second"]
    text = (
        f"box lid, tilted, mu 0.3: shipped peak {tilted['shipped_float32']['peak_N']:.3g} N, {rate:.0f} "
        f"steps/s; reduced vs full (1.2 mm) RMSE {100 * red['rmse_of_full_peak']:.2f} % of the full model's "
        f"peak; the +y pair engages {delay:.2f} mm after the -y pair "
        f"(slope {tilted['predicted_delay_mm']:.2f} mm)"
    )
    ccx = acc.get("tilt 0 mu 0", {}).get("calculix")
    if ccx:
        text += f"; untilted shipped mu 0 peak {ccx['shipped_float32']['peak_over_reference']:.3f} x CalculiX's"
    light = d["speed"].get("light_against_default")
    if light:
        rows = light["rows"]
        text += (
            f"; interleaved: shipped {rows['shipped']['steps_per_second']:.0f} against "
            f"{rows['default_sampling']['steps_per_second']:.0f} steps/s at the default contact spacings "
            f"(x{rows['speedup']:.2f})"
        )
    sizes = d["speed"].get("problem_sizes")
    if sizes:
        rows = sizes["rows"]
        fine = sorted(set(rows["shipped"]["problem_sizes"]) - set(rows["without_fine_sizes"]["problem_sizes"]))
        text += (
            f"; solves cut to {', '.join(map(str, fine))} slots too: {rows['shipped']['steps_per_second']:.0f} "
            f"against {rows['without_fine_sizes']['steps_per_second']:.0f} steps/s (x{rows['speedup']:.2f})"
        )
    order = d["speed"].get("rate_against_order")
    if order:
        text += (
            f"; step time {order['us_per_step_at_no_coordinates']:.0f} us + "
            f"{order['us_per_step_per_coordinate']:.1f} us per reduced coordinate (at most "
            f"{order['steps_per_second_at_no_coordinates']:.0f} steps/s at any order)"
        )
    alone = d["speed"].get("solve_alone")
    if alone:
        text += "; the contact solve alone per step: " + ", ".join(
            f"{name.upper()} {alone[name]['us_per_step_less_call_overhead']:.0f} us"
            for name in ("spg", "apgd", "admm")
        )
    return text


def _box_lid_roundoff(d):
    lo, hi = d["rmse_rise_range"]
    return (
        f"box lid, tilted, mu 0.3, 1.2 mm: the reduced model's RMSE over the rise against the full "
        f"model's peak in rollouts that differ by round-off only (float32/float64, problem sizes): "
        f"{100 * lo:.2f}-{100 * hi:.2f} %"
    )


def _annular(d):
    mu0, mu3 = d["accuracy"]["mu 0"], d["accuracy"]["mu 0.3"]
    red = mu0["reduced_float32"]
    rate = d["speed"]["reduced_float32"]["steps_per_second"]
    ccx0, ccx3 = mu0["calculix"][0], mu3["calculix"][0]
    return (
        f"annular snap, a {d['sector_deg']:g} degree sector x {d['ring_copies']:g}: frictionless peak "
        f"{red['peak_N']:.0f} N = {ccx0['reduced_float32']['peak_over_reference']:.3f} x CalculiX's, mu 0.3 "
        f"{mu3['reduced_float32']['peak_N']:.0f} N = {ccx3['reduced_float32']['peak_over_reference']:.3f} x; "
        f"reduced vs full rise RMSE {100 * red['rmse_rise_of_full_peak']:.2f} % (mu 0), "
        f"{100 * mu3['reduced_float32']['rmse_rise_of_full_peak']:.2f} % (mu 0.3); {rate:.0f} steps/s"
    )


def _annular_spacing(d):
    rows = {r["spacing_mm"]: r["full_float64"] for r in d["rows"]}
    late = [r["averaged_over_calculix"][-1] for r in rows.values()]
    rise = [x for r in rows.values() for x in r["averaged_over_calculix"][:-1]]
    flagged = sum(r["flags"] != "ok" for r in rows.values())
    return (
        f"annular snap, frictionless, contact.spacing {min(rows):g}-{max(rows):g} mm: the force averaged "
        f"over 0.05 mm is {min(rise):.3f}-{max(rise):.3f} x CalculiX's at {d['travels_mm'][0]:g} and "
        f"{d['travels_mm'][1]:g} mm, {min(late):.2f}-{max(late):.2f} x at {d['travels_mm'][2]:g} mm; "
        f"{flagged} of {len(rows)} spacings flagged"
    )


_LATCH_FACTORS = (("f_3d_beam", "beam theory"), ("f_root", "root gives way"), ("f_ramp", "ramp turned"))


def _cable_latch(d):
    acc = d["accuracy"]["mu 0.3"]
    red, guide = acc["reduced_float32"], acc["design_guide"]
    rate = d["speed"]["reduced_float32"]["steps_per_second"]
    rmse = 100 * red["rmse_of_full_peak"]
    factors = " x".join(f"{1 / guide[k]:.2f} ({what})" for k, what in _LATCH_FACTORS)
    text = (
        f"cable latch, mu 0.3: reduced float32 peak {red['peak_N']:.3g} N, RMSE {rmse:.2f} % of the full "
        f"model's peak, {rate:.0f} steps/s; design guide {guide['guide_mating_force_N']:.2f} N "
        f"= full x{factors}"
    )
    ccx = acc.get("calculix")
    if ccx:
        text += f"; full peak {ccx['full_float64']['peak_over_reference']:.3f} x CalculiX's"
    return text


def _rigid_family(d):
    rows = list(d["cases"].values())
    ok = sum(r["grid"]["status"] == "ok" for r in rows)
    wrong = max(r["grid"]["decision_mismatches_max"] for r in rows)
    bounded = max(r["bounded"]["decision_mismatches_max"] for r in rows)
    text = (
        f"{len(rows)} cases{'' if d.get('complete', True) else ' (stopped part-way)'}: grid status ok in {ok}, "
        f"at most {wrong} candidates per step decided against the exact distance "
        f"(former bounded search: {bounded})"
    )
    moves = [abs(r["refined"]["peak_ratio"] - 1) for r in rows if "refined" in r]
    if moves:
        text += f"; peak moves at most {100 * max(moves):.1f} % under refinement"
    if all("steps_per_second" in r["grid"] for r in rows):
        text += "; steps/s grid / brute force / bounded: " + ", ".join(
            "/".join(f"{r[k]['steps_per_second']:.0f}" for k in ("grid", "brute", "bounded")) for r in rows
        )
    return text


def _pin_case(d):
    first, finest = d["runs"][0], d["runs"][-1]
    return (
        f"defaults ({first['mesh_size_mm']:.2g} mm elements): {first['status']}, "
        f"{first['peak_insertion_force_N']:.3g} N, "
        f"{100 * (first['peak_ratio_to_finest'] - 1):+.1f} % from the finest run "
        f"({finest['mesh_size_mm']:.2g} mm, spacing {finest['contact_spacing_mm']:g} mm)"
    )


def _headline_convergence(d):
    rows = [r for r in d["rows"] if "change" in r]
    parts = ", ".join(
        f"{r['case']} {100 * r['change']['peak_force_N']:.1f} / {100 * r['change']['bending_strain']:.1f}"
        f" ({100 * r['change']['part_max_strain']:.0f})"
        for r in rows
    )
    skipped = [r["case"] for r in d["rows"] if "change" not in r]
    tail = f"; not run to two meshes: {', '.join(skipped)}" if skipped else ""
    return (
        f"change from each case's mesh to 0.8 times it, % of the peak force / the bending strain (the whole "
        f"part's largest strain): {parts}{tail}"
    )


def _gallery(d):
    parts = []
    for name, r in d["presets"].items():
        mats = ", ".join(f"{m} {v['peak_insertion_force_N']:.2f}" for m, v in r["materials"].items())
        parts.append(
            f"{name}: {' + '.join(map(str, r['orders']))} of {r['full_dof']} dof, peak "
            f"{r['peak_insertion_force_N']:.2f} N at {r['travel_at_peak_mm']:.2f} mm, strain "
            f"{100 * r['peak_strain']:.2f} %, {r['steps_per_second']:.0f} steps/s (load average "
            f"{r['load_average'][1][0]:.1f}); peak by material (N): {mats}"
        )
    return "shipped presets, reduced float32: " + "; ".join(parts)


def _sdf_scene(d):
    runs = d["runs"]
    n = runs["neural"]
    rates = ", ".join(f"{k} {v['steps_per_second']:.1f}" for k, v in runs.items())
    return f"neural vs exact mesh RMSE {100 * n['rmse_vs_mesh_rel_peak']:.2f} % of peak; steps/s: {rates}"


def _contact_squeeze(d):
    worst = max(d["problems"], key=lambda p: p["condition_number"])
    s = worst["solvers"]
    apgd, pgs = s["APGD"], s["PGS"]
    cap = d["iteration_cap"]
    pgs_txt = f"{pgs['iterations_to_tol']}" if pgs.get("converged") else f"not converged in {cap}"
    return (
        f"squeeze, cond {_fmt(worst['condition_number'])}: APGD {apgd['iterations_to_tol']} iterations, "
        f"PGS {pgs_txt}"
    )


def _fem_convergence(d):
    return (
        f"P2 tip deflection → {d['richardson_mm']:.4f} mm (Richardson, order {d['observed_order']:.2f}); "
        f"CalculiX {d['calculix_converged_mm']} mm"
    )


def _stability(d):
    by = {}
    for r in d["summary"]:
        by.setdefault(r["method"], set()).add(r["class"])
    Es = sorted({r["E_MPa"] for r in d["summary"]})
    verdicts = "; ".join(f"{m}: {'/'.join(sorted(c))}" for m, c in by.items())
    return f"E {Es[0] / 1e3:g}–{Es[-1] / 1e3:g} GPa, dt 1 ms: {verdicts}"


def _reduction_speed(d):
    h = d["headline"]
    scan, call = h["light_scan_steps_per_second"], h["light_python_steps_per_second"]
    return (
        f"{h['full_dof']} dof → {' + '.join(map(str, h['orders']))}, light contact (SPG): "
        f"scan {scan['full']:.0f} → "
        f"{scan['reduced']:.0f} steps/s (×{h['scan_speedup']:.1f}; socket alone ×{h['socket_speedup']:.0f}), "
        f"Python calls {call['reduced']:.0f} steps/s"
    )


def _scale(d):
    h = d["headline"]
    out = (
        f"{h['largest_full_dof']} dof → {sum(h['largest_orders'])} coordinates: reduced in "
        f"{h['largest_build_seconds']:.0f} s, peak {h['largest_build_peak_rss_gb']:.1f} GB, "
        f"{h['largest_scan_steps_per_second']:.0f} steps/s ({h['largest_quoted_dtype']})"
    )
    lp = h.get("load_patch")
    if lp:
        out += (
            f"; with load_patch {lp['patch_mm']:g} mm: {sum(lp['largest_orders'])} coordinates, "
            f"{lp['largest_build_seconds']:.0f} s, {lp['largest_build_peak_rss_gb']:.1f} GB, "
            f"{lp['largest_scan_steps_per_second']:.0f} steps/s ({lp['largest_quoted_dtype']}), peak "
            f"{100 * (lp['largest_against_point_loads']['peak_ratio'] - 1):+.1f} % of the point loads'"
        )
    g = h.get("design_guide_hook")
    if g:
        out += (
            f"; design-guide hook ({g['full_dof']} dof) peak {g['peak_N']:.1f} N vs guide "
            f"{g['design_guide_N']:.1f} N"
        )
    return out


def _load_patch(d):
    orders = d["orders"]
    meshes = [float(k.split()[1]) for k in orders]
    coarse, fine = max(meshes), min(meshes)

    def order(mesh, patch):
        return orders[f"mesh {mesh:g} patch {patch:g}"]["orders"][1]

    growth = ", ".join(f"{p:g} mm {order(coarse, p)} → {order(fine, p)}" for p in d["patches_mm"])
    rise = "; ".join(
        f"{mu}: "
        + ", ".join(
            f"{p} mm {100 * r['rmse_rise_of_full_peak']:.1f} %"
            for p, r in c["rows"].items()
            if p != "full_float64"
        )
        for mu, c in d["box_lid_1.2mm"].items()
    )
    return (
        f"default hook's contact-segment order, {coarse:g} → {fine:g} mm mesh, by patch: {growth}; "
        f"box lid (tilted) rise RMSE against its full model: {rise}"
    )


def _reduction_accuracy(d):
    parts = [
        f"{k}: {' + '.join(map(str, v['orders']))}, RMSE {100 * v['rmse_float64']:.2f} %"
        for k, v in d["headline"].items()
    ]
    b = min(d["coupling"]["rows"], key=lambda r: r["rmse_rel_peak"])
    return "; ".join(parts) + f"; segmented at k_c {b['interface_stiffness']:.0e}: {b['rmse_rel_peak']:.1e}"


def _frequency(d):
    h = d["headline"]
    parts, names = [], []
    for mesh, rates in h["scan_steps_per_second"].items():
        names = sorted(rates)
        parts.append(f"{h['full_dof'][mesh]} dof: " + " / ".join(f"{rates[k]:.3g}" for k in names))
    models = " / ".join(names)
    return f"scan steps/s, Models {models} ({h['element']}, SDF {h['sdf_models_2_4']}): " + "; ".join(parts)


def _throughput(d):
    h = d["headline"]
    out = (
        f"{h['device']}, {h['full_dof']} → {h['dof']} dof: vmap {h['batch_1_scene_steps_per_second']:.0f} "
        f"scene-steps/s at batch 1, best {h['best_scene_steps_per_second']:.0f} at {h['best_batch']}"
    )
    if "single_scene_no_vmap_steps_per_second" in h:
        out += f" (one scene, no vmap: {h['single_scene_no_vmap_steps_per_second']:.0f})"
    if "iterations_100_best_scene_steps_per_second" in h:
        out += f"; 100 iterations: {h['iterations_100_best_scene_steps_per_second']:.0f}"
    return out


def _pareto(d):
    h = d["headline"]
    df, f, g = h["default"], h["fastest_within_threshold"], h["fastest_as_accurate_as_default"]
    out = (
        f"vs {h['reference']}: default {df['steps_per_second']:.0f} steps/s, "
        f"RMSE {100 * df['rmse_rel_peak']:.1f} % of peak"
    )
    if f:
        out += (
            f"; fastest within {100 * h['threshold_rmse_rel_peak']:g} %: {f['label']} "
            f"{f['steps_per_second']:.0f} steps/s (×{f['speedup_vs_default']:.1f})"
        )
    else:
        out += f"; none within {100 * h['threshold_rmse_rel_peak']:g} %"
    r = h.get("fastest_within_threshold_on_rise")
    if r:
        out += (
            f" (on the rise to the peak: {r['label']} {r['steps_per_second']:.0f} steps/s, "
            f"{100 * r['rmse_rise_rel_peak']:.1f} %)"
        )
    if g["label"] != df["label"]:
        out += f"; as accurate as default: {g['label']} ×{g['speedup_vs_default']:.1f}"
    return out


def _identify(d):
    h = d["headline"]
    e = h["max_abs_error"]
    ok = "all within 3 %" if h["all_within_3_percent"] else "NOT all within 3 %"
    return (
        f"{h['starts']} starts a factor 2 off, {h['fit_model']}: errors ≤ {100 * e['E']:.1f} % (E), "
        f"{100 * e['friction']:.1f} % (μ), {ok}; fit {h['seconds_median']:.0f} s median, "
        f"{h['seconds_max']:.0f} s max"
    )


def _differentiation(d):
    rows = {(r["gradient"], r["checkpoint"]): r for r in d["cost"] if r.get("tolerance", 1e-6) >= 1e-6}
    imp, unr, raw = rows[("implicit", True)], rows[("unrolled", True)], rows[("unrolled", False)]
    return (
        "value_and_grad, checkpointed: "
        f"implicit {imp['run_s']:.0f} s / {imp['temp_GB']:.1f} GB, unrolled {unr['run_s']:.0f} s / "
        f"{unr['temp_GB']:.1f} GB; unrolled without checkpoint {raw['temp_GB']:.0f} GB"
    )


def _differentiation_check(d):
    p = d["check"]["params"]
    worst = max(p, key=lambda n: p[n]["rel_error"])
    method = d.get("check_method", "full")
    return (
        f"{method} socket; {', '.join(p)}: central FD over {len(d['fd_steps'])} steps each; "
        f"worst relative error {p[worst]['rel_error']:.1e} ({worst}), where the FD plateau's own spread is "
        f"{p[worst]['plateau_spread']:.1e}"
    )


def _contact_solvers(d):
    h = d["headline"]
    parts = []
    for c, v in h.items():
        a = v["apgd"]
        others = ", ".join(
            f"{s.upper()} ×{v[s]['scan_speedup']:.2f} per step, {v[s]['iterations']:.0f} iterations, "
            f"{v[s]['capped']} capped"
            for s in v
            if s not in ("apgd", "contact_steps")
        )
        parts.append(f"{c}: APGD {a['iterations']:.0f} iterations, {a['capped']} capped; {others}")
    return "; ".join(parts)


def _contact_tolerance(d):
    parts = [
        f"{r['tolerance']:.0e}: {r['scan_us_per_step']:.0f} µs per step, "
        f"{r['iterations_mean']:.0f} iterations, RMSE {100 * r['float64_rmse_rel_peak']:.2f} %"
        for r in d["rows"]
    ]
    return "1344-dof reduced, light contact (SPG), by tolerance: " + "; ".join(parts)


def _precision(d):
    h = d["headline"]
    parts = [
        f"{m} {100 * v['float32_vs_own_float64']:+.2f} % ({v['default_dtype']})"
        for m, v in h["methods"].items()
    ]
    agree = "every default justified" if h["defaults_justified"] else "a float32 default is NOT within 1 %"
    return (
        "shipped scene, float32 peak vs the same method's float64 peak (default dtype): "
        + ", ".join(parts)
        + f"; float32 within 1 %: {', '.join(h['float32_within_1_percent']) or 'none'} ({agree})"
    )


def _xla_option(d):
    h = d["headline"]
    lo, hi = h["load_average_range"]
    rates = f"{h['without']['steps_per_second']:.0f} → {h['with']['steps_per_second']:.0f} steps/s"
    fastest = h["speedup_fastest_rollouts"]
    out = (
        f"shipped scene ({h['full_dof']} → {h['dof']} dof, {h['dtype']}): {rates} with "
        f"jsnap.configure_xla_cpu() (×{h['speedup']:.2f}; fastest rollouts ×{fastest:.2f}; "
        f"medians of {h['rounds']} rounds, load average {lo:.1f}-{hi:.1f})"
    )
    if "float64_force_max_abs_diff_rel_peak" in h:
        out += f"; float64 forces within {h['float64_force_max_abs_diff_rel_peak']:.0e} of the peak"
    return out


def _xla_kernels(d):
    h = d["headline"]
    lo, hi = d["load_average_range"]
    parts = [f"{n} {v['library_steps_per_second']:.0f} → {v['own_steps_per_second']:.0f}" for n, v in h.items()]
    return (
        "steps/s with XLA's library fusions → its own kernels (jsnap.configure_xla_cpu()): "
        + ", ".join(parts)
        + f" (medians of {d['rounds_run']} rounds, load average {lo:.1f}-{hi:.1f})"
    )


def _generic(d):
    for key in ("summary", "headline"):
        if key in d:
            return json.dumps(d[key])[:160]
    return "see JSON"


BENCHMARKS = [
    Bench("calculix_compare", "full model against CalculiX (independent FEM)", True, _calculix, timed=False),
    Bench(
        "design_guide",
        "peak force against the snap-fit design guide, gap decomposed",
        True,
        _design_guide,
        timed=False,
    ),
    Bench(
        "strain",
        "peak strain of the shipped hook against the design guide and under refinement; its cost",
        True,
        _strain,
    ),
    Bench("sdf_accuracy", "neural SDF accuracy and training time (default plug)", False, _sdf_accuracy),
    Bench(
        "hook_family",
        "the default method against the full model on drawn hooks and frictions",
        False,
        _hook_family,
        timed=False,
    ),
    Bench(
        "own_parts",
        "one part from a tet file and from an STL, under refinement",
        False,
        _own_parts,
        timed=False,
    ),
    Bench("sdf_speed", "SDF query speed: neural against exact mesh", True, _sdf_speed),
    Bench(
        "part_size",
        "the shipped hook scaled 1/16 to 16 times, as a preset and as files, against dimensional analysis",
        False,
        _part_size,
        timed=False,
    ),
    Bench(
        "penetration",
        "how deep the shipped scenes go into the rigid part, against the DEEP_PENETRATION flag's limit",
        False,
        _penetration,
        timed=False,
    ),
    Bench(
        "hand_over_cost",
        "the face points' hand-over of contact to the edges: steps/s with and without it",
        False,
        _hand_over_cost,
    ),
    Bench("contact_squeeze", "APGD against PGS on the symmetric squeeze", True, _contact_squeeze),
    Bench(
        "two_hook_clip",
        "two-hook clip preset: reduced vs full vs CalculiX, contact solvers on its squeeze",
        True,
        _two_hook_clip,
    ),
    Bench(
        "box_lid",
        "box lid preset (four hooks, tilted box): reduced vs full vs CalculiX, engagement order, speed",
        False,
        _box_lid,
    ),
    Bench(
        "box_lid_roundoff",
        "the tilted box lid's reduced model against its full model in rollouts differing by round-off",
        False,
        # Untimed, but it reads box_lid's full-model curve: run after it, with the timed ones.
        _box_lid_roundoff,
    ),
    Bench(
        "cable_latch",
        "cable latch preset: reduced vs full vs CalculiX, the design guide's gap, speed side by side",
        False,
        _cable_latch,
    ),
    Bench(
        "annular",
        "annular snap preset (a sector of the ring): reduced vs full vs CalculiX, design guide, speed",
        False,
        _annular,
    ),
    Bench(
        "annular_spacing",
        "the annular snap's force against the density of its contact candidates, against CalculiX",
        False,
        _annular_spacing,
        timed=False,
    ),
    Bench(
        "rigid_family",
        "exact contact against rigid parts nobody tuned for: decisions, forces, refinement, speed",
        True,
        _rigid_family,
        args=("--refine", "--rounds", "0"),
    ),
    Bench(
        "pin_case",
        "a cylindrical pin on a tapered hook from STL files, defaults against refined",
        True,
        _pin_case,
        timed=False,
    ),
    Bench(
        "headline_convergence",
        "the summary's peak force and bending strain at two meshes on every preset and example",
        False,
        _headline_convergence,
        timed=False,
    ),
    Bench(
        "gallery",
        "every shipped preset: deformed part by strain, force curve, orders, steps/s; force by material",
        False,
        _gallery,
    ),
    Bench(
        "contact_solvers",
        "APGD, ADMM and SPG in rollouts of the reduced scene: iterations, cap, step time",
        False,
        _contact_solvers,
    ),
    Bench(
        "contact_tolerance",
        "light contact settings over contact.tolerance: step time, iterations, force error",
        False,
        _contact_tolerance,
    ),
    Bench(
        "fem_convergence",
        "cantilever tip deflection under refinement, P1/P2",
        True,
        _fem_convergence,
        timed=False,
    ),
    Bench(
        "stability",
        "nonlinear (SVK) integrators against linear PMI (the paper's Fig. 3)",
        True,
        _stability,
        timed=False,
    ),
    Bench("reduction_speed", "segmented / reduced models: accuracy and step rate", True, _reduction_speed),
    Bench("scale", "large parts: reduced build time, peak memory, orders and step rate vs size", True, _scale),
    Bench(
        "load_patch",
        "point or patch load cases in the reduction: order against the mesh, force against the full model",
        False,
        _load_patch,
    ),
    Bench(
        "reduction_accuracy",
        "segmented / reduced against full: k_c, tolerance",
        True,
        _reduction_accuracy,
        timed=False,
    ),
    Bench(
        "precision",
        "peak force of each model in float32 and float64 (the default rollout dtype)",
        True,
        _precision,
        timed=False,
    ),
    Bench(
        "differentiation_check",
        "converged gradient through contact against central differences (default scene)",
        False,
        _differentiation_check,
        timed=False,
        script="differentiation",
        args=("--part", "check"),
    ),
    Bench(
        "differentiation",
        "gradients through contact: implicit/unrolled, checkpointed or not: cost and accuracy",
        True,
        _differentiation,
        args=("--part", "cost"),
    ),
    Bench("identify", "E and friction from a noisy force (finer full model + 5 % noise)", True, _identify),
    Bench("pareto", "speed against accuracy: force error vs steps/s over solver settings", True, _pareto),
    # After pareto: its default, neural and mesh SDF runs are these (sdf_scene.py --from-pareto).
    Bench(
        "sdf_scene",
        "default scene with each SDF: force RMSE and step rate",
        True,
        _sdf_scene,
        args=("--from-pareto",),
    ),
    Bench("frequency", "steps/s of Models 1-4, ~660 and ~1300 dof (the paper's Fig. 4)", True, _frequency),
    Bench("throughput", "batched (vmap) scene-steps/s of the reduced model vs batch size", True, _throughput),
    Bench(
        "xla_option",
        "step rate of the shipped scene with and without jsnap.configure_xla_cpu()",
        True,
        _xla_option,
    ),
    Bench(
        "xla_kernels",
        "every preset's step rate with XLA's library fusions and with its own kernels",
        True,
        _xla_kernels,
    ),
]


def benchmarks_dir() -> Path:
    env = os.environ.get("JSNAP_BENCHMARKS")
    candidates = [Path(env)] if env else []
    candidates += [Path.cwd() / "benchmarks", Path(__file__).resolve().parents[2] / "benchmarks"]
    for c in candidates:
        if c.is_dir():
            return c
    raise FileNotFoundError(
        "benchmarks/ not found: run `jsnap bench` from a jsnap checkout or set JSNAP_BENCHMARKS"
    )


def available(root: Path) -> list[Bench]:
    return [b for b in BENCHMARKS if (root / b.file).is_file()]


def _result(root: Path, name: str, quick: bool):
    for stem in ([f"{name}_quick"] if quick else []) + [name]:
        path = root / "results" / f"{stem}.json"
        if path.is_file():
            return path, json.loads(path.read_text())
    return None, None


def write_readme(root: Path) -> Path:
    """Regenerate ``benchmarks/README.md`` from the results present."""
    lines = [
        "# Benchmarks",
        "",
        "Regenerated by `jsnap bench` from `benchmarks/results/*.json` (do not edit by hand).",
        "`jsnap bench NAME` runs one script, `jsnap bench --quick` the quick variants (`pytest --xslow`),",
        "`jsnap bench` all of them. Each chart names the machine it ran on.",
        "",
        "| benchmark | what | headline (full run) | results |",
        "|---|---|---|---|",
    ]
    for b in available(root):
        path, data = _result(root, b.name, quick=False)
        if data is None:
            head, files = "not run yet", ""
        else:
            try:
                head = b.summary(data)
            except (KeyError, TypeError, ValueError, IndexError) as err:
                head = f"result file not understood ({type(err).__name__}: {err})"
            pngs = sorted(p.name for p in (root / "results").glob(f"{b.name}*.png") if "_quick" not in p.name)
            files = ", ".join(f"[{n}](results/{n})" for n in [path.name, *pngs])
        lines.append(f"| `{b.name}` | {b.what} | {head} | {files} |")
    runs = [line for line in (_times_line(root, False), _times_line(root, True)) if line]
    if runs:
        lines += ["", "Last complete runs (per-script times in `results/bench_times*.json`):", ""]
        lines += [f"- {line}" for line in runs]
    out = root / "README.md"
    out.write_text("\n".join(lines) + "\n")
    return out


def _run_in_process(argv: list[str], cwd: Path) -> int:
    """Run a benchmark script as ``__main__`` in this process; its exit status. The environment,
    ``sys.argv``, ``sys.path``, the working directory and matplotlib's figures are restored
    afterwards."""
    import runpy
    import traceback

    env, old_argv, old_cwd, old_path = dict(os.environ), sys.argv, Path.cwd(), list(sys.path)
    sys.argv = list(argv)
    sys.path.insert(0, str(Path(argv[0]).parent))  # as `python script.py` does (benchmarks/_common.py)
    os.chdir(cwd)
    try:
        runpy.run_path(argv[0], run_name="__main__")
        return 0
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except Exception:
        traceback.print_exc()
        return 1
    finally:
        os.environ.clear()
        os.environ.update(env)
        sys.argv = old_argv
        sys.path[:] = old_path
        os.chdir(old_cwd)
        if "matplotlib.pyplot" in sys.modules:
            sys.modules["matplotlib.pyplot"].close("all")
        # Free the script's compiled programs before the next one.
        import gc

        import jax

        jax.clear_caches()
        gc.collect()


def _record_times(root: Path, times: dict, quick: bool, complete: bool, wall: float, **how) -> None:
    """Merge the scripts' wall times into ``results/bench_times{_quick}.json``; a run of every
    script also records its total and ``how`` it ran (workers, compiler flags): the
    benchmarks README quotes them."""
    path = root / "results" / f"bench_times{'_quick' if quick else ''}.json"
    data = json.loads(path.read_text()) if path.is_file() else {}
    data.setdefault("scripts", {}).update(times)
    load = ", ".join(f"{v:.1f}" for v in os.getloadavg())
    stamp = {"date": time.strftime("%Y-%m-%d %H:%M"), "cpus": os.cpu_count(), "load_average_after": load, **how}
    if complete:
        data["complete_run"] = {"seconds": round(wall, 1), **stamp}
    data["last"] = stamp
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1))


def _times_line(root: Path, quick: bool) -> str | None:
    path = root / "results" / f"bench_times{'_quick' if quick else ''}.json"
    if not path.is_file():
        return None
    run = json.loads(path.read_text()).get("complete_run")
    if not run:
        return None
    what = "`jsnap bench --quick`" if quick else "`jsnap bench` (every script)"
    workers = ""
    if run.get("workers", 1) > 1:
        workers = f", {run['workers']} worker processes"
    elif run.get("untimed_workers", 1) > 1:
        workers = (
            f", the untimed scripts {run['untimed_workers']} at a time ({run['untimed_seconds'] / 60:.1f} min)"
        )
    return (
        f"{what}: {run['seconds'] / 60:.1f} min on {run['cpus']} CPU cores{workers}, {run['date']} "
        f"(load average after: {run['load_average_after']})."
    )


# The quick variants are smoke runs dominated by XLA compilation (small meshes, few steps), so
# they compile with flags that trade a little run time for much less compile time:
# - XLA's older CPU emitters: the default 2.0 mm rollout's backend compilation 2.5 -> 1.2 s, the
#   same results; they run larger models slower (the 0.8 mm default scene: 88 -> 66 steps/s).
# - LLVM at -O1 instead of -O2: that rollout's whole XLA compilation (JAX_LOG_COMPILES; with the
#   older emitters already) 4.0 -> 2.7 s at the same run time (the 1.6 mm reduced scene: 311-323
#   against 300-301 us per step). -O0 compiles in 1.4 s but runs 2.6x slower, which costs the
#   quick scripts that run for a while (calculix_compare, design_guide, stability) more than it
#   saves. LLVM's optimisations reorder float32 arithmetic, so the quick curves differ from the
#   full runs' by round-off (a contact event can move by a step).
# The full runs, whose timings are the headline numbers, keep XLA's defaults for these two.
# And XLA's small-loop option (jsnap._apps.xla), which the scripts opt into themselves
# (jsnap.configure_xla_cpu() before their first computation): the quick scripts share worker
# processes and XLA reads its flags once per process, so a script's own opt-in would come too
# late after another script's first computation (it warns and changes nothing). The workers start
# with the option, for every script alike; a full run's scripts, each in its own process, inherit
# it from the command line (`jsnap` opts in for its process) and opt in again themselves.
QUICK_XLA_FLAGS = (
    f"--xla_backend_extra_options={SMALL_LOOP_OPTION}={SMALL_LOOP_BYTES} "
    "--xla_cpu_use_fusion_emitters=false --xla_backend_optimization_level=1"
)


def quick_xla_flags(user: str) -> str:
    """``XLA_FLAGS`` for the quick runs: the user's flags with ``jsnap.configure_xla_cpu``'s
    options (``xla_cpu_flags``: the small-loop option joined to the user's
    ``--xla_backend_extra_options``, the user's own values kept), then each other flag of
    ``QUICK_XLA_FLAGS`` that the user has not set (the user's own setting of a flag wins).
    Idempotent: flags that already went through ``jsnap.configure_xla_cpu`` give the same
    result."""
    flags = xla_cpu_flags(user.strip())
    extra = [f for f in QUICK_XLA_FLAGS.split() if not f.startswith(_EXTRA) and f.split("=")[0] not in flags]
    return " ".join([flags, *extra]).strip()


@contextlib.contextmanager
def _script_env(**extra: str):
    """The environment the benchmark scripts run in: ``extra``, and JAX's persistent
    compilation cache switched off (``JAX_ENABLE_COMPILATION_CACHE=false``), whatever the
    user's environment says: the scripts report compile times, which a program loaded from a
    cache would falsify (and a run's time budget is a run that compiles). Restored afterwards."""
    extra = {"JAX_ENABLE_COMPILATION_CACHE": "false", **extra}
    old = {k: os.environ.get(k) for k in extra}
    os.environ.update(extra)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _say(line: str) -> None:
    """A progress line on stderr in one write (``print`` writes the newline apart, so the lines
    of the quick run's worker processes, which share stderr, ran into each other)."""
    sys.stderr.write(line + "\n")
    sys.stderr.flush()


def _quick_task(name: str, argv: list[str], cwd: str) -> tuple[int, float]:
    """One quick script in this worker process (its exit status and wall time)."""
    _say(f"jsnap bench: {name} ...")
    t0 = time.perf_counter()
    rc = _run_in_process(argv, Path(cwd))
    return rc, time.perf_counter() - t0


def _longest_first(root: Path, todo: list[Bench], quick: bool) -> list[Bench]:
    """Longest first by the last recorded times (unknown ones first, in listed order), so that
    parallel workers finish together."""
    path = root / "results" / f"bench_times{'_quick' if quick else ''}.json"
    last = json.loads(path.read_text()).get("scripts", {}) if path.is_file() else {}
    return sorted(todo, key=lambda b: -last.get(b.name, {}).get("seconds", float("inf")))


def _done(name: str, rc: int, dt: float) -> dict:
    """Report a finished script; its entry in ``bench_times*.json``."""
    status = "ok" if rc == 0 else f"FAILED (exit {rc})"
    _say(f"jsnap bench: {name} {status} in {dt:.0f} s")
    return {"seconds": round(dt, 1), "ok": rc == 0}


def _run_quick(root: Path, todo: list[Bench], jobs: int) -> tuple[dict, str]:
    """The quick scripts in ``jobs`` worker processes (spawned, each running its scripts one
    after another in-process and taking the next as it finishes one); per-script times and the
    XLA flags they ran with."""
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from multiprocessing import get_context

    flags = quick_xla_flags(os.environ.get("XLA_FLAGS", ""))
    times = {}
    with _script_env(XLA_FLAGS=flags):
        with ProcessPoolExecutor(max_workers=jobs, mp_context=get_context("spawn")) as pool:
            futures = {
                pool.submit(_quick_task, b.name, [str(root / b.file), "--quick"], str(root.parent)): b
                for b in _longest_first(root, todo, quick=True)
            }
            for fut in as_completed(futures):
                name = futures[fut].name
                try:
                    rc, dt = fut.result()
                except Exception as err:  # the worker died (a crash in compiled code, out of memory)
                    _say(f"jsnap bench: {name}: worker failed ({type(err).__name__}: {err})")
                    rc, dt = 1, float("nan")
                times[name] = _done(name, rc, dt)
    return {b.name: times[b.name] for b in todo if b.name in times}, flags


def _run_script(root: Path, b: Bench) -> dict:
    """One script of a full run in its own process (its timings start from a clean process)."""
    _say(f"jsnap bench: {b.name} ...")
    t0 = time.perf_counter()
    rc = subprocess.call([sys.executable, str(root / b.file), *b.args], cwd=root.parent)
    return _done(b.name, rc, time.perf_counter() - t0)


def _run_full(root: Path, todo: list[Bench], jobs: int) -> tuple[dict, dict]:
    """A full run: first the untimed scripts (accuracy only), ``jobs`` at a time, longest first
    by the last recorded times; then the timed ones one at a time, alone on the machine, in the
    listed order (a timed script may read an untimed one's results: differentiation's cost rows
    are compared with differentiation_check's converged gradient)."""
    from concurrent.futures import ThreadPoolExecutor

    untimed = _longest_first(root, [b for b in todo if not b.timed], quick=False)
    times = {}
    t0 = time.perf_counter()
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        for b, entry in zip(untimed, pool.map(lambda b: _run_script(root, b), untimed), strict=True):
            times[b.name] = {**entry, "timed": False}
    untimed_wall = time.perf_counter() - t0
    for b in todo:
        if b.timed:
            times[b.name] = {**_run_script(root, b), "timed": True}
    how = {"untimed_workers": jobs, "untimed_seconds": round(untimed_wall, 1)}
    return {b.name: times[b.name] for b in todo}, how


def main(names: list[str], quick: bool, list_only: bool, jobs: int | None = None) -> int:
    root = benchmarks_dir()
    benches = available(root)
    if list_only:
        for b in benches:
            print(f"{b.name:18s} {b.what}{'' if b.quick else '  (no quick variant)'}")
        return 0
    known = {b.name: b for b in benches}
    unknown = [n for n in names if n not in known]
    if unknown:
        print(f"jsnap bench: unknown benchmark(s) {unknown}; known: {sorted(known)}", file=sys.stderr)
        return 2
    if jobs is not None and jobs < 1:
        print(f"jsnap bench: --jobs {jobs}: give a count >= 1", file=sys.stderr)
        return 2
    # Quick: two workers by default (compilation, 1.3x faster on 2 cores). Full: one. Two at a
    # time run the untimed scripts hardly faster on a 2-core machine, memory-bound as they are
    # (about the sum of their times alone), and stretch each ~2x, incidental timings included.
    jobs = jobs or (min(2, os.cpu_count() or 1) if quick else 1)
    todo = [known[n] for n in names] if names else benches
    t_all = time.perf_counter()
    if quick:
        for b in todo:
            if not b.quick:
                print(f"jsnap bench: {b.name}: no quick variant, skipped", file=sys.stderr)
        todo = [b for b in todo if b.quick]
        jobs = min(jobs, max(len(todo), 1))
        times, flags = _run_quick(root, todo, jobs) if todo else ({}, "")
        how = {"workers": jobs, "xla_flags": flags}
    else:
        with _script_env():
            times, how = _run_full(root, todo, jobs)
    failed = [n for n, t in times.items() if not t["ok"]]
    if times:
        _record_times(root, times, quick, complete=not names, wall=time.perf_counter() - t_all, **how)
    readme = write_readme(root)
    print(f"jsnap bench: wrote {readme}", file=sys.stderr)
    return 1 if failed else 0
