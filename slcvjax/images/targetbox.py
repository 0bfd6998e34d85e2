"""A box of targets for one's own rig: ``slcvjax setup init``'s ``setup.json`` and the build sheet.

The box frame is the camera's frame at the sensor's nominal place in the box: x right, y down,
z along the camera's axis towards the mirror, origin at the camera's centre, mm.  The mirror
(a cone, apex first) is on the z axis ``mirror_distance_mm`` in front of the lens.  Wall ``j``
of ``n_walls`` faces the axis at azimuth ``360 j / n_walls`` degrees (measured from +x towards
+y: the image azimuth of ``slcvjax.images.detect``, where a point at that azimuth is seen through
the mirror), ``width_mm / 2`` from the axis; its board is centred on the wall at the height
where the mirror sees it (:func:`mirror_band_z`).

A wall board is mounted upright with its printed face towards the sensor: the print's top edge
away from the camera, its x (left to right on the print) along increasing azimuth.  So its
``x_dir`` is +1, and its ``y_dir`` is -1 where the board's y runs down the print (towards the
camera: nearer the image centre, since the cone's apex, seen at the image centre, reflects rays
furthest back towards the camera) and +1 for Kalibr's aprilgrid, whose y runs up the print.
"""

import math

import numpy as np

from ..observations.targets import aprilgrid_points, board_points, charuco_points, grid_shape
from .detect import BoardLayout, Setup

TARGETS = ("charuco-box", "aprilgrid-box", "dots-box")


def mirror_band_z(radius: float, height: float, distance: float, wall_mm: float) -> tuple[float, float]:
    """The z range (box frame, mm) of a wall ``wall_mm`` from the axis seen in a cone mirror.

    The cone (base ``radius``, ``height``) has its apex ``distance`` in front of a camera on its
    axis.  A camera ray at angle ``alpha`` from the axis meets the cone at the apex (``alpha = 0``)
    up to its rim (``tan alpha = radius / (distance + height)``); reflected about the surface
    normal (half-angle ``beta``, ``tan beta = radius / height``) it leaves with the radial and axial
    components ``(sin a - 2 sin(a - b) cos b, cos a + 2 sin(a - b) sin b)`` and reaches the wall at
    the returned heights (the apex's ray first).
    """
    beta = math.atan2(radius, height)
    out = []
    for alpha, rho, z in ((0.0, 0.0, distance), (math.atan2(radius, distance + height), radius, distance + height)):
        dr = math.sin(alpha) - 2 * math.sin(alpha - beta) * math.cos(beta)
        dz = math.cos(alpha) + 2 * math.sin(alpha - beta) * math.sin(beta)
        out.append(z + (wall_mm - rho) * dz / dr)
    return out[0], out[1]


def _wall_spec(
    target: str, j: int, squares: tuple[int, int], square_mm: float, marker_mm: float, spacing: float
) -> tuple:
    """(spec, points, dot_radius_mm) of wall ``j``'s board; ids continue from the walls before it."""
    if target == "charuco-box":
        n = squares[0] * squares[1] // 2
        spec = {
            "type": "charuco",
            "dictionary": "DICT_4X4_250",
            "squares": list(squares),
            "square_mm": square_mm,
            "marker_mm": marker_mm,
            "first_marker_id": j * n,
        }
        return spec, charuco_points(squares, square_mm), None
    if target == "aprilgrid-box":
        spec = {
            "type": "aprilgrid",
            "tag_cols": squares[0],
            "tag_rows": squares[1],
            "tag_mm": square_mm,
            "spacing": spacing,
            "first_marker_id": j * squares[0] * squares[1],
        }
        return spec, aprilgrid_points(squares[0], squares[1], square_mm, spacing), None
    cols, rows = squares
    i, k = np.meshgrid(np.arange(cols, dtype=float), np.arange(rows, dtype=float))
    pts = np.stack([i.ravel() * square_mm, k.ravel() * marker_mm, np.zeros(cols * rows)], axis=1)
    return None, pts, 1.6


def _extent(spec, points, dot_radius):
    from .printable import board_drawing

    return board_drawing(spec, points, dot_radius).extent


