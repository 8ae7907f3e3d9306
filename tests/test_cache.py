"""The build cache (jsnap._build.cache): one artefact format whose files say what they are (kind
and key); a corrupt or foreign file is warned about and rebuilt, once; processes asking for the
same file at once build it once; JAX's compilation cache and `jsnap cache`."""

import json
import os
import subprocess
import sys
import textwrap
import warnings

import numpy as np
import pytest

from jsnap._build import cache as _cache


def test_cached_artefact_is_made_once_and_says_what_it_is(tmp_path, monkeypatch):
    monkeypatch.setenv("JSNAP_CACHE", str(tmp_path))
    key = _cache.KeyHash("modal").settings({"a": 1}).arrays(np.arange(3.0)).hexdigest()
    # Everything it depends on is in the key, the artefact's kind too.
    assert key != _cache.KeyHash("modal").settings({"a": 2}).arrays(np.arange(3.0)).hexdigest()
    assert key != _cache.KeyHash("modal").settings({"a": 1}).arrays(np.arange(3)).hexdigest()
    assert key != _cache.KeyHash("reduced").settings({"a": 1}).arrays(np.arange(3.0)).hexdigest()
    makes = []

    def make():
        makes.append(1)
        return {"w": np.ones(4)}, {"note": "test"}

    arrays, meta = _cache.cached("modal", key, make, what="a test artefact")
    path = _cache.artefact_path("modal", key)
    assert path.parent == tmp_path / "modal" and path.is_file()
    assert (meta["path"], meta["cached"], meta["shipped"], len(makes)) == (str(path), False, False, 1)
    arrays, meta = _cache.cached("modal", key, make, what="a test artefact")
    assert meta["cached"] and len(makes) == 1 and np.array_equal(arrays["w"], np.ones(4))
    _, stored = _cache.load_artefact(path, "modal", key)
    assert (stored["kind"], stored["key"], stored["note"]) == ("modal", key, "test")
    arrays, meta = _cache.cached("modal", key, make, what="a test artefact", fresh=True)
    assert not meta["cached"] and len(makes) == 2
    with pytest.raises(ValueError, match="unknown artefact kind 'xla'"):
        _cache.artefact_path("xla", key)


def test_foreign_or_corrupt_artefact_is_warned_about_and_made_again(tmp_path, monkeypatch):
    monkeypatch.setenv("JSNAP_CACHE", str(tmp_path))
    key = _cache.KeyHash("modal").settings({"a": 1}).hexdigest()
    other = _cache.KeyHash("modal").settings({"a": 2}).hexdigest()
    path = _cache.artefact_path("modal", key)

    def make():
        return {"w": np.ones(4)}, {}

    def check(arrays, meta):
        if arrays["w"].shape != (4,):
            raise _cache.ArtefactError(f"w has shape {arrays['w'].shape}, not (4,)")

    def again(why):
        with pytest.warns(UserWarning) as caught:
            arrays, meta = _cache.cached("modal", key, make, what="a test artefact", check=check)
        assert [str(w.message) for w in caught if "made again" in str(w.message)] == [
            f"{why}; not using it: a test artefact is made again"
        ]
        assert not meta["cached"] and np.array_equal(arrays["w"], np.ones(4))
        return meta

    _cache.save_artefact(path, "reduced", key, {}, {"w": np.ones(4)})
    again(f"{path}: a 'reduced' artefact, not 'modal'")
    _cache.save_artefact(path, "modal", other, {}, {"w": np.ones(4)})
    again(f"{path}: made for something else (key {other[:12]}…, expected {key[:12]}…)")
    _cache.save_artefact(path, "modal", key, {}, {"w": np.ones(5)})
    again("w has shape (5,), not (4,)")
    path.write_bytes(path.read_bytes()[:200])
    with pytest.raises(_cache.ArtefactError, match="unreadable or corrupt file"):
        _cache.load_artefact(path, "modal")
    with pytest.warns(UserWarning, match="unreadable or corrupt file .*; not using it"):
        _cache.cached("modal", key, make, what="a test artefact")
    _cache.load_artefact(path, "modal", key)  # made again: valid
    # A file the package ships for a key is read when the cache has none (and not copied).
    shipped = _cache.save_artefact(tmp_path / "package" / "s.npz", "modal", other, {}, {"w": np.full(4, 7.0)})
    arrays, meta = _cache.cached("modal", other, make, what="a test artefact", shipped=shipped)
    assert meta["shipped"] and meta["cached"] and arrays["w"][0] == 7.0
    assert not _cache.artefact_path("modal", other).exists()


