"""Stage 4 for line and ring lasers: each sheet of light from its stripes' points on posed boards.

Each stripe sample's reflected ray meets its board's plane at a 3D point (camera frame, mm).  Per
line laser a plane through its points, per ring laser a cone (:mod:`slcvjax.geometry.sheets`), each
by least squares on the points' distances from the sheet, with the points further than
``SHEET_TRIM_SIGMAS`` robust sigmas from it left out and the fit repeated (twice): a start for the
joint LM, which weighs every sample again under the calibration's robust loss.

A plane is the points' total least squares plane (the smallest singular vector).  A cone starts as
the flat disc through that plane, its apex where a circle fitted to the points in the plane has
its centre (a ring laser's light goes round its axis); a damped Gauss-Newton on the points'
distances from the cone (``rho sin(phi - theta)``, with ``rho`` a point's distance from the apex
and ``phi`` its angle from the axis) moves the apex, the axis and the half-angle from there.  A
cone is the same surface with its axis reversed and its half-angle ``pi - theta``; the fit gives
the one whose axis points along the camera's view (``+z``).

A sheet whose points cannot fix it is undetermined and held (its samples are left out): a plane
needs points off one line (spread at least 1 mm across), a cone points round its axis in at least
two planes at different distances.
"""

from dataclasses import dataclass

import numpy as np

from ..geometry.camera import Camera
from ..geometry.mirror import Mirror
from ..geometry.pose import Pose
from ..geometry.sheets import Sheets
from ..observations.problem import Kind, Packed, map_padded
from .base import StageReport, rays_with_pixel_metric

SHEET_TRIM_SIGMAS = 4.0  # points further than this many robust sigmas from their sheet are left out of the start
MIN_SPREAD_MM = 1.0  # a plane's points must spread this far across their best line
CONE_STEPS = 60  # Gauss-Newton steps of a cone's fit


@dataclass
class SheetFit:
    """:func:`fit_sheets`' result: the sheets, the stage's report, and which sheets are undetermined
    (held: their samples cannot fix them)."""

    sheets: Sheets
    report: StageReport
    undetermined: np.ndarray  # (S,) bool

    @property
    def held(self) -> tuple[int, ...]:
        return tuple(int(i) for i in np.flatnonzero(self.undetermined))


def stripe_points(camera: Camera, mirror: Mirror, pk: Packed, poses: list[Pose]) -> tuple[np.ndarray, np.ndarray]:
    """Each stripe sample's point where its reflected ray meets its board's plane (camera frame,
    mm), and whether it is usable (a valid ray, the board ahead of the mirror along it)."""
    n = int(pk.counts[Kind.STRIPE]) if pk.has_stripes else 0
    if n == 0:
        return np.zeros((0, 3)), np.zeros(0, bool)
    rays, _ = map_padded(rays_with_pixel_metric, camera, mirror, rows=np.asarray(pk.stripe_pixels)[:n])
    org, dirs, ok = np.asarray(rays.point), np.asarray(rays.direction), np.asarray(rays.valid)
    pose_of = np.asarray(pk.stripe_pose)[:n]
    normals = np.array([np.asarray(p.R)[:, 2] for p in poses]).reshape(-1, 3)[pose_of]
    origins = np.array([np.asarray(p.t) for p in poses]).reshape(-1, 3)[pose_of]
    den = np.sum(normals * dirs, axis=1)
    lam = np.sum(normals * (origins - org), axis=1) / np.where(np.abs(den) < 1e-9, np.nan, den)
    usable = ok & np.isfinite(lam) & (lam > 0)
    return org + np.where(usable, lam, 0.0)[:, None] * dirs, usable


