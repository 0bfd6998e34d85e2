"""Stage 4 of the staged calibration: the lasers' lines from their spots.

Each spot's reflected ray meets its board's plane at a 3D point; a 3D line per laser by consensus
over its spots, then least squares; spots that lie near another laser's line instead of their own
are given that laser, spots near none are left out (:func:`fit_lasers`).  :func:`aimed_lasers` aims
each laser from the camera's centre through its spots instead (another start for the joint fit).
"""

from dataclasses import dataclass

import numpy as np

from ..geometry.camera import Camera
from ..geometry.lasers import Lasers
from ..geometry.mirror import Mirror
from ..geometry.pose import Pose
from ..observations.problem import (
    Kind,
    Packed,
    map_padded,
)
from .base import StageReport, rays_with_pixel_metric
from .options import DEFAULT_POLICY, RobustPolicy

RAYLEIGH_MEDIAN = float(np.sqrt(2.0 * np.log(2.0)))  # median of |r| / sigma for 2D Gaussian r


@dataclass
class LaserFit:
    """:func:`fit_lasers`' result: the lines, the stage's report and what became of each spot.

    ``labels`` (S,): the laser each spot is given (its own, another laser's, or -1: left
    out); ``residual`` (S, L): each spot's distance from each laser's fitted line in px
    (first order, see :func:`spot_line_residuals`); ``threshold`` (px): the distance past
    which a spot does not belong to a line.
    """

    lasers: Lasers
    report: StageReport
    labels: np.ndarray
    residual: np.ndarray
    threshold: float
    undetermined: np.ndarray  # (L,) bool: lasers whose spots cannot fix a line (held, see fit_lasers)

    @property
    def held(self) -> tuple[int, ...]:
        """The undetermined lasers' indices."""
        return tuple(int(i) for i in np.flatnonzero(self.undetermined))


def spot_line_residuals(org, dirs, metric, normals, origins, points, directions) -> np.ndarray:
    """(S, L) px: each spot's distance from where each line ``(points, directions)`` meets
    the spot's board plane (``normals``, ``origins``, per spot), seen from the spot's mirror
    point ``org`` and mapped to pixels by its ray's ``metric`` (2x3, direction change to
    pixels, to first order); inf where the line misses the plane, the point is behind the
    mirror point, or behind the line's foot of the perpendicular from the camera centre (not
    on the beam: see :func:`slcvjax.measurement.measure.triangulate_spot`)."""
    den = normals @ directions.T  # (S, L)
    lam = np.sum(normals[:, None, :] * (origins[:, None, :] - points[None]), axis=2) / np.where(
        np.abs(den) < 1e-12, np.nan, den
    )
    q = points[None] + lam[..., None] * directions[None]  # (S, L, 3)
    v = q - org[:, None, :]
    dist = np.linalg.norm(v, axis=2)
    dq = v / np.where(dist > 0, dist, np.nan)[..., None]
    r = np.linalg.norm(np.einsum("sij,slj->sli", metric, dq - dirs[:, None, :]), axis=2)
    ahead = (np.sum(dq * dirs[:, None, :], axis=2) > 0.0) & (np.sum(q * directions[None], axis=2) > 0.0)
    return np.where(np.isfinite(r) & ahead, r, np.inf)


