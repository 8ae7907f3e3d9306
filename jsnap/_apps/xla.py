"""Explicit opt-in XLA:CPU settings: small loops compiled as one kernel, and XLA's own kernels
for every operation.

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

Measured side by side in fresh processes (``benchmarks/xla_option.py``): with both of
:func:`configure_xla_cpu`'s settings (this one and XLA's own kernels, below), the shipped
scene's reduced model steps 2.0x faster (1.8-2.3x round by round); the results move by
round-off only (float64 forces agree to 6e-12 of the peak).

The option belongs to the whole process: XLA reads ``XLA_FLAGS`` once, when JAX starts its CPU
backend. So ``import jsnap`` does not set it; a program opts in by calling
:func:`configure_xla_cpu` before its first JAX computation (the ``jsnap`` command line does), or
by setting ``XLA_FLAGS`` itself:

- the option joins an ``--xla_backend_extra_options`` the flags already give;
- a value of the option already in ``XLA_FLAGS`` is kept;
- called after JAX has started its backend it cannot take effect: it warns and changes nothing.

The second setting keeps every operation in XLA's own kernels. XLA:CPU hands matrix products
and reductions to the YNNPACK library by default, each then a library call on the runtime's
thread pool; a contact step is hundreds of such operations on small arrays (the candidate
points' signed distances reduced over three coordinates, a ~100 x 140 Delassus product), where
the call costs more than the arithmetic. ``--xla_cpu_experimental_ynn_fusion_type=`` (an empty
list) turns that off. Measured side by side in fresh processes (``benchmarks/xla_kernels.py``),
it speeds up the contact-heavy presets 1.2-1.4x (the two-hook clip, the box lid) and slows the
annular snap by 15 %, whose step is mostly a few larger products. The flag is experimental
in XLA, so it is set only where the installed jaxlib has it (:func:`library_flag_known`); an
``XLA_FLAGS`` that names it is kept as it is.
"""

import functools
import mmap
import os
import sys
import warnings
from pathlib import Path

SMALL_LOOP_OPTION = "xla_cpu_small_while_loop_byte_threshold"
# Bytes a loop's buffers may take for XLA to compile it into one kernel: the largest contact
# solve's loop (64 slots in float64: W alone is 192 x 192 x 8 B = 0.3 MB) fits, the full
# model's matrices (1344 dof in float32: 7 MB) do not.
SMALL_LOOP_BYTES = 1_000_000
_EXTRA = "--xla_backend_extra_options="
# XLA:CPU's list of operation kinds it hands to the YNNPACK library; empty: none.
LIBRARY_FLAG = "--xla_cpu_experimental_ynn_fusion_type"


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


@functools.cache
def library_flag_known() -> bool:
    """Whether the installed jaxlib has XLA's :data:`LIBRARY_FLAG`: XLA aborts the process on an
    ``XLA_FLAGS`` entry it does not know, and the flag is experimental (older jaxlibs have no
    library fusions, hence no flag). Its name is looked for in jaxlib's shared libraries, where
    XLA registers its flags."""
    try:
        import jaxlib
    except ImportError:
        return False
    name = LIBRARY_FLAG[2:].encode() + b"\0"
    libs = sorted(Path(jaxlib.__file__).parent.glob("*.so"), key=lambda p: -p.stat().st_size)
    for lib in libs:
        try:
            with open(lib, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
                if m.find(name) >= 0:
                    return True
        except (OSError, ValueError):
            continue
    return False


def with_own_kernels_option(flags: str) -> str:
    """``flags`` with XLA's own kernels for every operation (:data:`LIBRARY_FLAG` set to an
    empty list), unless they set the flag already or the installed jaxlib does not have it
    (then unchanged)."""
    if LIBRARY_FLAG in flags or not library_flag_known():
        return flags
    return " ".join([*flags.split(), f"{LIBRARY_FLAG}="])


def xla_cpu_flags(flags: str) -> str:
    """``flags`` with both of :func:`configure_xla_cpu`'s settings (each kept where the flags
    give it already)."""
    return with_own_kernels_option(with_small_loop_option(flags))


def without_xla_cpu_flags(flags: str) -> str:
    """``flags`` without :func:`configure_xla_cpu`'s settings: the small-loop option (the rest of
    an ``--xla_backend_extra_options`` kept) and :data:`LIBRARY_FLAG`. What a process that does
    not opt in runs with, for the benchmarks that compare the two."""
    out = []
    for token in flags.split():
        if token.startswith(LIBRARY_FLAG):
            continue
        if token.startswith(_EXTRA):
            kept = [o for o in token[len(_EXTRA) :].split(",") if o and not o.startswith(SMALL_LOOP_OPTION)]
            if kept:
                out.append(_EXTRA + ",".join(kept))
        else:
            out.append(token)
    return " ".join(out)


def _backend_started() -> bool:
    bridge = sys.modules.get("jax._src.xla_bridge")
    return bool(getattr(bridge, "_backends", None))


def configure_xla_cpu() -> str:
    """Set XLA:CPU's two options for this process: the contact solvers' loops compiled into
    single kernels instead of being run kernel by kernel, and XLA's own kernels for every
    operation instead of library calls (1.2-1.4x faster on the contact-heavy presets,
    ``benchmarks/xla_kernels.py``). Together they make the shipped scene's reduced model step
    2.0x faster (``benchmarks/xla_option.py``).

    The options (``xla_cpu_small_while_loop_byte_threshold`` set to :data:`SMALL_LOOP_BYTES`,
    and :data:`LIBRARY_FLAG` set to an empty list where the installed jaxlib has it, through
    ``XLA_FLAGS``) belong to the whole process and are read once, when JAX starts its CPU
    backend, so ``import jsnap`` does not set them: call this before the first JAX computation
    (the ``jsnap`` command line does), or set ``XLA_FLAGS`` yourself. The small-loop option joins
    an ``--xla_backend_extra_options`` that ``XLA_FLAGS`` already gives; a value of either that
    ``XLA_FLAGS`` gives is kept.

    Returns:
        What was done: ``"set"``; ``"user"`` (``XLA_FLAGS`` gives both already: kept);
        ``"late"`` (JAX's backend had started: nothing changed, with a warning).
    """
    current = os.environ.get("XLA_FLAGS", "")
    flags = xla_cpu_flags(current)
    if flags == current:
        return "user"
    if _backend_started():
        warnings.warn(
            "jsnap.configure_xla_cpu() was called after JAX started its CPU backend, so XLA's "
            "options cannot be set any more: the shipped scene's steps run ~2x slower. Call it before "
            f"the first JAX computation, or set XLA_FLAGS='{xla_cpu_flags('')}'.",
            stacklevel=2,
        )
        return "late"
    os.environ["XLA_FLAGS"] = flags
    return "set"
