"""The on-disk cache of built artefacts (trained neural SDFs, reduced models, a part's modes)
and, for the command line, of JAX's compiled programs.

Every artefact is one file in one format (:func:`save_artefact`, :func:`load_artefact`): an
``.npz`` of arrays with the format's name and version, the artefact's kind and key, metadata as
JSON and a SHA-256 checksum of all of it. Files live under :func:`cache_dir`
(``$JSNAP_CACHE`` or ``~/.cache/jsnap``), one folder per kind, named by the key: a hash of
everything the artefact depends on (:class:`KeyHash`). A file that is unreadable, corrupt, of
another format version, of another kind or for another key is never used: :func:`cached`
reports it with a warning and builds the artefact again. :func:`load_or_make`
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

__all__ = [
    "FORMAT", "FORMAT_VERSION", "KINDS", "ArtefactError", "KeyHash", "artefact_path", "cache_dir", "cached",
    "checksum", "clear", "load_artefact", "load_or_make", "save_artefact", "switched_off", "usage",
    "use_compilation_cache",
]  # fmt: skip

# The one file format of every cached artefact; bump the version when the layout of a file or
# the meaning of what it stores changes (older files are then rebuilt).
FORMAT = "jsnap-artefact"
FORMAT_VERSION = 1


class ArtefactError(ValueError):
    """A cached artefact file that cannot be used (unreadable, corrupt, another format version,
    kind or key); the message names the file and why."""


def switched_off(name: str) -> bool:
    """Whether the environment variable ``name`` (an on-by-default switch such as
    ``JSNAP_XLA_CACHE``) says off: 0, false, no or off."""
    return os.environ.get(name, "1").strip().lower() in ("0", "false", "no", "off")

T = TypeVar("T")


def cache_dir() -> Path:
    """Where built artefacts are cached: ``$JSNAP_CACHE`` or ``~/.cache/jsnap``."""
    root = os.environ.get("JSNAP_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "jsnap"


# The cache's folders: what each holds.
KINDS = {
    "neural_sdf": "trained neural SDF weights (jsnap train-sdf, solver.sdf = neural)",
    "reduced": "reduced part models (solver.method = reduced)",
    "modal": "a part's modes (the modal part)",
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


class KeyHash:
    """SHA-256 of everything an artefact depends on: JSON-able settings and arrays (dtype, shape
    and bytes), in the order given. The format's version is part of every key."""

    def __init__(self, kind: str):
        self._h = hashlib.sha256(json.dumps(dict(format=FORMAT, version=FORMAT_VERSION, kind=kind)).encode())

    def settings(self, value) -> KeyHash:
        self._h.update(json.dumps(value, sort_keys=True).encode())
        return self

    def arrays(self, *arrays) -> KeyHash:
        for a in arrays:
            a = np.ascontiguousarray(a)
            self._h.update(f"{a.dtype.str}|{a.shape}".encode())
            self._h.update(a.tobytes())
        return self

    def hexdigest(self) -> str:
        return self._h.hexdigest()


def artefact_path(kind: str, key: str) -> Path:
    """``cache_dir()/<kind>/<first 32 hex digits of key>.npz``."""
    if kind not in KINDS or kind == "xla":
        raise ValueError(f"unknown artefact kind {kind!r}")
    return cache_dir() / kind / f"{key[:32]}.npz"


def save_artefact(path, kind: str, key: str, meta: dict, arrays: dict) -> Path:
    """Write an artefact to ``path`` (``.npz``) atomically (a temporary file beside it, then a
    rename: a reader never sees half a file): its arrays, the format's name and version, its
    ``kind`` and ``key``, ``meta`` as JSON and the :func:`checksum` of all of them."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {k: np.asarray(v) for k, v in arrays.items() if v is not None}
    meta_json = json.dumps(dict(meta, kind=kind, key=key), sort_keys=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(
                fh,
                format=np.asarray(FORMAT),
                format_version=np.asarray(FORMAT_VERSION),
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


def load_artefact(path, kind: str, key: str | None = None) -> tuple[dict, dict]:
    """``(arrays, meta)`` of an artefact written by :func:`save_artefact`, after checking that
    it reads, that it is this format's version, that its checksum holds and that it is a
    ``kind`` artefact for ``key`` (None: any key).

    Raises:
        FileNotFoundError: no such file.
        ArtefactError: any other reason the file cannot be used.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")

    def bad(why):
        return ArtefactError(f"{path}: {why}")

    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as err:  # zipfile, zlib, OSError, ValueError ... all mean "unreadable"
        raise bad(f"unreadable or corrupt file ({type(err).__name__}: {err})") from None
    if "format" not in data or str(data["format"]) != FORMAT:
        raise bad(f"not a jsnap artefact (no 'format' = {FORMAT!r})")
    found = int(data.get("format_version", -1))
    if found != FORMAT_VERSION:
        raise bad(f"format version {found}, this jsnap reads version {FORMAT_VERSION}")
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
    if meta.get("kind") != kind:
        raise bad(f"a {meta.get('kind')!r} artefact, not {kind!r}")
    if key is not None and meta.get("key") != key:
        raise bad(f"made for something else (key {str(meta.get('key'))[:12]}…, expected {key[:12]}…)")
    return data, meta


def cached(kind: str, key: str, make, *, what: str, check=None, fresh: bool = False, shipped=None):
    """The artefact ``kind``/``key`` from the cache, or made by ``make()`` and cached.

    Args:
        make: ``() -> (arrays, meta)``, the artefact built.
        what: what is built, for messages.
        check: ``(arrays, meta) -> None``, raising :class:`ArtefactError` when a file's content
            does not fit (its arrays' shapes); optional.
        fresh: make it even if a usable file exists.
        shipped: a read-only file the package ships for this key, read when the cache has none.

    Returns:
        ``(arrays, meta)``; ``meta`` also holds ``path`` and ``cached`` (read, not made) and
        ``shipped`` (read from the package).
    """
    path = artefact_path(kind, key)

    def read(file):
        try:
            arrays, meta = load_artefact(file, kind, key)
            if check is not None:
                check(arrays, meta)
        except FileNotFoundError:
            return None
        except ArtefactError as err:
            warnings.warn(f"{err}; not using it: {what} is made again", stacklevel=4)
            return None
        return arrays, dict(meta, path=str(file), cached=True, shipped=file != path)

    def made():
        arrays, meta = make()
        save_artefact(path, kind, key, meta, arrays)
        return arrays, dict(meta, kind=kind, key=key, path=str(path), cached=False, shipped=False)

    if not fresh and shipped is not None and not path.is_file() and Path(shipped).is_file():
        found = read(Path(shipped))
        if found is not None:
            return found
    return load_or_make(path, lambda: read(path), made, what=what, fresh=fresh)


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
