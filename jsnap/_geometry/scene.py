"""Scene files: TOML in, a validated, immutable :class:`Scene` out.

Every key is declared once in ``_SCHEMA`` with its type, default (or ``REQUIRED``) and range.
Unknown keys, missing required keys, wrong types, non-finite numbers and out-of-range values
raise :class:`SceneError`, whose message names the key (``section.key``) and the value.

Units: mm, N, MPa, s, tonne (density in t/mm^3), angles in degrees.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from types import MappingProxyType
from typing import Any

__all__ = ["Scene", "SceneError", "default_scene_path", "load_scene"]


class SceneError(ValueError):
    """A scene file or scene value is invalid; the message names the key and the value."""


REQUIRED = object()

# Values the kernels implement in this version. A scene asking for another value of these keys
# is rejected at load time, naming the key, rather than accepted and silently replaced.
IMPLEMENTED = {
    ("solver", "method"): ("full", "modal", "segmented", "reduced"),
    ("solver", "sdf"): ("analytic", "mesh", "neural"),
}


@dataclass(frozen=True)
class _Key:
    kind: type
    default: Any = REQUIRED
    check: Callable[[Any], str | None] | None = None
    choices: tuple | None = None
    doc: str = ""


def _positive(v):
    return None if v > 0 else "must be > 0"


def _nonneg(v):
    return None if v >= 0 else "must be >= 0"


def _between(lo, hi, lo_open=True, hi_open=True):
    def check(v):
        ok_lo = v > lo if lo_open else v >= lo
        ok_hi = v < hi if hi_open else v <= hi
        if ok_lo and ok_hi:
            return None
        return f"must be in {'(' if lo_open else '['}{lo}, {hi}{')' if hi_open else ']'}"

    return check


def _optional_positive(v):
    return None if v is None or v > 0 else "must be > 0"


_SCHEMA: dict[str, dict[str, _Key]] = {
    "connector": {
        "type": _Key(str, choices=("cantilever",), doc="connector family"),
        "length": _Key(float, check=_positive, doc="L, mm"),
        "thickness": _Key(float, check=_positive, doc="h at the root, mm"),
        "tip_thickness": _Key(float, None, _optional_positive, doc="h_tip at z = L, mm"),
        "width": _Key(float, check=_positive, doc="b, mm"),
        "undercut": _Key(float, check=_positive, doc="y_u, mm"),
        "lead_angle": _Key(float, check=_between(0, 90), doc="alpha, degrees"),
        "return_angle": _Key(float, check=_between(0, 90, hi_open=False), doc="alpha', deg"),
        "flat": _Key(float, check=_nonneg, doc="flat land of the hook, mm"),
    },
    "material": {
        "youngs_modulus": _Key(float, check=_positive, doc="E, MPa"),
        "poissons_ratio": _Key(float, check=_between(-1, 0.5), doc="nu"),
        "density": _Key(float, check=_positive, doc="rho, t/mm^3"),
        "rayleigh_alpha": _Key(float, 0.0, _nonneg, doc="mass-proportional damping, 1/s"),
        "rayleigh_beta": _Key(float, 0.0, _nonneg, doc="stiffness-proportional damping, s"),
    },
    "contact": {
        "friction": _Key(float, 0.3, _nonneg, doc="Coulomb coefficient mu"),
        "capacity": _Key(int, 64, _positive, doc="contact buffer slots"),
        "spacing": _Key(float, 0.02, _positive, doc="candidate spacing along the section, mm"),
        "width_spacing": _Key(float, 1.0, _positive, doc="candidate spacing across width, mm"),
        "margin": _Key(float, 0.02, _nonneg, doc="distance below which a point is a candidate, mm"),
        "compliance": _Key(float, 0.0, _nonneg, doc="contact regularisation per point, mm/N"),
        "solver": _Key(str, "apgd", choices=("apgd", "admm", "spg", "pgs"), doc="cone-complementarity solver"),
        "iterations": _Key(int, 500, _positive, doc="maximum solver iterations per step"),
        "tolerance": _Key(float, 1e-6, _positive, doc="normalised KKT residual to stop at"),
        "gradient": _Key(
            str, "implicit", choices=("implicit", "unrolled"), doc="how jax.grad goes through the solve"
        ),
    },
    "plug": {
        "fillet": _Key(float, 0.1, _nonneg, doc="edge radius, mm"),
        "thickness": _Key(float, None, _optional_positive, doc="x extent, mm (1.25 y_u)"),
        "width": _Key(float, None, _optional_positive, doc="y extent, mm (b + 1)"),
        "height": _Key(float, 0.5, _positive, doc="z extent, mm"),
        "clearance": _Key(float, 0.02, _nonneg, doc="start gap above the hook top, mm"),
    },
    "motion": {
        "speed": _Key(float, 10.0, _positive, doc="insertion speed along -z, mm/s"),
        "stroke": _Key(float, None, _optional_positive, doc="travel, mm (default latches)"),
        "withdraw": _Key(bool, False, doc="return along +z after the stroke"),
        "control": _Key(str, "position", choices=("position", "impedance"), doc="plug drive"),
        "coupling_stiffness": _Key(float, 200.0, _positive, doc="virtual coupling, N/mm"),
        "coupling_damping": _Key(float, 2.0, _nonneg, doc="virtual coupling, N s/mm"),
        "plug_mass": _Key(float, 1e-5, _positive, doc="plug mass under impedance control, t"),
    },
    "solver": {
        "dt": _Key(float, 1e-3, _positive, doc="time step, s"),
        "method": _Key(str, "full", choices=("full", "modal", "segmented", "reduced")),
        "element": _Key(str, "P2", choices=("P1", "P2")),
        "mesh_size": _Key(float, 0.8, _positive, doc="element size, mm"),
        "hook_mesh_size": _Key(float, None, _optional_positive, doc="element size at the hook"),
        "sdf": _Key(str, "analytic", choices=("analytic", "mesh", "neural")),
        "dtype": _Key(str, "float32", choices=("float32", "float64"), doc="rollout precision"),
        # Segmented and reduced sockets (jsnap/_reduce.py, docs/reduction.md).
        "hsv_tolerance": _Key(
            float, 1e-2, _between(0, 1), doc="reduced: keep Hankel singular values above this x the largest"
        ),
        "subspace_modes": _Key(int, 30, _positive, doc="reduced: lowest modes per segment balanced over"),
        "segment_margin": _Key(float, 1.0, _nonneg, doc="contact segment grown by this, mm"),
        "segments": _Key(int, 1, _positive, doc="number of non-contact segments"),
        "interface_stiffness": _Key(float, 1e6, _positive, doc="k_c joining segment copies, N/mm"),
        "interface_damping": _Key(
            float, None, lambda v: None if v is None or v >= 0 else "must be >= 0", doc="b_c, N s/mm (k_c dt/2)"
        ),
    },
}


def _coerce(name: str, spec: _Key, value: Any) -> Any:
    """Check type, finiteness, choices and range of one value; return it normalised."""
    if value is None and spec.default is None:
        return None
    if spec.kind is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise SceneError(f"{name} = {value!r}: must be a number")
        value = float(value)
        if not math.isfinite(value):
            raise SceneError(f"{name} = {value!r}: must be finite")
    elif spec.kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise SceneError(f"{name} = {value!r}: must be an integer")
    elif spec.kind is bool:
        if not isinstance(value, bool):
            raise SceneError(f"{name} = {value!r}: must be true or false")
    elif spec.kind is str and not isinstance(value, str):
        raise SceneError(f"{name} = {value!r}: must be a string")
    if spec.choices is not None and value not in spec.choices:
        raise SceneError(f"{name} = {value!r}: must be one of {', '.join(spec.choices)}")
    if spec.check is not None:
        problem = spec.check(value)
        if problem:
            raise SceneError(f"{name} = {value!r}: {problem}")
    return value


@dataclass(frozen=True)
class Scene:
    """A validated scene: ``scene["material"]["youngs_modulus"]`` or ``scene.get(...)``.

    Attributes:
        sections: read-only mapping ``section -> key -> value`` with every default filled in.
        source: where the scene came from (a path, or ``"<dict>"``).
    """

    sections: Mapping[str, Mapping[str, Any]]
    source: str = field(default="<dict>", compare=False)

    def __getitem__(self, section: str) -> Mapping[str, Any]:
        return self.sections[section]

    def get(self, dotted: str) -> Any:
        """Value of ``"section.key"``."""
        section, key = _split(dotted)
        return self.sections[section][key]

    def replace(self, changes: Mapping[str, Any] | None = None, **kw: Any) -> Scene:
        """A new, re-validated scene with ``{"section.key": value}`` changes applied.

        Keyword form: ``scene.replace(solver__mesh_size=0.3)``.
        """
        changes = dict(changes or {})
        changes.update({k.replace("__", "."): v for k, v in kw.items()})
        raw = {s: dict(v) for s, v in self.sections.items()}
        for dotted, value in changes.items():
            section, key = _split(dotted)
            if section not in raw:
                raise SceneError(f"unknown section [{section}] in {dotted!r}")
            raw[section][key] = value
        return Scene.from_dict(raw, source=self.source)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """Plain nested dict (defaults included), e.g. for JSON summaries and cache keys."""
        return {s: dict(v) for s, v in self.sections.items()}

    @classmethod
    def from_dict(cls, raw: Mapping[str, Any], source: str = "<dict>") -> Scene:
        """Validate a nested mapping (as parsed from TOML) into a :class:`Scene`."""
        if not isinstance(raw, Mapping):
            raise SceneError(f"a scene must be a table of sections, got {type(raw).__name__}")
        for section in raw:
            if section not in _SCHEMA:
                raise SceneError(f"unknown section [{section}]; expected one of {', '.join(_SCHEMA)}")
        sections: dict[str, Mapping[str, Any]] = {}
        for section, keys in _SCHEMA.items():
            given = raw.get(section, {})
            if not isinstance(given, Mapping):
                raise SceneError(f"[{section}] must be a table, got {given!r}")
            for key in given:
                if key not in keys:
                    raise SceneError(
                        f"unknown key {section}.{key} = {given[key]!r}; [{section}] takes {', '.join(keys)}"
                    )
            values = {}
            for key, spec in keys.items():
                name = f"{section}.{key}"
                if key in given:
                    values[key] = _coerce(name, spec, given[key])
                elif spec.default is REQUIRED:
                    raise SceneError(f"{name} is required but missing ({spec.doc})")
                else:
                    values[key] = spec.default
                implemented = IMPLEMENTED.get((section, key))
                if implemented is not None and values[key] not in implemented:
                    raise SceneError(
                        f"{name} = {values[key]!r}: not available in this version of jsnap "
                        f"(available: {', '.join(implemented)})"
                    )
            sections[section] = MappingProxyType(values)
        scene = cls(MappingProxyType(sections), source)
        _check_consistency(scene)
        return scene


def _split(dotted: str) -> tuple[str, str]:
    parts = dotted.split(".")
    if len(parts) != 2:
        raise SceneError(f"expected 'section.key', got {dotted!r}")
    return parts[0], parts[1]


def connector_geometry(scene: Scene):
    """The scene's connector as a :class:`jsnap._geometry.cantilever.Cantilever` (validated)."""
    from jsnap._geometry.cantilever import Cantilever

    c = scene["connector"]
    keys = ("length", "thickness", "tip_thickness", "width", "undercut", "lead_angle")
    return Cantilever(**{k: c[k] for k in keys}, return_angle=c["return_angle"], flat=c["flat"])


