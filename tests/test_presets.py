"""Connector presets: each generates a deformable part, its fixed region, a rigid part and a
stroke from named dimensions (the same things a user gives in files); impossible dimensions are
errors naming the key."""

import numpy as np
import pytest

import jsnap
from jsnap._geometry.presets import clip_section, default_rigid, generate, latch_section, latch_tip_deflection
from jsnap._geometry.scene import SceneError, default_scene_path

CLIP = default_scene_path().parent / "two_hook_clip.toml"
LATCH = default_scene_path().parent / "cable_latch.toml"


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


def _reduced_and_full_peaks(scene):
    """``(F, F0, spread)``: the insertion force of ``scene``'s own (reduced, float32) model,
    checked finite and unflagged; the full model's float64 peak; and the full model's own
    float32-to-float64 spread of the peak."""
    full = jsnap.build(scene.replace({"solver.method": "full", "solver.dtype": "float64"}))
    prepared = jsnap.prepare(full)
    ref = jsnap.rollout(full, dtype="float64", prepared=prepared).check()
    F0 = float(np.asarray(ref.insertion_force).max())
    F32 = float(np.asarray(jsnap.rollout(full, dtype="float32", prepared=prepared).insertion_force).max())
    reduced = jsnap.build(scene)
    assert reduced.n_dof < full.n_dof / 10
    res = jsnap.rollout(reduced).check()  # float32, the scene's; raises on a flagged step
    F = np.asarray(res.insertion_force)
    assert np.all(np.isfinite(F))
    return F, F0, abs(F32 / F0 - 1)


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
    F, F0, spread = _reduced_and_full_peaks(scene)
    assert F0 > 1.0
    assert abs(F.max() / F0 - 1) <= 0.03 + spread, (F.max(), F0, spread)


# --------------------------------------------------------------------------------------------
# The cable latch
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def latch():
    scene = jsnap.load_scene(LATCH)
    c = scene["connector"]
    return scene, generate(c["type"], c, scene["plug"], scene["solver"]["mesh_size"])


def test_latch_mesh_fills_its_section_exactly(latch):
    """The tetrahedra's volume is the section's area times the width; the fixed nodes are
    exactly the plug body's back face; the lip starts above the catch with its inner face in
    the arm's outer face and ends 0.3 mm below the retention face."""
    scene, preset = latch
    c = scene["connector"]
    mesh = preset.mesh
    poly = latch_section(c)
    assert _area(poly) > 0
    np.testing.assert_allclose(mesh.volumes().sum(), _area(poly) * c["width"], rtol=1e-10)
    back = -c["gap"] - c["body_thickness"]
    np.testing.assert_allclose(mesh.points[mesh.base_nodes, 0], back, atol=1e-12)
    assert np.isclose(mesh.points[:, 0], back, atol=1e-9).sum() == mesh.base_nodes.size
    lip = preset.plug
    assert lip.start[0] - lip.half[0] == pytest.approx(c["thickness"])
    retention = c["length"] - c["catch_position"]
    assert lip.start[2] + lip.half[2] - preset.stroke == pytest.approx(retention - 0.3)
    # The catch's top is below the root: the lip reaches the catch before anything else.
    assert lip.start[2] - lip.half[2] < c["length"]


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"connector.catch_position": 1.2}, r"connector\.catch_position = 1\.2: the catch is 1\.3\d* mm tall"),
        ({"connector.catch_position": 10.0}, r"connector\.catch_position = 10\.0: .* in \(0, length\)"),
        ({"connector.gap": 0.8}, r"connector\.gap = 0\.8: .*free end moves ~1\.2\d* mm"),
        ({"connector.body_thickness": 0.0}, r"connector\.body_thickness = 0\.0: must be > 0"),
        ({"connector.return_angle": 0.0}, r"connector\.return_angle = 0\.0"),
        ({"connector.base_margin": 1.0}, r"unknown key connector\.base_margin"),
    ],
)
def test_latch_keys_are_checked_on_load(changes, message):
    with pytest.raises(SceneError, match=message):
        jsnap.load_scene(LATCH).replace(changes)


def test_latch_gap_check_is_beam_theory():
    """The free end's swing that the gap must clear: a cantilever of length L deflected by y at
    distance l from its root swings its end by y (3 L - l) / (2 l) (Roark, case 3a)."""
    c = jsnap.load_scene(LATCH)["connector"]
    L, y = c["length"], c["undercut"]
    lever = c["catch_position"] - c["flat"]  # square retention face: the flat's top
    assert latch_tip_deflection(c) == pytest.approx(y * (3 * L - lever) / (2 * lever))


@pytest.fixture(scope="module")
def latch_runs():
    """The shipped latch (reduced, float32), frictionless and at friction 0.3."""
    scene = jsnap.load_scene(LATCH)
    model = jsnap.build(scene)
    return scene, {mu: jsnap.rollout(model, model.params.replace(friction=mu)).check() for mu in (0.0, 0.3)}


@pytest.mark.parametrize("mu", [0.0, 0.3])
def test_latch_lip_face_pushes_along_its_normal_or_on_the_coulomb_cone(latch_runs, mu):
    """While every contact lies on the lip's flat inner face (the catch's ramp-to-land edge under
    it, away from its rounded edges), the force on the lip is along that face's normal x
    (frictionless) or on the Coulomb cone, |F_z| = mu |F_x| (sliding): whatever the catch's own
    faces' tilt under the deflected arm."""
    scene, runs = latch_runs
    res = runs[mu]
    p = scene["plug"]
    half_h = 0.5 * p["height"]
    face_x = scene["connector"]["thickness"]
    active = np.asarray(res.contact_active)
    points = np.asarray(res.contact_point)
    forces = np.asarray(res.contact_force)
    lip_z = np.asarray(res.plug)[:, 2]
    checked = 0
    for k in range(active.shape[0]):
        a = active[k]
        if not a.any():
            continue
        z, x = points[k, a, 2], points[k, a, 0]
        on_face = (np.abs(z - lip_z[k]) < half_h - p["fillet"] - 0.02) & (np.abs(x - face_x) < 0.03)
        if not on_face.all():
            continue
        f = forces[k, a].sum(axis=0)
        if abs(f[0]) < 0.5:
            continue
        checked += 1
        assert abs(f[2]) == pytest.approx(mu * abs(f[0]), abs=0.01 * abs(f[0])), (k, f)
    assert checked >= 5


def test_latch_reduced_model_follows_its_full_model_on_other_dimensions():
    """The shipped default method on a latch nobody tuned it for (shorter, thinner, the catch
    nearer the root, a smaller undercut at 35 degrees, friction 0.5; 1.0 mm mesh): float32 as
    shipped, finite and unflagged, its peak within 3 % of the full float64 model's plus the full
    model's own float32-to-float64 spread (tests/test_hook_family.py explains that allowance)."""
    case = {
        "connector.length": 8.0,
        "connector.thickness": 0.7,
        "connector.catch_position": 4.5,
        "connector.undercut": 0.5,
        "connector.lead_angle": 35.0,
        "connector.gap": 1.5,
        "contact.friction": 0.5,
        "solver.mesh_size": 1.0,
    }
    scene = jsnap.load_scene(LATCH).replace(case)
    F, F0, spread = _reduced_and_full_peaks(scene)
    assert F0 > 0.5
    assert abs(F.max() / F0 - 1) <= 0.03 + spread, (F.max(), F0, spread)
