"""The detector: laser spots, board dots, rim edge pixels and chessboard corners from images.

OpenCV stays here, at the edge.  A catadioptric image is read in two channels:
green shows the scene (white walls, dark dots; 650 nm laser light barely reaches
it) and red minus green shows the laser spots.  Steps, per image:

1. **Mirror**: Otsu's threshold on green, the bright regions of the mirror's view (pieces of
   it where dark wedges cut it up to the rim) and their convex hull are the mirror's disc; an
   ellipse fitted to their outline on the hull gives the image centre used for azimuths
   (``atan2(v - cv, u - cu)``, degrees, so increasing azimuth turns from +u towards +v) and a
   first rim.
2. **Rim**: in each sector of azimuth about that centre, a blurred step fitted to the
   pixels across the ellipse gives the edge's sub-pixel place.
3. **Dots**: dark connected regions inside the disc (against the wall's local level, away
   from its edge and not the dark centre), each located by its darkness-weighted centroid
   over its whole faint image; fainter streaks are kept apart, as evidence for a grid only.
4. **Spots**: connected regions of red minus green above a threshold, each located
   by the centroid of red over green over its whole profile.

Then, per image, the dots are grouped by azimuth into the boards of the setup
(each wall target has a nominal azimuth and the directions of its x and y axes
in the image), and a group is ordered into its grid (rows by image radius,
columns by azimuth) only where the image says which dot is which (:func:`order_grid`).  Across the
whole folder the spots are labelled with their lasers: the lasers are fixed on
the sensor, so each one's spots share an azimuth in every image.  Anything
that cannot be identified without guessing is left out and reported.
"""

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..observations.formats import (
    LASER_KINDS,
    CalibrationViewObs,
    FormatError,
    Observations,
    SpotObs,
    StripeObs,
    ViewObs,
    load_json,
    read_sensor_fields,
)
from ..observations.targets import check_disjoint_ids, grid_shape, read_board, spec_json
from .coded import coded_walls, detect_coded_view, detect_direct
from .disc import MirrorDisc, ellipse_radius, find_mirror
from .light import DEFAULT_LIGHT, DetectionSettings, laser_light, read_detection, scene_channel
from .stripes import StripeSamples, find_stripes

SETUP_FORMAT = "slcv-setup/1"


# --------------------------------------------------------------------------- setup


@dataclass
class BoardLayout:
    """A board as the detector knows it.

    Attributes:
        points: (M, 3) board points, mm, ``z = 0``, ordered x fastest on a ``cols x rows`` grid.
        cols, rows: the grid's size.
        azimuth_deg: for a target seen through the mirror, the image azimuth where it is
            nominally seen (None for a chessboard seen directly).
        x_dir: +1 if the board's x grows with the image azimuth, -1 if it shrinks.
        y_dir: +1 if the board's y grows with the distance from the image centre, -1 if it shrinks.
        dot_radius_mm: the printed dots' radius, when known (for the centroids' correction).
        target: the board's ``type`` and its fields (``slcvjax.observations.targets.read_board``'s
            spec: chessboard, charuco, aprilgrid), or None for a grid of dots given by its points.
    """

    points: np.ndarray
    cols: int
    rows: int
    azimuth_deg: float | None = None
    x_dir: int = 1
    y_dir: int = 1
    dot_radius_mm: float | None = None
    target: dict | None = None


@dataclass
class Setup:
    """What a user knows before detection (``slcv-setup/1``): the images and what they show."""

    image_size: tuple[int, int]
    mirror_radius: float
    mirror_height: float
    n_lasers: int
    boards: dict[str, BoardLayout]
    views: list[str]
    chessboard_views: list[tuple[str, str]]
    laser_azimuth_deg: list[float] | None = None
    extra: dict = field(default_factory=dict)
    spot_sigma_mm: float | None = None  # the laser spots' Gaussian std on a surface, when known
    rigid_boards: list[str] = field(default_factory=list)  # targets fixed to each other (one box)
    # each laser's kind (point, plane, cone) in order, when the setup has line or ring lasers
    laser_kinds: list[str] | None = None
    stripe_sigma_mm: float | None = None  # the stripes' Gaussian std across them on a surface, when known
    light: DetectionSettings = field(default_factory=DetectionSettings)  # the lasers' colour, the spot threshold

    @property
    def kinds(self) -> list[str]:
        """Each laser's kind in order (``point`` for all where the setup gives none)."""
        return list(self.laser_kinds) if self.laser_kinds else ["point"] * self.n_lasers

    @property
    def point_lasers(self) -> list[int]:
        """The index of each point laser (they draw spots), in order."""
        return [i for i, k in enumerate(self.kinds) if k == "point"]

    @property
    def sheet_lasers(self) -> list[int]:
        """The index of each line or ring laser (they draw stripes), in order."""
        return [i for i, k in enumerate(self.kinds) if k != "point"]


def setup_to_json(setup: Setup) -> dict:
    """The ``slcv-setup/1`` document of a setup."""
    boards = {}
    for name, b in setup.boards.items():
        d: dict[str, Any] = {
            **spec_json(b.target),
            "points": np.asarray(b.points, float).tolist(),
            "cols": b.cols,
            "rows": b.rows,
        }
        if b.azimuth_deg is not None:
            d.update(azimuth_deg=float(b.azimuth_deg), x_dir=int(b.x_dir), y_dir=int(b.y_dir))
        if b.dot_radius_mm is not None:
            d["dot_radius_mm"] = float(b.dot_radius_mm)
        boards[name] = d
    doc = {
        "format": SETUP_FORMAT,
        "image_size": list(setup.image_size),
        "mirror_shape": {"kind": "cone", "radius": setup.mirror_radius, "height": setup.mirror_height},
        "n_lasers": setup.n_lasers,
        "laser_azimuth_deg": None
        if setup.laser_azimuth_deg is None
        else [None if a is None else float(a) for a in setup.laser_azimuth_deg],
        "boards": boards,
        "views": [{"image": v} for v in setup.views],
        "chessboard_views": [{"image": im, "board": b} for im, b in setup.chessboard_views],
    }
    if setup.spot_sigma_mm is not None:
        doc["spot_sigma_mm"] = float(setup.spot_sigma_mm)
    if setup.rigid_boards:
        doc["rigid_boards"] = list(setup.rigid_boards)
    if setup.laser_kinds:
        doc["laser_kinds"] = list(setup.laser_kinds)
    if setup.stripe_sigma_mm is not None:
        doc["stripe_sigma_mm"] = float(setup.stripe_sigma_mm)
    if not setup.light.is_default:
        doc["detection"] = setup.light.to_json()
    doc.update(setup.extra)
    return doc


