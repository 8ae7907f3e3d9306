"""Build layer: a scene in, a :class:`jsnap._core.model.Model` pytree out (host side, float64,
once).

Geometry (the connector's mesh, the preset rigid part, the motion) -> assembly (scikit-fem) ->
contact candidates -> the deformable part's model (full, modal, segmented or reduced) -> the
rigid part's signed distance -> the model. Before the large allocations the build estimates
its memory and refuses with a message naming the setting to change. Units: mm, N, MPa, s, tonne.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from jsnap._build.fem import Assembly, assemble, output_rows, sparse_blocks
from jsnap._build.memory import BuildError, available_memory, require
from jsnap._build.modal import modal_part
from jsnap._build.neural_sdf import load_or_train
from jsnap._build.reduce import build_part, check_reduction
from jsnap._build.samples import (
    locate_on_faces,
    near_path,
    reachable_faces,
    line_reach,
    section_samples,
    turned_samples,
    surface_samples,
)
from jsnap._build.sdf import grid_mesh_sdf, mesh_sdf_from_trimesh
from jsnap._core.contact import ADMM, APGD, PGS, SPG
from jsnap._core.drive import ImpedanceDrive, PositionDrive
from jsnap._core.model import ContactSettings, MeshArrays, Model, Samples
from jsnap._core.params import Params
from jsnap._core.parts import FullPart
from jsnap._core.sdf import BoundedSDF, RoundedBoxSDF, RoundedCylinderSDF
from jsnap._geometry.motion import quat_matrix, sample_poses, straight_insertion, straight_poses
from jsnap._geometry.part import load_part, load_rigid
from jsnap._geometry.presets import generate, hook_of
from jsnap._geometry.size import STENCIL_SIDE, STENCIL_WIDTH
from jsnap._geometry.scene import (
    Scene,
    SceneError,
    SceneWarning,
    motion_keyposes,
    scene_file,
    sdf_kind,
)

__all__ = [
    "BuildError", "BuildReport", "PartEstimate", "available_memory", "build", "build_model", "check_memory",
    "check_part_size", "estimate_part", "params_from_scene", "with_capacity",
]  # fmt: skip

_SOLVERS = {"apgd": APGD, "spg": SPG, "admm": ADMM, "pgs": PGS}
# Half-width of the band about a mesh rigid part where its grid SDF is exact, in contact
# resolutions: twice the depth the penetration flag reads (rollout.PENETRATION_DEPTH, 4).
_GRID_BAND = 8.0
# The same for the neural SDF, whose lower bound is the plain bounding box: the network may read
# below it by its own error (default plug: 1.3 µm mean, 46 µm at most within 0.2 mm of the
# surface, benchmarks/sdf_accuracy.py), so points up to 50 µm past the margin get the network too.
_NEURAL_SLACK = 5e-2
# Dense n x n float64 matrices alive at once while a dense model is prepared (S, its Cholesky
# factor, the inverse and the symmetrised copies) or its modes computed (K, M, the eigenvectors
# and LAPACK's workspace).
_DENSE_COPIES = 6
# Bytes per dof of the assembled blocks (K_lam, K_mu, M1 and the stiffness made of them: P2
# rows hold ~80 nonzeros of 12 bytes, float64 and int32 index) and of the reduced model's
# largest dense array, the (n, r) reconstruction of the free dofs (r up to ~2000 columns).
_SPARSE_BYTES_PER_DOF = 4 * 80 * 12
_RECON_COLUMNS = 2000


@dataclass
class BuildReport:
    """What a build did, for the command line and benchmarks (host side, not part of the model).

    Attributes:
        seconds: wall time of the build, s.
        tets, full_dof: mesh size.   contact_points: candidate points.
        reduction: the modal/reduced artefact's metadata (cache path, whether it was read from
            the cache, orders, build time), or None.
        sdf: the neural SDF's training/cache information, or None.
    """

    seconds: float = 0.0
    tets: int = 0
    full_dof: int = 0
    contact_points: int = 0
    reduction: dict | None = None
    sdf: dict | None = None


def params_from_scene(scene: Scene) -> Params:
    """The scene's physical parameters."""
    m = scene["material"]
    return Params.create(
        m["youngs_modulus"],
        m["poissons_ratio"],
        m["density"],
        m["rayleigh_alpha"],
        m["rayleigh_beta"],
        scene["contact"]["friction"],
    )


