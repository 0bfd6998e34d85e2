import jax
import jax.numpy as jnp
import numpy as np
import pytest

import slcvjax as sj

from ._helpers import central_diff


def _board(rvec, t):
    return sj.Pose.from_rvec(np.asarray(rvec, float), np.asarray(t, float))


def test_spot_on_a_frontal_plane_closed_form():
    # plane z = 100 (board frame identity rotation, moved 100 mm forward)
    pose = _board([0, 0, 0], [0, 0, 100.0])
    x, ok = sj.line_plane_intersection(jnp.array([1.0, 2.0, 0.0]), jnp.array([0.6, 0.0, 0.8]), pose)
    assert bool(ok)
    np.testing.assert_allclose(np.asarray(x), [1.0 + 75.0, 2.0, 100.0], atol=1e-12)


def test_spot_lies_on_line_and_plane(rng):
    pose = _board(rng.normal(size=3), rng.normal(size=3) * 50 + [0, 0, 200])
    p = jnp.asarray(rng.normal(size=3))
    n = pose.R[:, 2]
    d = jnp.asarray(n + 0.3 * rng.normal(size=3))
    d = d / jnp.linalg.norm(d)
    x, ok = sj.line_plane_intersection(p, d, pose)
    assert bool(ok)
    assert abs(float(jnp.dot(n, x - pose.t))) < 1e-10
    assert float(jnp.linalg.norm(jnp.cross(x - p, d))) < 1e-10


def test_parallel_and_backward_beams_are_invalid_without_nan():
    pose = _board([0, 0, 0], [0, 0, 100.0])
    p = jnp.zeros(3)
    for d in [jnp.array([1.0, 0.0, 0.0]), jnp.array([0.0, 0.0, -1.0])]:
        x, ok = sj.line_plane_intersection(p, d, pose)
        assert not bool(ok)
        assert np.all(np.isfinite(np.asarray(x)))
        g = jax.jacrev(lambda d: sj.line_plane_intersection(p, d, pose)[0])(d)
        assert np.all(np.isfinite(np.asarray(g)))


@pytest.mark.slow
def test_retract_is_4_dof_per_line_and_keeps_unit_directions():
    lasers = sj.Lasers.create([[30.0, 0, 40], [0, 30.0, 40]], [[0.9, 0, -0.45], [0, 0.9, -0.45]])

    def flat(delta):
        las = lasers.retract(delta.reshape(2, 4))
        return jnp.concatenate([las.points.ravel(), las.directions.ravel()])

    j = np.asarray(jax.jit(jax.jacfwd(flat))(jnp.zeros(8)))
    assert np.linalg.matrix_rank(j, tol=1e-9) == 8
    moved = lasers.retract(jnp.full((2, 4), 0.1))
    np.testing.assert_allclose(np.linalg.norm(np.asarray(moved.directions), axis=1), 1.0, atol=1e-15)


def test_canonical_point_is_the_foot_of_the_perpendicular():
    lasers = sj.Lasers.create([[30.0, 5.0, 40.0]], [[0.9, 0.1, -0.45]])
    c = lasers.canonical()
    assert abs(float(jnp.dot(c.points[0], c.directions[0]))) < 1e-12
    # still the same line
    assert float(jnp.linalg.norm(jnp.cross(c.points[0] - lasers.points[0], lasers.directions[0]))) < 1e-12


def test_spot_jacobian_matches_finite_differences(rng):
    pose = _board([0.1, -0.2, 0.05], [5.0, -3.0, 150.0])

    def f(v):
        return sj.line_plane_intersection(v[:3], v[3:] / jnp.linalg.norm(v[3:]), pose)[0]

    v = jnp.array([1.0, 2.0, 3.0, 0.1, 0.2, 0.95])
    f = jax.jit(f)
    np.testing.assert_allclose(jax.jacfwd(f)(v), central_diff(f, np.asarray(v)), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(jax.jacfwd(f)(v), jax.jacrev(f)(v), atol=1e-12)


@pytest.mark.parametrize("n", [1, 3, 17])
def test_any_number_of_lasers(n):
    pts = np.zeros((n, 3))
    dirs = np.tile([0.0, 0.0, 1.0], (n, 1))
    las = sj.Lasers.create(pts, dirs)
    assert las.n == n
    assert las.retract(jnp.zeros((n, 4))).points.shape == (n, 3)


def test_working_point_foot_and_the_tangent_columns():
    rng = np.random.default_rng(3)
    n = 3
    d = rng.normal(size=(n, 3))
    lasers = sj.Lasers.create(rng.normal(size=(n, 3)) * 20, d / np.linalg.norm(d, axis=1, keepdims=True))
    x_ref = np.array([30.0, -40.0, 120.0])
    foot, direction = lasers.at_working_point(1, x_ref)
    # the foot lies on the line and x_ref - foot is perpendicular to it
    p, u = np.asarray(lasers.points[1]), np.asarray(lasers.directions[1])
    np.testing.assert_allclose(np.cross(np.asarray(foot) - p, u), 0.0, atol=1e-9)
    assert abs(np.dot(x_ref - np.asarray(foot), u)) < 1e-9
    np.testing.assert_allclose(direction, u)
    # laser 1's tangent columns move laser 1 alone, as at_working_point's own increment does
    from slcvjax.observations.simulate import paper_rig

    rig = paper_rig(n)
    delta = np.zeros(rig.tangent_dim)
    step = np.array([0.3, -0.2, 0.01, 0.02])
    delta[rig.layout.elements[1]] = step
    moved = rig.retract(jnp.asarray(delta))
    np.testing.assert_array_equal(np.asarray(moved.lasers.points)[[0, 2]], np.asarray(rig.lasers.points)[[0, 2]])
    np.testing.assert_array_equal(np.asarray(moved.camera.K), np.asarray(rig.camera.K))
    f1, d1 = moved.lasers.at_working_point(1, x_ref)
    f2, d2 = rig.lasers.at_working_point(1, x_ref, step)
    np.testing.assert_allclose(f1, f2, atol=1e-12)
    np.testing.assert_allclose(d1, d2, atol=1e-15)


def test_the_tangent_layout_comes_from_the_elements():
    from slcvjax.calibration.params import element_columns
    from slcvjax.geometry.rig import tangent_layout
    from slcvjax.observations.simulate import paper_rig

    rig = paper_rig(5)
    lay = rig.layout
    assert lay.camera == slice(0, 9) and lay.mirror == slice(9, 15)
    assert lay.elements == tuple(slice(15 + 4 * i, 19 + 4 * i) for i in range(5)) and lay.dim == rig.tangent_dim == 35
    # elements of other sizes (a plane of light 3, a cone of light 6) sit one after the other
    mixed = tangent_layout((4, 3, 6))
    assert mixed.elements == (slice(15, 19), slice(19, 22), slice(22, 28)) and mixed.dim == 28
    np.testing.assert_array_equal(mixed.element_dofs, [4, 3, 6])
    # the rows' columns, from traced element indices: each element's own, the spare column past them
    cols = np.asarray(jax.jit(lambda e: element_columns(rig, e, 6, 99))(jnp.asarray([0, 4, 2])))
    np.testing.assert_array_equal(cols[:, :4], [[15, 16, 17, 18], [31, 32, 33, 34], [23, 24, 25, 26]])
    assert np.all(cols[:, 4:] == 99)
