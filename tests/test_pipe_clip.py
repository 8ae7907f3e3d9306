"""A part nobody tuned jsnap for: a C-shaped pipe clip (tests/data/pipe_clip) spread by a rigid
pin, frictionless and undamped, with the default method (the reduced model) in float64.

Without friction or damping the contact can only store what the pin puts in: up to the peak the
part's energy must equal the pin's work (the default hook holds this to 1e-3, see
``test_simulate.py::test_frictionless_contact_conserves_energy_up_to_the_peak``), up to the
time discretisation's error, which halves with the step. Here the pin's large curved surface
presses the sharp edges of the clip's mouth, the case the contact normal rule
(``jsnap._core.collision.contact_normal``) must get right besides a small fillet on a face: the
face points beside those edges would, with their faces' normals, push the pin across a gap
(energy 0.14 of the work, a peak 8 times too high and moving with the step), and a facet that a
sampling line touches at a vertex only once gave an edge point no normal of its own.
"""

import functools
from pathlib import Path

import numpy as np
import pytest

import jsnap
from jsnap._apps.simulate import energy_to_peak
from jsnap._geometry.scene import with_internal

SCENE = Path(__file__).parent / "data" / "pipe_clip" / "scene.toml"


@functools.cache
def _rollout(dt, hand_over="auto"):
    frictionless = {"contact.friction": 0.0, "solver.dtype": "float64", "solver.dt": dt}
    scene = with_internal(jsnap.load_scene(SCENE), {**frictionless, "contact.hand_over": hand_over})
    res = jsnap.rollout(jsnap.build(scene))
    assert res.ok, res.status()
    return res


def _frictionless(dt):
    res = _rollout(dt)
    F = np.asarray(res.insertion_force)
    k = int(F.argmax())
    E, W = np.asarray(res.energy)[: k + 1], np.cumsum(np.asarray(res.work))[: k + 1]
    assert W[-1] > 0.3  # the arms were spread (N mm)
    return F[k], np.abs(E - W).max() / W[-1]


def test_pipe_clip_frictionless_contact_conserves_energy_up_to_the_peak():
    peak, error = _frictionless(1e-3)
    peak_half, error_half = _frictionless(5e-4)
    assert error < 2.5e-2
    assert error_half < 0.6 * error  # first order in the step
    assert abs(peak_half - peak) < 0.02 * peak


def test_simulate_warns_where_the_normal_forces_hold_the_pin_across_a_gap():
    """Without the hand-over the face points beside the mouth's edges hold the pin across a gap:
    their normal forces take most of its work, and ``jsnap simulate``'s energy budget says so;
    with it they take what the time step's error allows, and it does not."""
    budget, warning = energy_to_peak(_rollout(1e-3))
    assert warning is None
    assert 0 <= budget["normal_dissipation_Nmm"] < 2.5e-2 * budget["work_Nmm"]
    budget, warning = energy_to_peak(_rollout(1e-3, "off"))
    assert budget["normal_dissipation_Nmm"] > 0.5 * budget["work_Nmm"]
    assert warning is not None and "across a gap" in warning


def _off_centre_scene(tmp_path):
    """The clip's scene with the pin entering 0.2 mm off the clip's centre and turning by 3°."""
    a = np.radians(3.0) / 2
    first = "{ t = 0.0, position = [0.0, 0.0, 0.0], rotation = [1.0, 0.0, 0.0, 0.0] }"
    last = f"{{ t = 0.165, position = [0.2, -3.3, 0.0], rotation = [{np.cos(a)}, 0.0, 0.0, {np.sin(a)}] }}"
    text = SCENE.read_text()
    motion = f"[motion]\nwaypoints = [\n  {first},\n  {last},\n]\n\n"
    text = text[: text.index("[motion]")] + motion + text[text.index("[solver]") :]
    for name in ("clip.msh", "pin.stl"):
        (tmp_path / name).write_bytes((SCENE.parent / name).read_bytes())
    (tmp_path / "scene.toml").write_text(text)
    return jsnap.load_scene(tmp_path / "scene.toml")


@pytest.mark.xfail(
    strict=True,
    reason="after the snap the mouth's edges, sliding on the pin's back, and the seat's wall take normals 5-10 "
    "degrees off the pin's and hold it across gaps of a few um: 0.61 of the work is kept at the peak "
    "(docs/contact.md, known limitations)",
)
def test_off_centre_pin_frictionless_contact_conserves_energy_up_to_the_peak(tmp_path):
    frictionless = {"contact.friction": 0.0, "solver.dtype": "float64"}
    res = jsnap.rollout(jsnap.build(_off_centre_scene(tmp_path).replace(frictionless)))
    assert res.ok, res.status()
    budget, _ = energy_to_peak(res)
    assert budget["work_Nmm"] > 0.3
    assert budget["energy_Nmm"] > 0.975 * budget["work_Nmm"]
