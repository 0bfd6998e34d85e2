"""Conic mirrors of revolution against closed forms: the foci of the hyperboloid and the
paraboloid, the sphere's centre, projection and back-projection as inverses, and the implicit
derivative against finite differences."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slcvjax.geometry.camera import project
from slcvjax.geometry.conic import ConicMirror
from slcvjax.geometry.mirror import back_project, intersect, project_through_mirror, reflect, surface_normal
from slcvjax.observations.simulate import paper_camera

from ._helpers import back_project_many, project_many

# (kind, vertex radius R, conic constant) with a rim of 25 mm
SHAPES = [("sphere", 40.0, None), ("paraboloid", 30.0, None), ("hyperboloid", 20.0, -2.5), ("ellipsoid", 40.0, -0.5)]
SHAPES += [("ellipsoid", 40.0, 0.5)]


def _mirror(kind, R, conic, apex=(0.0, 0.0, 60.0), axis=(0.0, 0.0, 1.0)):
    return ConicMirror.of_kind(kind, apex, axis, R, 25.0, conic)


def _line_distance(point, direction, x):
    d = direction / np.linalg.norm(direction)
    v = x - point
    return np.linalg.norm(v - (v @ d) * d)


def _surface_samples(mirror, n, rng, max_frac=0.95):
    """Surface points of ``mirror`` inside the rim (host)."""
    from slcvjax.support.safe import orthonormal_basis

    e1, e2 = (np.asarray(e) for e in orthonormal_basis(mirror.axis))
    rho = float(mirror.radius) * max_frac * np.sqrt(rng.uniform(0, 1, n))
    th = rng.uniform(0, 2 * np.pi, n)
    s = np.asarray(mirror.sag(jnp.asarray(rho**2)))
    return (
        np.asarray(mirror.apex)
        + rho[:, None] * (np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2)
        + s[:, None] * np.asarray(mirror.axis)
    )


def test_hyperboloid_with_the_camera_at_its_far_focus_is_central(rng):
    """Every ray the camera (at the far focus) sees reflects along a line through the near focus."""
    R, kappa = 20.0, -2.5
    e = np.sqrt(-kappa)
    far = R / (e - 1.0)  # the far focus, on the camera's side of the vertex
    mirror = ConicMirror.of_kind("hyperboloid", (0.0, 0.0, far), (0.0, 0.0, 1.0), R, 25.0, kappa)
    near = np.array([0.0, 0.0, far + R / (1.0 + e)])
    for m in _surface_samples(mirror, 40, rng):
        d = m / np.linalg.norm(m)
        hit = intersect(mirror, jnp.zeros(3), jnp.asarray(d))
        assert bool(hit.valid)
        np.testing.assert_allclose(np.asarray(hit.point), m, atol=1e-9)
        r = np.asarray(reflect(jnp.asarray(d), surface_normal(mirror, hit.point)))
        assert _line_distance(m, r, near) < 1e-9


def test_paraboloid_reflects_rays_along_its_axis_through_its_focus(rng):
    R = 30.0
    mirror = ConicMirror.of_kind("paraboloid", (0.0, 0.0, 60.0), (0.0, 0.0, 1.0), R, 25.0)
    focus = np.array([0.0, 0.0, 60.0 + R / 2])
    for m in _surface_samples(mirror, 30, rng):
        origin = np.array([m[0], m[1], 0.0])
        hit = intersect(mirror, jnp.asarray(origin), jnp.array([0.0, 0.0, 1.0]))
        assert bool(hit.valid)
        np.testing.assert_allclose(np.asarray(hit.point), m, atol=1e-9)
        r = np.asarray(reflect(jnp.array([0.0, 0.0, 1.0]), surface_normal(mirror, hit.point)))
        assert _line_distance(m, r, focus) < 1e-9
    # the ray along the axis itself meets the vertex (the quadratic is linear there)
    hit = intersect(mirror, jnp.zeros(3), jnp.array([0.0, 0.0, 1.0]))
    assert bool(hit.valid)
    np.testing.assert_allclose(np.asarray(hit.point), [0.0, 0.0, 60.0], atol=1e-12)


def test_sphere_normal_points_from_its_centre(rng):
    mirror = _mirror("sphere", 40.0, None)
    centre = np.array([0.0, 0.0, 100.0])
    for m in _surface_samples(mirror, 20, rng):
        np.testing.assert_allclose(np.linalg.norm(m - centre), 40.0, rtol=1e-12)
        n = np.asarray(surface_normal(mirror, jnp.asarray(m)))
        np.testing.assert_allclose(n, (m - centre) / 40.0, atol=1e-12)


@pytest.mark.parametrize(("kind", "R", "conic"), SHAPES)
def test_projection_inverts_back_projection(kind, R, conic, rng):
    """A pixel back-projected, a point taken along its reflected ray, projected again: the same
    pixel; with the mirror off the camera's axis and tilted (a non-central camera)."""
    cam = paper_camera()
    mirror = _mirror(kind, R, conic, apex=(3.0, -2.0, 60.0), axis=(0.03, -0.02, 1.0))
    uv = np.stack([np.asarray(project(cam, jnp.asarray(m))[0]) for m in _surface_samples(mirror, 12, rng)])
    rays = back_project_many(cam, mirror, jnp.asarray(uv))
    assert np.all(np.asarray(rays.valid))
    for dist in (80.0, 400.0):
        res = project_many(cam, mirror, rays.point + dist * rays.direction)
        assert np.all(np.asarray(res.valid))
        np.testing.assert_allclose(np.asarray(res.uv), uv, atol=1e-6)
        np.testing.assert_allclose(np.asarray(res.mirror_point), np.asarray(rays.point), atol=1e-6)


