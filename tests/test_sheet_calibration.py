"""Line and ring lasers in the joint calibration: the stripe rows' Jacobian against finite
differences, exact recovery from exact observations, the files, and the stored problem."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import slcvjax as sj
from slcvjax.calibration.bound import sheet_errors, sheet_working_points
from slcvjax.calibration.linearise import rows_at
from slcvjax.calibration.params import Params
from slcvjax.calibration.report import to_calibration
from slcvjax.calibration.stored import load_result
from slcvjax.observations.formats import (
    FormatError,
    calibration_from_json,
    calibration_to_json,
    observations_from_json,
    observations_to_json,
    write_calibration,
)
from slcvjax.observations.problem import Kind, pack, stack_poses
from slcvjax.observations.simulate import box_scene, paper_rig, paper_views, sheet_rig, simulate


def scene(kinds, n_views=6, step=2.0, n_chess=4):
    rig, fans = sheet_rig(paper_rig(), kinds)
    sc = box_scene(rig, paper_views(n_views), n_chess_views=n_chess)
    sc.fans, sc.stripe_step_deg = fans, step
    return sc


def true_params(truth, pk) -> Params:
    poses = stack_poses([truth.board_poses[v][b] for v, b in pk.pose_keys])
    chess = stack_poses([truth.calibration_view_poses[c] for c in pk.chess_keys])
    return Params(truth.rig, poses, chess)


def test_stripe_rows_vanish_at_the_truth_and_their_jacobian_is_the_finite_difference_one():
    """Every column a stripe row reaches (camera, mirror, its sheet, its board pose) against central
    differences of the residuals: a cone and a plane beside point lasers."""
    sc = scene(("point", "cone", "plane", "point"), n_views=3, step=6.0, n_chess=2)
    obs, truth = simulate(sc, 0.0)
    pk = pack(obs)
    params = true_params(truth, pk)
    at = jax.jit(rows_at, static_argnames="with_jac")  # one program (op by op, the loops' scans are slow)
    arr = pk.arrays()
    rows = at(params, arr)
    kind, ok, r = np.asarray(rows.kind), np.asarray(rows.valid), np.asarray(rows.r)
    stripe = np.flatnonzero((kind == Kind.STRIPE) & ok)
    assert len(stripe) > 100
    assert np.abs(r[(kind == Kind.STRIPE) & ok]).max() < 1e-9  # px: exact samples lie on their curves
    sel = stripe[:: max(1, len(stripe) // 40)]
    G, nb = params.n_global, params.n_blocks
    jg, gidx = np.asarray(rows.jg)[sel], np.asarray(rows.gidx)[sel]
    jp, pidx = np.asarray(rows.jp)[sel], np.asarray(rows.pidx)[sel]
    J = np.zeros((len(sel), G + 1 + 6 * nb))
    for i in range(len(sel)):
        np.add.at(J[i], gidx[i], jg[i])
        J[i, G + 1 + 6 * pidx[i] : G + 7 + 6 * pidx[i]] += jp[i]

    def res(dg, dp):
        return np.asarray(at(params.retract(jnp.asarray(dg), jnp.asarray(dp)), arr, with_jac=False).r)[sel]

    eps = 1e-6
    fd = np.zeros((len(sel), G + 6 * nb))
    for c in range(G + 6 * nb):
        dg, dp = np.zeros(G), np.zeros((nb, 6))
        if c < G:
            dg[c] = eps
        else:
            dp.reshape(-1)[c - G] = eps
        fd[:, c] = (res(dg, dp) - res(-dg, -dp)) / (2 * eps)
    analytic = np.concatenate([J[:, :G], J[:, G + 1 :]], axis=1)
    scale = np.abs(fd).max()
    assert np.abs(analytic - fd).max() < 1e-6 * scale
    # the cone's six and the plane's three columns are reached
    lay = truth.rig.layout
    assert np.abs(fd[:, lay.elements[1]]).max(axis=0).min() > 0
    assert np.abs(fd[:, lay.elements[2]]).max(axis=0).min() > 0


@pytest.mark.slow
@pytest.mark.parametrize("kinds", [("cone", "point", "point", "point"), ("plane", "plane", "plane")])
def test_exact_observations_give_the_true_sheets(kinds):
    sc = scene(kinds)
    obs, truth = simulate(sc, 0.0)
    res = sj.calibrate(obs)
    x_ref = sheet_working_points(truth.rig, res.params.poses, res.packed)
    pos, normal, angle = sheet_errors(res.rig, truth.rig, x_ref)
    assert pos.max() < 1e-5 and normal.max() < 1e-7 and angle.max() < 1e-7, (pos, normal, angle)
    assert res.rig.kinds == truth.rig.kinds
    # the report's lasers follow the file's order, by kind
    doc = calibration_to_json(to_calibration(res))
    assert [las.get("kind", "point") for las in doc["lasers"]] == list(kinds)
    assert [las["kind"] for las in doc["uncertainty"]["lasers"]] == list(kinds)
    assert doc["residuals"]["by_kind_rms_px"]["stripe"] < 1e-6


@pytest.mark.slow
def test_a_stored_calibration_with_sheets_gives_back_its_covariance_and_report(tmp_path):
    sc = scene(("point", "cone", "point", "plane"), n_views=5)
    obs, _ = simulate(sc, 0.3, seed=2)
    res = sj.calibrate(obs)
    write_calibration(tmp_path / "cal.json", to_calibration(res))
    back = load_result(tmp_path / "cal.json")
    np.testing.assert_allclose(np.asarray(back.cov.glob), np.asarray(res.cov.glob), rtol=1e-9, atol=0)
    assert json.dumps(sj.report(back), sort_keys=True, default=float) == json.dumps(
        sj.report(res), sort_keys=True, default=float
    )


def test_plane_and_cone_lasers_round_trip_through_the_calibration_file():
    rig, _ = sheet_rig(paper_rig(), ("plane", "point", "cone"))
    doc = calibration_to_json(sj.Calibration(rig, []))
    assert doc["lasers"][0]["kind"] == "plane" and "kind" not in doc["lasers"][1]
    assert doc["lasers"][2]["kind"] == "cone"
    back = calibration_from_json(json.loads(json.dumps(doc)), "cal.json").rig
    assert back.kinds == rig.kinds
    np.testing.assert_allclose(np.asarray(back.sheets.apex), np.asarray(rig.sheets.apex))
    np.testing.assert_allclose(np.asarray(back.sheets.half_angle), np.asarray(rig.sheets.half_angle), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(back.lasers.points), np.asarray(rig.lasers.points))


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d["lasers"][2].update(half_angle_deg=180.0), r"lasers\[2\].half_angle_deg: must lie strictly"),
        (lambda d: d["lasers"][0].update(kind="line"), r"lasers\[0\].kind: expected one of point, plane, cone"),
        (lambda d: d["lasers"][0].update(normal=[0, 0, 0]), r"lasers\[0\].normal: zero vector"),
        (lambda d: d["lasers"][2].pop("apex"), r"lasers\[2\].apex: missing"),
    ],
)
def test_bad_sheets_in_a_calibration_file_are_named(edit, message):
    rig, _ = sheet_rig(paper_rig(), ("plane", "point", "cone"))
    doc = json.loads(json.dumps(calibration_to_json(sj.Calibration(rig, []))))
    edit(doc)
    with pytest.raises(FormatError, match=message):
        calibration_from_json(doc, "cal.json")


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d.update(laser_kinds=["cone"]), r"laser_kinds: expected 3 kinds"),
        (lambda d: d.update(laser_kinds=["cone", "disc", "point"]), r"laser_kinds\[1\]: expected one of"),
        (lambda d: d["views"][0]["stripes"][0].update(laser=2), r"views\[0\].stripes\[0\].laser: laser 2 is a point"),
        (lambda d: d["views"][0]["stripes"][0]["pixels"].append([1.0]), r"views\[0\].stripes\[0\].pixels\[\d+\]"),
        (
            lambda d: d["views"][0]["spots"].append({"laser": 0, "pixel": [1, 2]}),
            r"spots\[\d+\].laser: laser 0 is a cone",
        ),
    ],
)
def test_bad_stripes_in_observations_are_named(edit, message):
    sc = scene(("cone", "point", "point"), n_views=1, step=10.0, n_chess=1)
    obs, _ = simulate(sc, 0.0)
    doc = json.loads(json.dumps(observations_to_json(obs)))
    assert doc["laser_kinds"] == ["cone", "point", "point"] and doc["views"][0]["stripes"]
    observations_from_json(json.loads(json.dumps(doc)), "obs.json")  # as written: valid
    edit(doc)
    with pytest.raises(FormatError, match=message):
        observations_from_json(doc, "obs.json")
