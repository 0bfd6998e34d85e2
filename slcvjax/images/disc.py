"""The mirror's disc in a catadioptric image: where the mirror's view is, and its outline's ellipse."""

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class MirrorDisc:
    """The mirror's disc in an image: ellipse centre (u, v), semi-axes, angle (deg), filled mask."""

    centre: np.ndarray
    axes: tuple[float, float]
    angle: float
    mask: np.ndarray
    inside_level: float
    outside_level: float
    wall_map: np.ndarray | None = None  # the local level of the mirror's view (``wall_level``), once computed


MIRROR_PIECE = 0.05  # a bright region counts as part of the mirror's view when this fraction of the largest


def find_mirror(green: np.ndarray) -> MirrorDisc | None:
    """The mirror's disc: the bright regions (Otsu on green) of the mirror's view, and the ellipse
    of its outline.

    The view may be cut into pieces by dark wedges that reach the rim (a box whose corners are
    open, a dark object): every bright region of at least ``MIRROR_PIECE`` of the largest's area
    is taken, and their convex hull is the disc.  The ellipse is fitted to the pieces' outline
    pixels that lie on that hull (within 1.5 px), so neither the wedges' sides nor notches cut
    into the edge (a dark dot or a spot at the rim) pull it; then refitted to the outline pixels
    within 2 px of it.  The mask is the hull with its holes filled.
    """
    g8 = np.clip(green, 0, 255).astype(np.uint8)
    if float(green.max()) - float(green.min()) < 20:
        return None
    _, bright = cv2.threshold(g8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(bright, connectivity=8)
    if n < 2:
        return None
    areas = stats[1:, cv2.CC_STAT_AREA]
    keep = 1 + np.flatnonzero(areas >= MIRROR_PIECE * areas.max())
    region = np.isin(labels, keep).astype(np.uint8)
    contours, _ = cv2.findContours(region, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    pts = np.concatenate([c.reshape(-1, 2) for c in contours])
    if len(pts) < 20:
        return None
    hull = cv2.convexHull(pts.astype(np.int32))
    on_hull = np.array([cv2.pointPolygonTest(hull, (float(x), float(y)), True) for x, y in pts]) < 1.5
    outline = pts[on_hull].astype(np.float32)
    if len(outline) < 20:
        return None
    ell = cv2.fitEllipse(outline)
    for _ in range(2):
        (cu, cv_), (a, b), ang = ell
        probe = MirrorDisc(np.array([cu, cv_]), (a / 2, b / 2), ang, np.zeros(1, bool), 0.0, 0.0)
        d = outline - np.array([cu, cv_])
        dist = np.abs(np.hypot(d[:, 0], d[:, 1]) - ellipse_radius(probe, np.arctan2(d[:, 1], d[:, 0])))
        near = outline[dist < 2.0]
        if len(near) < 20:
            break
        ell = cv2.fitEllipse(near)
    (cu, cv_), (a, b), ang = ell
    mask = np.zeros_like(region)
    cv2.drawContours(mask, [hull], -1, 1, thickness=-1)
    inside = float(np.median(green[region > 0]))
    outside = float(np.median(green[mask == 0])) if np.any(mask == 0) else 0.0
    return MirrorDisc(np.array([cu, cv_]), (a / 2, b / 2), ang, mask.astype(bool), inside, outside)


def ellipse_radius(disc: MirrorDisc, theta: np.ndarray) -> np.ndarray:
    """The ellipse's radius (px) at polar angles ``theta`` (rad) about its centre."""
    a, b = disc.axes
    phi = theta - np.radians(disc.angle)
    return a * b / np.sqrt((b * np.cos(phi)) ** 2 + (a * np.sin(phi)) ** 2)
