"""Stripe measurement (issue 59, item 4): stripe samples -> 3D points on their sheets of light,
their std, a ring laser's circle and ellipse in a pipe, the grazing flag, the points file."""

import json

import jax.numpy as jnp
import numpy as np
import pytest

from slcvjax import cli
from slcvjax.geometry.mirror import back_project
from slcvjax.geometry.rig import Rig
from slcvjax.geometry.sheets import Sheets
from slcvjax.images.pipe import pipe_scene
from slcvjax.images.ring_pipe import ring_pipe_experiment, simulate_ring_pipe
from slcvjax.measurement.ring import fit_circle_factored, fit_ellipse, ring_plane_points
from slcvjax.measurement.stripes import measure_stripe_observations, measure_stripes
from slcvjax.observations.formats import Calibration, write_calibration, write_observations
from slcvjax.observations.simulate import box_scene, paper_rig, paper_views, sheet_rig, visible_stripes

RING_KINDS = ("cone", "point", "point", "point", "point")


@pytest.fixture(scope="module")
def ring_rig():
    return sheet_rig(paper_rig(), RING_KINDS)[0]


def _samples(stripes):
    """Flat arrays (lasers, stripe, sample, pixels, true points) of ``visible_stripes``' output."""
    las, so, sa, px, xs = [], [], [], [], []
    for k, (e, _, x, uv) in enumerate(stripes):
        las += [e] * len(uv)
        so += [k] * len(uv)
        sa += list(range(len(uv)))
        px.append(uv)
        xs.append(x)
    return np.array(las), np.array(so), np.array(sa), np.concatenate(px), np.concatenate(xs)


def test_exact_samples_give_the_simulators_true_points_on_planes_and_cones():
    rig, fans = sheet_rig(paper_rig(), ("cone", "plane", "point"))
    sc = box_scene(rig, paper_views(2), n_chess_views=1)
    sc.fans = fans
    las, so, sa, px, truth = _samples(visible_stripes(sc, 1))
    assert set(las.tolist()) == {0, 1}  # both a cone's and a plane's stripes
    (vp,) = measure_stripes(rig, las, so, sa, px, np.zeros(len(px), int), 1, 0.0)
    assert len(vp) == len(px) and not vp.missing
    assert np.max(np.abs(vp.xyz - truth)) < 1e-8
    np.testing.assert_array_equal(vp.lasers, las)
    np.testing.assert_array_equal(vp.sample_index, sa)


def test_ring_samples_in_a_pipe_lie_on_the_wall_and_give_its_diameter(ring_rig):
    scene = pipe_scene(ring_rig, 150.0, n_poses=3, seed=4)
    res = ring_pipe_experiment(ring_rig, scene, 0.0)
    for i, (p, truth) in enumerate(zip(res["poses"], res["truth"], strict=True)):
        wall = np.linalg.norm((np.concatenate(truth) - scene.centers[i])[:, :2], axis=1)  # the pipe's axis is z
        np.testing.assert_allclose(wall, 75.0, atol=1e-9)
        assert np.max(np.abs(p["error"])) < 1e-8
        circle = p["rings"][0]["circle"]
        assert abs(circle.diameter - 150.0) < 1e-9
        np.testing.assert_allclose(circle.center, scene.centers[i, :2], atol=1e-9)
    assert res["summary"]["stripe_points"] > 1000 and res["summary"]["grazing"] == 0


def test_the_ellipse_of_an_oval_pipe_recovers_its_diameters_and_orientation(ring_rig):
    scene = pipe_scene(ring_rig, 150.0, n_poses=2, seed=5)
    res = ring_pipe_experiment(ring_rig, scene, 0.0, minor=141.0, orientation_deg=25.0)
    for p in res["poses"]:
        el = p["rings"][0]["ellipse"]
        assert abs(el.major - 150.0) < 1e-7 and abs(el.minor - 141.0) < 1e-7
        assert abs(np.degrees(el.orientation) - 25.0) < 1e-6
        assert abs(el.ovality - 9.0 / 145.5) < 1e-9
        # the circle of an oval is not its truth: the ellipse is needed
        assert p["rings"][0]["circle"].rms > 1.0


