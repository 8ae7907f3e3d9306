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

from jsnap._build.fem import Assembly, assemble
from jsnap._geometry.cantilever import Cantilever, TetMesh, mesh_cantilever
from jsnap._core.pmi import Material, SparseBlocks
from jsnap._build.modal import ModalSocket, load_or_compute, socket_from_modes
from jsnap._build.neural_sdf import NeuralSDF, load_or_train
from jsnap._build.reduce import ReducedSocket, build_socket
from jsnap._geometry.scene import Scene, SceneError, connector_geometry
from jsnap._core.sdf import MeshSDF, rounded_box_mesh
from jsnap._core.parts import FullSocket

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
    n_groups: int  # lines of candidate points (see Model.sample_group)
    reduction: dict | None = None  # segmented/reduced socket: orders, build time, cache (_reduce)

    # HostData is a static field of Model, so it is part of the key under which jitted kernels
    # are cached. Kernels read only ``n_groups`` from it: two models equal in that (and in their
    # other static fields and array shapes) share compiled code, so a scene built again, or
    # differing only in values that are arrays (material, k_c...), does not compile anew.
    def __eq__(self, other):
        return isinstance(other, HostData) and self.n_groups == other.n_groups

    def __hash__(self):
        return hash(("HostData", self.n_groups))


class Model(eqx.Module):
    """A built scene: FEM blocks, base reaction rows, contact samples, plug and motion.

    Array fields (traced):
        socket: the socket's linear model as the contact step sees it (``_socket``): the
            full FEM (:class:`FullSocket`), the same in modal coordinates
            (:class:`jsnap._build.modal.ModalSocket`) or a reduced model.
        sample_rest: (P, 3) rest positions of contact candidate points on the socket, mm.
        sample_stencil: (P, 8, 3) rest positions of each point's normal stencils, mm: the
            deformed normals of its side and (at a corner) of the other side are
            ``cross(s3 - s2, s1 - s0)`` and ``cross(s7 - s6, s5 - s4)`` (``_section_samples``).
        sample_corner: (P,) bool, point on a convex socket edge (normal: the plug's, within the
            cone of the two sides' normals).
        sample_group: (P,) int, one group per section side and width position (a line of
            points along the side); sample_order: (P,) int, the point's place along it.
        plug_half: (3,) plug half extents, mm.   plug_radius: () fillet, mm.
        plug_start: (3,) plug centre at t = 0, mm.
        mesh_sdf: exact triangle-mesh SDF of the plug (or None for the analytic SDF).
        neural_sdf: trained neural SDF of the plug (``solver.sdf = "neural"``, else None).
        params: the scene's physical parameters.
    Static fields: dt (s), sizes, solver choices.
    """

    socket: FullSocket | ModalSocket | ReducedSocket
    sample_rest: jax.Array
    sample_stencil: jax.Array
    sample_corner: jax.Array
    sample_group: jax.Array
    sample_order: jax.Array
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
    compliance: float = eqx.field(static=True)
    contact_solver: str = eqx.field(static=True)
    iterations: int = eqx.field(static=True)
    tolerance: float = eqx.field(static=True)
    dtype: str = eqx.field(static=True)
    method: str = eqx.field(static=True)
    host: HostData = eqx.field(static=True)
    neural_sdf: NeuralSDF | None = None
    # contact.gradient: "implicit" (custom_root on the converged solve, _implicit) or "unrolled"
    contact_gradient: str = eqx.field(static=True, default="implicit")

    @property
    def n_dof(self) -> int:
        """Degrees of freedom of the socket's state (free dofs, or reduced coordinates)."""
        return self.socket.n_dof

    @property
    def n_groups(self) -> int:
        """Lines of candidate points (section side x width position)."""
        return int(self.host.n_groups)

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


# Half-size of the stencil whose deformed shape gives a contact point's normal, mm: along the
# section side (capped by the side's length) and across the width. A point force dimples the
# elastic surface over about an element; the normal of the face under the point would tilt with
# that dimple and give frictionless contacts a spurious tangential force, so the normal is taken
# from the deformed positions of points a stencil apart, which follow the face's rotation.
_STENCIL_SIDE = 0.25
_STENCIL_WIDTH = 0.5


