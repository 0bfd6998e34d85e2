"""Printable targets: a true-scale, vector PDF page per board, and the box's build sheet.

Each board is first drawn in its own frame (:func:`board_drawing`: black rectangles and discs
in millimetres, the frame of :mod:`slcvjax.observations.targets`), then placed on a page
(:func:`plan_page`: the smallest ISO A page, A4 to A0, either way round, that holds the board,
its caption and a 100 mm scale bar inside 12 mm margins; a custom page beyond A0) and written
as a one-page PDF by matplotlib's PDF backend (:func:`board_page`, :func:`write_pdf`): a figure
of the page's size, one axes over all of it in page millimetres, the board one filled vector
path, so the print is exact at any printer resolution (1 mm = 72 / 25.4 pt in the PDF).

- chessboard: ``(cols + 1) x (rows + 1)`` squares, the top-left one black;
- charuco: OpenCV's layout (:func:`~slcvjax.observations.targets.charuco_marker_squares`), each
  marker's bits from ``cv2.aruco``'s dictionary, drawn as vector cells centred in its square;
- aprilgrid: Kalibr's layout (tag 0 at the bottom left, each tag's bits as Kalibr's PDF draws
  them: OpenCV's ``DICT_APRILTAG_36h11`` image turned by 180 degrees, a one-bit black border),
  with Kalibr's black squares in the gaps at every tag corner;
- dots: a black disc of ``dot_radius_mm`` at each point.

The build sheet (:func:`slcvjax.images.targetbox.write_build_sheet`) is Markdown beside a PNG drawing of the box seen
along the camera's axis, one line per board: its print, its place and which way it faces.
"""

import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..observations.targets import charuco_marker_squares, describe, marker_ids

PT_PER_MM = 72.0 / 25.4
MARGIN_MM = 12.0  # every printer prints this far from the paper's edge
CAPTION_MM = 30.0  # the caption and scale bar below the board
GAP_MM = 10.0  # between the board and its caption (the axes drawn there on a y-up board)
SCALE_BAR_MM = 100.0
PAPERS_MM = {
    "A4": (210.0, 297.0),
    "A3": (297.0, 420.0),
    "A2": (420.0, 594.0),
    "A1": (594.0, 841.0),
    "A0": (841.0, 1189.0),
}
DEFAULT_DOT_RADIUS_MM = 1.6


# --------------------------------------------------------------------------- drawing a board


@dataclass
class Drawing:
    """A board's print in its own frame (millimetres).

    Attributes:
        extent: (x0, y0, x1, y1), the printed board's region in board coordinates.
        rects: (K, 4) black rectangles ``(x, y, w, h)``: the corner of least x and y, then sizes.
        discs: (D, 3) black discs ``(x, y, r)``.
        y_up: the board's y runs up the page (Kalibr's aprilgrid); else down (the others).
        origin_note: where the board frame's origin is on the print, in words.
    """

    extent: tuple[float, float, float, float]
    rects: np.ndarray
    discs: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    y_up: bool = False
    origin_note: str = ""


def _marker_cells(dictionary: str, marker_id: int) -> np.ndarray:
    """A marker's cells, its one-bit black border included: ``(n, n)`` bool, True black, row 0 on top."""
    import cv2

    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    n = d.markerSize + 2
    return d.generateImageMarker(int(marker_id), n, borderBits=1) < 128


def _cell_rects(cells: np.ndarray, x0: float, y0: float, cell: float, y_up: bool) -> list[tuple]:
    """Black cells as rectangles, each row's runs merged; row 0 at the top of the print."""
    out = []
    n_rows = cells.shape[0]
    for i, row in enumerate(cells):
        j = 0
        while j < len(row):
            if not row[j]:
                j += 1
                continue
            k = j
            while k < len(row) and row[k]:
                k += 1
            # y of the row's edge of least y: y down -> row i at y0 + i cell; y up -> the top row highest
            y = y0 + (n_rows - 1 - i) * cell if y_up else y0 + i * cell
            out.append((x0 + j * cell, y, (k - j) * cell, cell))
            j = k
    return out