def _basis(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    h = np.eye(3)[int(np.argmin(np.abs(a)))]
    e1 = h - (h @ a) * a
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(a, e1)


def plane_through(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The total least squares plane of points ``p`` (N, 3): its centroid and unit normal (the
    normal turned to point away from the camera's centre, the origin, where it can)."""
    c = p.mean(axis=0)
    n = np.linalg.svd(p - c)[2][-1]
    return c, (-n if n @ c < 0 else n)


def cone_distances(x: np.ndarray, apex, axis, theta) -> np.ndarray:
    """Signed distances (mm) of points ``x`` (N, 3) from the cone ``(apex, axis, theta)``:
    ``rho sin(phi - theta)`` with ``rho = |x - apex|`` and ``phi`` the angle of ``x - apex``
    from the axis (exact for ``|phi - theta| <= 90 deg``)."""
    q = x - apex
    rho = np.linalg.norm(q, axis=1)
    c = np.clip(q @ axis / np.where(rho > 0, rho, 1.0), -1.0, 1.0)
    return rho * np.sin(np.arccos(c) - theta)


def _cone_move(apex, axis, theta, d):
    e1, e2 = _basis(axis)
    a = axis + d[3] * e1 + d[4] * e2
    return apex + d[0] * e1 + d[1] * e2 + d[2] * axis, a / np.linalg.norm(a), theta + d[5]


def _circle_centre(u: np.ndarray) -> np.ndarray:
    """The centre of the least-squares circle through 2D points ``u`` (algebraic fit)."""
    A = np.column_stack([2 * u, np.ones(len(u))])
    sol = np.linalg.lstsq(A, np.sum(u * u, axis=1), rcond=None)[0]
    return sol[:2]


def fit_cone(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
    """A cone through points ``p`` (N, 3) by damped Gauss-Newton from the flat disc through their
    plane: apex, unit axis, half-angle (rad) and the RMS distance (mm)."""
    c, n = plane_through(p)
    e1, e2 = _basis(n)
    centre = c + _circle_centre(np.column_stack([(p - c) @ e1, (p - c) @ e2])) @ np.stack([e1, e2])
    best = None
    for axis in (n, -n):  # the light's side is unknown: a half-angle below or above 90 deg from each
        apex, a, th = centre, axis, np.pi / 2
        lam = 1e-3
        r = cone_distances(p, apex, a, th)
        cost = float(r @ r)
        for _ in range(CONE_STEPS):
            eps = 1e-6
            J = np.stack(
                [(cone_distances(p, *_cone_move(apex, a, th, eps * np.eye(6)[k])) - r) / eps for k in range(6)], axis=1
            )
            H, g = J.T @ J, J.T @ r
            moved = False
            for _ in range(10):
                d = -np.linalg.solve(H + lam * (np.diag(np.diag(H)) + 1e-12 * np.eye(6)), g)
                cand = _cone_move(apex, a, th, d)
                r2 = cone_distances(p, *cand)
                if float(r2 @ r2) < cost:
                    apex, a, th = cand
                    r, cost, lam, moved = r2, float(r2 @ r2), max(lam / 10, 1e-9), True
                    break
                lam *= 10
            if not moved or np.max(np.abs(d)) < 1e-10:
                break
        if 0 < th < np.pi and (best is None or cost < best[3]):
            best = (apex, a, float(th), cost)
    apex, a, th, cost = best
    if a[2] < 0:  # the same cone with its axis along the camera's view (+z): (a, theta) ~ (-a, pi - theta)
        a, th = -a, np.pi - th
    return apex, a, th, float(np.sqrt(cost / len(p)))


def _sheet_of(kind: str, p: np.ndarray):
    """One sheet through points ``p`` with the far ones trimmed: (apex, axis, half-angle, RMS
    mm, points kept), or the reason it is undetermined."""
    need = 3 if kind == "plane" else 6
    if len(p) < need:
        return f"{len(p)} usable stripe point(s) (a {kind} needs at least {need})"
    keep = np.ones(len(p), bool)
    for _ in range(3):
        q = p[keep]
        if kind == "plane":
            c, n = plane_through(q)
            sv = np.linalg.svd(q - c, compute_uv=False) / np.sqrt(len(q))
            if sv[1] < MIN_SPREAD_MM / 2:
                return f"its {len(q)} stripe points lie along one line (spread {2 * sv[1]:.2g} mm across it)"
            apex, axis, th = c, n, np.pi / 2
            d = (p - c) @ n
        else:
            apex, axis, th, _ = fit_cone(q)
            d = cone_distances(p, apex, axis, th)
        sigma = 1.4826 * float(np.median(np.abs(d[keep])))
        new = np.abs(d) <= max(SHEET_TRIM_SIGMAS * sigma, 1e-9)
        if new.sum() < need or np.array_equal(new, keep):
            break
        keep = new
    rms = float(np.sqrt(np.mean(np.square(d[keep]))))
    return apex, axis, th, rms, int(keep.sum())


def fit_sheets(
    camera: Camera, mirror: Mirror, pk: Packed, poses: list[Pose], kinds: tuple[str, ...], start: Sheets | None = None
) -> SheetFit:
    """The rig's line and ring lasers (``kinds``: each sheet's kind in order) from their stripes'
    points on the posed boards (``poses``: each board pose of ``pk``).  ``start``: sheets to keep
    for those that cannot be fitted (by default a placeholder, held).  See the module docstring."""
    n = len(kinds)
    pts, usable = stripe_points(camera, mirror, pk, poses)
    m = pts.shape[0]
    sheet_of = np.asarray(pk.stripe_sheet)[:m] if pk.has_stripes else np.zeros(0, int)
    apex, axis, angle = np.zeros((n, 3)), np.tile([0.0, 0.0, 1.0], (n, 1)), np.full(n, np.pi / 2)
    if start is not None:
        apex, axis, angle = (np.array(x, dtype=float) for x in (start.apex, start.axis, start.half_angle))
    undetermined = np.zeros(n, bool)
    notes, rms_all, used = [], [], 0
    for i, kind in enumerate(kinds):
        got = _sheet_of(kind, pts[usable & (sheet_of == i)])
        if isinstance(got, str):
            undetermined[i] = True
            notes.append(f"{kind} laser {i} undetermined: {got}; it is held and its stripes are left out")
            continue
        apex[i], axis[i], angle[i], rms, kept = got
        rms_all.append(rms)
        used += kept
    notes.insert(0, f"{n - int(undetermined.sum())} of {n} line and ring lasers from {used} stripe points")
    rms = float(np.sqrt(np.mean(np.square(rms_all)))) if rms_all else float("nan")
    sheets = Sheets.create(kinds, apex, axis, angle)
    return SheetFit(sheets, StageReport("sheets", rms, "mm", notes), undetermined)