def _section_samples(geom: Cantilever, lo, hi, spacing: float, width_spacing: float):
    """Candidate points of the extruded connector: its section outline sampled every
    ``spacing`` (mm, fine: across a contact line) times ``width_spacing`` across the width (mm,
    coarse: along it), kept inside the box [lo, hi].

    Returns points (P, 3); the rest outward normals (P, 2, 3) of the side each point lies on and
    of the other side at a corner (the same side elsewhere); a (P,) flag for points on a convex
    corner of the section (an edge of the socket, where its normal is any in the cone between the
    two sides'); the normal stencils (P, 8, 3) of those two sides: for each, two points along
    the side and two across the width, so that ``cross(s3 - s2, s1 - s0)`` is its outward normal;
    and each point's group (P,) (one group per section side and width position, numbered from 0)
    and its order (P,) along its side.
    """
    poly = geom.section()
    half_w = geom.width / 2
    sides = []  # (start, direction, length, outward normal) of the non-degenerate sides
    for i in range(len(poly)):
        a, b = poly[i], poly[(i + 1) % len(poly)]
        length = float(np.hypot(*(b - a)))
        if length > 0:
            d = (b - a) / length
            sides.append((a, d, length, np.array([d[1], -d[0]])))  # outward: counter-clockwise
    pts, nrm, corner, stn, side_of, pos = [], [], [], [], [], []
    for i, (a, d, length, out) in enumerate(sides):
        _, dp, lp, outp = sides[i - 1]
        convex = dp[0] * d[1] - dp[1] * d[0] > 0
        n = max(1, math.ceil(length / spacing))
        for j in range(n):
            s_here = length * j / n
            pts.append(a + d * s_here)
            own = (a + d * max(0.0, s_here - _STENCIL_SIDE), a + d * min(length, s_here + _STENCIL_SIDE))
            if j == 0 and convex:  # the corner: the previous side's stencil ends here
                other, n_other = (a - dp * min(lp, _STENCIL_SIDE), a), outp
            else:
                other, n_other = own, out
            corner.append(j == 0 and convex)
            side_of.append(i)
            pos.append(j)
            nrm.append((out, n_other))
            stn.append((*own, *other))
    pts, nrm, stn = np.array(pts), np.array(nrm), np.array(stn)  # (S, 2), (S, 2, 2), (S, 4, 2)
    ys = np.linspace(-half_w, half_w, math.ceil(geom.width / width_spacing) + 1)
    ny = ys.size

    def lift(xz, y):  # section coordinates (S, 2) x width positions (ny,) -> (S*ny, 3)
        return np.stack(
            [np.repeat(xz[:, 0], ny), np.broadcast_to(y, (len(xz), ny)).ravel(), np.repeat(xz[:, 1], ny)], 1
        )

    X = lift(pts, ys)
    N = np.stack([lift(nrm[:, k], np.zeros(ny)) for k in range(2)], axis=1)
    C = np.repeat(np.array(corner), ny)
    y_lo, y_hi = np.clip(ys - _STENCIL_WIDTH, -half_w, half_w), np.clip(ys + _STENCIL_WIDTH, -half_w, half_w)
    across = [lift(pts, y_lo), lift(pts, y_hi)]
    stencil = np.stack(
        [lift(stn[:, 0], ys), lift(stn[:, 1], ys), *across, lift(stn[:, 2], ys), lift(stn[:, 3], ys), *across],
        axis=1,
    )
    group = np.repeat(np.array(side_of), ny) * ny + np.tile(np.arange(ny), len(pts))
    order = np.repeat(np.array(pos), ny)
    keep = np.all((X >= lo) & (X <= hi), axis=1)
    _, group = np.unique(group[keep], return_inverse=True)  # renumber 0..G-1
    return X[keep], N[keep], C[keep], stencil[keep], group, order[keep]


