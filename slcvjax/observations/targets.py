"""Calibration targets as files: each board ``type``'s points, generated from its few numbers.

A board in ``slcv-setup/1`` and ``slcv-observations/1`` may carry a ``type``
(DESIGN section 3, ``docs/formats.md``):

- ``dots`` (the default where ``type`` is absent): a grid of dots given by its ``points``;
- ``chessboard``: ``"inner": [cols, rows], "square_mm"``;
- ``charuco``: ``"dictionary", "squares": [sx, sy], "square_mm", "marker_mm", "first_marker_id"``
  (OpenCV's ``cv2.aruco.CharucoBoard``);
- ``aprilgrid``: ``"tag_cols", "tag_rows", "tag_mm", "spacing", "first_marker_id"`` (Kalibr's,
  tag36h11).

Each generator below is a pure NumPy function returning ``(N, 3)`` float64 points in
millimetres in the board's own frame, ``z = 0``; point ``j`` is the target's feature ``j``
(the index a detector's output is matched by).  Nothing here imports OpenCV or JAX; the
tests check the generators against OpenCV and against closed forms.

:func:`read_board` validates a board's JSON object for the readers (``read_observations``,
``read_setup``): the type's fields, the generated points, and any ``points`` the file also
gives (they must agree with the generated ones to 1e-9 mm).  :func:`check_disjoint_ids`
refuses two boards of one rig that share a marker id.
"""

import json
from typing import Any

import numpy as np

BOARD_TYPES = ("dots", "chessboard", "charuco", "aprilgrid")
POINTS_TOLERANCE_MM = 1e-9  # a board's given points must agree with its type's to this

# OpenCV's predefined ArUco / AprilTag dictionaries: name -> (bits per side, number of markers)
# (``cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))``; the tests check this table).
DICTIONARIES: dict[str, tuple[int, int]] = {
    **{f"DICT_{b}X{b}_{n}": (b, n) for b in (4, 5, 6, 7) for n in (50, 100, 250, 1000)},
    "DICT_ARUCO_ORIGINAL": (5, 1024),
    "DICT_ARUCO_MIP_36h12": (6, 250),
    "DICT_APRILTAG_16h5": (4, 30),
    "DICT_APRILTAG_25h9": (5, 35),
    "DICT_APRILTAG_36h10": (6, 2320),
    "DICT_APRILTAG_36h11": (6, 587),
}
APRILGRID_DICTIONARY = "DICT_APRILTAG_36h11"  # Kalibr's aprilgrid family, tag36h11, as OpenCV names it


# --------------------------------------------------------------------------- generators


def chessboard_points(cols: int, rows: int, square_mm: float) -> np.ndarray:
    """A chessboard's inner corners: ``(cols * rows, 3)`` float64, mm.

    Frame: origin at the first inner corner, x along the ``cols`` corners of a row, y along
    the rows, z = 0; point ``i + cols * j`` is ``(i * square_mm, j * square_mm, 0)`` (x fastest,
    OpenCV's ``findChessboardCorners`` order and the project's ``grid_points``).  The printed
    board has ``(cols + 1) x (rows + 1)`` squares, its top-left square black, so the first inner
    corner lies one square right of and below the printed board's top-left corner (x right,
    y down on the print).
    """
    i, j = np.meshgrid(np.arange(cols, dtype=float), np.arange(rows, dtype=float))
    return np.stack([i.ravel() * square_mm, j.ravel() * square_mm, np.zeros(cols * rows)], axis=1)


def charuco_points(squares: tuple[int, int], square_mm: float) -> np.ndarray:
    """A ChArUco board's chessboard corners: ``((sx - 1) * (sy - 1), 3)`` float64, mm.

    The same points, in the same order and frame, as OpenCV's
    ``cv2.aruco.CharucoBoard((sx, sy), square_mm, marker_mm, dictionary, ids).getChessboardCorners()``
    (which returns them in float32): origin at the printed board's top-left corner, x right,
    y down, z = 0; corner ``j = i + (sx - 1) * k`` (x fastest) is ``((i + 1) * s, (k + 1) * s, 0)``.
    OpenCV's ChArUco detector reports corner ``j`` with id ``j``.
    """
    sx, sy = squares
    return chessboard_points(sx - 1, sy - 1, square_mm) + np.array([square_mm, square_mm, 0.0])


def charuco_marker_squares(squares: tuple[int, int]) -> np.ndarray:
    """The squares holding a ChArUco board's markers: ``(sx * sy // 2, 2)`` int, (column, row).

    Marker ``m`` (id ``first_marker_id + m``) sits in the ``m``-th white square in row-major order
    (row 0 at the printed top); the white squares are those with odd ``column + row``: the top-left
    square is black.  This is OpenCV's layout since 4.6 (not ``setLegacyPattern(True)``'s).
    """
    sx, sy = squares
    return np.array([(c, r) for r in range(sy) for c in range(sx) if (c + r) % 2 == 1], dtype=int).reshape(-1, 2)


