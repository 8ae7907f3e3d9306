"""The documentation: the site builds without a warning, links resolve, the generated references
are up to date, and the layering contracts hold.

- The Sphinx site (docs/, MyST Markdown) builds with ``sphinx-build -W --keep-going -b html``:
  warnings are errors, so every link between its pages and every heading anchor they name
  (``contact.md#some-heading``) resolves, a page outside the table of contents fails, and the
  docstrings of the API page are valid reStructuredText.
- Every relative link of README.md, and every link of a docs page to a file outside docs/,
  points at a file or folder of the repository (and, where it names one, at a heading of that
  Markdown file).
- docs/scene-reference.md is what ``python -m jsnap._apps.scene_reference`` prints now, and the
  drawing docs/img/imports.svg shows the imports the package makes now.
- ``lint-imports`` keeps the contracts in pyproject.toml (the layers; no host library in core).

Not checked: external links (http, https, mailto), which need a network that the tests do not
have; only that they are well-formed.
"""

from __future__ import annotations

import html
import importlib.util
import re
import shutil
import subprocess
import sys
from pathlib import Path
from urllib.parse import unquote, urlparse

import pytest

from jsnap._apps import scene_reference
from jsnap._geometry.scene import CONNECTORS, SCHEMA, load_scene

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
# The site's table of contents, in this order (docs/index.md).
PAGES = [
    "guide",
    "own-connector",
    "gallery",
    "scene-reference",
    "api",
    "architecture",
    "contact",
    "reduction",
    "modal",
    "neural_sdf",
    "differentiation",
    "stability",
    "validation",
]


def _tool(name: str):
    """A script of tools/ as a module."""
    spec = importlib.util.spec_from_file_location(name, ROOT / "tools" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _sphinx(src: Path, out: Path) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html", str(src), str(out)]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=1200)


# -- Markdown links --------------------------------------------------------------------------------

_FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
_CODE = re.compile(r"`[^`\n]*`")
_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]*)>?(?:\s+\"[^\"]*\")?\s*\)")
_REF_DEF = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s+.*)?$", re.M)
_HEADING = re.compile(r"^#{1,6}\s+(.*?)\s*#*\s*$", re.M)


def _prose(text: str) -> str:
    """Markdown without its code blocks and code spans (links in code are not links)."""
    return _CODE.sub("", _FENCE.sub("", text))


def links(text: str) -> list[str]:
    """The targets of a Markdown text's inline links, images and link definitions."""
    prose = _prose(text)
    return _LINK.findall(prose) + _REF_DEF.findall(prose)


def slug(title: str) -> str:
    """A heading's anchor as GitHub and MyST (``myst_heading_anchors``) make it."""
    title = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", title)  # a link's text
    title = title.replace("`", "")
    return re.sub(r"[^\w\- ]", "", title.lower().replace(" ", "-"))


def anchors(text: str) -> set[str]:
    """The heading anchors of a Markdown text (repeated titles: ``-1``, ``-2``... as well)."""
    found: set[str] = set()
    seen: dict[str, int] = {}
    for title in _HEADING.findall(_FENCE.sub("", text)):
        s = slug(title)
        found.add(s if s not in seen else f"{s}-{seen[s]}")
        seen[s] = seen.get(s, 0) + 1
    return found


def broken_links(md: Path, only_outside: Path | None = None) -> list[str]:
    """What is wrong with the links of ``md``: relative ones that leave the repository, point at
    nothing or at a heading that is not there; external ones that are not well-formed.
    ``only_outside``: check only the relative links that point outside this folder."""
    problems = []
    for target in links(md.read_text()):
        where = f"{md.relative_to(ROOT)}: ({target})"
        parsed = urlparse(target)
        if parsed.scheme:
            if parsed.scheme in ("http", "https") and not (parsed.netloc and " " not in target):
                problems.append(f"{where}: not a well-formed URL")
            elif parsed.scheme not in ("http", "https", "mailto"):
                problems.append(f"{where}: unexpected scheme {parsed.scheme!r}")
            continue
        path, _, anchor = target.partition("#")
        file = (md.parent / unquote(path)).resolve() if path else md
        if only_outside is not None and only_outside in [file, *file.parents]:
            continue
        if ROOT not in file.parents and file != ROOT:
            problems.append(f"{where}: outside the repository")
        elif not file.exists():
            problems.append(f"{where}: no such file or folder")
        elif anchor and file.suffix == ".md" and anchor not in anchors(file.read_text()):
            problems.append(f"{where}: no heading with the anchor #{anchor} in {file.relative_to(ROOT)}")
    return problems


