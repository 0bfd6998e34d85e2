"""Printable targets (``slcvjax.images.printable``), ``slcvjax setup init`` and ``slcvjax target``:
page sizes and the scale bar in PDF points, the drawings against OpenCV's own board image, and the
rendered PDFs detected by OpenCV at the right physical places."""

import json
import re
import shutil
import subprocess
import zlib

import cv2
import numpy as np
import pytest

from slcvjax.cli import main
from slcvjax.images.detect import read_setup
from slcvjax.images.printable import PT_PER_MM, board_drawing, board_page, pdf_bytes, plan_page, rasterize, write_pdf
from slcvjax.images.targetbox import box_setup, mirror_band_z
from slcvjax.observations.targets import (
    aprilgrid_points,
    aprilgrid_tag_corners,
    charuco_points,
    chessboard_points,
)

from .test_targets import CHARUCO  # the same board as the geometry's tests

APRILGRID = {"type": "aprilgrid", "tag_cols": 3, "tag_rows": 2, "tag_mm": 20.0, "spacing": 0.3, "first_marker_id": 5}
PDFTOCAIRO = shutil.which("pdftocairo")  # poppler-utils; cairo renders edges by their exact coverage


def _media_box(pdf: bytes) -> list[float]:
    return [float(v) for v in re.search(rb"/MediaBox \[([^\]]+)\]", pdf).group(1).split()]


def _content(pdf: bytes) -> bytes:
    """The PDF's streams inflated (matplotlib's PDF backend compresses them with Flate)."""
    return b"\n".join(
        zlib.decompressobj().decompress(m.group(1)) for m in re.finditer(rb"stream\r?\n(.*?)endstream", pdf, re.S)
    )


def _painted_rects(content: bytes) -> list[tuple[str, list[float]]]:
    """Every path painted on its own that is one axis-aligned rectangle (``m l l l [l] h`` or ``re``),
    with its paint operator: ``(op, [x, y, w, h])`` in points, x and y its corner of least x and y."""
    content = re.sub(rb"BT\b.*?\bET", b"", content, flags=re.S)  # no text: its strings are not operators
    out, subpaths, nums = [], [], []
    for tok in content.split():
        try:
            nums.append(float(tok))
            continue
        except ValueError:
            pass
        if tok == b"m":
            subpaths.append([nums[-2:]])
        elif tok == b"l":
            subpaths[-1].append(nums[-2:])
        elif tok == b"re":
            x, y, w, h = nums[-4:]
            subpaths.append([[x, y], [x + w, y], [x + w, y + h], [x, y + h]])
        elif tok in (b"f", b"f*", b"S", b"B", b"B*", b"n"):
            if len(subpaths) == 1:
                p = np.array(subpaths[0])
                if len(p) == 5 and np.allclose(p[4], p[0], atol=1e-9):
                    p = p[:4]  # a stroked path closed by its first point again
                lo, hi = p.min(axis=0), p.max(axis=0)
                on_edges = np.all(np.isclose(p, lo, atol=1e-9) | np.isclose(p, hi, atol=1e-9), axis=1)
                if len(p) == 4 and on_edges.all() and len({tuple(q) for q in np.round(p, 9)}) == 4:
                    out.append((tok.decode(), [*lo, *(hi - lo)]))
            subpaths = []
        nums = []
    return out


def _scale_bar_ops(pdf: bytes) -> list[list[float]]:
    """The scale bar's rectangles in points, [x, y, w, h] each: its outline (the page's only stroked
    rectangle) first, then the filled rectangles inside it, left to right."""
    rects = _painted_rects(_content(pdf))
    (outline,) = [r for op, r in rects if op == "S"]
    x, y, w, h = outline
    inside = [
        r
        for op, r in rects
        if op == "f"
        and r[0] >= x - 1e-6
        and r[0] + r[2] <= x + w + 1e-6
        and r[1] >= y - 1e-6
        and r[1] + r[3] <= y + h + 1e-6
    ]
    return [outline, *sorted(inside)]


def test_page_size_and_scale_bar_in_points():
    fig, plan, _ = board_page("wall0", CHARUCO, charuco_points((7, 5), 20.0))
    pdf = pdf_bytes(fig)
    assert plan.paper == "A4" and not plan.landscape
    np.testing.assert_allclose(_media_box(pdf), [0, 0, 210 * 72 / 25.4, 297 * 72 / 25.4], atol=1e-4)
    rects = _scale_bar_ops(pdf)
    outline, segments = rects[0], rects[1:]
    assert outline[2] == pytest.approx(100 * 72 / 25.4, abs=2e-4)  # 283.4646 pt
    assert len(segments) == 5 and all(s[2] == pytest.approx(10 * 72 / 25.4, abs=2e-4) for s in segments)
    # the segments alternate along the bar: starts 20 mm apart from its left end
    np.testing.assert_allclose([s[0] - outline[0] for s in segments], np.arange(5) * 20 * PT_PER_MM, atol=2e-4)
    assert b"(wall0: charuco DICT_4X4_250, 7 x 5 squares of 20 mm, markers 15 mm, ids 17..33)" in _content(pdf)
    assert b"/BaseFont /Helvetica" in pdf and b"CreationDate" not in pdf
    assert pdf_bytes(board_page("wall0", CHARUCO, charuco_points((7, 5), 20.0))[0]) == pdf  # the same bytes again


