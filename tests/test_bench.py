"""`jsnap bench`: the runner, the README table it regenerates, and a quick benchmark end to end."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from jsnap._apps import bench as _bench
from jsnap._apps.cli import main as cli_main
from jsnap._apps.xla import SMALL_LOOP_OPTION, xla_cpu_flags

ROOT = Path(__file__).resolve().parent.parent / "benchmarks"


def test_list_and_unknown_names(capsys):
    assert cli_main(["bench", "--list"]) == 0
    listed = capsys.readouterr().out
    for b in _bench.available(ROOT):
        assert b.name in listed
    assert cli_main(["bench", "no_such_benchmark"]) == 2


def test_readme_table_from_results(tmp_path, monkeypatch):
    """The table has one row per script, the headline from its JSON, 'not run yet' without one."""
    bench = tmp_path / "benchmarks"
    (bench / "results").mkdir(parents=True)
    for name in ("contact_squeeze", "fem_convergence"):
        shutil.copy(ROOT / f"{name}.py", bench / f"{name}.py")
    result = {"richardson_mm": 0.7696, "observed_order": 2.07, "calculix_converged_mm": 0.7695, "rows": []}
    (bench / "results" / "fem_convergence.json").write_text(json.dumps(result))
    monkeypatch.setenv("JSNAP_BENCHMARKS", str(bench))
    text = _bench.write_readme(_bench.benchmarks_dir()).read_text()
    rows = [line for line in text.splitlines() if line.startswith("| `")]
    assert len(rows) == 2
    assert "0.7696 mm" in next(r for r in rows if "fem_convergence" in r)
    assert "not run yet" in next(r for r in rows if "contact_squeeze" in r)


# Three scripts whose quick variants take seconds: the runner end to end (worker processes, the
# times file, the README) on every run of the suite.
SMOKE = ("contact_squeeze", "fem_convergence", "strain")


def _quick_run(tmp_path, monkeypatch, names: tuple[str, ...]) -> dict:
    """``jsnap bench [NAMES] --quick`` on a copy of benchmarks/, in its own process (the scripts'
    compiled programs and models stay out of the test process's memory); its times file."""
    bench = tmp_path / "benchmarks"
    shutil.copytree(ROOT, bench, ignore=shutil.ignore_patterns("results", "__pycache__"))
    monkeypatch.setenv("JSNAP_BENCHMARKS", str(bench))
    run = subprocess.run(
        [sys.executable, "-m", "jsnap._apps.cli", "bench", *names, "--quick"], cwd=tmp_path, check=False
    )
    assert run.returncode == 0
    times = json.loads((bench / "results" / "bench_times_quick.json").read_text())
    assert all(t["ok"] for t in times["scripts"].values())
    # The flags the scripts were compiled with are recorded.
    assert times["last"]["xla_flags"] == _bench.quick_xla_flags(os.environ.get("XLA_FLAGS", ""))
    return times


def test_quick_benchmarks_of_a_few_scripts_run(tmp_path, monkeypatch):
    """`jsnap bench NAME... --quick` runs the named scripts' quick variants end to end and records
    their times, not a complete run's."""
    times = _quick_run(tmp_path, monkeypatch, SMOKE)
    assert sorted(times["scripts"]) == sorted(SMOKE)
    assert "complete_run" not in times
    for name in SMOKE:
        assert (tmp_path / "benchmarks" / "results" / f"{name}_quick.json").is_file()


@pytest.mark.xslow
def test_quick_benchmarks_run(tmp_path, monkeypatch):
    """`jsnap bench --quick` runs every script that has a quick variant, end to end (so that the
    benchmarks never rot; its time is recorded in results/bench_times_quick.json, not asserted
    here). Benchmark-sized: about 8 minutes on two cores."""
    times = _quick_run(tmp_path, monkeypatch, ())
    quick = [b.name for b in _bench.available(ROOT) if b.quick]
    assert sorted(times["scripts"]) == sorted(quick)
    readme = (tmp_path / "benchmarks" / "README.md").read_text()
    assert "`jsnap bench --quick`:" in readme
    assert times["complete_run"]["xla_flags"] == times["last"]["xla_flags"]


def test_quick_xla_flags_keep_the_users():
    """The quick runs add their XLA flags to the user's (configure_xla_cpu's, then the quick
    ones), and a flag the user sets wins."""
    quick = [f for f in _bench.QUICK_XLA_FLAGS.split() if not f.startswith("--xla_backend_extra_options=")]
    flags = [*xla_cpu_flags("").split(), *quick]
    assert _bench.quick_xla_flags("").split() == flags
    assert _bench.quick_xla_flags(" --xla_foo=1 ").split() == ["--xla_foo=1", *flags]
    mine = "--xla_backend_optimization_level=3"
    out = _bench.quick_xla_flags(mine).split()
    assert mine in out and "--xla_backend_optimization_level=1" not in out
    assert "--xla_cpu_use_fusion_emitters=false" in out
    # XLA's small-loop option is among them (the quick scripts share worker processes, so a
    # script's own jsnap.configure_xla_cpu() would come too late), joined to the user's own extra
    # options; flags that already went through configure_xla_cpu (as `jsnap` does for its
    # process) give the same result.
    assert SMALL_LOOP_OPTION in _bench.quick_xla_flags("")
    user = "--xla_backend_extra_options=foo=1"
    out = _bench.quick_xla_flags(user)
    assert f"--xla_backend_extra_options=foo=1,{SMALL_LOOP_OPTION}=" in out
    assert _bench.quick_xla_flags(xla_cpu_flags(user)) == out
    assert _bench.quick_xla_flags(xla_cpu_flags("")) == _bench.quick_xla_flags("")


def test_full_run_untimed_side_by_side_then_timed_alone(tmp_path, monkeypatch):
    """A full run starts the untimed scripts together (two workers) and runs each timed one
    alone after them, all with JAX's compilation cache off; bench_times.json records which was
    which. Stand-in scripts log when they start (and the setting they saw) and when they end
    (the runner runs whatever benchmarks/<name>.py holds)."""
    bench = tmp_path / "benchmarks"
    (bench / "results").mkdir(parents=True)
    log = tmp_path / "log.txt"
    body = (
        "import os, sys, time\n"
        "log = open({log!r}, 'a')\n"
        "log.write(f'start {name} {{time.time()}} {{os.environ.get(\"JAX_ENABLE_COMPILATION_CACHE\")}}\\n')\n"
        "log.flush()\n"
        "time.sleep(1.0)\n"
        "log.write(f'end {name} {{time.time()}}\\n')\n"
    )
    names = ["fem_convergence", "stability", "contact_squeeze"]  # untimed, untimed, timed
    for name in names:
        (bench / f"{name}.py").write_text(body.format(log=str(log), name=name))
    monkeypatch.setenv("JSNAP_BENCHMARKS", str(bench))
    # A user's JAX compilation cache does not reach the scripts (they report compile times).
    monkeypatch.setenv("JAX_ENABLE_COMPILATION_CACHE", "true")
    assert _bench.main([], quick=False, list_only=False, jobs=2) == 0
    assert os.environ["JAX_ENABLE_COMPILATION_CACHE"] == "true"  # restored
    events = {}
    for line in log.read_text().splitlines():
        kind, name, t = line.split()[:3]
        events[(kind, name)] = float(t)
        if kind == "start":
            assert line.split()[3] == "false", line
    # The two untimed scripts overlapped; the timed one started after both had ended.
    assert events[("start", "stability")] < events[("end", "fem_convergence")]
    assert events[("start", "fem_convergence")] < events[("end", "stability")]
    last_untimed = max(events[("end", "fem_convergence")], events[("end", "stability")])
    assert events[("start", "contact_squeeze")] >= last_untimed
    times = json.loads((bench / "results" / "bench_times.json").read_text())
    assert {n: t["timed"] for n, t in times["scripts"].items()} == {
        "fem_convergence": False,
        "stability": False,
        "contact_squeeze": True,
    }
    assert times["complete_run"]["untimed_workers"] == 2


def test_jobs_must_be_positive(capsys):
    assert cli_main(["bench", "--jobs", "0", "contact_squeeze"]) == 2
    assert "--jobs 0" in capsys.readouterr().err
