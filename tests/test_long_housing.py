"""A part in a long housing: a three-prong hook whose two barbed prongs slide along the walls of
a housing's through-hole before they snap out over its upper face (the shipped
``examples/printed_hook``, drawn smaller and meshed coarser here). The housing's box encloses
every prong, so the candidates must follow the faces its surface passes near
(:func:`jsnap._build.samples.near_path`), not its box; the build's memory is estimated from the
segmentation before the expensive steps and refused naming the setting."""

import math
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh

import jsnap
from jsnap._build import memory, reduce
from jsnap._build.samples import near_path

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "printed_hook"
sys.path.insert(0, str(EXAMPLE))
import make_files  # noqa: E402  (the example's own drawing: one definition for both)

HOOK = dict(
    length=16.0, thickness=3.0, width=4.0, gap=2.0, undercut=0.8, land=0.5, base_thickness=3.0, base_margin=2.0
)
HOUSING = dict(thickness=10.0, clearance=0.3, side_clearance=2.0, wall=3.0, start_gap=0.5)
E, MU = 2200.0, 0.3


def _scene_text(stroke: float, mesh_size: float = 1.5) -> str:
    return (
        f'[part]\nmesh = "hook.stl"\nfixed_box = [[-12.0, -6.0, -3.01], [12.0, 6.0, -2.99]]\n'
        f'[rigid]\nmesh = "housing.stl"\n'
        f"[material]\nyoungs_modulus = {E}\npoissons_ratio = 0.35\ndensity = 1.05e-9\n"
        f"[contact]\nfriction = {MU}\nspacing = 0.1\nwidth_spacing = 2.0\ncapacity = 128\n"
        f"[motion]\ndirection = [0.0, 0.0, -1.0]\nstroke = {stroke}\nspeed = 20.0\n"
        f"[solver]\nmesh_size = {mesh_size}\n"
    )


def _stroke() -> float:
    """Travel until the housing's upper face is 1.5 mm below the barbs' retention faces."""
    top = HOOK["length"] + HOUSING["start_gap"] + HOUSING["thickness"]
    return top - make_files.retention_z({**make_files.HOOK, **HOOK}) + 1.5


@pytest.fixture(scope="module")
def sleeve(tmp_path_factory):
    folder = tmp_path_factory.mktemp("long_housing")
    make_files.write(folder, HOOK, HOUSING)
    (folder / "scene.toml").write_text(_scene_text(_stroke()))
    model = jsnap.build(jsnap.load_scene(folder / "scene.toml"))
    res = jsnap.rollout(model)
    res2 = jsnap.rollout(model, model.params.replace(E=2 * E))
    return folder, model, res, res2


def test_candidates_follow_the_surface_not_the_box():
    """A box sliding past points at known distances: kept within the reach, dropped beyond
    1.25 reach (the test's allowance), whatever the swept box holds."""
    box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))  # its own frame: [-1, 1]^3
    poses = np.stack([np.zeros(101), np.zeros(101), np.linspace(10.0, -10.0, 101)], axis=1)
    gap = np.array([0.1, 0.5, 0.95, 1.3, 2.0, 4.0])
    X = np.stack([1.0 + gap, np.zeros_like(gap), np.zeros_like(gap)], axis=1)  # beside its +x face
    near = near_path(X, box.vertices, box.faces, poses, reach=1.0)
    np.testing.assert_array_equal(near, gap <= 1.0)
    # A point the box passes straight through is near its surface on the way in.
    assert near_path(np.zeros((1, 3)), box.vertices, box.faces, poses, reach=0.05).all()
    # Turned a quarter about z, the box's +x face lies on +y: the points beside +x stay beside it.
    q = np.array([math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)])
    turned = np.concatenate([poses, np.tile(q, (len(poses), 1))], axis=1)
    np.testing.assert_array_equal(near_path(X, box.vertices, box.faces, turned, reach=1.0), gap <= 1.0)


def test_only_the_barbed_faces_are_candidates(sleeve):
    """The middle prong and the outer prongs' inner faces lie farther from the housing than the
    reach at every pose: no candidate there, though the housing's box encloses them."""
    _, model, _, _ = sleeve
    X = np.asarray(model.samples.rest)
    inner = make_files.outer_face({**make_files.HOOK, **HOOK}) - HOOK["thickness"]
    assert X.shape[0] > 0
    assert np.all(np.abs(X[:, 0]) > inner + 0.5)


