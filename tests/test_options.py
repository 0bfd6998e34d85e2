"""Calibration options as data: one frozen object for the API, the CLI and the calibration file."""

import copy
import json

import numpy as np
import pytest

import slcvjax as sj
from slcvjax.calibration.options import CalibrationOptions, RobustPolicy, merged_options
from slcvjax.observations.formats import FormatError
from slcvjax.observations.simulate import make_scene


def test_json_round_trip_and_defaults():
    opt = CalibrationOptions(
        robust=RobustPolicy(loss="cauchy", outlier_sigmas=4.0, consensus_px=6.0),
        max_steps=300,
        rigid=("wall0", "wall1"),
    )
    again = CalibrationOptions.from_json(json.loads(json.dumps(opt.to_json())), "opt.json")
    assert again == opt
    assert CalibrationOptions.from_json({}, "empty.json") == CalibrationOptions()
    # the keyword arguments of calibrate() that are given replace the options' fields
    merged = merged_options(opt, loss="linear", freeze={"lasers"})
    assert merged.robust.loss == "linear" and merged.freeze == ("lasers",) and merged.robust.outlier_sigmas == 4.0
    assert merged_options(None) is merged_options(None)  # no copies of the defaults


@pytest.mark.parametrize(
    "doc, field",
    [
        ({"max_step": 3}, "max_step: unknown option"),
        ({"robust": {"outlier_sigma": 3}}, "robust.outlier_sigma: unknown option"),
        ({"robust": {"loss": "l1"}}, "robust.loss"),
        ({"robust": {"outlier_sigmas": -1}}, "robust.outlier_sigmas"),
        ({"robust": {"min_board_dots": 2.5}}, "robust.min_board_dots"),
        ({"robust": {"loss_scale": 0}}, "robust.loss_scale"),
        ({"freeze": ["camera", "lens"]}, "freeze: unknown block 'lens'"),
        ({"freeze": "camera"}, "freeze"),
        ({"max_steps": 0}, "max_steps"),
        ({"rigid": "yes"}, "rigid"),
        ({"projection_test_level": 1.5}, "projection_test_level"),
        ([1, 2], "expected an object"),
    ],
)
def test_bad_options_are_refused_by_field(doc, field):
    with pytest.raises(FormatError, match="opt.json: .*" + field.replace(".", r"\.").replace("(", r"\(")):
        CalibrationOptions.from_json(doc, "opt.json")


@pytest.fixture(scope="module")
def moved_dot():
    """A 3-laser 6-view scene at 0.3 px with one dot moved 3 px (10 noise sigmas)."""
    obs, _ = sj.simulate(make_scene("paper", n_lasers=3, n_views=6), noise=0.3, seed=4)
    obs = copy.deepcopy(obs)
    view = obs.views[3]
    board = sorted(view.boards)[0]
    j = int(np.flatnonzero(view.boards[board][1])[0])
    view.boards[board][0][j] += np.array([3.0, 0.0])
    return obs, (view.name, board, j)


def _left_out(res, key):
    return [r for r in res.repairs if r.kind == "dot" and (r.view, r.board, r.index) == key]


def test_the_outlier_threshold_is_the_policys(moved_dot):
    obs, key = moved_dot
    strict = sj.calibrate(obs)  # 5 sigma: the 3 px dot is a gross outlier
    assert _left_out(strict, key) and strict.options == CalibrationOptions()
    lax = sj.calibrate(obs, options=CalibrationOptions(robust=RobustPolicy(outlier_sigmas=30.0)))
    assert not _left_out(lax, key) and lax.options.robust.outlier_sigmas == 30.0
    # the report's outliers use the same threshold: at 30 sigmas, nothing is an outlier
    assert sj.report(lax)["residuals"]["outliers"] == []


def test_the_cli_reads_an_options_file_and_the_calibration_keeps_it(moved_dot, tmp_path):
    from slcvjax.cli import main

    obs, key = moved_dot
    sj.write_observations(tmp_path / "obs.json", obs)
    (tmp_path / "opt.json").write_text(json.dumps({"robust": {"outlier_sigmas": 30.0}, "max_steps": 400}))
    out = tmp_path / "cal.json"
    assert (
        main(["calibrate", str(tmp_path / "obs.json"), "--options", str(tmp_path / "opt.json"), "--out", str(out)]) == 0
    )
    doc = json.loads(out.read_text())
    kept = CalibrationOptions.from_json(doc["problem"]["options"], "cal.json")
    assert kept.robust.outlier_sigmas == 30.0 and kept.max_steps == 400
    assert sj.load_result(out).options == kept
    assert not [r for r in doc["residuals"]["repairs"] if (r["view"], r.get("board"), r["index"]) == key]
    # a bad options file: one line naming the file and the field, exit 2
    (tmp_path / "bad.json").write_text(json.dumps({"robust": {"outlier_sigma": 3}}))
    bad = ["calibrate", str(tmp_path / "obs.json"), "--options", str(tmp_path / "bad.json"), "--out", str(out)]
    assert main(bad) == 2
