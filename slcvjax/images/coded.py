"""The coded-target detector: ChArUco and AprilGrid corners seen through the mirror.

A wall target seen in a cone mirror lies in an annulus around the image centre, each board a
wedge whose squares the mirror squeezes: their width in the image shrinks with the distance from
the centre (a wall's arc length maps to ``r dtheta`` pixels) while their height does not.  OpenCV's
marker detectors expect a perspective view of a plane, so the annulus is first unwarped into a
panorama, then the markers are found there, and every corner they give is mapped back and refined
in the original image.  Per image (:func:`detect_coded`):

1. **Mirror**: :func:`slcvjax.images.detect.find_mirror`'s disc (its ellipse's centre and rim
   radius) and :func:`~slcvjax.images.detect.body_radius` (the sensor's dark reflection at the
   centre) bound the annulus.
2. **Panorama** (:class:`Panorama`): column ``x`` is the azimuth ``theta0 + 2 pi x / n_cols`` (the
   seam ``theta0`` in the widest gap between the walls' nominal azimuths, and ``WRAP_DEG`` more
   after the full turn, so that a board across the seam is whole once); row ``y`` runs from the rim
   inwards (the image of a wall seen in a cone is mirror-reversed in (azimuth, radius): reading the
   rows from the rim undoes it), its radius from a table.  A first panorama samples the radius
   uniformly with ``ASPECT`` columns per pixel of rim circumference; the detected markers' height
   over width, fitted as ``log(aspect) = a + b r``, then gives a second one whose row step follows
   the squares' radial size (squares drawn square at every radius: the rows near the apex, which
   the mirror squeezes, are stretched), and whose column count makes the median marker square.
   Sampling is ``cv2.remap`` (bilinear).  A mirror-reversed image (the camera's image flipped, a
   mirror seen from another side) is handled by detecting in the panorama read the other way
   round as well, and keeping the reading whose markers belong to more of the setup's boards.
3. **Markers**: ``cv2.aruco.ArucoDetector`` (the board's dictionary; ``DICT_APRILTAG_36h11`` for
   an AprilGrid), every id looked up among the setup's boards (their ids are disjoint, so an id
   names its board); an id of no board is dropped.  A marker is kept only where the board's
   geometry agrees with its neighbours (:func:`markers_consistent`): the affine map of each detected
   marker (its four corners against their board positions) predicts where every other marker of
   its board lies; a marker that no other marker within ``NEIGHBOUR_SQUARES`` squares places within
   ``AGREE_MARKERS`` of a square's size is a misread id or a false marker, and is dropped (a lone
   marker of a board is kept: nothing contradicts it).
4. **Corners**: a ChArUco corner (its id is its point index, as OpenCV's) is where the homography
   of each kept marker in a white square touching it puts it; where two do they must agree within
   ``AGREE`` of a square (:func:`_charuco_corners`: OpenCV's ``CharucoDetector`` interpolates over
   several markers at once, which the panorama's bend defeats; it serves the direct views,
   :func:`detect_direct`).  AprilGrid corners are each tag's four corners, Kalibr's indices
   (:func:`~slcvjax.observations.targets.aprilgrid_tag_corners`; OpenCV's corner ``k`` of a Kalibr
   print is the tag's corner ``APRIL_CORNER[k]``).
5. **Sub-pixel**: each corner is mapped back through the panorama's map (exact: the map is
   closed form) and refined in the original image (:func:`refine_saddle`): the gradient of every
   pixel near a corner is perpendicular to the line from the corner to it (Forstner's and
   ``cv2.cornerSubPix``'s condition), solved in the least-squares sense over a window that is
   small in the board's own units (inside the white margin around a ChArUco marker, inside a
   tag's border bit) but at least ``MIN_WINDOW_PX`` wide along each board axis: where the mirror
   squeezes that margin narrower (near the apex) a marker's edge enters the window and biases the
   corner (``benchmarks/coded_targets.py``: 0.17 px RMS where the margin is 1-2 px).  A corner
   whose refinement moves it more than ``MAX_SHIFT`` of the local square, or whose window is degenerate, is dropped.

Every corner is labelled by its own marker ids and the board's geometry, never by its place in
a grid: a corner not found is absent (null), never guessed.
"""

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ..observations.targets import (
    APRILGRID_DICTIONARY,
    aprilgrid_tag_corners,
    board_points,
    charuco_marker_squares,
    marker_dictionary,
    marker_ids,
)

