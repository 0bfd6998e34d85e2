import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import slcvjax as sj
from slcvjax.support.safe import orthonormal_basis

from ._helpers import back_project_many, central_diff, project_many, random_camera, random_mirror
from ._reference import RefRig

solve_many = jax.jit(jax.vmap(sj.solve_mirror_point, in_axes=(None, 0)))
_back_project_one = jax.jit(sj.back_project)
_project_one = jax.jit(sj.project_through_mirror)


def _cone_point(mirror, s, theta):
    e1, e2 = (np.asarray(e) for e in orthonormal_basis(mirror.axis))
    a = np.asarray(mirror.axis)
    u = np.cos(theta)[:, None] * e1 + np.sin(theta)[:, None] * e2
    return np.asarray(mirror.apex) + s[:, None] * a + float(mirror.k) * s[:, None] * u


def _visible_pixels(cam, mirror, s_frac, theta):
    """Pixels of mirror points at axial fractions s_frac and azimuths theta (those seen by the camera)."""
    m = _cone_point(mirror, s_frac * float(mirror.height), theta)
    uv, ok = sj.project_points(cam, m)
    ok = np.asarray(ok) & np.array([bool(sj.in_image(cam, p)) for p in uv])
    return np.asarray(uv), ok, m


def test_intersect_closed_form_on_axis():
    # on-axis cone, apex at (0, 0, D): a ray at angle beta meets rho = k (z - D) at t = k D / (k cos b - sin b)
    k, D = 2.0, 50.0
    mirror = sj.ConeMirror.create([0, 0, D], [0, 0, 1], 20.0, 10.0)
    for beta in [0.01, 0.1, 0.3]:
        d = jnp.array([np.sin(beta), 0.0, np.cos(beta)])
        hit = sj.intersect(mirror, jnp.zeros(3), d)
        assert bool(hit.valid)
        assert float(hit.t) == pytest.approx(k * D / (k * np.cos(beta) - np.sin(beta)), rel=1e-13)


def test_intersect_misses_and_degenerate_rays():
    mirror = sj.ConeMirror.create([0, 0, 50.0], [0, 0, 1], 20.0, 10.0)
    o = jnp.zeros(3)
    cases = [
        jnp.array([0.6, 0.0, 1.0]),  # passes outside the rim
        jnp.array([0.0, 0.0, -1.0]),  # points away
        jnp.array([1.0, 0.0, 0.0]),  # perpendicular, never reaches the cone
    ]
    for d in cases:
        hit = sj.intersect(mirror, o, d / jnp.linalg.norm(d))
        assert not bool(hit.valid)
        assert np.all(np.isfinite(np.asarray(hit.point)))
    # a ray parallel to a generatrix (the quadratic's leading term vanishes) from the apex's far side
    k = 2.0
    d = jnp.array([k, 0.0, 1.0]) / np.sqrt(1 + k * k)
    hit = sj.intersect(mirror, jnp.array([-5.0, 0.0, 40.0]), d)
    assert np.all(np.isfinite(np.asarray(hit.point)))
    g = jax.grad(lambda d: sj.intersect(mirror, jnp.array([-5.0, 0.0, 40.0]), d).point.sum())(d)
    assert np.all(np.isfinite(np.asarray(g)))


@pytest.mark.parametrize("beta_deg", [0.5, 5.0, 10.0, 18.0])
def test_reflected_elevation_closed_form(beta_deg):
    # in the axial plane, a ray at beta from the axis reflects off a cone of slope k to the elevation
    # 2 atan(1/k) - 90 deg + beta (mirror image across the generatrix)
    k = 2.0
    mirror = sj.ConeMirror.create([0, 0, 50.0], [0, 0, 1], 20.0, 10.0)
    cam = sj.Camera.create(500, 500, 320, 240, np.zeros(5), 640, 480)
    b = np.radians(beta_deg)
    uv = jnp.array([320 + 500 * np.tan(b), 240.0])
    ray = sj.back_project(cam, mirror, uv)
    assert bool(ray.valid)
    elev = np.degrees(np.arctan2(float(ray.direction[2]), float(ray.direction[0])))
    assert elev == pytest.approx(2 * np.degrees(np.arctan(1 / k)) - 90 + beta_deg, abs=1e-8)