def _plateau(res) -> np.ndarray:
    """Steps where the hole's wall presses the barbs' lands: from 2 mm past the lands' lower
    edge (the ringing after the hole's sharp edge comes off the barbs' sharp edges has died
    down) to half a millimetre before the upper face's pass."""
    h = {**make_files.HOOK, **HOOK}
    ramp = h["undercut"] / math.tan(math.radians(h["lead_angle"]))
    travel = np.asarray(res.travel)
    start = HOUSING["start_gap"] + ramp + h["land"] + 2.0
    end = HOUSING["start_gap"] + HOUSING["thickness"] - 0.5
    return (travel > start) & (travel < end)


def test_it_latches_and_the_force_is_friction_on_the_deflection(sleeve):
    """Status ok; the barbs pressed in slide along the walls with a plateau of insertion force
    mu times the normal force that holds them in, and snap out past the upper face (the force
    falls to nothing). The normal force is that of the prongs' deflection: a Timoshenko
    cantilever pushed in by the interference at the land, clamped at the base's top face."""
    _, _, res, _ = sleeve
    assert res.ok, res.status()
    F = np.asarray(res.insertion_force)
    normal = np.sum(np.abs(np.asarray(res.contact_force)[..., 0]), axis=1)  # both barbs', N
    plateau = _plateau(res)
    assert plateau.sum() > 50
    np.testing.assert_allclose(np.median(F[plateau]), MU * np.median(normal[plateau]), rtol=0.05)
    # The deflection force of each prong: bending and shear of the prong (the base is stiffer).
    h = {**make_files.HOOK, **HOOK}
    t, b = h["thickness"], h["width"]
    delta = h["undercut"] - HOUSING["clearance"]
    L = make_files.retention_z(h) + 0.5 * h["land"]
    G = E / (2 * 1.35)
    beam = delta / (L**3 / (3 * E * b * t**3 / 12) + L / (5 / 6 * G * b * t))
    per_prong = 0.5 * np.median(normal[plateau])
    # The base and the prong's root are not rigid: the FE prong is softer than the beam.
    assert 0.7 * beam < per_prong < 1.05 * beam, (per_prong, beam)
    # Latched: past the upper face the barbs are out and the force is gone.
    assert abs(F[-1]) < 0.02 * np.median(F[plateau])
    assert np.max(np.abs(np.asarray(res.contact_force)[-1])) < 1e-6


@pytest.mark.xfail(
    strict=True,
    reason="the housing's sharp hole edges, not rounded, pass the barbs' sharp edges: at 2E a transient of "
    "-24 N opens the plateau and its median is 1.90 times E's, not 2 (docs/reduction.md, long contact regions)",
)
def test_forces_scale_with_youngs_modulus(sleeve):
    """Quasi-static and linear elastic with Coulomb friction: twice E, twice every force (to the
    inertia the insertion leaves)."""
    _, _, res, res2 = sleeve
    assert res2.ok, res2.status()
    F, F2 = np.asarray(res.insertion_force), np.asarray(res2.insertion_force)
    plateau = _plateau(res)
    assert abs(np.median(F2[plateau]) / np.median(F[plateau]) - 2.0) < 0.02
    normal = [np.sum(np.abs(np.asarray(r.contact_force)[..., 0]), axis=1)[plateau] for r in (res, res2)]
    assert abs(np.median(normal[1]) / np.median(normal[0]) - 2.0) < 0.02


def test_a_build_too_large_is_refused_in_seconds(sleeve, monkeypatch):
    """A reduction that would not fit is refused from the segmentation's estimate, before the
    rigid part's SDF and the factorisations, naming the settings to change."""
    folder, _, _, _ = sleeve
    (folder / "fine.toml").write_text(_scene_text(_stroke(), mesh_size=1.0))
    scene = jsnap.load_scene(folder / "fine.toml")
    # A machine of 64 MiB for the reduction (the part itself passes its own checks).
    small = lambda need, what, hint: memory.require(need, what, hint, available=64 * 2**20)  # noqa: E731
    monkeypatch.setattr(reduce, "require", small)
    t0 = time.perf_counter()
    with pytest.raises(jsnap.BuildError, match=r"load cases") as err:
        jsnap.build(scene)
    assert "solver.mesh_size" in str(err.value) and "contact.spacing" in str(err.value)
    assert time.perf_counter() - t0 < 30
