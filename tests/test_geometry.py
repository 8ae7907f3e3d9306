"""Tests of the cantilever geometry, its structured tetrahedral mesh, mesh quality and VTU export.

Facts checked against are independent of the code under test: hand-derived areas and perimeters
of the section, the section of the CalculiX reference (refs/calculix-cantilever), face counting
for conformity, the divergence theorem for outward normals, and meshio's own reader.
"""

import itertools
import math
import xml.etree.ElementTree as ET

import meshio
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jsnap._geometry.cantilever import Cantilever, mesh_box, mesh_cantilever
from jsnap._geometry.mesh import (
    MeshQualityError,
    TetMesh,
    check_quality,
    mean_ratio,
    write_vtu,
    write_vtu_series,
)

DEFAULT = dict(
    length=10.0,
    thickness=1.2,
    width=4.0,
    undercut=0.8,
    lead_angle=30.0,
    return_angle=90.0,
    flat=0.1144,
)
GEOMETRIES = {
    "default": DEFAULT,
    "tapered": {**DEFAULT, "tip_thickness": 0.6},
    "return60": {**DEFAULT, "return_angle": 60.0},
    "sharp_flat0": {**DEFAULT, "flat": 0.0, "return_angle": 45.0},
}
EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])


def cantilever(**kw) -> Cantilever:
    return Cantilever(**{**DEFAULT, **kw})


def hand_area(g: Cantilever) -> float:
    """Section area from its three pieces: arm trapezoid, body rectangle, hook trapezoid (its
    parallel sides are vertical: z_top − L at x = h_tip and the flat at x = h_tip + y_u)."""
    h, ht, L = g.thickness, g.h_tip, g.length
    hook_height = g.z_top - L
    return 0.5 * (h + ht) * L + ht * hook_height + 0.5 * g.undercut * (hook_height + g.flat)


def hand_perimeter(g: Cantilever) -> float:
    a, a_ret = math.radians(g.lead_angle), math.radians(g.return_angle)
    return (
        g.thickness  # base
        + math.hypot(g.thickness - g.h_tip, g.length)  # outer face
        + g.undercut / math.sin(a_ret)  # retention face
        + g.flat
        + g.undercut / math.sin(a)  # lead ramp
        + g.h_tip  # top face
        + g.z_top  # inner face x = 0
    )


def edge_lengths(mesh: TetMesh, in_plane: bool = False) -> np.ndarray:
    p = mesh.points[mesh.cells]
    e = p[:, EDGES[:, 1]] - p[:, EDGES[:, 0]]
    if in_plane:
        e = e[..., [0, 2]]
    return np.sqrt(np.sum(e * e, axis=-1))


# ---------------------------------------------------------------------------- geometry


def test_default_section_is_the_calculix_reference():
    # refs/calculix-cantilever/README.md lists this polygon for flat = 0.114359.
    g = cantilever(flat=0.114359)
    ref = [(0, 0), (1.2, 0), (1.2, 10), (2.0, 10), (2.0, 10.114359), (1.2, 11.5), (0, 11.5)]
    np.testing.assert_allclose(g.section(), ref, atol=1e-6)
    assert g.z_top == pytest.approx(11.5, abs=1e-6)
    assert cantilever().z_top == pytest.approx(11.5, abs=1e-4)
    assert g.h_tip == 1.2 and g.z_retention == 10.0


def test_return_angle_raises_retention_edge():
    g = cantilever(return_angle=60.0, tip_thickness=0.6)
    assert g.z_retention == pytest.approx(10.0 + 0.8 / math.tan(math.radians(60.0)))
    assert g.z_flat_end == pytest.approx(g.z_retention + 0.1144)
    assert g.z_top == pytest.approx(g.z_flat_end + 0.8 * math.sqrt(3.0))
    assert g.section()[3] == pytest.approx([0.6 + 0.8, g.z_retention])


@pytest.mark.parametrize("name", GEOMETRIES)
def test_volume_and_surface_area_match_hand_formulas(name):
    g = Cantilever(**GEOMETRIES[name])
    assert g.volume() == pytest.approx(hand_area(g) * g.width, rel=1e-13)
    expected = 2 * hand_area(g) + hand_perimeter(g) * g.width
    assert g.surface_area() == pytest.approx(expected, rel=1e-13)


