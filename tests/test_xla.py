"""The XLA:CPU small-loop option jsnap sets on import (jsnap._apps.xla)."""

import os
import subprocess
import sys
import textwrap

import pytest

from jsnap._apps import xla as _xla

OPTION = f"{_xla.SMALL_LOOP_OPTION}={_xla.SMALL_LOOP_BYTES}"


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


# A loop whose buffers (a 64 x 64 float32 carry, 16 kB) lie between XLA's own limit (1 kB) and
# jsnap's: compiled into one kernel ("xla_cpu_small_call") only with jsnap's setting.
_PROBE = textwrap.dedent(
    """
    import os, warnings
    warnings.simplefilter("always")
    {before}
    import jsnap, jax, jax.numpy as jnp
    loop = jax.jit(lambda a: jax.lax.fori_loop(0, 10, lambda i, a: jnp.sin(a) + 1.0, a))
    text = loop.lower(jnp.ones((64, 64), jnp.float32)).compile().as_text()
    print("HOISTED" if "xla_cpu_small_call" in text else "NOT", os.environ.get("XLA_FLAGS", ""))
    """
)


def _probe(env_extra: dict, before: str = "") -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JSNAP_XLA_FLAGS")}
    env.update(env_extra)
    code = _PROBE.format(before=before)
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)


def test_import_compiles_small_loops_into_one_kernel():
    run = _probe({})
    assert run.returncode == 0, run.stderr
    assert run.stdout.startswith("HOISTED"), run.stdout
    assert OPTION in run.stdout


def test_opt_out_leaves_xla_alone():
    run = _probe({"JSNAP_XLA_FLAGS": "0"})
    assert run.returncode == 0, run.stderr
    assert run.stdout.startswith("NOT"), run.stdout


def test_import_after_jax_started_warns_and_changes_nothing():
    run = _probe({}, before="import jax.numpy as jnp; jnp.ones(3).block_until_ready()")
    assert run.returncode == 0, run.stderr
    assert run.stdout.startswith("NOT"), run.stdout
    assert "jsnap was imported after JAX started its CPU backend" in run.stderr