WRAP_DEG = 45.0  # the panorama runs this far past a full turn (a board across the seam is whole once)
ASPECT = 2.0  # the first panorama's columns per pixel of rim circumference
ROWS_PER_PX = 1.5  # the panorama's rows per pixel of radius (the first one; the second keeps the count)
NEIGHBOUR_SQUARES = 2.5  # markers closer than this many squares (board units) vouch for each other
AGREE = 0.25  # of a square's size: how far two markers' homographies may place a corner apart
# of a square's size: how far a marker's affine map may place a neighbouring marker (two ChArUco
# markers' places differ by a square's diagonal at least, two tags' by a tag's pitch)
AGREE_MARKERS = 0.4
MIN_WINDOW_PX = 2.0  # the sub-pixel window's least half-width along each board axis, px
MAX_SHIFT = 0.25  # of the local square's size in pixels: the largest move of the sub-pixel refinement
APRIL_CORNER = (1, 0, 3, 2)  # OpenCV's corner k of a Kalibr tag -> its column in aprilgrid_tag_corners


# --------------------------------------------------------------------------- the panorama


@dataclass
class Panorama:
    """The annulus unwarped: column ``x`` -> azimuth, row ``y`` -> radius about ``centre``.

    Attributes:
        centre: (2,) the mirror disc's centre (u, v), px.
        theta0: the azimuth of column 0 (rad, ``atan2(v - cv, u - cu)``).
        n_cols: columns per full turn; the panorama has ``n_cols + wrap`` columns.
        wrap: columns past the full turn.
        radii: (H,) the radius of each row, px, from the rim inwards.
        reversed: the panorama is read right to left (a mirror-reversed image).
    """

    centre: np.ndarray
    theta0: float
    n_cols: int
    wrap: int
    radii: np.ndarray
    reversed: bool = False

    @property
    def shape(self) -> tuple[int, int]:
        return len(self.radii), self.n_cols + self.wrap

    def theta(self, x):
        x = np.asarray(x, float)
        if self.reversed:
            x = self.shape[1] - 1 - x
        return self.theta0 + 2 * math.pi * x / self.n_cols

    def radius(self, y):
        return np.interp(np.asarray(y, float), np.arange(len(self.radii)), self.radii)

    def to_image(self, xy: np.ndarray) -> np.ndarray:
        """Panorama pixels (..., 2) -> image pixels (..., 2) (OpenCV's: centres at integers)."""
        xy = np.asarray(xy, float)
        th, r = self.theta(xy[..., 0]), self.radius(xy[..., 1])
        return np.stack([self.centre[0] + r * np.cos(th), self.centre[1] + r * np.sin(th)], axis=-1)

    def jacobian(self, xy: np.ndarray) -> np.ndarray:
        """d(image px) / d(panorama px) at panorama points (..., 2): (..., 2, 2)."""
        xy = np.asarray(xy, float)
        th, r = self.theta(xy[..., 0]), self.radius(xy[..., 1])
        dth = (-1.0 if self.reversed else 1.0) * 2 * math.pi / self.n_cols
        dr = np.gradient(self.radii)
        dr_dy = np.interp(xy[..., 1], np.arange(len(self.radii)), dr)
        c, s = np.cos(th), np.sin(th)
        return np.stack([np.stack([-r * s * dth, c * dr_dy], -1), np.stack([r * c * dth, s * dr_dy], -1)], -2)

    def warp(self, grey: np.ndarray) -> np.ndarray:
        h, w = self.shape
        yy, xx = np.mgrid[0:h, 0:w].astype(float)
        m = self.to_image(np.stack([xx, yy], -1)).astype(np.float32)
        return cv2.remap(grey, m[..., 0], m[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _seam(azimuths_deg: list[float]) -> float:
    """The azimuth (rad) in the middle of the widest gap between the walls' nominal azimuths."""
    if not azimuths_deg:
        return 0.0
    a = np.sort(np.mod(azimuths_deg, 360.0))
    gaps = np.diff(np.append(a, a[0] + 360.0))
    i = int(np.argmax(gaps))
    return math.radians(a[i] + gaps[i] / 2)


BODY_ROUND = 0.75  # the sensor's reflection: dark on this fraction of a circle about the centre, at least


def inner_radius(green: np.ndarray, centre: np.ndarray, paper: float, r_out: float) -> float:
    """The radius (px) inside which the sensor's own dark reflection hides the mirror's view.

    On circles about ``centre`` (every 0.5 px of radius, 720 samples each), a sample is dark
    below the middle between the centre's level and ``paper`` (the mirror view's level); the
    body's edge is the first circle dark on less than ``BODY_ROUND`` of its length (the coded
    boards' black squares reach the body in wedges, never all round), plus 1 px; at most half
    of ``r_out``."""
    th = np.linspace(0.0, 2 * np.pi, 720, endpoint=False)
    h, w = green.shape
    cu, cv_ = (int(round(c)) for c in centre)
    body = float(np.median(green[max(cv_ - 1, 0) : cv_ + 2, max(cu - 1, 0) : cu + 2]))
    level = 0.5 * (body + paper)
    for r in np.arange(0.5, 0.5 * r_out, 0.5):
        u = np.clip(np.rint(centre[0] + r * np.cos(th)).astype(int), 0, w - 1)
        v = np.clip(np.rint(centre[1] + r * np.sin(th)).astype(int), 0, h - 1)
        if np.mean(green[v, u] < level) < BODY_ROUND:
            return float(r + 1.0)
    return 0.5 * r_out


def first_panorama(centre, r_in: float, r_out: float, theta0: float, reversed_: bool = False) -> Panorama:
    """The uniform panorama: ``ASPECT`` columns per pixel of rim circumference, ``ROWS_PER_PX``
    rows per pixel of radius from ``r_out`` to ``r_in``."""
    n_cols = int(round(2 * math.pi * r_out * ASPECT))
    rows = max(int(round((r_out - r_in) * ROWS_PER_PX)), 8)
    return Panorama(
        np.asarray(centre, float),
        theta0,
        n_cols,
        int(n_cols * WRAP_DEG / 360),
        np.linspace(r_out, r_in, rows),
        reversed_,
    )


def squared_panorama(pano: Panorama, quads: list[np.ndarray]) -> Panorama:
    """A panorama whose markers are square at every radius, from markers ``quads`` ((4, 2) pano px
    each, corners in OpenCV's order; a board's markers are square) found in ``pano``.

    Each marker's aspect (mean height over mean width in ``pano``) at its centre's radius ``r`` is
    fitted as ``log(aspect) = a + b r`` (least squares; ``b = 0`` with fewer than 4 markers or a
    radius span under 10 px).  The new panorama has ``c`` times the columns and, at radius ``r``,
    ``c / aspect(r)`` times the rows per pixel of radius, so every fitted aspect becomes 1;
    ``c = max(1, largest fitted aspect)`` (capped at 3) so that neither direction is sampled more
    coarsely than before."""
    if not quads:
        return pano
    q = np.asarray(quads, float)
    w = 0.5 * (np.linalg.norm(q[:, 1] - q[:, 0], axis=1) + np.linalg.norm(q[:, 2] - q[:, 3], axis=1))
    h = 0.5 * (np.linalg.norm(q[:, 3] - q[:, 0], axis=1) + np.linalg.norm(q[:, 2] - q[:, 1], axis=1))
    la = np.log(np.clip(h / np.maximum(w, 1e-6), 0.2, 5.0))
    r = pano.radius(q[:, :, 1].mean(axis=1))
    b = float(np.polyfit(r, la, 1)[0]) if len(q) >= 4 and np.ptp(r) > 10.0 else 0.0
    a = float(np.median(la - b * r))
    fine = np.linspace(pano.radii[0], pano.radii[-1], 4 * len(pano.radii))
    aspect = np.exp(a + b * fine)
    c = float(np.clip(aspect.max(), 1.0, 3.0))
    rows_per_px = (len(pano.radii) - 1) / (pano.radii[0] - pano.radii[-1])
    dens = rows_per_px * c / aspect  # new rows per pixel of radius
    dr = abs(fine[1] - fine[0])
    y = np.concatenate([[0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1]) * dr)])
    n_rows = int(np.clip(round(y[-1]) + 1, 8, 4 * len(pano.radii)))
    radii = np.interp(np.linspace(0.0, y[-1], n_rows), y, fine)
    n_cols = int(round(pano.n_cols * c))
    return Panorama(pano.centre, pano.theta0, n_cols, int(n_cols * WRAP_DEG / 360), radii, pano.reversed)


