"""Exact contact against rigid parts nobody tuned for: the candidate-grid mesh SDF
(``GridMeshSDF``, the default for a rigid part from a file) against the brute-force distance to
every triangle (``MeshSDF``), on the family of CAD-like shapes of ``benchmarks/_shapes.py``
(a faceted pin and ball, sharp and chamfered blocks, a wedge, a sleeve around the arm), and one
whole rollout against the brute-force SDF's."""

import dataclasses
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

import jsnap
from jsnap._build.sdf import grid_mesh_sdf, mesh_sdf_from_trimesh
from jsnap._core.sdf import PATH_CHECKS, GridMeshSDF, mesh_sdf_and_normal

BENCH = Path(__file__).resolve().parent.parent / "benchmarks"
sys.path.insert(0, str(BENCH))
import _shapes as shapes  # noqa: E402  (the benchmark's shapes: one definition for both)

HOOK = shapes.Hook(h_tip=1.2, width=4.0, z_top=11.5, length=10.0, undercut=0.8)
BAND = 0.16  # the default scene's: 8 contact resolutions of 0.02 mm


def _points(mesh, rng, n=6000):
    """Points near the surface (within ~2 band widths) and through the whole box."""
    surf, _ = trimesh.sample.sample_surface(mesh, n, seed=int(rng.integers(1 << 30)))
    near = surf + rng.normal(0.0, BAND, surf.shape)
    box = rng.uniform(mesh.bounds[0] - 2 * BAND, mesh.bounds[1] + 2 * BAND, (n, 3))
    return np.concatenate([near, box])


@pytest.fixture(scope="module", params=shapes.SHAPES)
def family(request):
    mesh, _ = shapes.shape(request.param, HOOK)
    mesh.apply_translation(-mesh.center_mass)  # the rigid part's own frame
    exact = mesh_sdf_from_trimesh(mesh)
    return request.param, mesh, exact, grid_mesh_sdf(exact, BAND)


def test_grid_equals_the_brute_force_distance_in_the_band(family):
    name, mesh, exact, grid = family
    pts = _points(mesh, np.random.default_rng(0))
    with jax.enable_x64(True):
        a, na = (np.asarray(v) for v in mesh_sdf_and_normal(exact, pts))
        b, nb = (np.asarray(v) for v in grid(jnp.asarray(pts)))
    band = np.abs(a) < BAND
    assert band.sum() > 1000, name
    np.testing.assert_allclose(b[band], a[band], atol=1e-12, err_msg=name)
    np.testing.assert_allclose(nb[band], na[band], atol=1e-9, err_msg=name)
    # Beyond the band: the right side, at least the band away (every contact decision holds).
    assert np.all(np.sign(b) == np.sign(a)), name
    assert np.all(np.abs(b[~band]) >= BAND * (1 - 1e-12)), name
    np.testing.assert_allclose(np.linalg.norm(nb, axis=1), 1.0, atol=1e-9)


def test_grid_decisions_in_float32(family):
    """In the rollout's precision a point may fall in a neighbouring cell by rounding: the lists
    allow for it, so φ still equals the brute-force float32 distance."""
    name, mesh, exact, grid = family
    pts = _points(mesh, np.random.default_rng(1)).astype(np.float32)
    a = np.asarray(mesh_sdf_and_normal(exact.astype(jnp.float32), pts)[0])
    b = np.asarray(grid.astype(jnp.float32)(jnp.asarray(pts))[0])
    band = np.abs(a) < BAND * 0.99
    np.testing.assert_allclose(b[band], a[band], atol=2e-6, err_msg=name)
    assert np.all((a < 0.02) == (b < 0.02)) or np.abs(a[(a < 0.02) != (b < 0.02)] - 0.02).max() < 2e-6


def test_grid_gradient_is_the_normal(family):
    name, mesh, _, grid = family
    pts = _points(mesh, np.random.default_rng(2), n=200)
    with jax.enable_x64(True):
        g = jax.grad(lambda x: jnp.sum(grid(x)[0]))(jnp.asarray(pts))
        phi, n = grid(jnp.asarray(pts))
    band = np.abs(np.asarray(phi)) < BAND
    np.testing.assert_allclose(np.asarray(g)[band], np.asarray(n)[band], atol=1e-9, err_msg=name)