def test_point_std_matches_a_monte_carlo_of_pixel_noise(ring_rig, rng):
    scene = pipe_scene(ring_rig, 150.0, n_poses=1, seed=6)
    obs, truth, _ = simulate_ring_pipe(scene, 0.0, step_deg=30.0)
    pix = obs.views[0].stripes[0].pixels
    sigma, trials = 0.5, 300
    m = len(pix)
    (vp,) = measure_stripes(ring_rig, np.zeros(m, int), np.zeros(m, int), np.arange(m), pix, np.zeros(m, int), 1, sigma)
    noisy = pix[None] + rng.normal(0.0, sigma, (trials, m, 2))
    n = trials * m
    (mc,) = measure_stripes(
        ring_rig, np.zeros(n, int), np.zeros(n, int), np.arange(n), noisy.reshape(-1, 2), np.zeros(n, int), 1, 0.0
    )
    assert len(mc) == n
    xyz = mc.xyz.reshape(trials, m, 3)
    for k in range(m):
        # along the direction of the largest reported std (where the ray's depth is lost)
        w, v = np.linalg.eigh(vp.pixel_cov[k])
        proj = (xyz[:, k] - truth[0][0][k]) @ v[:, -1]
        ratio = np.std(proj) / np.sqrt(w[-1])
        assert 0.8 < ratio < 1.25, (k, ratio)


def test_circle_std_from_the_factored_covariance_matches_the_dense_one(ring_rig, rng):
    scene = pipe_scene(ring_rig, 150.0, n_poses=1, seed=7)
    obs, _, _ = simulate_ring_pipe(scene, 0.3, seed=1, step_deg=6.0)
    g = ring_rig.tangent_dim
    a = rng.normal(size=(g, g)) * 1e-3
    cov = a @ a.T
    (svp,) = measure_stripe_observations(ring_rig, obs, 0.3, cov)
    pp = ring_plane_points(svp, 0)
    c = fit_circle_factored(pp, debias=False)
    from slcvjax.measurement.measure import fit_circle_3d
    from slcvjax.measurement.ring import reliable

    used = svp.select(reliable(svp, 0))
    assert len(used) == len(pp.q) > 40
    dense = fit_circle_3d(used.xyz, used.joint_cov())
    assert abs(c.diameter - dense.diameter) < 1e-9
    assert abs(c.diameter_std - dense.diameter_std) < 1e-9 * max(1.0, dense.diameter_std)


def test_ellipse_std_matches_a_monte_carlo_of_its_points(rng):
    # points on an ellipse with isotropic noise: the fitted semi-axes' spread against their std
    a, b, phi, c = 80.0, 72.0, 0.4, np.array([3.0, -2.0])
    t = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    ca, sa = np.cos(phi), np.sin(phi)
    exact = c + np.column_stack([a * np.cos(t) * ca - b * np.sin(t) * sa, a * np.cos(t) * sa + b * np.sin(t) * ca])
    s = 0.2
    from slcvjax.measurement.ring import PlanePoints

    cov = np.broadcast_to(s**2 * np.eye(2), (len(t), 2, 2)).copy()
    fits = [fit_ellipse(PlanePoints(exact + rng.normal(0, s, exact.shape), cov), debias=False) for _ in range(60)]
    major = np.array([f.major for f in fits])
    ov = np.array([f.ovality for f in fits])
    assert abs(np.mean(major) - 2 * a) < 4 * np.std(major) / np.sqrt(len(fits)) + 0.01
    ratio = np.std(major) / fits[0].std["major"]
    assert 0.65 < ratio < 1.5, ratio
    ratio = np.std(ov) / fits[0].std["ovality"]
    assert 0.65 < ratio < 1.5, ratio


def _grazing_rig(uv, tilt_deg: float):
    """The paper rig with one plane of light through the reflected ray of pixel ``uv`` (80 mm out),
    tilted ``tilt_deg`` from containing it."""
    base = paper_rig(1)
    ray = back_project(base.camera, base.mirror, jnp.asarray(uv))
    r, o = np.asarray(ray.direction), np.asarray(ray.point)
    n0 = np.cross(r, [0.0, 0.0, 1.0])
    n0 /= np.linalg.norm(n0)
    t = np.radians(tilt_deg)
    n = np.cos(t) * n0 + np.sin(t) * r  # the ray meets the plane at tilt_deg
    sheets = Sheets.create(["plane"], [o + 80.0 * r], [n])
    return Rig.of_elements(base.camera, base.mirror, base.lasers, sheets, ("point", "plane")), o + 80.0 * r


