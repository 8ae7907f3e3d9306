"""Neural signed distance of the plug (jsnap._build.neural_sdf). Lengths in mm.

Small nets on a small mesh, so that the whole file runs in well under a minute; the accuracy of
the default net on the default plug is measured by benchmarks/sdf_accuracy.py.
"""

import json
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

import jsnap
from jsnap._apps.cli import _SDF_SETTINGS
from jsnap._apps.cli import main as cli_main
from jsnap._build import neural_sdf as nsdf
from jsnap._build.cache import FORMAT_VERSION, ArtefactError
from jsnap._build.sdf import mesh_sdf_from_trimesh
from jsnap._core.sdf import NeuralSDF, mesh_sdf_and_normal, neural_sdf, neural_sdf_and_normal
from jsnap._geometry.plug import rounded_box_mesh

# A plug-like rounded block (428 triangles) and settings that train in a couple of seconds.
HALF = np.array([0.5, 1.0, 0.4])
RADIUS = 0.2
TINY = nsdf.NeuralSDFConfig(width=32, depth=2, steps=600, batch=512, samples=4000)
QUICK = nsdf.NeuralSDFConfig(width=16, depth=2, steps=100, batch=256, samples=1000)


@pytest.fixture(scope="module")
def mesh():
    return rounded_box_mesh(HALF, RADIUS, subdivisions=2)


@pytest.fixture(scope="module")
def trained(mesh):
    return nsdf.train(mesh, TINY, evaluate=False)


def _open_box():
    box = trimesh.creation.box(extents=[1.0, 2.0, 0.5])
    box.update_faces(np.arange(len(box.faces)) != 3)
    return box


# ----------------------------------------------------------------------------------------------
# Training and accuracy
# ----------------------------------------------------------------------------------------------


@pytest.mark.usefixtures("x64")
def test_training_reduces_error_to_a_bound_against_the_exact_sdf(mesh, trained):
    net, info = trained
    loss = np.asarray(info["loss"])
    assert loss.shape == (TINY.steps,) and np.all(np.isfinite(loss))
    assert loss[-50:].mean() < 0.1 * loss[:50].mean()
    # Independent points, uniform in the shell |φ| ≤ 0.2 mm, against the exact mesh SDF.
    rng = np.random.default_rng(7)
    x = rng.uniform(mesh.bounds[0] - 0.2, mesh.bounds[1] + 0.2, (6000, 3))
    phi, n = (np.asarray(a) for a in mesh_sdf_and_normal(mesh_sdf_from_trimesh(mesh), x))
    band = np.abs(phi) <= 0.2
    pred, pred_n = (np.asarray(a, np.float64) for a in neural_sdf_and_normal(net, x[band]))
    err = np.abs(pred - phi[band])
    assert err.mean() < 0.03  # measured 0.013 mm
    assert err.mean() < 0.3 * np.abs(phi[band]).mean()  # far better than guessing the surface
    angle = np.degrees(np.arccos(np.clip(np.sum(pred_n * n[band], axis=1), -1, 1)))
    assert np.median(angle) < 15.0  # measured 6 degrees
    report = nsdf.accuracy_report(net, mesh, band=0.2, points=2000, seed=3)
    assert report["points"] == 2000
    assert report["mae_mm"] == pytest.approx(err.mean(), rel=0.3)


# ----------------------------------------------------------------------------------------------
# The query: normals, far field, jit / vmap / grad, dtypes
# ----------------------------------------------------------------------------------------------


def _fd_gradient(net, p, h=1e-6):
    g = np.zeros_like(p)
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        g[:, k] = (np.asarray(neural_sdf(net, p + e)) - np.asarray(neural_sdf(net, p - e))) / (2 * h)
    return g


@pytest.mark.usefixtures("x64")
def test_normal_is_the_normalised_gradient(trained):
    net = trained[0].astype(jnp.float64)
    rng = np.random.default_rng(0)
    # Inside the training domain and outside it (where φ continues as distance + clamp).
    inside = rng.uniform(-0.8, 0.8, (40, 3)) * [1, 1.5, 0.8]
    outside = rng.normal(size=(40, 3)) * 4.0
    for p in (inside, outside):
        phi, n = neural_sdf_and_normal(net, p)
        assert phi.dtype == jnp.float64 and n.shape == p.shape
        np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
        g = _fd_gradient(net, p)
        np.testing.assert_allclose(n, g / np.linalg.norm(g, axis=1, keepdims=True), atol=1e-6)
        # jax.grad of φ points the same way.
        ag = jax.vmap(jax.grad(lambda q: neural_sdf(net, q)))(jnp.asarray(p))
        np.testing.assert_allclose(n, ag / np.linalg.norm(ag, axis=1, keepdims=True), atol=1e-10)


