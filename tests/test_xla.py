"""XLA:CPU's small-loop and own-kernels options (jsnap._apps.xla): an explicit opt-in, never a
side effect.

``import jsnap`` changes no process-wide setting: neither ``XLA_FLAGS`` nor
``jax_enable_x64``. ``jsnap.configure_xla_cpu()`` sets the options when called before JAX starts
its CPU backend ("set"), keeps the user's own values ("user" when both are given), and warns and
changes nothing when called too late ("late"). Each check runs in a fresh interpreter: both
settings belong to the whole process.
"""

import json
import os
import subprocess
import sys
import textwrap

import pytest

from jsnap._apps import xla as _xla

OPTION = f"{_xla.SMALL_LOOP_OPTION}={_xla.SMALL_LOOP_BYTES}"
# What configure_xla_cpu adds after the small-loop option (nothing where jaxlib has no such flag).
OWN = f" {_xla.LIBRARY_FLAG}=" if _xla.library_flag_known() else ""


@pytest.mark.parametrize(
    "flags, expected",
    [
        ("", f"--xla_backend_extra_options={OPTION}"),
        (
            "--xla_cpu_use_fusion_emitters=false",
            f"--xla_cpu_use_fusion_emitters=false --xla_backend_extra_options={OPTION}",
        ),
        # The user's extra options are kept, ours joins their list.
        ("--xla_backend_extra_options=foo=1 --x=2", f"--xla_backend_extra_options=foo=1,{OPTION} --x=2"),
        ("--xla_backend_extra_options=", f"--xla_backend_extra_options={OPTION}"),
        # The user's own value wins.
        (
            f"--xla_backend_extra_options={_xla.SMALL_LOOP_OPTION}=0",
            f"--xla_backend_extra_options={_xla.SMALL_LOOP_OPTION}=0",
        ),
    ],
)
def test_option_joins_the_users_flags(flags, expected):
    assert _xla.with_small_loop_option(flags) == expected


# Imports jsnap, records XLA_FLAGS and jax_enable_x64, runs `{action}` (which may set `returned`),
# then compiles a loop whose buffers (a 64 x 64 float32 carry, 16 kB) lie between XLA's own
# limit (1 kB) and jsnap's: one kernel ("xla_cpu_small_call") only with jsnap's setting. Prints
# one JSON line.
_PROBE = textwrap.dedent(
    """
    import json, os, warnings
    warnings.simplefilter("always")
    {before}
    import jsnap
    import jax
    after_import = dict(flags=os.environ.get("XLA_FLAGS"), x64=bool(jax.config.jax_enable_x64))
    returned = None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        {action}
    import jax.numpy as jnp
    loop = jax.jit(lambda a: jax.lax.fori_loop(0, 10, lambda i, a: jnp.sin(a) + 1.0, a))
    text = loop.lower(jnp.ones((64, 64), jnp.float32)).compile().as_text()
    # A reduction over three coordinates, as the signed distances' norms: a YNNPACK library
    # fusion unless XLA keeps it in its own kernels.
    norms = jax.jit(lambda a: jnp.sum(a * a, axis=-1)).lower(jnp.ones((1822, 3), jnp.float32))
    library = "__ynn_fusion" in norms.compile().as_text()
    print(json.dumps(dict(
        after_import=after_import,
        returned=returned,
        warnings=[f"{{w.category.__name__}}: {{w.message}}" for w in caught],
        hoisted="xla_cpu_small_call" in text,
        library=library,
        flags=os.environ.get("XLA_FLAGS"),
        x64=bool(jax.config.jax_enable_x64),
    )))
    """
)


def _clean_env(**extra) -> dict:
    """This process's environment without the settings under test (then ``extra``)."""
    drop = ("XLA_FLAGS", "JAX_ENABLE_X64")
    env = {k: v for k, v in os.environ.items() if k not in drop}
    env.update(extra)
    return env


def _probe(flags: str | None = None, before: str = "", action: str = "pass") -> dict:
    env = _clean_env() if flags is None else _clean_env(XLA_FLAGS=flags)
    code = _PROBE.format(before=before, action=action)
    run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("flags", [None, "--xla_cpu_use_fusion_emitters=false"])
def test_import_changes_no_process_setting(flags):
    """After ``import jsnap`` XLA_FLAGS (absent or the user's) and jax_enable_x64 are as they
    were, and XLA compiles with its own small-loop limit."""
    got = _probe(flags)
    assert got["after_import"] == {"flags": flags, "x64": False}
    assert got["flags"] == flags and got["x64"] is False
    assert not got["hoisted"]
    assert got["warnings"] == []


def test_configure_before_jax_starts_compiles_small_loops_into_one_kernel():
    got = _probe(action="returned = jsnap.configure_xla_cpu()")
    assert got["returned"] == "set"
    assert got["flags"] == f"--xla_backend_extra_options={OPTION}{OWN}"
    assert got["hoisted"]
    assert not got["library"]
    assert got["warnings"] == []
    assert got["x64"] is False  # the opt-in is about XLA's flags only