@pytest.mark.parametrize(
    "squares, square, paper, landscape",
    [
        ((7, 5), 20.0, "A4", False),
        ((12, 9), 25.0, "A3", True),
        ((20, 14), 30.0, "A1", True),
        ((42, 10), 30.0, "custom", False),
    ],
)
def test_the_page_is_the_smallest_a_size_that_fits(squares, square, paper, landscape):
    drawing = board_drawing(dict(CHARUCO, squares=list(squares), square_mm=square, marker_mm=0.7 * square), None)
    plan = plan_page(drawing)
    assert (plan.paper, plan.landscape) == (paper, landscape)
    w, h = plan.size_mm
    lo = plan.to_page_mm(np.array(drawing.extent[:2]))
    hi = plan.to_page_mm(np.array(drawing.extent[2:]))
    x0, x1 = sorted([lo[0], hi[0]])
    y0, y1 = sorted([lo[1], hi[1]])
    assert x0 >= 12 - 1e-9 and x1 <= w - 12 + 1e-9 and y1 <= h - 12 + 1e-9
    assert plan.scale_bar_mm[1] >= 12 - 1e-9 and plan.scale_bar_mm[1] + 10 < y0  # the bar below the board
    if paper == "custom":
        assert (w, h) == pytest.approx((x1 - x0 + 24, y1 - y0 + 10 + 30 + 24))


@pytest.mark.parametrize("squares, first", [((7, 5), 17), ((6, 4), 0), ((5, 8), 100)])
def test_the_charuco_drawing_is_opencvs_image(squares, first):
    """Rasterised at 8 px per mm, the vector drawing equals ``CharucoBoard.generateImage`` pixel for pixel."""
    spec = dict(CHARUCO, squares=list(squares), first_marker_id=first)
    img, _ = rasterize(board_drawing(spec, None), 8.0, border_mm=5.0)
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_250)
    board = cv2.aruco.CharucoBoard(squares, 20.0, 15.0, d, first + np.arange(squares[0] * squares[1] // 2))
    ref = board.generateImage((squares[0] * 160, squares[1] * 160), marginSize=0, borderBits=1)
    np.testing.assert_array_equal(img[40 : 40 + ref.shape[0], 40 : 40 + ref.shape[1]], ref)


def _aruco_corners(img, dictionary):
    """Each detected marker's corners (OpenCV's order), refined by ``cornerSubPix``: a tag's corner
    on Kalibr's print is an X-junction with the black square in the gap beside it."""
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)))
    corners, ids, _ = det.detectMarkers(img)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    out = {}
    for c, i in zip(corners, np.ravel(ids), strict=True):
        out[int(i)] = cv2.cornerSubPix(img, c.reshape(4, 1, 2).astype(np.float32), (9, 9), (-1, -1), crit).reshape(4, 2)
    return out


def test_the_aprilgrid_drawing_is_read_by_opencv_at_kalibrs_points():
    img, origin = rasterize(board_drawing(APRILGRID, None), 8.0)
    pts = aprilgrid_points(3, 2, 20.0, 0.3)
    uv = np.stack([(pts[:, 0] - origin[0]) * 8 - 0.5, (origin[1] - pts[:, 1]) * 8 - 0.5], axis=1)
    found = _aruco_corners(img, "DICT_APRILTAG_36h11")
    assert sorted(found) == list(range(5, 11))
    corners = aprilgrid_tag_corners(3, 2)  # (bottom-left, bottom-right, top-right, top-left) per tag
    for mid, c in found.items():
        # OpenCV's corners (its image's top-left, top-right, bottom-right, bottom-left) on Kalibr's
        # print, which draws each tag turned by 180 degrees: Kalibr's br, bl, tl, tr
        np.testing.assert_allclose(c, uv[corners[mid - 5][[1, 0, 3, 2]]], atol=0.1)


def _render(pdf_path, dpi, tmp_path):
    stem = tmp_path / "page"
    subprocess.run([PDFTOCAIRO, "-r", str(dpi), "-gray", "-png", "-singlefile", str(pdf_path), str(stem)], check=True)
    return cv2.imread(str(stem) + ".png", cv2.IMREAD_GRAYSCALE)