def box_setup(
    mirror_radius: float,
    mirror_height: float,
    n_lasers: int,
    target: str = "charuco-box",
    width_mm: float = 280.0,
    mirror_distance_mm: float = 48.0,
    n_walls: int = 4,
    squares: tuple[int, int] | None = None,
    square_mm: float | None = None,
    marker_mm: float | None = None,
    spacing: float = 0.3,
    image_size: tuple[int, int] = (640, 480),
    chessboard: tuple[int, int, float] | None = (9, 6, 20.0),
    board_z_mm: float | None = None,
) -> tuple[Setup, list[str]]:
    """A ``slcv-setup/1`` for a box of ``n_walls`` wall targets and a direct-view chessboard.

    ``target``: ``charuco-box`` (``squares`` of ``square_mm`` with ``marker_mm`` markers, DICT_4X4_250,
    ids continuing from wall to wall), ``aprilgrid-box`` (``squares`` tags of ``square_mm``, the gaps
    ``spacing`` times that, ids continuing) or ``dots-box`` (a ``squares`` grid of dots, ``square_mm`` across by
    ``marker_mm`` down).  ``chessboard``: (cols, rows, square_mm) of the inner corners of the
    board for the direct views (intrinsics), or None.  ``board_z_mm``: the boards' centre along
    the axis (default: the middle of :func:`mirror_band_z`).

    Returns the setup (no images yet: ``views`` and ``chessboard_views`` empty; its ``extra["box"]``
    holds the box: ``width_mm``, ``mirror_distance_mm``, the band the mirror sees, and per board
    ``T_box_board`` as ``{"R", "t"}``) and warnings (a board taller than the band, wider than its
    wall, or ids beyond the dictionary).
    """
    if target not in TARGETS:
        raise ValueError(f"unknown target {target!r} (known: {', '.join(TARGETS)})")
    defaults = {
        "charuco-box": ((8, 3), 18.0, 13.5),
        "aprilgrid-box": ((6, 2), 18.0, 0.0),
        "dots-box": ((3, 3), 50.0, 20.0),
    }
    d_sq, d_s, d_m = defaults[target]
    squares = tuple(squares or d_sq)
    square_mm = float(square_mm or d_s)
    marker_mm = float(marker_mm or d_m)
    half = width_mm / 2
    z_apex, z_rim = mirror_band_z(mirror_radius, mirror_height, mirror_distance_mm, half)
    z_lo, z_hi = min(z_apex, z_rim), max(z_apex, z_rim)
    zc = 0.5 * (z_lo + z_hi) if board_z_mm is None else float(board_z_mm)
    warnings: list[str] = []
    boards: dict[str, BoardLayout] = {}
    poses = {}
    for j in range(n_walls):
        name = f"wall{j}"
        spec, pts, dot_r = _wall_spec(target, j, squares, square_mm, marker_mm, spacing)
        az = 360.0 * j / n_walls
        th = math.radians(az)
        x_b = np.array([-math.sin(th), math.cos(th), 0.0])  # along increasing azimuth
        y_up = spec is not None and spec["type"] == "aprilgrid"
        y_b = np.array([0.0, 0.0, 1.0 if y_up else -1.0])  # the print's top edge away from the camera
        R = np.round(np.stack([x_b, y_b, np.cross(x_b, y_b)], axis=1), 12) + 0.0
        x0, y0, x1, y1 = _extent(spec, pts, dot_r)
        centre_board = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
        centre_box = np.array([half * math.cos(th), half * math.sin(th), zc])
        t = centre_box - R @ centre_board
        poses[name] = {"R": R.tolist(), "t": t.tolist()}
        cols, rows = grid_shape(spec) if spec is not None else squares
        boards[name] = BoardLayout(
            pts, cols, rows, azimuth_deg=az, x_dir=1, y_dir=1 if y_up else -1, dot_radius_mm=dot_r, target=spec
        )
        if y1 - y0 > z_hi - z_lo:
            warnings.append(
                f"{name}: {y1 - y0:.0f} mm tall, but the mirror sees {z_hi - z_lo:.0f} mm of the wall "
                f"(z {z_lo:.0f}..{z_hi:.0f} mm)"
            )
        wall_len = 2 * half * math.tan(math.pi / n_walls)
        if x1 - x0 > wall_len:
            warnings.append(f"{name}: {x1 - x0:.0f} mm wide, wider than its wall ({wall_len:.0f} mm)")
    chess = []
    if chessboard is not None:
        c, r, s = chessboard
        spec = {"type": "chessboard", "inner": [int(c), int(r)], "square_mm": float(s)}
        boards["chess"] = BoardLayout(board_points(spec), int(c), int(r), target=spec)
    setup = Setup(
        image_size=tuple(image_size),
        mirror_radius=float(mirror_radius),
        mirror_height=float(mirror_height),
        n_lasers=int(n_lasers),
        boards=boards,
        views=[],
        chessboard_views=chess,
        rigid_boards=[f"wall{j}" for j in range(n_walls)],
        extra={
            "box": {
                "frame": "the camera's at the sensor's nominal place: x right, y down, z along its axis, mm",
                "width_mm": float(width_mm),
                "mirror_distance_mm": float(mirror_distance_mm),
                "mirror_band_z_mm": [z_lo, z_hi],
                "T_box_board": poses,
            }
        },
    )
    return setup, warnings


