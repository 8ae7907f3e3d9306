"""Draw the imports between jsnap's modules, grouped by layer, as a Graphviz graph.

The graph is grimp's (the import graph that ``lint-imports`` checks the layering contracts on,
pyproject.toml); Graphviz lays it out:

    python tools/import_graph.py | dot -Tsvg -o docs/img/imports.svg

One box per layer (jsnap/_apps, _build, _core, _geometry), an arrow from each module to each
module it imports, the top-level package (the public API), and the host libraries that only
geometry, build and the applications may use (scikit-fem, meshio, trimesh, scipy, matplotlib,
flax, optax; dotted arrows). A dashed arrow is an import made on first use (the public names
``jsnap`` loads lazily, ``jsnap._LAZY``). Left to right: importers before what they import.
"""

from __future__ import annotations

import argparse
import sys

import grimp

PACKAGE = "jsnap"
LAYERS = {
    "_apps": ("applications", "#fde2e2"),
    "_build": ("build (host, once)", "#fff2cc"),
    "_geometry": ("geometry", "#e2f0d9"),
    "_core": ("core (pure JAX)", "#dae8fc"),
}
HOST = ("skfem", "meshio", "trimesh", "gmsh", "scipy", "matplotlib", "flax", "optax")


def _node(module: str) -> str:
    return '"' + module + '"'


def dot() -> str:
    """The import graph in Graphviz's DOT language (sorted: the same tree gives the same text)."""
    graph = grimp.build_graph(PACKAGE, include_external_packages=True)
    modules = sorted(m for m in graph.modules if m == PACKAGE or m.startswith(PACKAGE + "."))
    edges = sorted(
        (m, imported)
        for m in modules
        for imported in graph.find_modules_directly_imported_by(m)
        if imported in modules or imported.split(".")[0] in HOST
    )
    used = {m for edge in edges for m in edge}
    import jsnap

    lazy = sorted({(PACKAGE, module) for module in getattr(jsnap, "_LAZY", {}).values()})
    used |= {m for edge in lazy for m in edge}

    out = [
        "digraph imports {",
        '  graph [rankdir=LR, newrank=true, nodesep=0.15, ranksep=0.45, fontname="Helvetica", fontsize=12];',
        '  node [shape=box, style="rounded,filled", fillcolor=white, fontname="Helvetica", fontsize=10];',
        '  edge [color="#555555", arrowsize=0.6];',
        f'  {_node(PACKAGE)} [label="jsnap\\n(public API)", fillcolor="#eeeeee"];',
    ]
    for layer, (title, colour) in LAYERS.items():
        prefix = f"{PACKAGE}.{layer}"
        members = [m for m in modules if m.startswith(prefix + ".") or (m == prefix and m in used)]
        out.append(f'  subgraph "cluster_{layer}" {{')
        out.append(f'    label="{title}: jsnap/{layer}"; style=filled; color="#999999"; fillcolor="{colour}";')
        for m in members:
            label = m[len(prefix) + 1 :] or layer
            out.append(f'    {_node(m)} [label="{label}"];')
        out.append("  }")
    host = sorted({imported for _, imported in edges if imported.split(".")[0] in HOST})
    out.append('  subgraph "cluster_host" {')
    out.append('    label="host libraries"; style=dashed; color="#999999";')
    for m in host:
        out.append(f'    {_node(m)} [shape=ellipse, fillcolor="#f4f4f4"];')
    out.append("  }")
    for a, b in edges:
        style = ' [color="#aaaaaa", style=dotted]' if b in host else ""
        out.append(f"  {_node(a)} -> {_node(b)}{style};")
    for a, b in lazy:
        out.append(f"  {_node(a)} -> {_node(b)} [style=dashed];")
    out.append("}")
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.parse_args(argv)
    sys.stdout.write(dot())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