@settings(max_examples=150, deadline=None)
@given(
    length=st.floats(0.5, 50),
    thickness=st.floats(0.1, 5),
    taper=st.floats(0.05, 4),
    undercut=st.floats(0.01, 20),
    lead=st.floats(1, 89),
    ret=st.floats(1, 90),
    flat=st.floats(0, 5),
)
def test_valid_parameters_give_a_simple_ccw_section(length, thickness, taper, undercut, lead, ret, flat):
    # The docstring claims only ranges need checking: every valid parameter set gives a simple,
    # counter-clockwise polygon. Check it: positive area, no two non-adjacent edges meet.
    g = Cantilever(length, thickness, 4.0, undercut, lead, ret, flat, taper * thickness)
    p = g.section()
    assert g.section_area() > 0
    n = len(p)

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    for i in range(n):
        for j in range(i + 2, n):
            if i == 0 and j == n - 1:
                continue  # adjacent through the wrap-around
            a, b, c, d = p[i], p[(i + 1) % n], p[j], p[(j + 1) % n]
            proper = cross(a, b, c) * cross(a, b, d) < 0 and cross(c, d, a) * cross(c, d, b) < 0
            assert not proper, (i, j)
    # Each piece is non-degenerate and the hook really protrudes.
    assert g.z_retention >= g.length and g.z_top > g.z_flat_end >= g.z_retention


# ---------------------------------------------------------------------------- validation


@pytest.mark.parametrize(
    ("change", "pattern"),
    [
        ({"undercut": -0.2}, r"^connector\.undercut = -0\.2: must be > 0$"),
        ({"length": 0.0}, r"^connector\.length = 0\.0: must be > 0"),
        ({"thickness": float("nan")}, r"^connector\.thickness = nan: must be a finite number"),
        ({"width": float("inf")}, r"^connector\.width = inf: must be a finite number"),
        ({"width": "4"}, r"^connector\.width = '4': must be a finite number"),
        ({"length": True}, r"^connector\.length = True"),
        ({"tip_thickness": 4.81}, r"^connector\.tip_thickness = 4\.81: must be in \(0, 4"),
        ({"tip_thickness": 0.0}, r"^connector\.tip_thickness = 0\.0"),
        ({"lead_angle": 90.0}, r"^connector\.lead_angle = 90\.0: must be in \(0, 90\)"),
        ({"lead_angle": 0.0}, r"^connector\.lead_angle = 0\.0"),
        ({"return_angle": 90.5}, r"^connector\.return_angle = 90\.5: must be in \(0, 90\]"),
        ({"return_angle": -30.0}, r"^connector\.return_angle = -30\.0"),
        ({"flat": -0.01}, r"^connector\.flat = -0\.01: must be >= 0"),
        # tan(angle) underflows to 0: the hook would be infinitely tall.
        ({"lead_angle": 1e-320}, r"^connector\.lead_angle = 1e-320: too close to 0"),
        ({"return_angle": 1e-320}, r"^connector\.return_angle = 1e-320: too close to 0"),
        # The ramp's height y_u / tan(alpha) vanishes next to z in floating point.
        ({"lead_angle": 89.99999999999999}, r"^connector\.lead_angle = .*too close to 90"),
    ],
)
def test_invalid_values_name_the_scene_key(change, pattern):
    with pytest.raises(ValueError, match=pattern):
        cantilever(**change)


@pytest.mark.parametrize(
    "change",
    [
        {"return_angle": 90.0},
        {"flat": 0.0},
        {"tip_thickness": 4.8},  # exactly 4 h
        {"undercut": 15.0},  # hook taller than the arm is long: odd, but a valid section
        {"return_angle": 5.0},
        {"length": 1, "thickness": 2, "width": 3, "undercut": 1, "lead_angle": 45},  # ints
    ],
)
def test_edge_of_range_values_are_accepted(change):
    g = cantilever(**change)
    assert g.volume() > 0


# ---------------------------------------------------------------------------- cantilever mesh


@pytest.fixture(scope="module", params=list(GEOMETRIES))
def geom_mesh(request):
    g = Cantilever(**GEOMETRIES[request.param])
    return g, mesh_cantilever(g, size=0.5, hook_size=0.2)


def test_mesh_volume_and_surface_area_are_exact(geom_mesh):
    g, mesh = geom_mesh
    assert mesh.volumes().sum() == pytest.approx(hand_area(g) * g.width, rel=1e-12)
    expected = 2 * hand_area(g) + hand_perimeter(g) * g.width
    assert mesh.boundary_face_areas().sum() == pytest.approx(expected, rel=1e-12)


