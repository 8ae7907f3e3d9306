"""Gradients of a whole rollout through contact: implicit against unrolled differentiation of the
contact solve, with and without checkpointing the step; and the gradient check against central
finite differences in float64.

    python benchmarks/differentiation.py [--quick]

Loss: L = Σ_k F_k² (N²), F the insertion force, over the scene's whole insertion. Gradient with
respect to E (MPa), friction, Rayleigh alpha (1/s) and beta (s), at alpha = 20 1/s and
beta = 1e-5 s (the scene's values are 0, where a central difference would need negative
damping). Full run: the default scene (P2 0.8 mm, 10 mm/s). ``--coarse``: P2 1.5 mm at 20 mm/s,
with the converged-solve cost rows too (the coarse table of docs/differentiation.md).
``--quick`` (a CI smoke run): P2 2.5 mm at 40 mm/s, one cost row (implicit, checkpointed, converged
solves), its compiled gradient reused by the check, two FD steps.

1. Cost, at the scene's contact settings (500 iterations, tolerance 1e-6): for
   contact.gradient = implicit | unrolled and the step checkpointed or not, the compiled
   ``jax.value_and_grad``'s temporary memory (XLA's memory analysis), compile time and run time
   (the faster of two runs, one in the full run; not run when it would need more than
   ``--memory-limit`` GB).
2. Gradient check: the contact solve converged (tolerance 1e-11); implicit gradient against
   central differences over a sweep of relative steps ``STEPS``. The full and coarse runs check
   the full model in modal coordinates (``CHECK_METHOD``): the same discrete equations as
   the dense path (forces within 6e-8 of its peak on the default scene, gradients within 1e-6,
   ``tests/test_modal.py``), without a dense factorisation at each of the 40 FD points (3-6 s
   each) and at half the dense step's cost. ``--quick`` checks the dense path itself.
   The contact set is discrete: a step too large straddles contact events (a contact that
   starts or stops touching, the gap term's kink), one too small drowns in the solver's
   round-off. The reference is the
   plateau: the smaller of the two consecutive steps whose quotients agree best.
3. The cost variants' gradients against that reference: how accurate each is at the default
   tolerance. The coarse run also times both ways with converged solves (tolerance 1e-11).

``--part check`` runs only 2. and writes differentiation_check{,_coarse}.{json,png} (the FD
sweep); ``--part cost`` runs only 1. and takes 2. from that file when it was made for the same
scene (3. then compares them). ``jsnap bench`` runs the check among the untimed scripts and the
cost alone on the machine, since its timings are results. ``--part noise`` (not run by
``jsnap bench``) measures what limits the check: the loss's round-off, as the second differences
of L at E (1 + k 1e-6), k = -2 .. 2, for the dense inverse (XLA's Cholesky; the redesign removed
the LAPACK route the earlier runs compared it with), and what it predicts for each parameter's
quotients. Without ``--part``, both, one after
the other. Writes benchmarks/results/differentiation{,_coarse,_quick}.{json,png}.
"""

from __future__ import annotations

import argparse
import itertools
import json
import platform
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from _common import FULL, load_scene

import jsnap
from jsnap._core import rollout as _rollout
from jsnap._core.params import params_valid
from jsnap._core.step import Prepared, _step

# XLA's small-loop option, before the first JAX computation (the committed timings have it).
jsnap.configure_xla_cpu()

OUT = Path(__file__).parent / "results"
NAMES = ("E", "friction", "alpha", "beta")
# Relative central-difference steps swept in the gradient check (see the module docstring).
STEPS = (1e-2, 1e-3, 1e-4, 1e-5, 1e-6)
DAMPING = {"alpha": 20.0, "beta": 1e-5}
TIGHT = {"contact.iterations": 20000, "contact.tolerance": 1e-11}
CHECK_METHOD = "modal"  # the gradient check's socket (see the module docstring)


def _scan_plain(model, prepared, state, controls, keep_x):
    """jsnap._core.rollout._scan without the checkpoint (reverse mode then stores every step's
    internals)."""

    def body(s, c):
        s, out = _step(model, prepared, s, c)
        return s, (out, s.x if keep_x else None)

    return jax.lax.scan(body, state, controls)


