"""Tetrahedral meshes on the host: quality checks, boundary faces and VTU export (ParaView).

Units: mm (lengths), mm² (areas), mm³ (volumes).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

__all__ = [
    "TET_FACES",
    "MeshQualityError",
    "TetMesh",
    "check_quality",
    "mean_ratio",
    "signed_volumes",
    "write_vtu",
    "write_vtu_series",
]

# Below this |V| / l_max³ an element is "degenerate" (a regular tetrahedron has 0.118, the
# worst element the structured meshes here produce has ~1e-3): well above round-off of the
# volume computation (~1e-16) and far below anything a mesher should produce.
_DEGENERATE_RTOL = 1e-9

# Edges of a tetrahedron as vertex pairs (VTK tetra10 order of the edge midpoints).
_TET_EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])

# Faces of a tetrahedron whose right-hand normal points out of a positively oriented tet
# (signed volume det[p1-p0, p2-p0, p3-p0] / 6 > 0): each face omits one vertex.
TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


# --------------------------------------------------------------------------------------------
# Tetrahedral meshes
# --------------------------------------------------------------------------------------------


def signed_volumes(points: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """(m,) signed volumes in mm³ of tetrahedra ``cells`` (m, 4) over ``points`` (n, 3);
    positive when (p1 − p0, p2 − p0, p3 − p0) is a right-handed frame."""
    p = np.asarray(points, dtype=np.float64)[np.asarray(cells)[:, :4]]
    d = p[:, 1:] - p[:, :1]
    return np.einsum("ij,ij->i", d[:, 0], np.cross(d[:, 1], d[:, 2])) / 6.0


def mean_ratio(points: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """(m,) mean-ratio quality ``12 (3 V)^(2/3) / Σ l_ij²`` of tetrahedra (m, 4).

    Dimensionless, 1 for the regular tetrahedron, → 0 for a flat one, negative for an inverted
    one (it keeps the sign of the volume). A cube's Kuhn tetrahedra score 0.76.
    """
    p = np.asarray(points, dtype=np.float64)[np.asarray(cells)[:, :4]]
    vol = signed_volumes(points, cells)
    e = p[:, _TET_EDGES[:, 1]] - p[:, _TET_EDGES[:, 0]]
    sum_l2 = np.einsum("ijk,ijk->i", e, e)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = 12.0 * np.cbrt(3.0 * vol) ** 2 * np.sign(vol) / sum_l2
    return np.where(sum_l2 > 0, q, 0.0)


class MeshQualityError(ValueError):
    """A mesh has an inverted, degenerate or badly shaped element (the message names it)."""


def check_quality(points: np.ndarray, cells: np.ndarray, min_quality: float = 0.02) -> None:
    """Raise :class:`MeshQualityError` naming the first bad tetrahedron, else return None.

    An element is, in this order of precedence:
      * degenerate: ``|V| <= 1e-9 · l_max³`` (l_max its longest edge);
      * inverted: signed volume ``V < 0`` (node order not right-handed);
      * poor quality: mean ratio (see :func:`mean_ratio`) below ``min_quality``.
    The first element (lowest index) with any defect is reported, with its four node indices
    and the offending measure, plus the count of bad elements.

    Args:
        points: (n, 3) node positions, mm.
        cells: (m, 4) node indices (extra columns, e.g. tetra10 edge nodes, are ignored).
        min_quality: threshold on the mean ratio, in (0, 1).
    """
    cells = np.asarray(cells)
    vol = signed_volumes(points, cells)
    p = np.asarray(points, dtype=np.float64)[cells[:, :4]]
    e = p[:, _TET_EDGES[:, 1]] - p[:, _TET_EDGES[:, 0]]
    l_max = np.sqrt(np.max(np.einsum("ijk,ijk->ij", e, e), axis=1))
    q = mean_ratio(points, cells)
    degenerate = np.abs(vol) <= _DEGENERATE_RTOL * l_max**3
    inverted = ~degenerate & (vol < 0)
    poor = ~degenerate & ~inverted & (q < min_quality)
    bad = np.flatnonzero(degenerate | inverted | poor)
    if bad.size == 0:
        return
    i = int(bad[0])
    where = f"element {i} (nodes [{' '.join(str(int(n)) for n in cells[i, :4])}])"
    if degenerate[i]:
        what = f"is degenerate: signed volume {vol[i]:.3e} mm^3 with longest edge {l_max[i]:.3e} mm"
    elif inverted[i]:
        what = f"is inverted: signed volume {vol[i]:.3e} mm^3"
    else:
        what = f"has poor quality: mean ratio {q[i]:.3e} < {min_quality:g}"
    more = f" ({bad.size} bad elements in all)" if bad.size > 1 else ""
    raise MeshQualityError(f"{where} {what}{more}")


@dataclass(frozen=True, eq=False)
class TetMesh:
    """A linear tetrahedral mesh in mm.

    Attributes:
        points: (n, 3) float64 node positions, mm.
        cells: (m, 4) int64 node indices, positively oriented (signed volume > 0).
        base_nodes: (k,) int64 sorted indices of the nodes on the fixed base z = 0.
        sliding: symmetry planes, ``((nodes (k,) int64, unit normal (3,)), ...)``: those nodes
            move in their plane only (no displacement along its normal). A preset cut to a
            sector of an axisymmetric part holds its two cut faces so; their faces are not part
            of the surface contact can reach (:meth:`contact_faces`).
    """

    points: np.ndarray
    cells: np.ndarray
    base_nodes: np.ndarray
    sliding: tuple = ()

    def __post_init__(self):
        # Coerce once so downstream code can rely on the dtypes (eq=False: arrays have no
        # single truth value, identity is the only sensible equality).
        object.__setattr__(self, "points", np.asarray(self.points, dtype=np.float64))
        object.__setattr__(self, "cells", np.asarray(self.cells, dtype=np.int64))
        object.__setattr__(self, "base_nodes", np.asarray(self.base_nodes, dtype=np.int64))
        if self.points.ndim != 2 or self.points.shape[1] != 3:
            raise ValueError(f"points must be (n, 3), got {self.points.shape}")
        if self.cells.ndim != 2 or self.cells.shape[1] != 4:
            raise ValueError(f"cells must be (m, 4), got {self.cells.shape}")
        planes = []
        for nodes, normal in self.sliding:
            normal = np.asarray(normal, dtype=np.float64)
            if normal.shape != (3,) or not np.isclose(np.linalg.norm(normal), 1.0):
                raise ValueError(f"a sliding plane's normal must be a unit (3,) vector, got {normal!r}")
            planes.append((np.unique(np.asarray(nodes, dtype=np.int64)), normal))
        object.__setattr__(self, "sliding", tuple(planes))

    def volumes(self) -> np.ndarray:
        """(m,) element volumes, mm³."""
        return signed_volumes(self.points, self.cells)

    def boundary_faces(self, owners: bool = False):
        """(f, 3) int64 boundary triangles, ordered so the right-hand normal points outwards;
        with ``owners``, also the (f,) tet each belongs to."""
        faces = self.cells[:, TET_FACES].reshape(-1, 3)
        _, first, counts = np.unique(np.sort(faces, axis=1), axis=0, return_index=True, return_counts=True)
        at = np.sort(first[counts == 1])
        return (faces[at], at // len(TET_FACES)) if owners else faces[at]

    def contact_faces(self) -> np.ndarray:
        """(f, 3) :meth:`boundary_faces` less those on a sliding (symmetry) plane: the cut faces
        of a sector are inside the whole part, nothing touches them."""
        faces = self.boundary_faces()
        keep = np.ones(faces.shape[0], dtype=bool)
        for nodes, _ in self.sliding:
            on = np.zeros(self.points.shape[0], dtype=bool)
            on[nodes] = True
            keep &= ~np.all(on[faces], axis=1)
        return faces[keep]

    def boundary_face_areas(self) -> np.ndarray:
        """(f,) areas of :meth:`boundary_faces`, mm²."""
        p = self.points[self.boundary_faces()]
        return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)


# --------------------------------------------------------------------------------------------
# VTU export (ParaView)
# --------------------------------------------------------------------------------------------

_VTK_TET = {4: "tetra", 10: "tetra10"}


def write_vtu(
    path: str | os.PathLike,
    points: np.ndarray,
    cells: np.ndarray,
    point_data: dict[str, np.ndarray] | None = None,
    cell_data: dict[str, np.ndarray] | None = None,
) -> Path:
    """Write a tetrahedral mesh to a VTU file (via meshio) and return its path.

    Args:
        path: output file, ``.vtu``.
        points: (n, 3) node positions, mm.
        cells: (m, 4) linear tetrahedra (``tetra``) or (m, 10) quadratic ones (``tetra10``,
            VTK node order: 4 vertices, then the midpoints of edges 01, 12, 02, 03, 13, 23).
        point_data: name -> (n,) or (n, k) arrays.
        cell_data: name -> (m,) or (m, k) arrays.
    """
    import meshio  # build-layer dependency; keep `import jsnap._geometry.cantilever` light

    points = np.asarray(points, dtype=np.float64)
    cells = np.asarray(cells, dtype=np.int64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (n, 3), got {points.shape}")
    if cells.ndim != 2 or cells.shape[1] not in _VTK_TET:
        raise ValueError(f"cells must be (m, 4) or (m, 10), got {cells.shape}")
    for name, data in (point_data or {}).items():
        if np.shape(data)[0] != points.shape[0]:
            raise ValueError(f"point_data[{name!r}] has {np.shape(data)[0]} rows, expected {points.shape[0]}")
    for name, data in (cell_data or {}).items():
        if np.shape(data)[0] != cells.shape[0]:
            raise ValueError(f"cell_data[{name!r}] has {np.shape(data)[0]} rows, expected {cells.shape[0]}")
    mesh = meshio.Mesh(
        points,
        [(_VTK_TET[cells.shape[1]], cells)],
        point_data={k: np.asarray(v) for k, v in (point_data or {}).items()},
        cell_data={k: [np.asarray(v)] for k, v in (cell_data or {}).items()},
    )
    path = Path(path)
    meshio.write(path, mesh, file_format="vtu")
    return path


def write_vtu_series(
    directory: str | os.PathLike,
    stem: str,
    points: np.ndarray,
    cells: np.ndarray,
    displacements: np.ndarray,
    times: np.ndarray,
    deformed: bool = False,
    cell_data: dict[str, np.ndarray] | None = None,
) -> Path:
    """Write a time series as ``stem_0000.vtu, stem_0001.vtu, …`` plus a ParaView collection
    ``stem.pvd`` listing each file with its time; return the ``.pvd`` path.

    Args:
        directory: output folder (created if missing).
        stem: file name stem.
        points: (n, 3) reference node positions, mm.
        cells: (m, 4) or (m, 10) tetrahedra, see :func:`write_vtu`.
        displacements: (T, n, 3) nodal displacements, mm, written as point data
            ``displacement`` (ParaView's "Warp By Vector" shows the deformed shape).
        times: (T,) times, s.
        deformed: write the deformed positions ``points + displacement`` as the geometry
            instead of the reference ones.
        cell_data: name -> (T, m) or (T, m, k) per-element fields, frame ``k`` written with
            file ``k`` (e.g. an element's largest strain).
    """
    points = np.asarray(points, dtype=np.float64)
    u = np.asarray(displacements, dtype=np.float64)
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    if u.ndim != 3 or u.shape[1:] != points.shape or u.shape[0] != times.size:
        raise ValueError(
            f"displacements must be (T, n, 3) = ({times.size}, {points.shape[0]}, 3), got {u.shape}"
        )
    n_cells = np.shape(cells)[0]
    cell_data = {k: np.asarray(v) for k, v in (cell_data or {}).items()}
    for name, data in cell_data.items():
        if data.ndim < 2 or data.shape[:2] != (times.size, n_cells):
            raise ValueError(
                f"cell_data[{name!r}] must be ({times.size}, {n_cells}, ...) (frames, cells), got {data.shape}"
            )
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    width = max(4, len(str(max(times.size - 1, 0))))
    entries = []
    for k in range(times.size):
        name = f"{stem}_{k:0{width}d}.vtu"
        geometry = points + u[k] if deformed else points
        frame = {key: data[k] for key, data in cell_data.items()}
        write_vtu(directory / name, geometry, cells, point_data={"displacement": u[k]}, cell_data=frame)
        time = repr(float(times[k]))  # shortest exact decimal
        entries.append(f'    <DataSet timestep="{time}" part="0" file={quoteattr(name)}/>')
    pvd = directory / f"{stem}.pvd"
    pvd.write_text(
        '<?xml version="1.0"?>\n'
        '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">\n'
        "  <Collection>\n" + "\n".join(entries) + "\n  </Collection>\n</VTKFile>\n"
    )
    return pvd
