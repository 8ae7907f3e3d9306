"""A part nobody tuned jsnap for: a C-shaped pipe clip (tests/data/pipe_clip) spread by a rigid
pin, frictionless and undamped, with the default method (the reduced model) in float64.

Without friction or damping the contact can only store what the pin puts in: up to the peak the
part's energy must equal the pin's work (the default hook holds this to 1e-3, see
``test_simulate.py::test_frictionless_contact_conserves_energy_up_to_the_peak``). On this clip
it does not: the energy at the peak is 0.14 times the work (the full model's 0.16), and the peak
falls as the time step is refined (18.0 N at 1 ms, 15.2 N at 62.5 µs). The cause is the contact
normal (``jsnap._core.collision.contact_normal``): the part's own face normal on faces, and at
an edge the rigid part's normal held to the cone between the two faces' normals. With the rigid
part's normal at every point this clip conserves energy (0.98 of the work at 1 ms, 0.997 at
0.25 ms) and peaks at 2.2 N at either step; but the shipped hook needs the shipped rule (with
the rigid part's normal at its edges it peaks at 3.8 N frictionless, everywhere at 5.3 N,
against CalculiX's 2.49 N). A known
error, kept as a strict expected failure: once a rule serves both, this test passes and the
marker must go.
"""

from pathlib import Path

import numpy as np
import pytest

import jsnap

SCENE = Path(__file__).parent / "data" / "pipe_clip" / "scene.toml"


@pytest.mark.xfail(
    strict=True,
    reason="the contact normals at the clip's edges and curved faces do not follow the pin's surface: its "
    "frictionless contact dissipates energy",
)
def test_pipe_clip_frictionless_contact_conserves_energy_up_to_the_peak():
    scene = jsnap.load_scene(SCENE).replace({"contact.friction": 0.0, "solver.dtype": "float64"})
    res = jsnap.rollout(jsnap.build(scene))
    assert res.ok, res.status()
    F = np.asarray(res.insertion_force)
    k = int(F.argmax())
    E, W = np.asarray(res.energy)[: k + 1], np.cumsum(np.asarray(res.work))[: k + 1]
    assert W[-1] > 1.0  # the arms were spread (N mm)
    assert np.abs(E - W).max() < 2e-2 * W[-1]