def _uv_moved(x, cam, mirror, p):
    """The pixel of ``p + x[:3]`` through the mirror moved by ``x[3:]`` (its pose's 5 tangents)."""
    return project_through_mirror(cam, mirror.retract(x[3:]), p + x[:3]).uv


# the camera, mirror and point as arguments: one compilation serves every conic mirror
_uv_jacobian = jax.jit(jax.jacfwd(_uv_moved))
_uv_many = jax.jit(jax.vmap(_uv_moved, in_axes=(0, None, None, None)))


@pytest.mark.parametrize(("kind", "R", "conic"), SHAPES[:4])
@pytest.mark.slow
def test_implicit_derivative_matches_finite_differences(kind, R, conic, rng):
    cam = paper_camera()
    mirror = _mirror(kind, R, conic, apex=(2.0, 1.0, 60.0), axis=(-0.02, 0.01, 1.0))
    m = _surface_samples(mirror, 1, rng)[0]
    ray = back_project(cam, mirror, project(cam, jnp.asarray(m))[0])
    p = np.asarray(ray.point) + 150.0 * np.asarray(ray.direction)

    J = np.asarray(_uv_jacobian(jnp.zeros(8), cam, mirror, jnp.asarray(p)))
    h = 1e-5
    uv_pm = np.asarray(_uv_many(jnp.concatenate([h * jnp.eye(8), -h * jnp.eye(8)]), cam, mirror, jnp.asarray(p)))
    fd = ((uv_pm[:8] - uv_pm[8:]) / (2 * h)).T
    np.testing.assert_allclose(J, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())


@pytest.mark.slow
def test_second_derivatives_of_the_mirror_point_match_finite_differences(rng):
    """A hyperboloid's reflection point's Hessian in the scene point (what the implicit
    derivative of a calibration and the design's gradient differentiate) against central
    differences of its exact first derivative, forward over reverse and reverse over reverse."""
    kind, R, conic = SHAPES[2]
    from slcvjax.geometry.mirror import solve_mirror_point

    cam = paper_camera()
    mirror = _mirror(kind, R, conic, apex=(2.0, 1.0, 60.0), axis=(-0.02, 0.01, 1.0))
    m = _surface_samples(mirror, 1, rng)[0]
    ray = back_project(cam, mirror, project(cam, jnp.asarray(m))[0])
    p = jnp.asarray(np.asarray(ray.point) + 150.0 * np.asarray(ray.direction))

    def point(q):
        return solve_mirror_point(mirror, q)[0]

    jac = jax.jit(jax.jacfwd(point))
    h = 1e-3
    fd = np.stack([(jac(p.at[i].add(h)) - jac(p.at[i].add(-h))) / (2 * h) for i in range(3)], axis=-1)
    scale = np.abs(fd).max()
    assert scale > 1e-6
    for hess in (jax.jacfwd(jax.jacrev(point)), jax.jacrev(jax.jacrev(point))):
        np.testing.assert_allclose(np.asarray(jax.jit(hess)(p)), fd, atol=1e-5 * scale)


def test_points_off_the_mirror_are_invalid():
    cam = paper_camera()
    mirror = _mirror("hyperboloid", 20.0, -2.5)
    # behind the mirror's surface (inside its body), on its axis and off it
    res = project_many(cam, mirror, jnp.asarray([[0.0, 0.0, 200.0], [5.0, 0.0, 90.0]]))
    assert not np.any(np.asarray(res.valid))


def test_of_kind_checks_the_shape():
    with pytest.raises(ValueError, match="below -1"):
        ConicMirror.of_kind("hyperboloid", (0, 0, 50), (0, 0, 1), 20.0, 25.0, -0.5)
    with pytest.raises(ValueError, match="needs its conic constant"):
        ConicMirror.of_kind("ellipsoid", (0, 0, 50), (0, 0, 1), 20.0, 25.0)
    with pytest.raises(ValueError, match="widest circle"):
        ConicMirror.of_kind("sphere", (0, 0, 50), (0, 0, 1), 20.0, 25.0)
    with pytest.raises(ValueError, match="unknown mirror kind"):
        ConicMirror.of_kind("torus", (0, 0, 50), (0, 0, 1), 20.0, 25.0)
    assert ConicMirror.of_kind("paraboloid", (0, 0, 50), (0, 0, 1), 20.0, 25.0).kind == "paraboloid"