def with_images(setup, views: list[str], direct: list[str]):
    """``setup`` with its images: ``views`` (catadioptric) and ``direct`` (views of its one direct-view
    board), names relative to the image folder.  A copy; ``setup`` is left as it is."""
    import copy

    out = copy.copy(setup)
    out.views = list(views)
    boards = [k for k, b in setup.boards.items() if b.azimuth_deg is None]
    if direct and len(boards) != 1:
        raise ValueError(f"direct views need one board seen directly in the setup, found {len(boards)}: {boards}")
    out.chessboard_views = [(name, boards[0]) for name in direct]
    return out


def write_targets(setup: Setup, out_dir, source: str = "setup.json") -> tuple[list, str]:
    """Write a true-scale PDF per board of ``setup`` and the build sheet into ``out_dir``.

    Returns ``([(board, pdf path, PagePlan), ...], build sheet path)``.
    """
    from pathlib import Path

    from .printable import write_board_pdf

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    pages = []
    for name, b in setup.boards.items():
        path = out / f"{name}.pdf"
        plan = write_board_pdf(path, name, b.target, b.points, dot_radius_mm=b.dot_radius_mm, source=source)
        pages.append((name, path, plan))
    sheet = write_build_sheet(setup, out, {n: (p, plan) for n, p, plan in pages}, source)
    return pages, sheet


def _board_segment(setup: Setup, name: str, b: BoardLayout, box: dict | None) -> tuple[np.ndarray, bool]:
    """The board's printed width as a segment in the top view (box x, y in mm), and whether it is exact."""
    from .printable import board_drawing

    x0, y0, x1, y1 = board_drawing(b.target, b.points, b.dot_radius_mm).extent
    pose = None if box is None else box.get("T_box_board", {}).get(name)
    if pose is not None:
        R, t = np.asarray(pose["R"], float), np.asarray(pose["t"], float)
        ends = np.array([[x0, (y0 + y1) / 2, 0.0], [x1, (y0 + y1) / 2, 0.0]]) @ R.T + t
        return ends[:, :2], True
    # only the azimuth is known: a segment of the board's width across it, on a nominal ring
    th = math.radians(b.azimuth_deg)
    ring = 0.5 * float(box["width_mm"]) if box and "width_mm" in box else 150.0
    centre = ring * np.array([math.cos(th), math.sin(th)])
    along = b.x_dir * np.array([-math.sin(th), math.cos(th)])
    return np.stack([centre - along * (x1 - x0) / 2, centre + along * (x1 - x0) / 2]), False


