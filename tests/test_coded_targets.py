"""Coded targets through the mirror: a rendered ChArUco box detected against the exact projections
of the model (never against numbers copied from a run), a mirror-reversed image, a partly hidden
board, markers whose place contradicts their ids, and ChArUco / AprilGrid boards seen directly."""

import cv2
import numpy as np
import pytest

from slcvjax.geometry.camera import Camera
from slcvjax.geometry.mirror import ConeMirror
from slcvjax.geometry.rig import Rig
from slcvjax.images import coded
from slcvjax.images.coded_box import coded_box_scene, visible_corners
from slcvjax.images.printable import board_drawing, rasterize
from slcvjax.images.render import Renderer, RenderOptions
from slcvjax.images.render_coded import INK, PAPER, drawing_albedo, pack_drawings
from slcvjax.observations.simulate import paper_rig
from slcvjax.observations.targets import board_points

OPTS = RenderOptions(noise=0.0)


@pytest.fixture(scope="module")
def view():
    """One noise-free view of a small ChArUco box (a 560 x 420 camera, 30 mm squares), the sensor
    moved off the box's centre so that the walls differ in size, and the truth."""
    cam = Camera.create(460.0, 461.0, 283.0, 206.0, [-0.1, 0.02, 0.0005, -0.0003, 0.0], 560, 420)
    rig = Rig(cam, ConeMirror.create([0.3, -0.2, 47.0], [0.01, -0.008, 1.0], 25.0, 12.0), paper_rig(3).lasers)
    pose = np.array([[0.02, -0.01, 0.15, 12.0, -8.0, 2.0]])
    scene = coded_box_scene(rig, pose, squares=(5, 2), square_mm=30.0, marker_mm=22.0)
    walls = [b for b in scene.boards if b != scene.chess_board]
    drawings = {b: board_drawing(scene.board_types[b], scene.boards[b]) for b in walls}
    img = Renderer(cam, rig.mirror, OPTS).catadioptric(scene.box_poses[0], scene.boards, [], drawings=drawings)
    specs = {b: scene.board_types[b] for b in walls}
    az = {f"wall{j}": 90.0 * j for j in range(4)}
    return img, specs, az, visible_corners(scene, 0, OPTS)


def _errors(det, truth, flip_width=None):
    out, n_vis, n_found = [], 0, 0
    for b, (uv, vis) in truth.items():
        px, seen = det.boards[b]
        uv = uv.copy()
        if flip_width is not None:
            uv[:, 0] = flip_width - 1 - uv[:, 0]
        out.append(px[seen] - uv[seen])
        n_vis += int(vis.sum())
        n_found += int((seen & vis).sum())
    return np.concatenate(out), n_vis, n_found


def test_the_drawing_shader_is_ink_inside_the_print_and_paper_elsewhere():
    spec = {"type": "charuco", "dictionary": "DICT_4X4_50", "squares": [3, 2], "square_mm": 10.0, "marker_mm": 7.0}
    drawing = board_drawing(spec, board_points(spec))
    packed = pack_drawings([None, drawing])
    assert float(drawing_albedo(1, np.array([5.0, 5.0]), packed)) == INK  # the black top-left square
    assert float(drawing_albedo(1, np.array([15.0, 1.0]), packed)) == PAPER  # the white margin of a marker
    assert float(drawing_albedo(1, np.array([-3.0, 5.0]), packed)) == PAPER  # off the print
    assert float(drawing_albedo(0, np.array([5.0, 5.0]), packed)) == PAPER  # a wall without a drawing


def test_rendered_charuco_corners_are_found_at_their_exact_projections(view):
    img, specs, az, truth = view
    det = coded.detect_coded(img, specs, az)
    assert not det.reversed
    e, n_vis, n_found = _errors(det, truth)
    n = np.linalg.norm(e, axis=1)
    assert n.max() < 0.5, n.max()  # none labelled as another point (the next corner is a square away)
    assert np.sqrt((e**2).mean(axis=0)).max() < 0.06
    assert n_vis >= 12 and n_found >= 0.6 * n_vis, (n_found, n_vis)


