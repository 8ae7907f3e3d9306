"""The README's Python API examples run as written, in order, on a coarse mesh.

Every scene the examples (and the `jsnap simulate` that writes their measurement) load is made
coarse by wrapping ``jsnap.load_scene``: the test checks that the examples' calls exist and do
what the text says (the fit recovers the parameters that made the data), not the default mesh's
physics, which other tests check.
"""

import re
from pathlib import Path

import numpy as np
import pytest

import jsnap
from jsnap._apps.cli import main as cli_main

ROOT = Path(__file__).resolve().parents[1]
# The default motion (10 mm/s, 233 steps) on a coarse P1 mesh, in float64: the measurement
# (`jsnap simulate`, in the scene's dtype) is then the fitted model's own output at the true
# parameters. (Not faster motion: at 40 mm/s the snap falls between 0.04-mm steps, the fit's loss
# is piecewise smooth in E, and the fit from its seed stopped in a local minimum 2.4 % off E.)
COARSE = {"solver.element": "P1", "solver.mesh_size": 1.5, "solver.dtype": "float64"}


def python_blocks(path: Path) -> list[str]:
    """The fenced ```python blocks of a Markdown file, in order."""
    return re.findall(r"^```python\n(.*?)^```", path.read_text(), flags=re.S | re.M)


def test_python_blocks_found(tmp_path):
    md = tmp_path / "x.md"
    md.write_text("text\n```python\na = 1\n```\n```bash\nls\n```\n```python\nb = 2\nc = 3\n```\n")
    assert python_blocks(md) == ["a = 1\n", "b = 2\nc = 3\n"]


def test_readme_api_examples_run(tmp_path, monkeypatch, capsys):
    """README "Python API": build, rollout, new parameters, gradients, and the fit to the
    output of README's first command (`jsnap simulate`, run here first), in a fresh folder."""
    blocks = [b for b in python_blocks(ROOT / "README.md") if "jsnap." in b]
    assert len(blocks) == 2, "README's Python API section changed: update this test"
    load = jsnap.load_scene
    monkeypatch.setattr(jsnap, "load_scene", lambda *a, **k: load(*a, **k).replace(COARSE))
    monkeypatch.chdir(tmp_path)
    assert cli_main(["simulate", "--json"]) == 0  # README's first command: writes jsnap-out/
    capsys.readouterr()

    ns: dict = {}
    exec(compile(blocks[0], "README.md: Python API, block 1", "exec"), ns)
    F, F2 = np.asarray(ns["res"].insertion_force), np.asarray(ns["res2"].insertion_force)
    assert F.shape == (ns["model"].trajectory().shape[0] - 1,) and ns["res"].base_force.shape == (*F.shape, 3)
    # A linear socket, frictionless: up to the snap, force scales with E (2500 / 2200).
    rising = slice(int(np.argmax(F > 0.2 * F.max())), int(np.argmax(F)))
    assert np.allclose(F2[rising] / F[rising], 2500.0 / 2200.0, rtol=0.03)

    exec(compile(blocks[1], "README.md: Python API, block 2", "exec"), ns)
    assert np.isfinite(ns["dE"]) and np.isfinite(ns["dmu"])
    # Force grows with E: d(sum F^2)/dE > 0.
    assert ns["dE"] > 0
    fit = ns["fit"]
    # The measurement is `jsnap simulate`'s default scene (E 2200 MPa, friction 0.3) on the same
    # mesh: the fit from the frictionless model recovers both (measured: 0.11 % and 0.8 % off; the
    # violent snap of this stiff P1 mesh leaves a local minimum near the truth, 0.58 N RMS).
    assert fit.values["E"] == pytest.approx(2200.0, rel=0.02)
    assert fit.values["friction"] == pytest.approx(0.3, rel=0.02)
    assert "E" in capsys.readouterr().out  # summary printed