def _loss_fn(model):
    """``(loss, x0, arrays)``: ``loss(x, arrays)`` with the model's arrays an argument, not
    closed over: as constants of the program XLA would fold the dense assembly of S into it at
    every compile (~2.5 s and a 264 MB literal on the default mesh)."""
    base = model.params.replace(**DAMPING)
    arrays, static = eqx.partition(model, eqx.is_array)
    controls = model.trajectory()[1:]  # on the host, from the concrete model

    def loss(x, arrays):
        m = eqx.combine(arrays, static)
        params = base.replace(**dict(zip(NAMES, x, strict=True)))
        r = jsnap.rollout(m, params, controls=controls, dtype="float64")
        return jnp.sum(r.insertion_force**2)

    x0 = tuple(jnp.asarray(getattr(base, n)) for n in NAMES)
    return loss, x0, arrays


# Forward-pass seconds per tolerance (tight or not), timed once: the forward pass is the same
# computation for every row (the implicit gradient's custom_root runs the same iterations, and
# the checkpoint only changes what reverse mode stores).
_FORWARD_S: dict = {}


def cost(
    scene,
    gradient: str,
    checkpoint: bool,
    memory_limit_gb: float,
    repeats: int,
    tight: bool = False,
    keep=None,
    run: bool = True,
):
    """One row of the cost table; ``keep`` (a dict) receives the compiled value_and_grad and the
    jitted loss, for the gradient check to reuse (the quick run)."""
    # contact.gradient is an internal key (with_internal).
    model = jsnap.build(load_scene({"contact.gradient": gradient, **(TIGHT if tight else {})}, scene))
    loss, x0, arrays = _loss_fn(model)
    original = _rollout._scan
    if not checkpoint:
        _rollout._scan = _scan_plain
        # rollout's compiled whole (_rollout._whole) looks _scan up when it is traced: no cached trace
        jax.clear_caches()
    try:
        vg = jax.jit(jax.value_and_grad(loss))
        t0 = time.perf_counter()
        compiled = vg.lower(x0, arrays).compile()
        t_compile = time.perf_counter() - t0
        mem = compiled.memory_analysis()
        temp_gb = mem.temp_size_in_bytes / 2**30
        row = {
            "gradient": gradient,
            "checkpoint": checkpoint,
            "tolerance": model.contact.solver.tol,
            "dof": model.n_dof,
            "steps": model.n_steps,
            "compile_s": t_compile,
            "temp_GB": temp_gb,
            "argument_GB": mem.argument_size_in_bytes / 2**30,
        }
        if temp_gb > memory_limit_gb:
            row["run_s"] = None
            row["note"] = f"not run: needs {temp_gb:.1f} GB of temporaries (limit {memory_limit_gb} GB)"
        elif not run:
            row["run_s"] = None
            row["note"] = "compiled for its memory only (the same computation as checkpointed; the time budget)"
        else:
            times = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                v, g = compiled(x0, arrays)
                jax.block_until_ready(g)
                times.append(time.perf_counter() - t0)
            f = jax.jit(loss)
            if tight not in _FORWARD_S:
                jax.block_until_ready(f(x0, arrays))
                t0 = time.perf_counter()
                jax.block_until_ready(f(x0, arrays))
                _FORWARD_S[tight] = time.perf_counter() - t0
            row["forward_s"] = _FORWARD_S[tight]
            row["run_s"] = min(times)
            row["loss"] = float(v)
            row["grad"] = {n: float(gi) for n, gi in zip(NAMES, g, strict=True)}
            if keep is not None:
                scene_run = load_scene(TIGHT, scene) if tight else scene
                keep.update(vg=compiled, f=f, x0=x0, arrays=arrays, scene=scene_run)
    finally:
        if _rollout._scan is not original:
            _rollout._scan = original
            jax.clear_caches()
    print({k: v for k, v in row.items() if k != "grad"}, flush=True)
    return row


def _friction_losses(model, x0, frictions):
    """The loss at each friction (the other parameters at ``x0``).

    Friction does not enter the PMI operator, so the FD points share one ``prepare`` (on the
    default mesh ~3 s of each ~8 s evaluation). They are run one at a time: batched under
    ``vmap`` the ten points took as long as alone (measured 43 against 47 s for six), since a
    converged contact solve, not the pass over S^-1, bounds a step and a batched while-loop
    runs until its slowest member converges."""
    params = model.params.replace(**DAMPING).replace(**dict(zip(NAMES, x0, strict=True)))
    prepared = jsnap.prepare(model, params)
    controls = model.trajectory()[1:]

    @eqx.filter_jit  # the model an argument, not constants (see _loss_fn)
    def loss(model, prepared, mu):
        params = prepared.params.replace(friction=mu)
        p = Prepared(params, prepared.op, params_valid(params))
        r = jsnap.rollout(model, prepared=p, controls=controls, dtype="float64")
        return jnp.sum(r.insertion_force**2)

    return [loss(model, prepared, jnp.asarray(m, jnp.float64)) for m in frictions]


