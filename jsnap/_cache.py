"""The on-disk cache of built artefacts (trained neural SDFs, reduced models).

Files live under :func:`cache_dir` (``$JSNAP_CACHE`` or ``~/.cache/jsnap``), named by a hash of
everything they depend on, and are written atomically by their modules. :func:`load_or_make`
adds what several processes need when they build the same scene at once (parallel benchmark
workers, a pool of RL environments): one of them builds the file while the others wait for it
and load it, instead of each spending the build (the neural SDF's training is ~30 s on 2 cores).
The lock is an advisory ``flock`` on ``<file>.lock`` beside the file (POSIX; where ``fcntl`` is
missing each process builds on its own, as before). Lock files are left in place: removing one
while another process waits on it would let a third build beside it.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np

__all__ = ["cache_dir", "checksum", "load_or_make"]

T = TypeVar("T")


def cache_dir() -> Path:
    """Where built artefacts are cached: ``$JSNAP_CACHE`` or ``~/.cache/jsnap``."""
    root = os.environ.get("JSNAP_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "jsnap"


def checksum(meta_json: str, arrays: dict) -> str:
    """SHA-256 of a cache file's metadata (JSON) and of every array (name, dtype, shape, bytes),
    stored in the file and checked when it is read."""
    h = hashlib.sha256(meta_json.encode())
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}|{a.dtype.str}|{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _stamp(path: Path):
    """What identifies the file's current version (None: no file)."""
    try:
        st = path.stat()
    except FileNotFoundError:
        return None
    return st.st_mtime_ns, st.st_size, st.st_ino


@contextlib.contextmanager
def _locked(path: Path, what: str):
    """Hold the exclusive lock of ``path``'s build; says so on stderr when it has to wait."""
    try:
        import fcntl
    except ImportError:  # not POSIX: no cross-process lock
        yield
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.with_name(path.name + ".lock"), "a") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            sys.stderr.write(f"jsnap: waiting for another process building {what} ({path})\n")
            sys.stderr.flush()
            fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def load_or_make(
    path: Path, load: Callable[[], T | None], make: Callable[[], T], *, what: str, fresh=False
) -> T:
    """The cached artefact at ``path``, or a newly made one, made once across processes.

    Args:
        path: the cache file.
        load: reads ``path``; returns None where there is no usable file (a corrupt or foreign
            one is reported by ``load`` itself, with a warning).
        make: builds the artefact and writes it to ``path`` (atomically); returns it.
        what: what is built, for the message shown while waiting on another process.
        fresh: make it even if a usable file exists (``retrain``, ``rebuild``).

    Returns:
        ``load()``'s or ``make()``'s result. Under the lock the file is read again only if it
        changed while this process waited (another process wrote it), so a corrupt file is
        reported once.
    """
    stamp = _stamp(path)
    if not fresh and stamp is not None and (found := load()) is not None:
        return found
    with _locked(path, what):
        if not fresh and _stamp(path) not in (None, stamp) and (found := load()) is not None:
            return found
        return make()
