"""The summary's headline numbers: the bending strain (read where a designer reads it, away from
the singular edges and the contacts, found on its own for a part from a file) and the peak
insertion force (robust to a one-step impulse).

The part is the default hook written out as an STL and run from the command line as a part from
a file; beam theory on the rollout's own base wrench is the independent check of the strain.
"""

from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest
import trimesh

import jsnap
from jsnap._apps.cli import main as cli_main
from jsnap._apps.simulate import PEAK_FORCE_STEPS, peak_force
from jsnap._build.strain import bending_strain
from jsnap._geometry.cantilever import mesh_cantilever
from jsnap._geometry.presets import default_rigid
from jsnap._geometry.scene import connector_geometry

E, NU = 2200.0, 0.35
L, H, B, UNDERCUT = 10.0, 1.2, 4.0, 0.8  # the default hook's arm and undercut, mm


@pytest.fixture(scope="module")
def file_run(tmp_path_factory):
    """``jsnap simulate --json`` on the default hook and plug given as STL files (the default
    0.8 mm elements): the summary and the forces."""
    d = tmp_path_factory.mktemp("headline")
    scene = jsnap.load_scene()
    mesh = mesh_cantilever(connector_geometry(scene), 0.8)
    trimesh.Trimesh(mesh.points, mesh.boundary_faces()).export(d / "hook.stl")
    plug = default_rigid("cantilever", scene["connector"], scene["plug"])
    plug_mesh = plug.mesh()
    plug_mesh.apply_translation(plug.start)
    plug_mesh.export(d / "plug.stl")
    (d / "scene.toml").write_text(
        "[part]\n"
        'mesh = "hook.stl"\n'
        "fixed_box = [[-1.0, -3.0, -0.01], [2.5, 3.0, 0.01]]\n"
        "[rigid]\n"
        'mesh = "plug.stl"\n'
        "[material]\n"
        f"youngs_modulus = {E}\npoissons_ratio = {NU}\ndensity = 1.05e-9\n"
        "[motion]\n"
        "stroke = 2.3\n"
        "[solver]\n"
        "mesh_size = 0.8\n"
    )
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = cli_main(["simulate", str(d / "scene.toml"), "--out", str(d / "out"), "--json"])
    assert code == 0
    forces = np.genfromtxt(d / "out" / "forces.csv", delimiter=",", names=True)
    return json.loads(out.getvalue()), forces


def _beam_root_strain(forces, k: int) -> float:
    """Beam theory at the arm's root from the base wrench of step ``k``: the surface strain of
    the bending moment, ``6 |M_y| / (E b h^2)``, and the axial force's, ``-F_z / (E b h)``."""
    return 6.0 * abs(forces["base_my_Nmm"][k]) / (E * B * H**2) - forces["base_fz_N"][k] / (E * B * H)


def test_bending_strain_of_a_file_part_is_beam_theory_at_its_root(file_run):
    """Found on its own: the wall (the file's thinnest, the arm's 1.2 mm), the singular edges
    (the clamp's), and the peak extrapolated to the clamped root, where beam theory on the
    rollout's own base moment gives the strain; the design guide's nominal strain
    (1.5 h y / L^2, the undercut as the deflection at L) is within 10 %."""
    summary, forces = file_run
    assert summary["status"] == "ok"
    assert summary["design_guide_strain"] is None  # a part from a file has no guide
    assert summary["bending_wall_mm"] == pytest.approx(H, rel=1e-3)
    assert summary["bending_singular_edges"] > 0 and summary["bending_paths"] > 0
    assert summary["bending_strain_found"] == "extrapolated to a singular edge"
    x, _, z = summary["bending_peak_strain_position_mm"]
    assert abs(z) < 0.05 and x == pytest.approx(H, abs=0.05)  # the root's tension face
    eps, k = summary["bending_peak_strain"], summary["bending_peak_strain_step"]
    beam = _beam_root_strain(forces, k)
    assert eps == pytest.approx(beam, rel=0.03)
    assert eps == pytest.approx(1.5 * H * UNDERCUT / L**2, rel=0.10)
    # The read-out line: the strain falls off along the arm (a bent beam's, linear in z).
    readout = np.asarray(summary["bending_strain_readout"])
    assert np.polyfit(summary["bending_strain_readout_mm"], readout, 1)[0] < 0
    # The whole part's largest strain is kept, as a diagnostic, beside it.
    assert summary["peak_strain"] > 0 and summary["peak_strain_position_mm"] is not None


def test_bending_strain_of_the_preset_matches_the_file_part(file_run):
    """The preset (its structured mesh, its analytic plug) and the file part (gmsh's mesh of
    the same hook, the plug's triangles) give the same bending strain, to 3 %, with the guide
    only on the preset."""
    summary, _ = file_run
    scene = jsnap.load_scene()
    model = jsnap.build(scene)
    res = jsnap.rollout(model, keep_x=True)
    bend = bending_strain(model, res, wall=float(scene["connector"]["thickness"]))
    assert bend.at_edge
    assert bend.max_principal == pytest.approx(summary["bending_peak_strain"], rel=0.03)


def test_peak_force_leaves_out_a_one_step_impulse(file_run):
    """On the rollout's force history the headline peak is the curve's (within one step's rise
    of its largest step); an impulse put into one step and taken back in the next (the spike
    and dip of a contact point's impact, here 9.5 times the force there, then 0.6 N), or two
    steps of it, leave it unchanged, where the largest single step follows the spike."""
    summary, forces = file_run
    F = forces["insertion_force_N"]
    head, k = peak_force(F)
    assert summary["peak_force_N"] == pytest.approx(head, rel=1e-6)
    assert summary["peak_insertion_force_N"] == pytest.approx(F.max(), rel=1e-6)
    assert summary["peak_force_steps"] == PEAK_FORCE_STEPS
    rise = np.max(np.abs(np.diff(F[max(0, k - 5) : k + 5])))
    assert F.max() - rise <= head <= F.max()
    spiked = F.copy()
    i = int(np.argmin(np.abs(F - 0.5 * F.max())))  # on the rise, half way up
    spiked[i], spiked[i + 1] = 9.5 * F[i], 0.6
    assert spiked.max() > 4 * F.max()
    assert peak_force(spiked) == (head, k)
    spiked[i + 1] = 9.5 * F[i + 1]
    assert peak_force(spiked) == (head, k)
