"""The on-disk cache of built artefacts (trained neural SDFs, reduced models, the full socket's
modes) and, for the command line, of JAX's compiled programs.

Files live under :func:`cache_dir` (``$JSNAP_CACHE`` or ``~/.cache/jsnap``), named by a hash of
everything they depend on, and are written atomically by their modules. :func:`load_or_make`
adds what several processes need when they build the same scene at once (parallel benchmark
workers, a pool of RL environments): one of them builds the file while the others wait for it
and load it, instead of each spending the build (the neural SDF's training is ~30 s on 2 cores).
The lock is an advisory ``flock`` on ``<file>.lock`` beside the file (POSIX; where ``fcntl`` is
missing each process builds on its own, as before). Lock files are left in place: removing one
while another process waits on it would let a third build beside it.

:func:`use_compilation_cache` points JAX's persistent compilation cache at ``cache_dir()/xla``
(the command line does; a library leaves that process-wide setting to its program), and
:func:`usage` / :func:`clear` are what ``jsnap cache`` shows and removes.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import sys
import tempfile
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np

from jsnap._apps.xla import switched_off

__all__ = [
    "KINDS", "cache_dir", "checksum", "clear", "load_or_make", "read_npz", "save_npz", "usage",
    "use_compilation_cache",
]  # fmt: skip

T = TypeVar("T")


def cache_dir() -> Path:
    """Where built artefacts are cached: ``$JSNAP_CACHE`` or ``~/.cache/jsnap``."""
    root = os.environ.get("JSNAP_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "jsnap"


# The cache's folders: what each holds.
KINDS = {
    "neural_sdf": "trained neural SDF weights (jsnap train-sdf, solver.sdf = neural)",
    "reduced": "segmented and reduced socket models (solver.method = segmented | reduced)",
    "modal": "the full socket's modes (solver.method = modal)",
    "xla": "JAX's compiled programs, kept by the command line (use_compilation_cache)",
}


def use_compilation_cache() -> Path | None:
    """Keep JAX's compiled programs on disk, in ``cache_dir()/xla``, for this process.

    The command line calls it (``jsnap simulate``, ``fit``, ``train-sdf``): a later run of the
    same scene loads its compiled rollout instead of compiling it again. ``import jsnap`` does
    not: JAX's compilation cache is a setting of the whole process, which a library leaves to
    the program that uses it (a script sets it with one line, see the README's "Caches").

    It changes nothing (and returns None) when ``JSNAP_XLA_CACHE=0``, when the folder cannot be
    written (with one warning), when JAX already has a cache folder (``JAX_COMPILATION_CACHE_DIR``
    or ``jax.config``: that one is kept, and returned) or when JAX's cache is switched off
    (``JAX_ENABLE_COMPILATION_CACHE=false``, as ``jsnap bench`` runs its scripts: they measure
    compile times). JAX keeps the programs that took at least
    ``jax_persistent_cache_min_compile_time_secs`` (1 s by default) to compile; nothing evicts
    them (``jsnap cache --clear xla`` removes them). Call it before the first compilation: JAX
    opens its cache once per process.

    Returns:
        The folder JAX's compilation cache uses, or None when it has none.
    """
    import jax

    if not jax.config.jax_enable_compilation_cache:
        return None
    if jax.config.jax_compilation_cache_dir:
        return Path(jax.config.jax_compilation_cache_dir)
    if switched_off("JSNAP_XLA_CACHE"):
        return None
    path = cache_dir() / "xla"
    try:  # JAX would warn on every compilation instead
        path.mkdir(parents=True, exist_ok=True)
        if not os.access(path, os.W_OK):
            raise PermissionError(f"{path} is not writable")
    except OSError as err:
        warnings.warn(f"jsnap: compiling without a compilation cache ({err})", stacklevel=2)
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    return path


def _files(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if p.is_file() and not p.name.endswith(".lock")]


def _listing(name: str) -> tuple[Path, list[Path]]:
    """A folder of :data:`KINDS` and its files (lock files not counted)."""
    root = cache_dir() / name
    return root, (_files(root) if root.is_dir() else [])


def _size(files: list[Path]) -> int:
    return sum(f.stat().st_size for f in files)


def _folder(name: str) -> dict:
    root, files = _listing(name)
    return {"path": str(root), "files": len(files), "bytes": _size(files)}


def usage() -> dict:
    """Per folder of :data:`KINDS`: its path, the number of files it holds and their total size
    in bytes (lock files not counted). Nothing else in the cache folder is looked at: it may be
    a folder of the user's that holds other things."""
    return {name: _folder(name) for name in KINDS}


def clear(kinds=None) -> dict:
    """Remove the cached files of the given folders of :data:`KINDS` (default: all of them);
    returns ``{folder: bytes removed}``. Lock files stay (see the module's note); a process that
    is building an artefact meanwhile writes it again. Other names raise ValueError."""
    kinds = list(KINDS) if kinds is None else list(kinds)
    unknown = [k for k in kinds if k not in KINDS]
    if unknown:
        raise ValueError(f"unknown cache folder(s) {unknown}; jsnap's are {list(KINDS)}")
    removed = {}
    for kind in kinds:
        root, files = _listing(kind)  # one walk: the bytes reported are the files removed
        removed[kind] = _size(files)
        if kind == "xla":  # JAX's files only (no jsnap lock among them): the folder whole
            shutil.rmtree(root, ignore_errors=True)
        else:
            for f in files:
                f.unlink(missing_ok=True)
    return removed


def checksum(meta_json: str, arrays: dict) -> str:
    """SHA-256 of a cache file's metadata (JSON) and of every array (name, dtype, shape, bytes),
    stored in the file and checked when it is read."""
    h = hashlib.sha256(meta_json.encode())
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}|{a.dtype.str}|{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def save_npz(path, format_name: str, version: int, meta: dict, arrays: dict) -> Path:
    """Write ``arrays`` to ``path`` (``.npz``) atomically (a temporary file beside it, then a
    rename: a reader never sees half a file), with ``format`` and ``format_version``, ``meta``
    as JSON and the :func:`checksum` of both, which the module's reader verifies."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {k: np.asarray(v) for k, v in arrays.items()}
    meta_json = json.dumps(meta, sort_keys=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(
                fh,
                format=np.asarray(format_name),
                format_version=np.asarray(version),
                meta=np.asarray(meta_json),
                checksum=np.asarray(checksum(meta_json, arrays)),
                **arrays,
            )
        os.chmod(tmp, 0o644)  # mkstemp makes it private; nothing cached here is secret
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def read_npz(path: Path, format_name: str, version: int, what: str, bad) -> tuple[dict, dict]:
    """``(arrays, meta)`` from a file written by :func:`save_npz`, after checking that it reads,
    that it is a ``format_name`` file of ``version`` and that its checksum holds; ``bad(why)``
    makes the module's exception (raised here), ``what`` names the kind of file in the message.
    The caller checks that the file exists, and its key and arrays."""
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as err:  # zipfile, zlib, OSError, ValueError ... all mean "unreadable"
        raise bad(f"unreadable or corrupt file ({type(err).__name__}: {err})") from None
    if "format" not in data or str(data["format"]) != format_name:
        raise bad(f"not a {what} (no 'format' = {format_name!r})")
    found = int(data.get("format_version", -1))
    if found != version:
        raise bad(f"format version {found}, this jsnap reads version {version}")
    try:
        meta_json = str(data.pop("meta"))
        stored = str(data.pop("checksum"))
        meta = json.loads(meta_json)
    except (KeyError, ValueError, TypeError) as err:
        raise bad(f"corrupt metadata ({type(err).__name__}: {err})") from None
    for k in ("format", "format_version"):
        data.pop(k)
    if checksum(meta_json, data) != stored:
        raise bad("checksum mismatch: the file is corrupt")
    return data, meta


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
