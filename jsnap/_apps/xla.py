"""The XLA:CPU setting jsnap makes when it is imported: small loops compiled as one kernel.

XLA's CPU runtime runs a compiled program as a sequence of "thunks", one per fused kernel, and a
``while`` loop as one thunk sequence per trip. jsnap's contact solvers are such loops: tens of
tiny kernels per iteration (a 24- or 64-slot matvec, the cone projection, the residual's
reductions), run 50 times for the step size and up to a few hundred times for the forces, in
every time step. Dispatching those kernels one by one, not computing them, is most of a small
scene's step. XLA's small-while-loop pass instead compiles a loop whose buffers are small into
a single kernel; its size limit (``xla_cpu_small_while_loop_byte_threshold``, an XLA:CPU
backend option) is 1 kB by default, below any contact problem's. jsnap raises it to
:data:`SMALL_LOOP_BYTES`, which holds the largest solver loop jsnap makes (the 64-slot float64
problem, ~0.3 MB) and no loop over a full mesh.

Measured side by side (docs/reduction.md, "XLA's small-loop pass"): the 1344-dof reduced scene
with light contact settings steps 1.4-1.75x faster. The results move by round-off only (the same
arithmetic compiled into one kernel: float64 rollouts agree to 3e-9 of the peak force, float32
ones move as any compilation change moves them).

The setting is the process's, like ``jax_enable_x64`` which jsnap also sets: XLA reads
``XLA_FLAGS`` once, when JAX starts its CPU backend, and the option then applies to every
program of the process. So:

- it is added to ``XLA_FLAGS`` only when the user's flags do not name it already (the user's
  value wins), merged into an ``--xla_backend_extra_options`` the user gives;
- ``JSNAP_XLA_FLAGS=0`` leaves ``XLA_FLAGS`` alone;
- imported after JAX has started its backend (after a first computation), jsnap cannot change
  it any more and says so once (a warning naming the flag to set).
"""

import os
import sys
import warnings

SMALL_LOOP_OPTION = "xla_cpu_small_while_loop_byte_threshold"
# Bytes a loop's buffers may take for XLA to compile it into one kernel: the largest contact
# solve's loop (64 slots in float64: W alone is 192 x 192 x 8 B = 0.3 MB) fits, the full
# model's matrices (1344 dof in float32: 7 MB) do not.
SMALL_LOOP_BYTES = 1_000_000
OPT_OUT = "JSNAP_XLA_FLAGS"
_EXTRA = "--xla_backend_extra_options="


def with_small_loop_option(flags: str, nbytes: int = SMALL_LOOP_BYTES) -> str:
    """``flags`` (an ``XLA_FLAGS`` string) with the small-loop limit set to ``nbytes``, unless
    they set it already (then unchanged). The option joins the flags' own
    ``--xla_backend_extra_options`` (a comma-separated list) when they give one."""
    if SMALL_LOOP_OPTION in flags:
        return flags
    option = f"{SMALL_LOOP_OPTION}={int(nbytes)}"
    tokens = flags.split()
    for i, token in enumerate(tokens):
        if token.startswith(_EXTRA):
            tokens[i] = token + ("," if len(token) > len(_EXTRA) else "") + option
            break
    else:
        tokens.append(_EXTRA + option)
    return " ".join(tokens)


def switched_off(name: str) -> bool:
    """Whether the environment variable ``name`` (one of jsnap's on-by-default switches,
    ``JSNAP_XLA_FLAGS``, ``JSNAP_XLA_CACHE``) says off: 0, false, no or off."""
    return os.environ.get(name, "1").strip().lower() in ("0", "false", "no", "off")


def _backend_started() -> bool:
    bridge = sys.modules.get("jax._src.xla_bridge")
    return bool(getattr(bridge, "_backends", None))


def configure() -> str:
    """Add the small-loop limit to ``XLA_FLAGS`` for this process (see the module docstring).

    Returns what was done: ``"set"``; ``"user"`` (the user's flags name the option already);
    ``"off"`` (``JSNAP_XLA_FLAGS=0``); ``"late"`` (JAX's backend had started: nothing changed,
    with a warning).
    """
    if switched_off(OPT_OUT):
        return "off"
    current = os.environ.get("XLA_FLAGS", "")
    flags = with_small_loop_option(current)
    if flags == current:
        return "user"
    if _backend_started():
        warnings.warn(
            "jsnap was imported after JAX started its CPU backend, so XLA's small-loop option "
            "cannot be set any more: contact-heavy steps will run ~1.4-1.7x slower. Import jsnap before "
            f"the first JAX computation, or set XLA_FLAGS='{_EXTRA}{SMALL_LOOP_OPTION}="
            f"{SMALL_LOOP_BYTES}' (JSNAP_XLA_FLAGS=0 silences this).",
            stacklevel=3,
        )
        return "late"
    os.environ["XLA_FLAGS"] = flags
    return "set"
