"""Laser design for measurement: the predicted diameter std against Monte Carlo, its gradient, the optimiser."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slcvjax import cli
from slcvjax.experiments import laser_design as ld
from slcvjax.experiments.design import Plan
from slcvjax.images.pipe import PipeScene, measure_observations, simulate_pipe, view_circle
from slcvjax.observations.simulate import box_scene, paper_rig, paper_views

DIAMETERS = (110.0, 220.0)  # the preset's ring cannot show all its spots in the first


@pytest.fixture(scope="module")
def small():
    """The CLI's plan for 4 lasers and 6 views (so that the CLI test reuses the compilation)."""
    rig = paper_rig(4)
    views = paper_views(6)
    plan = Plan.from_scene(box_scene(rig, views), views, noise=0.5)
    return ld.MeasurePlan(plan, np.asarray(DIAMETERS))


def _diameters(rig, meas_rig, d, noise, rig_cov, trials, seed):
    """Diameters measured with ``meas_rig`` from ``trials`` noisy views of the pipe (sensor on the axis)."""
    pipe = PipeScene(rig, d, np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]))
    out = []
    for t in range(trials):
        obs, _ = simulate_pipe(pipe, noise=noise, seed=seed + t)
        r = meas_rig(t)
        out.append(view_circle(measure_observations(r, obs, noise, rig_cov)[0]).diameter - d)
    return np.asarray(out)


@pytest.mark.slow
def test_predicted_diameter_std_matches_monte_carlo_pixel_noise_and_calibration_error():
    """The first-order prediction against measurements of simulated spots: pixel noise with the
    exact rig, then pixel noise with rigs drawn from a calibration covariance."""
    rig = paper_rig(7)
    d, sigma = 170.0, 0.6
    g = rig.tangent_dim
    rng = np.random.default_rng(3)
    # a calibration covariance of plausible size: lasers 0.3 mm / 0.3 deg, mirror 0.02 mm, camera
    # small, the cone's shape given
    scale = np.concatenate([[0.2, 0.2, 0.2, 0.2, 1e-4, 1e-4, 1e-5, 1e-5, 1e-4], [0.02] * 3, [2e-4] * 2, [0.0],
                            np.tile([0.3, 0.3, 0.005, 0.005], rig.lasers.n)])  # fmt: skip
    a = rng.normal(size=(g, g)) / np.sqrt(g)
    cov = (scale[:, None] * (a @ a.T + 0.5 * np.eye(g))) * scale[None, :]
    body = jnp.asarray([ld.BODY_RADIUS_MM, ld.BODY_GAP_MM])
    prediction = jax.jit(ld.pipe_prediction)  # one program, not one per operation

    var_px, seen, *_ = prediction(rig, jnp.zeros((g, g)), sigma, d / 2, body)
    assert bool(np.all(seen))
    mc = _diameters(rig, lambda t: rig, d, sigma, None, 300, seed=0)
    # 300 trials: the std's relative sampling error is about 4 %
    assert np.std(mc) == pytest.approx(np.sqrt(float(var_px)), rel=0.12)

    var_both, *_ = prediction(rig, jnp.asarray(cov), sigma, d / 2, body)
    assert float(var_both) > 1.5 * float(var_px)  # the calibration's part is not negligible
    deltas = rng.multivariate_normal(np.zeros(g), cov, size=300)
    mc = _diameters(rig, lambda t: rig.retract(jnp.asarray(deltas[t])), d, sigma, cov, 300, seed=1000)
    assert np.sqrt(np.mean(mc**2)) == pytest.approx(np.sqrt(float(var_both)), rel=0.12)


