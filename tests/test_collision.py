"""The contact normal of a candidate point (``jsnap._core.collision.contact_normal``) against
analytic geometry: a flat face of the part (the plane z = 0, the part below it) and a rigid
cylinder along y (its SDF normal in closed form), whose tangency with the face's plane lies at
the cylinder's x. Where the tangency lies on the face, the face's normal is the contact's (a
fillet pressing the face, whose SDF normal at a sample beside the contact line is off by the
fillet's arc); where it lies beyond the face's edge, the rigid part touches that edge and the
face point carries no contact (the edge's own corner points do).
"""

import itertools
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jsnap
from jsnap._build.samples import line_reach, surface_samples
from jsnap._core.collision import contact_normal
from jsnap._geometry.scene import default_scene_path

SPACING = 0.02


def face_stencil(x):
    """(C, 8, 3) stencils of points (x, 0, 0) on the face z = 0 (outward +z): along x and
    across y, so that cross(s3 - s2, s1 - s0) is +z; the second half the same (face points)."""
    p = jnp.stack([x, jnp.zeros_like(x), jnp.zeros_like(x)], 1)
    ex, ey = jnp.asarray([0.25, 0, 0]), jnp.asarray([0, 0.5, 0])
    own = jnp.stack([p - ex, p + ex, p + ey, p - ey], 1)
    return jnp.concatenate([own, own], 1), p


def cylinder(c):
    """The outward SDF normal of a cylinder along y through c = (cx, cz)."""

    def normal(q):
        d = jnp.stack([q[:, 0] - c[0], jnp.zeros_like(q[:, 0]), q[:, 2] - c[1]], 1)
        return d / jnp.linalg.norm(d, axis=1, keepdims=True)

    return normal


def half_space(c):
    """The outward normal of a flat rigid face tilted by c[0] rad about y: (-sin, 0, -cos)."""
    return lambda q: jnp.broadcast_to(jnp.stack([-jnp.sin(c[0]), 0.0 * c[0], -jnp.cos(c[0])]), q.shape)


@partial(jax.jit, static_argnums=0)
def _classify(rigid, x, face, c):
    stencil, p = face_stencil(x)
    reach = jnp.stack([p[:, 0] - face[0], face[1] - p[:, 0]], 1)
    line = jnp.tile(jnp.asarray([1.0, 0, 0]), (p.shape[0], 1))
    normal_at = rigid(c)
    n_plug = normal_at(p)
    corner = jnp.zeros(p.shape[0], bool)
    phi = jnp.full(p.shape[0], 1e-3)  # outside the rigid part
    n, carries = contact_normal(stencil, phi, n_plug, corner, p, line, reach, SPACING, normal_at)
    return n, carries, n_plug


def classify(x, face, rigid, c):
    """Contact normals and whether each point carries a contact, for points at x on the face
    spanning x in ``face`` (its line of samples along +x), against ``rigid(c)``."""
    out = _classify(rigid, jnp.asarray(x, float), jnp.asarray(face, float), jnp.asarray(c, float))
    return tuple(np.asarray(a) for a in out)


@pytest.mark.parametrize("radius", [0.05, 0.1, 0.3, 1.0])
def test_a_fillet_pressing_a_face_takes_the_face_normal(radius):
    """A fillet of radius r tangent to the face (pressed 2 µm into it) at x = xc: every sample
    within two spacings of the tangency keeps the face normal and carries the contact, though
    the fillet's own normal there is off by up to 2 spacing / r (up to 39°)."""
    for xc, d in itertools.product([-0.4, 0.0, 0.3], np.linspace(-2 * SPACING, 2 * SPACING, 9)):
        n, carries, n_plug = classify([xc + d], (-1.0, 1.0), cylinder, (xc, radius - 0.002))
        assert carries.all(), (radius, xc, d)
        np.testing.assert_allclose(n, [[0, 0, -1]], atol=1e-6)
        if abs(d) >= SPACING:
            assert abs(n_plug[0, 0]) > 0.9 * np.sin(SPACING / radius)  # the fillet's normal is tilted


@pytest.mark.parametrize("radius,angle", list(itertools.product([1.0, 1.9, 5.0], [20.0, 35.0, 50.0])))
def test_a_face_point_beside_an_edge_a_large_rigid_part_presses_carries_no_contact(radius, angle):
    """A cylinder of radius R touching the face's edge x = 0 with its normal tilted by theta
    from the face's: its tangency with the face's plane lies R sin(theta) beyond the edge. The
    face points one and two spacings from the edge carry no contact (the face normal would
    push the rigid part across a gap); with the face extended past the tangency they keep
    the face normal."""
    t = np.radians(angle)
    c = (radius * np.sin(t), radius * np.cos(t) + 1e-4)
    x = [-SPACING, -2 * SPACING]
    _, carries, _ = classify(x, (-2.0, 0.0), cylinder, c)
    assert not carries.any(), (radius, angle)
    n, carries, _ = classify(x, (-2.0, 3 * radius), cylinder, c)
    assert carries.all()
    np.testing.assert_allclose(n, [[0, 0, -1]] * 2, atol=1e-6)