def test_link_checker_finds_broken_links(tmp_path, monkeypatch):
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    (tmp_path / "b.md").write_text("# B page\n\n## The `x` setting (opt-in)\n\n## Twice\n\n## Twice\n")
    md = tmp_path / "a.md"
    md.write_text(
        "# A\n[ok](b.md#the-x-setting-opt-in) [ok](b.md#twice-1) [ok](#a) ![img](b.md) [web](https://x.org/a)\n"
        "[bad anchor](b.md#nope) [missing](c.md) [outside](../elsewhere.md) [web](https:/x)\n"
        "`[in code](nothing.md)`\n```\n[in a block](nothing.md)\n```\n[def]: nothing2.md\n"
    )
    problems = broken_links(md)
    assert [p.split(": ", 1)[1] for p in problems] == [
        "(b.md#nope): no heading with the anchor #nope in b.md",
        "(c.md): no such file or folder",
        "(../elsewhere.md): outside the repository",
        "(https:/x): not a well-formed URL",
        "(nothing2.md): no such file or folder",
    ]


def test_readme_links_resolve():
    problems = broken_links(ROOT / "README.md")
    assert not problems, "\n".join(problems)


def test_docs_links_out_of_the_site_resolve():
    """Links from a page to the rest of the repository (Sphinx checks the ones between pages,
    and that these files exist; not their anchors)."""
    problems = [p for page in sorted(DOCS.glob("*.md")) for p in broken_links(page, only_outside=DOCS)]
    assert not problems, "\n".join(problems)


# -- the site --------------------------------------------------------------------------------------


def test_index_lists_the_pages_in_order():
    text = (DOCS / "index.md").read_text()
    blocks = re.findall(r"^```\{toctree\}\n(.*?)^```", text, flags=re.S | re.M)
    entries = [
        line.strip() for block in blocks for line in block.splitlines() if line.strip() and line[0] != ":"
    ]
    assert entries == PAGES


def test_site_builds_without_warnings(tmp_path):
    """The whole site, warnings as errors (the links and anchors between pages included)."""
    proc = _sphinx(DOCS, tmp_path / "html")
    assert proc.returncode == 0, f"sphinx-build failed:\n{proc.stdout[-5000:]}\n{proc.stderr[-10000:]}"
    for page in PAGES:
        assert (tmp_path / "html" / f"{page}.html").is_file()
    api = (tmp_path / "html" / "api.html").read_text()
    import jsnap

    for name in jsnap.__all__:
        assert f'id="jsnap.{name}"' in api, f"jsnap.{name} is missing from the API page"


def test_site_build_fails_on_a_broken_anchor(tmp_path):
    """The check above is real: with the site's configuration, a link to a heading that does
    not exist fails the build."""
    src = tmp_path / "docs"
    src.mkdir()
    shutil.copy(DOCS / "conf.py", src)
    (src / "index.md").write_text(
        "# Home\n\n[ok](b.md#part-two) [broken](b.md#part-three)\n\n```{toctree}\nb\n```\n"
    )
    (src / "b.md").write_text("# B\n\n## Part two\n")
    proc = _sphinx(src, tmp_path / "html")
    assert proc.returncode != 0
    assert "part-three" in proc.stderr and "part-two" not in proc.stderr


# -- generated references --------------------------------------------------------------------------


def test_scene_reference_is_up_to_date():
    committed = (DOCS / "scene-reference.md").read_text()
    assert committed == scene_reference.render(), (
        f"docs/scene-reference.md is out of date with the scene schema: run `{scene_reference.COMMAND}`"
    )


