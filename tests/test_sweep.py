"""Noise sweeps: the document, its files, exactness at zero noise and the bound at non-zero noise."""

import csv
import json

import numpy as np
import pytest

from slcvjax.calibration.bound import cramer_rao, laser_std
from slcvjax.cli import main
from slcvjax.experiments.sweep import COMPONENTS, laser_component_std, run_sweep, write_sweep
from slcvjax.observations.simulate import make_scene, simulate


@pytest.fixture(scope="module")
def sweep():
    # test_calibrate's sizes: the calibration's compilation is shared (persistent cache)
    return run_sweep("paper", noise=(0.0, 0.5), trials=2, seed=3, n_lasers=4, n_views=5)


@pytest.mark.slow
def test_sweep_document(sweep):
    assert sweep["format"] == "slcv-sweep/1"
    assert sweep["noise"] == [0.0, 0.5] and sweep["trials"] == 2
    for m in ("staged", "joint", "bound"):
        block = sweep["methods"][m]
        assert len(block["position_rms_mm"]) == 2 and len(block["direction_rms_deg"]) == 2
        for c in COMPONENTS:
            assert np.shape(block["per_laser"][c]) == (4, 2)
    assert sweep["converged"] == 4


@pytest.mark.slow
def test_sweep_is_exact_at_zero_noise_and_near_the_bound_at_half_a_pixel(sweep):
    joint, bound = sweep["methods"]["joint"], sweep["methods"]["bound"]
    assert joint["position_rms_mm"][0] < 1e-6 and joint["direction_rms_deg"][0] < 1e-6
    assert bound["position_rms_mm"][0] == 0.0
    # 2 trials x 4 lasers: the joint solve is within 1.1x of the bound on average (benchmarks/accuracy.py)
    assert joint["position_rms_mm"][1] < 2.0 * bound["position_rms_mm"][1]
    assert joint["direction_rms_deg"][1] < 2.0 * bound["direction_rms_deg"][1]
    assert joint["position_rms_mm"][1] > 0.3 * bound["position_rms_mm"][1]
    # the staged start is far worse than the joint solve
    assert sweep["methods"]["staged"]["position_rms_mm"][1] > 2.0 * joint["position_rms_mm"][1]


@pytest.mark.slow
def test_component_std_agrees_with_the_position_and_direction_std():
    obs, truth = simulate(make_scene("paper"))
    b = cramer_rao(truth, obs, 0.5)
    comp = laser_component_std(truth.rig, np.asarray(b["cov"].glob), b["x_ref"])
    pos, ang = laser_std(truth.rig, np.asarray(b["cov"].glob), b["x_ref"])
    np.testing.assert_allclose(np.linalg.norm(comp[:, :3], axis=1), pos, rtol=1e-9)
    # a unit direction's component variances add up to the two tilt variances
    np.testing.assert_allclose(np.linalg.norm(comp[:, 3:], axis=1), ang, rtol=1e-9)


@pytest.mark.slow
def test_sweep_files(sweep, tmp_path):
    paths = write_sweep(sweep, tmp_path)
    assert [p.name for p in paths] == ["sweep.json", "sweep.csv", "sweep.png"]
    assert json.loads((tmp_path / "sweep.json").read_text())["format"] == "slcv-sweep/1"
    with (tmp_path / "sweep.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 3 * 2 * 4
    j = [r for r in rows if r["method"] == "joint" and r["noise_px"] == "0.5" and r["laser"] == "3"][0]
    assert float(j["x0_rms"]) == pytest.approx(sweep["methods"]["joint"]["per_laser"]["x0"][3][1], rel=1e-5)
    assert (tmp_path / "sweep.png").stat().st_size > 10_000


def test_sweep_command_rejects_bad_levels(tmp_path, capsys):
    assert main(["sweep", "--noise", "0,abc", "--out", str(tmp_path / "s")]) == 2
    assert "--noise" in capsys.readouterr().err
    assert main(["sweep", "--noise", "0,-1", "--out", str(tmp_path / "s")]) == 2
    assert not (tmp_path / "s").exists()
