"""Large parts: the sparse factorisations and Schur complements of jsnap/_build/linalg.py against
dense linear algebra, the reduction's interface shapes (condensed segment by segment) against
the full model's dense flexibility, the contact points' location against a brute-force search,
and the memory guard (jsnap/_build/memory.py): a build that would not fit is refused, naming
the setting to change, before the allocation is attempted.

Small meshes (P2, 2.0 mm, 780 free dofs) keep these fast; the sizes that motivate them are
measured by benchmarks/scale.py.
"""

import numpy as np
import pytest
import scipy.linalg as sla

import jsnap
from jsnap._build import linalg, memory
from jsnap._build import model as build_module
from jsnap._build import reduce as R
from jsnap._build.fem import assemble, lame
from jsnap._build.memory import BuildError
from jsnap._build.samples import locate_on_faces, reachable_faces, section_samples
from jsnap._geometry.cantilever import mesh_cantilever
from jsnap._geometry.presets import default_rigid
from jsnap._geometry.scene import connector_geometry, motion_stroke

SMALL = {"solver.mesh_size": 2.0, "contact.width_spacing": 2.0}
E, NU = 2200.0, 0.35


@pytest.fixture(scope="module")
def scene():
    return jsnap.load_scene().replace(SMALL)


@pytest.fixture(scope="module")
def asm(scene):
    return assemble(mesh_cantilever(connector_geometry(scene), scene["solver"]["mesh_size"]), "P2")


def _stiffness(asm, dofs=None):
    lam, mu = lame(E, NU)
    K = (lam * asm.K_lam + mu * asm.K_mu).tocsr()
    dofs = asm.free if dofs is None else dofs
    return K[dofs][:, dofs].tocsc()


def test_factor_solves_like_dense(asm):
    K = _stiffness(asm)
    rng = np.random.default_rng(0)
    b = rng.standard_normal((K.shape[0], 5))
    x = linalg.factor(K, "the test matrix", "nothing").solve(b)
    ref = sla.solve(K.toarray(), b, assume_a="pos")
    assert np.abs(x - ref).max() <= 1e-10 * np.abs(ref).max()


def test_node_ordering_estimates_the_fill_it_gives(asm):
    """The fill predicted from the node graph (what the memory guard checks) is the factor's."""
    K = _stiffness(asm)
    perm, nnz = linalg.node_ordering(K)
    assert np.array_equal(np.sort(perm), np.arange(K.shape[0]))
    lu = linalg.Factor(K, perm).lu
    actual = lu.L.nnz + lu.U.nnz
    assert 0.9 * actual <= nnz <= 1.2 * actual