def noise(scene, check=None, k=(-2, -1, 0, 1, 2), h=1e-6):
    """Round-off of the loss: its second differences at E (1 + k h) (a smooth function's are
    ~h^2 L'' ~ 1e-11 here), for the dense inverse (``spd_inverse``: XLA's Cholesky; the host
    LAPACK route that earlier runs compared it with is gone since the redesign); with a saved
    ``check``, the central quotient's round-off error sqrt(2) sigma / (2 h |x dL/dx|) it
    predicts at each swept step, beside the measured error."""
    model = jsnap.build(load_scene(TIGHT, scene))
    loss, x0, arrays = _loss_fn(model)
    f = jax.jit(loss)
    L = np.array([float(f((x0[0] * (1 + j * h), *x0[1:]), arrays)) for j in k])
    d2 = np.diff(L, 2)
    # iid errors of size sigma give second differences of variance 6 sigma^2
    sigma = float(np.sqrt(np.mean(d2**2) / 6))
    out = {"xla_cholesky": {"loss": L.tolist(), "second_differences": d2.tolist(), "sigma": sigma}}
    print("xla_cholesky", out["xla_cholesky"], flush=True)
    out["sigma"] = sigma
    if check:
        out["predicted"] = {
            n: {
                hs: {
                    "round_off": np.sqrt(2) * sigma / (2 * float(hs) * abs(p["value"] * p["grad"])),
                    "measured": v["rel_error"],
                }
                for hs, v in p["sweep"].items()
            }
            for n, p in check["params"].items()
        }
        print(out["predicted"], flush=True)
    return out


def check(scene, steps=STEPS, compiled=None, method=None):
    """The gradient check on the converged solve; ``compiled``: a tight cost row's functions;
    ``method``: the socket (default: the scene's)."""
    if method:  # "modal" is an internal choice of solver.method (with_internal)
        scene = load_scene({"solver.method": method}, scene)
    model = jsnap.build(load_scene(TIGHT, scene))
    if compiled and compiled["scene"].to_dict() == load_scene(TIGHT, scene).to_dict():
        x0, f, arrays = compiled["x0"], compiled["f"], compiled["arrays"]
        t0 = time.perf_counter()
        v, g = compiled["vg"](x0, arrays)
    else:
        loss, x0, arrays = _loss_fn(model)
        t0 = time.perf_counter()
        v, g = jax.jit(jax.value_and_grad(loss))(x0, arrays)
        f = jax.jit(loss)
    t_grad = time.perf_counter() - t0
    out = {"loss": float(v), "grad_seconds_with_compile": t_grad, "params": {}}
    for i, n in enumerate(NAMES):
        ds = [h * float(x0[i]) for h in steps]
        points = [x0[i] + sign * d for d in ds for sign in (1, -1)]
        if n == "friction":
            losses = _friction_losses(model, x0, points)
        else:
            losses = [f((*x0[:i], p, *x0[i + 1 :]), arrays) for p in points]
        pairs = zip(steps, ds, strict=True)
        fds = {h: float((losses[2 * k] - losses[2 * k + 1]) / (2 * d)) for k, (h, d) in enumerate(pairs)}
        # The plateau: the two consecutive steps whose quotients agree best; the smaller one is
        # the reference (chosen from the differences alone, not from the gradient).
        pairs = list(itertools.pairwise(steps))
        h_big, h_ref = min(pairs, key=lambda p: abs(fds[p[1]] / fds[p[0]] - 1))
        fd = fds[h_ref]
        out["params"][n] = {
            "value": float(x0[i]),
            "grad": float(g[i]),
            "fd": fd,
            "fd_step_rel": h_ref,
            "plateau_spread": abs(fds[h_ref] / fds[h_big] - 1),
            "rel_error": abs(float(g[i]) / fd - 1),
            "sweep": {f"{h:g}": {"fd": val, "rel_error": abs(float(g[i]) / val - 1)} for h, val in fds.items()},
        }
        print(n, out["params"][n], flush=True)
    return out