def read_setup(path: str | Path) -> Setup:
    """Read and validate ``setup.json`` (raises :class:`FormatError` naming the file, field and index)."""
    ctx, doc = load_json(path)
    fmt = ctx.get(doc, "format", "", str)
    if fmt != SETUP_FORMAT:
        ctx.fail("format", f"expected {SETUP_FORMAT!r}, got {fmt!r}")
    (w, h), radius, height, n_lasers, shape = read_sensor_fields(ctx, doc)
    if shape is not None:
        ctx.fail("mirror_shape.kind", f"the detector supports the cone only, got {shape['kind']!r}")
    kinds_doc = ctx.get(doc, "laser_kinds", "", list, optional=True)
    laser_kinds = None
    if kinds_doc is not None:
        if len(kinds_doc) != n_lasers:
            ctx.fail("laser_kinds", f"expected {n_lasers} kinds (n_lasers), got {len(kinds_doc)}")
        for j, k in enumerate(kinds_doc):
            if k not in LASER_KINDS:
                ctx.fail(f"laser_kinds[{j}]", f"expected one of {', '.join(LASER_KINDS)}, got {json.dumps(k)[:40]}")
        laser_kinds = [str(k) for k in kinds_doc]
    az = ctx.get(doc, "laser_azimuth_deg", "", list, optional=True)
    laser_az = None
    if az is not None:
        if len(az) != n_lasers:
            ctx.fail("laser_azimuth_deg", f"expected a list of {n_lasers} numbers, got length {len(az)}")
        # a ring laser has no azimuth: null there (and for a laser whose azimuth is not known)
        laser_az = [None if a is None else ctx.number(a, f"laser_azimuth_deg[{i}]") for i, a in enumerate(az)]
        kinds = laser_kinds or ["point"] * n_lasers
        for i, a in enumerate(laser_az):
            if a is None and kinds[i] != "cone":
                ctx.fail(f"laser_azimuth_deg[{i}]", f"null, but laser {i} is a {kinds[i]} laser (only a ring has none)")
    boards = {}
    for name, b in ctx.get(doc, "boards", "", dict).items():
        where = f"boards.{name}"
        arr, spec = read_board(ctx, b, where)  # points given (dots) or generated by the board's type
        if spec is None:
            cols = ctx.integer(ctx.get(b, "cols", where), f"{where}.cols", lo=1)
            rows = ctx.integer(ctx.get(b, "rows", where), f"{where}.rows", lo=1)
            if cols * rows != len(arr):
                ctx.fail(f"{where}.points", f"{len(arr)} points do not make a {cols} x {rows} grid")
        else:
            cols, rows = grid_shape(spec)
            for key, n in (("cols", cols), ("rows", rows)):
                given = ctx.get(b, key, where, optional=True)
                if given is not None and given != n:
                    ctx.fail(f"{where}.{key}", f"its {spec['type']} has {n}, got {json.dumps(given)[:40]}")
        azimuth = ctx.get(b, "azimuth_deg", where, optional=True)
        layout = BoardLayout(arr, cols, rows, target=spec)
        if azimuth is not None:
            layout.azimuth_deg = ctx.number(azimuth, f"{where}.azimuth_deg")
            for key in ("x_dir", "y_dir"):
                v = ctx.get(b, key, where, optional=True)
                if v is not None and v not in (1, -1):
                    ctx.fail(f"{where}.{key}", f"must be 1 or -1, got {json.dumps(v)}")
                setattr(layout, key, 1 if v is None else int(v))
        dot_r = ctx.get(b, "dot_radius_mm", where, optional=True)
        if dot_r is not None:
            layout.dot_radius_mm = ctx.number(dot_r, f"{where}.dot_radius_mm")
            if not layout.dot_radius_mm > 0:
                ctx.fail(f"{where}.dot_radius_mm", f"must be positive, got {json.dumps(dot_r)}")
        boards[name] = layout
    check_disjoint_ids(ctx, {k: b.target for k, b in boards.items()})
    views = []
    for i, v in enumerate(ctx.list_of(doc, "views", "")):
        views.append(ctx.get(v, "image", f"views[{i}]", str))
    chess = []
    for i, v in enumerate(ctx.list_of(doc, "chessboard_views", "", optional=True)):
        where = f"chessboard_views[{i}]"
        im = ctx.get(v, "image", where, str)
        b = ctx.get(v, "board", where, str)
        if b not in boards:
            ctx.fail(f"{where}.board", f"unknown board {b!r} (known: {', '.join(sorted(boards)) or 'none'})")
        chess.append((im, b))
    if not any(b.azimuth_deg is not None for b in boards.values()) and views:
        ctx.fail("boards", "no board has an azimuth_deg: the detector cannot tell which target is which")
    spot_sigma = ctx.get(doc, "spot_sigma_mm", "", optional=True)
    if spot_sigma is not None:
        spot_sigma = ctx.number(spot_sigma, "spot_sigma_mm")
        if not spot_sigma > 0:
            ctx.fail("spot_sigma_mm", f"must be positive, got {json.dumps(spot_sigma)}")
    rigid = ctx.get(doc, "rigid_boards", "", list, optional=True) or []
    for i, b in enumerate(rigid):
        if not isinstance(b, str) or b not in boards:
            ctx.fail(f"rigid_boards[{i}]", f"unknown board {json.dumps(b)[:40]} (known: {', '.join(sorted(boards))})")
    stripe_sigma = ctx.get(doc, "stripe_sigma_mm", "", optional=True)
    if stripe_sigma is not None:
        stripe_sigma = ctx.number(stripe_sigma, "stripe_sigma_mm")
        if not stripe_sigma > 0:
            ctx.fail("stripe_sigma_mm", f"must be positive, got {json.dumps(stripe_sigma)}")
    known = {"format", "image_size", "mirror_shape", "n_lasers", "laser_azimuth_deg", "boards", "views"}
    known |= {"chessboard_views", "spot_sigma_mm", "rigid_boards", "laser_kinds", "stripe_sigma_mm", "detection"}
    extra = {k: v for k, v in doc.items() if k not in known}
    return Setup(
        (w, h), radius, height, n_lasers, boards, views, chess, laser_az, extra, spot_sigma, list(rigid),
        laser_kinds, stripe_sigma, read_detection(ctx, doc),
    )  # fmt: skip


# --------------------------------------------------------------------------- images


def _quiet_imread(path: Path) -> np.ndarray | None:
    """``cv2.imread`` (colour) without OpenCV's own log line on stderr for a broken file: the
    caller names the file in its error."""
    log = getattr(getattr(cv2, "utils", None), "logging", None)
    if log is None:
        return cv2.imread(str(path), cv2.IMREAD_COLOR)
    level = log.getLogLevel()
    log.setLogLevel(log.LOG_LEVEL_SILENT)
    try:
        return cv2.imread(str(path), cv2.IMREAD_COLOR)
    finally:
        log.setLogLevel(level)


def read_image(path: Path, size: tuple[int, int], source: str = "setup.json") -> np.ndarray:
    """Read a colour image and check its size against ``size`` (from ``source``); raises
    :class:`FormatError` naming the file."""
    if not path.is_file():
        raise FormatError(f"{path}: (file): no such image (listed in {source})")
    img = _quiet_imread(path)
    if img is None:
        raise FormatError(f"{path}: (file): not a readable image (truncated or not PNG/JPEG?)")
    h, w = img.shape[:2]
    if (w, h) != tuple(size):
        raise FormatError(f"{path}: (image): size {w}x{h}, {source} says {size[0]}x{size[1]}")
    return img


WALL_WINDOW = 1 / 6  # the local wall level: a median over a window of this fraction of the disc's radius


def wall_level(green: np.ndarray, disc: MirrorDisc) -> np.ndarray:
    """The local level of what the mirror shows, per pixel: the median of green over a square
    window of ``WALL_WINDOW`` of the disc's mean radius (odd, at least 15 px), the pixels off the
    disc or darker than half-way to the background (dots, dark wedges through a box's open
    corners) counted at the view's median level.  Light walls lit unevenly keep their dots' and
    spots' thresholds relative to the wall around them; a dot, or a squeezed row of them, covers
    far less than half a window."""
    if disc.wall_map is None:
        k = max(15, 2 * int(WALL_WINDOW * float(np.mean(disc.axes)) / 2) + 1)
        wall = disc.mask & (green > 0.5 * (disc.inside_level + disc.outside_level))
        filled = np.where(wall, np.clip(green, 0, 255), disc.inside_level).astype(np.uint8)
        disc.wall_map = cv2.medianBlur(filled, k).astype(float)
    return disc.wall_map


RIM_CLEAR = 0.05  # a rim sector is fitted only where no pixel off its edge strays from its side's level by this


def find_rim(green: np.ndarray, disc: MirrorDisc, n: int = 240, half: float = 4.0) -> np.ndarray:
    """Sub-pixel rim edge pixels, one per each of ``n`` equal sectors of azimuth about the disc's centre.

    In a sector, the pixels within ``half`` px of the fitted ellipse (along the radius) are
    fitted by a blurred step across the ellipse shifted by ``delta``: ``out + (in - out) *
    Phi(-(d - delta) / s)``, ``d`` the pixel centre's radial offset from the ellipse, ``Phi`` the
    normal CDF, with ``delta``, the blur ``s`` and both levels free (Gauss-Newton). The edge's
    place is estimated from every pixel across it, so its sub-pixel phase against the pixel grid
    does not bias it (a half-way crossing interpolated between pixels does, by a few hundredths
    of a pixel). The rim pixel is the ellipse's point at the sector's middle azimuth moved by
    ``delta``. A sector is skipped where a pixel more than 2 px inside the edge is darker than
    the mirror's level, or one outside brighter than the background's, by ``RIM_CLEAR`` of their
    contrast (a dark dot or a spot near the edge), at the image border, or where the fit does not
    settle within the band.
    """
    h, w = green.shape
    cu, cv_ = (float(c) for c in disc.centre)
    reach = max(disc.axes) + half + 2.0
    y0, y1 = int(max(np.floor(cv_ - reach), 0)), int(min(np.ceil(cv_ + reach) + 1, h))
    x0, x1 = int(max(np.floor(cu - reach), 0)), int(min(np.ceil(cu + reach) + 1, w))
    yy, xx = np.mgrid[y0:y1, x0:x1]
    theta = np.mod(np.arctan2(yy - cv_, xx - cu), 2 * np.pi)
    d = np.hypot(xx - cu, yy - cv_) - ellipse_radius(disc, theta)
    band = np.abs(d) <= half
    border = (yy == 0) | (xx == 0) | (yy == h - 1) | (xx == w - 1)
    d, theta, g, border = d[band], theta[band], green[y0:y1, x0:x1][band].astype(float), border[band]
    sector = np.minimum((theta / (2 * np.pi) * n).astype(int), n - 1)
    inside, outside = disc.inside_level, disc.outside_level
    clear = RIM_CLEAR * (inside - outside)
    stray = ((d < -2.0) & (g < inside - clear)) | ((d > 2.0) & (g > outside + clear)) | border
    bad = np.bincount(sector[stray], minlength=n) > 0
    order = np.argsort(sector, kind="stable")
    starts = np.searchsorted(sector[order], np.arange(n + 1))
    erf = np.vectorize(math.erf)
    out = []
    for k in range(n):
        idx = order[starts[k] : starts[k + 1]]
        if bad[k] or len(idx) < 12:
            continue
        dk, gk = d[idx], g[idx]
        p = np.array([0.0, 0.7, inside, outside])  # delta, s, in, out
        for _ in range(30):
            z = (dk - p[0]) / p[1]
            phi = 0.5 * (1.0 - erf(z / np.sqrt(2.0)))
            slope = (p[2] - p[3]) * np.exp(-0.5 * z**2) / np.sqrt(2 * np.pi) / p[1]
            jac = np.stack([slope, slope * z, phi, 1.0 - phi], axis=1)
            step = np.linalg.lstsq(jac, gk - (p[3] + (p[2] - p[3]) * phi), rcond=None)[0]
            p = p + step
            if not (abs(p[0]) < half / 2 and 0.1 < p[1] < half):
                break
            if abs(step[0]) < 1e-6:
                break
        if not (abs(p[0]) < half / 2 and 0.1 < p[1] < half and abs(step[0]) < 1e-6):
            continue
        mid = (k + 0.5) * 2 * np.pi / n
        r = float(ellipse_radius(disc, np.array([mid]))[0]) + p[0]
        out.append([cu + r * np.cos(mid), cv_ + r * np.sin(mid)])
    return np.array(out).reshape(-1, 2)