def _locate_on_faces(asm: Assembly, faces: np.ndarray, X: np.ndarray, normals: np.ndarray):
    """Face of each point (on the boundary) and its interpolating nodes and weights.

    A point on an edge of the socket lies on several faces; it is given the one whose normal is
    closest to ``normals`` (P, 3), the outward normal of the section side it was sampled on, so
    that every point of one side shares that side's normal. The weights are the element's own
    shape functions on the face (P1: barycentric; P2: vertex l(2l-1), edge 4 l_i l_j), so the
    contact resolution is independent of the mesh.
    Returns nodes (P, k), weights (P, k) and the face index (P,).
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
    if np.any(score.min(axis=1) > 1e-7):
        raise RuntimeError("contact sample not on the socket surface (geometry/mesh mismatch)")
    align = np.einsum("pd,fd->pf", normals, nrm / area2[:, None])
    f = np.argmax(np.where(score <= 1e-7, align, -np.inf), axis=1)
    r = np.arange(len(X))
    L = np.stack([l0[r, f], l1[r, f], l2[r, f]], axis=1).clip(0, 1)
    L /= L.sum(axis=1, keepdims=True)
    a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
    if asm.element == "P1":
        return np.stack([a, b, c], axis=1), L, f
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
    return nodes, w, f


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
    swept_lo, swept_hi = start - half - [0, 0, stroke], start + half
    apart = np.any(swept_hi < mesh.points.min(axis=0)) or np.any(swept_lo > mesh.points.max(axis=0))
    if faces.size == 0 or apart:
        raise SceneError(
            f"the plug's path never touches the socket (motion.stroke = {stroke:g} mm from "
            f"plug.clearance = {scene['plug']['clearance']:g} mm above the hook): no contact is possible"
        )
    X, normals, corner, stencil, group, order = _section_samples(
        geom, lo, hi, ct["spacing"], ct["width_spacing"]
    )
    nodes, weights, owner = _locate_on_faces(asm, faces, X, normals[:, 0])
    pad = max(_STENCIL_SIDE, _STENCIL_WIDTH)
    st_faces = _reachable_faces(mesh, lo - pad, hi + pad)
    st_nodes, st_weights, st_owner = _locate_on_faces(
        asm,
        st_faces,
        stencil.reshape(-1, 3),
        np.repeat(normals, 4, axis=1).reshape(-1, 3),
    )
    # Interpolating nodes that are clamped do not move: point them at free node 0, weight 0.
    node_to_free = -np.ones(asm.nodes.shape[0], dtype=np.int64)
    node_to_free[free[0::3] // 3] = np.arange(free.size // 3)

    def to_free(nodes, weights):
        fnodes = node_to_free[nodes]
        return jnp.asarray(np.where(fnodes < 0, 0, fnodes), jnp.int32), jnp.asarray(
            np.where(fnodes < 0, 0.0, weights)
        )

    fnodes, weights = to_free(nodes, weights)
    st_nodes, st_weights = to_free(
        st_nodes.reshape(*stencil.shape[:2], -1), st_weights.reshape(*stencil.shape[:2], -1)
    )

    plug_mesh = rounded_box_mesh(half, radius)
    mesh_sdf = MeshSDF.from_trimesh(plug_mesh) if s["sdf"] == "mesh" else None
    neural_sdf = None
    if s["sdf"] == "neural":  # trained once per plug mesh and settings, then cached on disk
        neural_sdf, info = load_or_train(plug_mesh, progress=progress)
        say(f"jsnap: neural SDF {'loaded from' if info['cached'] else 'trained, cached in'} {info['path']}")
    say(f"jsnap: {X.shape[0]} contact candidate points on {faces.shape[0]} faces")

    socket = FullSocket(
        blocks=blocks,
        reaction=reaction,
        base_offsets=jnp.asarray(base_offsets),
        sample_nodes=fnodes,
        sample_weights=weights,
        stencil_nodes=st_nodes,
        stencil_weights=st_weights,
    )
    reduction = None
    if s["method"] == "modal":  # the same full model in the coordinates of all its modes
        nu = float(scene["material"]["poissons_ratio"])
        w, Phi, reduction = load_or_compute(asm, nu, progress=progress)
        socket = socket_from_modes(asm, nu, w, Phi, (fnodes, weights), (st_nodes, st_weights))
        what = "loaded from" if reduction["cached"] else f"computed in {reduction['seconds']:.1f} s, cached in"
        say(f"jsnap: modal socket, {w.size} modes {what} {reduction['path']}")
    elif s["method"] != "full":  # segments: the elements of the contact faces (+ margin) and the rest
        seeds = np.concatenate([faces[owner], st_faces[st_owner]])
        socket, reduction = build_socket(
            asm,
            seeds,
            (fnodes, weights),
            (st_nodes, st_weights),
            normals,
            scene,
            progress=progress,
        )
        say(f"jsnap: {s['method']} socket, {' + '.join(map(str, socket.orders))} coordinates")
    host = HostData(scene, asm, geom, plug_mesh, free, owner, int(group.max()) + 1, reduction)
    return Model(
        socket=socket,
        sample_rest=jnp.asarray(X),
        sample_stencil=jnp.asarray(stencil),
        sample_corner=jnp.asarray(corner),
        sample_group=jnp.asarray(group, jnp.int32),
        sample_order=jnp.asarray(order, jnp.int32),
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
        compliance=ct["compliance"],
        contact_solver=ct["solver"],
        iterations=ct["iterations"],
        tolerance=ct["tolerance"],
        contact_gradient=ct["gradient"],
        dtype=s["dtype"],
        method=s["method"],
        host=host,
    )