# --------------------------------------------------------------------------- boards and markers


@dataclass
class CodedBoard:
    """What the detector knows of one coded board (from its spec).

    Attributes:
        name: the board's name in the setup.
        spec: its type and fields (:func:`slcvjax.observations.targets.read_board`'s).
        points: (N, 3) its points, mm (its own frame).
        ids: (K,) its marker ids, in marker order.
        marker_corners: (K, 4, 2) each marker's corners in the board frame (mm), in the order
            OpenCV's detector reports them (its image's top-left, top-right, bottom-right,
            bottom-left on an upright print).
        unit: the markers' pitch (mm): a ChArUco square, an AprilGrid tag plus its gap.
        half_mm: the sub-pixel window's half-size (mm, board units), inside the white margin
            around a ChArUco marker or inside a tag's border bit.
    """

    name: str
    spec: dict
    points: np.ndarray
    ids: np.ndarray
    marker_corners: np.ndarray
    unit: float
    half_mm: float

    @staticmethod
    def of(name: str, spec: dict) -> "CodedBoard":
        pts = board_points(spec)
        ids = marker_ids(spec)
        if spec["type"] == "charuco":
            s, m = spec["square_mm"], spec["marker_mm"]
            sq = charuco_marker_squares(tuple(spec["squares"])).astype(float)
            x0, y0 = sq[:, 0] * s + (s - m) / 2, sq[:, 1] * s + (s - m) / 2
            quad = np.array([[0, 0], [m, 0], [m, m], [0, m]], float)
            corners = np.stack([x0, y0], -1)[:, None] + quad[None]
            return CodedBoard(name, spec, pts, ids, corners, s, 0.8 * (s - m) / 2)
        if spec["type"] == "aprilgrid":
            tag, gap = spec["tag_mm"], spec["spacing"] * spec["tag_mm"]
            tc = aprilgrid_tag_corners(spec["tag_cols"], spec["tag_rows"])
            corners = pts[tc][:, list(APRIL_CORNER), :2]
            return CodedBoard(name, spec, pts, ids, corners, tag + gap, 0.8 * min(tag / 8, gap))
        raise ValueError(f"board {name!r}: a {spec['type']} board is not a coded target")

    @property
    def dictionary(self) -> str:
        return marker_dictionary(self.spec) or APRILGRID_DICTIONARY


