"""Batched throughput at a few chosen batch sizes, for comparing two versions of the code side
by side on one machine: the default series of ``benchmarks/throughput.py`` (same scene, lanes
and timing) and its single scene without vmap, for the jsnap found from the current directory.

    python benchmarks/throughput_points.py TAG OUT_DIR [--batches 1,4096]

Run it once from each checkout (``cd old && PYTHONPATH=$PWD python ../new/benchmarks/
throughput_points.py old OUT``) in the same session on the same machine; each run writes
``OUT_DIR/points_TAG.json`` (not registered with ``jsnap bench``: it compares versions,
it does not describe one). ``benchmarks/results/throughput_gpu_points.json`` holds such a
comparison on an H100 with provenance.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path.cwd() / "benchmarks"))  # the checkout's own throughput.py

import jax
import throughput as T
from _common import code_version, load_scene

import jsnap


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("tag", help="name of this checkout in the output file")
    ap.add_argument("out", type=Path, help="folder for points_TAG.json")
    ap.add_argument("--batches", default="1,4096", help="comma-separated batch sizes")
    ap.add_argument("--steps", type=int, default=20)
    a = ap.parse_args(argv)
    batches = [int(b) for b in a.batches.split(",")]
    with jax.enable_x64(True):
        model = jsnap.build(load_scene(T.SCENE))
        rows = T.sweep(model, a.steps, batches, saturate=False)
        single = T.single(model, a.steps)
    for row in (*rows, single):
        row.pop("insertion_force_lane0", None)
    result = {
        "tag": a.tag,
        "device": str(jax.devices()[0]),
        "jsnap": jsnap.__file__,
        "code": code_version(),
        "orders": [int(k) for k in model.part.orders],
        "rows": rows,
        "single": single,
        "load_average": os.getloadavg()[0],
    }
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / f"points_{a.tag}.json").write_text(json.dumps(result, indent=1) + "\n")
    print(a.tag, {r["batch"]: round(r["scene_steps_per_second"]) for r in rows}, flush=True)


if __name__ == "__main__":
    main()
