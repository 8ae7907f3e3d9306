"""The canonical cantilever snap hook and its structured tetrahedral meshing (host side).

The canonical cantilever (the scene reference: ``connector``) is a section polygon in the x–z
plane extruded over the width ``y ∈ [−b/2, b/2]``; its root face ``z = 0`` is the fixed base.
Everything here is plain numpy on the host, in float64. Units: mm (lengths), mm² (areas), mm³ (volumes), degrees
(angles).

Meshing (:func:`mesh_cantilever`): the section is cut into structured quadrilateral blocks,
each filled by transfinite (Coons) interpolation of its sides, extruded in y into hexahedra, and
every hexahedron split into six tetrahedra along its logical main diagonal (Kuhn/Freudenthal).
The blocks are
  * A, the arm ``z ∈ [0, L]``: (0,0) (h,0) (h_tip,L) (0,L);
  * B1, a band of height ``flat`` on top of the line z = L continued along the retention face,
    (0,L) (h_tip,L) (h_tip+y_u, z_retention) up to (h_tip+y_u, z_flat_end) (0, L+flat): its
    right side is the flat (absent when flat = 0);
  * B2, the rest: body and hook above the band, closed by the lead ramp and the top face.
A single hook block (h_tip,L) (h_tip+y_u,z_retention) (h_tip+y_u,z_flat_end) (h_tip,z_top) would
put the short flat opposite the 1.5 mm tall side shared with the body, squeezing every z-row of
the hook 13:1 into the flat (mean ratio below 0.01 at hook_size 0.05); with the band the flat
faces an equally short side. All blocks run u along +x (left to right along their bottom side), v up
and w along +y, so every shared quadrilateral face is cut along the same diagonal from both
sides and the mesh is conforming.

Mesh quality is the mean-ratio measure ``q = 12 (3|V|)^(2/3) / Σ l_ij²`` (1 for the regular
tetrahedron, 0 for a flat one, 0.76 for a cube's Kuhn tetrahedra), see
:func:`check_quality`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from jsnap._geometry.mesh import TetMesh, check_quality, signed_volumes

__all__ = ["HOOK_RANGES", "NEARBY_HOOK", "Cantilever", "draw_hooks", "mesh_box", "mesh_cantilever"]

# --------------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------------


def _is_real(value) -> bool:
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(value, bool)


def _cot(degrees: float) -> float:
    """cot of an angle in (0, 90] degrees; exactly 0 at 90 (a square face adds no height) and
    inf where tan underflows (validate() turns that into an error naming the key)."""
    if degrees == 90:
        return 0.0
    t = math.tan(math.radians(degrees))
    return 1.0 / t if t > 0 else math.inf


@dataclass(frozen=True)
class Cantilever:
    """The canonical cantilever snap hook. Lengths in mm, angles in degrees.

    Attributes:
        length: L, arm length from the root (z = 0) to the retention face (z = L).
        thickness: h, arm thickness in x at the root.
        width: b, extrusion in y, the arm spans y ∈ [−b/2, b/2].
        undercut: y_u, how far the hook protrudes in +x beyond the outer face at z = L.
        lead_angle: α ∈ (0, 90), angle of the lead ramp to the insertion direction (−z).
        return_angle: α' ∈ (0, 90], angle of the retention face to the insertion direction;
            90 is a square face (permanent latch), smaller angles make the joint separable.
        flat: length (≥ 0) of the land at x = h_tip + y_u between retention face and ramp.
        tip_thickness: h_tip, thickness at z = L (the arm tapers linearly); None means h.

    The section polygon (x–z plane, counter-clockwise) is always simple for values that pass
    :meth:`validate`: the arm is a trapezoid below z = L, the body above it the rectangle
    [0, h_tip] × [L, z_top], and the hook a trapezoid with vertical parallel sides x = h_tip
    (z ∈ [L, z_top]) and x = h_tip + y_u (z ∈ [z_retention, z_flat_end]), where
    L ≤ z_retention ≤ z_flat_end < z_top. So only ranges need checking.
    """

    length: float
    thickness: float
    width: float
    undercut: float
    lead_angle: float
    return_angle: float
    flat: float
    tip_thickness: float | None = None

    def __post_init__(self):
        self.validate()

    # -- derived sizes ------------------------------------------------------------------------

    @property
    def h_tip(self) -> float:
        """Arm thickness at z = L, mm."""
        return float(self.thickness if self.tip_thickness is None else self.tip_thickness)

    @property
    def z_retention(self) -> float:
        """z of the top of the retention face (its outer edge), mm; L when α' = 90°."""
        return self.length + self.undercut * _cot(self.return_angle)

    @property
    def z_flat_end(self) -> float:
        """z where the flat ends and the lead ramp starts, mm."""
        return self.z_retention + self.flat

    @property
    def z_top(self) -> float:
        """z of the arm's flat top face (where the lead ramp meets the outer face), mm."""
        return self.z_flat_end + self.undercut * _cot(self.lead_angle)

    # -- section ------------------------------------------------------------------------------

    def section(self) -> np.ndarray:
        """(7, 2) section polygon (x, z) in mm, counter-clockwise, starting at the root origin."""
        h, ht, yu, L = self.thickness, self.h_tip, self.undercut, self.length
        return np.array(
            [
                [0.0, 0.0],
                [h, 0.0],
                [ht, L],
                [ht + yu, self.z_retention],
                [ht + yu, self.z_flat_end],
                [ht, self.z_top],
                [0.0, self.z_top],
            ],
            dtype=np.float64,
        )

    def section_area(self) -> float:
        """Area of the section polygon, mm² (shoelace formula)."""
        p = self.section()
        x, z = p[:, 0], p[:, 1]
        return 0.5 * float(np.sum(x * np.roll(z, -1) - np.roll(x, -1) * z))

    def section_perimeter(self) -> float:
        """Perimeter of the section polygon, mm."""
        p = self.section()
        return float(np.sum(np.linalg.norm(np.roll(p, -1, axis=0) - p, axis=1)))

    def volume(self) -> float:
        """Exact volume of the arm, mm³ (section area × width)."""
        return self.section_area() * self.width

    def surface_area(self) -> float:
        """Exact surface area of the arm including the base face, mm²."""
        return 2.0 * self.section_area() + self.section_perimeter() * self.width

    # -- validation ---------------------------------------------------------------------------

    def validate(self) -> None:
        """Check ranges; raise ``ValueError`` naming the scene key, e.g.
        ``connector.undercut = -0.2: must be > 0``."""

        def fail(key, value, why):
            shown = value.item() if isinstance(value, np.generic) else value
            raise ValueError(f"connector.{key} = {shown!r}: {why}")

        keys = ("length", "thickness", "tip_thickness", "width", "undercut")
        keys += ("lead_angle", "return_angle", "flat")
        for key in keys:
            value = getattr(self, key)
            if key == "tip_thickness" and value is None:
                continue
            if not _is_real(value) or not math.isfinite(value):
                fail(key, value, "must be a finite number")
        for key in ("length", "thickness", "width", "undercut"):
            if getattr(self, key) <= 0:
                fail(key, getattr(self, key), "must be > 0")
        t = self.tip_thickness
        if t is not None and not 0 < t <= 4 * self.thickness:
            fail("tip_thickness", t, f"must be in (0, 4 * thickness] = (0, {4 * self.thickness:g}]")
        if not 0 < self.lead_angle < 90:
            fail("lead_angle", self.lead_angle, "must be in (0, 90) degrees")
        if not 0 < self.return_angle <= 90:
            fail("return_angle", self.return_angle, "must be in (0, 90] degrees")
        if self.flat < 0:
            fail("flat", self.flat, "must be >= 0")
        # What does break: angles so close to 0 that y_u / tan(angle) overflows to inf, or so
        # close to 90 that the ramp has no height left in floating point (z_top == z_flat_end).
        if not math.isfinite(self.z_top):
            key = "return_angle" if not math.isfinite(self.z_retention) else "lead_angle"
            fail(key, getattr(self, key), "too close to 0 degrees: the hook is infinitely tall")
        if not self.z_top > self.z_flat_end:
            fail("lead_angle", self.lead_angle, "too close to 90 degrees: the lead ramp vanishes")