def _conic_rig(kind="paraboloid", R=20.0, conic=None, n_lasers=5):
    from slcvjax.geometry.rig import Rig
    from slcvjax.observations.simulate import paper_rig

    base = paper_rig(n_lasers)
    mirror = ConicMirror.of_kind(kind, [0.5, -0.3, 40.0], [0.015, -0.01, 1.0], R, 20.0, conic)
    return Rig(base.camera, mirror, base.lasers)


@pytest.mark.slow
def test_conic_shapes_round_trip_through_the_files(tmp_path):
    from slcvjax.observations.formats import (
        Calibration,
        FormatError,
        read_calibration,
        read_observations,
        write_calibration,
        write_observations,
    )
    from slcvjax.observations.simulate import box_scene, paper_views, simulate

    rig = _conic_rig("hyperboloid", 15.0, -2.0)
    obs, truth = simulate(box_scene(rig, paper_views(3), n_chess_views=3), noise=0.0)
    write_observations(tmp_path / "obs.json", obs)
    back = read_observations(tmp_path / "obs.json")
    assert back.mirror_shape == {"kind": "hyperboloid", "vertex_radius": 15.0, "radius": 20.0, "conic_constant": -2.0}
    np.testing.assert_allclose(back.mirror_height, float(rig.mirror.height), rtol=1e-12)
    write_calibration(tmp_path / "cal.json", Calibration(rig, truth.board_poses))
    mir = read_calibration(tmp_path / "cal.json").rig.mirror
    assert isinstance(mir, ConicMirror) and mir.kind == "hyperboloid"
    for f in ("apex", "axis", "curvature", "conic", "radius"):
        np.testing.assert_allclose(np.asarray(getattr(mir, f)), np.asarray(getattr(rig.mirror, f)), rtol=1e-12)

    doc = json.loads((tmp_path / "obs.json").read_text())
    doc["mirror_shape"]["conic_constant"] = -0.5
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    with pytest.raises(FormatError, match=r"mirror_shape: a hyperboloid's conic constant is below -1"):
        read_observations(tmp_path / "bad.json")
    doc["mirror_shape"] = {"kind": "torus", "radius": 20.0}
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    with pytest.raises(FormatError, match=r"mirror_shape.kind: unknown mirror kind 'torus'"):
        read_observations(tmp_path / "bad.json")


@pytest.mark.slow
def test_a_paraboloid_rig_calibrates_near_its_bound():
    """The whole pipeline (rim, PnP through the mirror, the joint passes) with a paraboloid."""
    from slcvjax.calibration.bound import cramer_rao, laser_errors
    from slcvjax.calibration.calibrate import calibrate
    from slcvjax.observations.simulate import box_scene, paper_views, simulate

    scene = box_scene(_conic_rig(), paper_views(10), n_chess_views=6)
    obs, truth = simulate(scene, noise=0.3, seed=5)
    res = calibrate(obs)
    assert res.passes[-1].converged
    bound = cramer_rao(truth, obs, 0.3)
    pos, ang = laser_errors(res.rig, truth.rig, bound["x_ref"])
    assert np.sqrt(np.mean(pos**2)) < 3 * bound["position_rms_mm"]
    assert np.sqrt(np.mean(ang**2)) < 3 * bound["direction_rms_rad"]
    sd = np.sqrt(np.diag(np.asarray(res.cov.glob)))[9:12]
    err = np.asarray(res.rig.mirror.apex) - np.asarray(truth.rig.mirror.apex)
    assert np.all(np.abs(err) < 4 * sd), (err, sd)


def test_rendering_refuses_a_conic_mirror(tmp_path):
    from slcvjax.images.render import render_scene
    from slcvjax.observations.simulate import box_scene, paper_views

    with pytest.raises(ValueError, match="cone mirror only"):
        render_scene(box_scene(_conic_rig(), paper_views(2), n_chess_views=1), tmp_path)


@pytest.mark.slow
def test_a_catadioptric_camera_without_lasers_calibrates_from_the_cli(tmp_path, capsys):
    """A hyperboloid rig with no lasers (``n_lasers: 0``): the file read, the rig calibrated,
    the calibration written with no lasers and its mirror within its reported std."""
    from slcvjax import cli
    from slcvjax.geometry.lasers import Lasers
    from slcvjax.observations.formats import write_observations
    from slcvjax.observations.simulate import box_scene, paper_views, simulate

    rig = _conic_rig("hyperboloid", 15.0, -2.0)
    rig = rig.with_lasers(Lasers.create(np.zeros((0, 3)), np.zeros((0, 3))))
    obs, truth = simulate(box_scene(rig, paper_views(8), n_chess_views=6), noise=0.3, seed=4)
    write_observations(tmp_path / "obs.json", obs)
    assert cli.main(["calibrate", str(tmp_path / "obs.json"), "--out", str(tmp_path / "cal.json")]) == 0
    doc = json.loads((tmp_path / "cal.json").read_text())
    assert doc["lasers"] == [] and doc["mirror"]["kind"] == "hyperboloid"
    apex = np.asarray(doc["mirror"]["apex"])
    sd = np.asarray(doc["uncertainty"]["mirror_std"]["apex_mm"])
    assert np.all(np.abs(apex - np.asarray(truth.rig.mirror.apex)) < 4 * sd)
    assert "laser" not in capsys.readouterr().err
