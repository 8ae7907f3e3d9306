"""Neural signed distance of the plug: a Flax MLP trained on exact mesh distances.

A drop-in for the exact SDFs of :mod:`jsnap._core.sdf`, with the same convention: ``φ(p)`` in mm,
negative inside, for points ``p`` in the plug's frame; the normal is ``∇φ`` (by ``jax.vjp``),
normalised. :func:`neural_sdf_and_normal` is a pure JAX function of ``(net, points)``: it jits,
vmaps and differentiates (w.r.t. the points and the weights).

The network (default 3 → 64 → 64 → 64 → 1, softplus with β = 100) sees its input normalised per
axis to ``[-1, 1]`` over the *training domain*, the mesh's bounding box padded by
``NeuralSDFConfig.pad``; its output is scaled back to mm. Outside that domain the net is never
evaluated: ``φ(p) = φ_net(clamp(p)) + |p − clamp(p)|``, continuous, positive and growing like the
true distance, so points far from the plug can never fake a contact.

Training (host, once per mesh and settings, :func:`train`): points sampled near the surface
(most of them: offsets along the face normals, half with σ = band/4, half with σ = band) and
uniformly in the domain, labelled with exact signed distances from our JAX triangle-mesh SDF
(:class:`jsnap._core.sdf.MeshSDF`); Adam with a warm-up + cosine learning-rate schedule on an L1
loss, points farther than ``band`` from the surface weighted down (only contact-relevant
accuracy matters). Weights are saved as ``.npz`` with a format version, the architecture, the
normalisation, the hash of the mesh and settings and a checksum (:func:`save`, :func:`load`),
and cached under that hash (:func:`load_or_train`; ``$JSNAP_CACHE`` or ``~/.cache/jsnap``).

Units: mm.
"""

from __future__ import annotations

import dataclasses
import hashlib
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import equinox as eqx
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import trimesh

from jsnap._build.cache import ArtefactError, KeyHash, artefact_path, cached, load_artefact, save_artefact
from jsnap._build.sdf import mesh_sdf_from_trimesh
from jsnap._core.sdf import (
    MeshSDF,
    NeuralSDF,
    _neural_phi,
    activation,
    mesh_sdf_and_normal,
    neural_sdf_and_normal,
)
from jsnap._core.util import x64

__all__ = [
    "NeuralSDFConfig",
    "accuracy_report",
    "band_errors",
    "cache_key",
    "load",
    "load_mesh",
    "load_or_train",
    "save",
    "shipped_path",
    "summarise",
    "train",
]

ACTIVATIONS = ("softplus", "silu", "gelu", "tanh")

# Weights shipped with the package (read-only), used when the cache has none for the key: the
# default plug's, so that a first run does not spend the training (~30 s on 2 cores) and every
# machine uses the weights that the committed benchmark results were made with.
SHIPPED = Path(__file__).parents[1] / "data" / "neural_sdf"