def _ndiv(length: float, size: float) -> int:
    # The small relative slack keeps e.g. 1.2 / 0.6 from giving 3 by round-off.
    return max(1, math.ceil(length / size * (1.0 - 1e-12)))


def _polyline(vertices, counts) -> np.ndarray:
    """(1 + Σ counts, 2) nodes along the straight segments between ``vertices`` (k, 2), segment s
    divided uniformly into ``counts[s]`` parts. The vertices themselves are copied exactly, so
    blocks built from the same vertices agree bit for bit on their shared nodes."""
    vertices = np.asarray(vertices, dtype=np.float64)
    out = [vertices[:1]]
    for a, b, n in zip(vertices[:-1], vertices[1:], counts, strict=True):
        t = (np.arange(1, n + 1) / n)[:, None]
        seg = a + t * (b - a)
        seg[-1] = b
        out.append(seg)
    return np.concatenate(out)


def _arc_fractions(nodes: np.ndarray) -> np.ndarray:
    """(k,) cumulative arc length along a polyline of nodes (k, 2), normalised to [0, 1]."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(nodes, axis=0), axis=1))])
    return s / s[-1]


def _tfi(bottom, top, left, right) -> np.ndarray:
    """(nu+1, nv+1, 2) nodes of a block by transfinite (Coons) interpolation of its sides.

    ``bottom``/``top`` (nu+1, 2) run in +u, ``left``/``right`` (nv+1, 2) in +v, and meet at the
    corners. Interior nodes blend the sides (with u, v the arc-length fractions along bottom
    and left); the boundary nodes are copied from the sides exactly.
    """
    u = _arc_fractions(bottom)[:, None, None]
    v = _arc_fractions(left)[None, :, None]
    b, t = bottom[:, None], top[:, None]
    l, r = left[None, :], right[None, :]
    c00, c10, c01, c11 = bottom[0], bottom[-1], top[0], top[-1]
    grid = (1 - v) * b + v * t + (1 - u) * l + u * r
    grid -= (1 - u) * (1 - v) * c00 + u * (1 - v) * c10 + (1 - u) * v * c01 + u * v * c11
    grid[:, 0], grid[:, -1], grid[0, :], grid[-1, :] = bottom, top, left, right
    return grid


# Kuhn/Freudenthal split: one tetrahedron per axis order, each a monotone path from logical
# corner (0,0,0) to (1,1,1). Every quad face is then cut along its (min, max) logical diagonal,
# so neighbouring hexahedra whose shared edges run the same way logically agree on the cut.
_KUHN = []
for _perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
    _c = [0, 0, 0]
    _path = [tuple(_c)]
    for _ax in _perm:
        _c[_ax] = 1
        _path.append(tuple(_c))
    _KUHN.append(_path)
_KUHN = np.array(_KUHN)  # (6, 4, 3) logical offsets (du, dv, dw)


def _extrude(grids: list[np.ndarray], y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge structured section blocks, extrude them along y and split into tetrahedra.

    Args:
        grids: per block an (nu+1, nv+1, 2) array of section nodes (x, z), mm. Nodes on a
            shared block side must be bitwise equal in both blocks (they are merged exactly).
        y: (ny+1,) increasing y levels, mm.

    Returns:
        points (n2 (ny+1), 3), node id = id2d + n2 * k, and positively oriented cells (m, 4).
    """
    flat = np.concatenate([g.reshape(-1, 2) for g in grids])
    nodes2d, inverse = np.unique(flat, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    n2, ny = nodes2d.shape[0], y.size - 1
    points = np.empty((n2 * (ny + 1), 3))
    points[:, 0] = np.tile(nodes2d[:, 0], ny + 1)
    points[:, 1] = np.repeat(y, n2)
    points[:, 2] = np.tile(nodes2d[:, 1], ny + 1)
    cells, offset = [], 0
    for g in grids:
        nu, nv = g.shape[0] - 1, g.shape[1] - 1
        ids = inverse[offset : offset + (nu + 1) * (nv + 1)].reshape(nu + 1, nv + 1)
        offset += ids.size
        i, j, k = (a.ravel() for a in np.meshgrid(*map(np.arange, (nu, nv, ny)), indexing="ij"))
        for path in _KUHN:
            cells.append(np.stack([ids[i + a, j + b] + n2 * (k + c) for a, b, c in path], axis=1))
    cells = np.concatenate(cells).astype(np.int64)
    # Orientation depends on the block map (u, v, w) -> (x, z, y) and on the axis order.
    neg = signed_volumes(points, cells) < 0
    cells[neg] = cells[neg][:, [0, 2, 1, 3]]
    return points, cells


def _finish(points: np.ndarray, cells: np.ndarray, min_quality: float) -> TetMesh:
    check_quality(points, cells, min_quality)
    base = np.flatnonzero(points[:, 2] == 0.0).astype(np.int64)
    return TetMesh(points=points, cells=cells, base_nodes=base)


def mesh_cantilever(
    geom: Cantilever, size: float, hook_size: float | None = None, min_quality: float = 0.02
) -> TetMesh:
    """Structured, conforming tetrahedral mesh of the cantilever arm (see the module docstring).

    Divisions: a side of length l gets ``max(1, ceil(l / s))`` parts and a block the larger
    count of two opposite sides, with ``s = size`` in the arm (z < L) and across the body
    (x ∈ [0, h_tip]) above it, and ``s = hook_size`` along the retention face, the flat, the
    ramp and in z above L. Below z = L the mesh does not depend on ``hook_size`` (unless the
    width rule below adds layers). The width gets
    ``max(ceil(b / size), ceil(b / (10 hook_size)))`` layers: hook elements are at most 10:1
    needles (a 20:1 needle's mean ratio is 0.035, too close to the 0.02 threshold).

    Args:
        geom: the cantilever.
        size: target element edge length in the arm, mm.
        hook_size: target edge length at the hook (z ≥ L), mm; default ``size``.
        min_quality: mean-ratio threshold passed to :func:`check_quality`.

    Returns:
        The mesh, checked with :func:`check_quality` (raises :class:`MeshQualityError`).
    """
    hook_size = size if hook_size is None else hook_size
    for name, value in (("size", size), ("hook_size", hook_size)):
        if not (_is_real(value) and math.isfinite(value) and value > 0):
            raise ValueError(f"{name} = {value!r}: must be a finite number > 0")
    p = geom.section()
    h, ht, L, zt, flat = geom.thickness, geom.h_tip, geom.length, geom.z_top, geom.flat
    root, root_out, tip_out, ret_out, flat_end, ramp_top, top_in = p
    tip_in = np.array([0.0, L])

    def dist(a, b):
        return float(np.linalg.norm(b - a))

    # A: the arm, z in [0, L].
    nu_a = max(_ndiv(h, size), _ndiv(ht, size))
    nv_a = max(_ndiv(L, size), _ndiv(dist(root_out, tip_out), size))
    arm = _tfi(
        _polyline([root, root_out], [nu_a]),
        _polyline([tip_in, tip_out], [nu_a]),
        _polyline([root, tip_in], [nv_a]),
        _polyline([root_out, tip_out], [nv_a]),
    )
    grids = [arm]
    # The section's line z = L continued along the retention face; x-divisions of the blocks
    # above: the arm's across the body, hook_size along the retention face.
    n_ret = _ndiv(dist(tip_out, ret_out), hook_size)
    base = _polyline([tip_in, tip_out, ret_out], [nu_a, n_ret])
    if flat > 0:
        # B1: the band of height `flat` above that line (body and hook base, ending in the
        # flat). Cutting here keeps the short flat opposite an equally short side; a single
        # hook block would squeeze all of the hook's z-divisions into the flat.
        n_f = _ndiv(flat, hook_size)
        dz = flat * np.arange(n_f + 1) / n_f
        band = base[:, None, :] + np.stack([np.zeros_like(dz), dz], axis=1)[None]
        band[:, -1, 1] = base[:, 1] + flat
        band[-1, -1] = flat_end  # bitwise the section's vertex
        grids.append(band)
        base = band[:, -1]
    # B2: everything above, bounded by the ramp on the right and the top face z = z_top; its
    # top side takes the bottom side's arc-length fractions so the columns stay straight-ish.
    nv_b = max(_ndiv(zt - base[0, 1], hook_size), _ndiv(dist(flat_end, ramp_top), hook_size))
    top = np.stack([_arc_fractions(base) * ht, np.full(base.shape[0], zt)], axis=1)
    top[-1], top[0] = ramp_top, top_in
    grids.append(
        _tfi(
            base,
            top,
            _polyline([base[0], top_in], [nv_b]),
            _polyline([flat_end, ramp_top], [nv_b]),
        )
    )
    ny = max(_ndiv(geom.width, size), _ndiv(geom.width, 10.0 * hook_size))
    y = np.linspace(-0.5 * geom.width, 0.5 * geom.width, ny + 1)
    points, cells = _extrude(grids, y)
    return _finish(points, cells, min_quality)


def mesh_box(
    lx: float,
    ly: float,
    lz: float,
    size: float | None = None,
    divisions: tuple[int, int, int] | None = None,
    min_quality: float = 0.02,
) -> TetMesh:
    """Structured tetrahedral mesh of the straight arm x ∈ [0, lx], y ∈ [−ly/2, ly/2],
    z ∈ [0, lz] (mm), base z = 0.

    Args:
        lx, ly, lz: box sizes, mm.
        size: target edge length, mm (``ceil(l / size)`` divisions per axis).
        divisions: (nx, ny, nz) hexahedra per axis; overrides ``size``.
        min_quality: passed to :func:`check_quality`.
    """
    for name, value in (("lx", lx), ("ly", ly), ("lz", lz)):
        if not (_is_real(value) and math.isfinite(value) and value > 0):
            raise ValueError(f"{name} = {value!r}: must be a finite number > 0")
    if divisions is None:
        if size is None:
            raise ValueError("mesh_box needs size or divisions")
        divisions = (_ndiv(lx, size), _ndiv(ly, size), _ndiv(lz, size))
    nx, ny, nz = (int(d) for d in divisions)
    if min(nx, ny, nz) < 1:
        raise ValueError(f"divisions = {divisions!r}: must all be >= 1")
    c = np.array([[0.0, 0.0], [lx, 0.0], [lx, lz], [0.0, lz]])
    grid = _tfi(
        _polyline([c[0], c[1]], [nx]),
        _polyline([c[3], c[2]], [nx]),
        _polyline([c[0], c[3]], [nz]),
        _polyline([c[1], c[2]], [nz]),
    )
    points, cells = _extrude([grid], np.linspace(-0.5 * ly, 0.5 * ly, ny + 1))
    return _finish(points, cells, min_quality)


# Ranges of a cantilever hook family (mm, degrees) that snap-fit design guides cover; the default
# hook (L 10, h 1.2, b 4, y_u 0.8, 30°/90°, friction 0.3) lies inside them. The thinnest features
# are kept >= 0.7 mm so that full reference models of the family stay affordable.
HOOK_RANGES = {
    "connector.length": (8.0, 15.0),
    "connector.thickness": (1.1, 1.8),
    "taper": (0.65, 1.0),  # tip thickness / root thickness
    "connector.width": (3.0, 6.0),
    "connector.undercut": (0.7, 1.2),
    "connector.lead_angle": (20.0, 45.0),
    "connector.return_angle": (60.0, 90.0),
    "contact.friction": (0.0, 0.6),
}


# A hook slightly different from the default that once broke the float32 reduced model (stiff
# interface springs rounded): a fixed member of every hook-family check.
NEARBY_HOOK = {
    "connector.length": 12.0,
    "connector.thickness": 1.4,
    "connector.tip_thickness": 1.4,
    "connector.width": 5.0,
    "connector.undercut": 0.9,
    "connector.lead_angle": 35.0,
    "contact.friction": 0.4,
    "solver.mesh_size": 0.7,
}


def draw_hooks(seed: int, n: int, ranges: dict = HOOK_RANGES) -> list[dict]:
    """``n`` scene changes (``Scene.replace`` keys) of hooks drawn over ``ranges``, one draw per
    stratum of every range (a Latin hypercube), so each range is covered from its low to its
    high end. ``"taper"`` is the tip-to-root thickness ratio. Each hook is meshed with one P2
    element across its thinnest feature (undercut or tip), at most 1 mm: the coarsest mesh the
    scene accepts without a warning."""
    rng = np.random.default_rng(seed)
    cases = [{} for _ in range(n)]
    for key, (lo, hi) in ranges.items():
        u = (rng.permutation(n) + rng.random(n)) / n
        for case, x in zip(cases, lo + u * (hi - lo), strict=True):
            case[key] = round(float(x), 3)
    for case in cases:
        taper = case.pop("taper")
        case["connector.tip_thickness"] = round(taper * case["connector.thickness"], 3)
        thinnest = min(1.0, case["connector.undercut"], case["connector.tip_thickness"])
        case["solver.mesh_size"] = float(np.floor(100 * thinnest) / 100)
    return cases