def test_a_mirror_reversed_image_is_read_the_other_way_round(view):
    img, specs, az, truth = view
    flipped = np.ascontiguousarray(img[:, ::-1])
    det = coded.detect_coded(flipped, specs, az)
    assert det.reversed
    e, n_vis, n_found = _errors(det, truth, flip_width=img.shape[1])
    assert np.linalg.norm(e, axis=1).max() < 0.5
    assert n_found >= 0.6 * n_vis


def test_a_partly_hidden_board_gives_its_seen_corners_only(view):
    img, specs, az, truth = view
    full = coded.detect_coded(img, specs, az).boards["wall0"][1]
    uv = truth["wall0"][0]
    hidden = img.copy()
    # paper over the board's right half (its points of x beyond the middle, with a square's margin)
    pts = board_points(specs["wall0"])
    right = pts[:, 0] > pts[:, 0].mean()
    hull = cv2.convexHull(np.float32(uv[right]))
    mask = np.zeros(img.shape[:2], np.uint8)
    cv2.fillConvexPoly(mask, hull.astype(np.int32), 1)
    mask = cv2.dilate(mask, np.ones((25, 25), np.uint8)).astype(bool)
    hidden[mask] = np.median(img[~mask & (img[:, :, 1] > 120)], axis=0).astype(np.uint8)
    det = coded.detect_coded(hidden, specs, az)
    px, seen = det.boards["wall0"]
    assert 0 < seen.sum() < full.sum()
    assert not (seen & right & (pts[:, 0] > pts[right, 0].min())).any()  # under the paper: not found
    assert np.all(np.linalg.norm(px[seen] - uv[seen], axis=1) < 0.5)


def test_markers_whose_place_contradicts_their_ids_are_dropped():
    spec = {"type": "charuco", "dictionary": "DICT_4X4_50", "squares": [5, 3], "square_mm": 20.0, "marker_mm": 15.0}
    board = coded.CodedBoard.of("b", spec)
    H = np.array([[2.0, 0.1, 30.0], [-0.05, 1.8, 40.0], [1e-4, 0.0, 1.0]])
    found = {k: coded.apply_affine(H, board.marker_corners[k]) for k in range(len(board.ids))}
    assert set(coded.markers_consistent(board, found)) == set(found)
    swapped = dict(found)
    swapped[1], swapped[5] = found[5], found[1]  # two ids read at each other's place
    kept = coded.markers_consistent(board, swapped)
    assert 1 not in kept and 5 not in kept and len(kept) == len(found) - 2


@pytest.mark.parametrize("kind", ["charuco", "aprilgrid"])
def test_boards_seen_directly_are_labelled_by_their_markers(kind):
    if kind == "charuco":
        spec = {"type": kind, "dictionary": "DICT_4X4_50", "squares": [5, 4], "square_mm": 20.0, "marker_mm": 15.0}
    else:
        spec = {"type": kind, "tag_cols": 3, "tag_rows": 2, "tag_mm": 20.0, "spacing": 0.3}
    spec["first_marker_id"] = 4
    pts = board_points(spec)
    drawing = board_drawing(spec, pts)
    ppm = 6.0
    img, origin = rasterize(drawing, ppm, border_mm=12.0)
    v = (origin[1] - pts[:, 1]) if drawing.y_up else (pts[:, 1] - origin[1])
    uv = np.stack([(pts[:, 0] - origin[0]) * ppm - 0.5, v * ppm - 0.5], axis=1)
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    got = coded.detect_direct(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR), spec)
    assert got is not None
    px, seen = got
    assert seen.sum() >= 0.9 * len(pts)
    assert np.abs(px[seen] - uv[seen]).max() < 0.3
