import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import slcvjax as sj

from ._helpers import central_diff, random_camera

project_many = jax.jit(jax.vmap(sj.project, in_axes=(None, 0)))
undistort_many = jax.jit(jax.vmap(sj.undistort, in_axes=(None, 0)))


def _cv_dist(cam):
    return np.asarray(cam.dist, float)


@given(st.integers(0, 2**31 - 1))
def test_project_agrees_with_opencv(seed):
    rng = np.random.default_rng(seed)
    cam = random_camera(rng)
    pts = np.stack([rng.uniform(-300, 300, 50), rng.uniform(-250, 250, 50), rng.uniform(200, 900, 50)], 1)
    uv, valid = project_many(cam, jnp.asarray(pts))
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), np.asarray(cam.K), _cv_dist(cam))
    assert bool(np.all(valid))
    np.testing.assert_allclose(np.asarray(uv), ref.reshape(-1, 2), atol=1e-9, rtol=0)


@given(st.integers(0, 2**31 - 1))
def test_undistort_agrees_with_opencv_iterative(seed):
    rng = np.random.default_rng(seed)
    cam = random_camera(rng)
    uv = np.stack([rng.uniform(0, 639, 60), rng.uniform(0, 479, 60)], 1)
    xy, valid = undistort_many(cam, jnp.asarray(uv))
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    ref = cv2.undistortPoints(uv.reshape(-1, 1, 2), np.asarray(cam.K), _cv_dist(cam), None, None, None, crit)
    assert bool(np.all(valid))
    np.testing.assert_allclose(np.asarray(xy), ref.reshape(-1, 2), atol=1e-9)
    # and exactly inverts the projection
    back = jax.vmap(sj.project_normalized, in_axes=(None, 0))(cam, xy)
    np.testing.assert_allclose(np.asarray(back), uv, atol=1e-9)


def test_pixel_to_ray_points_through_pixel(rng):
    cam = random_camera(rng)
    uv = jnp.array([100.3, 400.7])
    d, ok = sj.pixel_to_ray(cam, uv)
    assert bool(ok)
    assert float(jnp.linalg.norm(d)) == pytest.approx(1.0)
    back, _ = sj.project(cam, 250.0 * d)
    np.testing.assert_allclose(np.asarray(back), np.asarray(uv), atol=1e-9)


def test_project_jacobians_agree(rng):
    cam = random_camera(rng)
    p = jnp.array([40.0, -25.0, 300.0])

    def f_params(params):
        return sj.project(cam.with_params(params), p)[0]

    def f_point(x):
        return sj.project(cam, x)[0]

    for f, x in [(f_params, cam.params()), (f_point, p)]:
        f = jax.jit(f)
        jf = np.asarray(jax.jacfwd(f)(x))
        jr = np.asarray(jax.jacrev(f)(x))
        fd = central_diff(f, np.asarray(x), eps=1e-5)
        np.testing.assert_allclose(jf, jr, atol=1e-10)
        np.testing.assert_allclose(jf, fd, rtol=1e-6, atol=1e-6)


def test_undistort_implicit_jacobian_matches_finite_differences(rng):
    cam = random_camera(rng)
    uv = jnp.array([500.0, 60.0])

    def f(params):
        return sj.undistort(cam.with_params(params), uv)[0]

    f = jax.jit(f)
    jf = np.asarray(jax.jacfwd(f)(cam.params()))
    jr = np.asarray(jax.jacrev(f)(cam.params()))
    fd = central_diff(f, np.asarray(cam.params()), eps=1e-6)
    np.testing.assert_allclose(jf, jr, atol=1e-12)
    np.testing.assert_allclose(jf, fd, rtol=1e-5, atol=1e-8)


def test_point_behind_camera_is_masked_without_nan(rng):
    cam = random_camera(rng)
    for p in [jnp.array([1.0, 2.0, -5.0]), jnp.zeros(3)]:
        uv, ok = sj.project(cam, p)
        assert not bool(ok)
        assert np.all(np.isfinite(np.asarray(uv)))
        g = jax.jacrev(lambda x: sj.project(cam, x)[0])(p)
        assert np.all(np.isfinite(np.asarray(g)))


def test_pixel_beyond_the_fold_of_the_distortion_is_flagged():
    # k1 = -0.6 alone: x (1 - 0.6 x^2) peaks at x = 1/sqrt(1.8), value 0.497; a pixel whose
    # normalised distorted radius exceeds that has no preimage.
    cam = sj.Camera.create(500, 500, 320, 240, [-0.6, 0, 0, 0, 0], 640, 480)
    xy, ok = sj.undistort(cam, jnp.array([320.0 + 0.55 * 500, 240.0]))
    assert not bool(ok)
    assert np.all(np.isfinite(np.asarray(xy)))
    xy, ok = sj.undistort(cam, jnp.array([320.0 + 0.3 * 500, 240.0]))
    assert bool(ok)


def test_in_image_bounds():
    cam = sj.Camera.create(500, 500, 320, 240, np.zeros(5), 640, 480)
    inside = [(-0.5, -0.5), (639.49, 479.49), (320.0, 240.0)]
    outside = [(-0.51, 10.0), (639.5, 10.0), (10.0, 479.5), (np.nan, 3.0)]
    assert all(bool(sj.in_image(cam, jnp.asarray(p))) for p in inside)
    assert not any(bool(sj.in_image(cam, jnp.asarray(p))) for p in outside)


def test_bad_image_size_is_rejected():
    with pytest.raises(ValueError, match="image size"):
        sj.Camera.create(500, 500, 320, 240, np.zeros(5), 0, 480)