def test_scene_reference_shows_the_visible_keys_only():
    text = scene_reference.render()
    for section, keys in SCHEMA.items():
        part = text.split(f"\n## [{section}]\n", 1)[1].split("\n## ", 1)[0]
        if section == "connector":  # each preset's keys in a table of its own, under ### type = "..."
            tables = part.split("\n### ")
            part = tables[0]
            for kind, kind_keys in CONNECTORS.items():
                table = next(t for t in tables[1:] if t.startswith(f'type = "{kind}"'))
                rows = set(re.findall(r"^\| `(\w+)` \|", table, flags=re.M))
                assert rows == {k for k, spec in kind_keys.items() if not spec.internal}, kind
        rows = set(re.findall(r"^\| `(\w+)` \|", part, flags=re.M))
        assert rows == {k for k, spec in keys.items() if not spec.internal}, section
        for spec in keys.values():
            for choice in spec.internal_choices:
                assert f'"{choice}"' not in part, (section, choice)


def test_scene_reference_example_is_a_valid_scene(tmp_path):
    example = re.search(r"```toml\n(.*?)```", scene_reference.render(), flags=re.S).group(1)
    (tmp_path / "minimal.toml").write_text(example)
    scene = load_scene(tmp_path / "minimal.toml")
    assert scene["material"]["youngs_modulus"] > 0


def test_import_drawing_is_up_to_date():
    """The SVG's edges (Graphviz writes each edge's ``a->b`` as its title) are the imports the
    package makes now."""
    dot = _tool("import_graph").dot()
    now = set(re.findall(r'^\s*"([\w.]+)" -> "([\w.]+)"', dot, flags=re.M))
    titles = re.findall(r"<title>(.*?)</title>", (DOCS / "img" / "imports.svg").read_text())
    drawn = {tuple(html.unescape(t).split("->")) for t in titles if "->" in html.unescape(t)}
    assert drawn == now, (
        "docs/img/imports.svg is out of date: with Graphviz installed, run "
        "`python tools/import_graph.py | dot -Tsvg -o docs/img/imports.svg`"
    )


def _have_revisions(*revs: str) -> bool:
    for rev in revs:
        proc = subprocess.run(["git", "cat-file", "-e", f"{rev}^{{commit}}"], cwd=ROOT, capture_output=True)
        if proc.returncode != 0:
            return False
    return True


def test_architecture_shape_table_is_what_the_script_prints():
    """The before/after table on the architecture page is the output of the command it shows."""
    text = (DOCS / "architecture.md").read_text()
    command = re.search(r"^python tools/package_shape\.py (.*)$", text, flags=re.M).group(1)
    revs = re.findall(r"--rev (\S+)", command)
    if not _have_revisions(*revs):
        pytest.skip(f"this clone lacks one of the revisions {revs}")
    out = subprocess.run(
        [sys.executable, str(ROOT / "tools" / "package_shape.py"), *command.split()],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert out.strip() in text


def test_package_shape_of_the_working_tree():
    shape = _tool("package_shape")
    result = shape.shape(shape.Source(None))
    visible = sum(not spec.internal for keys in SCHEMA.values() for spec in keys.values())
    assert result["scene_keys"] == {
        "visible": visible,
        "internal": sum(len(k) for k in SCHEMA.values()) - visible,
    }
    assert result["choices"]["contact.solver"] == list(SCHEMA["contact"]["solver"].choices)
    assert result["total"]["files"] == len(list((ROOT / "jsnap").rglob("*.py")))
    assert all(result["layers"][layer]["code"] > 0 for layer in ("geometry", "build", "core", "apps"))


# -- the layering ----------------------------------------------------------------------------------


def test_import_contracts_hold():
    """``lint-imports`` with the contracts of pyproject.toml: the layers, and no host library
    imported by jsnap._core, directly or through another module."""
    exe = Path(sys.executable).with_name("lint-imports")
    cmd = [str(exe) if exe.is_file() else shutil.which("lint-imports") or "lint-imports", "--no-cache"]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-5000:] + proc.stderr[-3000:]
    assert "0 broken" in proc.stdout
