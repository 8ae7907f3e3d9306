"""Build layer: a scene in, a :class:`Model` pytree out (host side, float64, once).

This is the only place (with ``_fem`` and ``_geometry``) that touches scikit-fem, meshio and
trimesh. Everything the kernels need is an array leaf of the model; sizes and solver choices
are static fields. Units: mm, N, MPa, s, tonne.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jsnap._fem import Assembly, assemble
from jsnap._geometry import Cantilever, TetMesh, mesh_cantilever
from jsnap._integrate import Material, SparseBlocks
from jsnap._neural_sdf import NeuralSDF, load_or_train
from jsnap._scene import Scene, SceneError, connector_geometry
from jsnap._sdf import MeshSDF, rounded_box_mesh

__all__ = ["Model", "Params", "build"]


class Params(eqx.Module):
    """Physical parameters, each a scalar array: traced, differentiable, batchable.

    Attributes:
        E: Young's modulus, MPa.   nu: Poisson's ratio.   rho: density, t/mm^3.
        alpha: Rayleigh mass damping, 1/s.   beta: Rayleigh stiffness damping, s.
        friction: Coulomb coefficient between plug and socket.
    """

    E: jax.Array
    nu: jax.Array
    rho: jax.Array
    alpha: jax.Array
    beta: jax.Array
    friction: jax.Array

    @classmethod
    def create(cls, E, nu, rho, alpha=0.0, beta=0.0, friction=0.0) -> Params:
        vals = (E, nu, rho, alpha, beta, friction)
        return cls(*(jnp.asarray(v, jnp.float64) for v in vals))

    @classmethod
    def from_scene(cls, scene: Scene) -> Params:
        m = scene["material"]
        return cls.create(
            m["youngs_modulus"],
            m["poissons_ratio"],
            m["density"],
            m["rayleigh_alpha"],
            m["rayleigh_beta"],
            scene["contact"]["friction"],
        )

    @property
    def material(self) -> Material:
        return Material(self.E, self.nu, self.rho, self.alpha, self.beta)

    def replace(self, **kw) -> Params:
        """A copy with some fields replaced, e.g. ``params.replace(E=2500.0)``."""
        for k in kw:
            if k not in {"E", "nu", "rho", "alpha", "beta", "friction"}:
                raise TypeError(f"Params has no field {k!r}")
        return Params(**{**{f: getattr(self, f) for f in self.__dataclass_fields__}, **kw})


@dataclass(frozen=True, eq=False)
class HostData:
    """Host-side data for outputs (meshes for ParaView, plots). Not used inside kernels."""

    scene: Scene
    assembly: Assembly
    connector: Cantilever
    plug_mesh: object  # trimesh.Trimesh of the plug, in the plug frame
    free: np.ndarray  # (n,) free dofs of the full 3N vector
    sample_faces: np.ndarray  # (P,) boundary face of each contact sample


class Model(eqx.Module):
    """A built scene: FEM blocks, base reaction rows, contact samples, plug and motion.

    Array fields (traced):
        blocks: free x free parameter-free blocks (n = free dofs).
        reaction: fixed x free blocks, for the base wrench.
        base_offsets: (nb, 3) base node positions minus the base centroid, mm.
        sample_rest: (P, 3) rest positions of contact candidate points on the socket, mm.
        sample_nodes: (P, k) free-node index of each interpolating node (k = 3 P1, 6 P2).
        sample_weights: (P, k) interpolation weights (0 where the node is clamped).
        sample_tri: (P, 3, 3) rest positions of the corners of each point's face, mm.
        sample_corner: (P,) bool, point on a socket edge (use the plug's normal there).
        plug_half: (3,) plug half extents, mm.   plug_radius: () fillet, mm.
        plug_start: (3,) plug centre at t = 0, mm.
        mesh_sdf: exact triangle-mesh SDF of the plug (or None for the analytic SDF).
        neural_sdf: trained neural SDF of the plug (``solver.sdf = "neural"``, else None).
        params: the scene's physical parameters.
    Static fields: dt (s), sizes, solver choices.
    """

    blocks: SparseBlocks
    reaction: SparseBlocks
    base_offsets: jax.Array
    sample_rest: jax.Array
    sample_nodes: jax.Array
    sample_weights: jax.Array
    sample_tri: jax.Array
    sample_corner: jax.Array
    plug_half: jax.Array
    plug_radius: jax.Array
    plug_start: jax.Array
    mesh_sdf: MeshSDF | None
    params: Params
    coupling: jax.Array  # (3,) stiffness N/mm, damping N s/mm, plug mass t (impedance control)
    dt: float = eqx.field(static=True)
    n_steps: int = eqx.field(static=True)
    speed: float = eqx.field(static=True)
    stroke: float = eqx.field(static=True)
    withdraw: bool = eqx.field(static=True)
    control: str = eqx.field(static=True)
    sdf: str = eqx.field(static=True)
    capacity: int = eqx.field(static=True)
    margin: float = eqx.field(static=True)
    contact_solver: str = eqx.field(static=True)
    iterations: int = eqx.field(static=True)
    tolerance: float = eqx.field(static=True)
    dtype: str = eqx.field(static=True)
    method: str = eqx.field(static=True)
    host: HostData = eqx.field(static=True)
    neural_sdf: NeuralSDF | None = None

    @property
    def n_dof(self) -> int:
        """Free degrees of freedom of the socket."""
        return self.blocks.n_rows

    @property
    def n_samples(self) -> int:
        return self.sample_rest.shape[0]

    def trajectory(self) -> np.ndarray:
        """(n_steps + 1, 3) desired plug centre positions at t_k = k dt, mm."""
        t = np.arange(self.n_steps + 1) * self.dt
        t_in = self.stroke / self.speed
        travel = np.where(t <= t_in, self.speed * t, self.stroke)
        if self.withdraw:
            travel = np.where(t > t_in, np.maximum(self.stroke - self.speed * (t - t_in), 0), travel)
        out = np.tile(np.asarray(self.plug_start), (t.size, 1))
        out[:, 2] -= travel
        return out


def _plug_geometry(scene: Scene, geom: Cantilever):
    """Plug half extents (3,), fillet, and centre at t = 0, in mm.

    The default plug is a rounded block whose face x = h_tip lies in the plane of the arm's outer
    face at the tip (so it must push the hook by the full undercut), 1.25 y_u thick, b + 1 mm
    wide and 0.5 mm tall, starting ``clearance`` above the hook's top (as in the CalculiX
    reference, refs/calculix-cantilever).
    """
    p = scene["plug"]
    thick = p["thickness"] or 1.25 * geom.undercut
    width = p["width"] or geom.width + 1.0
    half = np.array([thick, width, p["height"]]) / 2
    start = np.array([geom.h_tip + half[0], 0.0, geom.z_top + p["clearance"] + half[2]])
    return half, p["fillet"], start


def _default_stroke(scene: Scene, geom: Cantilever) -> float:
    """Travel that latches: the plug's top passes 0.3 mm below the retention edge z = L."""
    p = scene["plug"]
    return p["clearance"] + (geom.z_top - geom.length) + p["height"] + 0.3


