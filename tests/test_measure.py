"""Measurement: spots -> 3D points with uncertainty, circle fits, the pipe experiment, `measure`."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slcvjax import Lasers, Rig, cli
from slcvjax.images.pipe import measure_observations, pipe_experiment, pipe_scene, simulate_pipe, view_circle
from slcvjax.measurement.measure import (
    fit_circle,
    fit_circle_3d,
    measure_spots,
    plane_basis,
    triangulate_spot,
    triangulate_spots,
)
from slcvjax.observations.formats import Calibration, write_calibration, write_observations
from slcvjax.observations.simulate import paper_rig


@pytest.fixture(scope="module")
def rig():
    return paper_rig()


# one compilation for every spot and rig of these tests (run op by op, each spot compiled its own)
_triangulate = jax.jit(triangulate_spot)


@pytest.mark.parametrize("n_lasers,diameter,tilt", [(10, 150.0, 0.0), (6, 130.0, 4.0)])
@pytest.mark.slow
def test_exact_pixels_give_exact_points_and_diameters(n_lasers, diameter, tilt):
    rig = paper_rig(n_lasers)
    scene = pipe_scene(rig, diameter, n_poses=5, tilt_deg=tilt, seed=3)
    obs, truth = simulate_pipe(scene, noise=0.0)
    views = measure_observations(rig, obs, pixel_sigma=0.0)
    for i, vp in enumerate(views):
        assert len(vp.lasers) == int(np.sum(np.isfinite(truth[i, :, 0])))
        np.testing.assert_allclose(vp.xyz, truth[i, vp.lasers], atol=1e-6, rtol=0)
        # the pipe's true axis: every point lies on the circle of the pipe's diameter
        circle = fit_circle_3d(vp.xyz, axis=scene.axes[i])
        assert abs(circle.diameter - diameter) < 1e-6
        np.testing.assert_allclose(circle.center, plane_basis(scene.axes[i]) @ scene.centers[i], atol=1e-6)


def test_point_lies_on_the_laser_line_and_near_the_ray(rig):
    scene = pipe_scene(rig, n_poses=1, seed=1)
    obs, _ = simulate_pipe(scene, noise=0.3, seed=2)
    for s in obs.views[0].spots:
        sp = _triangulate(rig, jnp.asarray(s.laser), jnp.asarray(s.pixel))
        p, d = np.asarray(rig.lasers.points[s.laser]), np.asarray(rig.lasers.directions[s.laser])
        v = np.asarray(sp.xyz) - p
        assert np.linalg.norm(v - (v @ d) * d) < 1e-9  # on the line
        assert bool(sp.valid) and float(sp.gap) > 0.0  # noisy: ray and line are skew


def test_parallel_ray_and_line_is_invalid_with_finite_gradients(rig):
    from slcvjax import back_project

    uv = jnp.array([420.0, 200.0])
    ray = jax.jit(back_project)(rig.camera, rig.mirror, uv)
    las = Lasers(ray.point[None] + jnp.array([[0.0, 0.0, 5.0]]), ray.direction[None])
    r2 = rig.with_lasers(las)
    sp = _triangulate(r2, jnp.asarray(0), uv)
    assert not bool(sp.valid)
    g = jax.jit(jax.jacfwd(lambda u: triangulate_spot(r2, jnp.asarray(0), u).xyz))(uv)
    assert np.all(np.isfinite(np.asarray(g)))


def test_pixel_jacobian_matches_finite_differences(rig):
    scene = pipe_scene(rig, n_poses=1, seed=4)
    obs, _ = simulate_pipe(scene, noise=0.0)
    s = obs.views[0].spots[0]
    f = jax.jit(lambda u: triangulate_spot(rig, jnp.asarray(s.laser), u).xyz)
    jac = np.asarray(jax.jacfwd(f)(jnp.asarray(s.pixel)))
    h = 1e-4
    fd = np.stack(
        [(np.asarray(f(jnp.asarray(s.pixel + h * e))) - np.asarray(f(jnp.asarray(s.pixel - h * e)))) / (2 * h)
         for e in np.eye(2)], axis=1,
    )  # fmt: skip
    np.testing.assert_allclose(jac, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())


@pytest.mark.slow
def test_circle_fit_std_matches_monte_carlo():
    rng = np.random.default_rng(0)
    ang = np.sort(rng.uniform(0, 2 * np.pi, 10))
    q0 = np.stack([3.0 + 75 * np.cos(ang), -2.0 + 75 * np.sin(ang)], axis=1)
    sig = rng.uniform(0.2, 1.5, 10)  # per-point isotropic noise
    cov = np.kron(np.diag(sig**2), np.eye(2))
    exact = fit_circle(q0, cov)
    assert abs(exact.diameter - 150.0) < 1e-9 and exact.rms < 1e-9
    d = [fit_circle(q0 + rng.normal(size=q0.shape) * sig[:, None]).diameter for _ in range(3000)]
    d_w = [fit_circle(q0 + rng.normal(size=q0.shape) * sig[:, None], cov).diameter for _ in range(3000)]
    # weighted fit: the reported std matches the Monte Carlo and beats the unweighted fit
    assert 0.9 < np.std(d_w) / exact.diameter_std < 1.1
    assert np.std(d_w) < np.std(d)


def test_circle_needs_three_points():
    with pytest.raises(ValueError, match="at least 3"):
        fit_circle(np.array([[0.0, 1.0], [1.0, 0.0]]))
    with pytest.raises(ValueError, match="collinear"):
        fit_circle(np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]))


@pytest.mark.slow
def test_reported_point_std_matches_the_error_at_half_a_pixel(rig):
    """With the true rig at 0.5 px: RMS point error / reported std in [0.8, 1.25] (points used)."""
    scene = pipe_scene(rig, n_poses=16, seed=0)
    err2, std2, d_err, d_std = [], [], [], []
    for seed in range(12):
        res = pipe_experiment(rig, scene, noise=0.5, seed=seed)
        for p in res["poses"]:
            use = ~p["points"].parallel
            err2.append(np.sum(p["error"][use] ** 2, axis=1))
            std2.append(np.sum(p["points"].std[use] ** 2, axis=1))
        d_err.append(res["diameters"] - 150.0)
        d_std.append(res["diameter_stds"])
    ratio = np.sqrt(np.mean(np.concatenate(err2)) / np.mean(np.concatenate(std2)))
    assert 0.8 <= ratio <= 1.25
    d_err, d_std = np.concatenate(d_err), np.concatenate(d_std)
    assert 0.7 < np.std(d_err) / np.sqrt(np.mean(d_std**2)) < 1.3


@pytest.mark.slow
def test_calibration_covariance_propagates_like_monte_carlo(rig):
    """Points from exact pixels with the rig perturbed by N(0, cov): spread == J cov J^T."""
    scene = pipe_scene(rig, n_poses=1, seed=5)
    obs, _ = simulate_pipe(scene, noise=0.0)
    rng = np.random.default_rng(1)
    g = rig.tangent_dim
    a = rng.normal(size=(g, g)) * 1e-5  # small enough to stay in the linear regime
    cov = a @ a.T + np.eye(g) * 1e-8
    vp = measure_observations(rig, obs, 0.0, cov)[0]
    chol = np.linalg.cholesky(cov)
    lasers = jnp.asarray([s.laser for s in obs.views[0].spots])
    pixels = jnp.asarray(np.array([s.pixel for s in obs.views[0].spots]))
    retract = jax.jit(lambda d: rig.retract(d))
    samples = []
    for _ in range(400):
        r2 = retract(jnp.asarray(chol @ rng.normal(size=g)))
        samples.append(np.asarray(triangulate_spots(r2, lasers, pixels).xyz).ravel())
    mc = np.cov(np.array(samples).T)
    np.testing.assert_allclose(np.sqrt(np.diag(mc)), np.sqrt(np.diag(vp.cov)), rtol=0.15)


# ----------------------------------------------------------------------------- the commands


@pytest.fixture(scope="module")
def pipe_files(tmp_path_factory, rig):
    d = tmp_path_factory.mktemp("pipe")
    obs, _ = simulate_pipe(pipe_scene(rig, n_poses=3, seed=2), noise=0.05, seed=0)
    write_observations(d / "obs.json", obs)
    write_calibration(d / "cal.json", Calibration(rig, extra={"residuals": {"rms_px": 0.1, "sigma_px": 0.05}}))
    return d, obs


@pytest.mark.slow
def test_measure_command_writes_points(pipe_files):
    d, obs = pipe_files
    out = d / "points.json"
    assert cli.main(["measure", str(d / "cal.json"), str(d / "obs.json"), "--out", str(out), "--fit-circle"]) == 0
    doc = json.loads(out.read_text())
    assert doc["format"] == "slcv-points/1" and doc["pixel_sigma"] == 0.05
    assert doc["uncertainty"] == "pixel noise only"
    assert [v["name"] for v in doc["views"]] == [v.name for v in obs.views]
    v0 = doc["views"][0]
    assert len(v0["points"]) == len(obs.views[0].spots)
    assert set(v0["points"][0]) >= {"laser", "xyz", "std", "angle_deg", "nearly_parallel"}
    assert abs(v0["circle"]["diameter"] - 150.0) < 5 * v0["circle"]["diameter_std"]


@pytest.mark.slow
def test_measure_writes_csv_and_ply_beside_the_json(pipe_files, tmp_path, capsys):
    """--format json,csv,ply: the CSV's and the PLY's rows are the JSON's points, in its order."""
    d, _ = pipe_files
    out = tmp_path / "points.json"
    argv = ["measure", str(d / "cal.json"), str(d / "obs.json"), "--out", str(out), "--format", "json,csv,ply"]
    assert cli.main(argv) == 0
    doc = json.loads(out.read_text())
    pts = [(k, p) for k, v in enumerate(doc["views"]) for p in v["points"]]
    assert pts
    import csv

    rows = list(csv.DictReader(out.with_suffix(".csv").read_text().splitlines()))
    assert len(rows) == len(pts)
    for row, (k, p) in zip(rows, pts, strict=True):
        assert int(row["view"]) == k and row["view_name"] == doc["views"][k]["name"]
        assert int(row["laser"]) == p["laser"] and int(row["spot"]) == p["spot"]
        assert [float(row[c]) for c in ("x_mm", "y_mm", "z_mm")] == p["xyz"]
        assert [float(row[c]) for c in ("std_x_mm", "std_y_mm", "std_z_mm")] == p["std"]
        assert int(row["nearly_parallel"]) == p["nearly_parallel"]
    lines = out.with_suffix(".ply").read_text().splitlines()
    assert lines[:2] == ["ply", "format ascii 1.0"]
    assert f"element vertex {len(pts)}" in lines
    body = lines[lines.index("end_header") + 1 :]
    props = [ln.split()[-1] for ln in lines if ln.startswith("property")]
    assert len(body) == len(pts)
    for line, (k, p) in zip(body, pts, strict=True):
        vals = dict(zip(props, line.split(), strict=True))
        assert [float(vals[c]) for c in "xyz"] == p["xyz"] and int(vals["view"]) == k
    assert "points.csv" in capsys.readouterr().out
    assert cli.main([*argv[:-1], "json,xyz"]) == 2
    assert "--format: expected json, csv or ply" in capsys.readouterr().err