def _homography(board_xy: np.ndarray, pano_xy: np.ndarray) -> np.ndarray:
    return cv2.getPerspectiveTransform(np.float32(board_xy), np.float32(pano_xy))


def apply_affine(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    p = np.concatenate([np.asarray(xy, float), np.ones((*np.shape(xy)[:-1], 1))], -1) @ H.T
    return p[..., :2] / p[..., 2:]


def _h_jacobian(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """d(H x) / dx at board points (N, 2): (N, 2, 2)."""
    p = np.concatenate([np.asarray(xy, float), np.ones((len(xy), 1))], -1) @ H.T
    x = p[:, :2] / p[:, 2:]
    return (H[None, :2, :2] - x[:, :, None] * H[None, 2:3, :2]) / p[:, 2, None, None]


def markers_consistent(board: CodedBoard, found: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
    """The markers of ``found`` (index into ``board.ids`` -> (4, 2) pano corners) that the board's
    geometry confirms: each marker's affine map places some other marker within
    ``NEIGHBOUR_SQUARES`` squares of it (board units) within ``AGREE_MARKERS`` squares (in that marker's
    scale) of where it was found, or the other way round.  A marker with no other marker of
    its board that near is kept (nothing contradicts it); one with neighbours, none of which
    agrees, is dropped."""
    keys = list(found)
    if len(keys) < 2:
        return dict(found)
    centres_b = {k: board.marker_corners[k].mean(axis=0) for k in keys}
    # each marker's affine map (least squares on its four corners): steadier than its homography
    # over the one to two squares to its neighbours
    hs = {}
    for k in keys:
        X = np.concatenate([board.marker_corners[k], np.ones((4, 1))], axis=1)
        A = np.linalg.lstsq(X, found[k], rcond=None)[0].T
        hs[k] = np.vstack([A, [0.0, 0.0, 1.0]])
    centres_p = {k: found[k].mean(axis=0) for k in keys}
    scale = {
        k: math.sqrt(abs(cv2.contourArea(np.float32(found[k])))) / np.ptp(board.marker_corners[k][:, 0]) for k in keys
    }

    def agree(a: int, b: int) -> bool:
        err = np.linalg.norm(apply_affine(hs[a], centres_b[b][None])[0] - centres_p[b])
        return bool(err < AGREE_MARKERS * board.unit * scale[a])

    keep = {}
    for a in keys:
        near = [
            b for b in keys if b != a and np.linalg.norm(centres_b[a] - centres_b[b]) < NEIGHBOUR_SQUARES * board.unit
        ]
        if not near or any(agree(a, b) or agree(b, a) for b in near):
            keep[a] = found[a]
    return keep


def _charuco_corners(board: CodedBoard, markers: dict[int, np.ndarray]):
    """ChArUco corners in the panorama from the kept markers: (ids (M,), pano px (M, 2), board-to-pano
    homography per corner (M, 3, 3)).

    Corner ``j`` (its point index, OpenCV's ChArUco id) is where the homography of each kept marker
    in a white square touching it (one or two) puts the corner's board point; where two do, they
    must agree within ``AGREE`` of a square (their mean is taken), else the corner is left out.
    OpenCV's ``CharucoDetector`` interpolates the corners with homographies over several markers,
    which the panorama's bend (a flat wall's rows curve with the azimuth) defeats; a marker's own
    homography reaches only the corners of its square, a few millimetres from its own corners."""
    spec = board.spec
    sx, sy = spec["squares"]
    where = {(int(c), int(r)): m for m, (c, r) in enumerate(charuco_marker_squares((sx, sy)))}
    hs = {k: _homography(board.marker_corners[k], q) for k, q in markers.items()}
    ok_ids, ok_px, ok_h = [], [], []
    for j in range(len(board.points)):
        i, k = j % (sx - 1), j // (sx - 1)
        adj = [where[sq] for sq in ((i, k), (i + 1, k), (i, k + 1), (i + 1, k + 1)) if sq in where and where[sq] in hs]
        if not adj:
            continue
        xy = board.points[j, None, :2]
        pred = np.stack([apply_affine(hs[m], xy)[0] for m in adj])
        scale = [math.sqrt(abs(cv2.contourArea(np.float32(markers[m])))) / spec["marker_mm"] for m in adj]
        if len(adj) > 1 and np.linalg.norm(pred[0] - pred[1]) > AGREE * board.unit * min(scale):
            continue
        ok_ids.append(j)
        ok_px.append(pred.mean(axis=0))
        ok_h.append(hs[adj[0]])
    return np.asarray(ok_ids, int), np.asarray(ok_px, float).reshape(-1, 2), np.asarray(ok_h).reshape(-1, 3, 3)


def _april_corners(board: CodedBoard, markers: dict[int, np.ndarray]):
    """AprilGrid corners from the kept tags: each tag's four corners with Kalibr's indices."""
    spec = board.spec
    tc = aprilgrid_tag_corners(spec["tag_cols"], spec["tag_rows"])
    ids, px, hs = [], [], []
    for t, quad in markers.items():
        H = _homography(board.marker_corners[t], quad)
        for k in range(4):
            ids.append(int(tc[t, APRIL_CORNER[k]]))
            px.append(quad[k])
            hs.append(H)
    return np.asarray(ids, int), np.asarray(px, float).reshape(-1, 2), np.asarray(hs).reshape(-1, 3, 3)


# --------------------------------------------------------------------------- sub-pixel


def refine_saddle(
    grey: np.ndarray, uv: np.ndarray, J: np.ndarray, half: float, iters: int = 12, min_px: float = MIN_WINDOW_PX
) -> tuple:
    """Sub-pixel corners in the original image by the gradient-orthogonality condition.

    Args:
        grey: (H, W) float image.
        uv: (N, 2) first corners, px.
        J: (N, 2, 2) each corner's local map from the board frame (mm) to the image (px).
        half: the window's half-size in board units (mm).

    Every pixel ``q`` whose board offset ``b = J^-1 (q - p)`` lies within ``half`` of the corner
    ``p`` along both board axes weighs in with ``w = (1 - (b_x / half)^2)(1 - (b_y / half)^2)``; ``p``
    solves ``sum w g g^T (q - p) = 0`` (``g``: the image's gradient at ``q``; at an edge through
    ``p`` it is perpendicular to ``q - p``), then the window is moved to it, ``iters`` times or
    until it moves less than 1e-4 px.  The window is a parallelogram in the image, point-symmetric
    about ``p`` like the blurred X-junction of the four squares, so the junction's own
    gradients cancel.  Returns ``(uv (N, 2), ok (N,))``: ok is False where the window holds
    fewer than 6 pixels or its normal matrix is singular (a blank or single-edge window).
    """
    gx = cv2.Sobel(grey, cv2.CV_64F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(grey, cv2.CV_64F, 0, 1, ksize=3) / 8.0
    h_img, w_img = grey.shape
    out, ok = np.array(uv, float), np.zeros(len(uv), bool)
    for n in range(len(uv)):
        # each board axis's half-width: ``half`` mm, or ``min_px`` pixels where that is fewer
        hb = np.maximum(half, min_px / np.maximum(np.linalg.norm(J[n], axis=0), 1e-9))
        A = J[n] * hb[None, :]  # the window's unit square -> image px
        try:
            Ai = np.linalg.inv(A)
        except np.linalg.LinAlgError:
            continue
        ext = np.abs(A).sum(axis=1) + 1.5  # the window's half-extent in px along u, v
        p = out[n].copy()
        good = False
        for _ in range(iters):
            u0, u1 = int(math.floor(p[0] - ext[0])), int(math.ceil(p[0] + ext[0]))
            v0, v1 = int(math.floor(p[1] - ext[1])), int(math.ceil(p[1] + ext[1]))
            if u0 < 1 or v0 < 1 or u1 >= w_img - 1 or v1 >= h_img - 1:
                good = False
                break
            vv, uu = np.mgrid[v0 : v1 + 1, u0 : u1 + 1]
            q = np.stack([uu.ravel(), vv.ravel()], -1).astype(float)
            b = (q - p) @ Ai.T
            w = np.clip(1 - b[:, 0] ** 2, 0, None) * np.clip(1 - b[:, 1] ** 2, 0, None)
            if np.count_nonzero(w) < 6:
                good = False
                break
            g = np.stack([gx[v0 : v1 + 1, u0 : u1 + 1].ravel(), gy[v0 : v1 + 1, u0 : u1 + 1].ravel()], -1)
            M = np.einsum("k,ki,kj->ij", w, g, g)
            rhs = np.einsum("k,ki,kj,kj->i", w, g, g, q)
            if np.linalg.cond(M) > 1e6:
                good = False
                break
            new = np.linalg.solve(M, rhs)
            step = np.linalg.norm(new - p)
            p, good = new, True
            if step < 1e-4:
                break
        out[n], ok[n] = p, good
    return out, ok


# --------------------------------------------------------------------------- one image


@dataclass
class CodedDetection:
    """One image's coded corners.

    Attributes:
        boards: board name -> (pixels (N, 2), seen (N,) bool), N the board's points; a point not
            found is unseen (its pixel 0).
        problems: what was left out, in words.
        markers: board name -> the number of its markers kept.
        reversed: the image was read as mirror-reversed.
    """

    boards: dict[str, tuple[np.ndarray, np.ndarray]]
    problems: list[str]
    markers: dict[str, int]
    reversed: bool = False


def _detector(dictionary: str) -> cv2.aruco.ArucoDetector:
    p = cv2.aruco.DetectorParameters()
    p.minMarkerPerimeterRate = 0.005  # a panorama is wide: its markers are small against its width
    p.adaptiveThreshWinSizeMax = 43
    p.adaptiveThreshWinSizeStep = 4
    p.polygonalApproxAccuracyRate = 0.06  # a marker's sides bend slightly in the panorama
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    return cv2.aruco.ArucoDetector(d, p)


def _sharpen(pano: np.ndarray) -> np.ndarray:
    """An unsharp mask (sigma 2 px, gain 1): the thin white margins the mirror squeezes stand out."""
    f = pano.astype(np.float32)
    return np.clip(2.0 * f - cv2.GaussianBlur(f, (0, 0), 2.0), 0, 255).astype(np.uint8)


def _find_markers(pano_img: np.ndarray, boards: list[CodedBoard], n_cols: int) -> dict[str, dict[int, np.ndarray]]:
    """Markers in the panorama by board: name -> {marker index: (4, 2) pano corners}.

    Ids of no board are dropped.  A marker seen twice (once more past the full turn) is taken
    where it is nearest its board's middle (the circular mean of its markers' columns, moved
    past the full turn where it lies in the first half of the wrap), so that a board across the
    seam is whole."""
    owner = {int(i): (b, k) for b in boards for k, i in enumerate(b.ids)}
    sharp = _sharpen(pano_img)
    copies: dict[str, dict[int, list[np.ndarray]]] = {b.name: {} for b in boards}
    for dictionary in sorted({b.dictionary for b in boards}):
        corners, ids, _ = _detector(dictionary).detectMarkers(sharp)
        if ids is None:
            continue
        for c, i in zip(corners, ids.ravel(), strict=True):
            hit = owner.get(int(i))
            if hit is not None and hit[0].dictionary == dictionary:
                copies[hit[0].name].setdefault(hit[1], []).append(c.reshape(4, 2).astype(float))
    wrap = pano_img.shape[1] - n_cols
    out: dict[str, dict[int, np.ndarray]] = {}
    for name, per in copies.items():
        out[name] = {}
        if not per:
            continue
        cols = np.array([q[:, 0].mean() for qs in per.values() for q in qs])
        mid = np.angle(np.exp(2j * np.pi * cols / n_cols).mean()) % (2 * np.pi) * n_cols / (2 * np.pi)
        if mid < wrap / 2:
            mid += n_cols
        for k, qs in per.items():
            out[name][k] = min(qs, key=lambda q: abs(q[:, 0].mean() - mid))
    return out


def detect_coded(
    bgr: np.ndarray, specs: dict[str, dict], azimuths_deg: dict[str, float] | None = None, disc=None
) -> CodedDetection:
    """The coded boards' corners in one catadioptric image (see the module's steps).

    Args:
        bgr: the image (BGR uint8; a grey image is taken as is).
        specs: board name -> its spec (``charuco`` or ``aprilgrid``).
        azimuths_deg: the boards' nominal azimuths (deg), for the panorama's seam (in their
            widest gap); None: the seam at azimuth 0.
        disc: the mirror's disc (:func:`slcvjax.images.detect.find_mirror`), found here where None.
    """
    from .disc import find_mirror

    grey = bgr if bgr.ndim == 2 else cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    green = (bgr if bgr.ndim == 2 else bgr[:, :, 1]).astype(float)
    boards = [CodedBoard.of(n, s) for n, s in specs.items()]
    empty = {b.name: (np.zeros((len(b.points), 2)), np.zeros(len(b.points), bool)) for b in boards}
    disc = find_mirror(green) if disc is None else disc
    if disc is None:
        return CodedDetection(empty, ["no mirror found"], {})
    r_out = float(min(disc.axes)) - 1.0
    r_in = inner_radius(green, disc.centre, disc.inside_level, r_out)
    theta0 = _seam(list((azimuths_deg or {}).values()))

    def markers_of(pano):
        found = _find_markers(pano.warp(grey), boards, pano.n_cols)
        return found, sum(len(v) for v in found.values())

    best = None
    for rev in (False, True):
        pano = first_panorama(disc.centre, r_in, r_out, theta0, rev)
        found, n = markers_of(pano)
        if best is None or n > best[2]:
            best = (pano, found, n)
    pano, found, n = best
    if n:
        second = squared_panorama(pano, [q for f in found.values() for q in f.values()])
        found2, n2 = markers_of(second)
        if n2 >= n:
            pano, found = second, found2
    g64 = grey.astype(float)
    out, problems, counts = dict(empty), [], {}
    for b in boards:
        markers = markers_consistent(b, found[b.name])
        dropped = len(found[b.name]) - len(markers)
        if dropped:
            problems.append(f"{b.name}: {dropped} marker(s) left out (their place disagrees with their neighbours')")
        counts[b.name] = len(markers)
        if not markers:
            problems.append(f"{b.name}: not found")
            continue
        if b.spec["type"] == "charuco":
            ids, px, hs = _charuco_corners(b, markers)
        else:
            ids, px, hs = _april_corners(b, markers)
        if not len(ids):
            problems.append(f"{b.name}: {len(markers)} marker(s), no corner")
            continue
        uv = pano.to_image(px)
        J = pano.jacobian(px) @ np.stack(
            [_h_jacobian(h, b.points[j, None, :2])[0] for h, j in zip(hs, ids, strict=True)]
        )
        fine, ok = refine_saddle(g64, uv, J, b.half_mm)
        local = np.linalg.svd(J, compute_uv=False).min(axis=1) * b.unit  # the square's smaller side, px
        ok &= np.linalg.norm(fine - uv, axis=1) < np.maximum(MAX_SHIFT * local, 1.0)
        px_out, seen = empty[b.name][0].copy(), empty[b.name][1].copy()
        px_out[ids[ok]], seen[ids[ok]] = fine[ok], True
        out[b.name] = (px_out, seen)
        if (~ok).any():
            problems.append(f"{b.name}: {int((~ok).sum())} corner(s) left out (no sub-pixel fit)")
    return CodedDetection(out, problems, counts, pano.reversed)


# --------------------------------------------------------------------------- direct views, folders


def detect_direct(bgr: np.ndarray, spec: dict) -> tuple[np.ndarray, np.ndarray] | None:
    """A coded board seen directly (no mirror): ``(pixels (N, 2), seen (N,))`` by its point index, or
    None where no corner is found.

    ChArUco: ``cv2.aruco.CharucoDetector`` (OpenCV's board of the spec; a corner's id is its
    point index), then ``cv2.cornerSubPix`` (5 x 5 window).  AprilGrid: each tag's four corners
    (Kalibr's indices, as through the mirror), then ``cv2.cornerSubPix``.  Markers whose ids are
    not the board's are ignored by OpenCV's board (ChArUco) or dropped (AprilGrid)."""
    grey = bgr if bgr.ndim == 2 else cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    board = CodedBoard.of("direct", spec)
    n = len(board.points)
    if spec["type"] == "charuco":
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, spec["dictionary"]))
        cb = cv2.aruco.CharucoBoard(tuple(spec["squares"]), spec["square_mm"], spec["marker_mm"], d, board.ids)
        cc, cid, _, _ = cv2.aruco.CharucoDetector(cb).detectBoard(grey)
        if cid is None or not len(cid):
            return None
        ids, px = cid.ravel().astype(int), cc.reshape(-1, 2)
    else:
        corners, mids, _ = _detector(board.dictionary).detectMarkers(grey)
        if mids is None:
            return None
        owner = {int(i): k for k, i in enumerate(board.ids)}
        found = {owner[int(i)]: c.reshape(4, 2) for c, i in zip(corners, mids.ravel(), strict=True) if int(i) in owner}
        found = markers_consistent(board, found)
        if not found:
            return None
        ids, px, _ = _april_corners(board, found)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    px = cv2.cornerSubPix(grey, np.float32(px).reshape(-1, 1, 2), (5, 5), (-1, -1), crit).reshape(-1, 2)
    pixels, seen = np.zeros((n, 2)), np.zeros(n, bool)
    pixels[ids], seen[ids] = px, True
    return pixels, seen


def coded_walls(setup) -> dict[str, dict]:
    """The setup's coded targets seen through the mirror: name -> spec (charuco, aprilgrid)."""
    return {
        k: b.target
        for k, b in setup.boards.items()
        if b.azimuth_deg is not None and b.target is not None and b.target["type"] in ("charuco", "aprilgrid")
    }


def detect_coded_view(bgr: np.ndarray, setup, disc=None) -> CodedDetection:
    """:func:`detect_coded` for the coded walls of a ``slcv-setup/1`` (:func:`coded_walls`), the
    panorama's seam in the widest gap between their nominal azimuths."""
    specs = coded_walls(setup)
    return detect_coded(bgr, specs, {k: setup.boards[k].azimuth_deg for k in specs}, disc)
