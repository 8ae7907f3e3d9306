"""Parts of other sizes: the defaults that are lengths follow the part (jsnap._geometry.size).

The check is dimensional analysis. Scale every length of a scene by ``k`` and every time by
``k`` (the time step; the speed is unchanged): masses go as ``k^3``, accelerations as ``1/k``,
stiffnesses as ``k``, so every force goes as ``k^2`` and the whole history is the same, step by
step. A simulator with a hidden length (a candidate spacing, a stencil, a tolerance in mm) breaks
that: a 1 mm line spacing and a 0.25 mm stencil on a hook ten times smaller than the shipped one
put a frictionless peak 2.6 times too high, and a 1e-7 mm planarity tolerance, below the float32
rounding of a large STL part's vertices, splits its flat faces into single triangles.

Parts beyond a factor 2 of the shipped walls are sampled alike (the size is proportional to the
wall there): their histories agree to round-off. Across the band the contact is sampled at
another density per wall, so the forces agree to the discretisation's error only.
"""

from __future__ import annotations

import functools
import math
import tomllib

import numpy as np
import pytest
import trimesh

import jsnap
from jsnap._geometry.cantilever import mesh_cantilever
from jsnap._geometry.presets import default_rigid
from jsnap._geometry.scene import connector_geometry, default_scene_path, similar_scene
from jsnap._geometry.size import GEOMETRIC, SIZED, size_of, wall_thickness

# Coarse meshes keep the builds quick; the similarity does not depend on the resolution.
COARSE = {"solver.mesh_size": 1.6, "solver.dtype": "float64"}


def _forces(scene, frictions=(0.0, 0.3)) -> dict:
    """Insertion force per step of one build of ``scene`` rolled out at each friction."""
    model = jsnap.build(scene)
    return {
        mu: np.asarray(jsnap.rollout(model, model.params.replace(friction=mu)).insertion_force)
        for mu in frictions
    }


def test_wall_thickness_of_a_plate_and_a_tube():
    """A 1 x 4 x 10 mm plate measures 1 mm (its large faces see across the plate; the narrow
    ones, along it, are outweighed); a tube of 1 mm wall measures its wall, to its facets'
    sagitta; a surface scaled by k measures k times as much."""
    plate = trimesh.creation.box([1.0, 4.0, 10.0])
    assert wall_thickness(plate.vertices, plate.faces) == pytest.approx(1.0, rel=1e-12)
    tube = trimesh.creation.annulus(r_min=4.0, r_max=5.0, height=20.0, sections=64)
    sagitta = 5.0 * (1 - math.cos(math.pi / 64))
    assert abs(wall_thickness(tube.vertices, tube.faces) - 1.0) <= 2 * sagitta
    for k in (1e-2, 37.0):
        assert wall_thickness(plate.vertices * k, plate.faces) == pytest.approx(k, rel=1e-12)


def test_the_shipped_hook_measures_its_arm():
    """The file reference: the shipped hook's surface (its arm 1.2 mm thick) measures 1.2 mm,
    so the hook written to a file has the preset's size."""
    mesh = mesh_cantilever(connector_geometry(jsnap.load_scene()), 0.8)
    assert wall_thickness(mesh.points, mesh.boundary_faces()) == pytest.approx(1.2, rel=1e-9)


@pytest.mark.parametrize("k", [1 / 16, 1 / 3, 1.0, 1.7, 2.5, 40.0])
def test_unset_length_defaults_follow_the_part_and_given_ones_stay(k):
    """The shipped hook's scene file without its element size and plug fillet, its arm k times
    as thick (and as long, so that the hook stays a hook): the unset geometric defaults follow
    the wall ratio, the resolution defaults the size; a given key keeps its value, and a change
    of the thickness re-derives the rest."""
    raw = tomllib.loads(default_scene_path().read_text())
    del raw["solver"]["mesh_size"], raw["plug"]["fillet"]
    lengths = ("length", "thickness", "tip_thickness", "width", "undercut", "flat")
    for key in lengths:
        raw["connector"][key] *= k
    raw["motion"]["speed"] *= k  # as many steps of 1 ms
    scene = jsnap.Scene.from_dict(raw)
    size = size_of(k)
    assert scene.size == pytest.approx(size)
    assert size == 1.0 if 0.5 <= k <= 2 else size == pytest.approx(k / 2 if k > 2 else 2 * k)
    for dotted, value in SIZED.items():
        assert scene.get(dotted) == pytest.approx(value * size)
    for dotted, value in GEOMETRIC.items():
        assert scene.get(dotted) == pytest.approx(value * k)
    assert scene.get("connector.width") == pytest.approx(4.0 * k)  # given: kept
    kept = scene.replace({"contact.width_spacing": 0.7, "solver.mesh_size": 0.3 * k})
    assert (kept.get("contact.width_spacing"), kept.get("solver.mesh_size")) == (0.7, 0.3 * k)
    back = scene.replace(
        {**{f"connector.{key}": raw["connector"][key] / k for key in lengths}, "motion.speed": 10.0}
    )
    assert back.size == 1.0
    assert back.get("contact.spacing") == SIZED["contact.spacing"]
    assert back.get("solver.mesh_size") == pytest.approx(GEOMETRIC["solver.mesh_size"])