def _fails(capsys, argv, *needles):
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    for n in needles:
        assert n in err, err


@pytest.mark.slow
def test_measure_bad_inputs(pipe_files, tmp_path, capsys):
    d, obs = pipe_files
    out = str(tmp_path / "p.json")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": "slcv-observations/1"}))
    _fails(capsys, ["measure", str(bad), str(d / "obs.json"), "--out", out], "bad.json", "format")
    cam_only = tmp_path / "cam.json"
    from slcvjax.observations.formats import calibration_to_json

    no_lasers = Lasers.create(np.zeros((0, 3)), np.zeros((0, 3)))
    doc = calibration_to_json(Calibration(Rig(paper_rig().camera, None, no_lasers)))  # type: ignore[arg-type]
    cam_only.write_text(json.dumps(doc))
    _fails(capsys, ["measure", str(cam_only), str(d / "obs.json"), "--out", out], "cam.json", "camera-only")
    six = tmp_path / "six.json"
    write_calibration(six, Calibration(paper_rig(6)))
    _fails(capsys, ["measure", str(six), str(d / "obs.json"), "--out", out, "--pixel-sigma", "0.5"], "n_lasers", "6")
    few = tmp_path / "few.json"
    doc = json.loads((d / "obs.json").read_text())
    doc["views"][1]["spots"] = doc["views"][1]["spots"][:2]
    few.write_text(json.dumps(doc))
    _fails(capsys, ["measure", str(d / "cal.json"), str(few), "--out", out, "--fit-circle"], "views[1]", "at least 3")
    _fails(capsys, ["measure", str(d / "cal.json"), str(d / "obs.json"), "--out", out, "--axis", "0,0"], "--axis")
    unknown = tmp_path / "unknown.json"
    doc = json.loads((d / "obs.json").read_text())
    doc["views"][0]["spots"][0]["laser"] = 12
    unknown.write_text(json.dumps(doc))
    _fails(capsys, ["measure", str(d / "cal.json"), str(unknown), "--out", out], "views[0].spots[0].laser")
    import os

    assert not os.path.exists(out)