def _line_through(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    centre = p.mean(axis=0)
    d = np.linalg.svd(p - centre)[2][0]
    return centre, (-d if d @ centre < 0 else d)


def _spot_points(camera: Camera, mirror: Mirror, pk: Packed, poses: list[Pose]):
    """Each spot's point where its reflected ray meets its board's plane (camera frame, mm),
    whether that is usable (a valid ray, the board ahead of the mirror along it), and the rays'
    origins, directions and pixel metrics with the boards' normals and origins per spot."""
    rays, metric = map_padded(rays_with_pixel_metric, camera, mirror, rows=pk.spot_pixels)
    org, dirs, ok = np.asarray(rays.point), np.asarray(rays.direction), np.asarray(rays.valid)
    metric = np.asarray(metric)
    pose_of = np.asarray(pk.spot_pose)[: org.shape[0]]
    normals = np.array([np.asarray(p.R)[:, 2] for p in poses]).reshape(-1, 3)[pose_of]
    origins = np.array([np.asarray(p.t) for p in poses]).reshape(-1, 3)[pose_of]
    den = np.sum(normals * dirs, axis=1)
    lam = np.sum(normals * (origins - org), axis=1) / np.where(np.abs(den) < 1e-9, np.nan, den)
    # the board must lie ahead of the mirror along the reflected ray
    usable = ok & np.isfinite(lam) & (lam > 0)
    pts = org + np.where(usable, lam, 0.0)[:, None] * dirs
    return pts, usable, (org, dirs, metric, normals, origins)


def aimed_lasers(camera: Camera, mirror: Mirror, pk: Packed, poses: list[Pose], lasers: Lasers) -> Lasers:
    """``lasers`` with each line that has spots replaced by the line from the camera's centre
    through the centroid of its spots' points on their boards: another start for a laser whose
    spots lie along a short stretch of its line (aimed where the range hardly changes from view to
    view), whose direction the points alone do not fix."""
    pts, usable, _ = _spot_points(camera, mirror, pk, poses)
    laser_of = np.asarray(pk.spot_laser)[: pts.shape[0]]
    points, directions = np.array(lasers.points), np.array(lasers.directions)
    for i in range(lasers.n):
        sel = usable & (laser_of == i)
        if sel.any():
            c = pts[sel].mean(axis=0)
            if np.linalg.norm(c) > 1e-6:
                points[i], directions[i] = c, c / np.linalg.norm(c)
    return Lasers.create(points, directions).canonical()


def fit_lasers(
    camera: Camera,
    mirror: Mirror,
    pk: Packed,
    poses: list[Pose],
    n_lasers: int,
    repair: bool = True,
    policy: RobustPolicy = DEFAULT_POLICY,
) -> LaserFit:
    """One 3D line per laser through its spots' points on their boards' planes, robust to
    wrong labels and gross outliers.

    Each spot's reflected ray meets its board's plane at a point.  Per laser, every pair of
    its points proposes a line, and the one that most of its spots lie near (within
    ``policy.consensus_px``, the truncated quadratic cost of MSAC) wins; a least-squares line
    through those spots follows.  Then every spot is measured against every laser's line
    (:func:`spot_line_residuals`): one further than ``policy.repair_sigmas`` noise sigmas (the
    sigma from the median distance of the spots from their own lines) from its own line is
    given the one other line it lies near, or left out where none or more than one is near;
    the lines are fitted again to the spots they keep, twice.  ``repair=False``: every spot
    keeps its label (a plain least-squares line per laser).

    A laser whose consistent points cannot fix a line (fewer than 2, or all within 1 mm of each
    other) is undetermined (``LaserFit.undetermined``, the reason in the report's notes): it
    gets a placeholder line (:func:`_placeholder_line`) that nothing is fitted to, its spots are
    left out and no spot is given to it.  With no lasers, no lines.
    """
    if n_lasers == 0:
        n_s = int(pk.counts[Kind.SPOT])
        none = Lasers.create(np.zeros((0, 3)), np.zeros((0, 3)))
        report = StageReport("lasers", float("nan"), "px", ["no lasers"])
        return LaserFit(none, report, np.full(n_s, -1), np.zeros((n_s, 0)), float("inf"), np.zeros(0, bool))
    pts, usable, (org, dirs, metric, normals, origins) = _spot_points(camera, mirror, pk, poses)
    own = np.asarray(pk.spot_laser)[: org.shape[0]]

    def residuals(points, directions):
        return spot_line_residuals(org, dirs, metric, normals, origins, points, directions)

    def fit(labels, consensus: bool):
        points, directions = np.zeros((n_lasers, 3)), np.zeros((n_lasers, 3))
        why: dict[int, str] = {}
        for laser in range(n_lasers):
            idx = np.flatnonzero(usable & (labels == laser))
            p = pts[idx]
            spread = np.linalg.svd(p - p.mean(axis=0), compute_uv=False)[0] / np.sqrt(len(p)) if len(p) >= 2 else 0.0
            if len(p) < 2 or spread < 0.5:
                why[laser] = (
                    f"laser {laser} undetermined: {len(p)} consistent spot point(s) spread over {2 * spread:.2g} mm "
                    "cannot fix a line (it needs spots on at least 2 planes at different distances); it is held "
                    "and its spots are left out"
                )
                continue
            if consensus and len(p) > 2:
                a, b = np.triu_indices(len(p), 1)
                far = np.linalg.norm(p[a] - p[b], axis=1) > 1.0
                a, b = a[far], b[far]
                cand_d = (p[b] - p[a]) / np.linalg.norm(p[b] - p[a], axis=1, keepdims=True)
                r = residuals(p[a], cand_d)[idx]  # (own spots, candidates)
                best = int(np.argmin(np.sum(np.minimum(r, policy.consensus_px) ** 2, axis=0)))
                inl = r[:, best] < policy.consensus_px
                if inl.sum() >= 2:
                    p = p[inl]
            points[laser], directions[laser] = _line_through(p)
        for laser in why:
            points[laser], directions[laser] = _placeholder_line(pts[usable & (labels == laser)], directions, why)
        return points, directions, why

    labels = own.copy()
    points, directions, why = fit(labels, consensus=repair)
    threshold = np.inf
    for _ in range(2 if repair else 0):
        r = residuals(points, directions)
        r[:, list(why)] = np.inf  # no spot is given to an undetermined laser's placeholder
        r_own = r[np.arange(len(own)), own]
        finite = usable & np.isfinite(r_own)
        sigma = float(np.median(r_own[finite])) / RAYLEIGH_MEDIAN if finite.any() else 0.0
        threshold = max(policy.repair_sigmas * sigma, policy.min_repair_px)
        near = r <= threshold
        labels = np.where(near[np.arange(len(own)), own], own, -1)
        other = (labels < 0) & (near.sum(axis=1) == 1)
        labels[other] = np.argmax(near[other], axis=1)
        # a spot near no line keeps its own unless it is far from every line: with the
        # geometry not final yet, the joint stage decides on the smaller misfits
        keep = (labels < 0) & (near.sum(axis=1) == 0) & (r_own <= policy.consensus_px)
        labels[keep] = own[keep]
        labels[~usable] = -1
        points, directions, why = fit(labels, consensus=False)
    undetermined = np.isin(np.arange(n_lasers), list(why))
    lasers = Lasers.create(points, directions).canonical()
    r = residuals(np.asarray(lasers.points), np.asarray(lasers.directions))
    r[:, undetermined] = np.inf
    labels = np.where((labels >= 0) & undetermined[np.maximum(labels, 0)], -1, labels)
    kept = labels >= 0
    resid = r[np.flatnonzero(kept), labels[kept]]
    notes = [f"{n_lasers - len(why)} of {n_lasers} lasers from {int(kept.sum())} spots"]
    n_moved = int(np.sum(kept & (labels != own)))
    n_out = int(np.sum(usable & ~kept & ~undetermined[own]))
    if n_moved or n_out:
        notes.append(f"{n_moved} spot(s) given another laser, {n_out} left out (near no line, or near two)")
    notes += [why[i] for i in sorted(why)]
    report = StageReport("lasers", float(np.sqrt(np.mean(np.square(resid)))) if resid.size else 0.0, "px", notes)
    return LaserFit(lasers, report, labels, r, float(threshold), undetermined)


def _placeholder_line(p: np.ndarray, directions: np.ndarray, undetermined) -> tuple[np.ndarray, np.ndarray]:
    """A line for an undetermined laser: through its points' centroid (the camera's centre where
    it has none), along the mean direction of the lasers that are determined (the camera's axis
    where none is).  Nothing is fitted to it: the laser is held and its spots are left out."""
    known = np.delete(directions, list(undetermined), axis=0)
    d = known.sum(axis=0) if known.size else np.array([0.0, 0.0, 1.0])
    d = d / np.linalg.norm(d) if np.linalg.norm(d) > 1e-9 else np.array([0.0, 0.0, 1.0])
    return (p.mean(axis=0) if len(p) else np.zeros(3)), d
