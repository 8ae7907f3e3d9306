"""The rigid parts of the preset scenes: a rounded block or a rounded cylinder sized from the
connector (host side).

Units: mm.
"""

from __future__ import annotations

import numpy as np

__all__ = ["SHAPES", "Plug", "rounded_box_mesh", "rounded_cylinder_mesh"]

SHAPES = ("box", "cylinder")


class Plug:
    """A preset rigid part: a rounded box or a rounded cylinder (axis z), and where it starts.

    Attributes:
        half: (3,) half extents, mm (a cylinder's: radius, radius, half height).
        radius: fillet radius of its edges, mm.
        start: (3,) centre at t = 0, mm (in the frame of the deformable part's base).
        rotation: (4,) its orientation, a unit quaternion (w, x, y, z), kept along a straight
            insertion (the box lid's tilted box); None: axis-aligned.
        shape: ``"box"`` or ``"cylinder"``.
    """

    def __init__(self, half, radius: float, start, rotation=None, shape: str = "box"):
        if shape not in SHAPES:
            raise ValueError(f"shape = {shape!r}: must be one of {', '.join(SHAPES)}")
        self.half = np.asarray(half, dtype=np.float64)
        self.radius = float(radius)
        self.start = np.asarray(start, dtype=np.float64)
        self.rotation = None if rotation is None else np.asarray(rotation, dtype=np.float64)
        self.shape = shape

    def mesh(self):
        """Its closed triangle mesh (``trimesh.Trimesh``), in its own frame."""
        if self.shape == "cylinder":
            return rounded_cylinder_mesh(self.half[0], self.half[2], self.radius)
        return rounded_box_mesh(self.half, self.radius)


def rounded_cylinder_mesh(radius: float, half_height: float, fillet: float, sections: int = 128):
    """Closed triangle mesh of the cylinder ``x² + y² ≤ radius²``, ``|z| ≤ half_height`` with
    its two circular edges rounded by ``fillet`` (mm): its profile (flat ends, fillet arcs of 8
    segments, the side) turned about z in ``sections`` steps. The vertices lie on the exact
    surface, the facets inside it by at most the chord error ``radius (1 - cos(pi / sections))``.
    """
    import trimesh  # host library: only builds need the plug's surface

    r, h, f = float(radius), float(half_height), float(fillet)
    if not (r > 0 and h > 0 and 0 <= f <= min(r, h)):
        raise ValueError(f"need radius, half_height > 0 and 0 <= fillet <= both, got {r}, {h}, {f}")
    arc = np.linspace(0.0, 0.5 * np.pi, 9) if f > 0 else np.zeros(1)
    bottom = [(r - f + f * np.sin(t), -h + f - f * np.cos(t)) for t in arc]
    top = [(r - f + f * np.cos(t), h - f + f * np.sin(t)) for t in arc]
    profile = np.array([(0.0, -h), *bottom, *top, (0.0, h)])
    # trimesh turns a (rho, z) line about z; a profile from the axis back to the axis closes it.
    mesh = trimesh.creation.revolve(profile, sections=sections)
    mesh.merge_vertices()
    if not (mesh.is_watertight and mesh.is_winding_consistent):
        raise RuntimeError("the rounded cylinder's surface is not closed")
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def rounded_box_mesh(half_extents, radius, subdivisions=4):
    """Closed triangle mesh of the rounded box of :func:`rounded_box_sdf` (host, trimesh).

    Built as the convex hull of 8 icospheres of radius ``radius`` centred at the corners of the
    inner box ``half_extents − radius``. After one or more subdivisions an icosphere has vertices
    exactly on ±x, ±y, ±z, so the flat faces lie exactly at ``±half_extents``; the fillets are
    tessellated, the mesh lying inside the exact solid by at most the icosphere's chord error
    ``radius − sqrt(radius² − e²/3)`` for the longest icosphere edge ``e``. ``subdivisions=4``
    gives 5516 triangles for the default plug (half extents (0.5, 2.5, 0.25), radius 0.1);
    3 gives only 1484.

    Args:
        half_extents: (3,), mm.
        radius: fillet radius, mm, ``0 ≤ radius ≤ min(half_extents)``; 0 gives the 12-triangle
            box.
        subdivisions: icosphere subdivision level (≥ 1).

    Returns:
        A watertight, consistently wound ``trimesh.Trimesh`` with outward normals, float64.
    """
    import trimesh  # host library: only builds need the plug's surface

    h = np.asarray(half_extents, dtype=np.float64)
    radius = float(radius)
    if h.shape != (3,) or not np.all(h > 0):
        raise ValueError(f"half_extents must be 3 positive numbers, got {half_extents!r}")
    if not 0.0 <= radius <= h.min():
        raise ValueError(f"radius must lie in [0, min(half_extents) = {h.min()}], got {radius}")
    if radius == 0.0:
        return trimesh.creation.box(extents=2.0 * h)
    if subdivisions < 1:
        # Level 0 has no vertex on the axes, so the flat faces would sit inside ±half_extents.
        raise ValueError(f"subdivisions must be >= 1, got {subdivisions}")
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0).vertices
    corners = np.array(np.meshgrid(*[[-1.0, 1.0]] * 3, indexing="ij")).reshape(3, -1).T
    points = (corners[:, None, :] * (h - radius) + radius * sphere[None]).reshape(-1, 3)
    mesh = trimesh.convex.convex_hull(points)
    if not (mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0):
        raise RuntimeError("convex hull of the rounded box is not a closed outward mesh")
    return mesh