@pytest.mark.slow
def test_pipe_command_writes_points_and_plots(tmp_path, capsys):
    out = tmp_path / "pipe"
    assert cli.main(["pipe", "--poses", "3", "--noise", "0.05", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "mean diameter" in text and "150.042" in text
    for name in ["pipe_observations.json", "points.json", "pipe_points.png", "pipe_circles.png", "pipe_errors.png"]:
        assert (out / name).stat().st_size > 0


@pytest.mark.slow
def test_a_spot_with_a_wrong_laser_label_is_flagged_not_fitted():
    rig = paper_rig(6)
    scene = pipe_scene(rig, 140.0, n_poses=6, seed=4)
    obs, _ = simulate_pipe(scene, noise=0.3, seed=2)
    wrong = {}
    for v, j in [(0, 1), (2, 3), (4, 0)]:
        s = obs.views[v].spots[j]
        wrong[(v, j)] = s.laser
        s.laser = (s.laser + 1) % rig.lasers.n
    views = measure_observations(rig, obs, pixel_sigma=0.3)
    for v, vp in enumerate(views):
        for k, j in enumerate(vp.spot_index):
            if (v, j) in wrong:
                assert vp.off_line[k] and vp.fits_laser[k] == wrong[(v, j)]
            else:
                assert not vp.off_line[k]
        circle = view_circle(vp, scene.axes[v])
        assert circle.residuals.size == int(np.sum(~vp.off_line & ~vp.parallel))
        # the wrong spot's point is not in the fit: the circle is the pipe's, within its std
        assert abs(circle.diameter - 140.0) < 3.0 * circle.diameter_std


@pytest.mark.parametrize("mirror_kind", ["hyperboloid", "sphere", "telecentric paraboloid"])
@pytest.mark.slow
def test_the_pipe_is_measured_through_other_mirrors(mirror_kind):
    """The 150 mm pipe at 16 poses measured through a conic mirror (and before a telecentric
    camera), the exact rig, 0.3 px: every spot gives a point, the points' error against the truth
    over their reported std between 0.7 and 1.25, and at least 14 of 16 diameters within two
    reported std of the truth."""
    from slcvjax.geometry.camera import Camera
    from slcvjax.geometry.conic import ConicMirror
    from slcvjax.geometry.rig import Rig
    from slcvjax.images.pipe import pipe_experiment, pipe_scene
    from slcvjax.observations.simulate import paper_rig

    r0 = paper_rig(10)
    apex, axis = [0.6, -0.4, 48.0], [0.02, -0.015, 1.0]
    cam = r0.camera
    if mirror_kind == "hyperboloid":
        mirror = ConicMirror.of_kind("hyperboloid", apex, axis, 12.0, 20.0, -2.0)
    elif mirror_kind == "sphere":
        mirror = ConicMirror.of_kind("sphere", apex, axis, 30.0, 20.0)
    else:
        cam = Camera.create(360.0, 361.0, 322.0, 241.0, [-0.08, 0.01, 0.001, -0.001, 0.0], 640, 480, True, 20.0)
        mirror = ConicMirror.of_kind("paraboloid", apex, axis, 20.0, 22.0)
    rig = Rig(cam, mirror, r0.lasers)
    s = pipe_experiment(rig, pipe_scene(rig), noise=0.3, seed=1)["summary"]
    assert s["points"] == 160 and s["nearly_parallel"] == 0 and s["off_line"] == 0, s
    assert 0.7 < s["point_error_over_std_all"] < 1.25, s
    assert s["diameters_within_two_std"] >= 14, s


def _pipe_spots(rig, seed):
    """Laser indices, pixels and view indices of two simulated pipe views."""
    obs, _ = simulate_pipe(pipe_scene(rig, 140.0, n_poses=2, seed=seed), noise=0.3, seed=seed)
    spots = [(v, s) for v, view in enumerate(obs.views) for s in view.spots]
    return np.array([s.laser for _, s in spots]), np.array([s.pixel for _, s in spots]), np.array([v for v, _ in spots])


def _measure_and_fit(rig, spots):
    views = measure_spots(rig, *spots, 2, 0.3, np.eye(rig.tangent_dim) * 1e-6)
    return views, [fit_circle_3d(vp.xyz, vp.cov) for vp in views]


def test_simulating_another_pipe_compiles_nothing_and_puts_each_spot_on_its_beam_and_the_wall(compilations):
    """After one simulated pipe, another number of poses and a rig of another laser count (the
    same buckets) are simulated by the same program; each spot lies on its laser's beam, ahead of
    the emitter, and on the pipe's wall (its distance from the pipe's axis the radius)."""
    simulate_pipe(pipe_scene(paper_rig(7), 140.0, n_poses=3, seed=0))
    rig = paper_rig(5)
    scene = pipe_scene(rig, 120.0, n_poses=6, tilt_deg=3.0, seed=1)
    with compilations() as compiled:
        obs, truth = simulate_pipe(scene)
    assert compiled == [], "\n".join(compiled)
    assert truth.shape == (6, 5, 3) and len(obs.views) == 6
    seen = np.isfinite(truth[..., 0])
    assert seen.sum() >= 10 and [len(v.spots) for v in obs.views] == list(seen.sum(axis=1))
    p, d = np.asarray(rig.lasers.points), np.asarray(rig.lasers.directions)
    for i, k in zip(*np.nonzero(seen), strict=True):
        x = truth[i, k]
        lam = np.dot(x - p[k], d[k])
        assert lam > 0 and np.linalg.norm(x - p[k] - lam * d[k]) < 1e-9
        w = x - scene.centers[i]
        assert np.linalg.norm(w - np.dot(w, scene.axes[i]) * scene.axes[i]) == pytest.approx(60.0, abs=1e-9)


def test_measuring_a_new_number_of_spots_and_lasers_compiles_nothing(compilations):
    """After one measurement, spots of another count from a rig of another laser count in the
    same bucket are triangulated, with their Jacobians and circle fits, by the same programs."""
    rig7, rig5 = paper_rig(7), paper_rig(5)
    first, other = _pipe_spots(rig7, 1), _pipe_spots(rig5, 2)
    assert len(first[0]) != len(other[0])
    _measure_and_fit(rig7, first)
    with compilations() as compiled:
        views, circles = _measure_and_fit(rig5, other)
    assert compiled == []
    assert sum(len(vp.xyz) for vp in views) == len(other[0])
    assert all(c.diameter_std > 0 for c in circles)
