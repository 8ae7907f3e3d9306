"""The rigid part's start pose from the scene (``rigid.position``, ``rigid.rotation``).

A rigid part's file moved by hand into its start pose and the unmoved file placed by the two
keys must give the build the same rigid part: its surface in its own frame, its centroid (the
frame's origin at t = 0), the motion's poses and the box it sweeps. Checked on the geometry the
build starts from (``jsnap._build.model._geometry``), no rollout. The hand-moved file is an
ASCII STL written with 17 digits, so that it holds the float64 coordinates exactly.
"""

from __future__ import annotations

import math
import shutil
import tomllib
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

import jsnap
from jsnap._build.model import _geometry, _swept_box
from jsnap._geometry.motion import UNIT_TOLERANCE, quat_matrix
from jsnap._geometry.part import load_rigid
from jsnap._geometry.scene import SCHEMA

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "own_connector"
# A turn of 7 degrees about an oblique axis and a shift, small enough to keep the example's plug
# above its hook.
AXIS = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
ANGLE = math.radians(7.0)
QUAT = [math.cos(ANGLE / 2), *(float(x) for x in math.sin(ANGLE / 2) * AXIS)]  # w, x, y, z
SHIFT = [0.1, -0.2, 0.3]
TOL = 1e-9  # mm


def _write_ascii_stl(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    lines = ["solid placed"]
    for tri in vertices[faces]:
        lines += ["facet normal 0 0 0", " outer loop"]
        lines += ["  vertex " + " ".join(f"{float(x):.17g}" for x in p) for p in tri]
        lines += [" endloop", "endfacet"]
    lines.append("endsolid placed")
    path.write_text("\n".join(lines) + "\n")


def _scene_text(rigid: str) -> str:
    """The example's scene with its [rigid] table replaced by ``rigid``."""
    text = (EXAMPLE / "scene.toml").read_text()
    head, rest = text.split("[rigid]\n", 1)
    return head + rigid + "\n" + rest[rest.index("\n[") + 1 :]


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """(by hand, by the keys, the hand-moved surface's vertices and faces): the example's
    scene with its plug moved by hand into the start pose, and with the plug's file as it is
    and the pose in rigid.position and rigid.rotation."""
    d = tmp_path_factory.mktemp("placement")
    for name in ("hook.stl", "plug.stl"):
        shutil.copy(EXAMPLE / name, d / name)
    plug = trimesh.load(d / "plug.stl", force="mesh", process=True)
    centroid = np.asarray(plug.center_mass, np.float64)
    turn = Rotation.from_quat([*QUAT[1:], QUAT[0]]).as_matrix()  # scipy: x, y, z, w
    moved = (np.asarray(plug.vertices, np.float64) - centroid) @ turn.T + centroid + SHIFT
    _write_ascii_stl(d / "placed.stl", moved, np.asarray(plug.faces))
    (d / "by_hand.toml").write_text(_scene_text('[rigid]\nmesh = "placed.stl"\n'))
    keys = f'[rigid]\nmesh = "plug.stl"\nposition = {SHIFT!r}\nrotation = {QUAT!r}\n'
    (d / "by_keys.toml").write_text(_scene_text(keys))
    by_hand, by_keys = (jsnap.load_scene(d / f"{n}.toml") for n in ("by_hand", "by_keys"))
    return by_hand, by_keys, moved, centroid


def test_the_rotation_is_the_motions_convention():
    """rigid.rotation turns the part as the waypoints' rotations do (quat_matrix: w, x, y, z),
    which is scipy's rotation of the same quaternion; the doc's tolerance is the waypoints'."""
    turn = Rotation.from_quat([*QUAT[1:], QUAT[0]]).as_matrix()
    np.testing.assert_allclose(quat_matrix(QUAT), turn, rtol=0, atol=1e-15)
    assert UNIT_TOLERANCE == 1e-6
    assert "within 1e-6" in SCHEMA["rigid"]["rotation"].doc


def test_the_keys_are_read_and_default_to_the_files_pose(scenes):
    by_hand, by_keys, _, _ = scenes
    assert by_hand["rigid"]["position"] == [0.0, 0.0, 0.0]
    assert by_hand["rigid"]["rotation"] == [1.0, 0.0, 0.0, 0.0]
    assert by_keys["rigid"]["position"] == SHIFT
    np.testing.assert_allclose(by_keys["rigid"]["rotation"], QUAT, rtol=0, atol=1e-15)
    # A default list is the scene's own, not the schema's.
    other = jsnap.load_scene(EXAMPLE / "scene.toml")
    assert other["rigid"]["position"] is not by_hand["rigid"]["position"]


def test_placed_by_keys_is_the_file_placed_by_hand(scenes):
    """Surface in its own frame, centroid, start pose, poses and swept box agree to 1e-9 mm."""
    by_hand, by_keys, moved, centroid = scenes
    a, b = _geometry(by_hand), _geometry(by_keys)
    # The frame's origin: the file's centroid moved by rigid.position (the rotation is about it).
    np.testing.assert_allclose(b.rigid.start, centroid + SHIFT, rtol=0, atol=TOL)
    np.testing.assert_allclose(a.rigid.start, b.rigid.start, rtol=0, atol=TOL)
    np.testing.assert_allclose(a.poses, b.poses, rtol=0, atol=TOL)
    np.testing.assert_allclose(b.poses[0, :3], centroid + SHIFT, rtol=0, atol=TOL)
    np.testing.assert_allclose(a.axis, b.axis, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.rigid.half, b.rigid.half, rtol=0, atol=TOL)
    # The surfaces, vertex for vertex (the two files' vertices may be numbered apart) and
    # triangle for triangle, winding included.
    va, vb = np.asarray(a.rigid.mesh.vertices), np.asarray(b.rigid.mesh.vertices)
    assert va.shape == vb.shape
    dist, match = cKDTree(va).query(vb)
    assert dist.max() <= TOL and np.unique(match).size == vb.shape[0]
    fa = {tuple(np.roll(f, -int(np.argmin(f)))) for f in np.asarray(a.rigid.mesh.faces)}
    fb = {tuple(np.roll(f, -int(np.argmin(f)))) for f in match[np.asarray(b.rigid.mesh.faces)]}
    assert fa == fb
    # At t = 0 in the base's frame the placed surface is the hand-moved file.
    world = vb + b.poses[0, :3]
    dist, _ = cKDTree(moved).query(world)
    assert dist.max() <= TOL
    assert b.rigid.mesh.volume == pytest.approx(a.rigid.mesh.volume, rel=1e-12)
    for lo_hi_a, lo_hi_b in zip(_swept_box(a.rigid, a.poses), _swept_box(b.rigid, b.poses), strict=True):
        np.testing.assert_allclose(lo_hi_a, lo_hi_b, rtol=0, atol=TOL)
    # The deformable part is not moved.
    np.testing.assert_array_equal(a.mesh.points, b.mesh.points)


def test_load_rigid_defaults_keep_the_files_pose():
    plain = load_rigid(EXAMPLE / "plug.stl")
    same = load_rigid(EXAMPLE / "plug.stl", position=[0, 0, 0], rotation=[1, 0, 0, 0])
    np.testing.assert_array_equal(plain.centroid, same.centroid)
    np.testing.assert_array_equal(plain.mesh.vertices, same.mesh.vertices)
    file = trimesh.load(EXAMPLE / "plug.stl", force="mesh", process=True)
    np.testing.assert_allclose(plain.centroid, file.center_mass, rtol=0, atol=1e-12)


def _example(**rigid) -> dict:
    raw = tomllib.loads((EXAMPLE / "scene.toml").read_text())
    raw["rigid"].update(rigid)
    return raw


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("position", [1.0, 2.0], r"rigid\.position = \[1\.0, 2\.0\]: must be 3 numbers"),
        ("position", [1.0, 2.0, 3.0, 4.0], r"rigid\.position = .*: must be 3 numbers"),
        ("position", [0.0, float("inf"), 0.0], r"rigid\.position = .*: must be finite"),
        ("position", ["a", 0.0, 0.0], r"rigid\.position = .*: must be 3 numbers"),
        ("rotation", [1.0, 0.0, 0.0], r"rigid\.rotation = \[1\.0, 0\.0, 0\.0\]: must be 4 numbers"),
        ("rotation", [0.0, 0.0, 0.0, 0.0], r"rigid\.rotation = .*: must not be zero"),
        ("rotation", [1.0, 0.1, 0.0, 0.0], r"rigid\.rotation = .*: not a unit quaternion \(\|q\| = 1\.00498"),
        ("rotation", [2.0, 0.0, 0.0, 0.0], r"rigid\.rotation = .*: not a unit quaternion"),
        ("rotation", [float("nan"), 0.0, 0.0, 0.0], r"rigid\.rotation = .*: must be finite"),
        ("rotation", 1.0, r"rigid\.rotation = 1\.0: must be 4 numbers"),
    ],
)
def test_a_bad_pose_is_refused_naming_the_key(key, value, message):
    with pytest.raises(jsnap.SceneError, match=message):
        jsnap.Scene.from_dict(_example(**{key: value}), source=str(EXAMPLE / "scene.toml"))


def test_a_nearly_unit_rotation_is_normalised():
    """Within 1e-6 of unit length (a quaternion written to 7 digits), as the waypoints allow."""
    q = [0.9996573, 0.0261769, 0.0, 0.0]
    assert abs(np.linalg.norm(q) - 1) < 1e-6
    scene = jsnap.Scene.from_dict(_example(rotation=q), source=str(EXAMPLE / "scene.toml"))
    r = np.asarray(scene["rigid"]["rotation"])
    assert np.linalg.norm(r) == pytest.approx(1.0, abs=1e-15)
    np.testing.assert_allclose(r, q / np.linalg.norm(q), rtol=0, atol=1e-15)
    # replace keeps it valid and unit.
    again = scene.replace({"rigid.position": [0.0, 0.0, 1.0]})
    assert again["rigid"]["rotation"] == scene["rigid"]["rotation"]