def _edge_node_lookup(asm: Assembly):
    """Map a sorted vertex pair (a, b) to its P2 edge node index (P2 only)."""
    edges = np.sort(asm.basis.mesh.edges.T, axis=1)
    n_vert = asm.mesh.points.shape[0]
    return {(int(a), int(b)): n_vert + i for i, (a, b) in enumerate(edges)}


def _section_samples(geom: Cantilever, lo, hi, spacing: float, width_spacing: float):
    """Candidate points of the extruded connector: its section outline sampled every
    ``spacing`` (mm, fine: across a contact line) times ``width_spacing`` across the width (mm,
    coarse: along it), kept inside the box [lo, hi].

    Returns points (P, 3), rest outward normals (P, 3) and a (P,) flag for points on a corner
    of the section (an edge of the socket, where the socket has no normal of its own).
    """
    poly = geom.section()
    pts, nrm, corner = [], [], []
    for i in range(len(poly)):
        a, b = poly[i], poly[(i + 1) % len(poly)]
        d = b - a
        length = float(np.hypot(*d))
        if length == 0:
            continue
        n = max(1, math.ceil(length / spacing))
        out = np.array([d[1], -d[0]]) / length  # outward for a counter-clockwise polygon
        for j in range(n):
            pts.append(a + d * j / n)
            nrm.append(out)
            corner.append(j == 0)
    pts, nrm = np.array(pts), np.array(nrm)
    ys = np.linspace(-geom.width / 2, geom.width / 2, math.ceil(geom.width / width_spacing) + 1)
    X = np.stack(
        [np.repeat(pts[:, 0], ys.size), np.tile(ys, len(pts)), np.repeat(pts[:, 1], ys.size)],
        axis=1,
    )
    N = np.stack([np.repeat(nrm[:, 0], ys.size), np.zeros(X.shape[0]), np.repeat(nrm[:, 1], ys.size)], axis=1)
    C = np.repeat(np.array(corner), ys.size)
    keep = np.all((X >= lo) & (X <= hi), axis=1)
    return X[keep], N[keep], C[keep]