# --------------------------------------------------------------------------------------------
# Settings and network
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class NeuralSDFConfig:
    """Architecture and training settings (all part of the cache key). Lengths in mm.

    Attributes:
        width: neurons per hidden layer.
        depth: number of hidden layers.
        activation: one of ``softplus`` (``softplus(β x)/β``, a smoothed ReLU), ``silu``,
            ``gelu``, ``tanh``.
        softplus_beta: β of the softplus activation (in normalised input units).
        steps: Adam steps.
        batch: points per step.
        learning_rate: peak learning rate (after ``warmup`` steps, then cosine decay to 1 %).
        warmup: linear warm-up steps.
        samples: labelled training points (exact distances), drawn once.
        band: half-width of the contact-relevant shell around the surface, mm: accuracy is
            optimised and reported for ``|φ| ≤ band``.
        pad: padding of the mesh's bounding box that makes the training domain, mm (≥ band).
        box_fraction: fraction of the samples drawn uniformly in the domain (the rest near the
            surface).
        far_weight: loss weight of points farther than ``band`` from the surface.
        seed: seed of the sampling, the initial weights and the batches.
    """

    width: int = 64
    depth: int = 3
    activation: str = "softplus"
    softplus_beta: float = 100.0
    steps: int = 3000
    batch: int = 2048
    learning_rate: float = 5e-3
    warmup: int = 100
    samples: int = 100_000
    band: float = 0.2
    pad: float = 0.3
    box_fraction: float = 0.15
    far_weight: float = 0.1
    seed: int = 0

    def __post_init__(self):
        positive_int = ("width", "depth", "steps", "batch", "samples")
        for name in positive_int:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"NeuralSDFConfig.{name} = {v!r}: must be an integer >= 1")
        for name in ("warmup", "seed"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ValueError(f"NeuralSDFConfig.{name} = {v!r}: must be an integer >= 0")
        if self.activation not in ACTIVATIONS:
            raise ValueError(
                f"NeuralSDFConfig.activation = {self.activation!r}: must be one of {', '.join(ACTIVATIONS)}"
            )
        for name in ("softplus_beta", "learning_rate", "band"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and np.isfinite(v) and v > 0):
                raise ValueError(f"NeuralSDFConfig.{name} = {v!r}: must be a finite number > 0")
        if not (isinstance(self.pad, int | float) and np.isfinite(self.pad) and self.pad >= self.band):
            raise ValueError(
                f"NeuralSDFConfig.pad = {self.pad!r}: must be >= band = {self.band} (the contact "
                "shell must lie inside the training domain)"
            )
        for name in ("box_fraction", "far_weight"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and 0.0 <= v <= 1.0):
                raise ValueError(f"NeuralSDFConfig.{name} = {v!r}: must be in [0, 1]")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> NeuralSDFConfig:
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown NeuralSDFConfig keys: {', '.join(sorted(unknown))}")
        return cls(**d)

    @property
    def architecture(self) -> dict:
        return dict(
            inputs=3,
            width=self.width,
            depth=self.depth,
            outputs=1,
            activation=self.activation,
            softplus_beta=self.softplus_beta,
        )


class _MLP(nn.Module):
    """``depth`` hidden Dense layers of ``width`` neurons, then a scalar; input normalised."""

    width: int
    depth: int
    activation: str
    beta: float

    @nn.compact
    def __call__(self, x):
        act = activation(self.activation, self.beta)
        for i in range(self.depth):
            x = act(nn.Dense(self.width, name=f"hidden_{i}")(x))
        return nn.Dense(1, name="out")(x)[..., 0]


def _template_params(config: NeuralSDFConfig, key=None):
    mlp = _MLP(config.width, config.depth, config.activation, config.softplus_beta)
    x = jnp.zeros((1, 3), jnp.float32)
    if key is None:
        return jax.eval_shape(lambda: mlp.init(jax.random.PRNGKey(0), x))["params"]
    return mlp.init(key, x)["params"]


# --------------------------------------------------------------------------------------------
# Meshes, hashes, cache
# --------------------------------------------------------------------------------------------


def _check_mesh(mesh, name="mesh") -> MeshSDF:
    """The exact SDF of ``mesh``; ValueError naming ``name`` if it cannot have one."""
    if not isinstance(mesh, trimesh.Trimesh):
        raise TypeError(f"{name}: expected a trimesh.Trimesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0:
        raise ValueError(f"{name}: the mesh has no triangles")
    try:
        return mesh_sdf_from_trimesh(mesh)
    except ValueError as err:
        raise ValueError(f"{name}: {err}") from None


def load_mesh(path) -> trimesh.Trimesh:
    """Read a closed plug surface (STL, OBJ, PLY, … anything trimesh reads), in mm.

    Raises:
        FileNotFoundError: no such file.
        ValueError: unreadable, no triangles, not watertight or inconsistently wound (the
            message names the file and the problem).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such mesh file")
    try:
        mesh = trimesh.load(path, force="mesh")
    except Exception as err:  # trimesh raises many types for unreadable files
        raise ValueError(f"{path}: cannot read a triangle mesh ({type(err).__name__}: {err})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"{path}: the file holds no triangles")
    _check_mesh(mesh, str(path))
    return mesh


# Vertex coordinates are rounded to this many decimals (mm) before hashing.
_HASH_DECIMALS = 9


def mesh_hash(mesh: trimesh.Trimesh) -> str:
    """SHA-256 of the mesh as a set of oriented triangles.

    The same surface gives the same hash whatever the order of its vertices and faces and
    whichever corner each face starts at (orientation kept): what a mesher or a convex hull
    may change between library versions, while the distances (the training labels) stay the
    same. Coordinates are rounded to 1e-9 mm first, so that last-bit differences in how they
    were computed do not count.
    """
    v = np.round(np.asarray(mesh.vertices, np.float64), _HASH_DECIMALS) + 0.0  # -0.0 -> 0.0
    f = np.asarray(mesh.faces, np.int64)
    order = np.lexsort(v.T[::-1])  # vertices sorted by x, then y, then z
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    f = rank[f]
    start = np.argmin(f, axis=1)[:, None]  # each face from its lowest vertex, same orientation
    f = np.take_along_axis(f, (start + np.arange(3)) % 3, axis=1)
    f = f[np.lexsort(f.T[::-1])]
    h = hashlib.sha256()
    for a in (v[order], f):
        h.update(str(a.shape).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def cache_key(mesh: trimesh.Trimesh, config: NeuralSDFConfig) -> str:
    """SHA-256 of everything the weights depend on: the mesh (:func:`mesh_hash`), the settings
    and the cache format's version."""
    return KeyHash("neural_sdf").settings(dict(mesh=mesh_hash(mesh), config=config.to_dict())).hexdigest()


def cache_path(key: str) -> Path:
    return artefact_path("neural_sdf", key)


def shipped_path(key: str) -> Path:
    """Where the package ships weights for ``key`` (the default plug's; the file may not exist)."""
    return SHIPPED / f"{key[:32]}.npz"


# --------------------------------------------------------------------------------------------
# Training and evaluation
# --------------------------------------------------------------------------------------------


def _sample_points(mesh, exact: MeshSDF, config: NeuralSDFConfig, n: int, rng, progress=False):
    """Training points (n, 3) with exact φ (n,), float64."""
    lo = mesh.bounds[0] - config.pad
    hi = mesh.bounds[1] + config.pad
    n_box = round(n * config.box_fraction)
    n_near = n - n_box
    surf, face = trimesh.sample.sample_surface(mesh, n_near, seed=int(rng.integers(2**31)))
    sigma = np.where(rng.random(n_near) < 0.5, config.band / 4, config.band)
    near = surf + mesh.face_normals[face] * (rng.normal(size=n_near) * sigma)[:, None]
    box = rng.uniform(lo, hi, (n_box, 3))
    x = np.clip(np.concatenate([near, box]), lo, hi)
    return x, _exact_phi(exact, x, progress, "labelling (exact mesh SDF)")[0]


def _exact_phi(exact: MeshSDF, x, progress=False, desc=""):
    from tqdm.auto import tqdm

    chunk = 8192
    n = len(x)
    # Fixed-size chunks (the last padded with copies of point 0): one compile per mesh.
    xp = np.concatenate([x, np.broadcast_to(x[:1], (-n % chunk, 3))]) if n > chunk else x
    phi, nrm = [], []
    with tqdm(total=n, desc=desc, unit="pt", disable=not progress, leave=False) as bar:
        for i in range(0, len(xp), chunk):
            f, g = mesh_sdf_and_normal(exact, xp[i : i + chunk])
            phi.append(np.asarray(f))
            nrm.append(np.asarray(g))
            bar.update(min(chunk, n - i))
    return np.concatenate(phi)[:n], np.concatenate(nrm)[:n]


def _band_points(mesh, exact: MeshSDF, band: float, n: int, rng):
    """``n`` points uniform in the shell ``|φ| ≤ band``, with exact φ and normals."""
    lo = mesh.bounds[0] - band
    hi = mesh.bounds[1] + band
    xs, fs, ns = [], [], []
    have = 0
    for _ in range(100):
        x = rng.uniform(lo, hi, (max(2 * (n - have), 1024), 3))
        f, nr = _exact_phi(exact, x)
        keep = np.abs(f) <= band
        xs.append(x[keep])
        fs.append(f[keep])
        ns.append(nr[keep])
        have += int(keep.sum())
        if have >= n:
            break
    return np.concatenate(xs)[:n], np.concatenate(fs)[:n], np.concatenate(ns)[:n]


@x64
def band_errors(net: NeuralSDF, mesh, band: float = 0.2, points: int = 20_000, seed: int = 1234) -> dict:
    """Pointwise errors of the net (queried in float32) against the exact mesh SDF.

    Returns a dict of arrays over ``points`` points uniform in the shell ``|φ| ≤ band`` (mm):
    ``x`` (n, 3), exact ``phi`` (n,), distance error ``error`` = φ_net − φ (n,), mm, and the
    normal error ``angle`` (n,), degrees.
    """
    exact = _check_mesh(mesh)
    x, f, n = _band_points(mesh, exact, band, points, np.random.default_rng(seed))
    pf, pn = neural_sdf_and_normal(net, jnp.asarray(x, jnp.float32))
    cos = np.clip(np.sum(np.asarray(pn, np.float64) * n, axis=1), -1.0, 1.0)
    return dict(x=x, phi=f, error=np.asarray(pf, np.float64) - f, angle=np.degrees(np.arccos(cos)))


def summarise(errors: dict, band: float) -> dict:
    """The accuracy report of :func:`band_errors`' output; see :func:`accuracy_report`."""
    err = np.abs(errors["error"])
    ang = errors["angle"]
    surf = np.abs(errors["phi"]) <= band / 10
    return dict(
        points=len(err),
        band_mm=float(band),
        mae_mm=float(err.mean()),
        rmse_mm=float(np.sqrt(np.mean(err**2))),
        p95_mm=float(np.percentile(err, 95)),
        max_mm=float(err.max()),
        mae_surface_mm=float(err[surf].mean()) if surf.any() else float("nan"),
        normal_median_deg=float(np.median(ang)),
        normal_p95_deg=float(np.percentile(ang, 95)),
    )


@x64
def accuracy_report(net: NeuralSDF, mesh, band: float = 0.2, points: int = 20_000, seed: int = 1234) -> dict:
    """Errors of the net against the exact mesh SDF, uniformly over the shell ``|φ| ≤ band``.

    Returns a dict: ``points``, ``band_mm``; distance errors ``mae_mm``, ``rmse_mm``,
    ``p95_mm``, ``max_mm``, ``mae_surface_mm`` (over ``|φ| ≤ band/10``); normal errors in degrees
    ``normal_median_deg``, ``normal_p95_deg``.
    """
    return summarise(band_errors(net, mesh, band, points, seed), band)


def _optimizer(config: NeuralSDFConfig):
    import optax

    schedule = optax.warmup_cosine_decay_schedule(
        0.0,
        config.learning_rate,
        config.warmup,
        max(config.steps, config.warmup + 1),
        config.learning_rate * 0.01,
    )
    return optax.adam(schedule)


# Module level with the settings and the chunk length static, so that training again with the
# same settings and data size (another mesh, a retrain) reuses the compiled loop.
@partial(jax.jit, static_argnames=("config", "length"))
def _train_chunk(net, params, opt_state, key, data, *, config, length):
    """``length`` Adam steps on random batches of ``data = (x, φ, weight)``; L1 loss in mm."""
    import optax

    opt = _optimizer(config)

    def loss_fn(params, x, y, w):
        pred = _neural_phi(eqx.tree_at(lambda m: m.params, net, params), x)
        return jnp.mean(w * jnp.abs(pred - y))

    def body(carry, k):
        params, opt_state = carry
        idx = jax.random.randint(k, (config.batch,), 0, data[0].shape[0])
        loss, g = jax.value_and_grad(loss_fn)(params, *(a[idx] for a in data))
        updates, opt_state = opt.update(g, opt_state, params)
        return (optax.apply_updates(params, updates), opt_state), loss

    (params, opt_state), losses = jax.lax.scan(body, (params, opt_state), jax.random.split(key, length))
    return params, opt_state, losses


@x64
def train(
    mesh,
    config: NeuralSDFConfig | None = None,
    *,
    progress: bool = False,
    evaluate: bool = True,
    report_points: int = 20_000,
):
    """Train a neural SDF of a closed triangle mesh (host; float32 weights).

    Args:
        mesh: ``trimesh.Trimesh``, watertight and consistently wound, in mm.
        config: settings (default :class:`NeuralSDFConfig()`).
        progress: show progress bars (tqdm, on stderr).
        evaluate: also measure the accuracy (:func:`accuracy_report` over the config's band).
        report_points: points of that accuracy report.

    Returns:
        ``(net, info)``: the :class:`NeuralSDF` and a dict with ``loss`` (per-step training
        loss history, list), ``seconds`` (wall time of labelling + training), ``report`` (the
        accuracy report, or None), ``mesh_hash``, ``key``, ``config``.

    Raises:
        ValueError: the mesh is not watertight or its winding is inconsistent.
    """
    from tqdm.auto import tqdm

    config = config or NeuralSDFConfig()
    exact = _check_mesh(mesh)
    t0 = time.perf_counter()
    rng = np.random.default_rng(config.seed)
    x, phi = _sample_points(mesh, exact, config, config.samples, rng, progress)
    weight = np.where(np.abs(phi) <= config.band, 1.0, config.far_weight)

    lo = mesh.bounds[0] - config.pad
    hi = mesh.bounds[1] + config.pad
    center = (lo + hi) / 2
    half = (hi - lo) / 2
    key = jax.random.PRNGKey(config.seed)
    key, init_key = jax.random.split(key)
    net = NeuralSDF(
        params=_template_params(config, init_key),
        center=jnp.asarray(center, jnp.float32),
        half=jnp.asarray(half, jnp.float32),
        # Output in units of the thinnest half extent: O(1) targets for any mesh size.
        out_scale=jnp.asarray(half.min(), jnp.float32),
        width=config.width,
        depth=config.depth,
        activation=config.activation,
        softplus_beta=float(config.softplus_beta),
    )
    data = (jnp.asarray(x, jnp.float32), jnp.asarray(phi, jnp.float32), jnp.asarray(weight, jnp.float32))
    params = net.params
    opt_state = _optimizer(config).init(params)
    losses = []
    chunk = 100
    with tqdm(total=config.steps, desc="training neural SDF", unit="step", disable=not progress) as bar:
        done = 0
        while done < config.steps:
            length = min(chunk, config.steps - done)
            key, k = jax.random.split(key)
            params, opt_state, ls = _train_chunk(net, params, opt_state, k, data, config=config, length=length)
            ls = np.asarray(ls)
            losses.extend(ls.tolist())
            done += length
            bar.update(length)
            bar.set_postfix(loss_mm=f"{ls.mean():.2e}")
    if not np.all(np.isfinite(losses)):
        raise RuntimeError("neural SDF training diverged (non-finite loss): lower learning_rate")
    net = eqx.tree_at(lambda m: m.params, net, params)
    seconds = time.perf_counter() - t0
    report = accuracy_report(net, mesh, config.band, report_points) if evaluate else None
    info = dict(
        loss=losses,
        seconds=seconds,
        report=report,
        mesh_hash=mesh_hash(mesh),
        key=cache_key(mesh, config),
        config=config.to_dict(),
    )
    return net, info


# --------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------


def _named_leaves(params) -> dict:
    """``{"param/<layer>/<name>": leaf}`` in ``tree_flatten`` order."""
    leaves = jax.tree_util.tree_flatten_with_path(params)[0]
    return {"param/" + "/".join(str(k.key) for k in path): leaf for path, leaf in leaves}


def _arrays(net: NeuralSDF) -> dict:
    return {
        "center": np.asarray(net.center),
        "half": np.asarray(net.half),
        "out_scale": np.asarray(net.out_scale),
        **{k: np.asarray(v) for k, v in _named_leaves(net.params).items()},
    }


def save(net: NeuralSDF, path, *, key: str, mesh_hash: str, config: NeuralSDFConfig, extra=None) -> Path:
    """Write the weights to ``path`` (``.npz``, jsnap's artefact format, atomically): the
    normalisation (``center``, ``half``, ``out_scale``), the weights (``param/<layer>/<name>``)
    and as metadata the architecture, settings, mesh hash, cache key and ``extra``."""
    meta = dict(
        architecture=config.architecture, config=config.to_dict(), mesh_hash=mesh_hash, extra=extra or {}
    )
    return save_artefact(path, "neural_sdf", key, meta, _arrays(net))


def _net(data: dict, meta: dict) -> NeuralSDF:
    """The :class:`NeuralSDF` of a weights file's arrays (ArtefactError when they do not fit)."""
    try:
        config = NeuralSDFConfig.from_dict(meta["config"])
    except (KeyError, ValueError, TypeError) as err:
        raise ArtefactError(f"corrupt metadata ({type(err).__name__}: {err})") from None
    template = _template_params(config)
    expected = _named_leaves(template)
    got = {k: v for k, v in data.items() if k.startswith("param/")}
    if set(got) != set(expected) or any(got[k].shape != expected[k].shape for k in expected):
        raise ArtefactError(f"weights do not match the architecture {config.architecture}")
    params = jax.tree_util.tree_unflatten(
        jax.tree_util.tree_structure(template), [jnp.asarray(got[k]) for k in expected]
    )
    return NeuralSDF(
        params=params,
        center=jnp.asarray(data["center"]),
        half=jnp.asarray(data["half"]),
        out_scale=jnp.asarray(data["out_scale"]),
        width=config.width,
        depth=config.depth,
        activation=config.activation,
        softplus_beta=float(config.softplus_beta),
    )


@x64
def load(path, *, key: str | None = None) -> tuple[NeuralSDF, dict]:
    """Read weights written by :func:`save`, verifying format, checksum and (if given) key.

    Returns:
        ``(net, meta)``.

    Raises:
        FileNotFoundError: no such file.
        jsnap._build.cache.ArtefactError: unreadable or corrupt, another format version, arrays
            that do not fit the architecture, or trained for another mesh or settings than ``key``.
    """
    data, meta = load_artefact(path, "neural_sdf", key)
    try:
        return _net(data, meta), meta
    except ArtefactError as err:
        raise ArtefactError(f"{path}: {err}") from None


@x64
def load_or_train(
    mesh,
    config: NeuralSDFConfig | None = None,
    *,
    progress: bool = False,
    retrain: bool = False,
    report_points: int = 20_000,
):
    """The cached neural SDF of ``mesh`` for ``config``, training (and caching) it if needed.

    A cached file that is corrupt or was written for something else is never used: it is
    reported with a warning and replaced by a freshly trained one. Where the cache has no file,
    the weights shipped with the package for the key (:func:`shipped_path`: the default plug's,
    default settings) are used, read-only, before anything is trained. Processes that ask for the
    same weights at once train them once.

    Args:
        mesh: ``trimesh.Trimesh``, watertight and consistently wound, in mm.
        config: settings (default :class:`NeuralSDFConfig()`).
        progress: progress bars while training.
        retrain: train and overwrite even if a valid cached file exists.
        report_points: points of the accuracy report made after training (stored in the file).

    Returns:
        ``(net, info)``: info has ``path``, ``cached`` (bool: read, not trained), ``shipped``
        (bool: read from the package's weights), ``key``, ``mesh_hash``, ``config``, ``report``
        (accuracy at training time) and ``seconds`` (training time).

    Raises:
        ValueError: the mesh is not watertight or its winding is inconsistent.
    """
    config = config or NeuralSDFConfig()
    _check_mesh(mesh)
    key = cache_key(mesh, config)
    trained_net = {}

    def make():
        net, info = train(mesh, config, progress=progress, report_points=report_points)
        trained_net["net"] = net
        loss = float(np.mean(info["loss"][-100:]))
        extra = dict(report=info["report"], seconds=info["seconds"], final_loss=loss)
        meta = dict(
            architecture=config.architecture, config=config.to_dict(), mesh_hash=info["mesh_hash"], extra=extra
        )
        return _arrays(net), meta

    arrays, meta = cached(
        "neural_sdf",
        key,
        make,
        what="the neural SDF",
        check=lambda a, m: _net(a, m),
        fresh=retrain,
        shipped=shipped_path(key),
    )
    net = trained_net.get("net") or _net(arrays, meta)
    extra = meta.get("extra", {})
    return net, dict(
        path=Path(meta["path"]),
        cached=meta["cached"],
        shipped=meta["shipped"],
        key=key,
        mesh_hash=meta["mesh_hash"],
        config=meta["config"],
        report=extra.get("report"),
        seconds=extra.get("seconds"),
    )