def _weighted_centroids(weight: np.ndarray, labels: np.ndarray, ids: list[int], grow: int = 2) -> np.ndarray:
    """Centroid of ``weight`` over each labelled region grown by ``grow`` px (weights clipped at 0)."""
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * grow + 1, 2 * grow + 1))
    out = []
    for k in ids:
        ys, xs = np.nonzero(labels == k)
        y0, y1 = max(ys.min() - grow, 0), min(ys.max() + grow + 1, labels.shape[0])
        x0, x1 = max(xs.min() - grow, 0), min(xs.max() + grow + 1, labels.shape[1])
        m = cv2.dilate((labels[y0:y1, x0:x1] == k).astype(np.uint8), kernel).astype(bool)
        # never take weight from a neighbouring region
        m &= (labels[y0:y1, x0:x1] == 0) | (labels[y0:y1, x0:x1] == k)
        wgt = np.where(m, np.clip(weight[y0:y1, x0:x1], 0, None), 0.0)
        s = wgt.sum()
        yy, xx = np.mgrid[y0:y1, x0:x1]
        out.append([(wgt * xx).sum() / s, (wgt * yy).sum() / s])
    return np.array(out).reshape(-1, 2)


DOT_CONTRAST = 0.3  # a dot's pixel: below the wall by this fraction of the wall-to-darkest contrast
DOT_SUPPORT = 0.04  # a dot's centroid sums over its pixels below the wall by this fraction, and 2 px around
SPOT_SUPPORT = 4.0  # grey levels of red over green (blurred): the faintest part of a spot its centroid sums
ROW_EVIDENCE = 0.15  # darker than the local wall by this fraction: something lies where a row would
FAINT_DOT_CONTRAST = ROW_EVIDENCE  # a streak this dark, apart from every darker region, is a dot too
RIM_EDGE = 4  # px: a dot's region must lie this far inside the mirror's outline to be detected


def find_dots(
    green: np.ndarray,
    disc: MirrorDisc,
    edge: int = RIM_EDGE,
    contrast: float = DOT_CONTRAST,
    support: float = DOT_SUPPORT,
    with_faint: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Dark dots inside the mirror's disc: (K, 2) darkness-weighted centroids (and, ``with_faint``,
    which of them are the faint ones, (K,) bool).

    A pixel is dark when it lies below the wall's local level (:func:`wall_level`) by ``contrast`` of the way to the
    darkest level (near the apex the cone squeezes a dot into a thin streak that the blur
    lightens to about half the full contrast). A region counts when it lies at least ``edge`` px
    inside the disc's outline, is not the image centre's dark body (regions holding the
    ellipse centre or larger than 2 % of the disc are skipped) and has at least 3 pixels. A
    region darker by ``FAINT_DOT_CONTRAST`` only, holding no darker region, counts on the same
    conditions (a small dot squeezed into a streak narrower than a pixel near the apex) when
    ``with_faint``. Its
    centroid sums the darkness over the pixels below the wall by ``support`` of that contrast that
    are connected to it (where no other dot's are), grown by 2 px: the whole of its blurred image.
    """
    wall = wall_level(green, disc)
    darkest = min(disc.outside_level, float(np.percentile(green[disc.mask], 1)))
    dark_level = wall - contrast * (wall - darkest)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * edge + 1, 2 * edge + 1))
    core = cv2.erode(disc.mask.astype(np.uint8), kernel).astype(bool)
    dark = ((green < dark_level) & disc.mask).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(dark, connectivity=8)
    area_disc = float(disc.mask.sum())
    cu, cv_ = (int(round(c)) for c in disc.centre)
    ids = []
    for k in range(1, n):
        area = stats[k, cv2.CC_STAT_AREA]
        if area < 3 or area > 0.02 * area_disc:
            continue
        reg = labels == k
        if not core[reg].all():
            continue
        if 0 <= cv_ < labels.shape[0] and 0 <= cu < labels.shape[1] and labels[cv_, cu] == k:
            continue
        ids.append(k)
    n_strong = len(ids)
    # fainter streaks (small dots squeezed near the apex and blurred below ``contrast``): regions
    # darker by ``FAINT_DOT_CONTRAST`` that hold no region found above, on the same conditions
    weak = ((green < wall - FAINT_DOT_CONTRAST * (wall - darkest)) & disc.mask).astype(np.uint8)
    nw, wlabels, wstats, _ = cv2.connectedComponentsWithStats(weak, connectivity=8)
    has_strong = np.zeros(nw, bool)
    has_strong[np.unique(wlabels[labels > 0])] = True
    for k in range(1, nw):
        area = wstats[k, cv2.CC_STAT_AREA]
        if has_strong[k] or area < 3 or area > 0.02 * area_disc:
            continue
        reg = wlabels == k
        if not core[reg].all():
            continue
        if 0 <= cv_ < labels.shape[0] and 0 <= cu < labels.shape[1] and wlabels[cv_, cu] == k:
            continue
        labels[reg] = n
        ids.append(n)
        n += 1
    if not with_faint:
        ids = ids[:n_strong]
    faint = (wall - green > support * (wall - darkest)) & disc.mask
    dots = _weighted_centroids(wall - green, _with_faint_edges(labels, faint), ids)
    return (dots, np.arange(len(ids)) >= n_strong) if with_faint else dots


def _with_faint_edges(labels: np.ndarray, faint: np.ndarray) -> np.ndarray:
    """Each labelled region widened to the component of ``faint`` (a lower threshold's mask, holding
    every region) it lies in, when no other region lies in that component: a dot squeezed into a
    thin streak crosses the detection threshold along part of its length only, and a centroid over
    that part grown by a few pixels would cut off the streak's ends."""
    n, comp = cv2.connectedComponents(faint.astype(np.uint8), connectivity=8)
    at = np.zeros(labels.max() + 1, int)  # the faint component of each region
    ys, xs = np.nonzero(labels)
    at[labels[ys, xs]] = comp[ys, xs]
    regions_in = np.bincount(at[1:], minlength=n)
    owner = np.zeros(n, int)  # the one region of each faint component, or 0
    single = np.flatnonzero(regions_in == 1)
    single = single[single > 0]
    owner[single] = [int(np.flatnonzero(at == c)[0]) for c in single]
    out = owner[comp]
    keep = labels > 0
    out[keep] = labels[keep]
    return out


def find_spots(
    bgr: np.ndarray,
    disc: MirrorDisc,
    threshold: float = 25.0,
    edge: int = 2,
    support: float = SPOT_SUPPORT,
    exclude: np.ndarray | None = None,
    color: str = "red",
) -> np.ndarray:
    """Laser spots inside the mirror's disc: (S, 2) centroids (``color``: the lasers' colour,
    :mod:`slcvjax.images.light`; below, red is the laser's channel and green the reference).

    Found where red minus green exceeds ``threshold`` grey levels; located by the
    centroid of red / green - 1, the laser's light relative to the scene's, over the
    pixels above ``support`` connected to the spot (where no other spot's are), grown by
    2 px: the whole of its profile, whose tails a cut at ``threshold`` would leave out.  A
    spot whose bright part (above ``threshold``, and 2 px around) meets a dot's image is
    skipped: the blur mixes the dot's darkness into the ratio at the dot's edge, and the
    centroid moves by up to a fifth of a pixel.  A spot closer than ``edge`` px to the disc's outline is skipped: the
    rim cuts its image, and its centroid would lie off its centre.  ``exclude`` (H, W bool, or
    None): a region of red light that meets it is not a spot (a line or ring laser's stripe,
    and a spot on it).
    """
    red, raw = laser_light(bgr, color)
    red = cv2.GaussianBlur(red, (0, 0), 0.7)
    mask = ((red > threshold) & disc.mask).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    green = scene_channel(bgr, color)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * edge + 1, 2 * edge + 1))
    core = cv2.erode(disc.mask.astype(np.uint8), kernel).astype(bool)
    wall = wall_level(green, disc)
    dotted = (wall - green > DOT_SUPPORT * (wall - disc.outside_level)) & disc.mask  # a dot's faintest edge
    widened = _with_faint_edges(labels, (red > support) & disc.mask)
    grow = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    ids = []
    for k in range(1, n):
        if stats[k, cv2.CC_STAT_AREA] < 2:
            continue
        if not core[labels == k].all():
            continue
        if exclude is not None and exclude[labels == k].any():
            continue
        bright = cv2.dilate((labels == k).astype(np.uint8), grow).astype(bool)
        if not dotted[bright].any():
            ids.append(k)
    return _weighted_centroids(raw, widened, ids)


