"""A general smooth mirror of revolution (a conic plus even polynomial terms): its geometry against
closed forms and finite differences, its files, and a calibration through it."""

import dataclasses

import jax
import numpy as np
import pytest

from slcvjax.geometry.conic import AsphereMirror, ConicMirror
from slcvjax.geometry.mirror import back_project, project_through_mirror
from slcvjax.observations.simulate import paper_camera

from ._helpers import back_project_many, project_many

APEX, AXIS = [0.6, -0.4, 48.0], [0.02, -0.015, 1.0]
COEFFS = [1.5e-5, -2e-8]  # rho^4, rho^6 (1/mm^3, 1/mm^5)


def _sag(rho2, c=1 / 20.0, kappa=-1.5, coeffs=COEFFS):
    """The profile, written out (NumPy)."""
    base = c * rho2 / (1 + np.sqrt(1 - (1 + kappa) * c * c * rho2))
    return base + sum(a * rho2 ** (j + 2) for j, a in enumerate(coeffs))


def _mirror(coeffs=COEFFS):
    return AsphereMirror.create(APEX, AXIS, 1 / 20.0, -1.5, 20.0, coeffs)


def _pixels(cam, n=60, seed=0):
    rng = np.random.default_rng(seed)
    return np.array([cam.cx, cam.cy]) + rng.uniform(-180, 180, (n, 2))


@pytest.mark.slow
def test_an_asphere_without_terms_is_its_conic():
    cam = paper_camera()
    a, c = _mirror([0.0, 0.0]), ConicMirror.create(APEX, AXIS, 1 / 20.0, -1.5, 20.0)
    uv = _pixels(cam)
    many = jax.jit(jax.vmap(lambda m, u: back_project(cam, m, u), in_axes=(None, 0)))  # op by op: 130 compilations
    ra, rc = many(a, uv), many(c, uv)
    np.testing.assert_array_equal(np.asarray(ra.valid), np.asarray(rc.valid))
    ok = np.asarray(rc.valid)
    np.testing.assert_allclose(np.asarray(ra.point)[ok], np.asarray(rc.point)[ok], atol=1e-10)
    np.testing.assert_allclose(np.asarray(ra.direction)[ok], np.asarray(rc.direction)[ok], atol=1e-12)


@pytest.mark.slow
def test_an_asphere_reflects_by_its_profile():
    """Back-projected rays: the mirror point on the written-out profile (1e-9 mm), the law of
    reflection about the normal of that profile by central differences (1e-6), and points along
    the reflected rays projected back to their pixels (1e-6 px) with the projection's derivative
    equal to central differences."""
    cam = paper_camera()
    m = _mirror()
    uv = _pixels(cam)
    rays = back_project_many(cam, m, uv)
    ok = np.asarray(rays.valid)
    assert ok.sum() > 30
    a = np.asarray(m.axis)
    e1 = np.cross(a, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    for p, d in zip(np.asarray(rays.point)[ok], np.asarray(rays.direction)[ok], strict=True):
        q = p - np.asarray(m.apex)
        x, y = q @ e1, q @ e2
        assert abs(q @ a - _sag(x * x + y * y)) < 1e-9
        h = 1e-5

        def surf(x, y):
            return np.asarray(m.apex) + x * e1 + y * e2 + _sag(x * x + y * y) * a

        tx = (surf(x + h, y) - surf(x - h, y)) / (2 * h)
        ty = (surf(x, y + h) - surf(x, y - h)) / (2 * h)
        n = np.cross(tx, ty)
        n /= np.linalg.norm(n)
        d_in = p / np.linalg.norm(p)
        np.testing.assert_allclose(d, d_in - 2 * (d_in @ n) * n, atol=1e-6)
    pts = np.asarray(rays.point)[ok] + 250.0 * np.asarray(rays.direction)[ok]
    proj = project_many(cam, m, pts)
    assert np.all(np.asarray(proj.valid))
    np.testing.assert_allclose(np.asarray(proj.uv), uv[ok], atol=1e-6)
    x = pts[0]
    jac = np.asarray(jax.jit(jax.jacfwd(lambda x: project_through_mirror(cam, m, x).uv))(x))
    uv_pm = np.asarray(project_many(cam, m, np.concatenate([x + 1e-4 * np.eye(3), x - 1e-4 * np.eye(3)])).uv)
    fd = ((uv_pm[:3] - uv_pm[3:]) / 2e-4).T
    np.testing.assert_allclose(jac, fd, rtol=1e-5, atol=1e-7)


def test_an_asphere_is_checked_and_kept_in_files(tmp_path):
    import json

    from slcvjax.geometry.lasers import Lasers
    from slcvjax.geometry.rig import Rig
    from slcvjax.observations.formats import Calibration, FormatError, read_calibration, write_calibration

    with pytest.raises(ValueError, match="turn it back"):
        AsphereMirror.create(APEX, AXIS, 1 / 20.0, -1.5, 20.0, [0.0, -1e-4])
    rig = Rig(paper_camera(), _mirror(), Lasers.create(np.zeros((0, 3)), np.zeros((0, 3))))
    write_calibration(tmp_path / "cal.json", Calibration(rig, []))
    back = read_calibration(tmp_path / "cal.json").rig.mirror
    assert back.kind == "asphere"
    np.testing.assert_allclose(back.coefficients, COEFFS)
    doc = json.loads((tmp_path / "cal.json").read_text())
    del doc["mirror"]["coefficients"]
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    with pytest.raises(FormatError, match="mirror.*coefficients"):
        read_calibration(tmp_path / "bad.json")


@pytest.mark.slow
def test_a_rig_through_an_asphere_calibrates():
    """The asphere given (a datasheet's), 8 views of the walls through it: the camera within 4
    reported std of the truth and 4 unseen views predicted at the noise."""
    from slcvjax.calibration.calibrate import calibrate
    from slcvjax.calibration.model_selection import held_out_rms
    from slcvjax.calibration.report import report
    from slcvjax.geometry.lasers import Lasers
    from slcvjax.geometry.rig import Rig
    from slcvjax.observations.simulate import box_scene, paper_views, simulate

    rig = Rig(paper_camera(), _mirror(), Lasers.create(np.zeros((0, 3)), np.zeros((0, 3))))
    obs_all, truth = simulate(box_scene(rig, paper_views(12), n_chess_views=0), noise=0.3, seed=4)
    obs_all = dataclasses.replace(obs_all, views=[dataclasses.replace(v, rim=np.zeros((0, 2))) for v in obs_all.views])
    assert obs_all.mirror_shape["kind"] == "asphere"
    obs = dataclasses.replace(obs_all, views=obs_all.views[:8])
    held = dataclasses.replace(obs_all, views=obs_all.views[8:])
    res = calibrate(obs)
    assert res.rig.mirror.kind == "asphere"
    sd = np.sqrt(np.diag(np.asarray(res.cov.glob)))
    err = np.asarray(res.rig.camera.params()) - np.asarray(truth.rig.camera.params())
    assert np.all(np.abs(err) < 4 * sd[:9]), err / sd[:9]
    assert 0.3 < report(res, obs)["residuals"]["rms_px"] < 0.45
    rms, _, invalid = held_out_rms(res.rig, held)
    assert invalid == 0 and 0.3 < rms < 0.45, rms