def test_size_is_continuous_and_proportional_outside_the_band():
    r = np.geomspace(1e-2, 1e2, 2001)
    s = np.array([size_of(x) for x in r])
    assert np.all(np.diff(s) >= 0) and np.max(np.abs(np.diff(np.log(s)))) <= np.diff(np.log(r))[0] + 1e-12
    far = (r > 2) | (r < 0.5)
    assert np.allclose(s[far] / r[far], np.where(r[far] > 2, 0.5, 2.0))


@pytest.fixture(scope="module")
def hooks():
    """The default hook (reduced, float64, coarse mesh) scaled by 1/16, 1/8, 1, 8 and 16,
    frictionless and at friction 0.3: insertion force over k^2 per step."""
    base = jsnap.load_scene().replace(COARSE)
    out = {}
    for k in (1 / 16, 1 / 8, 1.0, 8.0, 16.0):
        out.update({(k, mu): f / k**2 for mu, f in _forces(similar_scene(base, k)).items()})
    return out


@pytest.mark.parametrize("mu", [0.0, 0.3])
@pytest.mark.parametrize("pair", [(8.0, 16.0), (1 / 16, 1 / 8)])
def test_similar_parts_beyond_the_band_have_the_same_history(hooks, pair, mu):
    """Outside the band the size is proportional to the part: the hooks 8 and 16 times the
    shipped one (or 1/8 and 1/16) are the same discrete problem, and their insertion forces
    over k^2 agree step for step to round-off, through the snap and the latch."""
    a, b = hooks[pair[0], mu], hooks[pair[1], mu]
    assert a.shape == b.shape
    assert np.max(np.abs(a - b)) <= 1e-6 * np.max(a)


@pytest.mark.parametrize("mu", [0.0, 0.3])
def test_peak_holds_across_sizes(hooks, mu):
    """Across the band the contact is sampled at a density per wall within a factor 2 of the
    shipped one: the peak over k^2 of hooks from 1/16 to 16 times the shipped one stays within
    2 % of the shipped hook's."""
    ref = hooks[1.0, mu].max()
    for (k, m), force in hooks.items():
        if m == mu:
            assert force.max() == pytest.approx(ref, rel=0.02), k


@pytest.fixture(scope="module")
def hook_files(tmp_path_factory):
    """The default hook and its plug as STL files (float32 vertices), scaled by 0.1, 1 and 10."""
    d = tmp_path_factory.mktemp("sizes")
    scene = jsnap.load_scene()
    mesh = mesh_cantilever(connector_geometry(scene), 0.8)
    plug = default_rigid("cantilever", scene["connector"], scene["plug"])
    plug_mesh = plug.mesh()
    plug_mesh.apply_translation(plug.start)
    for k in (0.1, 1.0, 10.0):
        trimesh.Trimesh(mesh.points * k, mesh.boundary_faces()).export(d / f"hook{k}.stl")
        p = plug_mesh.copy()
        p.apply_scale(k)
        p.export(d / f"plug{k}.stl")
    return d


def _file_scene(d, k, mu=0.3, mesh_size=None):
    raw = {
        "part": {
            "mesh": str(d / f"hook{k}.stl"),
            "fixed_box": [[-k, -3 * k, -0.01 * k], [2.5 * k, 3 * k, 0.01 * k]],
        },
        "rigid": {"mesh": str(d / f"plug{k}.stl")},
        "material": {"youngs_modulus": 2200.0, "poissons_ratio": 0.35, "density": 1.05e-9},
        "contact": {"friction": mu},
        "motion": {"stroke": 1.6 * k, "speed": 10.0 * k},  # past the peak (1.3 mm)
        "solver": {"method": "full", **({"mesh_size": mesh_size} if mesh_size else {})},
    }
    return jsnap.Scene.from_dict(raw)


def test_a_file_part_is_sized_by_its_wall(hook_files):
    """The hook's STL (float32 vertices) has the preset's size; ten times smaller, the size
    and the default element follow the measured wall."""
    one, tenth = _file_scene(hook_files, 1.0, 0.3), _file_scene(hook_files, 0.1, 0.3)
    assert one.size == pytest.approx(1.0, rel=1e-6)
    assert tenth.size == pytest.approx(size_of(0.1), rel=1e-6)
    assert tenth.get("solver.mesh_size") == pytest.approx(0.08, rel=1e-6)
    assert tenth.get("contact.width_spacing") == pytest.approx(0.2, rel=1e-6)


@pytest.mark.parametrize("mu", [0.0, 0.3])
def test_hook_files_ten_times_smaller_and_larger_give_the_same_peak(hook_files, mu):
    """The user's part at another size, with the defaults (the product's steps of 1 ms, the
    speed scaled with the part; quasi-static up to the peak): the 1.15 mm and the 115 mm hook's
    peak over k^2 within 3 % of the shipped size's, on the same coarse mesh per wall."""
    peaks = {k: f[mu].max() / k**2 for k, f in _file_forces(hook_files).items()}
    for k in (0.1, 10.0):
        assert peaks[k] == pytest.approx(peaks[1.0], rel=0.03), (k, peaks)


@functools.cache
def _file_forces(d):
    return {k: _forces(_file_scene(d, k, mesh_size=1.6 * k)) for k in (0.1, 1.0, 10.0)}