def _page_pixels(plan, xy, dpi):
    """Board points -> pixels of the page rendered at ``dpi`` (pixel centres at integers)."""
    p = plan.to_page_mm(xy[:, :2])
    k = dpi / 25.4
    return np.stack([p[:, 0] * k - 0.5, (plan.size_mm[1] - p[:, 1]) * k - 0.5], axis=1)


@pytest.mark.skipif(PDFTOCAIRO is None, reason="pdftocairo (poppler-utils) is not installed")
def test_the_charuco_pdf_is_detected_at_its_true_size(tmp_path):
    fig, plan, _ = board_page("wall0", CHARUCO, charuco_points((7, 5), 20.0))
    write_pdf(fig, tmp_path / "wall0.pdf")
    dpi = 200
    img = _render(tmp_path / "wall0.pdf", dpi, tmp_path)
    assert img.shape == (round(297 / 25.4 * dpi), round(210 / 25.4 * dpi))
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_250)
    board = cv2.aruco.CharucoBoard((7, 5), 20.0, 15.0, d, 17 + np.arange(17))
    cc, ci, _, mi = cv2.aruco.CharucoDetector(board).detectBoard(img)
    assert sorted(np.ravel(mi).tolist()) == list(range(17, 34))  # every marker
    assert sorted(np.ravel(ci).tolist()) == list(range(24))  # every corner, id j = point j
    cc, ci = cc.reshape(-1, 2), np.ravel(ci)
    want = _page_pixels(plan, charuco_points((7, 5), 20.0), dpi)
    np.testing.assert_allclose(cc, want[ci], atol=0.15)  # 0.02 mm (found: 0.05 px)
    # the spacing of neighbouring corners: 20 mm at 200 dpi
    order = np.argsort(ci)
    grid = cc[order].reshape(4, 6, 2)
    np.testing.assert_allclose(np.linalg.norm(np.diff(grid, axis=1), axis=-1), 20 * dpi / 25.4, rtol=2e-3)
    np.testing.assert_allclose(np.linalg.norm(np.diff(grid, axis=0), axis=-1), 20 * dpi / 25.4, rtol=2e-3)


@pytest.mark.skipif(PDFTOCAIRO is None, reason="pdftocairo (poppler-utils) is not installed")
def test_the_aprilgrid_and_chessboard_pdfs_are_detected_at_their_points(tmp_path):
    dpi = 200
    fig, plan, _ = board_page("g", APRILGRID, aprilgrid_points(3, 2, 20.0, 0.3))
    write_pdf(fig, tmp_path / "g.pdf")
    found = _aruco_corners(_render(tmp_path / "g.pdf", dpi, tmp_path), "DICT_APRILTAG_36h11")
    assert sorted(found) == list(range(5, 11))
    want = _page_pixels(plan, aprilgrid_points(3, 2, 20.0, 0.3), dpi)
    corners = aprilgrid_tag_corners(3, 2)
    for mid, c in found.items():
        np.testing.assert_allclose(c, want[corners[mid - 5][[1, 0, 3, 2]]], atol=0.15)

    spec = {"type": "chessboard", "inner": [9, 6], "square_mm": 20.0}
    fig, plan, _ = board_page("chess", spec, chessboard_points(9, 6, 20.0))
    write_pdf(fig, tmp_path / "chess.pdf")
    img = _render(tmp_path / "chess.pdf", dpi, tmp_path)
    ok, corners = cv2.findChessboardCorners(img, (9, 6))
    assert ok
    corners = cv2.cornerSubPix(
        img, corners, (5, 5), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    ).reshape(-1, 2)
    want = _page_pixels(plan, chessboard_points(9, 6, 20.0), dpi)
    if np.linalg.norm(corners[0] - want[0]) > np.linalg.norm(corners[0] - want[-1]):
        corners = corners[::-1]  # OpenCV may start from either end of a symmetric board
    np.testing.assert_allclose(corners, want, atol=0.3)


# --------------------------------------------------------------------------- setup init, target


def test_mirror_band_closed_form():
    """The apex's ray leaves at 2 beta from the axis: cos 2b = -0.6, sin 2b = 0.8 for r/h = 2."""
    lo, hi = mirror_band_z(20.0, 10.0, 48.0, 140.0)
    assert lo == pytest.approx(48.0 - 140.0 * 0.6 / 0.8, abs=1e-9)
    assert lo < hi


