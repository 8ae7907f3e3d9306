"""Connector presets: each generates a deformable part, its fixed region, a rigid part and a
stroke from named dimensions (the same things a user gives in files); impossible dimensions are
errors naming the key."""

import numpy as np
import pytest

import jsnap
from jsnap._geometry.presets import clip_section, default_rigid, generate
from jsnap._geometry.scene import SceneError, default_scene_path

CLIP = default_scene_path().parent / "two_hook_clip.toml"


def _area(poly):
    x, z = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.sum(x * np.roll(z, -1) - np.roll(x, -1) * z))


@pytest.fixture(scope="module")
def clip():
    scene = jsnap.load_scene(CLIP)
    c = scene["connector"]
    return scene, generate(c["type"], c, scene["plug"], scene["solver"]["mesh_size"])


def test_clip_mesh_fills_its_section_exactly(clip):
    """gmsh meshes the exact solid: the tetrahedra's volume is the section's area (shoelace,
    independent of the mesh) times the width, and the fixed nodes are exactly the bottom face's."""
    scene, preset = clip
    c = scene["connector"]
    mesh = preset.mesh
    poly = clip_section(c)
    assert _area(poly) > 0  # counter-clockwise
    np.testing.assert_allclose(mesh.volumes().sum(), _area(poly) * c["width"], rtol=1e-10)
    np.testing.assert_allclose(
        mesh.points.min(axis=0), [poly[:, 0].min(), -c["width"] / 2, -c["base_thickness"]]
    )
    base = mesh.points[mesh.base_nodes]
    np.testing.assert_allclose(base[:, 2], -c["base_thickness"], atol=1e-12)
    on_bottom = np.isclose(mesh.points[:, 2], -c["base_thickness"], atol=1e-9)
    assert on_bottom.sum() == mesh.base_nodes.size
    # The two arms mirror each other about x = 0: the section does exactly.
    np.testing.assert_allclose(np.sort(poly[:, 0]), np.sort(-poly[:, 0]), atol=1e-12)


def test_clip_rigid_block_is_the_gap_between_the_hooks(clip):
    scene, preset = clip
    c, p = scene["connector"], scene["plug"]
    block = default_rigid("two_hook_clip", c, p)
    np.testing.assert_allclose(2 * block.half, [c["gap"], c["width"] + 1.0, p["height"]])
    np.testing.assert_allclose(block.start[:2], 0.0)
    # It starts plug.clearance above the hooks' tops and latches 0.3 mm below the retention faces.
    z_top = preset.mesh.points[:, 2].max()
    assert block.start[2] - block.half[2] == pytest.approx(z_top + p["clearance"])
    assert block.start[2] + block.half[2] - preset.stroke == pytest.approx(c["length"] - 0.3)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"connector.gap": 1.6}, r"connector\.gap = 1\.6: the two hooks' lips would touch"),
        ({"connector.base_thickness": 0.0}, r"connector\.base_thickness = 0\.0: must be > 0"),
        ({"connector.base_margin": -1.0}, r"connector\.base_margin = -1\.0: must be >= 0"),
        ({"connector.tip_thickness": 1.0}, r"unknown key connector\.tip_thickness.*takes type, length"),
        ({"connector.length": 2.0}, r"connector\.undercut = 0\.8: the arm must bend its tip 0\.8 mm on a 2 mm"),
        (
            {"connector.type": "annular"},
            r"connector\.type = 'annular': must be one of cantilever, two_hook_clip",
        ),
        ({"plug.fillet": 0.3}, r"plug\.fillet = 0\.3: must be <= half"),
    ],
)
def test_clip_keys_are_checked_on_load(changes, message):
    with pytest.raises(SceneError, match=message):
        jsnap.load_scene(CLIP).replace(changes)


def test_cantilever_keys_are_not_the_clips():
    """Each type takes its own keys: the clip's are unknown to the cantilever."""
    with pytest.raises(SceneError, match=r"unknown key connector\.gap"):
        jsnap.load_scene().replace({"connector.gap": 4.0})
    raw = jsnap.load_scene().to_dict()
    del raw["connector"]["type"]
    with pytest.raises(SceneError, match=r"connector\.type is required but missing"):
        jsnap.Scene.from_dict(raw)