# A worker: waits for the go file, then load_or_make on the shared path; its make sleeps (so the
# others arrive while it builds) and logs each build. Prints what it got.
WORKER = textwrap.dedent(
    """
    import os, sys, time
    from pathlib import Path
    from jsnap._build.cache import load_or_make

    path, log, go = Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3])
    while not go.exists():
        time.sleep(0.01)

    def load():
        return path.read_text() if path.is_file() else None

    def make():
        with open(log, "a") as fh:
            fh.write(f"{os.getpid()}\\n")
        time.sleep(1.0)
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(f"built by {os.getpid()}")
        os.replace(tmp, path)
        return path.read_text()

    print(load_or_make(path, load, make, what="a test file"))
    """
)


def test_processes_asking_at_once_build_once(tmp_path):
    pytest.importorskip("fcntl")
    path, log, go = tmp_path / "thing.txt", tmp_path / "builds.log", tmp_path / "go"
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", WORKER, str(path), str(log), str(go)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for _ in range(3)
    ]
    go.touch()
    outs = [p.communicate(timeout=120) for p in procs]
    assert all(p.returncode == 0 for p in procs), [err for _, err in outs]
    builders = log.read_text().split()
    assert len(builders) == 1  # without the lock, each of the three would have built
    got = {out.strip() for out, _ in outs}
    assert got == {f"built by {builders[0]}"}
    # The processes that found the lock taken said why they waited.
    assert sum("waiting for another process building a test file" in err for _, err in outs) >= 1


def test_fresh_rebuilds_and_a_bad_file_is_read_once(tmp_path):
    path = tmp_path / "thing.txt"
    reads, makes = [], []

    def load():
        reads.append(1)
        text = path.read_text()
        if text == "corrupt":
            warnings.warn("corrupt file; rebuilding", stacklevel=2)
            return None
        return text

    def make():
        makes.append(1)
        path.write_text("good")
        return "good"

    assert _cache.load_or_make(path, load, make, what="x") == "good"  # no file: made, not read
    assert (len(reads), len(makes)) == (0, 1)
    assert _cache.load_or_make(path, load, make, what="x") == "good"  # read
    assert (len(reads), len(makes)) == (1, 1)
    assert _cache.load_or_make(path, load, make, what="x", fresh=True) == "good"  # rebuilt
    assert (len(reads), len(makes)) == (1, 2)
    path.write_text("corrupt")
    with pytest.warns(UserWarning) as caught:
        assert _cache.load_or_make(path, load, make, what="x") == "good"
    assert len(caught) == 1 and (len(reads), len(makes)) == (2, 3)  # unchanged under the lock: not re-read


@pytest.fixture
def jax_cache_config():
    """Restores JAX's compilation-cache settings after a test that changes them (nothing is
    compiled while they point at the test's folder)."""
    import jax

    names = ("jax_compilation_cache_dir", "jax_enable_compilation_cache")
    old = {n: getattr(jax.config, n) for n in names}
    yield jax.config
    for n, v in old.items():
        jax.config.update(n, v)


def test_compilation_cache_folder_and_what_overrides_it(tmp_path, monkeypatch, jax_cache_config):
    """The command line's JAX cache goes to <jsnap cache>/xla, unless JAX has a folder already
    (kept), the user switched it off (JSNAP_XLA_CACHE=0), the folder cannot be made or JAX's
    cache is disabled."""
    cfg = jax_cache_config
    monkeypatch.setenv("JSNAP_CACHE", str(tmp_path))
    monkeypatch.delenv("JSNAP_XLA_CACHE", raising=False)
    cfg.update("jax_enable_compilation_cache", True)
    cfg.update("jax_compilation_cache_dir", None)
    assert _cache.use_compilation_cache() == tmp_path / "xla"
    assert cfg.jax_compilation_cache_dir == str(tmp_path / "xla")

    mine = str(tmp_path / "users_own")
    cfg.update("jax_compilation_cache_dir", mine)
    assert _cache.use_compilation_cache() == tmp_path / "users_own"
    assert cfg.jax_compilation_cache_dir == mine

    cfg.update("jax_compilation_cache_dir", None)
    monkeypatch.setenv("JSNAP_XLA_CACHE", "0")
    assert _cache.use_compilation_cache() is None
    assert cfg.jax_compilation_cache_dir is None

    monkeypatch.delenv("JSNAP_XLA_CACHE")
    (tmp_path / "a_file").write_text("")  # a cache "folder" that cannot hold one: one warning
    monkeypatch.setenv("JSNAP_CACHE", str(tmp_path / "a_file"))
    with pytest.warns(UserWarning, match="compiling without a compilation cache"):
        assert _cache.use_compilation_cache() is None
    assert cfg.jax_compilation_cache_dir is None

    monkeypatch.setenv("JSNAP_CACHE", str(tmp_path))
    cfg.update("jax_enable_compilation_cache", False)
    assert _cache.use_compilation_cache() is None
    assert cfg.jax_compilation_cache_dir is None


