"""Experiment design: the predicted bound against the calibration's own bound, its gradient, the optimiser."""

import json

import jax.numpy as jnp
import numpy as np
import pytest

import slcvjax as sj
from slcvjax import cli
from slcvjax.experiments import design as _design
from slcvjax.observations.simulate import box_scene, paper_rig, paper_views


@pytest.fixture(scope="module")
def plan():
    views = paper_views(4)
    scene = box_scene(paper_rig(3), views)
    return scene, _design.Plan.from_scene(scene, views, noise=0.5)


@pytest.mark.slow
def test_a_padded_plan_predicts_as_the_unpadded_one_and_another_size_compiles_nothing(plan, compilations):
    """Three views padded to the bucket of four (and the direct views to theirs) against the
    same plan unpadded: the same prediction and gradient, none for the padded views; then the
    module's four-view plan, in the same buckets, compiles nothing."""
    views = paper_views(3)
    small = _design.Plan.from_scene(box_scene(paper_rig(3), views), views, noise=0.5)
    padded, plain = _design.Compiled(small), _design.Compiled(small, pad=False)
    assert (padded.cap, plain.cap) == (4, 3)
    assert padded.chess.t.shape[0] > plain.chess.t.shape[0]  # the direct views padded too
    a, b = padded.predict(views), plain.predict(views)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-9)
    args = (a[0], a[1], jnp.asarray(0.5))
    fa, ga = padded.value_and_grad(padded.u_of(views), *args)
    fb, gb = plain.value_and_grad(plain.u_of(views), *args)
    assert float(fa) == pytest.approx(float(fb), rel=1e-9)
    np.testing.assert_allclose(np.asarray(ga)[:3], np.asarray(gb), rtol=1e-7, atol=1e-9 * float(jnp.max(jnp.abs(gb))))
    assert np.all(np.asarray(ga)[3:] == 0.0)  # the padded view moves nowhere
    _, p = plan
    with compilations() as compiled:
        c = _design.Compiled(p)
        pos, ang, _, _ = c.predict(p.views)
        c.value_and_grad(c.u_of(p.views), pos, ang, jnp.asarray(0.5))
    assert compiled == [], "\n".join(compiled)


@pytest.mark.slow
def test_prediction_equals_the_bound_of_the_simulated_calibration(plan):
    scene, p = plan
    pred = _design.predict(p)
    obs, truth = sj.simulate(scene, noise=0.0, seed=0)
    cr = sj.cramer_rao(truth, obs, 0.5)
    # the same points are observed ...
    assert pred.n_spots == sum(len(v.spots) for v in obs.views)
    assert pred.n_dots == sum(int(s.sum()) for v in obs.views for _, s in v.boards.values())
    # ... and the bound agrees (the rim pixels differ: evenly spread here, random there)
    np.testing.assert_allclose(pred.position_std_mm, cr["position_std_mm"], rtol=5e-3)
    np.testing.assert_allclose(pred.direction_std_rad, cr["direction_std_rad"], rtol=5e-3)


@pytest.mark.slow
def test_gradient_of_the_bound_matches_finite_differences(plan):
    _, p = plan
    c = _design.Compiled(p)
    u = c.u_of(p.views)
    pos, ang, _, _ = c.predict(c.scale * jnp.tanh(u))
    args = (pos, ang, jnp.asarray(0.5))
    f0, g = c.value_and_grad(u, *args)
    assert float(f0) == pytest.approx(1.5, rel=1e-9)
    eps = 1e-5
    for i, j in [(1, 2), (2, 3), (3, 0), (1, 5)]:  # yaw, x, roll, z of a few views
        up = float(c.value_and_grad(u.at[i, j].add(eps), *args)[0])  # one compilation for both
        dn = float(c.value_and_grad(u.at[i, j].add(-eps), *args)[0])
        fd = (up - dn) / (2 * eps)
        assert float(g[i, j]) == pytest.approx(fd, rel=1e-4, abs=1e-7)
    assert float(jnp.max(jnp.abs(g))) > 1e-3


@pytest.mark.slow
def test_optimised_poses_stay_in_range_and_lower_the_bound(plan):
    _, p = plan
    res = _design.optimise(p, steps=6)
    assert len(res.history) >= 2
    assert all(b < a for a, b in zip(res.history, res.history[1:], strict=False))
    assert np.all(np.abs(res.after.views) <= p.scale + 1e-12)
    assert res.predicted_after.direction_rms_deg < res.predicted_before.direction_rms_deg
    doc = _design.design_document(res)
    assert doc["format"] == "slcv-design/1" and len(doc["views_after"]) == 4


@pytest.mark.parametrize(
    "argv, expected",
    [
        (["--rotation", "3,3"], "--rotation"),
        (["--translation", "a,b,c"], "--translation"),
        (["--views", "0"], "--views"),
        (["--box", "-1"], "--box"),
    ],
)
def test_design_command_bad_options(tmp_path, capsys, argv, expected):
    assert cli.main(["design", *argv, "--out", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err
    assert expected in err and "Traceback" not in err
    assert not (tmp_path / "d").exists()


def test_an_unsupported_prediction_is_written_as_null():
    from slcvjax.experiments.design import MIN_SPOTS, Prediction

    pred = Prediction(np.array([0.5, np.inf]), np.array([0.01, np.inf]), 100, 2)
    doc = json.loads(json.dumps(pred.to_json()))
    assert doc["position_rms_mm"] is None and doc["position_std_mm"] == [0.5, None]
    assert str(MIN_SPOTS) in doc["status"]
    ok = Prediction(np.array([0.5, 0.6]), np.array([0.01, 0.02]), 100, 20).to_json()
    assert "status" not in ok and ok["position_rms_mm"] == pytest.approx(np.sqrt((0.25 + 0.36) / 2))