def rollout_dtype(scene: Scene) -> str:
    """``solver.dtype``, or the default: float32 for the reduced model, float64 for the others
    (full, its modal form, segmented).

    The default scene's peak insertion force in float32 is within 1 % of float64 with the
    reduced model (-0.76 %), and more than 1 % off with the full one (-1.15 %), whose dense
    ``S^-1`` rounded to float32 perturbs the stiff contact response, and the segmented one
    (-1.28 %), whose stiff interface springs float32 rounds (``benchmarks/precision.py``)."""
    s = scene["solver"]
    return s["dtype"] or ("float32" if s["method"] == "reduced" else "float64")


def _estimate_dof(mesh, element: str) -> int:
    """Free dofs the assembly will have (P2: vertices and edge midpoints), before assembling."""
    nodes = mesh.points.shape[0]
    if element == "P2":
        edges = np.sort(mesh.cells[:, [[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]]].reshape(-1, 2), axis=1)
        nodes += np.unique(edges, axis=0).shape[0]
    return 3 * nodes


def check_memory(n_dof: int, method: str, available: int | None = None) -> int:
    """Estimated bytes of the build and ``prepare`` of an ``n_dof`` part by ``method``; raises
    :class:`BuildError` naming the settings to change when it would not fit in memory.

    The dense models (full, modal, segmented) hold a few n x n matrices. The reduced one never
    does: its build is checked here for the assembled sparse blocks and its (n, r) output arrays,
    and again before each sparse factorisation and dense subspace, from their actual sizes
    (``jsnap._build.linalg``, ``jsnap._build.reduce``)."""
    dense = method in ("full", "modal", "segmented")
    if dense:
        estimate = _DENSE_COPIES * 8 * n_dof**2
        hint = "solver.method = 'reduced' or a larger solver.mesh_size"
    else:
        estimate = _SPARSE_BYTES_PER_DOF * n_dof + 2 * 8 * n_dof * _RECON_COLUMNS
        hint = "a larger solver.mesh_size"
    return require(estimate, f"solver.method = {method!r} with {n_dof} dof", hint, available)


# Volume of one tetrahedron at element size h, in h^3. gmsh's (every preset but the cantilever,
# and surface files) fill 0.19-0.20 h^3 each on the shipped parts at their fine sizes (0.15-0.19
# at their default ones, where the part is a few elements thick); the cantilever's structured mesh
# 0.12-0.15 h^3 (six per cell of about h^3, more where a side is not a whole number of h). The
# estimate is for sizes far off, so the fine sizes' values (fewer tetrahedra) are taken: it
# counts too few, never too many (the shipped scenes' dofs 1.6-1.8 times the estimate at their
# sizes, 1.1-1.2 at a third of them; the annular sector, one element wide, 3.8 times).
_TET_VOLUME = {"structured": 0.14, "gmsh": 0.2}
# Dofs per tetrahedron of a large mesh: P2 has a node at each vertex and edge midpoint, 4.5
# dofs per tetrahedron at 100k dofs (4 in an unbounded mesh, more where surface dominates); P1
# 0.6 (a vertex per ~5 tetrahedra).
_DOF_PER_TET = {"P2": 4.5, "P1": 0.6}
# The largest part benchmarks/scale.py builds: 118008 dofs, a 166 s build at a 5.3 GB peak on 2
# cores. A part estimated beyond it warns that its build takes longer than anything measured.
_MEASURED_DOF = 118_008
# From this many dofs on a build takes ten seconds or more: it reports its phases (progress).
_LONG_DOF = 20_000
# A connector key that sets the part's volume: one whose 1 % change moves it by at least 0.3 %.
_VOLUME_ELASTICITY = 0.3


@dataclass
class PartEstimate:
    """The deformable part's size before it is meshed (:func:`estimate_part`).

    Attributes:
        volume: its volume, mm^3.   tets, dof: the elements and free dofs expected (to within
            a factor 2).   source: what sets the volume, for messages (scene keys or the file).
    """

    volume: float
    tets: int
    dof: int
    source: str


