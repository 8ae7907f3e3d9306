"""The package's shape in numbers: scene keys, solver choices a user can combine, lines per layer.

    python tools/package_shape.py                          # the working tree
    python tools/package_shape.py --rev 2f0cedf --rev HEAD # git revisions, side by side
    python tools/package_shape.py --rev 2f0cedf --worktree --json shape.json

For each revision (files read with ``git show REV:path``; the working tree from disk):

- scene keys: how many a scene file may set (visible) and how many only tests and benchmarks
  may set (internal), from the scene schema (``SCHEMA`` in jsnap/_geometry/scene.py, or
  ``_SCHEMA`` in jsnap/_scene.py before the layers, when every key was visible);
- combinations: the product of the numbers of visible choices of the keys that pick a solver or
  method (solver.method, solver.sdf, contact.solver, solver.element, solver.dtype,
  motion.control, contact.gradient): how many configurations a user can ask for, each of which
  must work;
- lines per layer: files, lines and code lines (neither blank, nor comment only, nor
  docstring) of the Python modules of each layer. Layers are the folders jsnap/_geometry,
  _build, _core and _apps, and jsnap/__init__.py (the public API); before the layers the flat
  modules map to them as listed in ``FLAT``.
"""

from __future__ import annotations

import argparse
import ast
import io
import json
import subprocess
import sys
import tokenize
import types
from pathlib import Path, PurePosixPath

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ("geometry", "build", "core", "apps", "api")
CHOICE_KEYS = (
    ("solver", "method"),
    ("solver", "sdf"),
    ("contact", "solver"),
    ("solver", "element"),
    ("solver", "dtype"),
    ("motion", "control"),
    ("contact", "gradient"),
)
# Where the scene schema lives (path, name), newest layout first.
SCHEMAS = (("jsnap/_geometry/scene.py", "SCHEMA"), ("jsnap/_scene.py", "_SCHEMA"))
# The flat modules of the package before the layers, by layer.
FLAT = {
    "geometry": ("_scene", "_geometry"),
    "build": ("_fem", "_model", "_modal", "_reduce", "_neural_sdf", "_cache"),
    "core": ("_integrate", "_socket", "_sim", "_contact", "_implicit", "_sdf", "_util", "_nonlinear"),
    "apps": ("_cli", "_identify", "_bench", "_xla"),
}


class Source:
    """The package's files at a git revision (``rev``) or in the working tree (``rev=None``)."""

    def __init__(self, rev: str | None):
        self.rev = rev
        if rev is not None:
            self.commit = self._git("rev-parse", "--short", f"{rev}^{{commit}}").strip()

    @property
    def name(self) -> str:
        if self.rev is None:
            return "working tree"
        return self.rev if self.commit.startswith(self.rev) else f"{self.rev} ({self.commit})"

    def _git(self, *args: str) -> str:
        return subprocess.run(["git", *args], cwd=ROOT, check=True, capture_output=True, text=True).stdout

    def python_files(self) -> list[str]:
        if self.rev is None:
            return sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "jsnap").rglob("*.py"))
        listed = self._git("ls-tree", "-r", "--name-only", self.rev, "--", "jsnap")
        return sorted(p for p in listed.splitlines() if p.endswith(".py"))

    def read(self, path: str) -> str | None:
        if self.rev is None:
            file = ROOT / path
            return file.read_text() if file.is_file() else None
        try:
            return self._git("show", f"{self.rev}:{path}")
        except subprocess.CalledProcessError:
            return None


def layer_of(path: str) -> str:
    """The layer of a module of the package, from its path (new layout or the flat one)."""
    parts = PurePosixPath(path).parts
    if parts == ("jsnap", "__init__.py"):
        return "api"
    folder = parts[1].removeprefix("_")
    if len(parts) > 2 and folder in LAYERS:
        return folder
    stem = PurePosixPath(path).stem
    for layer, modules in FLAT.items():
        if len(parts) == 2 and stem in modules:
            return layer
    raise ValueError(f"{path}: no layer for this module; add it to FLAT in {Path(__file__).name}")