@pytest.mark.parametrize("floating", [False, True])
def test_schur_complement_against_dense(asm, floating):
    """Onto scattered nodes, of the clamped part and of the unclamped (singular) one, whose
    Schur complement onto a set holding it is still defined: positive semidefinite with the six
    rigid motions in its null space."""
    dofs = np.arange(asm.n_dof) if floating else asm.free
    K = _stiffness(asm, dofs)
    n_nodes = K.shape[0] // 3
    keep = np.random.default_rng(1).choice(n_nodes, size=40, replace=False)
    S = linalg.schur_complement(K, keep, "the test matrix", "nothing")
    w = (3 * keep[:, None] + np.arange(3)).ravel()
    r = np.setdiff1d(np.arange(K.shape[0]), w)
    Kd = K.toarray()
    ref = Kd[np.ix_(w, w)] - Kd[np.ix_(w, r)] @ sla.solve(Kd[np.ix_(r, r)], Kd[np.ix_(r, w)], assume_a="pos")
    assert np.abs(S - ref).max() <= 1e-9 * np.abs(ref).max()
    if floating:
        rigid = R._rigid_shapes(asm.nodes[dofs[0::3] // 3][keep])
        assert np.abs(S @ rigid).max() <= 1e-8 * np.abs(S).max() * np.abs(rigid).max()


def test_interface_shapes_condensed_by_segment_equal_the_full_model(scene, asm):
    """The contact compliance and the interface shapes from the segments' Schur complements are
    the full model's, computed here from its dense inverse (the construction the segment-wise one
    replaces: unit loads at every contact and interface dof)."""
    from jsnap._build.model import _contact_candidates, _geometry

    g = _geometry(scene)
    g.mesh = asm.mesh  # the assembly's own mesh (the same cantilever)
    _, sample, _, seeds, normals = _contact_candidates(scene, g, asm)
    seg = R.segment(asm, seeds, 1.0, 1)
    blocks = [R.segment_blocks(asm, seg, i)[0] for i in range(seg.n_segments)]
    free = asm.free
    cnodes, Jn = R._contact_interp((free[0::3] // 3)[sample[0]], sample[1])
    cases = R._normal_loads(Jn, normals.reshape(Jn.shape[0], -1, 3))
    tol = 1e-2
    factor = R._load_factor(Jn)
    gamma, psi, compliance, gain = R.interface_shapes(asm, seg, blocks, lame(E, NU), cnodes, cases, factor, tol)

    # Dense reference on the full model's free dofs.
    pos = -np.ones(asm.n_dof, dtype=np.int64)
    pos[free] = np.arange(free.size)
    c = pos[(3 * cnodes[:, None] + np.arange(3)).ravel()]
    g = pos[(3 * gamma[:, None] + np.arange(3)).ravel()]
    Kinv = np.linalg.inv(_stiffness(asm).toarray())
    C = Kinv[np.ix_(c, c)]
    ref = np.einsum("aq,ab,bq->q", cases, C, cases)
    assert np.abs(compliance / ref - 1).max() < 1e-8
    # The whole part's largest static gain, the contact segment's truncation reference.
    B = np.kron(factor, np.eye(3))
    assert gain == pytest.approx(np.linalg.eigvalsh(B.T @ C @ B)[-1], rel=1e-8)
    F = Kinv[np.ix_(g, g)]
    S_G = np.linalg.inv(0.5 * (F + F.T))
    traces = Kinv[np.ix_(g, c)] @ cases
    # Every case's compliance lost by restricting the interface to the shapes is within tol.
    P = psi @ np.linalg.solve(psi.T @ S_G @ psi, psi.T @ S_G)
    resid = traces - P @ traces
    lost = np.einsum("an,ab,bn->n", resid, S_G, resid)
    assert np.all(lost <= tol * ref * (1 + 1e-6))
    # and the greedy choice is the same as with the dense S_G
    ref_psi = np.linalg.qr(
        np.concatenate(
            [
                np.linalg.qr(R._rigid_shapes(asm.nodes[gamma]))[0],
                R._greedy_energy(traces, S_G, np.linalg.qr(R._rigid_shapes(asm.nodes[gamma]))[0], ref, tol),
            ],
            axis=1,
        )
    )[0]
    assert psi.shape == ref_psi.shape
    assert np.abs(psi @ psi.T - ref_psi @ ref_psi.T).max() < 1e-6


def test_contact_points_located_as_by_brute_force(scene, asm):
    """The k-d tree's candidate faces give the faces, nodes and weights that testing every point
    against every face gives (an independent search, written out here)."""
    geom = connector_geometry(scene)
    plug = default_rigid("cantilever", scene["connector"], scene["plug"])
    lo, hi = plug.start - plug.half - 1.0, plug.start + plug.half + 1.0
    lo[2] -= motion_stroke(scene)
    faces = reachable_faces(asm.mesh, lo, hi)
    X, normals, *_ = section_samples(geom, lo, hi, 0.05, 1.0)
    nodes, weights, owner = locate_on_faces(asm, faces, X, normals[:, 0])
    pts = asm.mesh.points
    for i in range(0, len(X), 7):
        best, best_align = None, -np.inf
        for f, tri in enumerate(pts[faces]):
            n = np.cross(tri[1] - tri[0], tri[2] - tri[0])
            a2 = np.linalg.norm(n)
            lam = np.linalg.lstsq(np.stack([tri[1] - tri[0], tri[2] - tri[0]], 1), X[i] - tri[0], rcond=None)[0]
            bary = np.array([1 - lam.sum(), *lam])
            on = abs((X[i] - tri[0]) @ n) / a2 < 1e-7 and bary.min() > -1e-7 / np.sqrt(a2)
            if on and normals[i, 0] @ n / a2 > best_align + 1e-12:
                best, best_align = f, normals[i, 0] @ n / a2
        assert best is not None
        plane = pts[faces[best]].mean(0) @ normals[i, 0]  # coplanar faces are equally good
        assert np.isclose(pts[faces[owner[i]]].mean(0) @ normals[i, 0], plane)
        x = np.einsum("k,kd->d", weights[i], asm.nodes[nodes[i]])
        assert np.allclose(x, X[i], atol=1e-9)


# --------------------------------------------------------------------------------------------
# The memory guard
# --------------------------------------------------------------------------------------------


def test_a_dense_model_of_a_large_part_is_refused_before_assembly(monkeypatch):
    """The design guide's worked hook (58 725 dof at the default mesh) as a full model needs
    ~154 GiB: refused after meshing, before assembly, naming solver.method and the mesh."""
    scene = jsnap.load_scene().replace(
        {
            "connector.length": 19.0,
            "connector.thickness": 3.28,
            "connector.tip_thickness": 1.64,
            "connector.width": 9.5,
            "connector.undercut": 2.4,
            "solver.method": "full",
        }
    )
    # 100 GiB: the estimate made before meshing (a lower bound, ~35k dofs, ~55 GiB) fits, so the
    # count of the mesh itself refuses it. 16 GiB: refused before meshing, from the estimate.
    for where in (memory, build_module):
        monkeypatch.setattr(where, "available_memory", lambda: 100 * 2**30)

    def no_assembly(*a, **k):
        raise AssertionError("assembled before the memory check")

    monkeypatch.setattr(build_module, "assemble", no_assembly)
    with pytest.raises(BuildError, match=r"solver\.method = 'full' with 58725 dof needs about 15\d\.\d GiB.*"
                       r"solver\.method = 'reduced'.*solver\.mesh_size"):  # fmt: skip
        build_module.build_model(scene)
    for where in (memory, build_module):
        monkeypatch.setattr(where, "available_memory", lambda: 16 * 2**30)
    before = r"estimated before meshing.*solver\.method = 'full'.*solver\.mesh_size"
    with pytest.raises(BuildError, match=before):
        build_module.build_model(scene)


def test_reduced_estimate_is_linear_in_the_dofs():
    """The reduced build has no n x n array: its up-front estimate grows with n, not n^2."""
    a = build_module.check_memory(10_000, "reduced", available=2**40)
    b = build_module.check_memory(100_000, "reduced", available=2**40)
    assert b == pytest.approx(10 * a)
    with pytest.raises(BuildError, match=r"solver\.method = 'reduced' with 100000 dof.*solver\.mesh_size"):
        build_module.check_memory(100_000, "reduced", available=b)


@pytest.mark.parametrize("kind", ["factor", "schur"])
def test_a_factorisation_that_would_not_fit_is_refused_before_it_is_made(asm, monkeypatch, kind):
    """With the available memory below the estimated fill, the sparse factorisation of the dof
    matrix is never attempted (only the cheap node-graph one that gives the estimate)."""
    K = _stiffness(asm)
    _, nnz = linalg.node_ordering(K)
    monkeypatch.setattr(memory, "available_memory", lambda: nnz)  # less than 12 bytes a nonzero
    sizes = []
    real = linalg.spla.splu

    def spy(A, *a, **k):
        sizes.append(A.shape[0])
        return real(A, *a, **k)

    monkeypatch.setattr(linalg.spla, "splu", spy)
    with pytest.raises(BuildError, match=r"solver\.mesh_size"):
        if kind == "factor":
            R._factor(K)
        else:
            linalg.schur_complement(K, np.arange(5), "segment 0", R._MESH_HINT)
    assert sizes and max(sizes) < K.shape[0]  # node graphs only