def _volume_keys(kind: str, c) -> str:
    """The (at most three) connector keys that set the preset's volume most, the most grown
    from the shipped preset's first (``connector.gap = 500 mm, connector.width = 4 mm``)."""
    import tomllib

    from jsnap._geometry.presets import preset_volume
    from jsnap._geometry.scene import CONNECTORS, default_scene_path

    name = "default" if kind == "cantilever" else kind
    try:
        shipped = tomllib.loads((default_scene_path().parent / f"{name}.toml").read_text())["connector"]
    except (OSError, KeyError, tomllib.TOMLDecodeError):
        shipped = {}
    v0, scored = preset_volume(kind, c), []
    for key, spec in CONNECTORS[kind].items():
        value = c.get(key)
        if spec.unit != "mm" or not isinstance(value, float) or value <= 0:
            continue
        try:
            grown = preset_volume(kind, {**c, key: value * 1.01})
        except ValueError:
            continue
        elasticity = (grown / v0 - 1) / 0.01
        if elasticity >= _VOLUME_ELASTICITY:
            before = shipped.get(key)
            growth = value / before if isinstance(before, int | float) and before > 0 else 1.0
            scored.append((elasticity * max(1.0, growth), key, value))
    top = sorted(scored, reverse=True)[:3]
    return ", ".join(f"connector.{key} = {value:g} mm" for _, key, value in top)


def estimate_part(scene: Scene) -> PartEstimate | None:
    """The deformable part's volume and the elements and dofs it will be meshed into at
    ``solver.mesh_size``, before meshing it: a preset's from its dimensions
    (:func:`jsnap._geometry.presets.preset_volume`), a surface file's from the volume it encloses.
    None for tetrahedra from a file (they are counted as they are read) or a file that cannot be
    used (the build says why)."""
    from jsnap._geometry.part import SURFACE_SUFFIXES, PartError, surface_volume
    from jsnap._geometry.presets import preset_volume

    s, c = scene["solver"], scene["connector"]
    h = s["mesh_size"]
    if c:
        volume = preset_volume(c["type"], c)
        kind = "structured" if c["type"] == "cantilever" else "gmsh"
        source = f"{volume:.4g} mm^3 from {_volume_keys(c['type'], c)}"
        meshed = volume
        if c["type"] == "annular":  # a sector one element wide: as wide as an element when thinner
            meshed *= max(1.0, h / (c["radius"] * math.radians(c["sector"])))
    else:
        path = scene_file(scene, "part.mesh")
        if path.suffix.lower() not in SURFACE_SUFFIXES:
            return None
        try:
            volume = surface_volume(path, scene["part"]["units"])
        except PartError:
            return None
        kind, source = "gmsh", f"{volume:.4g} mm^3 enclosed by part.mesh = {scene['part']['mesh']!r}"
        meshed = volume
    tets = meshed / (_TET_VOLUME[kind] * h**3)
    return PartEstimate(volume, int(tets), int(tets * _DOF_PER_TET[s["element"]]), source)


def _count(n: int) -> str:
    """``n`` for a message: 5742, 40.5k, 52.3 million."""
    return str(n) if n < 10_000 else f"{n / 1e3:.3g}k" if n < 1_000_000 else f"{n / 1e6:.3g} million"


def _round_up(x: float) -> float:
    """``x`` rounded up to two significant digits."""
    unit = 10.0 ** (math.floor(math.log10(x)) - 1)
    return math.ceil(x / unit * (1 - 1e-9)) * unit


