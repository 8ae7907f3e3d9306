"""Small strain and von Mises stress of the deformable part, from its nodal displacement (host).

For a P1 or P2 tetrahedral mesh (``model.mesh``: nodes, cells, free dofs) and the nodal
displacement ``u``, the small-strain tensor ``eps = (grad u + grad u') / 2`` is evaluated at
the four vertices of every element, each element with its own value (the finite-element strain
is discontinuous between elements). Why the vertices: a P1 element's strain is constant and a
P2 element's is affine in the element, and both the largest principal strain (the largest
eigenvalue, a convex function of the tensor) and the equivalent strain (a norm of the
deviator, convex too) of an affine field reach their maximum over a tetrahedron at one of its
vertices. The largest of the four vertex values is therefore the element's exact maximum of
the finite-element field; the centroid or the interior quadrature points lie inside the
element and understate it (in a bent arm the largest strain is on the surface).

Measures, per point:

- ``max_principal``: the largest principal strain (signed, dimensionless): tension where
  positive, what a snap-fit design guide compares with the material's allowable strain;
- ``equivalent``: the von Mises equivalent strain ``sqrt(3/2 e:e) / (1 + nu)`` (``e`` the
  deviatoric strain), which is ``sigma_vm / E`` for a linear elastic material and equals the
  axial strain under uniaxial stress for every ``nu``;
- ``von_mises``: the von Mises stress ``sqrt(3/2 s:s) = E / (1 + nu) sqrt(3/2 e:e)``, MPa.

Where: :func:`peak_strain` is the largest value over every element (or those given), which on
a part with a clamped sharp edge, a sharp inside corner or a point contact is a singular value
that grows as the mesh is refined; :func:`bending_strain` is the strain where a designer reads
it, in the region that bends, extrapolated to those edges from one to three walls out and read
as it is away from them, the contacts of each step left out (its region found on the mesh by
:func:`bending_region`, for a preset and a part from a file alike).

The displacement of a rollout's steps comes from ``Result.x`` (a rollout with
``keep_x=True``) through ``model.part.free_displacement``: one matrix product per batch of steps
for a reduced or modal part. Memory is bounded by working through the steps in batches; nothing
is dense in the mesh size. Units: mm, MPa.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "BendingRegion",
    "BendingStrain",
    "PeakStrain",
    "Strain",
    "StrainOperator",
    "bending_region",
    "bending_strain",
    "equivalent_strain",
    "max_principal",
    "peak_strain",
    "scan",
    "singular_edges",
    "strain",
    "von_mises",
]

# Edges of the 10-node tetrahedron in the order of its nodes 4..9 (VTK tetra10 and scikit-fem).
_EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])

# Bytes of float64 work arrays per batch of steps (the gradient and its measures).
_BATCH_BYTES = 64 * 2**20


# --------------------------------------------------------------------------------------------
# The operator
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class StrainOperator:
    """Displacement gradient at the vertices of every element of a P1 or P2 tetrahedral mesh.

    Attributes:
        cells: (m, 4) or (m, 10) node indices per element (P2: VTK tetra10 order, the 4
            vertices, then the midpoints of edges 01, 12, 02, 03, 13, 23).
        grads: (m, 4, k, 3) gradient of element node ``a``'s shape function at the element's
            vertex ``v``, 1/mm (``k`` = 4 or 10).
        n_nodes: number of mesh nodes.
    """

    cells: np.ndarray
    grads: np.ndarray
    n_nodes: int

    @classmethod
    def from_mesh(cls, nodes, cells) -> StrainOperator:
        """The operator of the mesh ``nodes`` (N, 3) mm, ``cells`` (m, 4) or (m, 10).

        The element geometry is the straight-sided tetrahedron of the four vertices (P2 edge
        nodes at the midpoints, as the assembly puts them).

        Raises:
            ValueError: cells of another width, node indices out of range, or a degenerate
                element (named).
        """
        nodes = np.asarray(nodes, dtype=np.float64)
        cells = np.asarray(cells, dtype=np.int64)
        if nodes.ndim != 2 or nodes.shape[1] != 3:
            raise ValueError(f"nodes must be (N, 3), got {nodes.shape}")
        if cells.ndim != 2 or cells.shape[1] not in (4, 10):
            raise ValueError(f"cells must be (m, 4) or (m, 10), got {cells.shape}")
        if cells.size and (cells.min() < 0 or cells.max() >= nodes.shape[0]):
            raise ValueError(f"cells refer to nodes outside 0..{nodes.shape[0] - 1}")
        p = nodes[cells[:, :4]]
        J = np.transpose(p[:, 1:] - p[:, :1], (0, 2, 1))  # columns p1-p0, p2-p0, p3-p0
        det = np.linalg.det(J)
        scale = np.max(np.linalg.norm(p[:, 1:] - p[:, :1], axis=2), axis=1) ** 3
        bad = np.flatnonzero(~(np.abs(det) > 1e-12 * scale))
        if bad.size:
            raise ValueError(f"element {int(bad[0])} is degenerate (volume {det[bad[0]] / 6:.3e} mm^3)")
        # Rows of J^-1 are the gradients of the barycentric coordinates 1..3.
        g = np.empty((cells.shape[0], 4, 3))
        g[:, 1:] = np.linalg.inv(J)
        g[:, 0] = -g[:, 1:].sum(axis=1)
        m = cells.shape[0]
        if cells.shape[1] == 4:
            grads = np.broadcast_to(g[:, None], (m, 4, 4, 3)).copy()
        else:
            # Shape functions in barycentric coordinates L: vertex a, L_a (2 L_a - 1), gradient
            # (4 L_a - 1) grad L_a; edge (i, j), 4 L_i L_j, gradient 4 (L_j grad L_i + L_i grad L_j).
            # At vertex v, L = e_v.
            grads = np.zeros((m, 4, 10, 3))
            for v in range(4):
                for a in range(4):
                    grads[:, v, a] = (4.0 * (a == v) - 1.0) * g[:, a]
                for e, (i, j) in enumerate(_EDGES):
                    grads[:, v, 4 + e] = 4.0 * ((j == v) * g[:, i] + (i == v) * g[:, j])
        return cls(cells, grads, int(nodes.shape[0]))

    @property
    def n_elements(self) -> int:
        return self.cells.shape[0]

    def gradient(self, u) -> np.ndarray:
        """(..., m, 4, 3, 3) displacement gradient ``H[i, j] = d u_i / d x_j`` at every element's
        vertices, for nodal displacements ``u`` (..., N, 3) in mm."""
        u = np.asarray(u, dtype=np.float64)
        if u.shape[-2:] != (self.n_nodes, 3):
            raise ValueError(f"displacement must be (..., {self.n_nodes}, 3), got {u.shape}")
        lead = u.shape[:-2]
        H = self._gradient(u.reshape(-1, self.n_nodes, 3))  # (m, v, j, i, S)
        return np.transpose(H, (4, 0, 1, 3, 2)).reshape(*lead, self.n_elements, 4, 3, 3)

    def _gradient(self, U) -> np.ndarray:
        """(m, 4 v, 3 j, 3 i, S) displacement gradient of nodal displacements ``U`` (S, N, 3):
        one small matrix product per element, batched, ``(4 v * 3 j, k) @ (k, 3 i * S)``."""
        S, (m, k) = U.shape[0], self.cells.shape
        Ue = np.transpose(U[:, self.cells], (1, 2, 3, 0)).reshape(m, k, 3 * S)
        Gt = np.transpose(self.grads, (0, 1, 3, 2)).reshape(m, 12, k)
        return np.matmul(Gt, Ue).reshape(m, 4, 3, 3, S)

    def strain(self, u) -> np.ndarray:
        """(..., m, 4, 3, 3) small-strain tensor at every element's vertices (dimensionless)."""
        H = self.gradient(u)
        return 0.5 * (H + np.swapaxes(H, -1, -2))

    def _components(self, u) -> tuple[np.ndarray, ...]:
        """The six strain components ``xx, yy, zz, yz, xz, xy``, each (m, 4, S), of nodal
        displacements ``u`` (S, N, 3): :meth:`strain` without its transposed copies."""
        H = self._gradient(u)
        return (
            H[:, :, 0, 0],
            H[:, :, 1, 1],
            H[:, :, 2, 2],
            0.5 * (H[:, :, 1, 2] + H[:, :, 2, 1]),
            0.5 * (H[:, :, 0, 2] + H[:, :, 2, 0]),
            0.5 * (H[:, :, 0, 1] + H[:, :, 1, 0]),
        )