@given(st.integers(0, 2**31 - 1), st.sampled_from(["mid", "apex", "rim", "near", "far"]))
@pytest.mark.slow
def test_pixel_ray_point_pixel_roundtrip(seed, case):
    rng = np.random.default_rng(seed)
    cam, mirror = random_camera(rng), random_mirror(rng)
    n = 64
    s_frac = {
        "mid": rng.uniform(0.05, 0.95, n),
        "apex": rng.uniform(1e-3, 1e-2, n),
        "rim": 1 - rng.uniform(1e-6, 1e-3, n),
    }.get(case, rng.uniform(0.02, 0.98, n))
    uv, ok, _ = _visible_pixels(cam, mirror, s_frac, rng.uniform(-np.pi, np.pi, n))
    ray = back_project_many(cam, mirror, jnp.asarray(uv))
    keep = ok & np.asarray(ray.valid)
    assert keep.sum() >= n // 2
    depth = {"near": rng.uniform(1e-2, 1.0, n), "far": rng.uniform(1e3, 1e4, n)}.get(case, rng.uniform(5, 500, n))
    p = np.asarray(ray.point) + depth[:, None] * np.asarray(ray.direction)
    res = project_many(cam, mirror, jnp.asarray(p))  # every point (one shape, one compilation), the kept ones checked
    assert bool(np.all(np.asarray(res.valid)[keep]))
    np.testing.assert_allclose(np.asarray(res.uv)[keep], uv[keep], atol=1e-8, rtol=0)


@given(st.integers(0, 2**31 - 1))
@pytest.mark.slow
def test_law_of_reflection_at_the_solved_point(seed):
    rng = np.random.default_rng(seed)
    cam, mirror = random_camera(rng), random_mirror(rng)
    uv, ok, _ = _visible_pixels(cam, mirror, rng.uniform(0.01, 0.99, 40), rng.uniform(-np.pi, np.pi, 40))
    ray = back_project_many(cam, mirror, jnp.asarray(uv))
    p = np.asarray(ray.point) + rng.uniform(10, 400, 40)[:, None] * np.asarray(ray.direction)
    m, valid = solve_many(mirror, jnp.asarray(p))
    m, valid = np.asarray(m), np.asarray(valid)
    keep = ok & np.asarray(ray.valid)
    assert np.all(valid[keep])
    for mi, pi in zip(m[keep], p[keep], strict=True):
        n = np.asarray(sj.surface_normal(mirror, jnp.asarray(mi)))
        d_in = mi / np.linalg.norm(mi)
        d_out = (pi - mi) / np.linalg.norm(pi - mi)
        np.testing.assert_allclose(d_in - 2 * (d_in @ n) * n, d_out, atol=1e-10)
        # and the point is on the cone
        q = mi - np.asarray(mirror.apex)
        s = q @ np.asarray(mirror.axis)
        assert abs(np.linalg.norm(q - s * np.asarray(mirror.axis)) - float(mirror.k) * s) < 1e-10


def test_agrees_with_independent_implementation():
    rng = np.random.default_rng(5)
    for _ in range(3):
        cam, mirror = random_camera(rng), random_mirror(rng)
        ref = RefRig.from_package(cam, mirror)
        uv, ok, _ = _visible_pixels(cam, mirror, rng.uniform(0.05, 0.95, 12), rng.uniform(-np.pi, np.pi, 12))
        for pix in uv[ok]:
            bp = ref.back_project(pix)
            assert bp is not None
            mine = _back_project_one(cam, mirror, jnp.asarray(pix))
            np.testing.assert_allclose(np.asarray(mine.point), bp[0], atol=1e-9)
            np.testing.assert_allclose(np.asarray(mine.direction), bp[1], atol=1e-11)
            p = bp[0] + rng.uniform(20, 300) * bp[1]
            # the reference starts from a pixel 3 px away and solves on its own
            ref_uv, resid = ref.project_through_mirror(p, pix + rng.normal(0, 3, 2))
            assert resid < 1e-9
            res = _project_one(cam, mirror, jnp.asarray(p))
            assert bool(res.valid)
            np.testing.assert_allclose(np.asarray(res.uv), ref_uv, atol=1e-7)