def test_cantilever_preset_generates_todays_part():
    """The cantilever through the preset generator: the structured mesh and the rigid block that
    the scene always had (the block's face in the plane of the arm's outer face at the tip)."""
    from jsnap._geometry.cantilever import mesh_cantilever
    from jsnap._geometry.scene import connector_geometry, motion_stroke

    scene = jsnap.load_scene()
    c = scene["connector"]
    preset = generate("cantilever", c, scene["plug"], scene["solver"]["mesh_size"])
    geom = connector_geometry(scene)
    ref = mesh_cantilever(geom, scene["solver"]["mesh_size"])
    np.testing.assert_array_equal(preset.mesh.points, ref.points)
    np.testing.assert_array_equal(preset.mesh.cells, ref.cells)
    assert preset.stroke == motion_stroke(scene, geom)
    block = preset.plug
    assert block.start[0] - block.half[0] == geom.h_tip


@pytest.fixture(scope="module")
def squeezed():
    """The clip and the single hook of the same arm, frictionless, full model (float64) on a
    coarse 1.2 mm mesh (a SceneWarning: coarser than the undercut), quicker plug."""
    import warnings

    coarse = {
        "solver.method": "full",
        "solver.mesh_size": 1.2,
        "solver.dtype": "float64",
        "motion.speed": 20.0,
        "contact.friction": 0.0,
    }
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", jsnap.SceneWarning)
        for name, scene in (("clip", jsnap.load_scene(CLIP)), ("hook", jsnap.load_scene())):
            model = jsnap.build(scene.replace(coarse))
            out[name] = (model, jsnap.rollout(model).check())
    return out


def test_clip_squeezes_both_hooks_alike(squeezed):
    """Mirror symmetry: at the peak the two hooks carry the same contact force (mirrored in x),
    and the rigid block feels no net sideways force or moment (the gmsh mesh itself is not
    mirror-symmetric: its differences stay within 2 %)."""
    _, res = squeezed["clip"]
    F = np.asarray(res.insertion_force)
    k = int(F.argmax())
    point = np.asarray(res.contact_point)[k]
    force = np.asarray(res.contact_force)[k] * np.asarray(res.contact_active)[k][:, None]
    right, left = force[point[:, 0] > 0].sum(axis=0), force[point[:, 0] < 0].sum(axis=0)
    assert right[0] > 0.2 * F[k]  # each hook is pushed outwards
    np.testing.assert_allclose(left * [-1, 1, 1], right, atol=0.02 * F[k])
    assert abs(float(np.asarray(res.lateral_force)[k])) < 0.02 * F[k]
    # The base holds the block's push: force balance of the whole part, quasi-static.
    np.testing.assert_allclose(np.asarray(res.base_force)[k], -force.sum(axis=0), atol=0.02 * F[k])


def test_clip_force_is_two_hooks_on_a_compliant_base(squeezed):
    """The clip's peak is at most twice the single hook's (same arm, same element size): its
    hooks stand on a base block that gives way, where the single hook's root is clamped; and not
    much less (the base is 2 mm thick under 1.2 mm arms)."""
    clip = float(np.asarray(squeezed["clip"][1].insertion_force).max())
    hook = float(np.asarray(squeezed["hook"][1].insertion_force).max())
    assert 0.75 * 2 * hook < clip < 1.02 * 2 * hook


def test_clip_reduced_model_follows_its_full_model_on_other_dimensions():
    """The shipped default method on a clip nobody tuned it for (narrower gap, thinner arms, a
    smaller undercut, a thinner base, friction 0.5; coarse 1.2 mm mesh): float32 as shipped,
    finite and unflagged, its peak within 3 % of the full model's float64 peak plus the full
    model's own float32-to-float64 spread (tests/test_hook_family.py explains that allowance)."""
    import warnings

    case = {
        "connector.gap": 3.0,
        "connector.thickness": 1.0,
        "connector.undercut": 0.6,
        "connector.base_thickness": 1.5,
        "contact.friction": 0.5,
        "solver.mesh_size": 1.2,
    }
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", jsnap.SceneWarning)
        scene = jsnap.load_scene(CLIP).replace(case)
    full = jsnap.build(scene.replace({"solver.method": "full", "solver.dtype": "float64"}))
    prepared = jsnap.prepare(full)
    ref = jsnap.rollout(full, dtype="float64", prepared=prepared).check()
    F0 = float(np.asarray(ref.insertion_force).max())
    F32 = float(np.asarray(jsnap.rollout(full, dtype="float32", prepared=prepared).insertion_force).max())
    spread = abs(F32 / F0 - 1)
    reduced = jsnap.build(scene)
    assert reduced.n_dof < full.n_dof / 10
    res = jsnap.rollout(reduced).check()  # float32, the scene's; raises on a flagged step
    F = np.asarray(res.insertion_force)
    assert np.all(np.isfinite(F)) and F0 > 1.0
    assert abs(F.max() / F0 - 1) <= 0.03 + spread, (F.max(), F0, spread)