def _locate_on_faces(asm: Assembly, faces: np.ndarray, X: np.ndarray):
    """Face of each point (on the boundary) and its interpolating nodes and weights.

    The weights are the element's own shape functions on the face (P1: barycentric; P2:
    vertex l(2l-1), edge 4 l_i l_j), so the contact resolution is independent of the mesh.
    Returns nodes (P, k), weights (P, k), face vertex positions (P, 3, 3) and the face index.
    """
    pts = asm.mesh.points
    tri = pts[faces]  # (F, 3, 3)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    nrm = np.cross(e1, e2)
    area2 = np.linalg.norm(nrm, axis=1)
    d = X[:, None, :] - tri[None, :, 0]  # (P, F, 3)
    plane = np.abs(np.einsum("pfd,fd->pf", d, nrm)) / area2
    l2 = np.einsum("pfd,fd->pf", d, np.cross(nrm, e1)) / area2**2
    l1 = np.einsum("pfd,fd->pf", d, np.cross(e2, nrm)) / area2**2
    l0 = 1 - l1 - l2
    outside = np.maximum(np.maximum(-l0, -l1), -l2).clip(min=0)
    score = plane + outside * area2[None, :] ** 0.5
    f = np.argmin(score, axis=1)
    if np.any(score[np.arange(len(X)), f] > 1e-7):
        raise RuntimeError("contact sample not on the socket surface (geometry/mesh mismatch)")
    r = np.arange(len(X))
    L = np.stack([l0[r, f], l1[r, f], l2[r, f]], axis=1).clip(0, 1)
    L /= L.sum(axis=1, keepdims=True)
    a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
    if asm.element == "P1":
        return np.stack([a, b, c], axis=1), L, tri[f], f
    edge_node = _edge_node_lookup(asm)
    e = [
        [edge_node[tuple(sorted((int(i), int(j))))] for i, j in zip(u, v, strict=True)]
        for u, v in ((a, b), (b, c), (a, c))
    ]
    nodes = np.stack([a, b, c, *[np.array(x) for x in e]], axis=1)
    l0, l1, l2 = L.T
    w = np.stack(
        [
            l0 * (2 * l0 - 1),
            l1 * (2 * l1 - 1),
            l2 * (2 * l2 - 1),
            4 * l0 * l1,
            4 * l1 * l2,
            4 * l0 * l2,
        ],
        axis=1,
    )
    return nodes, w, tri[f], f