def board_drawing(spec: dict | None, points: np.ndarray, dot_radius_mm: float | None = None) -> Drawing:
    """The print of a board: its type's ``spec`` (None: dots) and its ``(N, 3)`` points in mm."""
    kind = "dots" if spec is None else spec["type"]
    if kind == "chessboard":
        (cols, rows), s = spec["inner"], spec["square_mm"]
        rects = [((c - 1) * s, (r - 1) * s, s, s) for r in range(rows + 1) for c in range(cols + 1) if (c + r) % 2 == 0]
        return Drawing((-s, -s, cols * s, rows * s), np.array(rects), origin_note="the first inner corner")
    if kind == "charuco":
        (sx, sy), s, m = spec["squares"], spec["square_mm"], spec["marker_mm"]
        rects = [(c * s, r * s, s, s) for r in range(sy) for c in range(sx) if (c + r) % 2 == 0]
        n_bits = _marker_cells(spec["dictionary"], 0).shape[0]
        for (c, r), mid in zip(charuco_marker_squares((sx, sy)), marker_ids(spec), strict=True):
            cells = _marker_cells(spec["dictionary"], mid)
            rects += _cell_rects(cells, c * s + (s - m) / 2, r * s + (s - m) / 2, m / n_bits, y_up=False)
        return Drawing((0.0, 0.0, sx * s, sy * s), np.array(rects), origin_note="the board's top-left corner")
    if kind == "aprilgrid":
        cols, rows, tag, spacing = spec["tag_cols"], spec["tag_rows"], spec["tag_mm"], spec["spacing"]
        gap, pitch = spacing * tag, (1.0 + spacing) * tag
        rects, corners = [], set()
        for t, mid in enumerate(marker_ids(spec)):
            x, y = (t % cols) * pitch, (t // cols) * pitch
            cells = np.rot90(_marker_cells("DICT_APRILTAG_36h11", mid), 2)  # Kalibr's orientation
            rects += _cell_rects(cells, x, y, tag / cells.shape[0], y_up=True)
            corners |= {(x - gap, y - gap), (x + tag, y - gap), (x + tag, y + tag), (x - gap, y + tag)}
        rects += [(round(cx, 9), round(cy, 9), gap, gap) for cx, cy in sorted(corners)]
        x1, y1 = (cols - 1) * pitch + tag + gap, (rows - 1) * pitch + tag + gap
        return Drawing(
            (-gap, -gap, x1, y1), np.array(rects), y_up=True, origin_note="tag 0's bottom-left corner (Kalibr's)"
        )
    pts = np.asarray(points, float)[:, :2]
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    spacing = float(np.min(d[d > 0])) if len(pts) > 1 else 10.0
    r = dot_radius_mm if dot_radius_mm is not None else min(DEFAULT_DOT_RADIUS_MM, spacing / 4)
    pad = max(3 * r, 5.0)
    lo, hi = pts.min(axis=0) - pad, pts.max(axis=0) + pad
    discs = np.concatenate([pts, np.full((len(pts), 1), r)], axis=1)
    return Drawing((lo[0], lo[1], hi[0], hi[1]), np.zeros((0, 4)), discs, origin_note="the first dot")


# --------------------------------------------------------------------------- the page


@dataclass
class PagePlan:
    """Where a board goes on its page; page coordinates in mm from the bottom-left, y up.

    Attributes:
        paper: ``A4`` ... ``A0`` or ``custom``; ``landscape`` where turned.
        size_mm: the page's (width, height).
        board_corner_mm: the page position of the board extent's corner of least board x, and of
            least board y (y_up) or greatest board y (y down): the print's bottom-left or top-left.
        extent: the board's extent in its own frame (:attr:`Drawing.extent`).
        y_up: the board's y runs up the page.
        scale_bar_mm: (x0, y0, length): the scale bar's left end and its length.
    """

    paper: str
    landscape: bool
    size_mm: tuple[float, float]
    board_corner_mm: tuple[float, float]
    extent: tuple[float, float, float, float]
    y_up: bool
    scale_bar_mm: tuple[float, float, float]

    def to_page_mm(self, xy: np.ndarray) -> np.ndarray:
        """Board coordinates ``(..., 2)`` mm -> page coordinates ``(..., 2)`` mm (from the bottom-left, y up)."""
        xy = np.asarray(xy, float)
        x = self.board_corner_mm[0] + (xy[..., 0] - self.extent[0])
        if self.y_up:
            y = self.board_corner_mm[1] + (xy[..., 1] - self.extent[1])
        else:
            y = self.board_corner_mm[1] - (xy[..., 1] - self.extent[1])
        return np.stack([x, y], axis=-1)


def plan_page(drawing: Drawing) -> PagePlan:
    """The smallest ISO A page (A4 to A0, portrait first) holding the board, its caption and the scale
    bar inside the margins; a custom page of exactly that size where even A0 is too small."""
    x0, y0, x1, y1 = drawing.extent
    bw, bh = x1 - x0, y1 - y0
    need_w = max(bw, SCALE_BAR_MM + 40.0) + 2 * MARGIN_MM
    need_h = bh + GAP_MM + CAPTION_MM + 2 * MARGIN_MM
    size, paper, landscape = (need_w, need_h), "custom", False
    for name, (w, h) in PAPERS_MM.items():
        options = [((w, h), False), ((h, w), True)]
        fit = [(dims, land) for dims, land in options if dims[0] >= need_w and dims[1] >= need_h]
        if fit:
            size, landscape = fit[0]
            paper = name
            break
    pw, ph = size
    # the block (board, gap, caption) centred on the page
    top = (ph + bh + GAP_MM + CAPTION_MM) / 2
    left = (pw - bw) / 2
    corner = (left, top - bh) if drawing.y_up else (left, top)
    bar = ((pw - SCALE_BAR_MM) / 2, top - bh - GAP_MM - CAPTION_MM + 6.0, SCALE_BAR_MM)
    return PagePlan(paper, landscape, (pw, ph), corner, drawing.extent, drawing.y_up, bar)


# matplotlib's own defaults (a user's matplotlibrc may set usetex, a tight bbox, another PDF font
# type), then Helvetica as one of the PDF's 14 standard fonts (not embedded, each string written
# whole) and compressed content streams
_PDF_RC = {"pdf.use14corefonts": True, "pdf.compression": 6}
_FONT, _WEIGHT = "Helvetica", "medium"  # the weight Helvetica.afm declares


def _mpl_context():
    """The rcParams the page is built and written under (see ``_PDF_RC``)."""
    import contextlib

    from matplotlib import rc_context, style

    stack = contextlib.ExitStack()
    stack.enter_context(style.context("default"))
    stack.enter_context(rc_context(_PDF_RC))
    return stack


def _rects_path(rects: np.ndarray, discs: np.ndarray):
    """One compound path of the black rectangles ``(x, y, w, h)`` and discs ``(x, y, r)``, in page mm;
    all counter-clockwise, so the non-zero fill is their union (no seams where cells meet)."""
    from matplotlib.path import Path as MplPath

    x, y, w, h = np.asarray(rects, float).reshape(-1, 4).T
    verts = np.stack([np.stack([x, y], -1), np.stack([x + w, y], -1), np.stack([x + w, y + h], -1)], axis=1)
    verts = np.concatenate([verts, np.stack([x, y + h], -1)[:, None], np.stack([x, y], -1)[:, None]], axis=1)
    codes = np.tile([MplPath.MOVETO, MplPath.LINETO, MplPath.LINETO, MplPath.LINETO, MplPath.CLOSEPOLY], len(x))
    paths = [MplPath(verts.reshape(-1, 2), codes)]
    paths += [MplPath.circle((cx, cy), r) for cx, cy, r in np.asarray(discs, float).reshape(-1, 3)]
    return MplPath.make_compound_path(*paths)


def _page_figure(width_mm: float, height_mm: float):
    """A figure of the page's size, one axes over all of it, its data units page mm from the
    bottom-left (y up): 1 mm = 72 / 25.4 pt in the PDF, the same scale along x and y."""
    from matplotlib.backends.backend_pdf import FigureCanvasPdf
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_mm / 25.4, height_mm / 25.4), dpi=72, frameon=False)
    FigureCanvasPdf(fig)
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0), frameon=False)
    ax.set_axis_off()
    ax.set_xlim(0.0, width_mm)
    ax.set_ylim(0.0, height_mm)
    return fig, ax


