"""``slcvjax diff``: two calibrations of one simulated rig from different noise differ by about what
their covariances predict; a perturbed camera shows."""

import json

import pytest

import slcvjax as sj
from slcvjax.experiments.diff import diff_maps
from slcvjax_cli import main


@pytest.fixture(scope="module")
def two(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("diff")
    scene = sj.make_scene("paper", n_lasers=3, n_views=5)
    paths = []
    for seed in (1, 2):
        obs, _ = sj.simulate(scene, noise=0.5, seed=seed)
        path = tmp / f"cal{seed}.json"
        sj.write_calibration(path, sj.to_calibration(sj.calibrate(obs)))
        paths.append(path)
    return tmp, paths


@pytest.mark.slow
def test_two_noisy_calibrations_differ_as_predicted(two, capsys):
    tmp, (a, b) = two
    out = diff_maps(a, b, range_mm=150.0)
    s = out["summary"]
    assert s["pixels"] > 500
    # of the order of the prediction: the ratio's median near 1 (the distance of two 3D Gaussians
    # has a median about 0.9 of its RMS), and mostly under mrcal's 2
    assert 0.3 < s["ratio"]["median"] < 2.0
    assert s["share_above_2"] < 0.3
    png = tmp / "diff.png"
    assert main(["diff", str(a), str(b), "--range", "150", "--out", str(png)]) == 0
    assert png.stat().st_size > 1000
    assert "consistent" in capsys.readouterr().out


@pytest.mark.slow
def test_a_perturbed_camera_shows(two, capsys):
    tmp, (a, _) = two
    doc = json.loads(a.read_text())
    shift = 10 * doc["uncertainty"]["camera_std"]["cx"]  # cx by 10 times its std (some 30 px in this small rig)
    doc["camera"]["K"][0][2] += shift
    moved = tmp / "moved.json"
    moved.write_text(json.dumps(doc))
    out = diff_maps(a, moved, range_mm=150.0)
    assert out["summary"]["ratio"]["median"] > 3.0
    same = diff_maps(a, a, range_mm=150.0)
    assert same["summary"]["diff_mm"]["max"] == 0.0
    assert main(["diff", str(a), str(moved)]) == 0
    assert "more than their noise predicts" in capsys.readouterr().out


def test_diff_refuses_a_camera_only_calibration(tmp_path, capsys):
    cam = tmp_path / "cam.json"
    sj.write_calibration(cam, sj.Calibration(sj.Rig.camera_only(sj.paper_rig(1).camera)))
    assert main(["diff", str(cam), str(cam)]) == 2
    assert "cam.json: mirror: a camera-only calibration" in capsys.readouterr().err
