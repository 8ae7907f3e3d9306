"""The frequency and throughput benchmarks: registered with `jsnap bench`, and their committed
results have the headline the README table reads (positive rates, the expected keys).

Running the scripts is tested by ``tests/test_bench.py::test_quick_benchmarks_run`` (``jsnap bench
--quick``); quick outputs are not committed.
"""

import json
from pathlib import Path

import pytest

from jsnap._apps import bench as _bench

ROOT = Path(__file__).resolve().parent.parent / "benchmarks"


def _load(stem):
    path = ROOT / "results" / f"{stem}.json"
    if not path.is_file():
        pytest.skip(f"{path.name} not present")
    return json.loads(path.read_text())


@pytest.mark.parametrize("name", ["frequency", "throughput"])
def test_registered_with_quick_variant(name):
    bench = {b.name: b for b in _bench.available(ROOT)}
    assert name in bench and bench[name].quick


def test_frequency_headline():
    d = _load("frequency")
    h = d["headline"]
    meshes = ["coarse", "fine"]
    assert set(h["full_dof"]) == set(meshes)
    for key in ("scan_steps_per_second", "python_steps_per_second", "scan_compile_seconds"):
        for mesh in meshes:
            assert set(h[key][mesh]) == {"1", "2", "3", "4"}
    rates = [
        v
        for key in ("scan_steps_per_second", "python_steps_per_second")
        for m in meshes
        for v in h[key][m].values()
    ]
    assert min(rates) > 0
    assert 600 <= h["full_dof"]["coarse"] <= 720 and 1150 <= h["full_dof"]["fine"] <= 1400
    assert "dof" in _bench._frequency(d)


def test_throughput_headline():
    d = _load("throughput")
    h = d["headline"]
    for key in ("device", "full_dof", "dof", "best_batch", "best_scene_steps_per_second"):
        assert key in h
    assert h["best_scene_steps_per_second"] > 0 and h["batch_1_scene_steps_per_second"] > 0
    assert h["dof"] < h["full_dof"]
    for result in d["results"].values():  # one entry per platform (cpu, gpu), kept apart
        for rows in result["series"].values():
            assert [r["batch"] for r in rows] == sorted(r["batch"] for r in rows)
            assert all(r["scene_steps_per_second"] > 0 for r in rows)
    assert "scene-steps/s" in _bench._throughput(d)
