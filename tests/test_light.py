"""The detector's light settings (slcvjax.images.light): lasers of another colour, or a monochrome
camera, found where the red lasers of the same scene are."""

import json

import cv2
import numpy as np
import pytest

from slcvjax.images.detect import detect_catadioptric, read_setup
from slcvjax.images.light import DetectionSettings
from slcvjax.images.render import RenderOptions, render_scene
from slcvjax.observations.formats import FormatError
from slcvjax.observations.simulate import make_scene, simulate


@pytest.fixture(scope="module")
def views(tmp_path_factory):
    scene = make_scene("paper", n_lasers=4, n_views=3)
    folder = tmp_path_factory.mktemp("light") / "images"
    render_scene(scene, folder, RenderOptions(noise=1.0, seed=2))
    exact, _ = simulate(scene)
    images = [cv2.imread(str(folder / f"view{i:02d}.png")) for i in range(3)]
    return folder, exact, images


def _spots(bgr, color="red", threshold=None):
    return detect_catadioptric(bgr, light=DetectionSettings(color, threshold)).spots


@pytest.mark.parametrize("color, swap", [("green", (2, 1)), ("blue", (2, 0))])
def test_a_green_or_blue_laser_is_found_as_the_red_one(views, color, swap):
    """The same image with the laser's channel swapped into green (or blue): the spots and the
    dots come out exactly as the red image's (the walls are grey: a swap changes nothing else)."""
    _, _, images = views
    for bgr in images:
        other = bgr.copy()
        other[:, :, list(swap)] = bgr[:, :, list(swap[::-1])]
        red, col = detect_catadioptric(bgr), detect_catadioptric(other, light=DetectionSettings(color))
        assert len(red.spots) > 0
        np.testing.assert_array_equal(col.spots, red.spots)
        np.testing.assert_array_equal(col.dots, red.dots)


def test_a_monochrome_camera_finds_the_spots_as_the_brightest_blobs(views):
    """The grey image (a monochrome camera): every spot the red detector finds is found within
    0.5 px of the exact projection, and no blob is taken for a spot elsewhere."""
    _, exact, images = views
    for bgr, truth in zip(images, exact.views, strict=True):
        grey = cv2.cvtColor(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), cv2.COLOR_GRAY2BGR)
        found = _spots(grey, "brightest")  # its default threshold
        true = np.array([s.pixel for s in truth.spots])
        d = np.linalg.norm(found[:, None] - true[None], axis=2).min(axis=1)
        assert np.all(d < 0.5), d
        assert len(found) >= len(_spots(bgr))


def test_the_setup_names_the_light_and_refuses_a_bad_one(views, tmp_path):
    folder, _, _ = views
    doc = json.loads((folder / "setup.json").read_text())
    doc["detection"] = {"laser_color": "green", "spot_threshold": 12}
    path = tmp_path / "setup.json"
    path.write_text(json.dumps(doc))
    assert read_setup(path).light == DetectionSettings("green", 12.0)
    doc["detection"] = {"laser_color": "purple"}
    path.write_text(json.dumps(doc))
    with pytest.raises(FormatError, match="detection.laser_color"):
        read_setup(path)
    doc["detection"] = {"spot_threshold": 300}
    path.write_text(json.dumps(doc))
    with pytest.raises(FormatError, match="detection.spot_threshold"):
        read_setup(path)