def write_build_sheet(setup: Setup, out_dir, pages: dict, source: str = "setup.json"):
    """The build sheet: ``build_sheet.md`` and its drawing ``build_sheet.png`` in ``out_dir``.

    The drawing is the box seen along the camera's axis from behind the camera (x right, y down:
    the image's azimuths), each wall board where ``setup.extra["box"]["T_box_board"]`` puts it, or,
    without it, across its ``azimuth_deg`` on a nominal ring; an arrow gives each board's x.  The
    Markdown lists each board's print, place and orientation.  Returns the Markdown's path.
    """
    from pathlib import Path

    from ..observations.formats import write_text_atomic
    from ..support.mpl import pyplot

    plt = pyplot()
    from ..observations.targets import describe

    out = Path(out_dir)
    box = setup.extra.get("box") if isinstance(setup.extra.get("box"), dict) else None
    walls = {k: b for k, b in setup.boards.items() if b.azimuth_deg is not None}
    fig, ax = plt.subplots(figsize=(7, 7))
    if box and "width_mm" in box:
        h = 0.5 * float(box["width_mm"])
        ax.plot([-h, h, h, -h, -h], [-h, -h, h, h, -h], color="0.4", lw=1.5)
    r = setup.mirror_radius
    ax.add_patch(plt.Circle((0, 0), r, fill=False, color="tab:blue"))
    ax.annotate("mirror", (0, 0), ha="center", va="center", fontsize=8, color="tab:blue")
    if setup.laser_azimuth_deg is not None:
        for i, a in enumerate(setup.laser_azimuth_deg):
            if a is None:  # a ring laser: no azimuth
                continue
            d = np.array([math.cos(math.radians(a)), math.sin(math.radians(a))])
            ax.plot(*np.stack([1.2 * r * d, 2.5 * r * d]).T, color="tab:red", lw=1)
            ax.annotate(f"L{i}", 2.8 * r * d, fontsize=7, color="tab:red", ha="center", va="center")
    exact = True
    for name, b in walls.items():
        seg, known = _board_segment(setup, name, b, box)
        exact &= known
        ax.plot(*seg.T, color="k", lw=5, solid_capstyle="butt")
        mid, d = seg.mean(axis=0), seg[1] - seg[0]
        ax.annotate("", seg[1] + 0.05 * d, seg[1] - 0.15 * d, arrowprops={"arrowstyle": "->", "color": "tab:green"})
        inward = -mid / max(np.linalg.norm(mid), 1e-9)
        ax.annotate(f"{name}\n{b.azimuth_deg:g} deg", mid + 28 * inward, ha="center", va="center", fontsize=8)
    ax.plot([0, 40], [0, 0], color="0.6", lw=0.8)
    ax.annotate("x", (44, 0), fontsize=8, color="0.4", va="center")
    ax.plot([0, 0], [0, 40], color="0.6", lw=0.8)
    ax.annotate("y", (0, 46), fontsize=8, color="0.4", ha="center")
    ax.set_aspect("equal")
    ax.invert_yaxis()  # y down, as in the image
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    note = "" if exact else " (boards without a pose in setup.json's box: drawn at their azimuth only)"
    ax.set_title(f"The box seen along the camera's axis, from behind the camera{note}", fontsize=9)
    png = out / "build_sheet.png"
    fig.savefig(png, dpi=120, bbox_inches="tight")
    plt.close(fig)

    lines = [
        f"# Build sheet: {source}",
        "",
        "![the box seen along the camera's axis](build_sheet.png)",
        "",
        "The drawing looks along the camera's axis from behind the camera: x right, y down, azimuths "
        "from +x towards +y, as in the image. Green arrows: each board's x (left to right on its print).",
        "",
        "1. Print each PDF at 100 % (actual size; no fit to page, no scaling) and measure its scale bar: "
        "it must be 100 mm. Where it is not, print again, or scale the board's sizes in setup.json by what "
        "you measured.",
        "2. Glue each print flat on a rigid board; keep the white border around it.",
        "3. Mount each wall board facing the sensor, upright, as the table says.",
        "",
        "| board | print | target | place | orientation |",
        "|---|---|---|---|---|",
    ]
    for name, b in setup.boards.items():
        path, plan = pages.get(name, (None, None))
        paper = "" if plan is None else f" ({plan.paper}{' landscape' if plan.landscape else ''})"
        print_ = f"[{Path(path).name}]({Path(path).name}){paper}" if path is not None else "-"
        if b.azimuth_deg is None:
            place, orient = "held in front of the camera (direct views)", "any"
        else:
            pose = None if box is None else box.get("T_box_board", {}).get(name)
            place = f"azimuth {b.azimuth_deg:g} deg"
            if pose is not None:
                x0, y0, x1, y1 = _extent_of(b)
                c = np.asarray(pose["R"]) @ np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0]) + np.asarray(pose["t"])
                c = np.round(c) + 0.0  # no -0
                place += f"; its centre at ({c[0]:.0f}, {c[1]:.0f}, {c[2]:.0f}) mm in the box"
            y_print = "up" if b.target is not None and b.target["type"] == "aprilgrid" else "down"
            away = (b.y_dir == 1) == (y_print == "down")
            orient = (
                f"x_dir {b.x_dir:+d}: its x runs {'with' if b.x_dir == 1 else 'against'} increasing azimuth; "
                f"y_dir {b.y_dir:+d}: the print's {'bottom' if away else 'top'} edge away from the image centre"
            )
        lines.append(f"| {name} | {print_} | {describe(b.target, len(b.points))} | {place} | {orient} |")
    if box and "mirror_band_z_mm" in box:
        lo, hi = box["mirror_band_z_mm"]
        lines += [
            "",
            f"The mirror sees the walls between z = {lo:.0f} and {hi:.0f} mm along the camera's axis "
            f"(the mirror's apex {box.get('mirror_distance_mm', float('nan')):g} mm in front of the lens; "
            "negative z is behind the lens).",
        ]
    lines += [
        "",
        "With a cone seen apex first, the image centre sees the part of a wall nearest the camera: "
        "mount a print whose top edge is away from the image centre with that edge away from the camera.",
        "",
    ]
    md = out / "build_sheet.md"
    write_text_atomic(md, "\n".join(lines))
    return md


def _extent_of(b: BoardLayout):
    return _extent(b.target, b.points, b.dot_radius_mm)
