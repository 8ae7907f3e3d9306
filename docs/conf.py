"""Sphinx configuration of jsnap's documentation (MyST Markdown, autodoc for the API page).

Build: ``sphinx-build -W --keep-going -b html docs docs/_build/html`` (warnings are errors; the
test suite runs the same build, tests/test_docs_build.py).
"""

import os
from pathlib import Path

from sphinx import addnodes

import jsnap

DOCS = Path(__file__).resolve().parent

project = "jsnap"
author = "the jsnap developers"
copyright = "the jsnap developers"
release = jsnap.__version__
version = release

extensions = [
    "myst_parser",  # Markdown pages
    "sphinx.ext.autodoc",  # the API page, from the docstrings
    "sphinx.ext.napoleon",  # Google-style docstrings (Args:, Returns:, Raises:, Attributes:)
]

source_suffix = {".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build"]

# MyST: anchors for headings down to level 4, so that links such as ``contact.md#some-heading``
# are resolved (and a missing anchor is a warning, hence an error under -W).
myst_heading_anchors = 4

# autodoc: members in source order; type hints in the description of the arguments the
# docstring documents, not in long signatures (the docstrings give shapes and units).
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_typehints_description_target = "documented"
autodoc_typehints_format = "short"
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False
napoleon_use_ivar = True  # a pytree's fields as one list (their docstrings give shapes and units)

html_theme = "furo"
html_title = f"jsnap {release}"
html_static_path: list[str] = []


def _link_repository_markdown(app, doctree):
    """A page's link to a Markdown file of the repository outside docs/ (the README, the
    benchmarks' README) is taken by MyST for a page of the site, which that file is not: link the
    file itself, as MyST links any other file of the repository. MyST has checked that it exists
    (a missing one is a warning, hence an error); tests/test_docs_build.py checks its anchors."""
    for node in list(doctree.findall(addnodes.pending_xref)):
        if node.get("reftype") != "myst" or node.get("refdomain") != "doc":
            continue
        target = Path(node["reftarget"])
        if not target.is_absolute() or DOCS in target.parents:
            continue
        file = Path(f"{target}.md")
        if not file.is_file():
            continue
        link = addnodes.download_reference(
            refdomain=None,
            reftarget="/" + Path(os.path.relpath(file, DOCS)).as_posix(),  # "/": from docs/
            refdoc=node["refdoc"],
            reftype="myst",
            refexplicit=node.get("refexplicit", True),
        )
        link += node.children
        node.replace_self(link)


def setup(app):
    app.connect("doctree-read", _link_repository_markdown, priority=400)  # before the file collectors
