"""An explicit opt-in XLA:CPU setting: small loops compiled as one kernel.

XLA's CPU runtime runs a compiled program as a sequence of "thunks", one per fused kernel, and a
``while`` loop as one thunk sequence per trip. jsnap's contact solvers are such loops: tens of
tiny kernels per iteration (a 24- or 64-slot matvec, the cone projection, the residual's
reductions), run up to a few hundred times in every time step. Dispatching those kernels one by
one, not computing them, is most of a small scene's step. XLA's small-while-loop pass instead
compiles a loop whose buffers are small into a single kernel; its size limit
(``xla_cpu_small_while_loop_byte_threshold``, an XLA:CPU backend option) is 1 kB by default,
below any contact problem's. :func:`configure_xla_cpu` raises it to :data:`SMALL_LOOP_BYTES`,
which holds the largest solver loop jsnap makes (the 64-slot float64 problem, ~0.3 MB) and no
loop over a full mesh.

Measured side by side in fresh processes (``benchmarks/xla_option.py``): the shipped scene's
reduced model steps 1.6-1.7x faster with it; the results move by round-off only (float64 forces
agree to 5e-8 of the peak).

The option belongs to the whole process: XLA reads ``XLA_FLAGS`` once, when JAX starts its CPU
backend. So ``import jsnap`` does not set it; a program opts in by calling
:func:`configure_xla_cpu` before its first JAX computation (the ``jsnap`` command line does), or
by setting ``XLA_FLAGS`` itself:

- the option joins an ``--xla_backend_extra_options`` the flags already give;
- a value of the option already in ``XLA_FLAGS`` is kept;
- called after JAX has started its backend it cannot take effect: it warns and changes nothing.
"""

import os
import sys
import warnings

SMALL_LOOP_OPTION = "xla_cpu_small_while_loop_byte_threshold"
# Bytes a loop's buffers may take for XLA to compile it into one kernel: the largest contact
# solve's loop (64 slots in float64: W alone is 192 x 192 x 8 B = 0.3 MB) fits, the full
# model's matrices (1344 dof in float32: 7 MB) do not.
SMALL_LOOP_BYTES = 1_000_000
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


def _backend_started() -> bool:
    bridge = sys.modules.get("jax._src.xla_bridge")
    return bool(getattr(bridge, "_backends", None))


def configure_xla_cpu() -> str:
    """Set XLA:CPU's small-loop option for this process: the contact solvers' loops are then
    compiled into single kernels instead of being run kernel by kernel, and the reduced model's
    steps run 1.6-1.7x faster (``benchmarks/xla_option.py``).

    The option (``xla_cpu_small_while_loop_byte_threshold``, set to :data:`SMALL_LOOP_BYTES`
    through ``XLA_FLAGS``) belongs to the whole process and is read once, when JAX starts its
    CPU backend, so ``import jsnap`` does not set it: call this before the first JAX
    computation (the ``jsnap`` command line does), or set ``XLA_FLAGS`` yourself. The option
    joins an ``--xla_backend_extra_options`` that ``XLA_FLAGS`` already gives.

    Returns:
        What was done: ``"set"``; ``"user"`` (``XLA_FLAGS`` names the option already: kept);
        ``"late"`` (JAX's backend had started: nothing changed, with a warning).
    """
    current = os.environ.get("XLA_FLAGS", "")
    flags = with_small_loop_option(current)
    if flags == current:
        return "user"
    if _backend_started():
        warnings.warn(
            "jsnap.configure_xla_cpu() was called after JAX started its CPU backend, so XLA's "
            "small-loop option cannot be set any more: contact-heavy steps run ~1.6x slower. Call "
            f"it before the first JAX computation, or set XLA_FLAGS='{_EXTRA}{SMALL_LOOP_OPTION}="
            f"{SMALL_LOOP_BYTES}'.",
            stacklevel=2,
        )
        return "late"
    os.environ["XLA_FLAGS"] = flags
    return "set"