def test_mesh_types_and_positive_orientation(geom_mesh):
    _, mesh = geom_mesh
    assert mesh.points.dtype == np.float64 and mesh.points.shape[1] == 3
    assert mesh.cells.dtype == np.int64 and mesh.cells.shape[1] == 4
    assert mesh.base_nodes.dtype == np.int64
    # Right-handed (p1 - p0, p2 - p0, p3 - p0), computed here without the module's helper.
    p = mesh.points[mesh.cells]
    det = np.linalg.det(np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], 1))
    assert np.all(det > 0)
    # Every node is used, none is duplicated.
    assert np.array_equal(np.unique(mesh.cells), np.arange(len(mesh.points)))
    assert len(np.unique(mesh.points, axis=0)) == len(mesh.points)
    rounded = np.round(mesh.points / 1e-9).astype(np.int64)
    assert len(np.unique(rounded, axis=0)) == len(mesh.points)


def test_mesh_is_conforming_and_its_boundary_is_the_analytic_one(geom_mesh):
    g, mesh = geom_mesh
    faces = np.sort(mesh.cells[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3), 1)
    _, counts = np.unique(faces, axis=0, return_counts=True)
    assert set(counts.tolist()) <= {1, 2}
    bfaces = mesh.boundary_faces()
    assert len(bfaces) == np.sum(counts == 1)

    # Each boundary triangle lies (all three vertices) on y = ±b/2 or on one polygon edge,
    # and its right-hand normal points out of that plane/edge.
    p = mesh.points[bfaces]  # (f, 3, 3)
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    on_side = np.zeros(len(bfaces), dtype=bool)
    for sign in (-1.0, 1.0):
        hit = np.all(np.abs(p[:, :, 1] - sign * g.width / 2) < 1e-12, axis=1)
        assert np.all(sign * normal[hit, 1] > 0)
        on_side |= hit
    poly = g.section()
    on_edge = np.zeros(len(bfaces), dtype=bool)
    for a, b in zip(poly, np.roll(poly, -1, axis=0), strict=True):
        t = b - a
        if not t.any():
            continue  # the flat of length 0
        out = np.array([t[1], -t[0]]) / np.linalg.norm(t)  # outward for a CCW polygon
        xz = p[:, :, [0, 2]] - a
        dist = np.abs(xz @ out)
        along = (xz @ t) / (t @ t)
        hit = np.all((dist < 1e-12) & (along > -1e-12) & (along < 1 + 1e-12), axis=1)
        assert np.all(normal[hit][:, [0, 2]] @ out > 0)
        on_edge |= hit
    assert np.all(on_side | on_edge)


def test_boundary_normals_point_out_by_the_divergence_theorem(geom_mesh):
    # V = (1/3) ∮ x · n dA: holds only if every boundary normal points outwards.
    _, mesh = geom_mesh
    p = mesh.points[mesh.boundary_faces()]
    area_normal = 0.5 * np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    flux = np.sum(area_normal * p.mean(axis=1)) / 3.0
    assert flux == pytest.approx(mesh.volumes().sum(), rel=1e-12)


def test_boundary_faces_of_a_single_tet_point_away_from_the_fourth_vertex():
    # The Kuhn meshes only ever expose two of a tetrahedron's four faces; test all four, for
    # every positively oriented vertex order (the 12 even permutations).
    points = np.array([[0, 0, 0], [2, 0, 0], [0, 1, 0], [0.2, 0.3, 1.5]])
    for perm in itertools.permutations(range(4)):
        cells = np.array([perm])
        if np.linalg.det(points[list(perm[1:])] - points[perm[0]]) < 0:
            continue
        faces = TetMesh(points, cells, np.array([0])).boundary_faces()
        assert len(faces) == 4
        for f in faces:
            (opposite,) = points[np.setdiff1d(np.arange(4), f)]
            normal = np.cross(points[f[1]] - points[f[0]], points[f[2]] - points[f[0]])
            assert normal @ (points[f[0]] - opposite) > 0


def test_base_nodes_are_the_nodes_on_z0():
    # size 0.5: the base (x in [0, 1.2]) has ceil(1.2 / 0.5) = 3 divisions -> 4 nodes, the
    # width ceil(4 / 0.5) = 8 layers -> 9 node rows.
    for change in ({}, {"tip_thickness": 0.6}, {"return_angle": 60.0}):
        mesh = mesh_cantilever(cantilever(**change), size=0.5, hook_size=0.2)
        expected = np.flatnonzero(mesh.points[:, 2] == 0.0)
        np.testing.assert_array_equal(mesh.base_nodes, expected)
        assert len(mesh.base_nodes) == 4 * 9
        base = mesh.points[mesh.base_nodes]
        assert base[:, 0].min() == 0 and base[:, 0].max() == 1.2
        assert base[:, 1].min() == -2 and base[:, 1].max() == 2


