"""The user's parts from files (host side): the deformable part as tetrahedra or a closed
surface tet-meshed here, with its fixed region; the rigid part as a closed surface.

Tetrahedra are read with meshio (any format it reads: Gmsh ``.msh``, VTK/VTU, Abaqus ``.inp``,
MED, ...); P2 files (``tetra10``) give their corner nodes and the P2 element is rebuilt on the
straight edges. Closed surfaces (STL, OBJ, PLY, ...) are read with trimesh and, for the deformable
part, tet-meshed with gmsh at ``solver.mesh_size``: gmsh is a maintained mesher with a Python
wheel on every platform, size control and a robust 3-D Delaunay; TetGen's Python binding is
AGPL and fTetWild has no wheel. Everything is converted to mm; every problem raises
:class:`PartError` naming the file and the scene key.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from jsnap._geometry.errors import SceneError
from jsnap._geometry.mesh import MeshQualityError, TetMesh, check_quality, signed_volumes
from jsnap._geometry.size import thinnest_wall

__all__ = [
    "UNITS",
    "PartError",
    "RigidSurface",
    "fixed_nodes",
    "load_part",
    "load_rigid",
    "part_thinnest_wall",
    "part_wall_thickness",
]

# Millimetres per unit of the files' coordinates.
UNITS = {"mm": 1.0, "m": 1000.0, "in": 25.4}
SURFACE_SUFFIXES = (".stl", ".obj", ".ply", ".off", ".glb", ".gltf")
# Snap-fit parts are millimetres to decimetres: a part outside [_SMALLEST, _LARGEST] mm after
# unit conversion was almost surely given in other units than declared.
_SMALLEST, _LARGEST = 0.05, 5000.0


class PartError(SceneError):
    """A part file that cannot be used; the message names the file and the scene key."""


def _check_size(points: np.ndarray, path: Path, key: str, units: str) -> None:
    size = float(np.linalg.norm(np.ptp(points, axis=0)))
    if not _SMALLEST <= size <= _LARGEST:
        guess = min(UNITS, key=lambda u: abs(np.log(size / UNITS[units] * UNITS[u] / 50.0)))
        raise PartError(
            f"{key} = {str(path)!r}: the part is {size:.4g} mm across with {key.split('.')[0]}.units = "
            f"{units!r}, outside the {_SMALLEST:g}-{_LARGEST:g} mm of snap-fit parts; are its "
            f"coordinates in {guess!r}?"
        )


def surface_volume(path, units: str = "mm") -> float:
    """The volume a closed surface file of the deformable part encloses, mm³ (the part before
    it is tet-meshed), read once per version of the file (its path, size and modification time).

    Raises:
        PartError: as :func:`load_part` for a surface it cannot use.
    """
    return _volume_of(*_file_version(path), units)


@functools.lru_cache(maxsize=32)
def _volume_of(path: str, size: int, mtime_ns: int, units: str) -> float:
    return float(_read_surface(Path(path), "part.mesh", units).volume)


def _read_surface(path: Path, key: str, units: str):
    import trimesh

    try:
        mesh = trimesh.load(path, force="mesh", process=True)
    except Exception as err:  # trimesh raises many types for unreadable files
        raise PartError(f"{key} = {str(path)!r}: cannot read the surface ({err})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise PartError(f"{key} = {str(path)!r}: no triangles in the file")
    mesh.apply_scale(UNITS[units])
    if not mesh.is_watertight:
        open_edges = int(np.sum(np.bincount(mesh.edges_unique_inverse) == 1))
        raise PartError(
            f"{key} = {str(path)!r}: the surface is not closed ({open_edges} edges belong to one "
            "triangle only): a solid needs a watertight surface"
        )
    if not mesh.is_winding_consistent:
        raise PartError(f"{key} = {str(path)!r}: the triangles' winding is inconsistent")
    if mesh.volume < 0:
        mesh.invert()
    _check_size(mesh.vertices, path, key, units)
    return mesh


def _tet_mesh_surface(surface, size: float, path: Path, key: str):
    """Tetrahedra filling a closed triangle surface (mm) at element size ``size`` (gmsh)."""
    import gmsh

    initialised = gmsh.isInitialized()
    if not initialised:
        gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("jsnap-part")
        tag = gmsh.model.addDiscreteEntity(2)
        nodes = np.arange(1, len(surface.vertices) + 1)
        gmsh.model.mesh.addNodes(2, tag, nodes, np.asarray(surface.vertices, np.float64).ravel())
        gmsh.model.mesh.addElementsByType(tag, 2, [], (np.asarray(surface.faces) + 1).ravel())
        # Split the surface at its edges (facets meeting at more than 15 degrees: a snap hook's
        # lead and return edges are 20-60 degrees) so that the new surface mesh keeps them, then
        # mesh anew at `size`.
        gmsh.model.mesh.classifySurfaces(np.radians(15.0), True, True, np.pi)
        gmsh.model.mesh.createGeometry()
        surfaces = [s[1] for s in gmsh.model.getEntities(2)]
        loop = gmsh.model.geo.addSurfaceLoop(surfaces)
        gmsh.model.geo.addVolume([loop])
        gmsh.model.geo.synchronize()
        # The element size is the user's: neither the STL's own vertex spacing nor its facets'
        # curvature refine it (the facets are already the surface's resolution).
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
        gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
        gmsh.option.setNumber("Mesh.Optimize", 1)
        gmsh.model.mesh.generate(3)
        tags, coords, _ = gmsh.model.mesh.getNodes()
        etypes, _, enodes = gmsh.model.mesh.getElements(3)
    except Exception as err:
        raise PartError(f"{key} = {str(path)!r}: gmsh could not tet-mesh the surface ({err})") from None
    finally:
        gmsh.model.remove()
        if not initialised:
            gmsh.finalize()
    if 4 not in list(etypes):
        raise PartError(f"{key} = {str(path)!r}: gmsh made no tetrahedra from the surface")
    index = np.zeros(int(tags.max()) + 1, np.int64)
    index[tags.astype(np.int64)] = np.arange(tags.size)
    cells = index[np.asarray(enodes[list(etypes).index(4)], np.int64).reshape(-1, 4)]
    return coords.reshape(-1, 3), cells


def _named_nodes(mesh, name: str, n_points: int) -> np.ndarray | None:
    """Node mask of a named group of a meshio mesh: a point set, a point-data mask, a cell set
    or a Gmsh physical group (nodes of its cells of any type); None when there is none."""
    mask = np.zeros(n_points, bool)
    if name in mesh.point_sets:
        mask[np.asarray(mesh.point_sets[name], np.int64)] = True
        return mask
    if name in mesh.point_data:
        return np.asarray(mesh.point_data[name]).reshape(n_points, -1).any(axis=1)
    if name in mesh.cell_sets:
        for block, ids in zip(mesh.cells, mesh.cell_sets[name], strict=False):
            ids = np.asarray(ids, np.int64)
            if ids.size:
                mask[np.asarray(block.data)[ids].ravel()] = True
        return mask
    physical = mesh.cell_data.get("gmsh:physical")
    if name in getattr(mesh, "field_data", {}) and physical is not None:
        tag = int(mesh.field_data[name][0])
        for block, tags in zip(mesh.cells, physical, strict=True):
            mask[np.asarray(block.data)[np.asarray(tags) == tag].ravel()] = True
        return mask
    return None


def _group_names(mesh) -> list[str]:
    names = list(mesh.point_sets) + list(mesh.cell_sets) + list(getattr(mesh, "field_data", {}))
    names += [k for k, v in mesh.point_data.items() if np.asarray(v).dtype.kind in "biu"]
    return sorted(set(names) - {"gmsh:dim_tags"})


def fixed_nodes(points: np.ndarray, box) -> np.ndarray:
    """(n,) bool: nodes inside ``box`` = [[x0, y0, z0], [x1, y1, z1]] (mm, inclusive, with a
    tolerance of 1e-9 of the part's size)."""
    lo, hi = np.asarray(box, np.float64)
    tol = 1e-9 * float(np.linalg.norm(np.ptp(points, axis=0)))
    return np.all((points >= lo - tol) & (points <= hi + tol), axis=1)


def _check_fixed(points: np.ndarray, cells: np.ndarray, fixed: np.ndarray, path: Path, what: str) -> None:
    """The fixed region must hold every connected piece of the part against rigid motion."""
    if not fixed.any():
        raise PartError(f"{what} selects no node of {str(path)!r}: the part would float freely")
    # Connected pieces of the mesh (nodes joined through their tetrahedra).
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = points.shape[0]
    rows = np.repeat(cells[:, :1], 3, axis=1).ravel()
    graph = coo_matrix((np.ones(rows.size), (rows, cells[:, 1:].ravel())), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    used = np.zeros(n, bool)
    used[cells.ravel()] = True
    for piece in np.unique(label[used]):
        held = points[(label == piece) & fixed]
        if held.shape[0] == 0:
            raise PartError(
                f"{what} leaves a piece of {str(path)!r} ({int(np.sum((label == piece) & used))} nodes) "
                "unheld: it would move as a rigid body"
            )
        spread = np.linalg.svd(held - held.mean(axis=0), compute_uv=False) if held.shape[0] > 1 else np.zeros(3)
        if spread.size < 2 or spread[1] <= 1e-9 * max(float(spread[0]), 1e-300):
            raise PartError(
                f"{what} holds {str(path)!r} at {held.shape[0]} node(s) on one line: the part could "
                "turn about it as a rigid body; fix a region that spans an area"
            )


def part_wall_thickness(path, units: str = "mm") -> float:
    """The wall thickness (:func:`jsnap._geometry.size.wall_thickness`, mm) of the deformable
    part's file: a closed surface, or the boundary of its tetrahedra. Measured once per version
    of the file (its path, size and modification time).

    Raises:
        PartError: as :func:`load_part` for a file it cannot read.
    """
    return part_thinnest_wall(path, units)[0]


def part_thinnest_wall(path, units: str = "mm") -> tuple[float, np.ndarray]:
    """The deformable part's thinnest wall (:func:`jsnap._geometry.size.thinnest_wall`): its
    thickness, mm, and (3,) the point of the surface it was measured from, mm (a copy).

    Raises:
        PartError: as :func:`load_part` for a file it cannot read.
    """
    wall, point = _wall_of(*_file_version(path), units)
    return wall, point.copy()


def _file_version(path) -> tuple[str, int, int]:
    """A part file's resolved path, size and modification time: the key of what is read once
    per version of it."""
    path = Path(path)
    if not path.is_file():
        raise PartError(f"part.mesh = {str(path)!r}: no such file")
    stat = path.stat()
    return str(path.resolve()), stat.st_size, stat.st_mtime_ns


@functools.lru_cache(maxsize=32)
def _wall_of(path: str, size: int, mtime_ns: int, units: str) -> tuple[float, np.ndarray]:
    key = "part.mesh"
    file = Path(path)
    if file.suffix.lower() in SURFACE_SUFFIXES:
        surface = _read_surface(file, key, units)
        return thinnest_wall(surface.vertices, surface.faces)
    points, cells, _ = _read_tets(file, key, units)
    flip = signed_volumes(points, cells) < 0
    cells = np.where(flip[:, None], cells[:, [0, 2, 1, 3]], cells)
    return thinnest_wall(points, TetMesh(points, cells, np.zeros(0)).boundary_faces())


def _read_tets(path: Path, key: str, units: str):
    """(points in mm, corner cells (m, 4)) of a tetrahedral mesh file, and the meshio mesh."""
    import meshio

    try:
        mesh = meshio.read(path)
    except Exception as err:  # meshio raises many types for unreadable files
        raise PartError(f"{key} = {str(path)!r}: cannot read it as a mesh ({err})") from None
    blocks = [b for b in mesh.cells if b.type in ("tetra", "tetra10")]
    if not blocks:
        kinds = ", ".join(sorted({b.type for b in mesh.cells})) or "none"
        raise PartError(
            f"{key} = {str(path)!r}: no tetrahedra in the file (cells: {kinds}); give tetrahedra "
            "or a closed surface (STL/OBJ/PLY) to be tet-meshed"
        )
    points = np.asarray(mesh.points, np.float64)[:, :3] * UNITS[units]
    cells = np.concatenate([np.asarray(b.data, np.int64)[:, :4] for b in blocks])
    return points, cells, mesh


def load_part(
    path, *, units: str = "mm", fixed: str | None = None, fixed_box=None, mesh_size: float
) -> TetMesh:
    """The deformable part of ``[part]``: a :class:`TetMesh` in mm whose ``base_nodes`` are its
    fixed region.

    Args:
        path: tetrahedra (any meshio format) or a closed surface (STL/OBJ/PLY/OFF/glTF).
        units: the file's length unit (``mm``, ``m`` or ``in``).
        fixed: the name of a group in the file (point set, cell set, point-data mask or Gmsh
            physical group) whose nodes are fixed; or
        fixed_box: [[x0, y0, z0], [x1, y1, z1]] in mm: the nodes inside are fixed.
        mesh_size: element size for a surface that is tet-meshed here, mm.

    Raises:
        PartError: unreadable file, open surface, no/inverted/degenerate tetrahedra, unknown
            group, a fixed region that selects nothing or leaves the part free, implausible size.
    """
    path = Path(path)
    key = "part.mesh"
    if not path.is_file():
        raise PartError(f"{key} = {str(path)!r}: no such file")
    if (fixed is None) == (fixed_box is None):
        raise PartError("[part] needs exactly one of part.fixed (a group name) and part.fixed_box")
    if path.suffix.lower() in SURFACE_SUFFIXES:
        if fixed is not None:
            raise PartError(
                f"part.fixed = {fixed!r}: a surface file ({path.name}) has no named groups; use part.fixed_box"
            )
        surface = _read_surface(path, key, units)
        points, cells = _tet_mesh_surface(surface, mesh_size, path, key)
        mask = None
    else:
        points, cells, mesh = _read_tets(path, key, units)
        mask = None
        if fixed is not None:
            mask = _named_nodes(mesh, fixed, points.shape[0])
            if mask is None:
                names = ", ".join(_group_names(mesh)) or "none"
                raise PartError(f"part.fixed = {fixed!r}: no such group in {str(path)!r} (groups: {names})")
        _check_size(points, path, key, units)
    # Nodes no tetrahedron uses (P2 mid-edge nodes, surface-only nodes) are dropped.
    used = np.unique(cells)
    renumber = -np.ones(points.shape[0], np.int64)
    renumber[used] = np.arange(used.size)
    points, cells = points[used], renumber[cells]
    mask = mask[used] if mask is not None else fixed_nodes(points, fixed_box)
    vol = signed_volumes(points, cells)
    if np.all(vol < 0):  # the file's convention winds the other way round
        cells = cells[:, [0, 2, 1, 3]]
    try:
        check_quality(points, cells, min_quality=1e-4)
    except MeshQualityError as err:
        raise PartError(f"{key} = {str(path)!r}: {err}") from None
    what = f"part.fixed = {fixed!r}" if fixed is not None else f"part.fixed_box = {fixed_box!r}"
    _check_fixed(points, cells, mask, path, what)
    return TetMesh(points=points, cells=cells, base_nodes=np.flatnonzero(mask))


@dataclass(frozen=True, eq=False)
class RigidSurface:
    """The rigid part of ``[rigid]`` in its own frame, placed at its start pose.

    Attributes:
        mesh: the closed surface (``trimesh.Trimesh``), mm, centred on ``centroid`` and turned
            to its start orientation (``rigid.rotation``).
        centroid: (3,) its volume centroid at t = 0 in the frame of the fixed base, mm (the
            file's, moved by ``rigid.position``): the origin of its frame and the point
            rotations turn about.
        half: (3,) half extents of a box about the origin holding the whole surface, mm.
    """

    mesh: object
    centroid: np.ndarray
    half: np.ndarray


def load_rigid(
    path, *, units: str = "mm", position=(0.0, 0.0, 0.0), rotation=(1.0, 0.0, 0.0, 0.0)
) -> RigidSurface:
    """The rigid part of ``[rigid]`` from a closed surface file, placed at its pose at t = 0 in
    the frame of the fixed base: the file's coordinates (in ``units``) turned by the unit
    quaternion ``rotation`` (w, x, y, z; ``rigid.rotation``) about the file's volume centroid,
    then moved by ``position`` (mm; ``rigid.position``). The defaults keep the file's pose."""
    path = Path(path)
    if not path.is_file():
        raise PartError(f"rigid.mesh = {str(path)!r}: no such file")
    if path.suffix.lower() not in SURFACE_SUFFIXES:
        raise PartError(f"rigid.mesh = {str(path)!r}: give a closed surface ({', '.join(SURFACE_SUFFIXES)})")
    mesh = _read_surface(path, "rigid.mesh", units)
    centroid = np.asarray(mesh.center_mass, np.float64)
    mesh.apply_translation(-centroid)
    q = np.asarray(rotation, np.float64)
    if not np.array_equal(q, [1.0, 0.0, 0.0, 0.0]):
        import trimesh

        # (w, x, y, z), the motion's convention (jsnap._geometry.motion.quat_matrix).
        mesh.apply_transform(trimesh.transformations.quaternion_matrix(q / np.linalg.norm(q)))
    half = np.max(np.abs(mesh.bounds), axis=0)
    return RigidSurface(mesh, centroid + np.asarray(position, np.float64), half)
