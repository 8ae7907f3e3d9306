"""Bad inputs users reported, each answered in seconds by an error (or, where the input is legal
but risky, a warning) that names the scene key, option or file and says what to do; and the
shipped scenes, which must load without any of them."""

import glob
import warnings
from pathlib import Path

import numpy as np
import pytest

import jsnap
from jsnap import BuildError, SceneError, SceneWarning
from jsnap._apps.identify import Measurement, MeasurementError, _check_force_sign
from jsnap._build import model as build_model
from jsnap._build.model import _estimate_dof, check_part_size, estimate_part
from jsnap._geometry.presets import generate
from jsnap._geometry.scene import default_scene_path

ROOT = Path(__file__).resolve().parents[1]
SCENES = sorted(glob.glob(str(default_scene_path().parent / "*.toml")))
OWN = ROOT / "examples" / "own_connector" / "scene.toml"
CLIP = default_scene_path().parent / "two_hook_clip.toml"
GiB = 2**30


@pytest.fixture
def machine(monkeypatch):
    """The memory the build may use set to ``gib`` GiB, so that the refusals do not depend on
    the machine the tests run on."""

    def set_memory(gib):
        monkeypatch.setattr(build_model, "available_memory", lambda: int(gib * GiB))

    return set_memory


@pytest.mark.parametrize("path", [*SCENES, str(OWN)], ids=lambda p: Path(p).parent.name + "/" + Path(p).name)
def test_shipped_scenes_load_without_errors_or_warnings(path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene = jsnap.load_scene(path)
        check_part_size(scene, available=64 * GiB)  # the build's check before meshing


def test_friction_of_5_is_an_error_naming_the_key():
    with pytest.raises(
        SceneError, match=r"contact\.friction = 5\.0: must be in \[0, 2\]: .*give the coefficient"
    ):
        jsnap.load_scene().replace({"contact.friction": 5})
    with pytest.warns(SceneWarning, match=r"contact\.friction = 1\.8 is above 1\.5"):
        jsnap.load_scene().replace({"contact.friction": 1.8})


def test_waypoints_100_mm_apart_within_a_step_are_an_error():
    jump = [
        {"t": 0.0, "position": [0.0, 0.0, 0.0]},
        {"t": 0.1, "position": [0.0, 0.0, -1.0]},
        {"t": 0.1005, "position": [0.0, 0.0, -101.0]},
        {"t": 0.2, "position": [0.0, 0.0, -101.0]},
    ]
    with pytest.raises(
        SceneError,
        match=r"motion\.waypoints: the rigid part moves 100 mm in one step of solver\.dt = 0\.001 s "
        r"between t = 0\.1 and 0\.101 s, more than the part's wall \(connector\.thickness = 1\.2 mm\): "
        r".*give that move at least 5000 steps",
    ):
        jsnap.load_scene().replace({"motion.waypoints": jump})


def test_trajectory_csv_with_a_100_mm_jump_is_an_error(tmp_path):
    path = tmp_path / "jump.csv"
    rows = ["t,x,y,z,qw,qx,qy,qz", "0,0,0,0,1,0,0,0", "0.05,0,0,-0.5,1,0,0,0", "0.0505,0,0,-100.5,1,0,0,0"]
    rows.append("0.24,0,0,-100.5,1,0,0,0")
    path.write_text("\n".join(rows) + "\n")
    with pytest.raises(
        SceneError, match=r"motion\.trajectory = '.*jump\.csv': the rigid part moves 100 mm in one step"
    ):
        jsnap.load_scene(OWN).replace({"motion.waypoints": None, "motion.trajectory": str(path)})


def test_rollout_controls_that_jump_100_mm_are_an_error():
    """Checked on the host before anything is prepared or compiled (a rollout batch too)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SceneWarning)  # 1.6 mm elements: a coarse model
        scene = jsnap.load_scene().replace(
            {"solver.method": "full", "solver.element": "P1", "solver.mesh_size": 1.6}
        )
    model = jsnap.build(scene)
    path = model.trajectory()[1:20]
    jump = path.copy()
    jump[10:, 2] -= 100.0
    with pytest.raises(
        ValueError,
        match=r"controls: the rigid part jumps 100 mm in one step \(from row 9 to row 10\), more than the "
        r"deformable part's smallest extent \(2 mm\): .*give one row per time step",
    ):
        jsnap.rollout(model, controls=jump)
    with pytest.raises(ValueError, match=r"\(rollout 1, from row 9 to row 10\)"):
        jsnap.rollout_batch(model, controls=np.stack([path, jump]))
    far = path + np.array([0.0, 0.0, 100.0])  # the first row 100 mm from the start
    with pytest.raises(ValueError, match=r"from its start \(plug_start\) to row 0"):
        jsnap.rollout(model, controls=far)


def test_measured_force_of_the_wrong_sign_is_an_error():
    """`jsnap fit` (jsnap.identify) compares the measured force with the model's at the
    starting parameters: mostly negative where the model's is positive is the other sign."""
    t = np.arange(1, 101) * 1e-3
    model = np.where(t < 0.08, 60.0 * t, -1.0)  # the ramp, then the snap
    meas = Measurement(t, -model, columns=("t_s", "Fz_N"))
    with pytest.raises(
        MeasurementError, match=r"force column 'Fz_N' is negative at 100 % of the times .*negate"
    ):
        _check_force_sign(meas, t, model, -model)
    noisy = model + np.random.default_rng(0).normal(0.0, 0.3, t.size)
    _check_force_sign(Measurement(t, noisy), t, model, noisy)  # the right sign, noisy: accepted


def test_coarse_time_step_warns_naming_solver_dt():
    with pytest.warns(
        SceneWarning,
        match=r"solver\.dt = 0\.01: the rigid part moves 0\.1 mm per step \(motion\.speed = 10 mm/s\), 5 times "
        r"the contact's resolution .*use solver\.dt <= 0\.002 s",
    ):
        jsnap.load_scene().replace({"solver.dt": 0.01})
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the default scene's 1 ms and the suggested 2 ms are fine
        jsnap.load_scene().replace({"solver.dt": 1e-3})
        jsnap.load_scene().replace({"solver.dt": 2e-3})


def test_clip_with_a_500_mm_gap_is_refused_before_meshing(machine):
    """The part's size comes from connector.gap: the error names it beside solver.mesh_size."""
    scene = jsnap.load_scene(CLIP).replace({"connector.gap": 500.0})
    machine(4)
    with pytest.raises(
        BuildError,
        match=r"solver\.mesh_size = 0\.8 mm: the part \(4151 mm\^3 from connector\.gap = 500 mm.*estimated "
        r"before meshing\); .*needs about .* GiB, more than the 3\.2 GiB .*solver\.mesh_size >= 1 mm",
    ):
        jsnap.build(scene)
    machine(64)  # where it fits, a build longer than any measured warns
    with pytest.warns(SceneWarning, match=r"connector\.gap = 500 mm.*expect a build of many minutes"):
        check_part_size(scene)


def test_stl_part_at_0_05_mm_is_refused_before_meshing(machine):
    machine(16)
    scene = jsnap.load_scene(OWN).replace({"solver.mesh_size": 0.05})
    with pytest.raises(
        BuildError,
        match=r"solver\.mesh_size = 0\.05 mm: the part \(57\.78 mm\^3 enclosed by part\.mesh = 'hook\.stl'\) "
        r"would be meshed into about 2\.31 million tetrahedra",
    ):
        jsnap.build(scene)


def test_preset_at_0_02_mm_is_refused_before_meshing(machine):
    machine(16)
    scene = jsnap.load_scene().replace({"solver.mesh_size": 0.02})
    with pytest.raises(
        BuildError, match=r"solver\.mesh_size = 0\.02 mm: .*million tetrahedra.*solver\.mesh_size >="
    ):
        jsnap.build(scene)


@pytest.mark.parametrize("path", SCENES, ids=lambda p: Path(p).stem)
def test_the_estimate_never_counts_too_many(path):
    """A refusal never hits a part that fits: the shipped presets' meshes have more dofs than
    estimated before meshing, and within 4 times."""
    scene = jsnap.load_scene(path)
    c = scene["connector"]
    mesh = generate(c["type"], c, scene["plug"], scene["solver"]["mesh_size"]).mesh
    assert 1.0 <= _estimate_dof(mesh, "P2") / estimate_part(scene).dof <= 4.0
