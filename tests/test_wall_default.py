"""The default element size of a part from a file follows its thinnest wall, and a scene warns
when its elements leave that wall unresolved (jsnap._geometry.size.thinnest_wall).

The case that made the change: a printed hook, arms 6 x 7 mm on a bulky 40 x 40 x 20 mm base.
The area-weighted median thickness measured the base (20 mm) and made 13.3 mm elements, fewer
than one across the arms, without a word. Geometry and scene checks only: no rollout.
"""

from __future__ import annotations

import glob
import tomllib
import warnings
from pathlib import Path

import gmsh
import pytest
import trimesh

import jsnap
from jsnap._geometry.part import part_thinnest_wall
from jsnap._geometry.size import REFERENCE_WALL, elements_across, thinnest_wall

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "own_connector"
BASE = (40.0, 40.0, 20.0)  # x, y, z, mm; its bottom face z = 0 is fixed
ARM = (6.0, 7.0, 30.0)  # on the base's top face, centred: 6 mm thick (x), 7 mm wide (y)


def _fused_boxes(path: Path) -> None:
    """The base and its arm fused into one closed surface (gmsh's OpenCASCADE kernel), STL."""
    initialised = gmsh.isInitialized()
    if not initialised:
        gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("block-arm")
        base = gmsh.model.occ.addBox(-BASE[0] / 2, -BASE[1] / 2, 0.0, *BASE)
        arm = gmsh.model.occ.addBox(-ARM[0] / 2, -ARM[1] / 2, BASE[2], *ARM)
        gmsh.model.occ.fuse([(3, base)], [(3, arm)])
        gmsh.model.occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMax", 2.0)
        gmsh.model.mesh.generate(2)
        gmsh.write(str(path))
    finally:
        gmsh.model.remove()
        if not initialised:
            gmsh.finalize()


@pytest.fixture(scope="module")
def block_arm(tmp_path_factory) -> dict:
    """A scene of the thin arm on its thick base, a rigid block above the arm's tip."""
    d = tmp_path_factory.mktemp("block_arm")
    _fused_boxes(d / "part.stl")
    block = trimesh.creation.box([4.0, 9.0, 2.0])
    block.apply_translation([ARM[0] / 2 + 1.0, 0.0, BASE[2] + ARM[2] + 0.5])
    block.export(d / "block.stl")
    return {
        "part": {"mesh": str(d / "part.stl"), "fixed_box": [[-21.0, -21.0, -0.01], [21.0, 21.0, 0.01]]},
        "rigid": {"mesh": str(d / "block.stl")},
        "material": {"youngs_modulus": 2200.0, "poissons_ratio": 0.35, "density": 1.05e-9},
        "motion": {"stroke": 3.0},
    }


def _scene(raw: dict, **solver) -> jsnap.Scene:
    return jsnap.Scene.from_dict({**raw, "solver": solver})


def test_the_thinnest_wall_is_the_arm(block_arm):
    """The arm's 6 mm, measured on the arm (the median by area was the base's 20 mm)."""
    surface = trimesh.load(block_arm["part"]["mesh"], force="mesh")
    wall, where = thinnest_wall(surface.vertices, surface.faces)
    assert wall == pytest.approx(ARM[0], rel=1e-9)
    assert where[2] > BASE[2]  # on the arm, above the base
    assert part_thinnest_wall(block_arm["part"]["mesh"])[0] == pytest.approx(ARM[0], rel=1e-9)


def test_the_default_element_size_resolves_the_arm(block_arm):
    """The default element is two thirds of the arm's 6 mm, 4 mm (as 0.8 mm is of the shipped
    hook's 1.2 mm arm, where the median made 13.3 mm): 2 elements across the arm, no warning."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene = _scene(block_arm)
    h = scene.get("solver.mesh_size")
    assert h == pytest.approx(0.8 * ARM[0] / REFERENCE_WALL, rel=1e-9)
    assert elements_across(ARM[0], h) >= 2 and ARM[0] / h >= 1.5


def test_a_coarse_element_size_warns_naming_the_key(block_arm):
    """7 mm elements put one across the 6 mm arm; P1 at the default puts two, not three."""
    with pytest.warns(
        jsnap.SceneWarning,
        match=r"solver\.mesh_size = 7 spans the thinnest wall of part\.mesh \(6 mm, measured from "
        r"\(-?3, .*\) mm\) with 1 element\(s\), fewer than 2 for P2 elements.*use solver\.mesh_size <= 4$",
    ):
        _scene(block_arm, mesh_size=7.0)
    with pytest.warns(
        jsnap.SceneWarning,
        match=r"solver\.mesh_size = 4 \(its default\) spans .* with 2 element\(s\), fewer than 3 for P1 "
        r"elements.*use solver\.mesh_size <= 2\.4$",
    ):
        _scene(block_arm, element="P1")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _scene(block_arm, mesh_size=5.9)  # two across the arm
        _scene(block_arm, element="P1", mesh_size=2.9)  # three


def test_elements_across_is_how_gmsh_divides_an_edge():
    """elements_across(t, h) is the number of segments gmsh puts on an edge t long at size h."""
    initialised = gmsh.isInitialized()
    if not initialised:
        gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        for ratio in (0.5, 0.99, 1.0, 1.005, 1.02, 1.2, 1.5, 1.98, 2.0, 2.5, 2.9, 3.2):
            gmsh.model.add("edge")
            a, b = gmsh.model.geo.addPoint(0, 0, 0), gmsh.model.geo.addPoint(ratio * 0.8, 0, 0)
            gmsh.model.geo.addLine(a, b)
            gmsh.model.geo.synchronize()
            gmsh.option.setNumber("Mesh.MeshSizeMax", 0.8)
            gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
            gmsh.model.mesh.generate(1)
            segments = len(gmsh.model.mesh.getElements(1)[1][0])
            gmsh.model.remove()
            assert elements_across(ratio * 0.8, 0.8) == segments, ratio
    finally:
        if not initialised:
            gmsh.finalize()


def test_the_shipped_hook_keeps_its_default():
    """The example's hook.stl measures its arm, 1.2 mm, as before: without solver.mesh_size its
    default element is 0.8 mm and its size 1, and no scene shipped warns."""
    assert part_thinnest_wall(EXAMPLE / "hook.stl")[0] == pytest.approx(1.2, rel=1e-6)
    raw = tomllib.loads((EXAMPLE / "scene.toml").read_text())
    del raw["solver"]["mesh_size"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene = jsnap.Scene.from_dict(raw, source=str(EXAMPLE / "scene.toml"))
    assert scene.get("solver.mesh_size") == pytest.approx(0.8, rel=1e-6)
    assert scene.size == 1.0


@pytest.mark.parametrize(
    "path",
    [
        *sorted(glob.glob(str(ROOT / "jsnap" / "scenes" / "*.toml"))),
        str(EXAMPLE / "scene.toml"),
        str(ROOT / "tests" / "data" / "pipe_clip" / "scene.toml"),
    ],
    ids=lambda p: str(Path(p).relative_to(ROOT)),
)
def test_the_shipped_scenes_do_not_warn(path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        jsnap.load_scene(path)