def _check_consistency(scene: Scene) -> None:
    """Checks that involve several keys (geometry the section cannot hold, plug sizes...)."""
    # The geometry module validates the connector and names the key itself.
    c = scene["connector"]
    try:
        connector_geometry(scene)
    except ValueError as err:
        raise SceneError(str(err)) from None
    p = scene["plug"]
    half = 0.5 * min(p["thickness"] or 1.25 * c["undercut"], p["width"] or c["width"] + 1.0, p["height"])
    if p["fillet"] > half:
        raise SceneError(
            f"plug.fillet = {p['fillet']!r}: must be <= half the plug's smallest side ({half:g} mm)"
        )
    ct = scene["contact"]
    if ct["solver"] == "spg" and ct["gradient"] == "unrolled":
        # Measured: 0.3 % off the solution's derivative on a well-conditioned problem solved to
        # 1e-13, where unrolled APGD and ADMM agree with finite differences to 1e-5.
        raise SceneError(
            "contact.gradient = 'unrolled' with contact.solver = 'spg': SPG's spectral steps reach "
            "past 2/||W||, so the unrolled iteration's derivative does not settle on the solution's; "
            "use contact.gradient = 'implicit' (the default)"
        )


def load_scene(path: str | Path | None = None) -> Scene:
    """Load and validate a scene TOML file (``None``: the shipped default scene).

    Raises:
        SceneError: unknown or missing keys, wrong types, impossible values (naming the key).
        FileNotFoundError: the file does not exist.
    """
    if path is None:
        path = default_scene_path()
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise FileNotFoundError(f"scene file not found: {path}") from None
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise SceneError(f"{path}: not valid TOML: {err}") from None
    try:
        return Scene.from_dict(raw, source=str(path))
    except SceneError as err:
        raise SceneError(f"{path}: {err}") from None


def default_scene_path() -> Path:
    """Path of the shipped default scene (the reference hook of the CalculiX comparison)."""
    return Path(str(resources.files("jsnap") / "scenes" / "default.toml"))
