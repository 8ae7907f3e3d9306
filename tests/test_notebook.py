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