# Compiles one program with the command line's cache setting; prints whether JAX found it on disk
# (its cache-hit event). The minimum compile time is lowered so that this small program is kept.
COMPILER = textwrap.dedent(
    """
    import jax, jax.numpy as jnp
    from jax import monitoring
    from jsnap._build.cache import use_compilation_cache

    hits = []
    monitoring.register_event_listener(lambda e, **kw: hits.append(e) if "cache_hits" in e else None)
    print("folder", use_compilation_cache())
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    f = jax.jit(lambda x: jnp.cumsum(jnp.sin(x) ** 2) @ x)
    print("value", float(f(jnp.arange(64.0))), "hit", bool(hits))
    """
)


def test_compiled_program_reloaded_by_the_next_process(tmp_path, monkeypatch, capsys):
    """A second process with the same setting loads the first one's compiled program from
    <jsnap cache>/xla (same result), and `jsnap cache` counts and clears those files."""
    env = {**os.environ, "JSNAP_CACHE": str(tmp_path)}
    for k in ("JSNAP_XLA_CACHE", "JAX_COMPILATION_CACHE_DIR", "JAX_ENABLE_COMPILATION_CACHE"):
        env.pop(k, None)
    runs = [
        subprocess.run(
            [sys.executable, "-c", COMPILER], env=env, capture_output=True, text=True, check=True
        ).stdout
        for _ in range(2)
    ]
    assert runs[0].splitlines()[0] == f"folder {tmp_path / 'xla'}"
    first, second = (r.splitlines()[1].split() for r in runs)
    assert first[1] == second[1]  # the same value
    assert (first[3], second[3]) == ("False", "True")  # compiled, then loaded

    from jsnap._apps.cli import main as cli_main

    monkeypatch.setenv("JSNAP_CACHE", str(tmp_path))
    assert cli_main(["cache", "--json"]) == 0
    xla = json.loads(capsys.readouterr().out)["folders"]["xla"]
    assert xla["files"] >= 1 and xla["bytes"] > 0
    assert cli_main(["cache", "--clear", "xla"]) == 0
    assert not (tmp_path / "xla").exists()


def test_cache_command_lists_and_clears(tmp_path, monkeypatch, capsys):
    """`jsnap cache` reports files and bytes per folder (lock files not counted) and
    `--clear [FOLDER ...]` removes the named folders' files only, leaving the locks; nothing
    outside jsnap's folders is listed or removed."""
    from jsnap._apps.cli import main as cli_main

    monkeypatch.setenv("JSNAP_CACHE", str(tmp_path))
    (tmp_path / "neural_sdf").mkdir()
    (tmp_path / "reduced").mkdir()
    (tmp_path / "neural_sdf" / "a.npz").write_bytes(b"x" * 100)
    (tmp_path / "reduced" / "b.npz").write_bytes(b"y" * 300)
    (tmp_path / "reduced" / "c.npz").write_bytes(b"z" * 50)
    (tmp_path / "reduced" / "b.npz.lock").write_bytes(b"")
    (tmp_path / "other").mkdir()  # JSNAP_CACHE may be a folder that holds other things too
    (tmp_path / "other" / "keep.txt").write_text("not jsnap's")

    def listed():
        assert cli_main(["cache", "--json"]) == 0
        return {k: (v["files"], v["bytes"]) for k, v in json.loads(capsys.readouterr().out)["folders"].items()}

    assert listed() == {"neural_sdf": (1, 100), "reduced": (2, 350), "modal": (0, 0), "xla": (0, 0)}
    assert cli_main(["cache"]) == 0
    assert "reduced" in capsys.readouterr().out
    assert cli_main(["cache", "--clear", "reduced", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["removed_bytes"] == {"reduced": 350}
    assert listed() == {"neural_sdf": (1, 100), "reduced": (0, 0), "modal": (0, 0), "xla": (0, 0)}
    assert (tmp_path / "reduced" / "b.npz.lock").exists()
    assert cli_main(["cache", "--clear", "nonsense"]) == 2
    assert "nonsense" in capsys.readouterr().err
    assert cli_main(["cache", "--clear"]) == 0
    assert "removed neural_sdf" in capsys.readouterr().out
    assert listed() == {"neural_sdf": (0, 0), "reduced": (0, 0), "modal": (0, 0), "xla": (0, 0)}
    assert (tmp_path / "other" / "keep.txt").read_text() == "not jsnap's"
