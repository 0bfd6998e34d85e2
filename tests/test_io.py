import copy
import json

import numpy as np
import pytest

import slcvjax as sj
from slcvjax.observations.formats import (
    FormatError,
    calibration_to_json,
    observations_to_json,
    read_calibration,
    read_observations,
    write_calibration,
    write_observations,
)
from slcvjax.observations.simulate import make_scene, simulate


@pytest.fixture(scope="module")
def small():
    scene = make_scene("paper", n_lasers=4, n_views=2)
    return simulate(scene, noise=0.3, seed=1)


def test_observations_roundtrip(tmp_path, small):
    obs, _ = small
    path = tmp_path / "obs.json"
    write_observations(path, obs)
    back = read_observations(path)
    assert observations_to_json(back) == observations_to_json(obs)
    assert back.n_lasers == 4 and len(back.views) == 2
    assert json.loads(path.read_text())["format"] == "slcv-observations/1"


def test_calibration_roundtrip(tmp_path, small):
    _, truth = small
    path = tmp_path / "cal.json"
    write_calibration(path, truth)
    back = read_calibration(path)
    a, b = calibration_to_json(back), calibration_to_json(truth)
    assert a.keys() == b.keys()
    np.testing.assert_allclose(a["camera"]["K"], b["camera"]["K"], rtol=1e-15)
    np.testing.assert_allclose(a["mirror"]["axis"], b["mirror"]["axis"], rtol=1e-15)
    np.testing.assert_allclose([x["direction"] for x in a["lasers"]], [x["direction"] for x in b["lasers"]], rtol=1e-15)
    np.testing.assert_allclose(a["board_poses"][1]["wall2"]["R"], b["board_poses"][1]["wall2"]["R"], atol=1e-15)
    assert len(back.calibration_view_poses) == len(truth.calibration_view_poses)


def test_a_camera_only_calibration_roundtrip(tmp_path, small):
    """A plain camera's calibration (no mirror, no lasers) is written and read back as such."""
    _, truth = small
    rig = sj.Rig.camera_only(truth.rig.camera)
    assert rig.mirror is None and rig.lasers.n == 0
    path = tmp_path / "camera.json"
    write_calibration(path, sj.Calibration(rig))
    doc = json.loads(path.read_text())
    assert "mirror" not in doc and doc.get("lasers", []) == []
    back = read_calibration(path)
    assert back.rig.mirror is None and back.rig.lasers.n == 0
    np.testing.assert_allclose(back.rig.camera.K, truth.rig.camera.K, rtol=1e-15)
    np.testing.assert_allclose(back.rig.camera.dist, truth.rig.camera.dist, rtol=1e-15)


def test_extra_fields_are_kept_and_ignored(tmp_path, small):
    obs, _ = small
    doc = observations_to_json(obs)
    doc["made_by"] = {"tool": "someone else's detector"}
    doc["views"][0]["exposure_ms"] = 3.0
    path = tmp_path / "obs.json"
    path.write_text(json.dumps(doc))
    back = read_observations(path)
    assert back.extra["made_by"]["tool"] == "someone else's detector"


def _mutations():
    """(description, mutate(doc), expected substrings of the one-line error)."""

    def setp(path, value):
        def f(doc):
            d = doc
            for k in path[:-1]:
                d = d[k]
            d[path[-1]] = value

        return f

    def delp(path):
        def f(doc):
            d = doc
            for k in path[:-1]:
                d = d[k]
            del d[path[-1]]

        return f

    return [
        ("wrong format", setp(["format"], "slcv-observations/9"), ["format", "slcv-observations/1"]),
        (
            "non-finite",
            setp(["views", 1, "boards", "wall2", 4], [float("nan"), 3.0]),
            ["views[1].boards.wall2[4][0]", "non-finite"],
        ),
        (
            "wrong shape",
            setp(["views", 0, "spots", 1, "pixel"], [1.0, 2.0, 3.0]),
            ["views[0].spots[1].pixel", "2 numbers"],
        ),
        ("laser out of range", setp(["views", 0, "spots", 2, "laser"], 12), ["views[0].spots[2].laser", "12"]),
        ("unknown board", setp(["views", 1, "spots", 0, "board"], "ceiling"), ["views[1].spots[0].board", "ceiling"]),
        ("count mismatch", lambda d: d["views"][0]["boards"]["wall1"].pop(), ["views[0].boards.wall1", "8 pixels"]),
        ("non-positive mirror", setp(["mirror_shape", "radius"], 0.0), ["mirror_shape.radius", "positive"]),
        ("negative height", setp(["mirror_shape", "height"], -3), ["mirror_shape.height", "positive"]),
        ("no views key", delp(["views"]), ["views", "missing"]),
        ("board z", setp(["boards", "wall0", "points", 3, 2], 1.0), ["boards.wall0.points[3][2]", "z = 0"]),
        ("calib board", setp(["calibration_views", 2, "board"], "nope"), ["calibration_views[2].board", "nope"]),
        ("image size", setp(["image_size"], [640]), ["image_size"]),
        ("rim point", setp(["views", 1, "rim", 5], "x"), ["views[1].rim[5]"]),
    ]


@pytest.mark.parametrize("case", _mutations(), ids=lambda c: c[0])
def test_bad_observations_name_file_field_and_index(tmp_path, small, case):
    _, mutate, expected = case
    doc = copy.deepcopy(observations_to_json(small[0]))
    mutate(doc)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(FormatError) as e:
        read_observations(path)
    msg = str(e.value)
    assert "\n" not in msg
    assert msg.startswith(str(path))
    for s in expected:
        assert s in msg, msg


def test_truncated_and_missing_files(tmp_path, small):
    path = tmp_path / "obs.json"
    write_observations(path, small[0])
    text = path.read_text()
    path.write_text(text[: len(text) // 2])
    with pytest.raises(FormatError, match="not valid JSON"):
        read_observations(path)
    with pytest.raises(FormatError, match="no such file"):
        read_observations(tmp_path / "absent.json")


def test_bad_calibration_files(tmp_path, small):
    doc = calibration_to_json(small[1])
    for mutate, expected in [
        (lambda d: d.update(format="slcv-observations/1"), "format"),
        (lambda d: d["mirror"].update(axis=[0, 0, 0]), "mirror.axis"),
        (lambda d: d["lasers"][1].update(direction=[1, 2]), "lasers[1].direction"),
        (lambda d: d["board_poses"][0]["wall1"].update(R=[[1, 0, 0], [0, 1, 0], [0, 0, 2]]), "board_poses[0].wall1.R"),
        (lambda d: d["camera"].update(dist=[0, 0, 0, 0, float("inf")]), "camera.dist[4]"),
    ]:
        d = copy.deepcopy(doc)
        mutate(d)
        path = tmp_path / "cal.json"
        path.write_text(json.dumps(d))
        with pytest.raises(FormatError, match=expected.replace("[", r"\[").replace("]", r"\]")):
            read_calibration(path)


def test_atomic_write_leaves_nothing_on_failure(tmp_path, small):
    _, truth = small
    bad = truth.rig.with_lasers(sj.Lasers.create([[np.nan, 0, 0]], [[1.0, 0, 0]]))
    path = tmp_path / "out.json"
    with pytest.raises(ValueError):
        write_calibration(path, sj.observations.formats.Calibration(bad))
    assert list(tmp_path.iterdir()) == []
