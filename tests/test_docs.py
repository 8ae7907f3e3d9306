"""The user-facing pages do what they say: README's and the guide's Python examples run as
written, in order, and give what their text promises; README's tables of outputs name what
`jsnap simulate` writes; relative links between the pages resolve.

The examples run on a coarse mesh: every scene they load (and the one `jsnap simulate`, README's
first command, runs to write their "measurement") is made coarse by wrapping ``load_scene``.
The test checks that the calls exist and do what the text says, not the default mesh's physics,
which other tests and the benchmarks check.
"""

import json
import re
import warnings
from pathlib import Path

import numpy as np
import pytest

import jsnap
import jsnap._geometry.scene as scene_module
from jsnap._apps.cli import main as cli_main

ROOT = Path(__file__).resolve().parents[1]
# The default scene (P2, 10 mm/s, 233 steps of 1 ms) on a 1.6 mm mesh: 1344 full dofs, a
# reduced model of 68. Elements larger than the undercut warn (SceneWarning): expected here.
COARSE = {"solver.mesh_size": 1.6}
# Pages made by the documentation build (docs/conf.py): links to them are checked only where
# they exist in this checkout.
GENERATED = {"docs/index.md", "docs/api.md", "docs/scene-reference.md", "docs/architecture.md"}
PAGES = ["README.md", *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "docs").glob("*.md"))]


def python_blocks(path: Path) -> list[str]:
    """The fenced ```python blocks of a Markdown file, in order."""
    return re.findall(r"^```python\n(.*?)^```", path.read_text(), flags=re.S | re.M)


def test_python_blocks_found(tmp_path):
    md = tmp_path / "x.md"
    md.write_text("text\n```python\na = 1\n```\n```bash\nls\n```\n```python\nb = 2\nc = 3\n```\n")
    assert python_blocks(md) == ["a = 1\n", "b = 2\nc = 3\n"]


@pytest.fixture
def coarse(monkeypatch, tmp_path):
    """``load_scene`` (public and the one the command line uses) returns coarse scenes; the
    working directory is a fresh folder; a fresh jsnap cache."""
    load = scene_module.load_scene

    def coarse_scene(*args, **kwargs):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", scene_module.SceneWarning)
            return load(*args, **kwargs).replace(COARSE)

    monkeypatch.setattr(jsnap, "load_scene", coarse_scene)
    monkeypatch.setattr(scene_module, "load_scene", coarse_scene)
    monkeypatch.setenv("JSNAP_CACHE", str(tmp_path / "cache"))
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    return work


def run(block: str, name: str, ns: dict) -> dict:
    exec(compile(block, name, "exec"), ns)
    return ns


def table_names(text: str, heading: str) -> list[str]:
    """The backquoted names in the first column of the Markdown table whose header row is
    ``heading``."""
    lines = text[text.index(heading) :].splitlines()[2:]  # past the header and the rule
    names = []
    for line in lines:
        if not line.strip().startswith("|"):
            break
        names += re.findall(r"`([^`]+)`", line.strip().split("|")[1])
    return names