def main(argv=None):
    # jsnap's rollouts are differentiated and jitted here inside the script's own programs, which
    # JAX lowers and transposes in the caller's mode: 64-bit, as every computation here ran
    # before the redesign (importing jsnap no longer switches it on for the whole process).
    with jax.enable_x64(True):
        _main(argv)


def _main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="CI smoke run: P2 2.5 mm, 40 mm/s")
    ap.add_argument("--coarse", action="store_true", help="P2 1.5 mm, 20 mm/s, converged-solve costs")
    ap.add_argument("--memory-limit", type=float, default=6.0, help="GB of temporaries above which not to run")
    ap.add_argument("--skip-cost", action="store_true")
    parts = ("all", "check", "cost", "noise")
    ap.add_argument("--part", choices=parts, default="all", help="see the module docstring")
    a = ap.parse_args(argv)
    if a.quick and a.part != "all":
        ap.error("--quick runs both parts (its check reuses the cost row's compiled gradient)")
    changes = {"solver.dtype": "float64"}
    if a.quick:
        changes |= {"solver.mesh_size": 2.5, "motion.speed": 40.0}
    elif a.coarse:
        changes |= {"solver.mesh_size": 1.5, "motion.speed": 20.0}
    # The full model (the shipped scene's method when the committed results were taken; now
    # "reduced"), in float64 (``changes``).
    scene = load_scene({**FULL, **changes})
    machine = f"{platform.machine()}, {platform.processor() or platform.system()}, {jax.devices()[0].platform}"
    stem = "differentiation" + ("_quick" if a.quick else "_coarse" if a.coarse else "")
    OUT.mkdir(exist_ok=True)
    method = None if a.quick else CHECK_METHOD
    result = {
        "machine": machine,
        "base": FULL,
        "changes": changes,
        "damping": DAMPING,
        "fd_steps": STEPS,
        "tight": TIGHT,
    }
    result["check_method"] = method or scene["solver"]["method"]
    path = OUT / f"{stem}.json"
    check_path = OUT / f"{stem}_check.json"
    # As it reads back from JSON (tuples become lists), to compare with a saved check's.
    keys = ("changes", "damping", "fd_steps", "tight", "check_method")
    header = json.loads(json.dumps({k: result[k] for k in keys}))
    if a.part == "noise":
        saved = json.loads(check_path.read_text()) if check_path.exists() else None
        same = saved and saved.get("changes") == header["changes"]
        result["noise"] = noise(scene, saved["check"] if same else None)
        (OUT / f"{stem}_noise.json").write_text(json.dumps(result, indent=2))
        return
    if a.part == "check":
        result["check"] = check(scene, STEPS, method=method)
        check_path.write_text(json.dumps(result, indent=2))
        plot_sweep(result, OUT / f"{stem}_check.png")
        return
    kept = {}
    if a.skip_cost and path.exists():
        result["cost"] = json.loads(path.read_text()).get("cost", [])
    else:
        if a.quick:  # one compiled program: the converged implicit gradient, reused by the check
            result["cost"] = [cost(scene, "implicit", True, a.memory_limit, 1, tight=True, keep=kept)]
        else:
            result["cost"] = [
                cost(scene, g, c, a.memory_limit, 2 if a.coarse else 1, run=(g, c) != ("implicit", False))
                for g in ("implicit", "unrolled")
                for c in (True, False)
            ]
        if a.coarse:  # converged solves: what an accurate gradient costs each way
            result["cost"] += [
                cost(scene, g, True, a.memory_limit, 1, tight=True) for g in ("implicit", "unrolled")
            ]
    path.write_text(json.dumps(result, indent=2))
    if a.part == "all":
        result["check"] = check(scene, STEPS[1:3] if a.quick else STEPS, kept, method=method)
        if not a.quick:
            check_path.write_text(json.dumps({**result, "cost": None}, indent=2))
            plot_sweep(result, OUT / f"{stem}_check.png")
    elif (saved := json.loads(check_path.read_text()) if check_path.exists() else {}) and all(
        saved.get(k) == v for k, v in header.items()
    ):
        result["check"] = saved["check"]
        result["check_from"] = check_path.name
    else:
        print(f"no {check_path.name} for this scene: the cost rows are not compared with a converged FD")
    if "check" in result:
        ref = {n: p["fd"] for n, p in result["check"]["params"].items()}
        for row in result["cost"]:
            if row.get("grad"):
                row["rel_error_vs_converged_fd"] = {n: abs(row["grad"][n] / ref[n] - 1) for n in NAMES}
    path.write_text(json.dumps(result, indent=2))
    plot(result, OUT / f"{stem}.png")