# --------------------------------------------------------------------------------------------
# Measures of a strain tensor
# --------------------------------------------------------------------------------------------


def max_principal(eps) -> np.ndarray:
    """Largest eigenvalue of symmetric 3x3 tensors ``eps`` (..., 3, 3), in closed form.

    The trigonometric solution of the characteristic cubic (Smith 1961): with ``q = tr/3`` and
    ``p`` the deviator's root-mean-square size, ``lambda = q + 2 p cos(acos(r) / 3)``,
    ``r = det((eps - q I) / p) / 2``. Its absolute error is of order ``sqrt(machine eps) * p`` at
    worst (a double eigenvalue, where ``acos`` is steep), far below a strain's meaning.
    """
    a = np.asarray(eps, dtype=np.float64)
    return _max_principal(a[..., 0, 0], a[..., 1, 1], a[..., 2, 2], a[..., 1, 2], a[..., 0, 2], a[..., 0, 1])


def _max_principal(a00, a11, a22, a12, a02, a01):
    q = (a00 + a11 + a22) / 3.0
    d0, d1, d2 = a00 - q, a11 - q, a22 - q
    p2 = d0 * d0 + d1 * d1 + d2 * d2 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)
    p = np.sqrt(p2 / 6.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        det = d0 * (d1 * d2 - a12 * a12) - a01 * (a01 * d2 - a12 * a02) + a02 * (a01 * a12 - d1 * a02)
        r = np.clip(det / (2.0 * p**3), -1.0, 1.0)
        lam = q + 2.0 * p * np.cos(np.arccos(r) / 3.0)
    return np.where(p > 0, lam, q)


def _deviator_norm2(eps) -> np.ndarray:
    """``e:e`` of the deviatoric part of ``eps`` (..., 3, 3)."""
    a = np.asarray(eps, dtype=np.float64)
    return _dev2(a[..., 0, 0], a[..., 1, 1], a[..., 2, 2], a[..., 1, 2], a[..., 0, 2], a[..., 0, 1])


def _dev2(a00, a11, a22, a12, a02, a01):
    """``e:e`` of the deviator from the six components, as the sum of squared differences of
    the normal components (no cancellation against the trace)."""
    normal = (a00 - a11) ** 2 + (a11 - a22) ** 2 + (a22 - a00) ** 2
    return normal / 3.0 + 2.0 * (a12 * a12 + a02 * a02 + a01 * a01)


def equivalent_strain(eps, nu) -> np.ndarray:
    """von Mises equivalent strain ``sqrt(3/2 e:e) / (1 + nu)`` of ``eps`` (..., 3, 3): ``sigma_vm / E``
    of a linear elastic material with Poisson ratio ``nu``; the axial strain under uniaxial stress."""
    return np.sqrt(1.5 * _deviator_norm2(eps)) / (1.0 + nu)


def von_mises(eps, E, nu) -> np.ndarray:
    """von Mises stress (MPa) of a linear elastic material (``E`` MPa, ``nu``) at strain ``eps``
    (..., 3, 3): ``sqrt(3/2 s:s)`` with the deviatoric stress ``s = E / (1 + nu) e``."""
    return E * equivalent_strain(eps, nu)


# --------------------------------------------------------------------------------------------
# Strain of a rollout
# --------------------------------------------------------------------------------------------


def _operator(model) -> StrainOperator:
    return StrainOperator.from_mesh(np.asarray(model.mesh.nodes), np.asarray(model.mesh.cells))


def _material(model, params) -> tuple[float, float]:
    p = model.params if params is None else params
    E, nu = np.asarray(p.E, dtype=np.float64), np.asarray(p.nu, dtype=np.float64)
    if E.ndim or nu.ndim:
        raise ValueError(
            f"params: one parameter set is needed (E has shape {E.shape}, nu {nu.shape}); "
            "pass the parameters of the one rollout whose strain is wanted"
        )
    E, nu = float(E), float(nu)
    if not (math.isfinite(E) and E > 0):
        raise ValueError(f"params.E = {E!r}: must be a finite number > 0 (MPa)")
    if not (math.isfinite(nu) and -1.0 < nu < 0.5):
        raise ValueError(f"params.nu = {nu!r}: must be in (-1, 0.5)")
    return E, nu


def _coordinates(result) -> np.ndarray:
    x = getattr(result, "x", None)
    if x is None:
        raise ValueError(
            "result.x is None: the strain needs the part's coordinates at every step; roll out with keep_x=True"
        )
    x = np.asarray(x)
    if x.ndim != 2:
        raise ValueError(
            f"result.x has shape {x.shape}: one rollout (steps, dof) is needed; for a batch from "
            "rollout_batch, take one rollout's coordinates (jax.tree_util.tree_map(lambda a: a[i], result))"
        )
    return x


def _nodal_displacement(model, x, rows: int | None = None) -> np.ndarray:
    """(S, N, 3) nodal displacement, mm, of the coordinates ``x`` (S, dof).

    ``rows``: pad ``x`` to this many rows for the part's map, so that batches of one size are
    computed by one compiled program (JAX compiles once per shape)."""
    import jax
    import jax.numpy as jnp

    if x.shape[1] != model.n_dof:
        raise ValueError(f"result.x has {x.shape[1]} coordinates per step, the model {model.n_dof}")
    S = x.shape[0]
    padded = np.zeros((max(S, rows or 0), x.shape[1]))
    padded[:S] = x
    with jax.enable_x64(True):
        free_disp = np.asarray(jax.vmap(model.part.free_displacement)(jnp.asarray(padded, jnp.float64)))[:S]
    nodes = model.mesh.nodes.shape[0]
    u = np.zeros((S, 3 * nodes))
    u[:, np.asarray(model.mesh.free)] = free_disp
    return u.reshape(S, nodes, 3)


def _batch(op: StrainOperator) -> int:
    """Steps per batch: the (S, m, 4, 3, 3) gradient, its strain and transposed copies."""
    per_step = op.n_elements * 4 * 9 * 8 * 4 + op.n_nodes * 3 * 8 * 2
    return max(1, _BATCH_BYTES // per_step)


@dataclass(frozen=True, eq=False)
class Strain:
    """The small strain of some steps of a rollout, at the vertices of every element.

    Attributes:
        tensor: (S, m, 4, 3, 3) strain tensor of step ``steps[s]``, element ``e``, at the
            element's vertex ``v`` (its node ``model.mesh.cells[e, v]``), dimensionless.
        steps: (S,) the steps (rows of the result).
        E: Young's modulus the stress is computed with, MPa.
        nu: Poisson's ratio.

    The measures below are per element vertex; an element's largest value over its vertices
    (``.max(axis=-1)``) is its largest over the element.
    """

    tensor: np.ndarray
    steps: np.ndarray
    E: float
    nu: float

    @property
    def max_principal(self) -> np.ndarray:
        """(S, m, 4) the largest principal strain (signed; positive: tension)."""
        return max_principal(self.tensor)

    @property
    def equivalent(self) -> np.ndarray:
        """(S, m, 4) the von Mises equivalent strain, ``von_mises / E``."""
        return equivalent_strain(self.tensor, self.nu)

    @property
    def von_mises(self) -> np.ndarray:
        """(S, m, 4) the von Mises stress, MPa."""
        return von_mises(self.tensor, self.E, self.nu)


def strain(model, result, *, steps=None, params=None) -> Strain:
    """The small strain of a rollout's steps at the vertices of every element (host, numpy).

    Args:
        model: the built model (its mesh and part).
        result: one rollout's result with its coordinates (``rollout(..., keep_x=True)``).
        steps: the steps wanted (indices or a slice into the result's steps); None: every step.
            The tensor takes ``288 m`` bytes per step (``m`` elements).
        params: the parameters the rollout ran with (``E``, ``nu`` for the stress); None:
            ``model.params``.

    Returns:
        :class:`Strain`, whose ``max_principal``, ``equivalent`` and ``von_mises`` are per
        element vertex; :func:`peak_strain` finds the peak of a whole rollout in bounded memory.

    Raises:
        ValueError: the result has no coordinates (``keep_x`` was off) or is a batch, or the
            parameters are not one valid set.
    """
    E, nu = _material(model, params)
    x = _coordinates(result)
    index = np.arange(x.shape[0])[slice(None) if steps is None else steps]
    index = np.atleast_1d(index)
    op = _operator(model)
    parts, size = [], _batch(op)
    for start in range(0, index.size, size):
        sel = index[start : start + size]
        parts.append(op.strain(_nodal_displacement(model, x[sel], rows=min(size, index.size))))
    tensor = np.concatenate(parts) if parts else np.zeros((0, op.n_elements, 4, 3, 3))
    return Strain(tensor, index, E, nu)


@dataclass(frozen=True, eq=False)
class PeakStrain:
    """The largest strain and stress of a whole rollout: every step, over the elements looked
    at (all, or those :func:`peak_strain` was given).

    Attributes:
        max_principal: the largest principal strain (dimensionless; NaN when no step is finite).
        step: the step where it occurs (row of the result; -1 when none is finite).
        time: that step's time, s.
        element: the element where it occurs (index into ``model.mesh.cells``).
        position: (3,) the element vertex where it occurs, in the reference configuration, mm.
        von_mises: the largest von Mises stress, MPa.
        von_mises_step: the step where that occurs (-1 when none is finite).
        von_mises_position: (3,) where, mm.
        history: (n,) per step, the largest principal strain over the elements looked at.
        von_mises_history: (n,) per step, the largest von Mises stress over them, MPa.
        element_max_principal: (m,) every element's largest principal strain over the rollout
            (all elements).
        element_von_mises: (m,) every element's largest von Mises stress over the rollout, MPa.
    """

    max_principal: float
    step: int
    time: float
    element: int
    position: np.ndarray
    von_mises: float
    von_mises_step: int
    von_mises_position: np.ndarray
    history: np.ndarray
    von_mises_history: np.ndarray
    element_max_principal: np.ndarray
    element_von_mises: np.ndarray


def _nanmax_arg(values) -> tuple[np.ndarray, np.ndarray]:
    """Per row of (S, P): the largest finite value (NaN if none) and its column (0 if none)."""
    filled = np.where(np.isnan(values), -np.inf, values)
    arg = np.argmax(filled, axis=1)
    top = np.take_along_axis(values, arg[:, None], axis=1)[:, 0]
    none = ~np.isfinite(filled).any(axis=1)
    return np.where(none, np.nan, top), arg


def _elements(elements, m: int) -> np.ndarray:
    """Sorted element indices from a boolean mask (m,) or indices; all for None."""
    if elements is None:
        return np.arange(m)
    sel = np.asarray(elements)
    if sel.dtype == bool:
        if sel.shape != (m,):
            raise ValueError(f"elements: a mask must have one entry per element ({m}), got {sel.shape}")
        sel = np.flatnonzero(sel)
    sel = np.unique(sel.astype(np.int64).reshape(-1))
    if sel.size == 0 or sel[0] < 0 or sel[-1] >= m:
        raise ValueError(f"elements: indices must be non-empty and within 0..{m - 1}")
    return sel


def scan(
    model, x, t, E: float, nu: float, keep=(), regions=None, bending: BendingRegion | None = None, contacts=None
) -> tuple[dict, dict]:
    """Go through every step of the coordinates ``x`` (n, dof) at times ``t`` (n,) once, in
    batches of steps.

    Returns:
        ``peaks``: region name -> :class:`PeakStrain` over that region's elements, for
        ``regions`` (name -> element mask or indices, None for all; default ``{"part": None}``),
        and with a ``bending`` region (:func:`bending_region`), ``"bending"`` -> its
        :class:`BendingStrain` (``contacts``: the result's ``(contact_index, contact_active)``);
        ``kept``: for the steps ``keep``, ``{"displacement": (K, N, 3), "max_principal": (K, m),
        "von_mises": (K, m)}`` (each element's largest value) for output files.
    """
    op = _operator(model)
    nodes = np.asarray(model.mesh.nodes)
    n, m = x.shape[0], op.n_elements
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    if t.size != n:
        raise ValueError(f"result.t has {t.size} steps, result.x {n}")
    regions = {name: _elements(sel, m) for name, sel in (regions or {"part": None}).items()}
    keep = np.asarray(keep, dtype=np.int64).reshape(-1)
    kept = {
        "displacement": np.zeros((keep.size, op.n_nodes, 3)),
        "max_principal": np.zeros((keep.size, m)),
        "von_mises": np.zeros((keep.size, m)),
    }
    # Per region and measure: each step's largest value and where (index into region x 4).
    hist = {(r, f): (np.full(n, np.nan), np.zeros(n, dtype=np.int64)) for r in regions for f in ("mp", "vm")}
    el_mp, el_vm = np.full(m, -np.inf), np.full(m, -np.inf)
    size = _batch(op)
    if bending is not None:
        excluded = _contact_exclusion(model, bending, contacts)
        J = bending.points.shape[1]
        # Per measure: each step's value, which path or vertex, and that path's read-outs.
        bend = {f: (np.full(n, np.nan), np.zeros(n, np.int64), np.full((n, J), np.nan)) for f in ("mp", "vm")}
    for start in range(0, n, size):
        rows = np.arange(start, min(n, start + size))
        u = _nodal_displacement(model, x[rows], rows=min(size, n))
        c = op._components(u)
        fields = {
            "mp": np.transpose(_max_principal(*c), (2, 0, 1)),  # (S, m, 4)
            "vm": np.transpose(E / (1.0 + nu) * np.sqrt(1.5 * _dev2(*c)), (2, 0, 1)),
        }
        for (r, f), (values, arg) in hist.items():
            sel = regions[r]
            field = fields[f] if sel.size == m else fields[f][:, sel]
            values[rows], arg[rows] = _nanmax_arg(field.reshape(rows.size, -1))
        mp, vm = fields["mp"], fields["vm"]
        el_mp = np.fmax(el_mp, np.max(np.where(np.isnan(mp), -np.inf, mp), axis=(0, 2)))
        el_vm = np.fmax(el_vm, np.max(np.where(np.isnan(vm), -np.inf, vm), axis=(0, 2)))
        if bending is not None:
            for f, (value, arg, read) in _bending_batch(c, bending, E, nu, excluded(rows)).items():
                bend[f][0][rows], bend[f][1][rows] = value, arg
                on = np.flatnonzero(arg < read.shape[1])
                bend[f][2][rows[on]] = read[on, arg[on]]
        hit = np.flatnonzero((keep >= rows[0]) & (keep <= rows[-1]))
        if hit.size:
            local = keep[hit] - rows[0]
            kept["displacement"][hit] = u[local]
            kept["max_principal"][hit] = mp[local].max(axis=-1)
            kept["von_mises"][hit] = vm[local].max(axis=-1)
    el_mp[np.isinf(el_mp)] = np.nan
    el_vm[np.isinf(el_vm)] = np.nan

    def where(r, f):
        values, arg = hist[(r, f)]
        if not np.isfinite(values).any():
            return np.nan, -1, -1, np.full(3, np.nan)
        k = int(np.nanargmax(values))
        e, v = divmod(int(arg[k]), 4)
        e = int(regions[r][e])
        return float(values[k]), k, e, nodes[op.cells[e, v]].astype(np.float64)

    peaks = {}
    for r in regions:
        peak, step, element, position = where(r, "mp")
        vm_peak, vm_step, _, vm_position = where(r, "vm")
        peaks[r] = PeakStrain(
            **_peak_fields(
                t,
                (peak, step, element, position, hist[(r, "mp")][0]),
                (vm_peak, vm_step, vm_position, hist[(r, "vm")][0]),
                el_mp,
                el_vm,
            )
        )
    if bending is not None:
        peaks["bending"] = _bending_peak(bending, bend, t, el_mp, el_vm)
    return peaks, kept


def _peak_fields(t, mp, vm, el_mp, el_vm) -> dict:
    """:class:`PeakStrain`'s fields from the largest principal strain's (value, step, element,
    position, history) and the von Mises stress's (value, step, position, history)."""
    peak, step, element, position, history = mp
    vm_peak, vm_step, vm_position, vm_history = vm
    return dict(
        max_principal=peak,
        step=step,
        time=float(t[step]) if step >= 0 else np.nan,
        element=element,
        position=position,
        von_mises=vm_peak,
        von_mises_step=vm_step,
        von_mises_position=vm_position,
        history=history,
        von_mises_history=vm_history,
        element_max_principal=el_mp,
        element_von_mises=el_vm,
    )


def peak_strain(model, result, *, params=None, elements=None) -> PeakStrain:
    """The largest principal strain and von Mises stress of a whole rollout (host, numpy).

    Every step is looked at, and every element (or those of ``elements``), at the element
    vertices (where an element's largest value lies, see :func:`strain`), in batches of steps,
    so the memory does not grow with the number of steps. A snap-fit's first design check is
    the arm's peak strain against the material's allowable strain.

    Two places have a peak that the linear-elastic model does not converge to under mesh
    refinement, because the exact field there is singular: the edges of the clamped root (a
    rigid clamp; a real part's root has a radius) and a sharp edge of the hook where the rigid
    part presses on it (contact forces act at the candidate points). For the arm's bending
    strain, pass the arm's elements (for the shipped cantilever: every vertex below
    ``connector.length``), as ``jsnap simulate`` does for its ``arm_`` fields.

    Args:
        model: the built model.
        result: one rollout's result with its coordinates (``rollout(..., keep_x=True)``).
        params: the parameters the rollout ran with; None: ``model.params``.
        elements: the elements to look at, a boolean mask (m,) or indices into
            ``model.mesh.cells``; None: all.

    Returns:
        :class:`PeakStrain`.

    Raises:
        ValueError: as :func:`strain`, or ``elements`` empty or out of range.
    """
    E, nu = _material(model, params)
    x = _coordinates(result)
    peaks, _ = scan(model, x, np.asarray(result.t), E, nu, regions={"part": elements})
    return peaks["part"]


# --------------------------------------------------------------------------------------------
# The bending strain: where a designer reads it
# --------------------------------------------------------------------------------------------

# The read-out: along a path on the surface across each singular edge, the strain from
# READ_FROM to READ_TO walls from the edge at READ_POINTS points, fitted by a straight line and
# extrapolated to the edge (a linear surface extrapolation, as the hot-spot rules of the IIW
# recommendations for fatigue design read a weld toe, Hobbacher 2016, sec. 2.2.3). Along a
# bent arm the surface strain is linear in the distance from its root, so the line gives the
# root's nominal strain (the design guide's) without the singular peak at the edge. The window
# starts one wall out, beyond the first element of a mesh of at most a wall per element, where
# the element next to a singular edge overshoots; eleven points average the P2 strain's jumps
# between elements.
READ_FROM, READ_TO, READ_POINTS = 1.0, 3.0, 11
# Within this many walls of a singular edge the strain of a mesh of about a wall per element is
# not read as it is: it is the line's. On the cable latch, whose arm's outer face runs on flush
# into the bridge one wall from the inside corner of its root, the largest element value there
# differs by 12 % between 0.8 and 0.6 mm meshes.
SINGULAR_ZONE = 1.5
# Points within this many walls of a contact point of the step are not read (the dent under a
# point or line load, singular where the rigid part presses an edge).
CONTACT_CLEARANCE = 1.0
# An edge between two free faces is re-entrant (a sharp inside corner, singular for a linear
# material) where the surface turns inwards across it by more than this, degrees. A fillet's
# facets turn by less; the corners the presets and CAD parts have turn by 90.
CONCAVE_ANGLE = 30.0
# A read-out point is used only where the surface runs on from the edge: its closest point on
# the part's free surface lies within this many walls of it (and it lies READ_FROM walls, less
# this, or more from every singular edge).
_ON_SURFACE = 0.05
# A start point whose direction away from its nearest edge point lies mostly across its face
# (straight across a wall) gives no direction along the face: it needs this much in the plane.
_IN_PLANE = 0.2
# Spacing of the paths along a singular edge and of the points that measure the distance to the
# singular edges, in walls.
_ALONG = 0.1
_SAMPLING = 0.05


def _boundary(cells4: np.ndarray):
    """Boundary triangles of a tetrahedral mesh: (F, 3) vertex indices, (F,) the element each
    belongs to and (F, 3) their local vertex numbers in it (0..3)."""
    local = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
    faces = cells4[:, local].reshape(-1, 3)
    _, first, counts = np.unique(np.sort(faces, axis=1), axis=0, return_index=True, return_counts=True)
    at = np.sort(first[counts == 1])
    owner, which = np.divmod(at, 4)
    return faces[at], owner, local[which]


def _free_faces(nodes, cells4, fixed):
    """The boundary triangles not wholly in the fixed region, as :func:`_boundary`, and their
    outward unit normals (F, 3)."""
    faces, owner, local = _boundary(cells4)
    free = ~np.all(fixed[faces], axis=1)
    faces, owner, local = faces[free], owner[free], local[free]
    p = nodes[faces]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    inner = nodes[cells4[owner, 6 - local.sum(axis=1)]]  # the element's fourth vertex
    normal *= -np.sign(np.einsum("fd,fd->f", inner - p[:, 0], normal))[:, None]
    return faces, owner, local, normal


def singular_edges(nodes, cells, fixed) -> np.ndarray:
    """(E, 2) vertex pairs of a tetrahedral mesh's singular edges: the fixed region's edges on
    the free surface (a clamp's edge) and the re-entrant edges between free faces (inside
    corners that turn by more than :data:`CONCAVE_ANGLE`). ``nodes`` (N, 3) mm, ``cells``
    (m, 4 or 10), ``fixed`` (N,) bool, the fixed nodes."""
    nodes = np.asarray(nodes, np.float64)
    cells4 = np.asarray(cells)[:, :4]
    fixed = np.asarray(fixed, bool)
    faces, _, _, normal = _free_faces(nodes, cells4, fixed)
    edges = np.sort(faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    face_of = np.repeat(np.arange(faces.shape[0]), 3)
    clamp = edges[np.all(fixed[edges], axis=1)]
    # Shared by two free faces, the second rising above the first's plane.
    key, inverse = np.unique(edges, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    order = np.argsort(inverse, kind="stable")
    pair = np.flatnonzero(np.diff(inverse[order]) == 0)
    a, b = face_of[order[pair]], face_of[order[pair + 1]]
    shared = key[inverse[order[pair]]]
    turn = np.degrees(np.arccos(np.clip(np.einsum("fd,fd->f", normal[a], normal[b]), -1.0, 1.0)))
    rise = np.einsum("fd,fd->f", nodes[faces[b]].mean(axis=1) - nodes[shared].mean(axis=1), normal[a])
    concave = shared[(turn > CONCAVE_ANGLE) & (rise > 0)]
    return np.unique(np.concatenate([clamp, concave]).reshape(-1, 2), axis=0)


def _on_edges(nodes, edges, spacing: float) -> np.ndarray:
    """Points every ``spacing`` (or closer) along the edges (E, 2), ends included, mm."""
    a, b = nodes[edges[:, 0]], nodes[edges[:, 1]]
    k = np.maximum(1, np.ceil(np.linalg.norm(b - a, axis=1) / spacing)).astype(int)
    t = np.concatenate([np.linspace(0.0, 1.0, n + 1) for n in k])
    e = np.repeat(np.arange(edges.shape[0]), k + 1)
    return a[e] + t[:, None] * (b - a)[e]


def _fit_weights() -> tuple[np.ndarray, np.ndarray]:
    """The read-out distances (J,) in walls and the weights (J,) that give a straight line's
    least-squares value at distance 0 from values there."""
    d = np.linspace(READ_FROM, READ_TO, READ_POINTS)
    return d, np.linalg.pinv(np.stack([np.ones_like(d), d], axis=1))[0]


@dataclass(frozen=True, eq=False)
class BendingRegion:
    """Where :func:`bending_strain` reads the strain of a part (geometry only, mm).

    Attributes:
        wall: the wall thickness the distances are in, mm.
        edges: (E, 2) vertex pairs of the singular edges (:func:`singular_edges`).
        root: (R, 3) the paths' starts on those edges (every ``0.1 wall`` along each, on each
            free face beside it).
        points: (R, J, 3) each path's read-out points on the free surface, ``READ_FROM`` to
            ``READ_TO`` walls from its root across the face.
        cell: (R, J) their elements; bary: (R, J, 4) their barycentric coordinates there.
        vertices: (K, 2) the (element, local vertex) pairs at least ``SINGULAR_ZONE`` walls
            from every singular edge: the region away from the edges, where the strain is read
            as it is.
        vertex_position: (K, 3) their positions.
    """

    wall: float
    edges: np.ndarray
    root: np.ndarray
    points: np.ndarray
    cell: np.ndarray
    bary: np.ndarray
    vertices: np.ndarray
    vertex_position: np.ndarray


def _fixed_nodes(model) -> np.ndarray:
    n = np.asarray(model.mesh.nodes).shape[0]
    free = np.zeros(3 * n, dtype=bool)
    free[np.asarray(model.mesh.free)] = True
    return ~free.reshape(n, 3).any(axis=1)


def _surface_grid(nodes, faces, spacing: float):
    """Points on the triangles ``faces`` (F, 3) at most ``spacing`` apart (a barycentric grid
    per triangle): (P, 3) positions and (P,) their triangles."""
    p = nodes[faces]
    size = np.max(np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2), axis=1)
    points, tris = [np.zeros((0, 3))], [np.zeros(0, np.int64)]
    for n in np.unique(np.maximum(1, np.ceil(size / spacing)).astype(int)):
        sel = np.flatnonzero(np.maximum(1, np.ceil(size / spacing)).astype(int) == n)
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        keep = i + j <= n
        lam = np.stack([i[keep], j[keep], n - i[keep] - j[keep]], axis=1) / n  # (G, 3)
        points.append(np.einsum("gk,fkd->fgd", lam, p[sel]).reshape(-1, 3))
        tris.append(np.repeat(sel, lam.shape[0]))
    return np.concatenate(points), np.concatenate(tris)


def bending_region(model, wall: float) -> BendingRegion:
    """The read-out paths and region of :func:`bending_strain` on the model's mesh, for the
    wall thickness ``wall`` (mm, > 0).

    The paths run on the free surface away from the singular edges: from each point of the
    surface within ``SINGULAR_ZONE`` walls of an edge, in its face's plane, away from the
    edge's nearest point; a path starts at the foot of that point's line (the line's point
    nearest the edge: on a face beside the edge, the edge itself; on the face across a wall
    from an inside corner, the point opposite it) and is read ``READ_FROM`` to ``READ_TO``
    walls from there. A path is kept where every read-out point lies on the free surface (the
    surface runs on flat) and none lies within ``READ_FROM`` walls of a singular edge.
    The region read as it is: every element vertex at least ``SINGULAR_ZONE`` walls from the
    edges.
    """
    import trimesh
    from scipy.spatial import cKDTree

    wall = float(wall)
    if not (math.isfinite(wall) and wall > 0):
        raise ValueError(f"wall = {wall!r}: must be a finite length > 0 (mm)")
    nodes = np.asarray(model.mesh.nodes, np.float64)
    cells4 = np.asarray(model.mesh.cells)[:, :4]
    fixed = _fixed_nodes(model)
    edges = singular_edges(nodes, cells4, fixed)
    faces, owner, local, normal = _free_faces(nodes, cells4, fixed)
    samples = _on_edges(nodes, edges, _SAMPLING * wall) if edges.size else np.zeros((0, 3))
    tree = cKDTree(samples) if samples.size else None

    def nearest(x):
        if tree is None:
            return np.full(len(x), np.inf), np.zeros((len(x), 3))
        d, i = tree.query(x)
        return d, samples[i]

    # Start points on the faces near the edges, their direction away from the nearest edge
    # point in their face's plane, and the foot of that line.
    near_faces = np.zeros(faces.shape[0], bool)
    if tree is not None:
        reach = SINGULAR_ZONE * wall + np.max(
            np.linalg.norm(nodes[faces] - nodes[faces].mean(1, keepdims=True), axis=2), axis=1
        )
        near_faces = nearest(nodes[faces].mean(axis=1))[0] <= reach
    start, tri = _surface_grid(nodes, faces[near_faces], _ALONG * wall)
    tri = np.flatnonzero(near_faces)[tri]
    d, s = nearest(start)
    inside = d <= SINGULAR_ZONE * wall
    start, tri, s, d = start[inside], tri[inside], s[inside], d[inside]
    away = start - s
    n = normal[tri]
    in_plane = away - np.einsum("pd,pd->p", away, n)[:, None] * n
    length = np.linalg.norm(in_plane, axis=1)
    ok = length >= _IN_PLANE * np.maximum(d, 1e-300)
    u = in_plane[ok] / length[ok, None]
    foot = start[ok] - np.einsum("pd,pd->p", away[ok], u)[:, None] * u
    # One path per foot and direction (many start points share them).
    key = np.round(np.concatenate([foot / (_ALONG * wall), u / _ALONG], axis=1)).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    root, u = foot[first], u[first]
    dist, _ = _fit_weights()
    R, J = root.shape[0], dist.size
    points, cell, bary = np.zeros((R, J, 3)), np.zeros((R, J), np.int64), np.zeros((R, J, 4))
    keep = np.zeros(R, bool)
    if R:
        surface = trimesh.Trimesh(nodes, faces, process=False)
        target = root[:, None] + (wall * dist)[None, :, None] * u[:, None]  # (R, J, 3)
        q, gap, on = trimesh.proximity.closest_point(surface, target.reshape(-1, 3))
        ok = (gap <= _ON_SURFACE * wall) & (nearest(q)[0] >= (READ_FROM - _ON_SURFACE) * wall)
        keep = ok.reshape(R, J).all(axis=1)
        b3 = np.clip(trimesh.triangles.points_to_barycentric(nodes[faces[on]], q), 0.0, 1.0)
        b4 = np.zeros((q.shape[0], 4))
        np.put_along_axis(b4, local[on], b3, axis=1)
        b4 /= b4.sum(axis=1, keepdims=True)
        points, cell, bary = q.reshape(R, J, 3), owner[on].reshape(R, J), b4.reshape(R, J, 4)
    vert = nodes[cells4]  # (m, 4, 3)
    beyond = nearest(vert.reshape(-1, 3))[0].reshape(-1, 4) >= SINGULAR_ZONE * wall
    vertices = np.argwhere(beyond)
    return BendingRegion(
        wall=wall,
        edges=edges,
        root=root[keep],
        points=points[keep],
        cell=cell[keep],
        bary=bary[keep],
        vertices=vertices,
        vertex_position=vert[vertices[:, 0], vertices[:, 1]],
    )


@dataclass(frozen=True, eq=False)
class BendingStrain(PeakStrain):
    """The peak strain of a rollout where a designer reads it (:func:`bending_strain`): the
    fields of :class:`PeakStrain` over the bending region, and how it was found.

    Attributes:
        at_edge: the peak is a singular edge's, extrapolated along a path from it (False: the
            largest strain of the region away from the edges, read as it is).
        readout: (J,) the largest principal strain at that path's points at the peak's step
            (NaN when not ``at_edge``), ``readout_distance`` (J,) mm from the edge.
        wall: the wall thickness the distances are in, mm.
        region: the :class:`BendingRegion` it was read on.

    ``position`` is the point on the edge the strain was extrapolated to, or the element vertex
    of the region where it was read; ``element`` the element of the path's first point or of
    that vertex. The von Mises stress follows the same rule (its own peak, edge or region).
    """

    at_edge: bool
    readout: np.ndarray
    readout_distance: np.ndarray
    wall: float
    region: BendingRegion


def _contact_exclusion(model, region: BendingRegion, contacts):
    """A function of the steps (S,) -> ``(path (S, R), vertex (S, K))`` bool: the paths with a
    point and the region vertices within ``CONTACT_CLEARANCE`` walls of a contact point
    active in the step (rest positions). ``contacts``: ``(index (n, C), active (n, C))``."""
    from scipy.sparse import csr_matrix
    from scipy.spatial import cKDTree

    R, J, K = region.points.shape[0], region.points.shape[1], region.vertices.shape[0]
    if contacts is None:
        return lambda rows: (np.zeros((rows.size, R), bool), np.zeros((rows.size, K), bool))
    index, active = (np.asarray(a) for a in contacts)
    ever, slot = np.unique(np.where(active, index, -1), return_inverse=True)
    slot = slot.reshape(index.shape)
    first = 1 if ever.size and ever[0] < 0 else 0  # -1: an inactive slot
    rest = np.asarray(model.samples.rest, np.float64)[ever[first:]]
    targets = np.concatenate([region.points.reshape(-1, 3), region.vertex_position])
    near = csr_matrix((rest.shape[0], targets.shape[0]), dtype=np.int8)
    if rest.size and targets.size:
        hits = cKDTree(targets).query_ball_point(rest, CONTACT_CLEARANCE * region.wall)
        counts = np.fromiter((len(h) for h in hits), np.int64, len(hits))
        cols = np.fromiter((j for h in hits for j in h), np.int64, int(counts.sum()))
        rows_ = np.repeat(np.arange(len(hits)), counts)
        near = csr_matrix((np.ones(cols.size, np.int8), (rows_, cols)), shape=near.shape)

    def excluded(rows):
        s = slot[rows] - first  # (S, C); negative: an inactive slot
        r, c = np.nonzero(s >= 0)
        step_of = csr_matrix((np.ones(r.size, np.int8), (r, s[r, c])), shape=(rows.size, rest.shape[0]))
        hit = (step_of @ near).toarray() > 0  # (S, targets)
        return hit[:, : R * J].reshape(rows.size, R, J).any(axis=2), hit[:, R * J :]

    return excluded


def _bending_batch(c, region: BendingRegion, E: float, nu: float, excluded):
    """Per step of one batch and per measure ("mp", "vm"): the value (S,), which (a path's
    index, or ``R + k`` for region vertex ``k``), and every path's read-outs (S, R, J); from
    the vertex strain components ``c`` (six (m, 4, S))."""
    R, J = region.cell.shape
    _, weights = _fit_weights()
    measures = {
        "mp": lambda comps: _max_principal(*comps),
        "vm": lambda comps: E / (1.0 + nu) * np.sqrt(1.5 * _dev2(*comps)),
    }
    cell, bary = region.cell.reshape(-1), region.bary.reshape(-1, 4)
    at_paths = tuple(np.einsum("pv,pvs->ps", bary, comp[cell]) for comp in c)  # P1/P2: affine per element
    at_vertices = tuple(comp[region.vertices[:, 0], region.vertices[:, 1]] for comp in c)
    path_out, vertex_out = excluded
    out = {}
    for name, f in measures.items():
        read = np.moveaxis(f(at_paths).reshape(R, J, c[0].shape[-1]), 2, 0)  # (S, R, J)
        line = np.where(path_out, np.nan, read @ weights)  # (S, R): the fit at the edge
        vert = np.where(vertex_out, np.nan, f(at_vertices).T)  # (S, K)
        value, arg = _nanmax_arg(np.concatenate([line, vert], axis=1))
        out[name] = (value, arg, read)
    return out


def _bending_peak(region: BendingRegion, bend: dict, t, el_mp, el_vm) -> BendingStrain:
    """The :class:`BendingStrain` of :func:`scan`'s per-step bending values."""
    R = region.root.shape[0]
    dist, _ = _fit_weights()

    def where(f):
        value, arg, read = bend[f]
        if not np.isfinite(value).any():
            return np.nan, -1, -1, np.full(3, np.nan), False, np.full(dist.size, np.nan)
        k = int(np.nanargmax(value))
        j = int(arg[k])
        if j < R:
            return float(value[k]), k, int(region.cell[j, 0]), region.root[j].copy(), True, read[k]
        v = region.vertices[j - R]
        position = region.vertex_position[j - R].copy()
        return float(value[k]), k, int(v[0]), position, False, np.full(dist.size, np.nan)

    peak, step, element, position, at_edge, readout = where("mp")
    vm_peak, vm_step, _, vm_position, _, _ = where("vm")
    return BendingStrain(
        **_peak_fields(
            t,
            (peak, step, element, position, bend["mp"][0]),
            (vm_peak, vm_step, vm_position, bend["vm"][0]),
            el_mp,
            el_vm,
        ),
        at_edge=at_edge,
        readout=readout,
        readout_distance=dist * region.wall,
        wall=region.wall,
        region=region,
    )


def bending_strain(model, result, *, wall: float, params=None, region: BendingRegion | None = None):
    """The peak strain of a whole rollout where a designer reads it: in the region of the part
    that bends, away from the places where the linear-elastic strain is singular (host, numpy).

    The largest principal strain at a clamped sharp edge, at a sharp inside corner and under a
    point or line contact grows without bound as the mesh is refined; a design guide's strain
    is the nominal strain there. So, at every step:

    - from each singular edge (the fixed region's edges on the free surface and the re-entrant
      edges, :func:`singular_edges`), along paths across the faces beside it, the surface
      strain ``READ_FROM`` = 1 to ``READ_TO`` = 3 walls from the edge is fitted by a straight
      line and extrapolated to the edge: on a bent arm's root, the root's nominal strain;
    - everywhere at least ``SINGULAR_ZONE`` = 1.5 walls from those edges, the strain is read as
      it is, at the element vertices (where each element's largest value lies);
    - points within ``CONTACT_CLEARANCE`` = 1 wall of a contact point active in that step are
      not read (a path with such a point is left out for that step).

    The peak is the largest of these over the steps. ``wall`` is the thickness of the part's
    bending walls, mm (a preset's ``connector.thickness``; a part file's thinnest wall). The
    whole part's largest strain (:func:`peak_strain`) stays the diagnostic of the singular
    places.

    Args:
        model: the built model.
        result: one rollout's result with its coordinates (``rollout(..., keep_x=True)``); its
            contact slots (``contact_index``, ``contact_active``) place the contacts.
        wall: the wall thickness, mm.
        params: the parameters the rollout ran with; None: ``model.params``.
        region: a :func:`bending_region` of the model for this ``wall`` computed before.

    Returns:
        :class:`BendingStrain`.

    Raises:
        ValueError: as :func:`peak_strain`, or ``wall`` not a length > 0.
    """
    E, nu = _material(model, params)
    x = _coordinates(result)
    contacts = (np.asarray(result.contact_index), np.asarray(result.contact_active))
    region = bending_region(model, wall) if region is None else region
    peaks, _ = scan(model, x, np.asarray(result.t), E, nu, bending=region, contacts=contacts)
    return peaks["bending"]