def test_readme_examples_run(coarse, capsys):
    """README: `jsnap simulate` writes what the text lists; the Python examples build, roll out,
    batch, differentiate and fit the output of `jsnap simulate` as their comments say."""
    readme = (ROOT / "README.md").read_text()
    assert readme.startswith("# jsnap\n\n```bash\npip install -e . && jsnap simulate\n")
    assert 'pip install -e ".[test]" && python -m pytest -q' in readme.split("```")[1]

    assert cli_main(["simulate", "--json"]) == 0  # README's first command: writes jsnap-out/
    summary = json.loads(capsys.readouterr().out)
    out = coarse / "jsnap-out"
    for name in ("forces.csv", "forces.png", "summary.json", "vtu/socket.pvd"):
        assert (out / name).is_file(), name
    header = (out / "forces.csv").read_text().splitlines()[0].split(",")
    assert table_names(readme, "| column | meaning |") == header
    listed = re.findall(r"`(\w+)`", readme[readme.index("`summary.json`: the summary") :].split("\n\n")[0])
    assert set(listed) - {"summary", "json", "ok"} == set(summary), "README's summary.json fields"
    assert json.loads((out / "summary.json").read_text())["status"] == "ok"

    blocks = python_blocks(ROOT / "README.md")
    assert len(blocks) == 3, "README's Python examples changed: update this test"
    ns = run(blocks[0], "README.md: Python, block 1", {})
    res, stiffer, reference = ns["res"], ns["stiffer"], ns["reference"]
    F, F2 = np.asarray(res.insertion_force), np.asarray(stiffer.insertion_force)
    assert res.status() == "ok" and F.shape == (ns["model"].n_steps,)
    assert res.base_force.shape == res.base_moment.shape == (*F.shape, 3)
    # A linear part: up to the snap the force scales with E (2500 / 2200).
    rising = slice(int(np.argmax(F > 0.2 * F.max())), int(np.argmax(F)))
    assert np.allclose(F2[rising] / F[rising], 2500.0 / 2200.0, rtol=0.03)
    assert ns["full"].method == "full" and np.asarray(reference.insertion_force).dtype == np.float64
    assert F.max() == pytest.approx(np.asarray(reference.insertion_force).max(), rel=0.02)  # "~1 %"

    run(blocks[1], "README.md: Python, block 2", ns)
    assert ns["batch"].insertion_force.shape == (3, F.size) and np.all(ns["batch"].ok)
    peaks = np.asarray(ns["batch"].insertion_force).max(axis=1)
    assert peaks[0] < peaks[1] < peaks[2]
    dE, dfriction = float(ns["dE"]), float(ns["dfriction"])  # float64: read outside JAX
    assert np.isfinite(dfriction) and dE > 0  # the force grows with E

    capsys.readouterr()
    run(blocks[2], "README.md: Python, block 3", ns)
    fit = ns["fit"]
    # The "measurement" is the same scene's own output at E = 2200 MPa, friction 0.3.
    assert fit.values["E"] == pytest.approx(2200.0, rel=0.02)
    assert fit.values["friction"] == pytest.approx(0.3, rel=0.02)
    assert "E" in capsys.readouterr().out and (coarse / "fit.png").is_file()


def test_guide_examples_run(coarse, capsys):
    """docs/guide.md: every Python example runs as written, in order, on the coarse scene."""
    blocks = python_blocks(ROOT / "docs" / "guide.md")
    assert blocks, "docs/guide.md has no Python examples"
    assert cli_main(["simulate", "--json"]) == 0  # the guide's first run: writes jsnap-out/
    capsys.readouterr()
    ns: dict = {}
    for i, block in enumerate(blocks, 1):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", scene_module.SceneWarning)
            run(block, f"docs/guide.md: Python, block {i}", ns)


def _anchors(path: Path) -> set[str]:
    """GitHub-style anchors of a Markdown file's headings."""
    out = set()
    text = re.sub(r"^```.*?^```", "", path.read_text(), flags=re.S | re.M)
    for title in re.findall(r"^#+ (.+)$", text, flags=re.M):
        slug = re.sub(r"[^\w\- ]", "", title.strip().lower().replace("`", "")).replace(" ", "-")
        out.add(slug)
    return out


@pytest.mark.parametrize("page", PAGES)
def test_relative_links_resolve(page):
    """Every relative link of README.md and docs/*.md names a file (and heading) that exists."""
    path = ROOT / page
    text = re.sub(r"^```.*?^```", "", path.read_text(), flags=re.S | re.M)
    assert "../shared" not in text and "/work/shared" not in text
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+:", target):
            continue
        file, _, anchor = target.partition("#")
        dest = (path.parent / file).resolve() if file else path
        rel = str(dest.relative_to(ROOT)) if dest.is_relative_to(ROOT) else str(dest)
        if rel in GENERATED and not dest.exists():
            continue
        assert dest.exists(), f"{page}: link to {target}: no such file"
        if anchor and dest.suffix == ".md":
            assert anchor in _anchors(dest), f"{page}: link to {target}: no such heading"


@pytest.mark.parametrize("page", PAGES)
def test_no_history(page):
    """The pages state what holds; the project's history lives in git."""
    text = (ROOT / page).read_text()
    assert not re.search(r"sessions? [0-9]+|session [0-9]", text, flags=re.I)