def test_the_box_setup_places_boards_where_the_forward_model_sees_them():
    """Each wall board of ``box_setup``, projected through a cone 48 mm in front of a camera on its
    axis, is seen at its ``azimuth_deg`` with its ``x_dir`` and ``y_dir`` (as ``scene_setup`` derives them)."""
    import jax.numpy as jnp

    from slcvjax.geometry.camera import Camera
    from slcvjax.geometry.lasers import Lasers
    from slcvjax.geometry.mirror import ConeMirror
    from slcvjax.geometry.pose import Pose
    from slcvjax.geometry.rig import Rig, project_board_points
    from slcvjax.images.detect import azimuth_deg

    cam = Camera.create(600.0, 600.0, 400.0, 400.0, np.zeros(5), 800, 800)
    rig = Rig(
        cam,
        ConeMirror.create([0.0, 0.0, 48.0], [0.0, 0.0, 1.0], 20.0, 10.0),
        Lasers.create(np.zeros((1, 3)), np.eye(3)[:1]),
    )
    centre = np.array([400.0, 400.0])
    for target in ("charuco-box", "aprilgrid-box", "dots-box"):
        setup, warnings = box_setup(20.0, 10.0, 10, target=target, width_mm=280.0, mirror_distance_mm=48.0)
        assert warnings == []
        for name, b in setup.boards.items():
            if b.azimuth_deg is None:
                continue
            pose = setup.extra["box"]["T_box_board"][name]
            T = Pose(jnp.asarray(pose["R"]), jnp.asarray(pose["t"]))
            uv, ok = project_board_points(rig, T, jnp.asarray(b.points))
            uv, ok = np.asarray(uv), np.asarray(ok)
            assert ok.all(), (target, name)
            az = azimuth_deg(uv, centre)
            assert abs((np.mean(np.unwrap(np.radians(az))) * 180 / np.pi - b.azimuth_deg + 180) % 360 - 180) < 5
            grid = uv.reshape(b.rows, b.cols, 2)
            d = (azimuth_deg(grid[:, -1], centre) - azimuth_deg(grid[:, 0], centre) + 180) % 360 - 180
            assert np.sign(np.median(d)) == b.x_dir, (target, name)
            r = np.linalg.norm(grid - centre, axis=-1)
            assert np.sign(np.median(r[-1] - r[0])) == b.y_dir, (target, name)


def test_setup_init_then_target(tmp_path, capsys):
    setup_path = tmp_path / "setup.json"
    rc = main(
        [
            "setup",
            "init",
            "--mirror",
            "cone:20x10",
            "--lasers",
            "10",
            "--target",
            "charuco-box",
            "--out",
            str(setup_path),
        ]
    )
    assert rc == 0
    setup = read_setup(setup_path)
    assert setup.n_lasers == 10 and (setup.mirror_radius, setup.mirror_height) == (20.0, 10.0)
    walls = [b for b in setup.boards.values() if b.azimuth_deg is not None]
    assert len(walls) == 4 and all(b.target["type"] == "charuco" for b in walls)
    assert setup.boards["chess"].target["type"] == "chessboard"
    doc = json.loads(setup_path.read_text())
    assert doc["rigid_boards"] == ["wall0", "wall1", "wall2", "wall3"]
    out = tmp_path / "targets"
    assert main(["target", str(setup_path), "--out", str(out)]) == 0
    for name in ["wall0", "wall1", "wall2", "wall3", "chess"]:
        pdf = (out / f"{name}.pdf").read_bytes()
        assert pdf.startswith(b"%PDF-1.4") and pdf.rstrip().endswith(b"%%EOF")
        assert f"({name}: ".encode() in _content(pdf)
    assert b"ids 36..47" in _content((out / "wall3.pdf").read_bytes())
    sheet = (out / "build_sheet.md").read_text()
    assert "wall2.pdf" in sheet and "azimuth 180 deg" in sheet and (out / "build_sheet.png").stat().st_size > 1000
    for target in ("aprilgrid-box", "dots-box"):
        p = tmp_path / f"{target}.json"
        assert (
            main(["setup", "init", "--mirror", "cone:20x10", "--lasers", "3", "--target", target, "--out", str(p)]) == 0
        )
        assert main(["target", str(p), "--out", str(tmp_path / target)]) == 0


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--mirror", "sphere:20x10"], "the cone only"),
        (["--mirror", "cone:20"], "cone:RADIUSxHEIGHT"),
        (["--mirror", "cone:20xten"], "expected numbers"),
        (["--mirror", "cone:20x10", "--squares", "8"], "--squares"),
        (["--mirror", "cone:20x10", "--chessboard", "9x6"], "--chessboard"),
    ],
)
def test_setup_init_names_bad_options(tmp_path, capsys, argv, message):
    rc = main(["setup", "init", "--lasers", "4", "--out", str(tmp_path / "s.json"), *argv])
    assert rc == 2 and message in capsys.readouterr().err


def test_target_names_a_bad_setup(tmp_path, capsys):
    bad = tmp_path / "setup.json"
    bad.write_text(json.dumps({"format": "slcv-setup/1"}))
    assert main(["target", str(bad), "--out", str(tmp_path / "t")]) == 2
    assert "setup.json: image_size: missing" in capsys.readouterr().err