def test_refinement_shrinks_edges_and_hook_size_acts_only_at_the_hook():
    g = cantilever()
    longest = []
    for size in (1.0, 0.5, 0.25):
        mesh = mesh_cantilever(g, size)
        longest.append(edge_lengths(mesh).max())
        # Arm elements are cut from hexahedra with sides <= size: edges <= the hex diagonal.
        assert longest[-1] <= math.sqrt(3) * size * (1 + 1e-12)
    assert longest[0] > longest[1] > longest[2]

    coarse = mesh_cantilever(g, 0.6, hook_size=0.3)
    fine = mesh_cantilever(g, 0.6, hook_size=0.1)
    for hook_size, mesh in ((0.3, coarse), (0.1, fine)):
        centroid = mesh.points[mesh.cells].mean(axis=1)
        in_hook = centroid[:, 0] > g.h_tip
        assert edge_lengths(mesh, in_plane=True)[in_hook].max() <= 1.5 * hook_size
    # Below z = L both meshes are the same.
    arm = [m.cells[m.points[m.cells].mean(axis=1)[:, 2] < g.length] for m in (coarse, fine)]
    assert len(arm[0]) == len(arm[1])
    np.testing.assert_array_equal(
        np.unique(coarse.points[arm[0].ravel()], axis=0),
        np.unique(fine.points[arm[1].ravel()], axis=0),
    )
    assert len(fine.cells) > 2 * len(coarse.cells)


@pytest.mark.parametrize("size", [1.0, 0.6, 0.3])
def test_default_meshes_pass_quality_with_margin(size):
    # check_quality (mean ratio >= 0.02) runs inside mesh_cantilever; demand 2.5x that.
    g = cantilever()
    for hook_size in (None, 0.2, 0.1, 0.05):
        if hook_size is not None and hook_size > size:
            continue
        mesh = mesh_cantilever(g, size, hook_size)
        assert mean_ratio(mesh.points, mesh.cells).min() >= 0.05, (size, hook_size)


def test_near_degenerate_geometry_is_rejected_by_the_mesher():
    # A valid section whose ramp is 1.4 um tall: no usable elements fit, and the mesher says so.
    with pytest.raises(MeshQualityError, match=r"^element \d+ \(nodes \[\d+ \d+ \d+ \d+\]\)"):
        mesh_cantilever(cantilever(lead_angle=89.9), size=0.5)


# ---------------------------------------------------------------------------- box mesh


def test_mesh_box_counts_volume_and_base():
    mesh = mesh_box(1.2, 4.0, 10.0, divisions=(2, 3, 5))
    assert mesh.points.shape == (3 * 4 * 6, 3)
    assert mesh.cells.shape == (6 * 2 * 3 * 5, 4)
    assert mesh.volumes().min() > 0
    assert mesh.volumes().sum() == pytest.approx(1.2 * 4.0 * 10.0, rel=1e-13)
    area = 2 * (1.2 * 4 + 1.2 * 10 + 4 * 10)
    assert mesh.boundary_face_areas().sum() == pytest.approx(area, rel=1e-13)
    assert len(mesh.base_nodes) == 3 * 4
    np.testing.assert_allclose(mesh.points.min(0), [0, -2, 0])
    np.testing.assert_allclose(mesh.points.max(0), [1.2, 2, 10])
    # size: ceil(l / size) per axis.
    assert mesh_box(1.2, 4.0, 10.0, size=0.5).cells.shape[0] == 6 * 3 * 8 * 20


# ---------------------------------------------------------------------------- quality check


def _two_tets():
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1.0]])
    return points, np.array([[0, 1, 2, 3], [1, 2, 3, 4]])


def test_check_quality_accepts_good_and_names_inverted_element():
    mesh = mesh_box(1, 1, 1, divisions=(2, 2, 2))
    check_quality(mesh.points, mesh.cells)  # no error
    cells = mesh.cells.copy()
    for bad in (30, 17):
        cells[bad] = cells[bad][[0, 2, 1, 3]]
    nodes = " ".join(str(n) for n in cells[17])
    vol = -1.0 / 48  # each Kuhn tetrahedron of a 0.5 mm cube
    pattern = (
        rf"^element 17 \(nodes \[{nodes}\]\) is inverted: signed volume {vol:.3e} mm\^3 "
        r"\(2 bad elements in all\)$"
    )
    with pytest.raises(MeshQualityError, match=pattern):
        check_quality(mesh.points, cells)
    assert issubclass(MeshQualityError, ValueError)