def test_configure_joins_and_keeps_the_users_flags():
    """The option joins the user's other flags; a value of the option the user gave is kept
    (here 0 bytes: no loop is small enough, so the probe's loop stays a loop)."""
    got = _probe("--xla_cpu_use_fusion_emitters=false", action="returned = jsnap.configure_xla_cpu()")
    assert got["returned"] == "set"
    assert got["flags"] == f"--xla_cpu_use_fusion_emitters=false --xla_backend_extra_options={OPTION}{OWN}"
    assert got["hoisted"]
    mine = f"--xla_backend_extra_options={_xla.SMALL_LOOP_OPTION}=0"
    got = _probe(mine, action="returned = jsnap.configure_xla_cpu()")
    assert got["returned"] == ("set" if OWN else "user")
    assert got["flags"] == mine + OWN
    assert not got["hoisted"]
    assert got["warnings"] == []


@pytest.mark.skipif(not OWN, reason="the installed jaxlib has no library-fusion flag")
def test_own_kernels_option_is_what_keeps_reductions_out_of_the_library():
    """Without the option XLA hands the three-coordinate reduction to YNNPACK; with jsnap's
    options it does not; a value of the flag the user gives (here the library for products
    only) is kept, and with both given configure_xla_cpu changes nothing."""
    assert _probe()["library"]
    assert not _probe(f"{_xla.LIBRARY_FLAG}=")["library"]
    mine = f"--xla_backend_extra_options={OPTION} {_xla.LIBRARY_FLAG}=LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT"
    got = _probe(mine, action="returned = jsnap.configure_xla_cpu()")
    assert got["returned"] == "user" and got["flags"] == mine
    assert not got["library"]


@pytest.mark.parametrize("flags", ["", "--x=2", "--xla_backend_extra_options=foo=1 --x=2"])
def test_without_flags_undoes_configure_and_keeps_the_users(flags):
    """What the benchmarks' processes that do not opt in run with: the user's flags as given."""
    assert _xla.without_xla_cpu_flags(_xla.xla_cpu_flags(flags)) == flags


def test_own_kernels_option_only_where_jaxlib_has_the_flag(monkeypatch):
    """XLA aborts on a flag it does not know: without it in jaxlib the flags are unchanged."""
    monkeypatch.setattr(_xla, "library_flag_known", lambda: False)
    assert _xla.with_own_kernels_option("--x=1") == "--x=1"
    assert _xla.xla_cpu_flags("") == f"--xla_backend_extra_options={OPTION}"
    monkeypatch.setattr(_xla, "library_flag_known", lambda: True)
    assert _xla.with_own_kernels_option("--x=1") == f"--x=1 {_xla.LIBRARY_FLAG}="
    assert _xla.with_own_kernels_option(f"{_xla.LIBRARY_FLAG}=X") == f"{_xla.LIBRARY_FLAG}=X"


def test_configure_after_jax_started_warns_and_changes_nothing():
    got = _probe(
        before="import jax.numpy as jnp; jnp.ones(3).block_until_ready()",
        action="returned = jsnap.configure_xla_cpu()",
    )
    assert got["returned"] == "late"
    assert got["flags"] is None
    assert not got["hoisted"]
    assert got["library"] == bool(OWN)
    assert len(got["warnings"]) == 1
    assert got["warnings"][0].startswith(
        "UserWarning: jsnap.configure_xla_cpu() was called after JAX started its CPU backend"
    )


# A user's program: no x64, no XLA flags. A coarse full model (P1, 1.6 mm) rolled out in both
# precisions; prints the dtypes, the peaks, whether both rollouts are clean and the settings after.
_ROLLOUTS = textwrap.dedent(
    """
    import json, os, warnings
    import numpy as np
    import jax
    import jsnap

    warnings.simplefilter("ignore", jsnap.SceneWarning)  # 1.6 mm elements: a coarse model
    scene = jsnap.load_scene().replace(
        {"solver.method": "full", "solver.element": "P1", "solver.mesh_size": 1.6, "motion.speed": 40.0}
    )
    model = jsnap.build(scene)
    out = {}
    for dtype in ("float32", "float64"):
        res = jsnap.rollout(model, dtype=dtype)
        F = np.asarray(res.insertion_force)
        out[dtype] = dict(
            dtype=str(res.insertion_force.dtype),
            energy_dtype=str(res.energy.dtype),
            peak=float(F.max()),
            finite=bool(np.isfinite(F).all()),
            ok=bool(res.ok),
        )
    print(json.dumps(dict(out, flags=os.environ.get("XLA_FLAGS"), x64=bool(jax.config.jax_enable_x64))))
    """
)


def test_float32_and_float64_rollouts_without_x64(tmp_path):
    """A program that never enables x64 gets both precisions it asks for: jsnap computes in 64
    bits inside its own calls only, and leaves the process's settings as they were."""
    env = _clean_env(JSNAP_CACHE=str(tmp_path))
    run = subprocess.run(
        [sys.executable, "-c", _ROLLOUTS], env=env, capture_output=True, text=True, timeout=900
    )
    assert run.returncode == 0, run.stderr
    got = json.loads(run.stdout.strip().splitlines()[-1])
    assert got["flags"] is None and got["x64"] is False
    for dtype in ("float32", "float64"):
        r = got[dtype]
        assert (r["dtype"], r["energy_dtype"]) == (dtype, dtype)
        assert r["finite"] and r["ok"]
        assert r["peak"] > 1.0  # the hook was pushed aside (N)
    # The same scene in both precisions (measured: peaks 4e-4 apart; the stiff, locking P1 mesh
    # makes them ~26.7 N, not the converged 2.5 N).
    assert got["float32"]["peak"] == pytest.approx(got["float64"]["peak"], rel=5e-3)