@pytest.mark.slow
def test_design_sees_every_spot_and_lowers_the_predicted_error(small):
    res = ld.optimise_lasers(small, steps=8)
    b, a = res.predicted_before, res.predicted_after
    # the start cannot see every spot in the small pipe; the design does, in both pipes
    assert not np.all(b.seen)
    assert res.feasible and np.all(a.seen) and a.emitters_seen == 0
    assert np.min(a.rim_margin_mm) >= small.margin_mm and np.min(a.body_margin_mm) >= small.margin_mm
    assert np.all(np.isfinite(a.diameter_std_mm))
    # every accepted gradient step lowered the objective
    assert len(res.history) >= 2 and np.all(np.diff(res.history) < 0)
    # the reported prediction is the objective's
    assert np.mean(a.diameter_std_mm**2 / a.diameters**2) == pytest.approx(res.history[-1], rel=1e-9)
    # the mounting stayed within its range
    m0, m1 = ld.mounting_of(res.rig_before.lasers), ld.mounting_of(res.rig_after.lasers)
    assert np.all(np.abs(np.degrees(m1["elevation"] - m0["elevation"])) <= small.elevation_range_deg + 1e-9)
    assert np.all(np.abs(m1["z"] - m0["z"]) <= small.ring_z_range_mm + 1e-9)
    np.testing.assert_allclose(m1["azimuth"], m0["azimuth"], atol=1e-12)


@pytest.mark.slow
def test_gradient_of_the_relative_variance_matches_finite_differences(small):
    c = ld.Compiled(small)
    u = jnp.asarray(np.concatenate([np.full(c.n, -0.45), [0.0, 0.9]]))  # a mounting that sees every spot
    assert np.all(c.evaluate(u).seen)
    f, grad = c.value_and_grad(u)
    h = 1e-5
    for k in (0, c.n, c.n + 1):  # one elevation, the ring's radius, its height
        e = jnp.zeros_like(u).at[k].set(h)
        fd = (float(c.value_and_grad(u + e)[0]) - float(c.value_and_grad(u - e)[0])) / (2 * h)
        assert float(grad[k]) == pytest.approx(fd, rel=1e-4, abs=1e-6 * abs(float(f)))


@pytest.mark.slow
def test_cli_design_measure_writes_the_design(tmp_path, capsys):
    rc = cli.main(
        ["design", "--measure", "--views", "6", "--lasers", "4", "--steps", "3", "--diameters",
         ",".join(f"{d:g}" for d in DIAMETERS), "--out", str(tmp_path)]
    )  # fmt: skip
    assert rc == 0
    doc = json.loads((tmp_path / "laser_design.json").read_text())
    assert doc["format"] == "slcv-laser-design/1" and doc["feasible"] is True
    assert doc["predicted"]["before"]["diameter_std_mm"][0] is None  # not every spot seen: null
    assert all(x is not None for x in doc["predicted"]["after"]["diameter_std_mm"])
    assert len(doc["lasers_after"]["points_mm"]) == 4
    assert (tmp_path / "laser_design.png").stat().st_size > 0
    assert "not measurable" in capsys.readouterr().out


def test_measure_plan_rejects_a_ring_outside_the_pipe(small):
    with pytest.raises(ValueError, match="inside the smallest pipe"):
        ld.MeasurePlan(small.plan, np.array([60.0]))
    with pytest.raises(ValueError, match="diameters"):
        ld.MeasurePlan(small.plan, np.array([-1.0]))


@pytest.mark.slow
def test_confirmation_measures_every_pipe_with_each_simulated_calibration(small):
    res = ld.optimise_lasers(small, steps=2)
    out = ld.confirm_lasers(small, res.rig_after, trials=3, seed=4)
    assert out["trials"] == 3 and out["failed"] == 0
    assert out["circles"] == [3, 3]
    for err, rep, pred in zip(out["diameter_error_rms_mm"], out["reported_std_rms_mm"],
                              res.predicted_after.diameter_std_mm, strict=True):  # fmt: skip
        # three trials: the error scatters, but its size and the reported std follow the prediction
        assert 0.1 * pred < err < 4.0 * pred
        assert rep == pytest.approx(pred, rel=0.3)