def test_check_quality_names_degenerate_and_poor_elements():
    points, cells = _two_tets()
    check_quality(points, cells)
    flat = points.copy()
    flat[4] = (flat[1] + flat[2] + flat[3]) / 3  # on the plane of nodes 1, 2, 3
    with pytest.raises(MeshQualityError, match=r"^element 1 \(nodes \[1 2 3 4\]\) is degenerate"):
        check_quality(flat, cells)
    sliver = points.copy()
    sliver[4] = (sliver[1] + sliver[2] + sliver[3]) / 3 + 3e-4  # just above it: q = 0.009
    with pytest.raises(MeshQualityError, match=r"^element 1 .*poor quality: mean ratio"):
        check_quality(sliver, cells)
    check_quality(sliver, cells, min_quality=1e-3)  # the threshold is honoured


# ---------------------------------------------------------------------------- VTU export


def test_write_vtu_round_trip_tetra(tmp_path):
    mesh = mesh_box(1, 2, 3, divisions=(1, 2, 2))
    u = np.random.default_rng(0).normal(size=mesh.points.shape)
    vol = mesh.volumes()
    path = write_vtu(tmp_path / "box.vtu", mesh.points, mesh.cells, {"u": u}, {"volume": vol})
    back = meshio.read(path)
    np.testing.assert_array_equal(back.points, mesh.points)
    assert [b.type for b in back.cells] == ["tetra"]
    np.testing.assert_array_equal(back.cells[0].data, mesh.cells)
    np.testing.assert_array_equal(back.point_data["u"], u)
    np.testing.assert_array_equal(back.cell_data["volume"][0], vol)


def test_write_vtu_round_trip_tetra10(tmp_path):
    mesh = mesh_box(1, 1, 1, divisions=(1, 1, 1))
    # Edge midpoints in VTK tetra10 order (01, 12, 02, 03, 13, 23), one node per edge.
    edges = np.sort(mesh.cells[:, EDGES].reshape(-1, 2), axis=1)
    uniq, inv = np.unique(edges, axis=0, return_inverse=True)
    points = np.vstack([mesh.points, mesh.points[uniq].mean(axis=1)])
    cells = np.hstack([mesh.cells, len(mesh.points) + inv.reshape(-1, 6)])
    path = write_vtu(tmp_path / "p2.vtu", points, cells, {"z": points[:, 2]})
    back = meshio.read(path)
    assert [b.type for b in back.cells] == ["tetra10"]
    np.testing.assert_array_equal(back.cells[0].data, cells)
    np.testing.assert_array_equal(back.points, points)
    np.testing.assert_array_equal(back.point_data["z"], points[:, 2])
    with pytest.raises(ValueError, match=r"\(m, 4\) or \(m, 10\)"):
        write_vtu(tmp_path / "bad.vtu", points, cells[:, :8])


def test_write_vtu_series_and_pvd(tmp_path):
    mesh = mesh_box(1, 1, 1, divisions=(1, 1, 2))
    times = np.array([0.0, 0.5e-3, 1e-3])
    u = np.stack([t * 100 * mesh.points for t in times])  # (T, n, 3)
    pvd = write_vtu_series(tmp_path / "out", "snap", mesh.points, mesh.cells, u, times)
    assert pvd == tmp_path / "out" / "snap.pvd"
    root = ET.parse(pvd).getroot()
    assert root.get("type") == "Collection"
    datasets = root.findall("./Collection/DataSet")
    assert [float(d.get("timestep")) for d in datasets] == times.tolist()
    assert [d.get("file") for d in datasets] == [f"snap_{k:04d}.vtu" for k in range(3)]
    for k, d in enumerate(datasets):
        back = meshio.read(pvd.parent / d.get("file"))
        np.testing.assert_array_equal(back.point_data["displacement"], u[k])
        np.testing.assert_array_equal(back.points, mesh.points)

    pvd = write_vtu_series(tmp_path, "def", mesh.points, mesh.cells, u, times, deformed=True)
    back = meshio.read(tmp_path / "def_0002.vtu")
    np.testing.assert_allclose(back.points, mesh.points + u[2])
    with pytest.raises(ValueError, match=r"displacements must be \(T, n, 3\)"):
        write_vtu_series(tmp_path, "bad", mesh.points, mesh.cells, u[:, :-1], times)
