"""Board types (``slcvjax.observations.targets``): the generated points against OpenCV and closed
forms, and the readers' refusals (file, field and index named)."""

import copy
import json

import cv2
import numpy as np
import pytest

from slcvjax.images.detect import read_setup, setup_to_json
from slcvjax.observations.formats import FormatError, observations_to_json, read_observations, write_observations
from slcvjax.observations.targets import (
    DICTIONARIES,
    aprilgrid_points,
    aprilgrid_tag_corners,
    charuco_marker_squares,
    charuco_points,
    chessboard_points,
    marker_ids,
)

CHARUCO = {
    "type": "charuco",
    "dictionary": "DICT_4X4_250",
    "squares": [7, 5],
    "square_mm": 20.0,
    "marker_mm": 15.0,
    "first_marker_id": 17,
}
APRILGRID = {"type": "aprilgrid", "tag_cols": 3, "tag_rows": 2, "tag_mm": 20.0, "spacing": 0.3}


def _opencv_board(squares, square, marker, dictionary, first):
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    return cv2.aruco.CharucoBoard(tuple(squares), square, marker, d, first + np.arange(squares[0] * squares[1] // 2))


# squares of sizes a float32 holds exactly: OpenCV's corners (float32) then equal the closed form
@pytest.mark.parametrize(
    "squares, square, marker, first",
    [
        ((7, 5), 20.0, 15.0, 0),
        ((5, 7), 12.5, 9.0, 40),
        ((6, 4), 30.0, 22.5, 3),
        ((2, 2), 8.0, 6.0, 0),
        ((9, 6), 0.75, 0.5, 100),
    ],
)
def test_charuco_points_and_ids_are_opencvs(squares, square, marker, first):
    board = _opencv_board(squares, square, marker, "DICT_4X4_250", first)
    ours = charuco_points(squares, square)
    theirs = np.asarray(board.getChessboardCorners(), dtype=np.float64)
    assert ours.dtype == np.float64 and ours.shape == theirs.shape == ((squares[0] - 1) * (squares[1] - 1), 3)
    np.testing.assert_array_less(np.abs(ours - theirs), 1e-12)
    spec = {"type": "charuco", "squares": list(squares), "first_marker_id": first}
    np.testing.assert_array_equal(marker_ids(spec), np.asarray(board.getIds()).ravel())
    # each marker (in id order) sits in the square charuco_marker_squares names, centred
    corners = np.asarray(board.getObjPoints(), dtype=np.float64)  # (markers, 4, 3) in id order
    centres = corners.mean(axis=1)[:, :2]
    np.testing.assert_allclose(centres, (charuco_marker_squares(squares) + 0.5) * square, atol=1e-5 * square)
    np.testing.assert_allclose(corners[:, 1, 0] - corners[:, 0, 0], marker, rtol=1e-6)


def test_charuco_points_of_any_size_agree_to_opencvs_float32():
    board = _opencv_board((8, 3), 18.3, 13.1, "DICT_5X5_100", 0)
    theirs = np.asarray(board.getChessboardCorners(), dtype=np.float64)
    np.testing.assert_allclose(charuco_points((8, 3), 18.3), theirs, rtol=1e-7, atol=0)


def test_the_dictionary_table_is_opencvs():
    for name, (bits, n) in DICTIONARIES.items():
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
        assert (d.markerSize, len(d.bytesList)) == (bits, n), name


def test_chessboard_points_closed_form():
    pts = chessboard_points(4, 3, 25.0)
    assert pts.shape == (12, 3) and pts.dtype == np.float64
    for j in range(3):
        for i in range(4):
            assert pts[i + 4 * j].tolist() == [25.0 * i, 25.0 * j, 0.0]


def test_aprilgrid_points_are_kalibrs():
    """Kalibr's ``createGridPoints`` written out, and a hand-computed example."""
    cols, rows, tag, spacing = 3, 2, 20.0, 0.3
    pts = aprilgrid_points(cols, rows, tag, spacing)
    assert pts.shape == (4 * cols * rows, 3) and pts.dtype == np.float64
    for r in range(2 * rows):
        for c in range(2 * cols):
            x = int(c / 2) * (1 + spacing) * tag + (c % 2) * tag
            y = int(r / 2) * (1 + spacing) * tag + (r % 2) * tag
            np.testing.assert_allclose(pts[r * 2 * cols + c], [x, y, 0.0], atol=1e-12)
    # the first rows of points: tags 0, 1, 2 along x at a pitch of 26 mm, then their tops at y = 20
    np.testing.assert_allclose(pts[:6, 0], [0, 20, 26, 46, 52, 72], atol=1e-12)
    np.testing.assert_allclose(pts[6:12, 1], 20.0, atol=1e-12)
    np.testing.assert_allclose(pts[12:18, 1], 26.0, atol=1e-12)
    # each tag's corners (bottom-left, bottom-right, top-right, top-left) bound a tag_mm square
    idx = aprilgrid_tag_corners(cols, rows)
    assert idx.shape == (6, 4) and sorted(idx.ravel().tolist()) == list(range(24))
    for t in range(cols * rows):
        q = pts[idx[t], :2]
        origin = np.array([t % cols, t // cols]) * (1 + spacing) * tag
        np.testing.assert_allclose(q, origin + tag * np.array([[0, 0], [1, 0], [1, 1], [0, 1]]), atol=1e-12)
    # Kalibr's pIdx for tag 4 of a 3-column grid (baseId = (4 // 3) * 12 + (4 % 3) * 2 = 14)
    assert idx[4].tolist() == [14, 15, 21, 20]


# --------------------------------------------------------------------------- the readers


def _observations(boards: dict) -> dict:
    return {
        "format": "slcv-observations/1",
        "units": "mm",
        "image_size": [640, 480],
        "mirror_shape": {"kind": "cone", "radius": 20.0, "height": 10.0},
        "n_lasers": 1,
        "boards": boards,
        "calibration_views": [],
        "views": [],
    }


def _write(tmp_path, doc, name="obs.json"):
    path = tmp_path / name
    path.write_text(json.dumps(doc))
    return path


def test_typed_boards_are_read_generated_and_written_back(tmp_path):
    boards = {"c": dict(CHARUCO), "a": dict(APRILGRID), "k": {"type": "chessboard", "inner": [4, 3], "square_mm": 25}}
    obs = read_observations(_write(tmp_path, _observations(boards)))
    np.testing.assert_array_equal(obs.boards["c"], charuco_points((7, 5), 20.0))
    np.testing.assert_array_equal(obs.boards["a"], aprilgrid_points(3, 2, 20.0, 0.3))
    np.testing.assert_array_equal(obs.boards["k"], chessboard_points(4, 3, 25.0))
    assert obs.board_types["a"]["first_marker_id"] == 0 and obs.board_types["c"]["first_marker_id"] == 17
    path = tmp_path / "back.json"
    write_observations(path, obs)
    doc = json.loads(path.read_text())
    assert doc["boards"]["c"]["type"] == "charuco" and doc["boards"]["c"]["squares"] == [7, 5]
    back = read_observations(path)  # the written points agree with the type
    assert observations_to_json(back) == observations_to_json(obs)


def test_given_points_that_agree_are_accepted(tmp_path):
    board = dict(CHARUCO, points=(charuco_points((7, 5), 20.0) + 4e-10).tolist())
    read_observations(_write(tmp_path, _observations({"wall0": board})))


@pytest.mark.parametrize(
    "mutate, field, message",
    [
        (lambda b: b["points"][3].__setitem__(0, b["points"][3][0] + 2e-9), r"boards\.wall0\.points\[3\]", "off by"),
        (lambda b: b["points"].pop(), r"boards\.wall0\.points", "23 points, but its charuco has 24"),
        (lambda b: b.__setitem__("type", "checker"), r"boards\.wall0\.type", "unknown board type 'checker'"),
        (lambda b: b.__setitem__("dictionary", "DICT_4X4_25"), r"boards\.wall0\.dictionary", "unknown dictionary"),
        (lambda b: b.__setitem__("marker_mm", 20.0), r"boards\.wall0\.marker_mm", "smaller than the square"),
        (lambda b: b.__setitem__("squares", [7]), r"boards\.wall0\.squares", "expected \\[columns, rows\\]"),
        (lambda b: b["squares"].__setitem__(1, 1), r"boards\.wall0\.squares\[1\]", "minimum 2"),
        (lambda b: b.__setitem__("square_mm", float("nan")), r"boards\.wall0\.square_mm", "non-finite"),
        (lambda b: b.__setitem__("first_marker_id", 240), r"boards\.wall0\.first_marker_id", "240..256"),
        (lambda b: b.__setitem__("first_marker_id", -1), r"boards\.wall0\.first_marker_id", "minimum 0"),
    ],
)
def test_bad_charuco_boards_are_named(tmp_path, mutate, field, message):
    board = dict(CHARUCO, squares=[7, 5], points=charuco_points((7, 5), 20.0).tolist())
    mutate(board)
    path = _write(tmp_path, _observations({"wall0": board}))
    with pytest.raises(FormatError, match=rf"obs\.json: {field}: .*{message}"):
        read_observations(path)


@pytest.mark.parametrize(
    "mutate, field, message",
    [
        (lambda b: b.__setitem__("spacing", 1.5), "spacing", r"\(0, 1\]"),
        (lambda b: b.__setitem__("family", "tag25h9"), "family", "tag36h11"),
        (lambda b: b.__setitem__("tag_cols", 0), "tag_cols", "minimum 1"),
        (lambda b: b.__setitem__("first_marker_id", 582), "first_marker_id", "exceed DICT_APRILTAG_36h11's 587"),
        (lambda b: b.pop("tag_mm"), "tag_mm", "missing"),
    ],
)
def test_bad_aprilgrids_are_named(tmp_path, mutate, field, message):
    board = copy.deepcopy(APRILGRID)
    mutate(board)
    with pytest.raises(FormatError, match=rf"boards\.g\.{field}: .*{message}"):
        read_observations(_write(tmp_path, _observations({"g": board})))


def test_a_dots_board_still_needs_its_points(tmp_path):
    with pytest.raises(FormatError, match=r"boards\.d\.points: missing"):
        read_observations(_write(tmp_path, _observations({"d": {"type": "dots"}})))


def test_overlapping_marker_ids_are_refused_naming_both_boards(tmp_path):
    a = dict(CHARUCO, first_marker_id=0)  # ids 0..16
    b = dict(CHARUCO, first_marker_id=16)  # ids 16..32: id 16 is on both
    with pytest.raises(
        FormatError, match=r"boards\.wall1\.first_marker_id: boards 'wall0' and 'wall1' share 1 .*\(16\)"
    ):
        read_observations(_write(tmp_path, _observations({"wall0": a, "wall1": b})))
    # other dictionaries, or a disjoint range, are fine
    read_observations(_write(tmp_path, _observations({"wall0": a, "wall1": dict(b, first_marker_id=17)})))
    read_observations(_write(tmp_path, _observations({"wall0": a, "wall1": dict(b, dictionary="DICT_5X5_250")})))
    # an aprilgrid and a charuco of tag36h11 share one id space
    c = dict(CHARUCO, dictionary="DICT_APRILTAG_36h11", first_marker_id=5)
    with pytest.raises(FormatError, match=r"boards 'g' and 'c' share 1 DICT_APRILTAG_36h11 marker id\(s\) \(5\)"):
        read_observations(_write(tmp_path, _observations({"g": dict(APRILGRID), "c": c})))


def _setup(boards: dict) -> dict:
    return {
        "format": "slcv-setup/1",
        "image_size": [640, 480],
        "mirror_shape": {"kind": "cone", "radius": 20.0, "height": 10.0},
        "n_lasers": 2,
        "laser_azimuth_deg": None,
        "boards": boards,
        "views": [],
        "chessboard_views": [],
    }


def test_read_setup_takes_typed_boards(tmp_path):
    boards = {
        "wall0": dict(CHARUCO, azimuth_deg=0.0, x_dir=1, y_dir=-1),
        "wall1": dict(APRILGRID, azimuth_deg=90.0, first_marker_id=100),
        "chess": {"type": "chessboard", "inner": [9, 6], "square_mm": 20.0},
    }
    path = _write(tmp_path, _setup(boards), "setup.json")
    setup = read_setup(path)
    w0, w1, ch = setup.boards["wall0"], setup.boards["wall1"], setup.boards["chess"]
    assert (w0.cols, w0.rows, w0.target["type"]) == (6, 4, "charuco")
    assert (w1.cols, w1.rows) == (6, 4) and len(w1.points) == 24
    np.testing.assert_array_equal(ch.points, chessboard_points(9, 6, 20.0))
    # written back and read again: the same boards
    path2 = _write(tmp_path, setup_to_json(setup), "setup2.json")
    again = read_setup(path2)
    for k in boards:
        np.testing.assert_array_equal(again.boards[k].points, setup.boards[k].points)
        assert again.boards[k].target == setup.boards[k].target


@pytest.mark.parametrize(
    "board, field, message",
    [
        (dict(CHARUCO, cols=5, azimuth_deg=0.0), r"boards\.wall0\.cols", "its charuco has 6"),
        (dict(CHARUCO, azimuth_deg=0.0, points=[[0, 0, 0]]), r"boards\.wall0\.points", "1 points, but"),
        (dict(CHARUCO, azimuth_deg=0.0, x_dir=2), r"boards\.wall0\.x_dir", "must be 1 or -1"),
    ],
)
def test_bad_typed_boards_in_a_setup_are_named(tmp_path, board, field, message):
    with pytest.raises(FormatError, match=rf"setup\.json: {field}: .*{message}"):
        read_setup(_write(tmp_path, _setup({"wall0": board}), "setup.json"))


def test_overlapping_ids_in_a_setup_are_refused(tmp_path):
    boards = {"wall0": dict(CHARUCO, azimuth_deg=0.0), "wall1": dict(CHARUCO, azimuth_deg=90.0)}
    with pytest.raises(FormatError, match=r"setup\.json: boards\.wall1\.first_marker_id: boards 'wall0' and 'wall1'"):
        read_setup(_write(tmp_path, _setup(boards), "setup.json"))


def test_the_detector_refuses_targets_it_cannot_find_yet(tmp_path):
    from slcvjax.images.detect import detect_folder

    """A chessboard through the mirror is refused, naming the board: its corners carry no id, so
    which wall and which corner could not be told without guessing (ChArUco and AprilGrid walls
    are detected: tests/test_coded_targets.py)."""
    chess = {"type": "chessboard", "inner": [4, 3], "square_mm": 20.0}
    doc = _setup({"wall0": dict(chess, azimuth_deg=0.0)})
    _write(tmp_path, doc, "setup.json")
    with pytest.raises(FormatError, match=r"boards\.wall0\.type: the detector finds dots, ChArUco and AprilGrid"):
        detect_folder(tmp_path)
