"""Segmentation and passive balanced reduction (jsnap/_build/reduce.py, docs/reduction.md).

Coarse P2 meshes (2.0 mm, 780 free dofs; coarser than the 0.8 mm undercut: a SceneWarning) and a
light contact configuration keep these fast; each model is built once per module and reduced
models are cached in a temporary directory. Tests that run the parts' float64 kernels directly
use the ``x64`` fixture.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sla
import scipy.sparse.linalg as spla

import jsnap
from jsnap._build import cache as _cache
from jsnap._build import reduce as R
from jsnap._build.fem import assemble, lame
from jsnap._build.model import build_model
from jsnap._core.contact import APGD
from jsnap._geometry.cantilever import mesh_cantilever
from jsnap._geometry.scene import SceneError, connector_geometry, with_internal

SMALL = {
    "solver.mesh_size": 2.0,
    "solver.dtype": "float64",
    "motion.speed": 20.0,
    "contact.capacity": 16,
    "contact.width_spacing": 2.0,
    "contact.iterations": 200,
}


@pytest.fixture(scope="module")
def scene():
    return jsnap.load_scene().replace(SMALL)


@pytest.fixture(scope="module")
def built(cache, scene):
    """Full, segmented and reduced models of the same small scene, with their build reports."""
    return {m: build_model(scene.replace({"solver.method": m})) for m in ("full", "segmented", "reduced")}


@pytest.fixture(scope="module")
def models(built):
    return {m: model for m, (model, _) in built.items()}


@pytest.fixture(scope="module")
def asm(scene, models):
    """The full assembly the models were built from (the build keeps none: assembled again)."""
    a = assemble(mesh_cantilever(connector_geometry(scene), scene["solver"]["mesh_size"]), "P2")
    assert a.free.size == models["full"].full_dof
    assert np.array_equal(a.nodes, np.asarray(models["full"].mesh.nodes))
    return a


def _full_compliance(asm, full, points):
    """(3p, 3p) static compliance J K^-1 J' of the full model at candidate points, mm/N."""
    p = full.params
    lam, mu = lame(float(p.E), float(p.nu))
    f = asm.free
    K = (lam * asm.K_lam + mu * asm.K_mu)[f][:, f].tocsc()
    s = full.part
    J = np.zeros((3 * len(points), f.size))
    nodes, w = np.asarray(s.sample_nodes)[points], np.asarray(s.sample_weights)[points]
    for i in range(len(points)):
        for k in range(nodes.shape[1]):
            for a in range(3):
                J[3 * i + a, 3 * nodes[i, k] + a] += w[i, k]
    return J @ spla.splu(K).solve(J.T)


def _socket_compliance(model, points, kc=None):
    """The same for a segmented or reduced socket (a segmented one's interface springs at
    ``kc``, default its own)."""
    s = model.part
    with jax.enable_x64(True):
        if kc is not None:
            s = eqx.tree_at(lambda s: s.coupling, s, jnp.asarray([kc, 0.0], jnp.float64))
        K = np.asarray(s.stiffness(model.params.material))
    rows = np.einsum(
        "pk,pkdr->pdr",
        np.asarray(s.sample_weights)[points],
        np.asarray(s.node_rows)[np.asarray(s.sample_nodes)[points]],
    ).reshape(3 * len(points), -1)
    return rows @ sla.solve(K, rows.T, assume_a="pos")


