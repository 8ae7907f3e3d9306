"""Scene files: the default loads; bad input raises errors that name the key and value;
internal keys are set through ``with_internal`` only."""

import json
import re
import tomllib
import warnings

import pytest

import jsnap
from jsnap import SceneError, SceneWarning
from jsnap._geometry.scene import with_internal


def test_default_scene_loads_with_design_values():
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing doubtful in the shipped scene
        s = jsnap.load_scene()
    assert s.get("connector.length") == 10.0
    assert s.get("material.youngs_modulus") == 2200.0
    assert s.get("contact.friction") == 0.3
    assert s.get("solver.method") == "reduced"


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"material.youngs_modulus": -1.0}, r"material\.youngs_modulus = -1\.0: must be > 0"),
        ({"material.poissons_ratio": 0.5}, r"material\.poissons_ratio = 0\.5"),
        ({"solver.dt": 0.0}, r"solver\.dt = 0\.0"),
        ({"material.density": float("nan")}, r"material\.density = nan: must be finite"),
        ({"connector.undercut": -0.2}, r"connector\.undercut"),
        ({"plug.fillet": 5.0}, r"plug\.fillet = 5\.0"),
        ({"solver.element": "P3"}, r"solver\.element = 'P3'"),
        # The internal "modal" is not offered.
        ({"solver.method": "sparse"}, r"solver\.method = 'sparse': must be one of reduced, full, segmented$"),
        ({"contact.capacity": 2.5}, r"contact\.capacity = 2\.5: must be an integer"),
        ({"connector.undercut": 3.0}, r"connector\.undercut = 3\.0: the arm must bend its tip 3 mm"),
        ({"solver.dt": 0.02}, r"solver\.dt = 0\.02: .* would take 11\.6 steps; at least 20 are needed"),
        (
            {"solver.mesh_size": 3.3},
            r"solver\.mesh_size = 3\.3: elements more than 4 times connector\.undercut = 0\.8 mm",
        ),
    ],
)
def test_bad_values_name_the_key(change, match):
    with pytest.raises(SceneError, match=match):
        jsnap.load_scene().replace(change)


def test_bad_internal_combination_names_the_keys():
    with pytest.raises(SceneError, match=r"contact\.gradient = 'unrolled' with contact\.solver = 'spg'"):
        with_internal(jsnap.load_scene(), {"contact.solver": "spg", "contact.gradient": "unrolled"})


def test_coarse_elements_warn():
    """Elements larger than the thinnest feature (the 0.8 mm undercut) warn; up to 4 times it
    is allowed (above, an error: test_bad_values_name_the_key)."""
    with pytest.warns(
        SceneWarning, match=r"solver\.mesh_size = 1\.6 is larger than connector\.undercut = 0\.8 mm"
    ):
        jsnap.load_scene().replace({"solver.mesh_size": 1.6})
    with pytest.warns(SceneWarning):
        jsnap.load_scene().replace({"solver.mesh_size": 3.2})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        jsnap.load_scene().replace({"solver.mesh_size": 0.8})


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (
            {"contact.margin": 0.05},
            r"unknown key contact\.margin = 0\.05; \[contact\] takes friction, capacity",
        ),
        ({"solver.segments": 2}, r"unknown key solver\.segments = 2"),
        ({"plug.clearance": 0.1}, r"unknown key plug\.clearance = 0\.1"),
        ({"contact.solver": "admm"}, r"contact\.solver = 'admm': must be one of apgd, spg$"),
        ({"solver.method": "modal"}, r"solver\.method = 'modal': must be one of reduced, full, segmented$"),
        ({"solver.hook_mesh_size": 0.4}, r"unknown key solver\.hook_mesh_size"),  # removed
    ],
)
def test_internal_keys_and_choices_are_not_scene_keys(change, match, tmp_path):
    """Scene.replace and scene files refuse internal keys and choices; with_internal sets them,
    and a scene holding them can still be changed with replace."""
    with pytest.raises(SceneError, match=match):
        jsnap.load_scene().replace(change)
    ((dotted, value),) = change.items()
    section, key = dotted.split(".")
    p = tmp_path / "s.toml"
    text = re.sub(rf"^{key} = .*\n", "", open(jsnap.load_scene().source).read(), flags=re.M)
    p.write_text(text.replace(f"[{section}]", f"[{section}]\n{key} = {json.dumps(value)}"))
    with pytest.raises(SceneError, match=match.replace("$", "")):
        jsnap.load_scene(p)
    if dotted == "solver.hook_mesh_size":
        return
    s = with_internal(jsnap.load_scene(), change)
    assert s.get(dotted) == value
    s = s.replace({"contact.friction": 0.1})
    assert (s.get(dotted), s.get("contact.friction")) == (value, 0.1)


def test_unknown_and_missing_keys(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text('[connector]\ntype = "cantilever"\nlenght = 10.0\n')
    with pytest.raises(SceneError, match=r"unknown key connector\.lenght"):
        jsnap.load_scene(p)
    p.write_text('[connector]\ntype = "cantilever"\n')
    with pytest.raises(SceneError, match=r"connector\.length is required"):
        jsnap.load_scene(p)
    p.write_text("[materail]\nE = 1\n")
    with pytest.raises(SceneError, match=r"unknown section \[materail\]"):
        jsnap.load_scene(p)


def test_is_set_tells_the_keys_given_from_the_defaults():
    """``Scene.is_set``: the keys of the file, and those of every later ``replace``, are set;
    a default filled in is not, even though the scene holds its value."""
    s = jsnap.load_scene()
    assert s.is_set("connector.length") and s.is_set("contact.friction")
    assert not s.is_set("contact.capacity") and s.get("contact.capacity") == 64
    r = s.replace({"contact.capacity": 64}).replace(solver__dt=5e-4)
    assert r.is_set("contact.capacity") and r.is_set("solver.dt") and r.is_set("connector.length")
    assert not r.is_set("contact.margin")
    raw = tomllib.loads(open(s.source).read())
    raw["contact"] = {"friction": 0.5}
    d = jsnap.Scene.from_dict(raw)
    assert d.is_set("contact.friction") and not d.is_set("contact.tolerance")
    with pytest.raises(SceneError, match=r"'section\.key'"):
        s.is_set("capacity")