def azimuth_deg(px: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Image azimuth (degrees in [0, 360)) of pixels about a centre: ``atan2(v - cv, u - cu)``."""
    d = np.asarray(px, float).reshape(-1, 2) - centre
    return np.degrees(np.arctan2(d[:, 1], d[:, 0])) % 360.0


def _wrap(a):
    return (np.asarray(a) + 180.0) % 360.0 - 180.0


def order_grid(
    px: np.ndarray,
    centre: np.ndarray,
    layout: BoardLayout,
    disc_radius: float | None = None,
    dead_zone: float = 0.3,
    rim_margin: float = 25.0,
    probe=None,
    body_radius: float | None = None,
    seen_radius: float = 0.0,
) -> tuple[np.ndarray, np.ndarray] | str | None:
    """Place one board's dots on its grid: (pixels (M, 2), seen (M,)); None where they do not
    form the grid, or a reason where a whole row is missing and the evidence cannot say which.

    Through a cone mirror a wall's columns (lines across the axis's direction)
    image as nearly radial lines, so the dots are split into ``cols`` azimuth
    groups (each gap wider than 3x the groups' own spread), and each column is
    ordered by image radius.  A column with missing dots takes its rows from the
    fullest columns' radii, interpolated in azimuth; a dot must fall within 0.3
    row spacings of its row.  One whole missing row is placed only where the evidence says
    on which side it lies: the fullest columns extended by one row spacing reach inside
    ``dead_zone`` of the disc's radius (near the apex the image is squeezed and the sensor's
    own reflection sits) or beyond the rim less ``rim_margin`` px (dots there are cut) on that
    side only; where the image's own measure of the sensor's dark reflection is given
    (``body_radius``, px; 0 where none is seen) these limits follow the grid and the image
    instead of fixed fractions: through the cone equal steps along a wall image as steps that
    shrink towards the apex and grow towards the rim, so the row beyond the inner one, extended
    by one step, is at least that far out (hidden only when that lies within the reflection
    and a fifth of a step, where a squeezed row may be there unseen), and the row beyond the
    outer one at least one step out (hidden when one and a half steps reach within ``RIM_EDGE``
    px of the rim, where a dot is cut); nor is a row said to be seen where the image has shown
    no dot at all: within ``seen_radius`` (px) of the centre, the nearest any dot of the image
    was found (a dim, blurred image's squeezed rows may be there unseen even by the probe); and
    ``probe`` (see :func:`_darkness_probe`), when given, finds nothing dark where the row would
    lie on the other side (a row there, seen but too faint to be detected, would mean the other
    placement).  Where both sides would be out of sight the image cannot tell which row is
    missing: nothing is placed, and the reason is returned.
    """
    cols, rows = layout.cols, layout.rows
    split = _columns(px, centre, layout)
    if split is None:
        # near the apex's image a dot's azimuth is least sure: try again without the dots
        # within a quarter of the others' median radius (they are left out)
        rad = np.linalg.norm(px - centre, axis=1)
        keep = rad >= 0.25 * np.median(rad)
        if keep.all() or keep.sum() < cols:
            return None
        return order_grid(px[keep], centre, layout, disc_radius, dead_zone, rim_margin, probe, body_radius, seen_radius)
    groups, a, r = split
    m = max(len(g) for g in groups)
    full = [k for k, g in enumerate(groups) if len(g) == m]
    ref = np.array([r[groups[k]] for k in full])  # (F, m) radii of the fullest columns
    first = 0
    if m < rows:  # whole rows missing: only where they would lie out of sight, on one side only
        if m < 2 or disc_radius is None:
            return None
        inner, outer = (ref[:, 0], ref[:, -1]) if layout.y_dir > 0 else (ref[:, -1], ref[:, 0])
        step = np.abs(np.diff(ref, axis=1))
        step_in, step_out = (step[:, 0], step[:, -1]) if layout.y_dir > 0 else (step[:, -1], step[:, 0])
        if body_radius is None:
            hid_in = inner - step_in < dead_zone * disc_radius
            hid_out = outer + step_out > disc_radius - rim_margin
        else:
            hid_in = inner - step_in < np.maximum(body_radius + 0.2 * step_in, seen_radius)
            hid_out = outer + 1.5 * step_out > disc_radius - RIM_EDGE
        if rows - m > 1:
            return None
        a0 = circular_mean_deg(azimuth_deg(px, centre))
        col_az_abs = [a0 + float(np.mean(a[groups[k]])) for k in full]

        def side(edge, step_next, hid) -> str:
            """What the image shows where the row beyond ``edge`` would lie: ``hidden`` (out of
            sight in every column), ``seen`` (something dark in every column where it would be in
            sight: a row too faint to be detected), ``absent`` (nothing dark in any), ``unclear``."""
            if np.all(hid):
                return "hidden"
            if probe is None:
                return "absent"
            dark = [probe(az, r0 + 0.5 * s, r0 + 1.5 * s)
                    for az, r0, s, h in zip(col_az_abs, edge, step_next, hid, strict=True) if not h]  # fmt: skip
            return "seen" if all(dark) else "absent" if not any(dark) else "unclear"

        # the missing row lies on the one side that does not show nothing where it would be seen
        s_in, s_out = side(inner, -step_in, hid_in), side(outer, step_out, hid_out)
        if s_in == "hidden" and s_out == "hidden":
            return "a whole row is hidden and either neighbouring row could be it (ambiguous rows)"
        if s_in == "absent" and s_out == "absent":
            return None
        if s_out == "absent":
            hidden_in = True
        elif s_in == "absent":
            hidden_in = False
        else:
            return "a whole row is missing and the image shows something on both sides (ambiguous rows)"
        # grid row 0 comes first in the columns' order: it is the inner row when y grows outwards
        first = 1 if hidden_in == (layout.y_dir > 0) else 0
    col_az = np.array([np.mean(a[g]) for g in groups])
    out = np.zeros((rows * cols, 2))
    seen = np.zeros(rows * cols, bool)
    present = np.arange(first, first + m)
    # each column's row radii (NaN: not yet known); the fullest columns first, then column by column
    # outwards from them, each predicted from its placed neighbours: interpolated in azimuth
    # between the nearest on either side, else extrapolated along the nearest two on one side
    # (through the cone a row's image radius drifts across an oblique wall)
    row_r = np.full((cols, rows), np.nan)
    for k in full:
        row_r[k, present] = r[groups[k]]
    placed = set(full)
    while len(placed) < cols:
        k = min((c for c in range(cols) if c not in placed), key=lambda c: min(abs(c - q) for q in placed))
        g = groups[k]
        # the rows predicted two ways: from the nearest placed column as it is, and along the
        # drift of the nearest two; a dot takes the row both agree on (or the one that fits)
        fits = {}
        for how in ("nearest", "drift"):
            pred = _predict_rows(col_az, row_r, sorted(placed), k, how)[present]
            if not len(g):
                fits.setdefault((), pred)
                continue
            spacing = np.min(np.abs(np.diff(pred))) if m > 1 else np.inf
            near_row = np.array([int(np.argmin(np.abs(pred - r[i]))) for i in g])
            near = np.abs(pred[near_row] - r[g]) < ROW_TOLERANCE * spacing
            if len(set(near_row.tolist())) == len(g) and near.all():
                fits.setdefault(tuple(near_row.tolist()), pred)
        if len(fits) != 1:
            return None
        ((rows_k, pred),) = fits.items()
        if len(g):
            near_row = np.asarray(rows_k, int)
            # the rows it does not show follow the prediction moved by the column's mean drift from it
            row_r[k, present] = pred + np.mean(r[g] - pred[near_row])
            row_r[k, present[near_row]] = r[g]
        else:
            row_r[k, present] = pred
        placed.add(k)
    for k, g in enumerate(groups):
        for i in g:
            j = present[int(np.argmin(np.abs(row_r[k, present] - r[i])))]
            out[j * cols + k] = px[i]
            seen[j * cols + k] = True
    return out, seen


ROW_TOLERANCE = 0.3  # a dot of a partial column lies within this fraction of the row spacing of its predicted row


def _predict_rows(col_az: np.ndarray, row_r: np.ndarray, placed: list[int], k: int, how: str = "drift") -> np.ndarray:
    """Row radii of column ``k`` from the placed columns' (``row_r`` rows), in azimuth ``col_az``:
    interpolated between the nearest on either side; beyond them, the nearest one's
    (``how="nearest"``) or extrapolated along the nearest two (``"drift"``)."""
    lo = [q for q in placed if q < k]
    hi = [q for q in placed if q > k]
    if lo and hi:
        a, b = lo[-1], hi[0]
    elif how == "nearest":
        return row_r[lo[-1] if lo else hi[0]].copy()
    elif len(lo) >= 2:
        a, b = lo[-2], lo[-1]
    elif len(hi) >= 2:
        a, b = hi[0], hi[1]
    else:
        return row_r[(lo or hi)[0]].copy()
    w = (col_az[k] - col_az[a]) / (col_az[b] - col_az[a])
    return row_r[a] + w * (row_r[b] - row_r[a])


def _columns(px: np.ndarray, centre: np.ndarray, layout: BoardLayout):
    """A target's dots split into its columns by azimuth (each gap wider than 3x the groups' own
    spread), in grid order, each column in grid order of its rows: ``(groups, azimuths
    relative to their mean, image radii)``, or None.

    The columns image as lines through the image of the cone's apex, which is not the rim's
    centre (the mirror's tilt and offset, the perspective of the rim): about the rim's centre a
    column's dots near the apex fan out by degrees.  Where the split about ``centre`` fails,
    the point the columns meet is fitted to their dots (:func:`_column_point`) and the split is
    made again about it."""
    cols, rows = layout.cols, layout.rows
    if len(px) < cols or len(px) > cols * rows:
        return None
    a = _wrap(azimuth_deg(px, centre) - circular_mean_deg(azimuth_deg(px, centre)))
    r = np.linalg.norm(px - centre, axis=1)
    groups = _split_columns(a, cols)
    if groups is None:
        near = _column_point(px, centre, a, cols)
        if near is None:
            return None
        groups = _split_columns(_wrap(azimuth_deg(px, near) - circular_mean_deg(azimuth_deg(px, near))), cols)
        if groups is None:
            return None
    if layout.x_dir < 0:
        groups = groups[::-1]
    if any(len(g) > rows for g in groups):
        return None
    return [g[np.argsort(layout.y_dir * r[g])] for g in groups], a, r


def _split_columns(a: np.ndarray, cols: int) -> list[np.ndarray] | None:
    """Indices of ``cols`` groups of azimuths ``a`` (deg, about their mean) split at the widest
    gaps, in increasing azimuth; None unless each gap is wider than 3x the groups' own spread."""
    order = np.argsort(a)
    if cols == 1:
        return [order]
    gaps = np.diff(a[order])
    cut = np.sort(np.argsort(gaps)[-(cols - 1) :])
    groups = np.split(order, cut + 1)
    spread = max(float(np.ptp(a[g])) for g in groups)
    if gaps[cut].min() <= 3.0 * max(spread, 0.2):
        return None
    return groups


def _column_point(px: np.ndarray, centre: np.ndarray, a: np.ndarray, cols: int) -> np.ndarray | None:
    """The point where a target's columns meet: the columns first split at the widest gaps of
    azimuth ``a`` about ``centre``; then Gauss-Newton on the point ``c`` and each column's
    direction for the dots' distances to the lines through ``c``.  None where fewer than two
    columns hold two dots or more, where the fit leaves fewer than 2 degrees of freedom, or
    where ``c`` moves from ``centre`` by more than a tenth of the dots' median radius."""
    order = np.argsort(a)
    gaps = np.diff(a[order])
    groups = np.split(order, np.sort(np.argsort(gaps)[-(cols - 1) :]) + 1) if cols > 1 else [order]
    groups = [g for g in groups if len(g) >= 2]
    n = sum(len(g) for g in groups)
    if len(groups) < 2 or n - 2 - len(groups) < 2:
        return None
    c = np.asarray(centre, float).copy()
    th = np.array([np.arctan2(*(px[g] - c).mean(0)[::-1]) for g in groups])
    for _ in range(10):
        rows_j, res = [], []
        for k, g in enumerate(groups):
            d = px[g] - c
            s, co = np.sin(th[k]), np.cos(th[k])
            jac = np.zeros((len(g), 2 + len(groups)))
            jac[:, 0], jac[:, 1], jac[:, 2 + k] = -s, co, d[:, 0] * co + d[:, 1] * s
            rows_j.append(jac)
            res.append(d[:, 0] * s - d[:, 1] * co)
        step = np.linalg.lstsq(np.concatenate(rows_j), -np.concatenate(res), rcond=None)[0]
        c, th = c + step[:2], th + step[2:]
        if np.abs(step[:2]).max() < 1e-3:
            break
    if not np.all(np.isfinite(c)) or np.linalg.norm(c - centre) > 0.1 * np.median(np.linalg.norm(px - centre, axis=1)):
        return None
    return c


MAX_CANDIDATES = 64


def candidate_placements(
    px: np.ndarray, centre: np.ndarray, layout: BoardLayout
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Every placement of a target's dots on its grid that keeps each column's dots in the
    order of their rows (for a target that cannot be placed from the image alone; the
    calibration decides among them by the box, :func:`slcvjax.images.centroids.resolve_ambiguous_boards`):
    ``[(pixels (M, 2), seen (M,)), ...]``; empty where the dots do not split into columns or
    the choices would exceed ``MAX_CANDIDATES``."""
    from itertools import combinations, product

    split = _columns(px, centre, layout)
    if split is None:
        return []
    groups = split[0]
    cols, rows = layout.cols, layout.rows
    choices = [list(combinations(range(rows), len(g))) for g in groups]
    if int(np.prod([len(c) for c in choices])) > MAX_CANDIDATES:
        return []
    out = []
    for pick in product(*choices):
        pix, seen = np.zeros((rows * cols, 2)), np.zeros(rows * cols, bool)
        for k, (g, rows_of) in enumerate(zip(groups, pick, strict=True)):
            for i, j in zip(g, rows_of, strict=True):
                pix[j * cols + k], seen[j * cols + k] = px[i], True
        out.append((pix, seen))
    return out


def _central_body(green: np.ndarray, disc: MirrorDisc) -> tuple[np.ndarray, np.ndarray | None]:
    """The pixels darker than the wall by ``ROW_EVIDENCE`` of the dots' contrast 4 px or more
    inside the disc, and the dark region holding the disc's centre among them (the sensor's own
    reflection), or None where the centre is not dark."""
    wall = wall_level(green, disc)
    darkest = min(disc.outside_level, float(np.percentile(green[disc.mask], 1)))
    level = wall - ROW_EVIDENCE * (wall - darkest)
    core = cv2.erode(disc.mask.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)  # not the rim's edge
    dark = (green < level) & core
    n, labels = cv2.connectedComponents(dark.astype(np.uint8), connectivity=8)
    cu, cv_ = (int(round(c)) for c in disc.centre)
    if 0 <= cv_ < dark.shape[0] and 0 <= cu < dark.shape[1] and labels[cv_, cu] > 0:
        return dark, labels == labels[cv_, cu]
    return dark, None


def body_radius(green: np.ndarray, disc: MirrorDisc) -> float:
    """The image radius (px) of the sensor's dark reflection about the disc's centre (the largest
    distance of its pixels from the centre), 0 where the centre is not dark."""
    _, body = _central_body(green, disc)
    if body is None:
        return 0.0
    ys, xs = np.nonzero(body)
    return float(np.max(np.hypot(xs - disc.centre[0], ys - disc.centre[1])))


def _darkness_probe(green: np.ndarray, disc: MirrorDisc):
    """``probe(azimuth_deg, r0, r1)``: whether the image is darker than the wall by ``ROW_EVIDENCE``
    of the dots' contrast anywhere along the radial segment from image radius ``r0`` to ``r1``
    (within 2 px across it), 4 px or more inside the mirror's disc; the centre's dark body never counts."""
    dark, body = _central_body(green, disc)
    # the sensor's own reflection: the dark region holding the disc's centre, and a margin round it
    if body is not None:
        dark &= ~cv2.dilate(body.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    h, w = dark.shape

    def probe(az_deg: float, r0: float, r1: float) -> bool:
        lo, hi = sorted((max(r0, 0.0), max(r1, 0.0)))
        th = np.radians(az_deg)
        e, n_ = np.array([np.cos(th), np.sin(th)]), np.array([-np.sin(th), np.cos(th)])
        for r in np.arange(lo, hi + 0.5, 0.5):
            for off in (-2.0, -1.0, 0.0, 1.0, 2.0):
                u, v = disc.centre + r * e + off * n_
                iu, iv = int(round(u)), int(round(v))
                if 0 <= iv < h and 0 <= iu < w and dark[iv, iu]:
                    return True
        return False

    return probe


def _split_by_azimuth(az: np.ndarray, k: int) -> list[np.ndarray]:
    """Split points on the circle into ``k`` groups at the ``k`` largest gaps (indices per group)."""
    if len(az) == 0 or k < 1:
        return []
    order = np.argsort(az)
    s = az[order]
    gaps = (np.roll(s, -1) - s) % 360.0
    if len(s) == 1:
        return [order]
    cut = np.sort(np.argsort(gaps)[-min(k, len(s)) :])
    groups = []
    for i in range(len(cut)):
        a, b = cut[i - 1] + 1, cut[i] + 1
        idx = np.arange(a, b) if i > 0 else np.r_[np.arange(cut[-1] + 1, len(s)), np.arange(0, b)]
        groups.append(order[idx % len(s)])
    return [g for g in groups if len(g)]


@dataclass
class ImageDetection:
    """What one catadioptric image showed: the disc, rim pixels, dot and spot centroids."""

    name: str
    disc: MirrorDisc | None
    rim: np.ndarray
    dots: np.ndarray
    spots: np.ndarray
    green: np.ndarray | None = None  # the image's green channel, for evidence where dots were not found
    faint: np.ndarray | None = None  # (K,) which dots are faint streaks (``find_dots(with_faint=True)``)
    stripes: StripeSamples | None = None  # the stripes' centre-line samples, where looked for


def detect_catadioptric(
    bgr: np.ndarray, name: str = "", stripes: bool = False, light: DetectionSettings = DEFAULT_LIGHT
) -> ImageDetection:
    """Rim pixels, dot centroids and spot centroids of one catadioptric image (unlabelled); with
    ``stripes``, also the centre-line samples of line and ring lasers' stripes
    (:func:`slcvjax.images.stripes.find_stripes`, away from the dots), and no spot is taken
    from a stripe's light.  ``light``: the lasers' colour and spot threshold (the scene is read
    in a channel the lasers do not reach)."""
    green = scene_channel(bgr, light.laser_color)
    spot_args = {"threshold": light.threshold, "color": light.laser_color}
    disc = find_mirror(green)
    if disc is None:
        return ImageDetection(name, None, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 2)))
    dots, faint = find_dots(green, disc, with_faint=True)
    if not stripes:
        return ImageDetection(name, disc, find_rim(green, disc), dots, find_spots(bgr, disc, **spot_args), green, faint)
    wall = wall_level(green, disc)
    dotted = (wall - green > DOT_SUPPORT * (wall - disc.outside_level)) & disc.mask
    st = find_stripes(bgr, disc.mask, dotted)
    lit = np.zeros(disc.mask.shape, np.uint8)
    iu = np.clip(np.rint(st.pixels).astype(int), 0, [lit.shape[1] - 1, lit.shape[0] - 1])
    lit[iu[:, 1], iu[:, 0]] = 1
    lit = cv2.dilate(lit, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (7, 7))).astype(bool)
    spots = find_spots(bgr, disc, exclude=lit, **spot_args)
    return ImageDetection(name, disc, find_rim(green, disc), dots, spots, green, faint, st)


def label_boards(
    det: ImageDetection, setup: Setup, candidates: dict | None = None
) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], list[str]]:
    """Group one image's dots into the setup's wall targets and order each grid; returns (boards, problems).

    A target left out (ambiguous rows, or dots that do not fit the grid) gets its possible
    placements (:func:`candidate_placements`) in ``candidates[name]`` when a dict is given."""
    walls = {k: b for k, b in setup.boards.items() if b.azimuth_deg is not None and b.target is None}  # dot grids
    problems: list[str] = []
    out = {k: (np.zeros((len(b.points), 2)), np.zeros(len(b.points), bool)) for k, b in walls.items()}
    if det.disc is None:  # the caller reports the image's "no mirror found"
        return out, problems
    if len(det.dots) == 0:  # each target is reported, as when some other is found
        return out, [f"{name}: not found" for name in walls]
    faint = np.zeros(len(det.dots), bool) if det.faint is None else det.faint
    strong = np.flatnonzero(~faint)
    az_all = azimuth_deg(det.dots, det.disc.centre)
    az = az_all[strong]
    groups = [strong[g] for g in _split_by_azimuth(az, len(walls))]
    # each faint dot joins the group of the nearest dot in azimuth
    extra: list[list[int]] = [[] for _ in groups]
    for i in np.flatnonzero(faint):
        if groups:
            near = [np.min(np.abs(_wrap(az_all[g] - az_all[i]))) for g in groups]
            extra[int(np.argmin(near))].append(int(i))
    az = az_all
    names = list(walls)
    nominal = np.array([walls[k].azimuth_deg for k in names])
    means = [circular_mean_deg(az[g]) for g in groups]
    assign = [int(np.argmin(np.abs(_wrap(m - nominal)))) for m in means]
    used: dict[int, int] = {}
    probe = None if det.green is None else _darkness_probe(det.green, det.disc)
    body = None if det.green is None else body_radius(det.green, det.disc)
    for gi, j in enumerate(assign):
        name = names[j]
        d = abs(float(_wrap(means[gi] - nominal[j])))
        if j in used or d > 45.0:
            problems.append(f"{len(groups[gi])} dots near azimuth {means[gi] % 360:.0f} deg match no single target")
            continue
        used[j] = gi
        got = _place_with_faint(det, groups[gi], extra[gi], walls[name], probe, body)
        if isinstance(got, str) or got is None:
            why = got if isinstance(got, str) else f"{len(groups[gi])} dots could not be placed on the grid"
            problems.append(f"{name}: {why}; board left out")
            if candidates is not None:
                placed = candidate_placements(det.dots[groups[gi]], det.disc.centre, walls[name])
                if len(placed) > 1:
                    candidates[name] = placed
            continue
        px, seen = got
        out[name] = (px, seen)
        if not seen.all():
            problems.append(f"{name}: {int(seen.sum())} of {len(seen)} dots found")
    for j, name in enumerate(names):
        if j not in used and not any(name in p for p in problems):
            problems.append(f"{name}: not found")
    return out, problems


def _place_with_faint(det: ImageDetection, strong: np.ndarray, faint: list[int], layout: BoardLayout, probe, body):
    """:func:`order_grid` of a target's dots, helped by its faint streaks: they take part in the
    placement where the other dots alone cannot be placed, or where, with them, every other dot
    keeps its grid position and more are placed; they are not placed themselves (a streak
    narrower than a pixel next to the apex, or cut by the sensor's reflection, does not give its
    dot's centre to a tenth of a pixel)."""
    radius = float(np.mean(det.disc.axes))
    seen = float(np.min(np.linalg.norm(det.dots - det.disc.centre, axis=1))) if len(det.dots) else np.inf
    kw = dict(probe=probe, body_radius=body, seen_radius=seen)
    got = order_grid(det.dots[strong], det.disc.centre, layout, radius, **kw)
    if not faint:
        return got
    more = order_grid(det.dots[np.r_[strong, faint]], det.disc.centre, layout, radius, **kw)
    if not isinstance(more, tuple):
        return got
    px, seen = more
    faint_px = det.dots[faint]
    seen = seen & ~np.any(np.all(px[:, None, :] == faint_px[None, :, :], axis=2), axis=1)
    if not isinstance(got, tuple):
        return (px, seen) if seen.any() else got
    same = np.all(seen[got[1]]) and np.allclose(px[got[1]], got[0][got[1]])
    return (px, seen) if same and seen.sum() > got[1].sum() else got


def _wall_azimuths(det: ImageDetection, walls: dict[str, BoardLayout], seen_boards: dict) -> dict[str, float]:
    """Each wall target's azimuth in one image (deg): its dots' circular mean where found, else
    the nominal one."""
    out = {}
    for name, layout in walls.items():
        px, seen = seen_boards[name]
        out[name] = circular_mean_deg(azimuth_deg(px[seen], det.disc.centre)) if seen.any() else layout.azimuth_deg
    return out


def _spot_board(az: float, wall_az: dict[str, float], margin: float) -> str | None:
    """The wall target nearest in azimuth, or None within ``margin`` deg of the bisector of the two nearest."""
    if not wall_az:
        return None
    d = sorted((abs(float(_wrap(az - a))), b) for b, a in wall_az.items())
    if len(d) > 1 and d[1][0] - d[0][0] < 2 * margin:
        return None
    return d[0][1]


def label_spots(
    dets: list[ImageDetection],
    setup: Setup,
    boards_seen: list[dict[str, tuple[np.ndarray, np.ndarray]]],
    corner_margin: float = 15.0,
) -> tuple[list[list[SpotObs]], list[list[str]]]:
    """Label every image's spots with their laser and their board; returns spots and problems per image.

    Laser azimuths come from ``setup.laser_azimuth_deg`` when given; otherwise the
    spots of all images are split into ``n_lasers`` azimuth clusters and laser ``k``
    is the ``k``-th cluster by increasing azimuth, counted from the one nearest 0 deg; where
    the clusters are not apart by more than their own spread (a laser never found), no spot
    is labelled.
    A spot's board is the wall target whose dots' mean azimuth (in its image, else the
    nominal one) is nearest; within ``corner_margin`` deg of the bisector of two
    targets the spot may lie on either wall (where the corner falls depends on the
    sensor's position), so its board is left null: the calibration puts it on the
    first board plane its reflected ray meets, once the boards' poses are known.
    With line or ring lasers in the setup (``laser_kinds``) only the point lasers draw spots:
    ``n_lasers`` above counts those, and a spot's laser is its index among all lasers.
    """
    point_of = setup.point_lasers
    n = len(point_of)
    problems: list[list[str]] = [[] for _ in dets]
    spots_out: list[list[SpotObs]] = [[] for _ in dets]
    all_az, owner = [], []
    for i, d in enumerate(dets):
        if d.disc is None:
            continue
        for j, a in enumerate(azimuth_deg(d.spots, d.disc.centre)):
            all_az.append(a)
            owner.append((i, j))
    if n == 0 or not all_az:
        return spots_out, problems
    all_az = np.array(all_az)
    if setup.laser_azimuth_deg is not None:
        centres = np.asarray([setup.laser_azimuth_deg[i] for i in point_of], float) % 360.0
    else:
        groups = _split_by_azimuth(all_az, n)
        centres = np.array([circular_mean_deg(all_az[g]) % 360 for g in groups])
        if len(centres) < n or not _well_separated(all_az, groups):
            for i in range(len(dets)):
                problems[i].append(
                    f"the spots do not form {n} azimuth groups apart from each other (one per laser: a laser never "
                    "found?); none labelled (setup.json's laser_azimuth_deg would label them)"
                )
            return spots_out, problems
        start = int(np.argmin(np.abs(_wrap(centres))))
        centres = np.roll(np.sort(centres), -int(np.searchsorted(np.sort(centres), centres[start])))
    spacing = np.min(np.abs(_wrap(centres[:, None] - centres[None, :])) + 360 * np.eye(n)) if n > 1 else 360.0
    label = np.full(len(all_az), -1)
    for k, a in enumerate(all_az):
        d = np.abs(_wrap(a - centres))
        j = int(np.argmin(d))
        if d[j] < 0.5 * spacing:
            label[k] = j
    walls = {k: b for k, b in setup.boards.items() if b.azimuth_deg is not None}
    for i, d in enumerate(dets):
        if d.disc is None:
            continue
        idx = [k for k, (o, _) in enumerate(owner) if o == i]
        lab = label[idx]
        wall_az = _wall_azimuths(d, walls, boards_seen[i])
        for k, li in zip(idx, lab, strict=True):
            j = owner[k][1]
            px = d.spots[j]
            if li < 0:
                problems[i].append(f"spot at ({px[0]:.1f}, {px[1]:.1f}) matches no laser's azimuth; left out")
                continue
            if np.sum(lab == li) > 1:
                problems[i].append(f"laser {point_of[li]}: {int(np.sum(lab == li))} spots; left out")
                continue
            board = _spot_board(all_az[k], wall_az, corner_margin)
            spots_out[i].append(SpotObs(int(point_of[li]), board, px.copy()))
        found = {s.laser for s in spots_out[i]}
        missing = [str(k) for k in point_of if k not in found]
        if missing:
            problems[i].append(f"no spot for laser {', '.join(missing)}")
    return spots_out, problems


def label_stripes(
    dets: list[ImageDetection],
    setup: Setup,
    boards_seen: list[dict[str, tuple[np.ndarray, np.ndarray]]],
    corner_margin: float = 15.0,
) -> tuple[list[list[StripeObs]], list[list[str]]]:
    """Label every image's stripe samples with their laser and their board; returns the stripes
    and the problems per image.

    A sample's laser: with one ring laser (``cone``) and no line laser, every sample is the
    ring's (it draws one closed curve about the mirror's axis); with line lasers alone, the line
    laser whose azimuth (``setup.laser_azimuth_deg``: the image azimuth of the middle of its
    fan) is nearest, within half the spacing of their azimuths (one line laser with no
    azimuth takes every sample).  Anything else (a ring with other line or ring lasers, line
    lasers with no azimuths) cannot be told apart by azimuth: those samples are left out and
    reported.  A sample's board is the wall target nearest in azimuth, as a spot's
    (:func:`label_spots`): null within ``corner_margin`` deg of the bisector of two targets (the
    calibration puts it on the first board plane its ray meets).  One stripe per laser and board
    (or null) in each image, its samples in order of azimuth.  What the detector left out
    (:attr:`StripeSamples.dropped`) is reported too.
    """
    sheets = setup.sheet_lasers
    kinds = setup.kinds
    out: list[list[StripeObs]] = [[] for _ in dets]
    problems: list[list[str]] = [[] for _ in dets]
    if not sheets:
        return out, problems
    rings = [i for i in sheets if kinds[i] == "cone"]
    lines = [i for i in sheets if kinds[i] == "plane"]
    azs = setup.laser_azimuth_deg
    why = None
    centres = None
    if len(rings) == 1 and not lines:
        pass
    elif not rings and len(lines) == 1 and (azs is None or azs[lines[0]] is None):
        pass
    elif not rings and azs is not None:
        centres = np.asarray([azs[i] for i in lines], float) % 360.0
    elif rings:
        why = "a ring laser's stripe cannot be told from other line or ring lasers' by azimuth"
    else:
        why = "line lasers need setup.json's laser_azimuth_deg (each fan's middle in the image)"
    walls = {k: b for k, b in setup.boards.items() if b.azimuth_deg is not None}
    for i, d in enumerate(dets):
        st = d.stripes
        if d.disc is None or st is None:
            continue
        for reason, k in st.dropped.items():
            problems[i].append(f"{k} stripe samples {reason}; left out")
        if not len(st.pixels):
            problems[i].append(f"no stripe for laser {', '.join(map(str, sheets))}")
            continue
        az = azimuth_deg(st.pixels, d.disc.centre)
        if why is not None:
            problems[i].append(f"{len(az)} stripe samples: {why}; left out")
            continue
        if centres is None:
            label = np.full(len(az), (rings or lines)[0])
        else:
            n = len(centres)
            spacing = np.min(np.abs(_wrap(centres[:, None] - centres[None, :])) + 360 * np.eye(n)) if n > 1 else 360.0
            dist = np.abs(_wrap(az[:, None] - centres[None, :]))
            j = np.argmin(dist, axis=1)
            label = np.where(dist[np.arange(len(az)), j] < 0.5 * spacing, np.asarray(lines)[j], -1)
            if (label < 0).any():
                problems[i].append(f"{int((label < 0).sum())} stripe samples match no line laser's azimuth; left out")
        wall_az = _wall_azimuths(d, walls, boards_seen[i])
        board = np.array([_spot_board(a, wall_az, corner_margin) for a in az], dtype=object)
        for laser in sheets:
            sel = label == laser
            if not sel.any():
                problems[i].append(f"no stripe for laser {laser}")
                continue
            rel = _wrap(az - circular_mean_deg(az[sel]))
            for b in dict.fromkeys(board[sel]):
                part = np.flatnonzero(sel & np.array([x == b for x in board]))
                order = part[np.argsort(rel[part])]
                out[i].append(StripeObs(int(laser), b, st.pixels[order].copy()))
    return out, problems


def _well_separated(az: np.ndarray, groups: list[np.ndarray]) -> bool:
    """Whether azimuth groups (deg) are apart by more than any group's own spread: a laser whose
    spots were never found leaves one group fewer, and the split at the widest gaps then cuts
    another laser's group in two, across a gap narrower than the groups' spread."""
    if len(groups) < 2:
        return True
    spread = max(float(np.ptp(_wrap(az[g] - circular_mean_deg(az[g])))) for g in groups)
    means = np.sort(np.array([circular_mean_deg(az[g]) % 360 for g in groups]))
    lo = np.array([np.min(_wrap(az[g] - circular_mean_deg(az[g]))) for g in groups])
    hi = np.array([np.max(_wrap(az[g] - circular_mean_deg(az[g]))) for g in groups])
    order = np.argsort([circular_mean_deg(az[g]) % 360 for g in groups])
    gaps = [
        (means[(i + 1) % len(means)] + lo[order[(i + 1) % len(means)]] - means[i] - hi[order[i]]) % 360
        for i in range(len(means))
    ]
    return min(gaps) > max(spread, 1.0)


def detect_chessboard(bgr: np.ndarray, cols: int, rows: int) -> np.ndarray | None:
    """Inner corners (cols*rows, 2) of a chessboard seen directly, ordered x fastest, or None."""
    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    ok, corners = cv2.findChessboardCorners(
        grey, (cols, rows), flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    )
    if not ok:
        return None
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    corners = cv2.cornerSubPix(grey, corners, (5, 5), (-1, -1), crit)
    return corners.reshape(-1, 2).astype(float)


def _stripe_leftout(p: str) -> bool:
    """Whether a problem line counts stripe samples left out (``"N stripe samples ...; left out"``)."""
    return p.endswith("left out") and " stripe samples" in p and p.split()[0].isdigit()


@dataclass
class DetectionReport:
    """Per image, what could not be found (empty lists where all was found)."""

    problems: dict[str, list[str]]
    counts: dict[str, dict[str, int]]

    def lines(self) -> list[str]:
        out = []
        for name, c in self.counts.items():
            desc = ", ".join(f"{v} {k}" for k, v in c.items())
            probs = self.problems.get(name, [])
            out.append(f"{name}: {desc}" + (f"; {'; '.join(probs)}" if probs else ""))
        return out

    def summary(self) -> str:
        """One line: how many images had problems, and how often each kind of problem came up."""
        probs = [p for ps in self.problems.values() for p in ps]
        kinds = {
            "boards left out": sum("board left out" in p for p in probs),
            "ambiguous rows": sum("ambiguous rows" in p for p in probs),
            "missing spots": sum(p.count(",") + 1 for p in probs if p.startswith("no spot for laser")),
            "spots left out": sum(p.endswith("left out") and ("spot" in p) and ("stripe" not in p) for p in probs),
            "stripe samples left out": sum(int(p.split()[0]) for p in probs if _stripe_leftout(p)),
        }
        with_problems = sum(1 for ps in self.problems.values() if ps)
        listed = ", ".join(f"{v} {k}" for k, v in kinds.items() if v)
        return f"{with_problems} of {len(self.counts)} images with something not found" + (
            f" ({listed})" if listed else ""
        )


def detect_folder(folder: str | Path, progress: bool = False) -> tuple[Observations, DetectionReport]:
    """Detect everything in an image folder described by its ``setup.json``.

    Returns ``slcv-observations/1`` content and a report of what was not found.
    Raises :class:`FormatError` for a bad ``setup.json``, a missing, unreadable,
    wrongly sized or blank image (naming the file).
    """
    folder = Path(folder)
    setup = read_setup(folder / "setup.json")
    _check_detectable(setup, folder / "setup.json")
    problems: dict[str, list[str]] = {}
    counts: dict[str, dict[str, int]] = {}
    cal_views = []
    items = [(im, b) for im, b in setup.chessboard_views]
    it = _progress(items + [(v, None) for v in setup.views], progress, "detect")
    images = {}
    for im, _ in it:
        img = read_image(folder / im, setup.image_size)
        if int(img.max()) - int(img.min()) < 10:
            raise FormatError(f"{folder / im}: (image): blank image (no contrast)")
        images[im] = img
    for im, b in items:
        layout = setup.boards[b]
        name = Path(im).stem
        if layout.target is not None and layout.target["type"] in ("charuco", "aprilgrid"):
            got = detect_direct(images[im], layout.target)  # a coded board: by its markers' ids
            counts[name] = {"corners": 0 if got is None else int(got[1].sum())}
            if got is None:
                problems[name] = [f"no {layout.target['type']} corner found"]
            else:
                cal_views.append(CalibrationViewObs(name, b, *got))
            continue
        corners = detect_chessboard(images[im], layout.cols, layout.rows)
        if corners is None:
            problems[name] = [f"no {layout.cols}x{layout.rows} chessboard found"]
            counts[name] = {"corners": 0}
            continue
        counts[name] = {"corners": len(corners)}
        cal_views.append(CalibrationViewObs(name, b, corners, np.ones(len(corners), bool)))
    with_stripes = bool(setup.sheet_lasers)
    dets = [detect_catadioptric(images[v], Path(v).stem, stripes=with_stripes, light=setup.light) for v in setup.views]
    boards_seen, board_probs, ambiguous = [], [], []
    for v, d in enumerate(dets):
        cands: dict = {}
        bs, pr = label_boards(d, setup, cands)
        if coded_walls(setup):  # ChArUco and AprilGrid walls: each corner by its own markers' ids
            cd = detect_coded_view(images[setup.views[v]], setup, d.disc)
            bs, pr = {**bs, **cd.boards}, pr + cd.problems
        boards_seen.append(bs)
        board_probs.append(pr)
        for b, placed in cands.items():
            options = [{"pixels": px[sn].tolist(), "indices": np.flatnonzero(sn).tolist()} for px, sn in placed]
            ambiguous.append({"view": v, "board": b, "candidates": options})
    spots, spot_probs = label_spots(dets, setup, boards_seen)
    stripes, stripe_probs = label_stripes(dets, setup, boards_seen)
    views = []
    for d, bs, bp, sp, spp, st, stp in zip(
        dets, boards_seen, board_probs, spots, spot_probs, stripes, stripe_probs, strict=True
    ):
        p = ([] if d.disc is not None else ["no mirror found"]) + bp + spp + stp
        if p:
            problems[d.name] = p
        counts[d.name] = {
            "dots": int(sum(s.sum() for _, s in bs.values())),
            "spots": len(sp),
            "rim pixels": len(d.rim),
        }
        if with_stripes:
            counts[d.name]["stripe samples"] = int(sum(len(x.pixels) for x in st))
        views.append(ViewObs(d.name, bs, sp, d.rim, st))
    obs = Observations(
        image_size=setup.image_size,
        mirror_radius=setup.mirror_radius,
        mirror_height=setup.mirror_height,
        n_lasers=setup.n_lasers,
        boards={k: np.asarray(b.points, float) for k, b in setup.boards.items()},
        calibration_views=cal_views,
        views=views,
        board_types={k: b.target for k, b in setup.boards.items() if b.target is not None},
        laser_kinds=tuple(setup.laser_kinds) if setup.laser_kinds else (),
        extra={
            "detection": {
                "folder": str(folder),
                "problems": problems,
                "dot_radius_mm": {k: b.dot_radius_mm for k, b in setup.boards.items() if b.dot_radius_mm},
                "spot_sigma_mm": setup.spot_sigma_mm,
                **({"stripe_sigma_mm": setup.stripe_sigma_mm} if setup.stripe_sigma_mm is not None else {}),
                "ambiguous_boards": ambiguous,
            },
            **({"rigid_boards": list(setup.rigid_boards)} if setup.rigid_boards else {}),
        },
    )
    return obs, DetectionReport(problems, counts)


def _check_detectable(setup: Setup, path: Path) -> None:
    """Refuse, naming the board, what the detector cannot find: a chessboard seen through the mirror
    (its corners carry no id: which wall and which corner could not be told without guessing)."""
    for name, b in setup.boards.items():
        kind = "dots" if b.target is None else b.target["type"]
        if b.azimuth_deg is not None and kind == "chessboard":
            raise FormatError(
                f"{path}: boards.{name}.type: the detector finds dots, ChArUco and AprilGrid targets through "
                f"the mirror, not a {kind} board; its printable target and the observations' format accept it"
            )
    for i, (_, b) in enumerate(setup.chessboard_views):
        kind = "dots" if setup.boards[b].target is None else setup.boards[b].target["type"]
        if kind not in ("dots", "chessboard", "charuco", "aprilgrid"):
            raise FormatError(
                f"{path}: chessboard_views[{i}].board: direct views are detected as chessboards, "
                f"not as board {b!r}'s {kind} (yet)"
            )


def _progress(items, enabled: bool, desc: str):
    if not enabled:
        return items
    from tqdm import tqdm

    return tqdm(items, desc=desc, unit="image", leave=False)


def circular_mean_deg(a: np.ndarray) -> float:
    return float(math.degrees(np.angle(np.exp(1j * np.radians(a)).mean())))