def _rect(ax, x: float, y: float, w: float, h: float, fill: bool = True, line_mm: float = 0.25) -> None:
    from matplotlib.patches import Rectangle

    style = {"facecolor": "black", "edgecolor": "none"} if fill else {"fill": False, "edgecolor": "black"}
    ax.add_patch(Rectangle((x, y), w, h, linewidth=line_mm * PT_PER_MM, clip_on=False, **style))


def _line(ax, x0: float, y0: float, x1: float, y1: float, line_mm: float = 0.25) -> None:
    ax.plot([x0, x1], [y0, y1], color="black", lw=line_mm * PT_PER_MM, solid_capstyle="butt", clip_on=False)


def _text(ax, x: float, y: float, s: str, size_pt: float = 8.0) -> None:
    """``s`` from its baseline's left end at ``(x, y)`` mm; plain text (no mathtext), ASCII."""
    s = s.encode("ascii", "replace").decode("ascii")
    kw = {"ha": "left", "va": "baseline", "color": "black", "clip_on": False}
    ax.text(x, y, s, fontsize=size_pt, family=_FONT, weight=_WEIGHT, usetex=False, parse_math=False, **kw)


def _arrow(ax, start: np.ndarray, direction: np.ndarray, length: float, label: str) -> None:
    from matplotlib.patches import Polygon

    d = direction / np.linalg.norm(direction)
    normal = np.array([-d[1], d[0]])
    tip = start + length * d
    _line(ax, *start, *(tip - 1.5 * d), line_mm=0.35)
    head = np.array([tip, tip - 2.5 * d + 1.0 * normal, tip - 2.5 * d - 1.0 * normal])
    ax.add_patch(Polygon(head, closed=True, facecolor="black", edgecolor="none", clip_on=False))
    _text(ax, *(tip + 1.5 * d - np.array([1.0, 1.2])), label, 8)