def _reachable_faces(mesh: TetMesh, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Boundary faces whose bounding box meets the box [lo, hi] (mm)."""
    faces = mesh.boundary_faces()
    tri = mesh.points[faces]
    fmin, fmax = tri.min(axis=1), tri.max(axis=1)
    hit = np.all(fmax >= lo, axis=1) & np.all(fmin <= hi, axis=1)
    return faces[hit]


def build(scene: Scene, *, progress: bool = False) -> Model:
    """Build the model of a scene on the host: mesh, assembly, contact samples, plug.

    Args:
        scene: a validated scene (``jsnap.load_scene``).
        progress: print what is being built (long builds on fine meshes).

    Returns:
        A :class:`Model` pytree (float64 arrays; rollouts cast to ``solver.dtype``).
    """
    s = scene["solver"]
    geom = connector_geometry(scene)
    say = print if progress else (lambda *a, **k: None)
    mesh = mesh_cantilever(geom, s["mesh_size"], s["hook_mesh_size"])
    asm = assemble(mesh, s["element"])
    say(f"jsnap: {s['element']} mesh, {mesh.cells.shape[0]} tets, {asm.free.size} free dofs")

    free, fixed = asm.free, asm.fixed
    blocks = SparseBlocks.from_scipy(*(m[free][:, free] for m in (asm.K_lam, asm.K_mu, asm.M1)))
    reaction = SparseBlocks.from_scipy(*(m[fixed][:, free] for m in (asm.K_lam, asm.K_mu, asm.M1)))
    base_pos = asm.nodes[fixed[0::3] // 3]
    base_offsets = base_pos - base_pos.mean(axis=0)

    half, radius, start = _plug_geometry(scene, geom)
    m = scene["motion"]
    stroke = m["stroke"] or _default_stroke(scene, geom)
    duration = stroke / m["speed"] * (2 if m["withdraw"] else 1)
    n_steps = math.ceil(duration / s["dt"] - 1e-9)

    # Contact candidates: socket faces the plug can reach along its whole path, plus a reach
    # margin for the socket's own motion toward the plug.
    ct = scene["contact"]
    reach = ct["margin"] + 0.5 * geom.undercut + ct["spacing"]
    lo = start - half - reach
    hi = start + half + reach
    lo[2] -= stroke
    faces = _reachable_faces(mesh, lo, hi)
    if faces.size == 0:
        raise SceneError(
            "the plug's path never comes near the socket (motion.stroke / plug placement): "
            "no contact is possible"
        )
    X, normals, corner = _section_samples(geom, lo, hi, ct["spacing"], ct["width_spacing"])
    nodes, weights, tri, owner = _locate_on_faces(asm, faces, X)
    # Interpolating nodes that are clamped do not move: point them at free node 0, weight 0.
    node_to_free = -np.ones(asm.nodes.shape[0], dtype=np.int64)
    node_to_free[free[0::3] // 3] = np.arange(free.size // 3)
    fnodes = node_to_free[nodes]
    weights = np.where(fnodes < 0, 0.0, weights)
    fnodes = np.where(fnodes < 0, 0, fnodes)

    plug_mesh = rounded_box_mesh(half, radius)
    mesh_sdf = MeshSDF.from_trimesh(plug_mesh) if s["sdf"] == "mesh" else None
    neural_sdf = None
    if s["sdf"] == "neural":  # trained once per plug mesh and settings, then cached on disk
        neural_sdf, info = load_or_train(plug_mesh, progress=progress)
        say(f"jsnap: neural SDF {'loaded from' if info['cached'] else 'trained, cached in'} {info['path']}")
    say(f"jsnap: {X.shape[0]} contact candidate points on {faces.shape[0]} faces")
    del normals  # the kernel uses the deformed face normal

    host = HostData(scene, asm, geom, plug_mesh, free, owner)
    return Model(
        blocks=blocks,
        reaction=reaction,
        base_offsets=jnp.asarray(base_offsets),
        sample_rest=jnp.asarray(X),
        sample_nodes=jnp.asarray(fnodes, jnp.int32),
        sample_weights=jnp.asarray(weights),
        sample_tri=jnp.asarray(tri),
        sample_corner=jnp.asarray(corner),
        plug_half=jnp.asarray(half),
        plug_radius=jnp.asarray(radius, jnp.float64),
        plug_start=jnp.asarray(start),
        mesh_sdf=mesh_sdf,
        neural_sdf=neural_sdf,
        params=Params.from_scene(scene),
        coupling=jnp.asarray([m["coupling_stiffness"], m["coupling_damping"], m["plug_mass"]]),
        dt=s["dt"],
        n_steps=n_steps,
        speed=m["speed"],
        stroke=stroke,
        withdraw=m["withdraw"],
        control=m["control"],
        sdf=s["sdf"],
        capacity=ct["capacity"],
        margin=ct["margin"],
        contact_solver=ct["solver"],
        iterations=ct["iterations"],
        tolerance=ct["tolerance"],
        dtype=s["dtype"],
        method=s["method"],
        host=host,
    )