def test_a_small_fillet_rolling_over_the_faces_edge_leaves_the_face_its_normal():
    """A fillet of radius 0.1 mm rolling over the face's edge x = 0 (its normal there tilted
    30 degrees): its tangency lies beyond the edge, but its normal turns 11 degrees per
    spacing, so the gap beside the edge opens fast; the face points keep the face's normal."""
    t = np.radians(30.0)
    c = (0.1 * np.sin(t), 0.1 * np.cos(t) + 1e-4)
    n, carries, _ = classify([-SPACING, -2 * SPACING], (-2.0, 0.0), cylinder, c)
    assert carries.all()
    np.testing.assert_allclose(n, [[0, 0, -1]] * 2, atol=1e-6)


@pytest.mark.parametrize("tilt,carries", [(0.5, True), (5.0, True), (30.0, False)])
def test_a_flat_rigid_face_tilted_to_the_face_meets_its_edge(tilt, carries):
    """A flat rigid face (a half-space) tilted by beta about y touches the part's face only at
    its edge: a face point carries no contact, unless the two are within 10 degrees of
    parallel (the gap beside the edge is then at most a sixth of the distance to it)."""
    _, c, _ = classify([-0.5, 0.0, 0.5], (-1.0, 1.0), half_space, [np.radians(tilt)])
    assert (c == carries).all()


def test_an_edge_point_takes_the_rigid_normal_within_its_cone():
    """A corner point on the edge between the face z = 0 (into-part normal -z) and the face
    x = 0 (-x): a rigid normal inside the cone between them is the contact's; outside it, the
    nearer face's normal."""
    stencil, p = face_stencil(np.zeros(3))
    # The second stencil on the face x = 0 (outward +x): cross(s7 - s6, s5 - s4) = +x.
    ez, ey = np.array([0, 0, 0.25]), np.array([0, 0.5, 0])
    other = np.stack([p, p - ez, p + ey, p - ey], 1)
    stencil = np.concatenate([stencil[:, :4], other], 1)
    a = np.radians([40.0, 100.0, -10.0])  # from -z toward -x
    n_plug = jnp.asarray(np.stack([-np.sin(a), 0 * a, -np.cos(a)], 1))
    n, carries = contact_normal(
        jnp.asarray(stencil), jnp.zeros(3), n_plug, jnp.ones(3, bool), jnp.asarray(p), jnp.zeros((3, 3)),
        jnp.zeros((3, 2)), SPACING, lambda q: n_plug,
    )  # fmt: skip
    assert np.asarray(carries).all()
    np.testing.assert_allclose(np.asarray(n), [np.asarray(n_plug[0]), [-1, 0, 0], [0, 0, -1]], atol=1e-6)


def test_line_reach_measures_each_points_line():
    """Two lines of points, given out of order: each point's direction is its line's (first
    to last by order) and its reach back and on sum to the line's length."""
    X = np.array([[0.0, 0, 0], [0.2, 0, 0], [0.1, 0, 0], [0, 1, 1], [0, 1, 0.5], [5, 5, 5]])
    group = np.array([0, 0, 0, 1, 1, 2])
    order = np.array([0, 2, 1, 0, 1, 0])
    u, reach = line_reach(X, group, order)
    np.testing.assert_allclose(u, [[1, 0, 0]] * 3 + [[0, 0, -1]] * 2 + [[0, 0, 0]])
    np.testing.assert_allclose(reach, [[0, 0.2], [0.2, 0], [0.1, 0.1], [0, 0.5], [0.5, 0], [0, 0]], atol=1e-12)


@pytest.mark.parametrize(
    "scene,box",
    [
        (Path(__file__).parent / "data" / "pipe_clip" / "scene.toml", None),
        (default_scene_path().parent / "box_lid.toml", ([1.5, -6.5, 8.0], [4.0, -1.5, 11.0])),  # one hook
    ],
    ids=["pipe_clip", "box_lid"],
)
def test_every_candidate_points_stencils_give_its_faces_normals(scene, box):
    """The general surface sampling over the whole part: each point's two normal stencils
    (its own face's and, at a corner, the face across the edge) give unit normals equal to the
    faces' it reports (on the box lid, around one hook). On the clip's curved faces every
    facet is a patch of its own, and a sampling line may touch one at a vertex only: its
    stencil has no length along the line and no normal, which the sampler replaces by the
    facet's own triangle."""
    from jsnap._build import model as M

    scene = jsnap.load_scene(scene)
    g = M._geometry(scene)
    ct = scene["contact"]
    whole = (g.mesh.points.min(axis=0) - 1, g.mesh.points.max(axis=0) + 1)
    lo, hi = whole if box is None else map(np.array, box)
    X, normals, corner, stencil, _, _ = surface_samples(
        g.mesh, lo, hi, g.axis, ct["spacing"], ct["width_spacing"]
    )
    assert X.shape[0] > 100 and corner.any()
    for k in (0, 1):
        s = stencil[:, 4 * k : 4 * k + 4]
        m = np.cross(s[:, 3] - s[:, 2], s[:, 1] - s[:, 0])
        size = np.linalg.norm(m, axis=1)
        assert size.min() > 1e-6, np.flatnonzero(size <= 1e-6)
        np.testing.assert_allclose(m / size[:, None], normals[:, k], atol=1e-6)
