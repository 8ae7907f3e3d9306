"""notebooks/fit_material.ipynb runs top to bottom at its small settings.

nbformat/nbclient are not dependencies: a notebook is JSON, and its code cells run here in one
namespace, in order, in a scratch directory, with a non-interactive matplotlib backend.
"""

import json
import os
from pathlib import Path

import matplotlib
import numpy as np
import pytest

NOTEBOOK = Path(__file__).parents[1] / "notebooks" / "fit_material.ipynb"


@pytest.mark.slow
def test_fit_material_notebook_runs(tmp_path, monkeypatch):
    matplotlib.use("Agg")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("JSNAP_NOTEBOOK_SMALL", "1")
    nb = json.loads(NOTEBOOK.read_text())
    assert nb["nbformat"] == 4
    ns = {"__name__": "__main__"}
    code = [c for c in nb["cells"] if c["cell_type"] == "code"]
    assert len(code) >= 4
    for i, cell in enumerate(code):
        exec(compile("".join(cell["source"]), f"{NOTEBOOK.name}[code cell {i}]", "exec"), ns)
    assert os.path.getsize("measured.csv") > 0 and os.path.getsize("fit_material.png") > 10_000
    fit = ns["fit"]
    # Small settings (coarse meshes, 6 iterations): the fit moves from a factor 2 off to within
    # 25 % of the truth, and the standard errors are finite and positive.
    for k, true in ns["TRUE"].items():
        assert abs(fit.values[k] / true - 1) < 0.25
        assert 0 < fit.std_errors[k] < float("inf")
    # The fitted force is far closer to the measurement than the starting model's.
    m = fit.mask
    rms = lambda F: float(np.sqrt(np.mean((F[m] - fit.measured[m]) ** 2)))  # noqa: E731
    assert rms(fit.fitted) < 0.3 * rms(fit.start)


OWN = Path(__file__).parents[1] / "notebooks" / "own_connector.ipynb"


@pytest.mark.slow
def test_own_connector_notebook_runs(tmp_path, monkeypatch):
    """Two STL files to a force curve and a ParaView series: the notebook runs top to bottom
    (small settings: the full model on a coarse mesh) and its peak is the shipped hook's within
    the mesh difference and the tilt's effect."""
    matplotlib.use("Agg")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("JSNAP_NOTEBOOK_SMALL", "1")
    nb = json.loads(OWN.read_text())
    ns = {"__name__": "__main__"}
    for i, cell in enumerate(c for c in nb["cells"] if c["cell_type"] == "code"):
        exec(compile("".join(cell["source"]), f"{OWN.name}[code cell {i}]", "exec"), ns)
    assert os.path.getsize("own_connector.png") > 10_000
    assert (tmp_path / "own_connector" / "vtu" / "socket.pvd").is_file()
    assert ns["result"].status() == "ok"
    assert 4.0 < float(np.max(ns["F"])) < 6.5  # the default hook peaks at 5.1 N


DESIGN = Path(__file__).parents[1] / "notebooks" / "design_preset.ipynb"


@pytest.mark.slow
def test_design_preset_notebook_runs(tmp_path, monkeypatch):
    """The two-hook clip preset, redesigned twice: the notebook runs top to bottom (small
    settings: the full model on a coarse mesh, a fast block) and leaves the three designs' peaks
    ordered as it says: the thinner arm with the smaller undercut lowers the force and the arms'
    strain, the stiffer PC raises the force by about the ratio of the moduli."""
    matplotlib.use("Agg")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("JSNAP_NOTEBOOK_SMALL", "1")
    nb = json.loads(DESIGN.read_text())
    code = [c for c in nb["cells"] if c["cell_type"] == "code"]
    assert all(not c["outputs"] and c["execution_count"] is None for c in code)  # stored cleared
    ns = {"__name__": "__main__"}
    for i, cell in enumerate(code):
        exec(compile("".join(cell["source"]), f"{DESIGN.name}[code cell {i}]", "exec"), ns)
    assert os.path.getsize("design_preset.png") > 10_000
    shipped, slim, pc = ns["shipped"], ns["slim"], ns["pc"]
    forces = [d.peak_force for d in (shipped, slim, pc)]
    strains = [d.arm.max_principal for d in (shipped, slim, pc)]
    assert np.all(np.isfinite(forces)) and np.all(np.isfinite(strains))
    assert forces[1] < forces[0] and forces[1] < forces[2]
    assert strains[1] < strains[0] and strains[1] < slim.allowable
    assert abs(forces[2] / forces[1] / (ns["E_PC"] / ns["E_ABS"]) - 1) < 0.03
    # The shipped clip peaks at 8.8 N (full model, 0.8 mm mesh, 10 mm/s); at the small settings
    # (1.6 mm, 40 mm/s) at 9.6 N.
    assert 8.0 < forces[0] < 11.0