def _setup_for_gradients():
    rng = np.random.default_rng(42)
    cam, mirror = random_camera(rng), random_mirror(rng)
    uv, ok, _ = _visible_pixels(cam, mirror, np.array([0.4, 0.7]), np.array([0.3, 2.5]))
    ray = sj.back_project(cam, mirror, jnp.asarray(uv[0]))
    p = ray.point + 120.0 * ray.direction
    return cam, mirror, p


@pytest.mark.parametrize("wrt", ["point", "mirror", "camera"])
@pytest.mark.slow
def test_projection_jacobians_fwd_rev_fd(wrt):
    cam, mirror, p = _setup_for_gradients()
    if wrt == "point":
        f, x = (lambda x: sj.project_through_mirror(cam, mirror, x).uv), p
    elif wrt == "mirror":
        f, x = (lambda d: sj.project_through_mirror(cam, mirror.retract(d), p).uv), jnp.zeros(5)
    else:
        f, x = (lambda c: sj.project_through_mirror(cam.with_params(c), mirror, p).uv), cam.params()
    f = jax.jit(f)
    jf = np.asarray(jax.jit(jax.jacfwd(f))(x))
    jr = np.asarray(jax.jit(jax.jacrev(f))(x))
    fd = central_diff(f, np.asarray(x), eps=1e-6)
    np.testing.assert_allclose(jf, jr, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(jf, fd, rtol=2e-6, atol=2e-5)


@pytest.mark.slow
def test_implicit_derivative_equals_unrolled_derivative():
    cam, mirror, p = _setup_for_gradients()

    def f(d, implicit):
        return sj.project_through_mirror(cam, mirror.retract(d[:5]), p + d[5:], implicit=implicit).uv

    x = jnp.zeros(8)
    j_implicit = jax.jit(jax.jacfwd(lambda d: f(d, True)))
    j_unrolled = jax.jit(jax.jacfwd(lambda d: f(d, False)))
    np.testing.assert_allclose(j_implicit(x), j_unrolled(x), rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize(
    "p",
    [
        [0.0, 0.0, 0.0],  # the camera centre
        [0.0, 0.0, 200.0],  # on the axis behind the mirror
        [0.5, -0.2, 55.0],  # inside the cone
        [0.0, 0.0, -300.0],  # behind the camera on the axis
        [3000.0, 0.0, 4000.0],  # outside the field: reflected rays never go up there
        [0.6, -0.4, 48.0],  # at the apex
    ],
)
@pytest.mark.slow
def test_invisible_points_are_masked_with_finite_values_and_gradients(p):
    mirror = sj.ConeMirror.create([0.6, -0.4, 48.0], [0.02, -0.015, 1.0], 20.0, 10.0)
    cam = sj.Camera.create(551.757, 551.95, 322.826, 205.202, [-0.28, 0.09, 0.0012, -0.0008, -0.01], 640, 480)
    x = jnp.asarray(p, dtype=float)
    res = sj.project_through_mirror(cam, mirror, x)
    assert not bool(res.valid)
    assert np.all(np.isfinite(np.asarray(res.uv)))

    def loss(x, d, c):
        r = sj.project_through_mirror(cam.with_params(c), mirror.retract(d), x)
        return jnp.sum(jnp.where(r.valid, r.uv, 0.0) ** 2)

    grads = _masked_loss_grad(loss)(x, jnp.zeros(5), cam.params())
    for g in grads:
        assert np.all(np.isfinite(np.asarray(g)))


def _masked_loss_grad(loss):
    return jax.jit(jax.grad(loss, argnums=(0, 1, 2)))


def test_rim_points_lie_on_the_base_circle():
    rng = np.random.default_rng(3)
    mirror = random_mirror(rng)
    pts = np.asarray(mirror.rim_points(jnp.linspace(0, 2 * np.pi, 7)))
    q = pts - np.asarray(mirror.apex)
    s = q @ np.asarray(mirror.axis)
    np.testing.assert_allclose(s, float(mirror.height), atol=1e-12)
    np.testing.assert_allclose(
        np.linalg.norm(q - s[:, None] * np.asarray(mirror.axis), axis=1), float(mirror.radius), atol=1e-12
    )


def test_mirror_retract_keeps_a_unit_axis_and_moves_5_dof():
    mirror = sj.ConeMirror.create([0.6, -0.4, 48.0], [0.02, -0.015, 1.0], 20.0, 10.0)
    j = np.asarray(
        jax.jacfwd(lambda d: jnp.concatenate([mirror.retract(d).apex, mirror.retract(d).axis]))(jnp.zeros(5))
    )
    assert np.linalg.matrix_rank(j, tol=1e-9) == 5
    m2 = mirror.retract(jnp.array([0.1, 0.2, 0.3, 0.05, -0.02]))
    assert float(jnp.linalg.norm(m2.axis)) == pytest.approx(1.0, abs=1e-15)


@pytest.mark.slow
def test_apex_margin_continues_the_projection_smoothly_through_the_apex():
    from slcvjax.observations.simulate import paper_rig

    rig = paper_rig(1)
    cam, mirror = rig.camera, rig.mirror
    # a wall point seen a hair off the apex: back-project a pixel next to the apex's image
    apex_px, _ = sj.project(cam, mirror.apex)
    ray = _back_project_one(cam, mirror, apex_px + jnp.array([2.0, 0.0]))
    assert bool(ray.valid)
    target = ray.point + 200.0 * ray.direction
    a = mirror.axis
    side = orthonormal_basis(a)[1]  # moving the apex this way moves the reflection across it

    def pixel(shift, margin):
        m = sj.ConeMirror(mirror.apex + shift * side, a, mirror.radius, mirror.height)
        res = sj.project_through_mirror(cam, m, target, apex_margin=margin)
        return res.uv, res.valid, jnp.dot(res.mirror_point - m.apex, a)

    shifts = np.linspace(-0.5, 0.2, 36)
    with_margin = jax.jit(jax.vmap(lambda d: pixel(d, 0.05)))
    uv, ok, s = (np.asarray(x) for x in with_margin(jnp.asarray(shifts)))
    _, ok0, _ = (np.asarray(x) for x in jax.jit(jax.vmap(lambda d: pixel(d, 0.0)))(jnp.asarray(shifts)))
    assert s.min() < 0 < s.max()
    assert ok.all()  # with the margin every shift keeps its pixel
    assert not ok0[s < 0].any() and ok0[s > 1e-6].all()  # without it the far side is lost
    # smooth: the pixel's second differences are tiny against its first differences
    d1, d2 = np.diff(uv, axis=0), np.diff(uv, n=2, axis=0)
    assert np.abs(d2).max() < 0.05 * np.abs(d1).max()
    # and the implicit derivative at the apex crossing matches central differences
    k = int(np.argmin(np.abs(s)))
    jac = np.asarray(jax.jit(jax.jacfwd(lambda d: pixel(d, 0.05)[0]))(shifts[k]))
    h = 1e-6
    uv_pm = np.asarray(with_margin(jnp.asarray([shifts[k] + h, shifts[k] - h]))[0])
    fd = (uv_pm[0] - uv_pm[1]) / (2 * h)
    np.testing.assert_allclose(jac, fd, rtol=1e-5, atol=1e-6)