def test_grid_path_minimum_on_the_needed_points(family):
    """``least_along`` with a mask: at the needed points the least brute-force distance over the
    path's four fractions (signed in the search, exact in the band; the side beyond it)."""
    name, mesh, exact, grid = family
    rng = np.random.default_rng(4)
    start = _points(mesh, rng, n=400)
    step = rng.normal(0.0, 0.05, start.shape)  # paths of ~0.1 mm, a few contact resolutions
    need = rng.random(len(start)) < 0.6
    with jax.enable_x64(True):
        path = lambda f: jnp.asarray(start + f * step)  # noqa: E731
        least = np.asarray(grid.least_along(path, None, 0.02, jnp.asarray(need)))
        ref = np.min([np.asarray(mesh_sdf_and_normal(exact, start + f * step)[0]) for f in PATH_CHECKS], axis=0)
    band = need & (np.abs(ref) < BAND)
    assert band.sum() > 100, name
    np.testing.assert_allclose(least[band], ref[band], atol=1e-12, err_msg=name)
    assert np.all(np.sign(least[need]) == np.sign(ref[need])), name


def test_grid_vmaps_and_jits():
    mesh, _ = shapes.shape("cylinder", HOOK)
    mesh.apply_translation(-mesh.center_mass)
    with jax.enable_x64(True):
        grid = grid_mesh_sdf(mesh_sdf_from_trimesh(mesh), BAND)
        pts = jnp.asarray(_points(mesh, np.random.default_rng(3), n=300)[:600].reshape(4, 150, 3))
        batched = jax.jit(jax.vmap(lambda q: grid(q)[0]))(pts)
        np.testing.assert_allclose(batched, np.stack([grid(q)[0] for q in pts]), atol=1e-14)


def test_bad_band_is_refused():
    mesh, _ = shapes.shape("sharp_block", HOOK)
    with pytest.raises(ValueError, match="band"):
        grid_mesh_sdf(mesh_sdf_from_trimesh(mesh), 0.0)


def test_sleeve_around_the_arm_rolls_out_as_the_brute_force_distance(tmp_path):
    """A housing whose box encloses the arm (the bound of the former SDF was no help there):
    the default model latches with status ok, and its forces are those of the brute-force SDF at
    every point, the independent reference."""
    mesh, stroke = shapes.shape("sleeve", HOOK)
    mesh.export(tmp_path / "sleeve.stl")
    text = (
        '[connector]\ntype = "cantilever"\nlength = 10.0\nthickness = 1.2\nwidth = 4.0\nundercut = 0.8\n'
        "lead_angle = 30.0\nreturn_angle = 90.0\nflat = 0.1144\n"
        f'[rigid]\nmesh = "sleeve.stl"\n[material]\nyoungs_modulus = 2200.0\npoissons_ratio = 0.35\n'
        f"density = 1.05e-9\n[contact]\nfriction = 0.3\n[motion]\nstroke = {stroke}\n"
    )
    (tmp_path / "scene.toml").write_text(text)
    model = jsnap.build(jsnap.load_scene(tmp_path / "scene.toml"))
    assert isinstance(getattr(model.rigid, "inner", model.rigid), GridMeshSDF)
    prepared = jsnap.prepare(model)
    res = jsnap.rollout(model, prepared=prepared)
    brute = shapes.with_distance(model.rigid, lambda grid: grid.mesh)
    ref = jsnap.rollout(dataclasses.replace(model, rigid=brute), prepared=prepared)
    assert res.ok, res.status()
    assert ref.ok, ref.status()
    F, F_ref = np.asarray(res.insertion_force), np.asarray(ref.insertion_force)
    peak = F_ref.max()
    assert np.max(np.abs(F - F_ref)) < 0.01 * peak
    # It latches: past the wall the hook is released (the force falls back near zero).
    assert peak > 1.0 and abs(F[-1]) < 0.05 * peak