def test_a_nearly_grazing_ray_is_flagged_and_one_in_the_sheet_gives_no_point():
    uv = np.array([[420.0, 240.0]])
    one = (np.ones(1, int), np.zeros(1, int), np.zeros(1, int))
    rig, x = _grazing_rig(uv[0], 30.0)
    (ok,) = measure_stripes(rig, *one, uv, np.zeros(1, int), 1, 0.3)
    assert not ok.grazing[0] and abs(np.degrees(ok.angle[0]) - 30.0) < 1e-6
    assert np.max(np.abs(ok.xyz[0] - x)) < 1e-8
    rig, x = _grazing_rig(uv[0], 0.2)
    (near,) = measure_stripes(rig, *one, uv, np.zeros(1, int), 1, 0.3)
    assert near.grazing[0] and abs(np.degrees(near.angle[0]) - 0.2) < 1e-6
    assert np.max(near.std) > 50 * np.max(ok.std)  # a large std goes with the flag
    assert np.all(np.isfinite(near.xyz)) and np.all(np.isfinite(near.std))
    rig, _ = _grazing_rig(uv[0], 0.0)
    (none,) = measure_stripes(rig, *one, uv, np.zeros(1, int), 1, 0.3)
    assert len(none) == 0 and len(none.missing) == 1 and "nowhere" in none.missing[0][3]


def test_a_stripe_on_a_point_laser_is_refused_by_name(ring_rig):
    with pytest.raises(ValueError, match="view 0, stripe 2, sample 5: laser 1 is a point laser"):
        measure_stripes(ring_rig, [1], [2], [5], [[300.0, 200.0]], [0], 1, 0.3)


def test_measure_command_writes_stripe_points_rings_and_spots(ring_rig, tmp_path):
    scene = pipe_scene(ring_rig, 150.0, n_poses=2, seed=8)
    obs, _, _ = simulate_ring_pipe(scene, 0.2, seed=3, step_deg=2.0)
    write_observations(tmp_path / "obs.json", obs)
    extra = {"residuals": {"rms_px": 0.3, "sigma_px": 0.2, "by_kind_sigma_px": {"spot": 0.2, "stripe": 0.25}}}
    write_calibration(tmp_path / "cal.json", Calibration(ring_rig, extra=extra))
    out = tmp_path / "points.json"
    argv = ["measure", str(tmp_path / "cal.json"), str(tmp_path / "obs.json"), "--out", str(out), "--fit-circle"]
    assert cli.main(argv) == 0
    doc = json.loads(out.read_text())  # conftest checks it against slcv-points/1's schema
    assert doc["stripe_pixel_sigma"] == 0.25 and doc["pixel_sigma"] == 0.2
    v0 = doc["views"][0]
    stripe_pts = [p for p in v0["points"] if "stripe" in p]
    spot_pts = [p for p in v0["points"] if "spot" in p]
    assert len(stripe_pts) == len(obs.views[0].stripes[0].pixels) and len(spot_pts) == len(obs.views[0].spots)
    assert {p["laser"] for p in stripe_pts} == {0} and {p["laser"] for p in spot_pts} <= {1, 2, 3, 4}
    assert [p["sample"] for p in stripe_pts] == list(range(len(stripe_pts)))
    ring = v0["rings"][0]
    assert ring["laser"] == 0 and abs(ring["circle"]["diameter"] - 150.0) < 5 * ring["circle"]["diameter_std"]
    assert ring["ellipse"]["ovality"] < 0.01


def test_pipe_command_runs_the_ring_experiment(tmp_path):
    out = tmp_path / "ring"
    argv = ["pipe", "--laser", "ring", "--poses", "2", "--noise", "0.2", "--out", str(out)]
    assert cli.main(argv) == 0
    doc = json.loads((out / "points.json").read_text())  # conftest checks it against its schema
    for v in doc["views"]:
        assert abs(v["rings"][0]["circle"]["diameter"] - 150.0) < 5 * v["rings"][0]["circle"]["diameter_std"]