def check_part_size(scene: Scene, available: int | None = None) -> PartEstimate | None:
    """Refuse, before meshing, a part that the build could not hold: :func:`check_memory` of the
    dofs :func:`estimate_part` expects, its message naming ``solver.mesh_size``, what sets the
    part's volume and the element size that fits; warn (:class:`SceneWarning`) when the part is
    larger than any the build is measured on. Returns the estimate (None: nothing to mesh).

    Raises:
        BuildError: the part at ``solver.mesh_size`` would not fit in memory.
    """
    est = estimate_part(scene)
    if est is None:
        return None
    s = scene["solver"]
    h, method = s["mesh_size"], s["method"]
    about = (
        f"solver.mesh_size = {h:g} mm: the part ({est.source}) would be meshed into about {_count(est.tets)} "
        f"tetrahedra, {_count(est.dof)} {s['element']} dofs (estimated before meshing)"
    )
    available = available_memory() if available is None else available
    try:
        check_memory(est.dof, method, available)
    except BuildError as err:
        lo, hi = 1, est.dof  # the most dofs that fit (check_memory grows with them)
        while hi - lo > max(1, lo // 100):
            mid = (lo + hi) // 2
            try:
                check_memory(mid, method, available)
                lo = mid
            except BuildError:
                hi = mid
        fit = _round_up(h * (est.dof / lo) ** (1 / 3))
        raise BuildError(f"{about}; {err} (here solver.mesh_size >= {fit:g} mm)") from None
    if est.dof > _MEASURED_DOF:
        fit = _round_up(h * (est.dof / _MEASURED_DOF) ** (1 / 3))
        warnings.warn(
            f"{about}: more than the largest part the build is measured on ({_count(_MEASURED_DOF)} dofs: "
            f"about 3 minutes and 5 GB on 2 cores, benchmarks/scale.py); expect a build of many minutes, "
            f"or use solver.mesh_size >= {fit:g} mm",
            SceneWarning,
            stacklevel=4,
        )
    return est


@dataclass
class _Rigid:
    """The rigid part as the build needs it: its surface in its own frame, a box about its
    frame's origin that holds it, the fillet radius and shape of a preset plug (a rounded box
    or cylinder), its start centre."""

    mesh: object
    half: np.ndarray
    radius: float | None
    start: np.ndarray
    shape: str = "box"


@dataclass
class _Geometry:
    """What the geometry layer gives the build: the part's mesh (its fixed region in
    ``base_nodes``), the rigid part, the desired poses (n + 1, 3 or 7), the insertion axis, and
    for the canonical cantilever its section and stroke (its own contact sampling)."""

    mesh: object
    rigid: _Rigid
    poses: np.ndarray
    axis: np.ndarray
    cantilever: object | None = None
    stroke: float | None = None
    radius: float | None = None


def _geometry(scene: Scene) -> _Geometry:
    """The scene's deformable part, rigid part and motion (presets or files)."""
    s, m = scene["solver"], scene["motion"]
    c = scene["connector"]
    preset = generate(c["type"], c, scene["plug"] or {}, s["mesh_size"]) if c else None
    if preset is not None:
        mesh = preset.mesh
    else:
        p = scene["part"]
        mesh = load_part(
            scene_file(scene, "part.mesh"),
            units=p["units"],
            fixed=p["fixed"],
            fixed_box=p["fixed_box"],
            mesh_size=s["mesh_size"],
        )
    if scene["rigid"]:
        r = scene["rigid"]  # placed at its start pose: the SDF, the candidates and the poses see it there
        surface = load_rigid(
            scene_file(scene, "rigid.mesh"), units=r["units"], position=r["position"], rotation=r["rotation"]
        )
        rigid = _Rigid(surface.mesh, surface.half, None, surface.centroid)
    else:
        plug = preset.plug
        rigid = _Rigid(plug.mesh(), plug.half, plug.radius, plug.start, plug.shape)
    keys = motion_keyposes(scene)
    if keys is None:
        d = np.asarray(m["direction"] or [0.0, 0.0, -1.0], np.float64)
        d = d / np.linalg.norm(d)
        stroke = m["stroke"] if m["stroke"] is not None else preset.stroke
        # A preset's turned rigid part (the box lid's tilted box) goes straight in, turned.
        turned = None if scene["rigid"] else preset.plug.rotation
        if m["direction"] is None and turned is None:
            poses = straight_insertion(rigid.start, m["speed"], stroke, m["withdraw"], s["dt"])
        else:
            poses = straight_poses(rigid.start, d, m["speed"], stroke, m["withdraw"], s["dt"])
            if turned is None:
                poses = poses[:, :3]
            else:
                poses[:, 3:] = turned
    else:
        poses = sample_poses(*keys, rigid.start, s["dt"])
        net = poses[np.argmax(np.linalg.norm(poses[:, :3] - poses[0, :3], axis=1)), :3] - poses[0, :3]
        if np.linalg.norm(net) < 1e-9:
            raise SceneError("the motion's waypoints never move the rigid part's centre: no insertion axis")
        d = net / np.linalg.norm(net)
    if c and c["type"] == "cantilever":
        return _Geometry(mesh, rigid, poses, d, hook_of(c), m["stroke"] or preset.stroke)
    if c and c["type"] == "annular":  # its hook section turned about z (a sector: straight down)
        return _Geometry(mesh, rigid, poses, d, hook_of(c), m["stroke"] or preset.stroke, c["radius"])
    return _Geometry(mesh, rigid, poses, d)


def _swept_box(rigid: _Rigid, poses: np.ndarray):
    """Bounding box (lo, hi) of the rigid part's surface over all its poses, mm."""
    v = np.asarray(rigid.mesh.vertices, np.float64)
    every = max(1, poses.shape[0] // 200)
    chosen = np.concatenate([poses[::every], poses[-1:]])
    if poses.shape[1] == 7:
        world = np.einsum("kij,vj->kvi", quat_matrix(chosen[:, 3:]), v) + chosen[:, None, :3]
    else:
        world = v[None] + chosen[:, None, :3]
    return world.reshape(-1, 3).min(axis=0), world.reshape(-1, 3).max(axis=0)


def _contact_candidates(scene: Scene, g: _Geometry, asm: Assembly):
    """Candidate points where the rigid part can reach along its path, located on the mesh."""
    ct = scene["contact"]
    mesh, rigid, poses = g.mesh, g.rigid, g.poses
    straight_down = motion_keyposes(scene) is None and scene["motion"]["direction"] is None
    if g.cantilever is not None and not scene["rigid"] and straight_down:
        # The preset's faces the rigid part can reach along its whole path, plus a reach margin
        # for the deformable part's own motion toward it.
        stroke = g.stroke
        reach = ct["margin"] + 0.5 * g.cantilever.undercut + ct["spacing"]
        lo = rigid.start - rigid.half - reach
        hi = rigid.start + rigid.half + reach
        lo[2] -= stroke
        swept_lo, swept_hi = rigid.start - rigid.half - [0, 0, stroke], rigid.start + rigid.half
    else:
        swept_lo, swept_hi = _swept_box(rigid, poses)
        # The deformable part moves toward the rigid part by a fraction of its size at most.
        reach = ct["margin"] + ct["spacing"] + 0.1 * float(np.min(rigid.half))
        lo, hi = swept_lo - reach, swept_hi + reach
        stroke = float(np.max(np.linalg.norm(poses[:, :3] - poses[0, :3], axis=1)))
    faces = reachable_faces(mesh, lo, hi)
    apart = np.any(swept_hi < mesh.points.min(axis=0)) or np.any(swept_lo > mesh.points.max(axis=0))
    if faces.size == 0 or apart:
        raise BuildError(
            f"the rigid part's path never comes near the deformable part (it travels {stroke:g} mm, its "
            f"swept box [{', '.join(f'{a:.3g}' for a in swept_lo)}] - [{', '.join(f'{a:.3g}' for a in swept_hi)}] mm "
            "misses the part): no contact is possible; check motion.stroke, motion.direction or the waypoints"
        )
    sampler = surface_samples
    if g.radius is not None and ct["sampling"] == "auto":
        sampler = turned_samples
        X, normals, corner, stencil, group, order = turned_samples(
            g.cantilever, g.radius, mesh, lo, hi, ct["spacing"], ct["width_spacing"], scene.size
        )
    elif g.cantilever is not None and ct["sampling"] == "auto":
        # The canonical cantilever keeps its own section sampling: the general one differs from
        # it by 0.16 % in the default scene's peak, but by 3 % on a 1.2 mm mesh (see "Where
        # contact is sampled" in docs/own-connector.md).
        sampler = section_samples
        X, normals, corner, stencil, group, order = section_samples(
            g.cantilever, lo, hi, ct["spacing"], ct["width_spacing"], scene.size
        )
    else:
        X, normals, corner, stencil, group, order = surface_samples(
            mesh, lo, hi, g.axis, ct["spacing"], ct["width_spacing"], scene.size
        )
        # Only where the rigid part's surface passes near, not all its swept box holds (a
        # housing's box encloses the prongs it slides along): the contact region, and with it
        # the reduction's order, grows with the faces it touches, not with its travel.
        near = near_path(X, rigid.mesh.vertices, rigid.mesh.faces, poses, reach)
        X, normals, corner, stencil, order = X[near], normals[near], corner[near], stencil[near], order[near]
        _, group = np.unique(group[near], return_inverse=True)
    if X.shape[0] == 0:
        raise BuildError("no contact candidate on the part's surface where the rigid part passes")
    nodes, weights, owner = locate_on_faces(asm, faces, X, normals[:, 0], scene.size)
    pad = max(STENCIL_SIDE, STENCIL_WIDTH) * scene.size
    st_faces = reachable_faces(mesh, lo - pad, hi + pad)
    st_nodes, st_weights, st_owner = locate_on_faces(
        asm, st_faces, stencil.reshape(-1, 3), np.repeat(normals, 4, axis=1).reshape(-1, 3), scene.size
    )
    # Interpolating nodes that are clamped do not move: point them at free node 0, weight 0.
    node_to_free = -np.ones(asm.nodes.shape[0], dtype=np.int64)
    node_to_free[asm.free[0::3] // 3] = np.arange(asm.free.size // 3)

    def to_free(nodes, weights):
        fnodes = node_to_free[nodes]
        return np.where(fnodes < 0, 0, fnodes).astype(np.int32), np.where(fnodes < 0, 0.0, weights)

    sample = to_free(nodes, weights)
    st = to_free(st_nodes.reshape(*stencil.shape[:2], -1), st_weights.reshape(*stencil.shape[:2], -1))
    seeds = np.concatenate([faces[owner], st_faces[st_owner]])
    line, reach = line_reach(X, group, order)
    samples = Samples(
        rest=jnp.asarray(X),
        stencil=jnp.asarray(stencil),
        corner=jnp.asarray(corner),
        group=jnp.asarray(group, jnp.int32),
        order=jnp.asarray(order, jnp.int32),
        line=jnp.asarray(line),
        reach=jnp.asarray(reach),
        n_groups=int(group.max()) + 1,
        spacing=float(ct["spacing"]),
        hand_over={"auto": sampler is surface_samples, "on": True, "off": False}[ct["hand_over"]],
    )
    return samples, sample, st, seeds, normals


def _rigid_sdf(scene: Scene, rigid: _Rigid, report: BuildReport, progress: bool):
    """The rigid part's signed distance component (``solver.sdf``)."""
    kind = sdf_kind(scene)
    if kind == "analytic":
        exact = RoundedCylinderSDF if rigid.shape == "cylinder" else RoundedBoxSDF
        return exact(jnp.asarray(rigid.half), jnp.asarray(rigid.radius, jnp.float64))
    if kind == "mesh":
        # Exact within twice the depth the penetration flag reads (and so over the margin and the
        # normals' stencil too); beyond, the side of the surface, which is all a decision needs.
        ct = scene["contact"]
        band = _GRID_BAND * max(float(ct["margin"]), float(ct["spacing"]))
        return grid_mesh_sdf(mesh_sdf_from_trimesh(rigid.mesh), band, progress=progress)
    # Trained once per rigid-part mesh and settings, then cached on disk.
    net, info = load_or_train(rigid.mesh, progress=progress)
    report.sdf = info
    # A lower bound that culls far points cheaply: a plain box holding the surface.
    bound = RoundedBoxSDF(jnp.asarray(rigid.half), jnp.asarray(0.0, jnp.float64))
    return BoundedSDF(net, bound, _NEURAL_SLACK)


def build_model(scene: Scene, *, progress: bool = False) -> tuple[Model, BuildReport]:
    """:func:`build`, with a :class:`BuildReport` of what was done."""
    t0 = time.perf_counter()
    report = BuildReport()
    say = print if progress else (lambda *a, **k: None)
    s, m, ct = scene["solver"], scene["motion"], scene["contact"]
    expected = check_part_size(scene)  # in seconds, before a mesh that could not be held is made
    if expected is not None and expected.dof >= _LONG_DOF:
        say(
            f"jsnap: meshing the part at solver.mesh_size = {s['mesh_size']:g} mm: about {expected.tets} tets, "
            f"{expected.dof} dofs expected"
        )
    g = _geometry(scene)
    mesh = g.mesh
    n_dof = _estimate_dof(mesh, s["element"])
    check_memory(n_dof, s["method"])
    if n_dof >= _LONG_DOF:
        say(f"jsnap: {mesh.cells.shape[0]} tets meshed; assembling {n_dof} dofs")
    asm = assemble(mesh, s["element"])
    report.tets, report.full_dof = int(mesh.cells.shape[0]), int(asm.free.size)
    say(f"jsnap: {s['element']} mesh, {report.tets} tets, {report.full_dof} free dofs")

    with jax.enable_x64(True):
        if n_dof >= _LONG_DOF:
            say("jsnap: sampling the contact candidates on the part's surface")
        samples, sample, stencil, seeds, normals = _contact_candidates(scene, g, asm)
        report.contact_points = int(samples.rest.shape[0])
        say(f"jsnap: {report.contact_points} contact candidate points")
        if s["method"] == "reduced":  # refused now, not after the SDF and the factorisations
            need = max(b for b, _ in check_reduction(asm, seeds, sample, normals, scene))
            say(f"jsnap: the reduction's largest arrays estimated at {need / 1e9:.2f} GB")
        rigid = _rigid_sdf(scene, g.rigid, report, progress)
        if report.sdf is not None:
            what = "loaded from" if report.sdf["cached"] else "trained, cached in"
            say(f"jsnap: neural SDF {what} {report.sdf['path']}")

        if s["method"] == "full":
            f = asm.free
            blocks = sparse_blocks(*(a[f][:, f] for a in (asm.K_lam, asm.K_mu, asm.M1)))
            out = {k: jnp.asarray(v) for k, v in output_rows(asm).items()}
            part = FullPart(
                blocks=blocks,
                **out,
                sample_nodes=jnp.asarray(sample[0]),
                sample_weights=jnp.asarray(sample[1]),
                stencil_nodes=jnp.asarray(stencil[0]),
                stencil_weights=jnp.asarray(stencil[1]),
            )
        elif s["method"] == "modal":  # the same full model in the coordinates of all its modes
            nu = scene["material"]["poissons_ratio"]
            part, report.reduction = modal_part(asm, nu, sample, stencil, progress=progress)
            say(f"jsnap: modal part, {part.n_dof} modes")
        else:  # segments: the elements of the contact faces (+ margin) and the rest
            part, report.reduction = build_part(
                asm, seeds, sample, stencil, normals, scene, progress=progress, points=np.asarray(samples.rest)
            )
            say(f"jsnap: {s['method']} part, {' + '.join(map(str, part.orders))} coordinates")

        solver = _SOLVERS[ct["solver"]](
            max_iters=ct["iterations"], tol=ct["tolerance"], implicit=ct["gradient"] == "implicit"
        )
        if m["control"] == "position":
            drive = PositionDrive()
        else:
            keys = ("coupling_stiffness", "coupling_damping", "plug_mass")
            drive = ImpedanceDrive(*(jnp.asarray(m[key], jnp.float64) for key in keys))
        model = Model(
            part=part,
            samples=samples,
            rigid=rigid,
            drive=drive,
            # More slots than candidate points would only be empty slots (and top_k refuses).
            contact=ContactSettings(
                solver,
                min(ct["capacity"], report.contact_points),
                ct["margin"],
                ct["compliance"],
                ct["stabilisation"],
            ),
            params=params_from_scene(scene),
            motion=jnp.asarray(g.poses),
            mesh=MeshArrays(
                jnp.asarray(asm.nodes), jnp.asarray(asm.cells, jnp.int32), jnp.asarray(asm.free, jnp.int32)
            ),
            dt=float(s["dt"]),
            dtype=rollout_dtype(scene),
            axis=jnp.asarray(g.axis),
        )
    report.seconds = time.perf_counter() - t0
    return model, report


def build(scene: Scene, *, progress: bool = False) -> Model:
    """Build the model of a scene on the host: mesh, assembly, contact candidates, the
    deformable part's model (reduced by default), the rigid part's signed distance.

    Args:
        scene: a validated scene (``jsnap.load_scene``).
        progress: print what is being built (long builds on fine meshes).

    Returns:
        A :class:`jsnap.Model` pytree (float64 arrays; rollouts cast to ``solver.dtype``).

    Raises:
        BuildError: the build would not fit in memory, or the motion never makes contact
            (the message names the setting to change).
    """
    return build_model(scene, progress=progress)[0]


def with_capacity(model: Model, capacity: int) -> Model:
    """The same model with ``capacity`` contact buffer slots (at most its candidate points).

    Only the contact buffer changes: the part's model, its prepared operator and the states of
    a rollout stay valid. The buffer's size is static, so a rollout compiles anew.
    """
    if int(capacity) < 1:
        raise ValueError(f"contact capacity must be at least 1 slot, got {capacity}")
    settings = dataclasses.replace(model.contact, capacity=min(int(capacity), model.n_samples))
    return dataclasses.replace(model, contact=settings)