def _normals(model, points):
    """(p, 3) outward normals of the candidate points' own side (from the rest stencil)."""
    s = np.asarray(model.samples.stencil)[points]
    n = np.cross(s[:, 3] - s[:, 2], s[:, 1] - s[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _normal_compliance(C, normals):
    p = len(normals)
    return np.einsum("pd,pdqe,qe->pq", normals, C.reshape(p, 3, p, 3), normals).diagonal()


def _seeds(asm, model):
    """Boundary faces of the candidate points (as build finds them)."""
    s = model.part
    nodes = (asm.free[0::3] // 3)[np.asarray(s.sample_nodes)]
    contact = np.unique(nodes[np.asarray(s.sample_weights) != 0])
    faces = asm.mesh.boundary_faces()
    return faces[np.isin(faces, contact).all(axis=1)]


@pytest.mark.parametrize("n_rest", [1, 2])
def test_segments_partition_the_mesh_and_sum_to_the_full_blocks(models, asm, n_rest):
    full = models["full"]
    seeds = _seeds(asm, full)
    seg = R.segment(asm, seeds, 1.0, n_rest)
    assert seg.n_segments == n_rest + 1
    assert set(np.unique(seg.element_segment)) == set(range(n_rest + 1))
    # Every element touching a seed face is in the contact segment: its nodes are interior.
    assert np.all(seg.element_segment[np.isin(asm.mesh.cells, seeds).any(axis=1)] == 0)
    free_pos = -np.ones(asm.n_dof, dtype=int)
    free_pos[asm.free] = np.arange(asm.free.size)
    total = 0
    for i in range(seg.n_segments):
        (kl, _km, _m1), (rl, _, _) = R.segment_blocks(asm, seg, i)
        dofs = free_pos[(3 * seg.nodes[i][:, None] + np.arange(3)).ravel()]
        assert np.all(dofs >= 0)  # clamped nodes are not copied
        P = np.zeros((asm.free.size, dofs.size))
        P[dofs, np.arange(dofs.size)] = 1.0
        total = total + P @ kl.toarray() @ P.T
        assert (rl.nnz > 0) == (i == n_rest)  # the base is in the segment farthest from contact
    K = asm.K_lam[asm.free][:, asm.free].toarray()
    assert np.abs(total - K).max() < 1e-12 * np.abs(K).max()
    for sa, la, sb, lb in seg.pairs:  # springs join copies of one node
        assert seg.nodes[sa][la] == seg.nodes[sb][lb] and sa != sb
    shared = np.unique(np.concatenate(seg.nodes), return_counts=True)[1]
    assert len(seg.pairs) == np.sum(shared - 1)


def test_position_gramians_solve_the_lyapunov_equations():
    rng = np.random.default_rng(0)
    s, m, zeta = 6, 2, 0.05
    w, b = np.sort(rng.uniform(1.0, 10.0, s)), rng.normal(size=(s, m))
    A = np.block([[np.zeros((s, s)), np.eye(s)], [-np.diag(w**2), -2 * zeta * np.diag(w)]])
    B = np.vstack([np.zeros((s, m)), b])
    C = np.hstack([b.T, np.zeros((m, s))])
    P = sla.solve_continuous_lyapunov(A, -B @ B.T)[:s, :s]
    Q = sla.solve_continuous_lyapunov(A.T, -C.T @ C)[:s, :s]
    Pp, Qp = R.position_gramians(w, b, zeta)
    assert np.abs(Pp - P).max() < 1e-12 * np.abs(P).max()
    assert np.abs(Qp - Q).max() < 1e-12 * np.abs(Q).max()
    # One mode: sigma = |b|^2 sqrt(1 + 4 zeta^2) / (4 zeta w^2), its static compliance / 4 zeta.
    _, hsv = R.balance(np.diag(w**2), np.eye(s)[:, :1], 1e-3, zeta)
    assert hsv[0] == pytest.approx(np.sqrt(1 + 4 * zeta**2) / (4 * zeta * w[0] ** 2), rel=1e-9)


@pytest.mark.parametrize("method", ["reduced", "segmented"])
def test_energy_conserved_without_damping_or_input(models, x64, method):
    """D = 0, b_c = 0, no contact: PMI conserves the energy to round-off, for the reduced part
    (joined exactly) and the segmented one (interface springs of 1e6 N/mm, ~1e4 times the arm's
    stiffness, factored out of the residual)."""
    model = models[method]
    s = model.part
    if method == "segmented":
        s = eqx.tree_at(lambda s: s.coupling, s, s.coupling.at[1].set(0.0))
    op = s.prepare(model.params.material, model.dt)
    J = jnp.einsum("k,kdr->dr", s.sample_weights[0], s.node_rows[s.sample_nodes[0]])
    x0 = jnp.linalg.solve(s.stiffness(model.params.material), J.T @ jnp.array([1.0, 0.0, 0.0]))

    def body(c, _):
        x, v = c
        vbar = s.free_velocity(op, x, v)
        x, v = x + op.dt * vbar, 2 * vbar - v
        return (x, v), s.energy(op, x, v)

    steps = 5_000
    _, e = jax.jit(lambda x: jax.lax.scan(body, (x, 0 * x), None, length=steps))(x0)
    e0 = s.energy(op, x0, 0 * x0)
    # Round-off: a step's rounding changes the energy by ~eps times the stiffest term's share
    # (the springs: ~1e4 times the arm's stiffness), and the change adds up linearly in the steps
    # (jsnap._core.pmi). Twice that bound: ~2e-8 of the energy after 5000 steps.
    assert float(jnp.max(jnp.abs(e - e0)) / e0) < 2 * 1e4 * np.finfo(np.float64).eps * steps


def _three_segments(models, asm, scene):
    """The small part cut into a contact segment and two others: ``(seg, blocks, material,
    (sample, normals))``, what ``reduce_bases`` takes."""
    full = models["full"]
    seg = R.segment(asm, _seeds(asm, full), scene["solver"]["segment_margin"], 2)
    blocks = [R.segment_blocks(asm, seg, i)[0] for i in range(seg.n_segments)]
    m = scene["material"]
    material = (m["youngs_modulus"], m["poissons_ratio"], m["density"])
    s = full.part
    nodes, w = np.asarray(s.sample_nodes), np.asarray(s.sample_weights)
    normals = np.repeat(_normals(full, np.arange(full.n_samples))[:, None], 2, axis=1)
    return seg, blocks, material, ((nodes, w), normals)


def test_reduced_segments_are_joined_exactly(models, asm, scene):
    """Every segment's copy of a shared node moves as the others for every reduced coordinate:
    the joined basis has no gap to close (no springs), and it is mass-orthonormal with a
    diagonal stiffness at the nominal material (the reduced model's own modes)."""
    seg, blocks, material, inputs = _three_segments(models, asm, scene)
    bases, _ = R.reduce_bases(asm, seg, blocks, material, *inputs, 1e-2, 30)
    Vs, orders = R.join_bases(bases, blocks, material)
    assert sum(orders) == Vs[0].shape[1] and orders[0] >= 6  # at least the interface's rigid motions
    scale = max(np.abs(V).max() for V in Vs)
    for sa, la, sb, lb in seg.pairs:
        gap = Vs[sa][3 * la : 3 * la + 3] - Vs[sb][3 * lb : 3 * lb + 3]
        assert np.abs(gap).max() <= 1e-12 * scale
    lam, mu = lame(*material[:2])
    M = sum(V.T @ (material[2] * b[2] @ V) for V, b in zip(Vs, blocks, strict=True))
    K = sum(V.T @ ((lam * b[0] + mu * b[1]) @ V) for V, b in zip(Vs, blocks, strict=True))
    np.testing.assert_allclose(M, np.eye(len(M)), atol=1e-10)
    off = K - np.diag(np.diag(K))
    assert np.abs(off).max() <= 1e-9 * np.abs(K).max()


def test_segments_reduced_at_once_or_in_turn_give_the_same_model(models, asm, scene, monkeypatch):
    """The segments' bases are computed a thread each when their memory fits together, else one
    after the other: the same reduced model either way (its modes at the nominal material), and
    the threads are used only when the memory allows."""
    seg, blocks, material, inputs = _three_segments(models, asm, scene)
    pools = []

    class Pool(R.ThreadPoolExecutor):
        def __init__(self, workers):
            pools.append(workers)
            super().__init__(workers)

    monkeypatch.setattr(R, "ThreadPoolExecutor", Pool)
    monkeypatch.setattr(R.os, "cpu_count", lambda: 2)
    modes = []
    for memory in (None, 0):  # this machine's, then none to spare for two at once
        if memory is not None:
            monkeypatch.setattr(R, "available_memory", lambda: memory)
        bases, _ = R.reduce_bases(asm, seg, blocks, material, *inputs, 1e-2, 30)
        Vs, orders = R.join_bases(bases, blocks, material)
        lam, mu = lame(*material[:2])
        K = sum(V.T @ ((lam * b[0] + mu * b[1]) @ V) for V, b in zip(Vs, blocks, strict=True))
        modes.append((orders, np.sort(np.diag(K))))
    assert pools == [2]  # threads for the first build only
    assert modes[0][0] == modes[1][0]
    np.testing.assert_allclose(modes[0][1], modes[1][1], rtol=1e-8)  # round-off: BLAS threads differ


def test_reduced_damping_only_removes_energy(models, x64):
    red = models["reduced"]
    s = red.part
    op = s.prepare(red.params.replace(alpha=30.0, beta=2e-6).material, red.dt)
    J = jnp.einsum("k,kdr->dr", s.sample_weights[0], s.node_rows[s.sample_nodes[0]])
    x0 = jnp.linalg.solve(s.stiffness(red.params.material), J.T @ jnp.ones(3))

    def body(c, _):
        x, v = c
        vbar = s.free_velocity(op, x, v)
        x, v = x + op.dt * vbar, 2 * vbar - v
        return (x, v), s.energy(op, x, v)

    _, e = jax.lax.scan(body, (x0, 0 * x0), None, length=500)
    e = np.concatenate([[float(s.energy(op, x0, 0 * x0))], np.asarray(e)])
    assert np.max(np.diff(e)) <= 1e-12 * e[0]
    assert e[-1] < 0.5 * e[0]


def test_static_normal_compliance_at_the_contact_points(models, asm, scene):
    """The reduced model keeps the normal compliance at every candidate point to the tolerance
    (1e-2 by default); the segmented one to ~1/k_c, its interface springs' compliance."""
    full = models["full"]
    pts = np.arange(full.n_samples)
    n = _normals(full, pts)
    c_full = _normal_compliance(_full_compliance(asm, full, pts), n)
    tol = scene["solver"]["hsv_tolerance"]
    c = {m: _normal_compliance(_socket_compliance(models[m], pts), n) for m in ("segmented", "reduced")}
    assert np.max(np.abs(c["segmented"] / c_full - 1)) < 1e-3
    assert np.max(np.abs(c["reduced"] / c_full - 1)) < 1.5 * tol
    # The reduced model is a Galerkin projection of the full one: never softer.
    assert np.all(c["reduced"] <= c_full * (1 + 1e-9))


def test_patch_weights_spread_a_unit_load_over_one_side():
    """Each load case spread over its neighbours on the same side, Gaussian in the distance,
    a unit total; never across a 90-degree edge; a patch far below the spacing is each point
    alone."""
    at = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [0.1, 0, 0]])
    n = np.array([[0.0, 0, 1], [0, 0, 1], [0, 0, 1], [1, 0, 0]])  # the last: the other side of point 1
    W = R._patch_weights(at, n, 0.1).toarray()
    np.testing.assert_allclose(W.sum(axis=0), 1.0, rtol=1e-14)
    assert np.all(W[3, :3] == 0) and np.all(W[:3, 3] == 0) and W[3, 3] == 1.0
    # Column 1 (the middle point): its neighbours 0.1 mm = one standard deviation away.
    np.testing.assert_allclose(W[[0, 2], 1] / W[1, 1], np.exp(-0.5), rtol=1e-12)
    np.testing.assert_allclose(W[2, 0] / W[1, 0], np.exp(-1.5), rtol=1e-12)  # 2 sigma against 1
    np.testing.assert_array_equal(R._patch_weights(at, n, 1e-4).toarray(), np.eye(4))


def test_reduction_at_patch_loads_keeps_their_compliance(models, asm, scene, cache):
    """With ``solver.load_patch``, the reduced model keeps the static compliance of every patch
    load (a unit normal force spread over the candidate points by a Gaussian, built here densely
    from the points' rest positions and both sides' normals) to the tolerance against the full
    model, never softer, with fewer coordinates than at point loads."""
    patch = 0.5
    reduced = jsnap.build(scene.replace({"solver.method": "reduced", "solver.load_patch": patch}))
    full = models["full"]
    pts = np.arange(full.n_samples)
    st = np.asarray(full.samples.stencil)
    own = np.cross(st[:, 3] - st[:, 2], st[:, 1] - st[:, 0])
    other = np.cross(st[:, 7] - st[:, 6], st[:, 5] - st[:, 4])
    own, other = (v / np.linalg.norm(v, axis=1, keepdims=True) for v in (own, other))
    second = np.linalg.norm(other - own, axis=1) > 1e-6  # a corner: the other side's normal too
    point = np.concatenate([pts, pts[second]])
    normal = np.concatenate([own, other[second]])
    X = np.asarray(full.samples.rest)[point]
    d = np.linalg.norm(X[:, None] - X[None], axis=-1)
    W = np.exp(-0.5 * (d / patch) ** 2) * (d <= 4 * patch) * (normal @ normal.T > 0.5)
    W /= W.sum(axis=0)
    L = np.zeros((3 * pts.size, point.size))  # the patch loads on the points' force components
    for a, (p, nrm) in enumerate(zip(point, normal, strict=True)):
        L[3 * p : 3 * p + 3, a] = nrm
    L = L @ W
    c_full = np.einsum("ij,ij->j", L, _full_compliance(asm, full, pts) @ L)
    c_red = np.einsum("ij,ij->j", L, _socket_compliance(reduced, pts) @ L)
    # The interface shapes lose at most tol/2 of a load's compliance and the contact segment's
    # interior at most tol (energy norms), so the whole basis at most (sqrt(1/2) + 1)^2 tol.
    tol = scene["solver"]["hsv_tolerance"]
    assert np.max(1 - c_red / c_full) < (0.5**0.5 + 1) ** 2 * tol
    assert np.all(c_red <= c_full * (1 + 1e-9))
    assert reduced.part.orders[1] < models["reduced"].part.orders[1]


def test_segmented_tends_to_the_full_model_as_the_coupling_stiffens(models, asm):
    full, seg = models["full"], models["segmented"]
    pts = np.arange(0, full.n_samples, 7)
    C0 = _full_compliance(asm, full, pts)
    errs = [
        np.linalg.norm(_socket_compliance(seg, pts, kc) - C0) / np.linalg.norm(C0) for kc in (1e2, 1e4, 1e6)
    ]
    assert errs[0] > 1e-2 and errs[2] < 1e-4
    assert errs[1] < errs[0] / 30 and errs[2] < errs[1] / 30  # ~ 1 / k_c


@pytest.fixture(scope="module")
def rollouts(models):
    return {m: jsnap.rollout(models[m]) for m in ("full", "reduced")}


def test_reduced_insertion_force_follows_the_full_model(models, rollouts):
    """Up to the snap (a knife edge: a stiffness change of 1e-3 moves it by a step), the reduced
    insertion force follows the full model's within the tolerance; the peak within 2%."""
    F0 = np.asarray(rollouts["full"].insertion_force)
    F = np.asarray(rollouts["reduced"].insertion_force)
    ramp = slice(0, int(np.argmax(F0)) - 5)
    assert np.abs(F[ramp] - F0[ramp]).max() < 1e-2 * F0.max()
    assert F.max() == pytest.approx(F0.max(), rel=2e-2)
    assert models["reduced"].n_dof < models["full"].n_dof / 4


def test_reduced_rollout_is_passive_and_its_base_wrench_balances_contact(rollouts):
    res = rollouts["reduced"]
    E = np.asarray(res.energy)
    W = np.cumsum(np.asarray(res.work))
    assert E.max() > 0.3  # the hook really was bent (N mm)
    assert np.all(E <= W + 1e-6 * E.max())  # the socket never holds more than the plug put in
    contact = np.asarray(res.contact_force).sum(axis=1)
    base = np.asarray(res.base_force)
    assert np.abs(base + contact).max() < 2e-2 * np.abs(contact).max()


def test_free_displacement_reconstructs_the_static_deflection(models, asm, x64):
    """A unit normal force at a hook point: the reduced model's reconstructed displacement field
    matches the full model's static one."""
    full, red = models["full"], models["reduced"]
    p = int(np.argmax(np.asarray(full.samples.rest)[:, 2]))  # the hook's top
    n = _normals(full, [p])[0]
    lam, mu = lame(float(full.params.E), float(full.params.nu))
    f = asm.free
    K = (lam * asm.K_lam + mu * asm.K_mu)[f][:, f].tocsc()
    s = full.part
    load = np.zeros(f.size)
    for k in range(s.sample_nodes.shape[1]):
        load[3 * int(s.sample_nodes[p, k]) + np.arange(3)] += float(s.sample_weights[p, k]) * n
    u = spla.splu(K).solve(load)
    r = red.part
    Kr = np.asarray(r.stiffness(red.params.material))
    J = np.einsum("k,kdr->dr", np.asarray(r.sample_weights[p]), np.asarray(r.node_rows[r.sample_nodes[p]]))
    z = np.linalg.solve(Kr, J.T @ n)
    u_r = np.asarray(r.free_displacement(jnp.asarray(z)))
    assert np.linalg.norm(u_r - u) < 0.02 * np.linalg.norm(u)


def test_gradient_wrt_youngs_modulus_through_a_reduced_rollout(models, x64):
    """V is held fixed: E enters only through prepare (lambda, mu times stored blocks), so the
    gradient of a contact rollout is exact; checked against central differences (JAX
    transformations of jsnap calls run in 64-bit mode: the ``x64`` fixture)."""
    # A short, cheap rollout; the gradient differentiates the solver's own 60 iterations
    # ("unrolled", APGD(implicit=False)): exact for what the rollout computes (the implicit mode
    # differentiates the converged solution, which 60 iterations only approach).
    red = models["reduced"]
    solver = APGD(max_iters=60, tol=red.contact.solver.tol, implicit=False)
    red = eqx.tree_at(lambda m: m.contact.solver, red, solver)
    controls = red.trajectory()[1:13]  # on the ramp, in contact from the first step

    @jax.jit
    @jax.value_and_grad
    def loss(E):
        return jnp.mean(jsnap.rollout(red, red.params.replace(E=E), controls=controls).insertion_force)

    E0, h = 2200.0, 2.2
    value, g = loss(jnp.asarray(E0))
    fd = (float(loss(jnp.asarray(E0 + h))[0]) - float(loss(jnp.asarray(E0 - h))[0])) / (2 * h)
    assert float(value) > 0.1 and float(g) > 0  # in contact; a stiffer hook resists more
    assert float(g) == pytest.approx(fd, rel=1e-4)


def test_reduced_model_is_cached_and_a_corrupt_file_is_rebuilt(built, scene, cache):
    red, report = built["reduced"]
    info = report.reduction
    path = info["path"]
    red_scene = scene.replace({"solver.method": "reduced"})
    again, again_report = build_model(red_scene)
    assert again_report.reduction["cached"] and again_report.reduction["path"] == path
    assert np.array_equal(np.asarray(again.part.kl), np.asarray(red.part.kl))
    _arrays, meta = _cache.load_artefact(path, "reduced", key=info["key"])
    assert meta["orders"] == list(red.part.orders)
    assert (meta["kind"], meta["key"]) == ("reduced", info["key"])  # the file says what it is
    # Corrupt the file: it is reported and rebuilt, never used.
    raw = bytearray(open(path, "rb").read())
    raw[len(raw) // 4 : 3 * len(raw) // 4] = b"\0" * (3 * len(raw) // 4 - len(raw) // 4)  # array data
    open(path, "wb").write(bytes(raw))
    with pytest.raises(_cache.ArtefactError, match=r"corrupt|unreadable|checksum"):
        _cache.load_artefact(path, "reduced")
    with pytest.warns(UserWarning, match="not using it: the reduced model is made again"):
        rebuilt, rebuilt_report = build_model(red_scene)
    assert not rebuilt_report.reduction["cached"]
    # The rebuilt basis may differ by a change of coordinates (ARPACK's start vector), so the
    # check is on invariants: the reduced model's generalised eigenvalues.
    import scipy.linalg

    def spectrum(part):
        k = np.asarray(part.kl) + np.asarray(part.km)
        return scipy.linalg.eigh(k, np.asarray(part.m1), eigvals_only=True)

    assert rebuilt.part.orders == red.part.orders
    ref = spectrum(red.part)
    np.testing.assert_allclose(spectrum(rebuilt.part), ref, rtol=1e-6, atol=1e-9 * np.abs(ref).max())
    _cache.load_artefact(path, "reduced", key=info["key"])  # valid again


def test_reduced_file_checks(built, tmp_path, monkeypatch):
    """A reduced model's file is refused (ArtefactError) when it was made for another key, is
    of another kind, was altered, is of another format version or is not a file of ours; its
    arrays must be of the order its metadata states."""
    info = built["reduced"][1].reduction
    key = info["key"]
    arrays, meta = _cache.load_artefact(info["path"], "reduced")
    good = _cache.save_artefact(tmp_path / "m.npz", "reduced", key, meta, arrays)
    _cache.load_artefact(good, "reduced", key=key)
    with pytest.raises(_cache.ArtefactError, match="made for something else"):
        _cache.load_artefact(good, "reduced", key="0" * 64)
    with pytest.raises(_cache.ArtefactError, match="a 'reduced' artefact, not 'modal'"):
        _cache.load_artefact(good, "modal", key=key)
    with pytest.raises(_cache.ArtefactError, match="not of order"):
        R._check_arrays(dict(arrays, kl=arrays["kl"][:-1, :-1]), meta)
    tampered = dict(arrays, kl=arrays["kl"] * 1.01)
    np.savez(tmp_path / "t.npz", **{k: v for k, v in np.load(good).items() if k not in tampered}, **tampered)
    with pytest.raises(_cache.ArtefactError, match="checksum mismatch"):
        _cache.load_artefact(tmp_path / "t.npz", "reduced")
    monkeypatch.setattr(_cache, "FORMAT_VERSION", _cache.FORMAT_VERSION + 1)
    with pytest.raises(_cache.ArtefactError, match="format version"):
        _cache.load_artefact(good, "reduced")
    (tmp_path / "x.npz").write_bytes(b"not a zip file")
    with pytest.raises(_cache.ArtefactError, match="unreadable"):
        _cache.load_artefact(tmp_path / "x.npz", "reduced")
    with pytest.raises(FileNotFoundError):
        _cache.load_artefact(tmp_path / "missing.npz", "reduced")


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"solver.hsv_tolerance": 0.0}, r"solver\.hsv_tolerance = 0\.0: must be in \(0, 1\)"),
        ({"solver.hsv_tolerance": 1.5}, r"solver\.hsv_tolerance = 1\.5"),
        ({"solver.subspace_modes": 0}, r"solver\.subspace_modes = 0: must be >= 1"),
        ({"solver.segments": 0}, r"solver\.segments = 0"),
        ({"solver.segment_margin": -1.0}, r"solver\.segment_margin = -1\.0: must be >= 0"),
        ({"solver.interface_stiffness": 0.0}, r"solver\.interface_stiffness = 0\.0: must be > 0"),
        ({"solver.interface_damping": -1.0}, r"solver\.interface_damping = -1\.0: must be >= 0"),
        ({"solver.segments": 1.5}, r"solver\.segments = 1\.5: must be an integer"),
        ({"solver.load_patch": -0.1}, r"solver\.load_patch = -0\.1: must be >= 0"),
    ],
)
def test_bad_reduction_keys_name_the_key(change, match):
    # solver.hsv_tolerance and solver.load_patch are scene keys; the others are internal (tests
    # and benchmarks).
    with pytest.raises(SceneError, match=match):
        with_internal(jsnap.load_scene(), change)


def test_a_margin_that_swallows_the_socket_is_an_error(scene, cache):
    scene = with_internal(scene.replace({"solver.method": "segmented"}), {"solver.segment_margin": 50.0})
    with pytest.raises(
        ValueError, match=r"solver\.segment_margin = 50\.0: the contact segment holds the whole"
    ):
        jsnap.build(scene)