def board_page(name: str, spec: dict | None, points: np.ndarray, dot_radius_mm: float | None = None, source: str = ""):
    """A board's page as a matplotlib ``Figure`` (write it with :func:`write_pdf`): the drawing
    placed by :func:`plan_page`, its caption, axes and scale bar.  Returns ``(figure, plan, drawing)``."""
    from matplotlib.patches import PathPatch

    drawing = board_drawing(spec, points, dot_radius_mm)
    plan = plan_page(drawing)
    with _mpl_context():
        fig, ax = _page_figure(*plan.size_mm)
        rects = np.asarray(drawing.rects, float).reshape(-1, 4)
        lo = np.minimum(plan.to_page_mm(rects[:, :2]), plan.to_page_mm(rects[:, :2] + rects[:, 2:]))
        discs = np.asarray(drawing.discs, float).reshape(-1, 3)
        discs_page = np.concatenate([plan.to_page_mm(discs[:, :2]), discs[:, 2:]], axis=1)
        board = PathPatch(_rects_path(np.concatenate([lo, rects[:, 2:]], axis=1), discs_page), clip_on=False)
        board.set(facecolor="black", edgecolor="none")
        ax.add_patch(board)
        # the board frame's axes, just outside the board's corner nearest its origin
        x0, y0, x1, y1 = drawing.extent
        corner = plan.to_page_mm(np.array([x0, y0]))
        ex, ey = np.array([1.0, 0.0]), np.array([0.0, 1.0 if plan.y_up else -1.0])
        start = corner - 4.0 * ex - 4.0 * ey
        _arrow(ax, start, ex, 12.0, "x")
        _arrow(ax, start, ey, 12.0, "y")
        # the caption and the scale bar
        bx, by, length = plan.scale_bar_mm
        lines = [
            f"{name}: {describe(spec, len(points))}",
            f"{len(points)} points; board frame: origin at {drawing.origin_note}, x right, "
            f"y {'up' if plan.y_up else 'down'}, mm",
            f"Print at 100 % (actual size, no fit to page) on {plan.paper}"
            f"{' landscape' if plan.landscape else ''}: the bar below must measure {length:g} mm.",
        ]
        if source:
            lines.append(f"slcvjax target {source}")
        top = by + CAPTION_MM - 6.0 - 3.0
        for i, s in enumerate(lines):
            _text(ax, bx - 20.0, top - 4.2 * i, s, 8 if i else 9)
        _rect(ax, bx, by, length, 2.0, fill=False, line_mm=0.2)
        for k in range(0, int(round(length / 10)), 2):
            _rect(ax, bx + 10.0 * k, by, 10.0, 2.0)
        for k in range(0, int(round(length / 10)) + 1):
            _line(ax, bx + 10.0 * k, by - 1.5, bx + 10.0 * k, by, line_mm=0.2)
        _text(ax, bx, by - 5.0, "0", 7)
        _text(ax, bx + length - 8.0, by - 5.0, f"{length:g} mm", 7)
    return fig, plan, drawing