def load_schema(source: Source) -> dict:
    """The scene schema of a revision: its module run on its own, with jsnap's imports left out
    (the schema needs none of them; the module's functions are never called)."""
    found = [(path, name, source.read(path)) for path, name in SCHEMAS]
    found = [f for f in found if f[2] is not None]
    if not found:
        raise FileNotFoundError(f"{source.name}: no scene schema at {', '.join(p for p, _ in SCHEMAS)}")
    path, name, text = found[0]
    tree = ast.parse(text)
    body = []
    for node in tree.body:
        if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "jsnap":
            names = [alias.asname or alias.name for alias in node.names]
            body.append(ast.parse("\n".join(f"{n} = None" for n in names)).body)
        else:
            body.append([node])
    tree.body = [node for nodes in body for node in nodes]
    module = types.ModuleType("_jsnap_schema_at_revision")
    sys.modules[module.__name__] = module  # dataclasses look their module up
    try:
        exec(compile(tree, f"{source.name}:{path}", "exec"), module.__dict__)
    finally:
        del sys.modules[module.__name__]
    return getattr(module, name)


def code_lines(text: str) -> int:
    """Lines that hold code: not blank, not only a comment, not part of a docstring."""
    lines = set()
    for tok in tokenize.generate_tokens(io.StringIO(text).readline):
        if tok.type not in (tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT):
            lines.update(range(tok.start[0], tok.end[0] + 1))
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
            first = node.body[0] if node.body else None
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                if isinstance(first.value.value, str):
                    lines -= set(range(first.lineno, first.end_lineno + 1))
    lines.discard(len(text.splitlines()) + 1)  # the end marker's line
    return len(lines)


def shape(source: Source) -> dict:
    """The numbers of one revision (see the module docstring)."""
    schema = load_schema(source)
    visible = internal = 0
    for keys in schema.values():
        for spec in keys.values():
            if getattr(spec, "internal", False):
                internal += 1
            else:
                visible += 1
    choices = {}
    combinations = 1
    for section, key in CHOICE_KEYS:
        spec = schema[section][key]
        options = [] if getattr(spec, "internal", False) else list(spec.choices)
        choices[f"{section}.{key}"] = options
        combinations *= max(len(options), 1)
    layers = {layer: {"files": 0, "lines": 0, "code": 0} for layer in LAYERS}
    for path in source.python_files():
        text = source.read(path)
        counts = layers[layer_of(path)]
        counts["files"] += 1
        counts["lines"] += len(text.splitlines())
        counts["code"] += code_lines(text)
    total = {k: sum(c[k] for c in layers.values()) for k in ("files", "lines", "code")}
    return {
        "revision": source.name,
        "scene_keys": {"visible": visible, "internal": internal},
        "choices": choices,
        "combinations": combinations,
        "layers": layers,
        "total": total,
    }


def _counts(c: dict) -> str:
    return f"{c['files']} / {c['lines']} / {c['code']}"


def table(results: list[dict]) -> str:
    """The numbers as a Markdown table, one column per revision."""
    rows = [
        ("scene keys a scene file may set", lambda r: r["scene_keys"]["visible"]),
        ("internal scene keys (tests, benchmarks)", lambda r: r["scene_keys"]["internal"]),
        ("solver/method combinations offered", lambda r: r["combinations"]),
        *[
            (f"`{k}` choices", lambda r, k=k: " ".join(r["choices"][k]) or "(internal)")
            for k in (f"{s}.{k}" for s, k in CHOICE_KEYS)
        ],
        *[(f"{a}: files / lines / code lines", lambda r, a=a: _counts(r["layers"][a])) for a in LAYERS],
        ("total: files / lines / code lines", lambda r: _counts(r["total"])),
    ]
    out = ["| | " + " | ".join(r["revision"] for r in results) + " |", "|---" * (len(results) + 1) + "|"]
    out += [f"| {title} | " + " | ".join(str(get(r)) for r in results) + " |" for title, get in rows]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rev", action="append", default=[], help="a git revision (repeatable)")
    parser.add_argument("--worktree", action="store_true", help="also the working tree (the default alone)")
    parser.add_argument("--json", metavar="PATH", help="also write the numbers as JSON to PATH")
    args = parser.parse_args(argv)
    sources = [Source(rev) for rev in args.rev]
    if args.worktree or not sources:
        sources.append(Source(None))
    results = [shape(s) for s in sources]
    print(table(results))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