def _plot_errors(ax, result, rows, labels):
    """Each gradient's error against the converged central difference, per parameter."""
    chk = result["check"]["params"]
    names = list(chk)
    w = 0.8 / (1 + sum(1 for r in rows if r.get("grad")))
    ax.bar(
        np.arange(len(names)) - 0.4 + w / 2,
        [max(chk[n]["rel_error"], 1e-16) for n in names],
        w,
        label="implicit, converged solve (tol 1e-11)",
    )
    k = 1
    for r, lab in zip(rows, labels, strict=True):
        if r.get("grad"):
            e = r["rel_error_vs_converged_fd"]
            ax.bar(
                np.arange(len(names)) - 0.4 + w / 2 + k * w,
                [max(e[n], 1e-16) for n in names],
                w,
                label=lab.replace("\n", ", ") + ("" if "tol" in lab else ", tol 1e-6"),
            )
            k += 1
    ax.axhline(1e-3, color="k", ls="--", lw=0.8)
    ax.set_yscale("log")
    ax.set_xticks(np.arange(len(names)), names)
    ax.set_ylabel("|grad / central FD − 1| (FD on the converged solve)")
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=2)
    ax.grid(alpha=0.3, axis="y")


def plot_sweep(result, path):
    """|grad / FD − 1| against the relative FD step for each parameter, the reference marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for i, (n, p) in enumerate(result["check"]["params"].items()):
        hs = [float(h) for h in p["sweep"]]
        ax.loglog(hs, [max(v["rel_error"], 1e-16) for v in p["sweep"].values()], "o-", color=f"C{i}", label=n)
        ax.loglog([p["fd_step_rel"]], [max(p["rel_error"], 1e-16)], "o", ms=12, mfc="none", color=f"C{i}")
    ax.axhline(1e-3, color="k", ls="--", lw=0.8)
    ax.invert_xaxis()
    ax.set_xlabel("relative central-difference step")
    ax.set_ylabel("|implicit gradient / central FD − 1|")
    ax.legend(title="circled: the plateau (reference)", fontsize=8)
    ax.grid(alpha=0.3, which="both")
    ax.set_title(
        f"Converged gradient (tol 1e-11) against central differences\n{_what(result)}, float64 — "
        f"{result['machine']}",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _what(result):
    ch = result["changes"]
    if "solver.mesh_size" not in ch:
        return "default scene (P2 0.8 mm, 10 mm/s)"
    return f"P2 {ch['solver.mesh_size']} mm, {ch.get('motion.speed', 10):g} mm/s"


def plot(result, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["cost"]
    labels = [
        f"{r['gradient']}\n{'checkpoint' if r['checkpoint'] else 'no checkpoint'}"
        + (f"\ntol {r['tolerance']:g}" if r.get("tolerance", 1e-6) < 1e-6 else "")
        for r in rows
    ]
    fig, ax = plt.subplots(1, 3, figsize=(14, 4.8))
    x = np.arange(len(rows))
    ax[0].bar(x, [r["temp_GB"] for r in rows], color="tab:blue")
    ax[0].set_yscale("log")
    ax[0].set_ylabel("XLA temporaries of value_and_grad (GB)")
    run = [r["run_s"] if r["run_s"] is not None else 0 for r in rows]
    ax[1].bar(x, run, color="tab:orange")
    for i, r in enumerate(rows):
        if r["run_s"] is None:
            why = "memory" if "GB" in r.get("note", "") else "not timed"
            ax[1].text(i, 0, f"not run\n({why})", ha="center", va="bottom", fontsize=8)
        elif "forward_s" in r:
            ax[1].text(
                i, r["run_s"], f"{r['run_s'] / r['forward_s']:.1f}× fwd", ha="center", va="bottom", fontsize=8
            )
    ax[1].set_ylabel("value_and_grad run time (s)")
    for a in ax[:2]:
        a.set_xticks(x, labels, fontsize=8)
        a.grid(alpha=0.3, axis="y")
    if "check" in result:
        _plot_errors(ax[2], result, rows, labels)
    else:
        ax[2].text(0.5, 0.5, "no converged FD check\nfor this scene", ha="center", va="center")
        ax[2].set_axis_off()
    what = _what(result)
    fig.suptitle(f"d(Σ F²)/d(E, μ, α, β) through contact, {what}, float64 — {result['machine']}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
