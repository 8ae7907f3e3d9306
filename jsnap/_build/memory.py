"""The build's memory guard: estimates checked against the memory this process can have, before
the large allocations, so that a part too large for the machine is refused with the setting to
change instead of being killed by the kernel part way (host side)."""

from __future__ import annotations

import os

from jsnap._geometry.scene import SceneError

__all__ = ["MEMORY_SHARE", "BuildError", "available_memory", "require"]

# Fraction of the available memory one allocation of the build may plan to use.
MEMORY_SHARE = 0.8


class BuildError(SceneError):
    """A scene that is valid but cannot be built here (memory, a path that never makes contact);
    the message names the setting to change."""


def available_memory() -> int:
    """Bytes of memory available to this process (Linux's MemAvailable, else physical memory)."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def require(estimate: int, what: str, hint: str, available: int | None = None) -> int:
    """Refuse an allocation of about ``estimate`` bytes that would not fit.

    Args:
        estimate: bytes the step is about to allocate (at its peak).
        what: what would be allocated, for the message.
        hint: the setting(s) to change, for the message.
        available: bytes available (default: :func:`available_memory`, read now).

    Returns:
        ``estimate``.

    Raises:
        BuildError: ``estimate`` exceeds :data:`MEMORY_SHARE` of the available memory.
    """
    available = available_memory() if available is None else available
    if estimate > MEMORY_SHARE * available:
        raise BuildError(
            f"{what} needs about {estimate / 2**30:.1f} GiB, more than the "
            f"{MEMORY_SHARE * available / 2**30:.1f} GiB this machine can give it: use {hint}"
        )
    return estimate