@pytest.mark.usefixtures("x64")
def test_far_field_is_positive_and_continuous(trained):
    net = trained[0].astype(jnp.float64)
    lo = np.asarray(net.center - net.half)
    hi = np.asarray(net.center + net.half)
    far = np.array([[30.0, 0.0, 0.0], [0.0, -50.0, 3.0], [100.0, 100.0, 100.0]])
    gap = np.linalg.norm(far - np.clip(far, lo, hi), axis=1)
    phi = np.asarray(neural_sdf(net, far))
    assert np.all(phi >= gap) and np.all(phi <= gap + 2 * np.max(hi - lo))
    # Across the domain's face x = hi_x, φ changes by about the step.
    eps = 1e-7
    on = np.array([hi[0], 0.1, 0.05])
    dx = np.array([eps, 0.0, 0.0])
    step = neural_sdf(net, on + dx) - neural_sdf(net, on - dx)
    assert abs(float(step)) < 10 * eps


def test_jit_vmap_grad_and_dtypes(trained):
    net = trained[0]
    rng = np.random.default_rng(1)
    batch = jnp.asarray(rng.uniform(-1, 1, (4, 32, 3)), jnp.float32)
    phi, n = jax.jit(jax.vmap(neural_sdf_and_normal, (None, 0)))(net, batch)
    assert phi.shape == (4, 32) and n.shape == (4, 32, 3) and phi.dtype == jnp.float32
    for i in range(4):
        p_i, n_i = neural_sdf_and_normal(net, batch[i])
        np.testing.assert_allclose(phi[i], p_i, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(n[i], n_i, rtol=1e-5, atol=1e-5)
    # Arbitrary leading shapes, and gradients w.r.t. the weights (e.g. for fine-tuning).
    assert neural_sdf(net, batch).shape == (4, 32)
    g = jax.grad(lambda m: jnp.sum(neural_sdf_and_normal(m, batch[0])[0] ** 2))(net)
    leaves = jax.tree.leaves(g.params)
    assert all(np.all(np.isfinite(x)) for x in leaves) and any(np.any(x != 0) for x in leaves)
    with pytest.raises(ValueError, match=r"shape \(\.\.\., 3\)"):
        neural_sdf(net, jnp.zeros((5, 2)))


# ----------------------------------------------------------------------------------------------
# Files and cache
# ----------------------------------------------------------------------------------------------


def _save(net, info, path, config=TINY):
    return nsdf.save(net, path, key=info["key"], mesh_hash=info["mesh_hash"], config=config)


def test_save_load_round_trip(trained, mesh, tmp_path):
    net, info = trained
    path = _save(net, info, tmp_path / "w.npz")
    back, meta = nsdf.load(path, key=nsdf.cache_key(mesh, TINY))
    assert meta["mesh_hash"] == nsdf.mesh_hash(mesh)
    assert meta["config"] == TINY.to_dict()
    x = np.random.default_rng(2).normal(size=(64, 3))
    for a, b in zip(neural_sdf_and_normal(net, x), neural_sdf_and_normal(back, x), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with np.load(path) as z:
        assert int(z["format_version"]) == FORMAT_VERSION
        assert json.loads(str(z["meta"]))["architecture"]["width"] == TINY.width


def _rewrite(path, **changes):
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}
    data.update(changes)
    np.savez(path, **data)


def test_corrupt_or_mismatched_files_are_rejected(trained, mesh, tmp_path):
    net, info = trained
    key = nsdf.cache_key(mesh, TINY)

    p = _save(net, info, tmp_path / "edited.npz")
    with np.load(p) as z:
        kernel = z["param/hidden_0/kernel"].copy()
    kernel[0, 0] += 1e-3
    _rewrite(p, **{"param/hidden_0/kernel": kernel})
    with pytest.raises(ArtefactError, match=r"edited\.npz: checksum mismatch"):
        nsdf.load(p)

    p = _save(net, info, tmp_path / "truncated.npz")
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    with pytest.raises(ArtefactError, match=r"truncated\.npz: unreadable or corrupt"):
        nsdf.load(p)

    p = _save(net, info, tmp_path / "other.npz")
    other = nsdf.cache_key(mesh, nsdf.NeuralSDFConfig(**{**TINY.to_dict(), "seed": 1}))
    with pytest.raises(ArtefactError, match="made for something else"):
        nsdf.load(p, key=other)
    assert nsdf.load(p, key=key)[1]["key"] == key

    p = _save(net, info, tmp_path / "future.npz")
    _rewrite(p, format_version=np.asarray(FORMAT_VERSION + 1))
    with pytest.raises(ArtefactError, match=f"format version {FORMAT_VERSION + 1}"):
        nsdf.load(p)

    p = tmp_path / "foreign.npz"
    np.savez(p, weights=np.zeros(3))
    with pytest.raises(ArtefactError, match="not a jsnap artefact"):
        nsdf.load(p)

    with pytest.raises(FileNotFoundError, match=r"missing\.npz"):
        nsdf.load(tmp_path / "missing.npz")


def test_cache_trains_once_then_loads_and_replaces_a_corrupt_entry(mesh, tmp_path, monkeypatch):
    monkeypatch.setenv("JSNAP_CACHE", str(tmp_path / "cache"))
    net, info = nsdf.load_or_train(mesh, QUICK, report_points=500)
    assert not info["cached"] and info["path"].parent == tmp_path / "cache" / "neural_sdf"
    assert info["path"].name.startswith(nsdf.cache_key(mesh, QUICK)[:32])
    again, info2 = nsdf.load_or_train(mesh, QUICK, report_points=500)
    assert info2["cached"] and info2["path"] == info["path"]
    assert info2["report"] == info["report"]
    x = np.random.default_rng(3).normal(size=(16, 3))
    np.testing.assert_array_equal(neural_sdf(net, x), neural_sdf(again, x))
    # Damage the cached file: never used, reported, retrained and replaced.
    raw = bytearray(info["path"].read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    info["path"].write_bytes(bytes(raw))
    with pytest.warns(UserWarning, match="not using it: the neural SDF is made again"):
        _, info3 = nsdf.load_or_train(mesh, QUICK, report_points=500)
    assert not info3["cached"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert nsdf.load_or_train(mesh, QUICK, report_points=500)[1]["cached"]


def test_mesh_hash_is_the_surface_not_its_listing(mesh):
    """The cache key's mesh hash: the same for the same oriented triangles listed in any order
    (vertices, faces, a face's starting corner) or off in the last bit; another for a moved
    vertex or flipped faces."""
    h = nsdf.mesh_hash(mesh)
    rng = np.random.default_rng(5)
    perm = rng.permutation(len(mesh.vertices))
    inverse = np.argsort(perm)
    faces = inverse[np.asarray(mesh.faces)][rng.permutation(len(mesh.faces))]
    faces = np.stack([np.roll(f, k) for f, k in zip(faces, rng.integers(0, 3, len(faces)), strict=True)])
    shuffled = trimesh.Trimesh(np.asarray(mesh.vertices)[perm], faces, process=False)
    assert nsdf.mesh_hash(shuffled) == h
    ulp = trimesh.Trimesh(np.nextafter(mesh.vertices, np.inf), mesh.faces, process=False)
    assert nsdf.mesh_hash(ulp) == h
    moved = np.array(mesh.vertices)
    moved[7] += 1e-6
    assert nsdf.mesh_hash(trimesh.Trimesh(moved, mesh.faces, process=False)) != h
    flipped = trimesh.Trimesh(mesh.vertices, np.asarray(mesh.faces)[:, ::-1], process=False)
    assert nsdf.mesh_hash(flipped) != h


def test_shipped_weights_are_read_before_training(mesh, trained, tmp_path, monkeypatch):
    """Weights shipped for a key are used, read-only, when the cache has none; a cached file
    comes first; ``retrain`` and a corrupt shipped file train."""
    net, info = trained
    key = nsdf.cache_key(mesh, TINY)
    monkeypatch.setattr(nsdf, "SHIPPED", tmp_path / "shipped")
    shipped = _save(net, info, nsdf.shipped_path(key))
    monkeypatch.setenv("JSNAP_CACHE", str(tmp_path / "cache"))

    def no_training(*a, **k):
        raise AssertionError("trained")

    monkeypatch.setattr(nsdf, "train", no_training)
    got, got_info = nsdf.load_or_train(mesh, TINY)
    assert got_info["cached"] and got_info["shipped"] and got_info["path"] == shipped
    x = np.random.default_rng(6).normal(size=(16, 3))
    np.testing.assert_array_equal(neural_sdf(got, x), neural_sdf(net, x))
    assert not (tmp_path / "cache" / "neural_sdf").exists()  # nothing written
    with pytest.raises(AssertionError, match="trained"):
        nsdf.load_or_train(mesh, TINY, retrain=True)
    # A file in the cache comes first.
    mine = _save(net, info, nsdf.cache_path(key))
    assert nsdf.load_or_train(mesh, TINY)[1]["path"] == mine
    mine.unlink()
    # A corrupt shipped file is reported and not used.
    raw = bytearray(shipped.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    shipped.write_bytes(bytes(raw))
    with pytest.warns(UserWarning, match="checksum|corrupt"), pytest.raises(AssertionError, match="trained"):
        nsdf.load_or_train(mesh, TINY)


def test_shipped_weights_are_the_default_plugs(tmp_path, monkeypatch):
    """The package's weights describe the current default plug: the default settings, and
    within the training-time accuracy of the exact SDF of the plug that the default scene
    builds now. Where that plug's mesh has the shipped key they are used without training;
    where a mesh library triangulates it differently (another key), the plug is trained."""
    from jsnap._geometry.presets import default_rigid

    files = sorted(nsdf.SHIPPED.glob("*.npz"))
    assert len(files) == 1
    net, meta = nsdf.load(files[0])  # verifies the checksum
    assert meta["config"] == nsdf.NeuralSDFConfig().to_dict() and files[0].stem == meta["key"][:32]
    scene = jsnap.load_scene()
    plug = default_rigid("cantilever", scene["connector"], scene["plug"]).mesh()
    report = nsdf.accuracy_report(net, plug, points=4000)
    assert report["mae_mm"] < 2e-3 and report["normal_median_deg"] < 2.0, report

    monkeypatch.setenv("JSNAP_CACHE", str(tmp_path / "cache"))

    def no_training(*a, **k):
        raise AssertionError("trained")

    monkeypatch.setattr(nsdf, "train", no_training)
    if nsdf.cache_key(plug, nsdf.NeuralSDFConfig()) == meta["key"]:
        assert nsdf.load_or_train(plug)[1]["shipped"]
    else:
        with pytest.raises(AssertionError, match="trained"):
            nsdf.load_or_train(plug)


# ----------------------------------------------------------------------------------------------
# Bad input
# ----------------------------------------------------------------------------------------------


def test_meshes_without_a_signed_distance_are_rejected(tmp_path):
    with pytest.raises(ValueError, match="not watertight"):
        nsdf.train(_open_box(), QUICK)
    flipped = trimesh.creation.box(extents=[1.0, 2.0, 0.5])
    flipped.faces[0] = flipped.faces[0, ::-1]
    with pytest.raises(ValueError, match="winding is inconsistent"):
        nsdf.load_or_train(flipped, QUICK)
    path = tmp_path / "open.stl"
    _open_box().export(path)
    with pytest.raises(ValueError, match=r"open\.stl: mesh is not watertight"):
        nsdf.load_mesh(path)
    path = tmp_path / "junk.stl"
    path.write_text("not a mesh")
    with pytest.raises(ValueError, match=r"junk\.stl"):
        nsdf.load_mesh(path)


@pytest.mark.parametrize(
    "change, match",
    [
        (dict(width=0), "width"),
        (dict(depth=2.5), "depth"),
        (dict(activation="relu"), "activation = 'relu'"),
        (dict(band=0.5, pad=0.3), "pad"),
        (dict(learning_rate=float("nan")), "learning_rate"),
        (dict(box_fraction=1.5), "box_fraction"),
    ],
)
def test_bad_settings_name_the_setting(change, match):
    with pytest.raises(ValueError, match=match):
        nsdf.NeuralSDFConfig(**change)


# ----------------------------------------------------------------------------------------------
# CLI and the whole-scene path
# ----------------------------------------------------------------------------------------------


def test_cli_train_sdf(mesh, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("JSNAP_CACHE", str(tmp_path / "cache"))
    stl = tmp_path / "plug.stl"
    mesh.export(stl)
    out = tmp_path / "plug_sdf.npz"
    args = ["train-sdf", str(stl), *(f"--{k}={v}" for k, v in QUICK.to_dict().items() if k in _SDF_SETTINGS)]
    assert cli_main([*args, "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["triangles"] == len(mesh.faces) and not summary["cached"]
    assert summary["accuracy"]["points"] > 0 and summary["accuracy"]["mae_mm"] > 0
    net, meta = nsdf.load(out)
    assert meta["config"] == QUICK.to_dict() and net.width == QUICK.width
    assert cli_main(args) == 0
    assert "loaded from the cache" in capsys.readouterr().out

    bad = tmp_path / "open.stl"
    _open_box().export(bad)
    assert cli_main(["train-sdf", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "open.stl" in err and "not watertight" in err


def test_scene_with_neural_sdf_builds_and_dispatches(tmp_path, monkeypatch):
    from jsnap._build import model as _model
    from jsnap._core.sdf import BoundedSDF
    from jsnap._geometry.presets import default_rigid

    monkeypatch.setenv("JSNAP_CACHE", str(tmp_path / "cache"))
    # The default settings take a minute to train; the wiring is the same with tiny ones.
    monkeypatch.setattr(
        _model, "load_or_train", lambda m, **kw: nsdf.load_or_train(m, QUICK, report_points=500, **kw)
    )
    scene = jsnap.load_scene().replace(
        {"solver.sdf": "neural", "solver.method": "full", "solver.element": "P1", "solver.mesh_size": 1.5}
    )
    model = jsnap.build(scene)
    assert isinstance(model.rigid, BoundedSDF) and isinstance(model.rigid.exact, NeuralSDF)
    # Trained on the scene's own plug mesh, and found in the cache under its key.
    assert (tmp_path / "cache" / "neural_sdf").is_dir()
    plug = default_rigid("cantilever", scene["connector"], scene["plug"]).mesh()
    assert nsdf.load_or_train(plug, QUICK)[1]["cached"]
    with jax.enable_x64(True):  # the model's float64 kernels, called directly
        q = jnp.asarray(np.random.default_rng(4).uniform(-1, 1, (10, 3)))
        phi, n = model.rigid.scene_query(q, model.contact.margin)
        ref_phi, ref_n = neural_sdf_and_normal(model.rigid.exact, q)
        np.testing.assert_array_equal(phi, ref_phi)
        np.testing.assert_array_equal(n, ref_n)
        # The array leaves cast with the model (rollouts run in float32).
        cast = jax.tree.map(lambda a: a.astype(jnp.float32), model.rigid.exact)
        query = eqx_replace(model, cast).rigid.scene_query(q.astype(jnp.float32), model.contact.margin)
        assert query[0].dtype == jnp.float32


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("n_contact", [40, 300])
def test_step_query_is_the_network_where_contact_needs_it(mesh, trained, n_contact):
    """The step's neural query (``BoundedSDF.scene_query`` of the network over the plug's box,
    as ``solver.sdf = "neural"`` builds it: the network at the points nearest the box, in blocks
    of ``_NEAR_BLOCK``, the box's distance elsewhere) against the network at every point: the
    same values and normals wherever a contact decision needs them (below the margin), the same
    decisions everywhere, with one block (40 near points) and several (300), under ``vmap``
    (every block evaluated) and with fewer points than the blocks hold."""
    from jsnap._build.model import _NEURAL_SLACK
    from jsnap._core import sdf as _sdf

    net = trained[0].astype(jnp.float64)
    margin = 0.02
    rng = np.random.default_rng(12)
    surf, face = trimesh.sample.sample_surface(mesh, n_contact, seed=5)
    near = surf + mesh.face_normals[face] * rng.uniform(-margin, margin, (n_contact, 1))
    # Others that are no candidates: off the surface by 0.1-0.6 mm, and far.
    surf, face = trimesh.sample.sample_surface(mesh, 500, seed=6)
    off = surf + mesh.face_normals[face] * rng.uniform(0.1, 0.6, (500, 1))
    far = rng.uniform(-3, 3, (200, 3))
    q = jnp.asarray(rng.permutation(np.concatenate([near, off, far])))
    box = _sdf.RoundedBoxSDF(jnp.asarray(HALF), jnp.asarray(0.0, jnp.float64))
    rigid = _sdf.BoundedSDF(net, box, _NEURAL_SLACK)
    query = jax.jit(lambda q: rigid.scene_query(q, margin))
    ref, ref_n = neural_sdf_and_normal(net, q)
    need = np.asarray(ref < margin)
    assert np.sum(need) >= 0.9 * n_contact
    assert (np.sum(need) <= _sdf._NEAR_BLOCK) == (n_contact == 40)
    for phi, n in (query(q), [a[0] for a in jax.vmap(query)(q[None])]):
        np.testing.assert_allclose(phi[need], ref[need], rtol=0, atol=1e-12)
        np.testing.assert_allclose(n[need], ref_n[need], rtol=0, atol=1e-10)
        np.testing.assert_array_equal(phi < margin, need)
        np.testing.assert_array_equal(phi < -0.5 * margin, ref < -0.5 * margin)
        np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    # Fewer points than the blocks hold: the last block overlaps the one before.
    sub = q[:200]
    phi_s, _ = jax.jit(lambda q: rigid.scene_query(q, margin))(sub)
    np.testing.assert_allclose(phi_s[need[:200]], ref[:200][need[:200]], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(phi_s < margin, need[:200])


def eqx_replace(model, net):
    import equinox as eqx

    return eqx.tree_at(lambda m: m.rigid.exact, model, net)