def pdf_bytes(fig) -> bytes:
    """A page of :func:`board_page` as PDF bytes, by matplotlib's PDF backend: the page exactly the
    figure's size (no bbox cropping), no creation date, so the same board gives the same bytes."""
    import io

    buf = io.BytesIO()
    with _mpl_context():
        fig.savefig(buf, format="pdf", bbox_inches=None, metadata={"Creator": "slcvjax", "CreationDate": None})
    return buf.getvalue()


def write_pdf(fig, path: str | os.PathLike) -> None:
    """Write a page of :func:`board_page` to ``path`` atomically (a temporary file beside it, then renamed)."""
    data = pdf_bytes(fig)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_board_pdf(path: str | os.PathLike, name: str, spec: dict | None, points: np.ndarray, **kw) -> PagePlan:
    """Write a board's true-scale page to ``path`` (see :func:`board_page`); returns its plan."""
    fig, plan, _ = board_page(name, spec, points, **kw)
    write_pdf(fig, path)
    return plan


def rasterize(drawing: Drawing, px_per_mm: float, border_mm: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """A drawing as an 8-bit image (black 0 on white 255), pixel centres sampled, y down the image.

    Returns ``(image (H, W) uint8, origin)``: board point ``(x, y)`` lies at pixel
    ``(u, v) = ((x - origin[0]) * px_per_mm - 0.5, (origin[1] - y) * px_per_mm - 0.5)`` for a
    y-up drawing, ``(y - origin[1]) * px_per_mm - 0.5`` for v of a y-down one.  For tests and
    previews; the PDF is the print.
    """
    x0, y0, x1, y1 = drawing.extent
    w = int(math.ceil((x1 - x0 + 2 * border_mm) * px_per_mm))
    h = int(math.ceil((y1 - y0 + 2 * border_mm) * px_per_mm))
    u = (np.arange(w) + 0.5) / px_per_mm + x0 - border_mm
    if drawing.y_up:
        origin = np.array([x0 - border_mm, y1 + border_mm])
        v = origin[1] - (np.arange(h) + 0.5) / px_per_mm
    else:
        origin = np.array([x0 - border_mm, y0 - border_mm])
        v = origin[1] + (np.arange(h) + 0.5) / px_per_mm
    black = np.zeros((h, w), bool)
    for x, y, rw, rh in drawing.rects:
        cols = (u >= x) & (u < x + rw)
        rows = (v >= y) & (v < y + rh)
        black |= rows[:, None] & cols[None, :]
    for x, y, r in drawing.discs:
        black |= (u[None, :] - x) ** 2 + (v[:, None] - y) ** 2 <= r * r
    return np.where(black, 0, 255).astype(np.uint8), origin