def aprilgrid_points(tag_cols: int, tag_rows: int, tag_mm: float, spacing: float) -> np.ndarray:
    """An aprilgrid's tag corners in Kalibr's order and frame: ``(4 * tag_cols * tag_rows, 3)`` float64, mm.

    Kalibr (``GridCalibrationTargetAprilgrid::createGridPoints``) numbers the corners on a grid of
    ``2 * tag_rows`` rows and ``2 * tag_cols`` columns, x fastest: point ``r * 2 * tag_cols + c`` is
    ``(c // 2 * (1 + spacing) * tag_mm + c % 2 * tag_mm,  r // 2 * (1 + spacing) * tag_mm + r % 2 * tag_mm, 0)``.
    Frame: Kalibr's target frame, origin at tag 0's bottom-left (outer black) corner, x right,
    **y up** on the print, z = 0; tags numbered row-major from the bottom-left (tag ``t`` in tag row
    ``t // tag_cols``, column ``t % tag_cols``), tag ``t`` carrying id ``first_marker_id + t``.  A
    tag's corners are points ``(b, b + 1, b + 2 tag_cols + 1, b + 2 tag_cols)`` with
    ``b = 4 tag_cols (t // tag_cols) + 2 (t % tag_cols)``: bottom-left, bottom-right, top-right,
    top-left (:func:`aprilgrid_tag_corners`).  ``tag_mm`` is the tag's black square (its 1-bit black
    border included, its white quiet zone not) and ``spacing`` the gap between tags over ``tag_mm``.

    Why Kalibr's frame and not the charuco's (top-left, y down): the board is Kalibr's, so an
    index here is Kalibr's index, a pose estimated here is Kalibr's ``T_camera_target``, and a print
    from :mod:`slcvjax.images.printable` is laid out like Kalibr's own PDF (tag 0 at the bottom
    left, each tag's bits oriented as Kalibr draws them).
    """
    cols, rows = 2 * tag_cols, 2 * tag_rows
    c, r = np.meshgrid(np.arange(cols), np.arange(rows))
    c, r = c.ravel(), r.ravel()
    pitch = (1.0 + spacing) * tag_mm
    x = (c // 2) * pitch + (c % 2) * tag_mm
    y = (r // 2) * pitch + (r % 2) * tag_mm
    return np.stack([x, y, np.zeros(cols * rows)], axis=1).astype(float)


def aprilgrid_tag_corners(tag_cols: int, tag_rows: int) -> np.ndarray:
    """Each tag's corners as indices into :func:`aprilgrid_points`: ``(tag_cols * tag_rows, 4)`` int.

    Row ``t`` is tag ``t`` (id ``first_marker_id + t``); its columns are the tag's bottom-left,
    bottom-right, top-right and top-left corners in Kalibr's y-up frame (Kalibr's ``pIdx``, the
    AprilTag detector's counter-clockwise corner order in an image of the upright print).
    """
    t = np.arange(tag_cols * tag_rows)
    base = (t // tag_cols) * 4 * tag_cols + (t % tag_cols) * 2
    return np.stack([base, base + 1, base + 2 * tag_cols + 1, base + 2 * tag_cols], axis=1)


def marker_ids(spec: dict) -> np.ndarray:
    """The marker ids a board's ``spec`` (:func:`read_board`'s) prints: ``(K,)`` int, in point order.

    ChArUco: ``first_marker_id + m`` for the ``sx * sy // 2`` markers; aprilgrid:
    ``first_marker_id + t`` for its tags; none for dots and chessboards.
    """
    kind = spec.get("type", "dots")
    first = int(spec.get("first_marker_id", 0))
    if kind == "charuco":
        sx, sy = spec["squares"]
        return first + np.arange(sx * sy // 2)
    if kind == "aprilgrid":
        return first + np.arange(spec["tag_cols"] * spec["tag_rows"])
    return np.zeros(0, dtype=int)


def marker_dictionary(spec: dict) -> str | None:
    """The OpenCV dictionary a board's markers come from (None for dots and chessboards)."""
    kind = spec.get("type", "dots")
    return spec["dictionary"] if kind == "charuco" else APRILGRID_DICTIONARY if kind == "aprilgrid" else None


def board_points(spec: dict) -> np.ndarray:
    """The points of a typed board (``spec`` as :func:`read_board` returns it): ``(N, 3)`` float64, mm.

    Dispatches to :func:`chessboard_points`, :func:`charuco_points` or :func:`aprilgrid_points`;
    a ``dots`` board has no generator (its ``points`` are the file's): ValueError.
    """
    kind = spec.get("type", "dots")
    if kind == "chessboard":
        return chessboard_points(*spec["inner"], spec["square_mm"])
    if kind == "charuco":
        return charuco_points(tuple(spec["squares"]), spec["square_mm"])
    if kind == "aprilgrid":
        return aprilgrid_points(spec["tag_cols"], spec["tag_rows"], spec["tag_mm"], spec["spacing"])
    raise ValueError(f"a {kind!r} board has no generated points: give its points")


def grid_shape(spec: dict) -> tuple[int, int]:
    """(cols, rows) of a typed board's points, x fastest (the detector's ``cols``, ``rows``)."""
    kind = spec["type"]
    if kind == "chessboard":
        return int(spec["inner"][0]), int(spec["inner"][1])
    if kind == "charuco":
        return int(spec["squares"][0]) - 1, int(spec["squares"][1]) - 1
    if kind == "aprilgrid":
        return 2 * int(spec["tag_cols"]), 2 * int(spec["tag_rows"])
    raise ValueError(f"a {kind!r} board's grid is given by its file")


# --------------------------------------------------------------------------- reading


def _int_pair(ctx, val: Any, where: str, lo: int) -> list[int]:
    if not isinstance(val, list) or len(val) != 2:
        ctx.fail(where, f"expected [columns, rows], got {json.dumps(val)[:40]}")
    return [ctx.integer(v, f"{where}[{i}]", lo=lo) for i, v in enumerate(val)]


def _type_spec(ctx, b: dict, where: str, kind: str) -> dict:
    """A typed board's fields, validated (``ctx``: the reader's ``ReadContext``)."""
    if kind == "chessboard":
        inner = _int_pair(ctx, ctx.get(b, "inner", where), f"{where}.inner", lo=2)
        return {
            "type": kind,
            "inner": inner,
            "square_mm": ctx.positive(ctx.get(b, "square_mm", where), f"{where}.square_mm"),
        }
    first = ctx.integer(ctx.get(b, "first_marker_id", where, optional=True) or 0, f"{where}.first_marker_id", lo=0)
    if kind == "charuco":
        name = ctx.get(b, "dictionary", where, str)
        if name not in DICTIONARIES:
            ctx.fail(f"{where}.dictionary", f"unknown dictionary {name!r} (known: {', '.join(DICTIONARIES)})")
        squares = _int_pair(ctx, ctx.get(b, "squares", where), f"{where}.squares", lo=2)
        square = ctx.positive(ctx.get(b, "square_mm", where), f"{where}.square_mm")
        marker = ctx.positive(ctx.get(b, "marker_mm", where), f"{where}.marker_mm")
        if marker >= square:
            ctx.fail(
                f"{where}.marker_mm", f"the marker ({marker:g} mm) must be smaller than the square ({square:g} mm)"
            )
        spec = {"type": kind, "dictionary": name, "squares": squares, "square_mm": square, "marker_mm": marker}
        n = squares[0] * squares[1] // 2
    else:
        family = ctx.get(b, "family", where, str, optional=True)
        if family is not None and family != "tag36h11":
            ctx.fail(f"{where}.family", f"an aprilgrid is Kalibr's tag36h11, got {family!r}")
        cols = ctx.integer(ctx.get(b, "tag_cols", where), f"{where}.tag_cols", lo=1)
        rows = ctx.integer(ctx.get(b, "tag_rows", where), f"{where}.tag_rows", lo=1)
        tag = ctx.positive(ctx.get(b, "tag_mm", where), f"{where}.tag_mm")
        spacing = ctx.positive(ctx.get(b, "spacing", where), f"{where}.spacing")
        if spacing > 1.0:
            ctx.fail(f"{where}.spacing", f"the gap over the tag size must be in (0, 1] (Kalibr's), got {spacing:g}")
        spec = {"type": kind, "tag_cols": cols, "tag_rows": rows, "tag_mm": tag, "spacing": spacing}
        name, n = APRILGRID_DICTIONARY, cols * rows
    size = DICTIONARIES[name][1]
    if first + n > size:
        ctx.fail(
            f"{where}.first_marker_id",
            f"ids {first}..{first + n - 1} of its {n} markers exceed {name}'s {size} (0..{size - 1})",
        )
    spec["first_marker_id"] = first
    return spec


def read_board(ctx, b: Any, where: str) -> tuple[np.ndarray, dict | None]:
    """A board's points and type from its JSON object ``b`` at ``where`` (``boards.NAME``).

    ``ctx`` is the reader's context (:class:`slcvjax.observations.formats.ReadContext`: ``fail`` raises
    :class:`~slcvjax.observations.formats.FormatError` naming the file, the field and the index).
    Returns ``(points (N, 3) float64 mm, spec)``: ``spec`` is None for a ``dots`` board (its
    ``points`` required, as before types), else the type's normalised fields (``type`` and the
    numbers above, ``first_marker_id`` filled in).  A typed board's ``points`` may be left out;
    where given they must agree with the generated ones to ``POINTS_TOLERANCE_MM``, else the
    message names the first point that does not (``boards.wall0.points[3]``).
    """
    if not isinstance(b, dict):
        ctx.fail(where, f"expected an object, got {type(b).__name__}")
    kind = ctx.get(b, "type", where, str, optional=True) or "dots"
    if kind not in BOARD_TYPES:
        ctx.fail(f"{where}.type", f"unknown board type {kind!r} (known: {', '.join(BOARD_TYPES)})")
    spec = None if kind == "dots" else _type_spec(ctx, b, where, kind)
    given = ctx.list_of(b, "points", where, optional=spec is not None)
    if spec is None and not given:
        ctx.fail(f"{where}.points", "a board needs at least one point")
    pts = np.stack([ctx.vector(p, 3, f"{where}.points[{i}]") for i, p in enumerate(given)]) if given else None
    if pts is not None:
        bad = np.flatnonzero(np.abs(pts[:, 2]) > 1e-9)
        if bad.size:
            ctx.fail(f"{where}.points[{bad[0]}][2]", f"board points must have z = 0, got {pts[bad[0], 2]:g}")
        pts[:, 2] = 0.0  # within 1e-9 of it: the board's plane, exactly
    if spec is None:
        return pts, None
    gen = board_points(spec)
    if pts is not None:
        if len(pts) != len(gen):
            ctx.fail(f"{where}.points", f"{len(pts)} points, but its {kind} has {len(gen)}")
        err = np.abs(pts - gen).max(axis=1)
        bad = np.flatnonzero(err > POINTS_TOLERANCE_MM)
        if bad.size:
            i = int(bad[0])
            ctx.fail(
                f"{where}.points[{i}]",
                f"{pts[i].tolist()} is not its {kind}'s point {i} {gen[i].tolist()} (off by {err[i]:.3g} mm; "
                f"{bad.size} of {len(gen)} points disagree)",
            )
    return gen, spec


def check_disjoint_ids(ctx, specs: dict[str, dict | None]) -> None:
    """Refuse two boards of one rig that print a marker of the same dictionary with the same id.

    ``specs``: board name -> :func:`read_board`'s spec (None for dots).  The message
    (``ctx.fail``, field ``boards``) names both boards and the ids they share.
    """
    seen: dict[str, list[tuple[str, np.ndarray]]] = {}
    for name, spec in specs.items():
        if spec is None or (dictionary := marker_dictionary(spec)) is None:
            continue
        ids = marker_ids(spec)
        for other, other_ids in seen.get(dictionary, []):
            common = np.intersect1d(ids, other_ids)
            if common.size:
                ctx.fail(
                    f"boards.{name}.first_marker_id",
                    f"boards {other!r} and {name!r} share {common.size} {dictionary} marker id(s) "
                    f"({_id_range(common)}): the boards of one rig need disjoint ids",
                )
        seen.setdefault(dictionary, []).append((name, ids))


def _id_range(ids: np.ndarray) -> str:
    ids = np.sort(np.asarray(ids))
    if ids.size and np.all(np.diff(ids) == 1):
        return f"{ids[0]}..{ids[-1]}" if ids.size > 1 else f"{ids[0]}"
    return ", ".join(str(i) for i in ids[:8]) + (", ..." if ids.size > 8 else "")


def spec_json(spec: dict | None) -> dict:
    """The JSON fields of a board's type (``{}`` for dots), to write beside its ``points``."""
    if spec is None:
        return {}
    return {k: (list(v) if isinstance(v, (list, tuple)) else v) for k, v in spec.items()}


def describe(spec: dict | None, n_points: int) -> str:
    """A one-line description of a board for reports and prints (type, size, marker ids)."""
    if spec is None:
        return f"dots, {n_points} points"
    kind = spec["type"]
    if kind == "chessboard":
        c, r = spec["inner"]
        return f"chessboard, {c} x {r} inner corners, {spec['square_mm']:g} mm squares"
    ids = marker_ids(spec)
    if kind == "charuco":
        sx, sy = spec["squares"]
        head = (
            f"charuco {spec['dictionary']}, {sx} x {sy} squares of {spec['square_mm']:g} mm, "
            f"markers {spec['marker_mm']:g} mm"
        )
    else:
        head = (
            f"aprilgrid tag36h11, {spec['tag_cols']} x {spec['tag_rows']} tags of {spec['tag_mm']:g} mm, "
            f"spacing {spec['spacing']:g}"
        )
    return f"{head}, ids {_id_range(ids)}"
