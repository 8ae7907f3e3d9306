"""The build cache's cross-process behaviour (jsnap._cache): processes asking for the same file
at once build it once; a corrupt file is rebuilt, once."""

import subprocess
import sys
import textwrap
import warnings

import pytest

from jsnap import _cache

# A worker: waits for the go file, then load_or_make on the shared path; its make sleeps (so the
# others arrive while it builds) and logs each build. Prints what it got.
WORKER = textwrap.dedent(
    """
    import os, sys, time
    from pathlib import Path
    from jsnap._cache import load_or_make

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
