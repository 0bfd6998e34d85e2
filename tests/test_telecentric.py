"""A telecentric (orthographic) camera before a mirror: closed forms of its geometry, its files,
and a calibration through the mirror alone against the simulator's truth."""

import dataclasses

import jax
import numpy as np
import pytest

from slcvjax.geometry.camera import Camera, pixel_to_line, project
from slcvjax.geometry.conic import ConicMirror
from slcvjax.geometry.lasers import Lasers
from slcvjax.geometry.mirror import ConeMirror, back_project, project_through_mirror
from slcvjax.geometry.rig import Rig
from slcvjax.observations.simulate import box_scene, paper_views, simulate

from ._helpers import back_project_many, project_many

_NO_LASERS = Lasers.create(np.zeros((0, 3)), np.zeros((0, 3)))
W, H = 800, 700


def _camera(dist=(0.0, 0.0, 0.0, 0.0, 0.0), unit=20.0, f=18.0):
    """``f`` px per mm (``fx = f * unit``)."""
    return Camera.create(f * unit, 1.01 * f * unit, 402.0, 347.0, dist, W, H, telecentric=True, unit=unit)


def test_a_telecentric_pixel_sees_a_line_along_z():
    """The pixel of ``(X, Y, Z)`` is ``K (distort((X, Y) / L), 1)`` at every depth, and its line
    runs from ``(X, Y, 0)`` along +z."""
    cam = _camera(dist=(-0.1, 0.02, 0.001, -0.002, 0.0))
    p = np.array([3.0, -7.0, 55.0])
    uv, ok = project(cam, p)
    xy = p[:2] / cam.unit
    r2 = xy @ xy
    k1, k2, p1, p2, k3 = np.asarray(cam.dist)
    rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = xy[0] * rad + 2 * p1 * xy[0] * xy[1] + p2 * (r2 + 2 * xy[0] ** 2)
    yd = xy[1] * rad + p1 * (r2 + 2 * xy[1] ** 2) + 2 * p2 * xy[0] * xy[1]
    assert bool(ok)
    np.testing.assert_allclose(uv, [cam.fx * xd + cam.cx, cam.fy * yd + cam.cy], rtol=1e-12)
    np.testing.assert_allclose(project(cam, p * np.array([1, 1, -3.0]))[0], uv, rtol=1e-12)  # any depth
    o, d, ok = pixel_to_line(cam, uv)
    assert bool(ok)
    np.testing.assert_allclose(o, [3.0, -7.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(d, [0.0, 0.0, 1.0])


@pytest.mark.slow
def test_a_telecentric_camera_on_a_paraboloids_axis_is_central():
    """Parallel rays along a paraboloid's axis reflect off its convex side as if from its focus
    (the vertex plus half the vertex radius along the axis): every back-projected ray's line
    passes through it."""
    R = 20.0
    mirror = ConicMirror.of_kind("paraboloid", [0.0, 0.0, 150.0], [0.0, 0.0, 1.0], R, 30.0)
    cam = _camera()
    rng = np.random.default_rng(0)
    uv = np.array([cam.cx, cam.cy]) + rng.uniform(-250, 250, (200, 2))
    rays = jax.jit(jax.vmap(lambda u: back_project(cam, mirror, u)))(uv)
    ok = np.asarray(rays.valid)
    assert ok.sum() > 100
    focus = np.array([0.0, 0.0, 150.0 + R / 2])
    p, d = np.asarray(rays.point)[ok], np.asarray(rays.direction)[ok]
    off = (focus - p) - np.sum((focus - p) * d, axis=1, keepdims=True) * d
    assert np.max(np.linalg.norm(off, axis=1)) < 1e-9


@pytest.mark.parametrize(
    "mirror",
    [
        ConeMirror.create([0.4, -0.2, 120.0], [0.02, -0.01, 1.0], 25.0, 30.0),
        ConicMirror.of_kind("hyperboloid", [0.4, -0.2, 120.0], [0.02, -0.01, 1.0], 15.0, 25.0, -1.8),
        ConicMirror.of_kind("sphere", [0.4, -0.2, 120.0], [0.02, -0.01, 1.0], 40.0, 20.0),
    ],
    ids=["cone", "hyperboloid", "sphere"],
)
@pytest.mark.slow
def test_telecentric_projection_inverts_back_projection(mirror):
    """Points along the reflected rays of pixels before a telecentric camera, through a tilted
    mirror: each projects back to its pixel (1e-6 px), and the projection's derivative matches
    central differences."""
    cam = _camera(dist=(-0.05, 0.01, 0.0, 0.0, 0.0))
    rng = np.random.default_rng(3)
    r_px = 0.9 * float(mirror.radius) * 18.0  # the rim's image radius, about
    ang, rad = rng.uniform(0, 2 * np.pi, 60), r_px * np.sqrt(rng.uniform(0.05, 1.0, 60))
    uv = np.array([cam.cx, cam.cy]) + rad[:, None] * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    uv = uv[(uv[:, 0] > 5) & (uv[:, 0] < W - 5) & (uv[:, 1] > 5) & (uv[:, 1] < H - 5)]
    rays = back_project_many(cam, mirror, uv)
    ok = np.asarray(rays.valid)
    assert ok.sum() > 30
    pts = np.asarray(rays.point)[ok] + rng.uniform(100.0, 400.0, (ok.sum(), 1)) * np.asarray(rays.direction)[ok]
    proj = project_many(cam, mirror, pts)
    assert np.all(np.asarray(proj.valid))
    np.testing.assert_allclose(np.asarray(proj.uv), uv[ok], atol=1e-6)
    x = pts[0]
    jac = np.asarray(jax.jit(jax.jacfwd(lambda x: project_through_mirror(cam, mirror, x).uv))(x))
    h = 1e-4
    steps = np.concatenate([x + h * np.eye(3), x - h * np.eye(3)])
    uv_pm = np.asarray(project_many(cam, mirror, steps).uv)
    fd = ((uv_pm[:3] - uv_pm[3:]) / (2 * h)).T
    np.testing.assert_allclose(jac, fd, rtol=1e-5, atol=1e-7)


@pytest.mark.slow
def test_a_telecentric_calibration_and_observations_round_trip(tmp_path):
    """The camera's projection and unit survive the calibration file; the observations'
    ``camera_projection`` too, and an unknown one is refused naming the field."""
    import json

    from slcvjax.observations.formats import (
        Calibration,
        FormatError,
        read_calibration,
        read_observations,
        write_calibration,
        write_observations,
    )

    mirror = ConicMirror.of_kind("paraboloid", [0.0, 0.0, 150.0], [0.0, 0.0, 1.0], 20.0, 30.0)
    cam = _camera(dist=(-0.05, 0.01, 0.0, 0.0, 0.0), unit=17.5)
    write_calibration(tmp_path / "cal.json", Calibration(Rig(cam, mirror, _NO_LASERS), []))
    back = read_calibration(tmp_path / "cal.json").rig.camera
    assert back.telecentric and back.unit == 17.5
    np.testing.assert_allclose(back.params(), cam.params())
    doc = json.loads((tmp_path / "cal.json").read_text())
    doc["camera"]["projection"] = "fisheye"
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    with pytest.raises(FormatError, match="camera.projection"):
        read_calibration(tmp_path / "bad.json")

    obs, _ = _observations(Rig(cam, mirror, None), n_views=2, noise=0.0)
    write_observations(tmp_path / "obs.json", obs)
    assert read_observations(tmp_path / "obs.json").camera_projection == "telecentric"
    write_observations(tmp_path / "obs_auto.json", dataclasses.replace(obs, camera_projection="auto"))
    assert read_observations(tmp_path / "obs_auto.json").camera_projection == "auto"
    doc = json.loads((tmp_path / "obs.json").read_text())
    doc["camera_projection"] = "orthographic"
    (tmp_path / "bad_obs.json").write_text(json.dumps(doc))
    with pytest.raises(FormatError, match="camera_projection"):
        read_observations(tmp_path / "bad_obs.json")


def _observations(rig, n_views=8, noise=0.3, seed=4):
    """The box's walls through the mirror only (no direct views, no rim), as telecentric observations."""
    rig = rig.with_lasers(_NO_LASERS)
    obs, truth = simulate(box_scene(rig, paper_views(n_views), n_chess_views=0), noise=noise, seed=seed)
    views = [dataclasses.replace(v, rim=np.zeros((0, 2))) for v in obs.views]
    return dataclasses.replace(obs, views=views, camera_projection="telecentric"), truth


@pytest.mark.parametrize("shape", ["paraboloid", "hyperboloid estimated"])
@pytest.mark.slow
def test_a_telecentric_rig_calibrates_through_its_mirror(shape):
    """A distorted telecentric camera before a slightly tilted, off-axis mirror (8 views of the
    walls through it).  A paraboloid: the solution converges, with the camera and the mirror's
    lateral place within 4 reported std of the truth (its depth is the view's gauge, held).  A
    hyperboloid whose conic constant is estimated: the walls seen through it fix only the map
    from the pixel's radius to the ray's elevation, which the focal lengths, the radial
    distortion and the conic share: the solution still converges (the LM's damping follows the
    curved, nearly flat valley), the reported std of the focal length exceeds half of it and the
    conic constant lies within 4 std.  (At that minimum the mirror's lateral place and cx lie
    about 5 reported std off: in so flat a valley the first-order std understate them, and the
    focal length's std is what says the data do not determine this camera.)  Both predict 4
    unseen views at the noise."""
    from slcvjax.calibration.calibrate import calibrate
    from slcvjax.calibration.model_selection import held_out_rms
    from slcvjax.calibration.report import report

    conic = -1.0 if shape == "paraboloid" else -1.6
    mirror = ConicMirror.create([0.6, -0.4, 60.0], [0.012, -0.008, 1.0], 1.0 / 20.0, conic, 32.0)
    cam = Camera.create(360.0, 361.0, 322.0, 241.0, [-0.08, 0.01, 0.001, -0.001, 0.0], 640, 480, True, 20.0)
    obs_all, truth = _observations(Rig(cam, mirror, None), n_views=12)
    obs = dataclasses.replace(obs_all, views=obs_all.views[:8])
    held = dataclasses.replace(obs_all, views=obs_all.views[8:])
    obs = dataclasses.replace(
        obs, mirror_shape={"kind": shape.split()[0]} | ({} if shape == "paraboloid" else {"vertex_radius": 20.0})
    )
    res = calibrate(obs)
    assert res.rig.camera.telecentric
    rep = report(res, obs)
    unc = rep["uncertainty"]
    assert res.converged and unc["converged"]
    sd = np.sqrt(np.diag(np.asarray(res.cov.glob)))
    assert sd[11] == 0.0  # the depth: held
    if shape == "paraboloid":
        apex_err = np.asarray(res.rig.mirror.apex)[:2] - np.asarray(mirror.apex)[:2]
        assert np.all(np.abs(apex_err) < 4 * sd[9:11]), apex_err / sd[9:11]
        cam_err = np.asarray(res.rig.camera.params()) - np.asarray(cam.params())
        assert np.all(np.abs(cam_err) < 4 * sd[:9]), cam_err / sd[:9]
    else:
        assert unc["camera_std"]["fx"] > 0.5 * float(res.rig.camera.fx)
        std = unc["mirror_std"]["conic_constant"]
        assert abs(float(res.rig.mirror.conic) - conic) < 4 * std, (float(res.rig.mirror.conic), std)
    assert 0.3 < rep["residuals"]["rms_px"] < 0.45
    rms, _, invalid = held_out_rms(res.rig, held)
    assert invalid == 0 and 0.3 < rms < 0.45, rms


def test_a_telecentric_camera_needs_a_conic_mirror_seen_through():
    """Direct views (OpenCV's pinhole calibration) cannot start a telecentric camera: a clear error."""
    from slcvjax.calibration.base import CalibrationError
    from slcvjax.calibration.calibrate import calibrate
    from slcvjax.observations.simulate import paper_rig

    obs, _ = simulate(box_scene(paper_rig(2), paper_views(2), n_chess_views=3), noise=0.0, seed=1)
    obs = dataclasses.replace(obs, camera_projection="telecentric")
    with pytest.raises(CalibrationError, match="camera_projection"):
        calibrate(obs)


def test_the_perspective_test_is_an_f_test():
    """:func:`perspective_test`'s p-value against scipy's F distribution, from the two fits'
    sigma and degrees of freedom; a pinhole that fits no better gives p = 1."""
    from types import SimpleNamespace

    from scipy.stats import f as f_dist

    from slcvjax.calibration.model_selection import perspective_test

    def fit(sigma, dof):
        return SimpleNamespace(cov=SimpleNamespace(sigma=np.float64(sigma), dof=np.int64(dof)))

    for s_t, s_p, dof_t, dof_p in ((0.31, 0.30, 371, 370), (0.052, 0.05, 900, 897), (0.5, 0.4999, 50, 49)):
        pval, q, dof = perspective_test(fit(s_t, dof_t), fit(s_p, dof_p))
        S_t, S_p = s_t**2 * dof_t, s_p**2 * dof_p
        F = (S_t - S_p) / (dof_t - dof_p) / (S_p / dof_p)
        assert (q, dof) == (dof_t - dof_p, dof_p)
        np.testing.assert_allclose(pval, f_dist.sf(F, dof_t - dof_p, dof_p), rtol=1e-9)
    assert perspective_test(fit(0.30, 371), fit(0.31, 370))[0] == 1.0


@pytest.mark.slow
def test_auto_keeps_the_perspective_only_where_the_views_need_it():
    """``camera_projection = "auto"`` through a paraboloid (its kind given): views rendered
    through a pinhole 32 mm below the mirror (non-central: a telecentric camera cannot show
    their parallax) keep the pinhole; the same walls seen by a telecentric camera are left
    telecentric.  The test's level is 5 %: one draw of noise in twenty of a telecentric truth
    keeps the pinhole by design (this draw is not one of them).  The stage ``camera_projection``
    reports both fits."""
    from slcvjax.calibration.calibrate import calibrate

    persp = Rig(
        Camera.create(330.0, 331.0, 321.0, 238.0, [-0.05, 0.01, 0.0, 0.0, 0.0], 640, 480),
        ConicMirror.of_kind("paraboloid", [0.3, -0.2, 32.0], [0.01, -0.008, 1.0], 16.0, 30.0),
        None,
    )
    tele = Rig(
        Camera.create(360.0, 361.0, 322.0, 241.0, [-0.08, 0.01, 0.001, -0.001, 0.0], 640, 480, True, 20.0),
        ConicMirror.create([0.6, -0.4, 60.0], [0.012, -0.008, 1.0], 1.0 / 20.0, -1.0, 32.0),
        None,
    )
    for rig, want in ((persp, "perspective"), (tele, "telecentric")):
        obs, _ = _observations(rig, n_views=8, noise=0.05, seed=5)
        obs = dataclasses.replace(obs, camera_projection="auto", mirror_shape={"kind": "paraboloid"})
        res = calibrate(obs)
        stage = res.staged.reports[0]
        assert stage.name == "camera_projection" and any("telecentric: sigma" in n for n in stage.notes)
        assert res.rig.camera.projection == want, stage.notes
        assert res.converged


def test_auto_projection_needs_views_through_a_conic_mirror():
    """``camera_projection = "auto"`` with direct views (or a cone): a clear error, naming the field."""
    from slcvjax.calibration.base import CalibrationError
    from slcvjax.calibration.calibrate import calibrate
    from slcvjax.observations.simulate import paper_rig

    obs, _ = simulate(box_scene(paper_rig(2), paper_views(2), n_chess_views=3), noise=0.0, seed=1)
    with pytest.raises(CalibrationError, match="camera_projection: auto"):
        calibrate(dataclasses.replace(obs, camera_projection="auto"))
