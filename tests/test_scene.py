"""Scene files: the default loads; bad input raises errors that name the key and value."""

import pytest

import jsnap
from jsnap import SceneError


def test_default_scene_loads_with_design_values():
    s = jsnap.load_scene()
    assert s.get("connector.length") == 10.0
    assert s.get("material.youngs_modulus") == 2200.0
    assert s.get("contact.friction") == 0.3


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
        ({"solver.method": "sparse"}, r"solver\.method = 'sparse': must be one of full, modal, segm"),
        ({"contact.capacity": 2.5}, r"contact\.capacity = 2\.5: must be an integer"),
        (
            {"contact.solver": "spg", "contact.gradient": "unrolled"},
            r"contact\.gradient = 'unrolled' with contact\.solver = 'spg'",
        ),
    ],
)
def test_bad_values_name_the_key(change, match):
    with pytest.raises(SceneError, match=match):
        jsnap.load_scene().replace(change)


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
