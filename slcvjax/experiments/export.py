"""A calibration in other tools' camera formats, and the central approximation of a catadioptric rig.

:func:`export` writes a calibration's camera in one of six formats:

- ``opencv``: OpenCV FileStorage YAML, ``camera_matrix`` (3x3) and ``distortion_coefficients``
  (1x5, ``k1, k2, p1, p2, k3``), as ``cv2.calibrateCamera`` gives them;
- ``opencv-omnidir``: OpenCV's ``omnidir`` module (Mei's unified model): ``camera_matrix`` (3x3,
  skew 0), ``distortion_coefficients`` (1x4, ``k1, k2, p1, p2``) and ``xi`` (1x1);
- ``ros``: ROS ``camera_info`` YAML (``plumb_bob``, 5 coefficients, identity rectification);
- ``kalibr``: a Kalibr camchain YAML with one camera ``cam0``: ``camera_model`` ``pinhole``
  (``intrinsics: [fu, fv, pu, pv]``) or ``omni`` (``intrinsics: [xi, fu, fv, pu, pv]``),
  ``distortion_model: radtan``, ``distortion_coeffs: [k1, k2, r1, r2]``, ``resolution``;
- ``ocamcalib``: Scaramuzza's OCamCalib ``calib_results.txt`` (the direct polynomial of
  ``cam2world``, the inverse polynomial of ``world2cam``, the centre as row and column, the affine
  ``c d e``, the image's height and width);
- ``mrcal``: an mrcal ``.cameramodel`` (``LENSMODEL_OPENCV5``, the reference frame the camera's).

The camera's own lens (pinhole with Brown distortion) is exact in ``opencv``, ``ros`` and
``mrcal``. Kalibr's ``radtan`` has no ``k3`` and omnidir's Mei model none either: where the camera
has a ``k3``, the format's model is fitted to the camera over the image and the fit's error is
reported. A catadioptric calibration (one with a mirror) is not central: no single viewpoint sees
every reflected ray. For ``opencv-omnidir``, ``kalibr`` (``omni``) and ``ocamcalib`` the export is
the best central approximation in the tool's model, fitted over the mirror's field
(:func:`field_samples`: every pixel of a grid over the mirror's image that sees a valid reflected
ray, at three ranges about a working range; where the file carries its problem, only the pixels
of the annulus where the calibration has data, :func:`observed_radii`); its RMS and largest pixel
difference are written into the file and returned. ``opencv``, ``ros`` and ``mrcal`` (and every
format with ``lens=True``) export the camera behind the mirror, its lens alone, and say so.

The approximation's frame. A central model projects points of its own frame; here
``X_model = B R(w)^T (X_cam - t)``: ``t`` (mm) is the fitted viewpoint and ``R(w)`` a fitted
rotation, both in the camera frame, and ``B`` the fixed axis change between the camera frame and
the model's convention: for a mirror, seeing the world reflected, ``B`` is a reflection (Mei:
``diag(1, 1, -1)``, the image's centre looking back at the camera along the model's +z; OCamCalib:
x along the image rows, y along the columns, z as the camera's), so the model's frame is
left-handed in the camera's. Every file carries ``T_cam_model`` (``R_cam_model = R(w) B^T``, and
``t``), with which ``X_cam = R_cam_model X_model + t``. For a lens alone ``t = 0``, ``R(w) = I``.
"""

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ..geometry.camera import Camera, pixel_to_ray
from ..geometry.mirror import back_project
from ..geometry.pose import so3_exp
from ..geometry.rig import Rig
from ..observations.formats import (
    Calibration,
    FormatError,
    OutputError,
    abandon_target,
    atomic_target,
    commit_target,
    write_text_atomic,
)

log = logging.getLogger(__name__)

FORMATS = ("opencv", "opencv-omnidir", "ros", "kalibr", "ocamcalib", "mrcal")
# the ranges of the fit's points, as multiples of the working range
RANGE_FACTORS = (0.5, 1.0, 2.0)
# Mei: the camera frame's axes in the model's, for a mirror (a reflection) and for a lens
B_MEI_MIRROR = np.diag([1.0, 1.0, -1.0])
B_MEI_LENS = np.eye(3)
# OCamCalib: x along the rows (the camera's y), y along the columns (the camera's x); its z looks away
# from the image's centre: the camera's +z for a mirror (whose centre sees the camera), -z for a lens
B_OCAM_MIRROR = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
B_OCAM_LENS = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
OCAM_INVPOL_DEGREE = 10  # world2cam: rho = sum_i invpol[i] theta^i, i = 0..10
OCAM_POL_DEGREE = 4  # cam2world: f(rho) = a0 + a2 rho^2 + a3 rho^3 + a4 rho^4 (a1 = 0, OCamCalib's form)


# --------------------------------------------------------------------------- samples of the field


@dataclass
class FieldSamples:
    """Where the rig sees: ``pixels`` (n, 2) px and ``points`` (n, 3) mm in the camera frame, each
    point on its pixel's (reflected) ray at ``ranges_mm[range_index]`` from the camera's centre;
    ``mirror``: whether the rays are reflected by a mirror (else the lens's own)."""

    pixels: np.ndarray
    points: np.ndarray
    range_index: np.ndarray
    ranges_mm: tuple[float, ...]
    mirror: bool


def _mirror_points(camera: Camera, mirror, grid, ranges):
    def one(uv):
        ray = back_project(camera, mirror, uv)
        m, d = ray.point, ray.direction
        md = jnp.dot(m, d)

        def at(r):
            disc = md * md - jnp.dot(m, m) + r * r
            s = -md + jnp.sqrt(jnp.maximum(disc, 0.0))
            return m + s * d, ray.valid & (disc > 0.0) & (s > 0.0)

        return jax.vmap(at)(ranges)

    return jax.vmap(one)(grid)


def _lens_points(camera: Camera, grid, ranges):
    def one(uv):
        d, ok = pixel_to_ray(camera, uv)
        return jax.vmap(lambda r: (r * d, ok))(ranges)

    return jax.vmap(one)(grid)


_mirror_points_jit = jax.jit(_mirror_points)
_lens_points_jit = jax.jit(_lens_points)


def points_at_ranges(rig: Rig, pixels, ranges_mm, lens: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel (n, 2) and range (k,): the point (n, k, 3), camera frame, mm, on the pixel's
    reflected ray (the lens's ray where the rig has no mirror or ``lens``) at that distance from
    the camera's centre, and whether it exists (n, k)."""
    grid, r = jnp.asarray(np.asarray(pixels, float)), jnp.asarray(np.asarray(ranges_mm, float))
    if rig.mirror is not None and not lens:
        pts, ok = _mirror_points_jit(rig.camera, rig.mirror, grid, r)
    else:
        pts, ok = _lens_points_jit(rig.camera, grid, r)
    pts = np.asarray(pts)
    return pts, np.asarray(ok) & np.all(np.isfinite(pts), axis=-1)


def field_samples(
    rig: Rig, range_mm: float, lens: bool = False, n_grid: int = 60, radii_px: tuple[float, float] | None = None
) -> FieldSamples:
    """Pixels of an ``n_grid`` x ``n_grid`` grid over the image (over the sensor's part of the
    mirror's image where the rig has a mirror and ``lens`` is False) and their points at
    ``RANGE_FACTORS`` times ``range_mm`` from the camera's centre along each pixel's ray (the
    reflected ray of :func:`slcvjax.geometry.mirror.back_project`, else the lens's ray); pixels
    without a valid ray at a range are left out. ``radii_px``: for a mirror, keep only the pixels
    whose distance from the image of the mirror's apex lies in this range (px): where the
    calibration has data (:func:`observed_radii`). Raises ``ValueError`` where none is left."""
    cam = rig.camera
    w, h = int(cam.width), int(cam.height)
    use_mirror = rig.mirror is not None and not lens
    lo, hi = np.zeros(2), np.array([w - 1.0, h - 1.0])
    if use_mirror:
        rim = np.asarray(rig.mirror.rim_points(jnp.linspace(0.0, 2 * np.pi, 360, endpoint=False)))
        z = rim[:, 2]
        if cam.telecentric:
            xy = rim[:, :2] / cam.unit
        else:
            xy = rim[:, :2] / np.where(z > 1e-9, z, np.nan)[:, None]
        fx, fy, cx, cy = (float(v) for v in (cam.fx, cam.fy, cam.cx, cam.cy))
        uv = np.stack([fx * xy[:, 0] + cx, fy * xy[:, 1] + cy], axis=1)  # the rim's image, undistorted: its box
        uv = uv[np.all(np.isfinite(uv), axis=1)]
        if len(uv):
            pad = 0.05 * (uv.max(axis=0) - uv.min(axis=0))
            lo, hi = np.maximum(uv.min(axis=0) - pad, lo), np.minimum(uv.max(axis=0) + pad, hi)
    us, vs = np.linspace(lo[0], hi[0], n_grid), np.linspace(lo[1], hi[1], n_grid)
    grid = np.stack(np.meshgrid(us, vs), axis=-1).reshape(-1, 2)
    if use_mirror and radii_px is not None:
        r = np.linalg.norm(grid - apex_pixel(rig), axis=1)
        grid = grid[(r >= radii_px[0]) & (r <= radii_px[1])]
    ranges = tuple(float(range_mm) * f for f in RANGE_FACTORS)
    r = jnp.asarray(ranges)
    if use_mirror:
        pts, ok = _mirror_points_jit(cam, rig.mirror, jnp.asarray(grid), r)
    else:
        if cam.telecentric:
            raise ValueError(
                "camera.projection: telecentric: a telecentric lens has no viewpoint; no central model describes it"
            )
        pts, ok = _lens_points_jit(cam, jnp.asarray(grid), r)
    pts, ok = np.asarray(pts), np.asarray(ok) & np.all(np.isfinite(np.asarray(pts)), axis=-1)
    idx_pix, idx_r = np.nonzero(ok)
    if len(idx_pix) < 50:
        raise ValueError(f"the {'mirror' if use_mirror else 'camera'} gives {len(idx_pix)} valid rays: too few to fit")
    return FieldSamples(grid[idx_pix], pts[idx_pix, idx_r], idx_r, ranges, use_mirror)


def apex_pixel(rig: Rig) -> np.ndarray:
    """The pixel (2,) where the camera sees the mirror's apex (the centre of the mirror's image)."""
    cam, apex = rig.camera, np.asarray(rig.mirror.apex, float)
    xy = apex[:2] / cam.unit if cam.telecentric else apex[:2] / apex[2]
    return np.array([float(cam.fx) * xy[0] + float(cam.cx), float(cam.fy) * xy[1] + float(cam.cy)])


def observed_radii(cal: Calibration, margin: float = 0.05) -> tuple[float, float] | None:
    """The range of distances (px) from :func:`apex_pixel` of the pixels the calibration was
    fitted to through the mirror (its stored problem's board points, spots and stripe samples),
    widened by ``margin`` of its width at each end: the annulus where the calibration has data.
    None where the file carries no problem or no such pixel.  Outside it the fitted model (a high
    distortion term, a mirror's rim held at a placeholder) is an extrapolation, and a central
    approximation fitted there would describe that extrapolation."""
    obs = ((cal.extra or {}).get("problem") or {}).get("observations")
    if not isinstance(obs, dict) or cal.rig.mirror is None:
        return None
    pix = []
    for view in obs.get("views") or []:
        for px in (view.get("boards") or {}).values():
            pix.extend(px)
        pix.extend(s.get("pixel") for s in view.get("spots") or [] if isinstance(s, dict))
        for st in view.get("stripes") or []:
            pix.extend(st.get("pixels") or [])
    try:
        uv = np.array([p for p in pix if p is not None], dtype=float).reshape(-1, 2)
    except (TypeError, ValueError):
        return None
    uv = uv[np.all(np.isfinite(uv), axis=1)]
    if len(uv) < 3:
        return None
    r = np.linalg.norm(uv - apex_pixel(cal.rig), axis=1)
    lo, hi = float(r.min()), float(r.max())
    pad = margin * (hi - lo)
    return max(lo - pad, 0.0), hi + pad


def viewpoint(samples: FieldSamples) -> np.ndarray:
    """The point (camera frame, mm) nearest, in least squares, to the lines through each sample's
    points at its several ranges: the central approximation's viewpoint to start from."""
    a, b = np.zeros((3, 3)), np.zeros(3)
    near = samples.range_index == 0
    far = samples.range_index == len(samples.ranges_mm) - 1
    keys_near = {tuple(p): i for i, p in zip(np.flatnonzero(near), samples.pixels[near], strict=True)}
    for j, p in zip(np.flatnonzero(far), samples.pixels[far], strict=True):
        i = keys_near.get(tuple(p))
        if i is None:
            continue
        d = samples.points[j] - samples.points[i]
        d = d / np.linalg.norm(d)
        proj = np.eye(3) - np.outer(d, d)
        a += proj
        b += proj @ samples.points[i]
    if np.linalg.cond(a) > 1e12:
        return np.zeros(3)
    return np.linalg.solve(a, b)


# --------------------------------------------------------------------------- the central models


def mei_project(intr, x_model):
    """Mei's unified model, as ``cv2.omnidir.projectPoints``: one point of the model's frame (3,)
    to its pixel (2,). ``intr = (fx, fy, cx, cy, xi, k1, k2, p1, p2)`` (skew 0). The point on the
    unit sphere ``s = X / |X|`` goes to ``m = (s_x, s_y) / (s_z + xi)``, then radial-tangential
    distortion, then ``K``."""
    fx, fy, cx, cy, xi, k1, k2, p1, p2 = (intr[i] for i in range(9))
    s = x_model / jnp.linalg.norm(x_model)
    den = s[2] + xi
    x, y = s[0] / den, s[1] / den
    r2 = x * x + y * y
    radial = 1.0 + k1 * r2 + k2 * r2 * r2
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return jnp.stack([fx * xd + cx, fy * yd + cy])


def ocam_project(intr, x_model):
    """OCamCalib's ``world2cam`` for one point of the model's frame (3,), returning OpenCV's pixel
    ``(u, v)`` = (column, row). ``intr = (xc, yc, c, d, e, invpol[0], ..., invpol[N])`` with ``xc``
    the centre's row and ``yc`` its column: ``theta = atan(z / |(x, y)|)``,
    ``rho = sum_i invpol[i] theta^i``, ``(x', y') = (x, y) rho / |(x, y)|``, row ``= c x' + d y' + xc``,
    column ``= e x' + y' + yc``."""
    xc, yc, c, d, e = (intr[i] for i in range(5))
    invpol = intr[5:]
    norm = jnp.sqrt(x_model[0] ** 2 + x_model[1] ** 2)
    theta = jnp.arctan2(x_model[2], norm)
    rho = jnp.polyval(invpol[::-1], theta)
    x, y = x_model[0] / norm * rho, x_model[1] / norm * rho
    return jnp.stack([e * x + y + yc, c * x + d * y + xc])


def _model_points(ext, base, points):
    """``X_model = B R(w)^T (X - t)`` for points (n, 3); ``ext = (w, t)``."""
    r = so3_exp(ext[:3])
    return (points - ext[3:6]) @ r @ jnp.asarray(base).T


def _residuals(project, base, n_intr):
    def fun(p, points, pixels):
        xm = _model_points(p[n_intr:], base, points)
        return (jax.vmap(lambda x: project(p[:n_intr], x))(xm) - pixels).reshape(-1)

    return fun


def levenberg_marquardt(fun, p0, free, iters: int = 300, args=()) -> np.ndarray:
    """Minimise ``|fun(p, *args)|^2`` over the entries of ``p`` where ``free`` (bool mask) by
    Levenberg-Marquardt (Marquardt's scaling by the normal matrix's diagonal); ``fun`` is a JAX
    function, differentiated by ``jax.jacfwd``. Returns the parameters (numpy)."""
    f = jax.jit(fun)
    jac = jax.jit(jax.jacfwd(fun))
    p = np.asarray(p0, float).copy()
    free = np.asarray(free, bool)
    r = np.asarray(f(p, *args))
    cost = float(r @ r)
    lam = 1e-3
    for _ in range(iters):
        j = np.asarray(jac(p, *args))[:, free]
        a, g = j.T @ j, j.T @ r
        diag = np.maximum(np.diag(a), 1e-12 * max(np.max(np.diag(a)), 1e-300))
        improved = False
        while lam < 1e12:
            try:
                step = -np.linalg.solve(a + lam * np.diag(diag), g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            q = p.copy()
            q[free] += step
            rq = np.asarray(f(q, *args))
            cq = float(rq @ rq) if np.all(np.isfinite(rq)) else np.inf
            if cq < cost:
                done = cost - cq < 1e-12 * cost or np.max(np.abs(step)) < 1e-12
                p, r, cost, lam, improved = q, rq, cq, max(lam / 10.0, 1e-9), True
                break
            lam *= 10.0
        if not improved or done:
            break
    return p


@dataclass
class CentralFit:
    """A central model fitted to the rig's rays.

    ``model``: ``"mei"`` or ``"ocam"``; ``intrinsics``: :func:`mei_project`'s or
    :func:`ocam_project`'s ``intr``; ``R_cam_model`` (3, 3) and ``t_cam_model`` (3,) mm: the
    model's frame in the camera's (``X_cam = R X_model + t``); ``rms_px`` and ``max_px``: the
    pixel differences between the model's projection of each sample's point and the sample's
    pixel (all ranges), ``per_range_rms_px`` per range; ``ranges_mm``; ``samples``: their number;
    ``mirror``: a fit to the mirror's field (else to the lens); ``pol``: OCamCalib's direct
    polynomial (``a0, a1 = 0, a2, ...``) and ``pol_consistency_px`` the largest pixel difference
    of ``world2cam(cam2world(pixel))`` over the samples."""

    model: str
    intrinsics: np.ndarray
    R_cam_model: np.ndarray
    t_cam_model: np.ndarray
    rms_px: float
    max_px: float
    per_range_rms_px: list[float]
    ranges_mm: tuple[float, ...]
    samples: int
    mirror: bool
    pol: np.ndarray | None = None
    pol_consistency_px: float | None = None
    notes: list[str] = field(default_factory=list)

    def project(self, points_cam) -> np.ndarray:
        """Pixels (n, 2) of points (n, 3) of the camera frame (mm) by the fitted model."""
        base_points = (np.asarray(points_cam, float) - self.t_cam_model) @ self.R_cam_model
        proj = mei_project if self.model == "mei" else ocam_project
        return np.asarray(jax.vmap(lambda x: proj(jnp.asarray(self.intrinsics), x))(jnp.asarray(base_points)))

    def summary(self) -> str:
        what = "the mirror's field" if self.mirror else "the lens's image"
        return (
            f"central approximation ({'Mei unified model' if self.model == 'mei' else 'OCamCalib polynomial'}) "
            f"over {what}: RMS {self.rms_px:.3f} px, worst {self.max_px:.3f} px over {self.samples} rays at "
            + ", ".join(f"{r:g}" for r in self.ranges_mm)
            + " mm"
        )


def _finish(model, base, intr, ext, samples, n_intr) -> CentralFit:
    fun = _residuals(mei_project if model == "mei" else ocam_project, base, n_intr)
    res = np.asarray(fun(jnp.asarray(np.concatenate([intr, ext])), samples.points, samples.pixels)).reshape(-1, 2)
    err = np.linalg.norm(res, axis=1)
    per = [
        float(np.sqrt(np.mean(err[samples.range_index == k] ** 2))) if np.any(samples.range_index == k) else math.nan
        for k in range(len(samples.ranges_mm))
    ]
    r = np.asarray(so3_exp(jnp.asarray(ext[:3])))
    return CentralFit(
        model,
        np.asarray(intr, float),
        r @ base.T,
        np.asarray(ext[3:6], float),
        float(np.sqrt(np.mean(err**2))),
        float(err.max()),
        per,
        samples.ranges_mm,
        len(err),
        samples.mirror,
    )


def _start(samples: FieldSamples, base) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The extrinsics to start from, the image's centre and each sample's model-frame point."""
    ext = np.zeros(6)
    if samples.mirror:
        ext[3:] = viewpoint(samples)
    xm = np.asarray(_model_points(jnp.asarray(ext), base, jnp.asarray(samples.points)))
    return ext, xm, samples.pixels


def fit_mei(camera: Camera, samples: FieldSamples, xi_free: bool = True) -> CentralFit:
    """Mei's unified model fitted to ``samples`` (:func:`field_samples`); for a lens with
    ``xi_free`` False, ``xi = 0``: a pinhole with radial-tangential distortion (Kalibr's
    ``pinhole-radtan``, OpenCV's model without ``k3``)."""
    base = B_MEI_MIRROR if samples.mirror else B_MEI_LENS
    ext, xm, px = _start(samples, base)
    s = xm / np.linalg.norm(xm, axis=1, keepdims=True)
    if samples.mirror:
        xi = 1.0
        centre = px[np.argmax(s[:, 2])]  # the pixel looking most nearly along the model's +z
        rad = np.linalg.norm(px - centre, axis=1)
        m = np.hypot(s[:, 0], s[:, 1]) / (s[:, 2] + xi)
        ok = m > 1e-3
        f0 = float(np.median(rad[ok] / m[ok]))
        intr = np.array([f0, f0, centre[0], centre[1], xi, 0, 0, 0, 0], float)
    else:
        xi = 0.0
        intr = np.array([camera.fx, camera.fy, camera.cx, camera.cy, 0.0, 0, 0, 0, 0], float)
    fun = _residuals(mei_project, base, 9)
    p = np.concatenate([intr, ext])
    args = (jnp.asarray(samples.points), jnp.asarray(samples.pixels))
    free = np.ones(15, bool)
    free[4] = xi_free
    if not samples.mirror:
        free[9:] = False  # a lens: the camera's own frame
    first = free.copy()
    first[5:9] = False  # without distortion first
    p = levenberg_marquardt(fun, p, first, args=args)
    p = levenberg_marquardt(fun, p, free, args=args)
    return _finish("mei", base, p[:9], p[9:], samples, 9)


def _ocam_project_scaled(intr, x_model, theta0, half):
    """:func:`ocam_project` with the inverse polynomial in ``u = (theta - theta0) / half`` (the fit's
    well-conditioned variable; :func:`_theta_polynomial` converts it)."""
    xc, yc, c, d, e = (intr[i] for i in range(5))
    norm = jnp.sqrt(x_model[0] ** 2 + x_model[1] ** 2)
    u = (jnp.arctan2(x_model[2], norm) - theta0) / half
    rho = jnp.polyval(intr[5:][::-1], u)
    x, y = x_model[0] / norm * rho, x_model[1] / norm * rho
    return jnp.stack([e * x + y + yc, c * x + d * y + xc])


def _theta_polynomial(coef_u, theta0: float, half: float) -> np.ndarray:
    """The coefficients in ``theta`` (increasing powers) of the polynomial with coefficients
    ``coef_u`` in ``u = (theta - theta0) / half``."""
    from numpy.polynomial import Polynomial

    return np.asarray((Polynomial(coef_u)(Polynomial([-theta0 / half, 1.0 / half]))).coef, float)


def _cam2world(intr, pol, pixel):
    """OCamCalib's ``cam2world`` of one pixel (OpenCV's ``u, v``): the unnormalised ray of the
    model's frame ``(x', y', f(rho))``."""
    xc, yc, c, d, e = (intr[i] for i in range(5))
    row, col = pixel[1] - xc, pixel[0] - yc
    inv = 1.0 / (c - d * e)
    xp, yp = inv * (row - d * col), inv * (-e * row + c * col)
    return jnp.stack([xp, yp, jnp.polyval(pol[::-1], jnp.sqrt(xp * xp + yp * yp))])


def fit_ocam(camera: Camera, samples: FieldSamples) -> CentralFit:
    """OCamCalib's polynomial model fitted to ``samples``: ``world2cam`` (the inverse polynomial
    of degree ``OCAM_INVPOL_DEGREE`` in the elevation ``theta``, the centre, the affine ``c, d, e``;
    the rotation about the model's axis held, as the affine has it) by Levenberg-Marquardt on the
    pixels, then ``cam2world``'s direct polynomial (``a1 = 0``, OCamCalib's form) by linear least
    squares on ``f(rho) = rho tan(theta)`` along the fitted inverse, refined by Levenberg-Marquardt
    on the pixels of ``world2cam(cam2world(pixel))``."""
    base = B_OCAM_MIRROR if samples.mirror else B_OCAM_LENS
    ext, xm, px = _start(samples, base)
    theta = np.arctan2(xm[:, 2], np.hypot(xm[:, 0], xm[:, 1]))
    theta0, half = 0.5 * (theta.max() + theta.min()), max(0.5 * (theta.max() - theta.min()), 1e-3)
    centre = px[np.argmin(theta)] if samples.mirror else np.array([float(camera.cx), float(camera.cy)])
    rho = np.linalg.norm(px - centre, axis=1)
    n = OCAM_INVPOL_DEGREE + 1
    coef_u = np.linalg.lstsq(np.vander((theta - theta0) / half, n, increasing=True), rho, rcond=None)[0]
    n_intr = 5 + n
    scaled = lambda intr, x: _ocam_project_scaled(intr, x, theta0, half)  # noqa: E731
    fun = _residuals(scaled, base, n_intr)
    p = np.concatenate([[centre[1], centre[0], 1.0, 0.0, 0.0], coef_u, ext])
    free = np.ones(n_intr + 6, bool)
    free[n_intr + 2] = False  # the rotation about the model's axis: the affine's
    if not samples.mirror:
        free[n_intr:] = False
    args = (jnp.asarray(samples.points), jnp.asarray(samples.pixels))
    p = levenberg_marquardt(fun, p, free, args=args)
    intr = np.concatenate([p[:5], _theta_polynomial(p[5:n_intr], theta0, half)])
    if len(intr) < n_intr:
        intr = np.concatenate([intr, np.zeros(n_intr - len(intr))])
    fit = _finish("ocam", base, intr, p[n_intr:], samples, n_intr)
    # cam2world: f(rho) = rho tan(theta) along the inverse polynomial, over the samples' elevations
    grid = np.linspace(theta.min() - 0.05 * half, theta.max() + 0.05 * half, 400)
    r = np.polyval(p[5:n_intr][::-1], (grid - theta0) / half)
    keep = r > 1e-6
    powers = [0] + list(range(2, OCAM_POL_DEGREE + 1))
    scale = max(float(np.max(r[keep])), 1.0)
    a = np.stack([(r[keep] / scale) ** k for k in powers], axis=1)
    coef = np.linalg.lstsq(a, r[keep] * np.tan(grid[keep]), rcond=None)[0] / scale ** np.asarray(powers)
    pol0 = np.zeros(OCAM_POL_DEGREE + 1)
    pol0[powers] = coef
    fit_intr = jnp.asarray(fit.intrinsics)

    def consistency(pol, pixels):
        rays = jax.vmap(lambda q: _cam2world(fit_intr, pol, q))(pixels)
        return (jax.vmap(lambda x: ocam_project(fit_intr, x))(rays) - pixels).reshape(-1)

    free_pol = np.ones(OCAM_POL_DEGREE + 1, bool)
    free_pol[1] = samples.mirror  # a lens: a1 = 0 (OCamCalib's form); a mirror's ring-shaped image needs it
    pol = levenberg_marquardt(consistency, pol0, free_pol, args=(jnp.asarray(samples.pixels),))
    fit.pol = pol
    err = np.asarray(consistency(jnp.asarray(pol), jnp.asarray(samples.pixels))).reshape(-1, 2)
    fit.pol_consistency_px = float(np.max(np.linalg.norm(err, axis=1)))
    return fit


def ocam_project_rays(intr, pol, pixels) -> np.ndarray:
    """OCamCalib's ``cam2world``: the unit rays (n, 3) of the model's frame of pixels (n, 2)
    (OpenCV's ``u, v``), from the centre, the affine ``c, d, e`` of ``intr`` and the direct
    polynomial ``pol`` (``a0, a1, ...``)."""
    v = np.asarray(jax.vmap(lambda q: _cam2world(jnp.asarray(intr), jnp.asarray(pol), q))(jnp.asarray(pixels)))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


# --------------------------------------------------------------------------- the writers


def _num(x: float) -> str:
    return repr(float(x))


def _flow(values) -> str:
    return "[" + ", ".join(_num(v) for v in np.asarray(values, float).reshape(-1)) + "]"


def _require_pinhole(camera: Camera, fmt: str) -> None:
    if camera.telecentric:
        raise FormatError(
            f"camera.projection: telecentric: the {fmt} format describes a pinhole lens only; a telecentric "
            "camera's central approximation through its mirror is --format opencv-omnidir or ocamcalib"
        )


def write_opencv(path, camera: Camera, comments: list[str] | None = None, extra: dict | None = None) -> None:
    """Write a camera as OpenCV FileStorage YAML: ``image_width``, ``image_height``,
    ``camera_matrix`` (3x3) and ``distortion_coefficients`` (1x5, ``k1, k2, p1, p2, k3``), as
    ``cv2.calibrateCamera`` gives them; ``comments`` as YAML comments, ``extra`` as more fields
    (a number or an array each). Written atomically."""
    import cv2

    _require_pinhole(camera, "opencv")
    fields = {
        "image_width": int(camera.width),
        "image_height": int(camera.height),
        "camera_matrix": np.asarray(camera.K, float),
        "distortion_coefficients": np.asarray(camera.dist, float).reshape(1, 5),
    }
    _filestorage(path, fields | (extra or {}), comments or [], cv2)


def _filestorage(path, fields: dict, comments: list[str], cv2) -> None:
    path, tmp = atomic_target(path, ".yaml" if Path(path).suffix not in (".yml", ".yaml") else Path(path).suffix)
    try:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_YAML)
        if not fs.isOpened():
            raise OutputError(f"{path}: cannot write: OpenCV cannot open it for writing")
        for c in comments:
            fs.writeComment(c)
        for k, v in fields.items():
            fs.write(k, v)
        fs.release()
    except BaseException as e:
        abandon_target(tmp)
        if isinstance(e, cv2.error):
            raise OutputError(f"{path}: cannot write: {e.err or e}") from None
        raise
    commit_target(path, tmp)


def ros_text(camera: Camera, name: str = "camera", comments: list[str] | None = None) -> str:
    """ROS ``camera_info`` YAML (as ``camera_calibration_parsers`` reads it): ``plumb_bob`` with the
    five coefficients, identity rectification, ``projection_matrix`` ``[K | 0]``."""
    _require_pinhole(camera, "ros")
    k = np.asarray(camera.K, float)
    p = np.concatenate([k, np.zeros((3, 1))], axis=1)

    def mat(rows, cols, data):
        return f"  rows: {rows}\n  cols: {cols}\n  data: {_flow(data)}\n"

    head = "".join(f"# {c}\n" for c in comments or [])
    return (
        head
        + f"image_width: {int(camera.width)}\nimage_height: {int(camera.height)}\ncamera_name: {name}\n"
        + "camera_matrix:\n"
        + mat(3, 3, k)
        + "distortion_model: plumb_bob\ndistortion_coefficients:\n"
        + mat(1, 5, camera.dist)
        + "rectification_matrix:\n"
        + mat(3, 3, np.eye(3))
        + "projection_matrix:\n"
        + mat(3, 4, p)
    )


def kalibr_text(width: int, height: int, model: str, intrinsics, dist, comments: list[str] | None = None) -> str:
    """A Kalibr camchain YAML with one camera ``cam0``: ``camera_model`` (``pinhole``: intrinsics
    ``[fu, fv, pu, pv]``; ``omni``: ``[xi, fu, fv, pu, pv]``), ``distortion_model: radtan``,
    ``distortion_coeffs: [k1, k2, r1, r2]``, ``resolution: [width, height]``."""
    head = "".join(f"# {c}\n" for c in comments or [])
    return (
        head
        + "cam0:\n"
        + f"  camera_model: {model}\n"
        + f"  intrinsics: {_flow(intrinsics)}\n"
        + "  distortion_model: radtan\n"
        + f"  distortion_coeffs: {_flow(dist)}\n"
        + f"  resolution: [{int(width)}, {int(height)}]\n"
        + "  cam_overlaps: []\n"
        + "  rostopic: /cam0/image_raw\n"
    )


def ocamcalib_text(fit: CentralFit, width: int, height: int, comments: list[str] | None = None) -> str:
    """OCamCalib's ``calib_results.txt``, laid out as its C reader (``get_ocam_model``) reads it:
    per section a comment line, a blank line and the values; the direct polynomial (its length,
    then ``a0 a1 ...``), the inverse polynomial (likewise), the centre (row, column), the affine
    ``c d e``, the image's height and width. ``comments`` follow the last section."""
    pol, intr = np.asarray(fit.pol, float), np.asarray(fit.intrinsics, float)
    invpol = intr[5:]
    lines = [
        "#polynomial coefficients for the DIRECT mapping function (ocam_model.ss in MATLAB). These are used by "
        "cam2world",
        "",
        f"{len(pol)} " + " ".join(f"{v:.12e}" for v in pol),
        "",
        "#polynomial coefficients for the inverse mapping function (ocam_model.invpol in MATLAB). These are used by "
        "world2cam",
        "",
        f"{len(invpol)} " + " ".join(f"{v:.12e}" for v in invpol),
        "",
        '#center: "row" and "column", starting from 0 (C convention)',
        "",
        f"{intr[0]:.12f} {intr[1]:.12f}",
        "",
        '#affine parameters "c", "d", "e"',
        "",
        f"{intr[2]:.12f} {intr[3]:.12f} {intr[4]:.12f}",
        "",
        '#image size: "height" and "width"',
        "",
        f"{int(height)} {int(width)}",
        "",
    ]
    return "\n".join(lines + [f"#{c}" for c in comments or []]) + "\n"


def mrcal_text(camera: Camera, comments: list[str] | None = None) -> str:
    """An mrcal ``.cameramodel`` (a Python literal): ``lensmodel`` ``LENSMODEL_OPENCV5``,
    ``intrinsics`` ``[fx, fy, cx, cy, k1, k2, p1, p2, k3]``, ``extrinsics`` ``rt_cam_ref`` (zero:
    the reference frame is the camera's), ``imagersize`` ``[width, height]``."""
    _require_pinhole(camera, "mrcal")
    intr = [camera.fx, camera.fy, camera.cx, camera.cy, *np.asarray(camera.dist, float)]
    head = "".join(f"# {c}\n" for c in comments or [])
    return (
        head
        + "{\n"
        + "    'lensmodel': 'LENSMODEL_OPENCV5',\n"
        + "    # intrinsics are fx,fy,cx,cy,distortion0,distortion1,....\n"
        + f"    'intrinsics': {_flow(intr)},\n"
        + "    # extrinsics are rt_cam_ref: the reference frame is the camera's\n"
        + "    'extrinsics': [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],\n"
        + f"    'imagersize': [{int(camera.width)}, {int(camera.height)}],\n"
        + "}\n"
    )


# --------------------------------------------------------------------------- export


def working_range(cal: Calibration) -> tuple[float, str]:
    """The range (mm from the camera's centre) the approximation is fitted about, and why: the
    mean working range of the determined lasers, else the mean distance of the boards' origins
    over the views, else 1000 mm."""
    unc = cal.extra.get("uncertainty") or {}
    ranges = [x["working_range_mm"] for x in unc.get("lasers", []) if x.get("working_range_mm") is not None]
    if ranges:
        return float(np.mean(ranges)), f"the mean working range of the {len(ranges)} lasers"
    if not ranges and cal.rig.lasers.n and cal.rig.mirror is not None:
        pts = np.asarray(cal.rig.lasers.points) + 100.0 * np.asarray(cal.rig.lasers.directions)
        if np.all(np.isfinite(pts)):
            return float(np.mean(np.linalg.norm(pts, axis=1))), "100 mm along the lasers (no working range stored)"
    dists = [float(np.linalg.norm(np.asarray(p.t))) for view in cal.board_poses for p in view.values()]
    if dists:
        return float(np.mean(dists)), f"the mean distance of the boards over {len(cal.board_poses)} views"
    return 1000.0, "a default of 1000 mm (no laser and no board pose in the file)"


@dataclass
class ExportReport:
    """What :func:`export` wrote: ``path``, ``format``, ``what`` (one line: the lens or the
    approximation), ``fit`` (a :class:`CentralFit` where a model was fitted, else None) and
    ``range_mm``/``range_why`` (the fit's working range)."""

    path: Path
    format: str
    what: str
    fit: CentralFit | None = None
    range_mm: float | None = None
    range_why: str = ""


def _fit_lines(fit: CentralFit, why: str) -> list[str]:
    lines = [fit.summary(), f"working range: {why}"]
    lines.append(
        "per range RMS px: "
        + ", ".join(f"{r:g} mm {v:.3f}" for r, v in zip(fit.ranges_mm, fit.per_range_rms_px, strict=True))
    )
    if fit.mirror:
        lines.append(
            "model frame in the camera frame (X_cam = R X_model + t), left-handed (a mirror's image): R = "
            + _flow(fit.R_cam_model)
            + " t_mm = "
            + _flow(fit.t_cam_model)
        )
    if fit.pol_consistency_px is not None:
        lines.append(f"cam2world polynomial against world2cam: worst {fit.pol_consistency_px:.3f} px")
    return lines


def export(cal: Calibration, fmt: str, path, range_mm: float | None = None, lens: bool = False) -> ExportReport:
    """Write calibration ``cal``'s camera to ``path`` in format ``fmt`` (one of :data:`FORMATS`;
    see the module's docstring); ``lens``: the camera's lens alone even where the rig has a
    mirror; ``range_mm``: the working range of a fitted approximation (default
    :func:`working_range`). Returns an :class:`ExportReport`; raises :class:`FormatError` where the
    format cannot describe the camera (a telecentric lens in a pinhole format)."""
    if fmt not in FORMATS:
        raise FormatError(f"--format: expected one of {', '.join(FORMATS)}, got {fmt!r}")
    camera = cal.rig.camera
    mirror = cal.rig.mirror is not None and not lens
    lens_note = "the camera behind the mirror, its lens alone: this format has no model of the mirror"
    comments = ["written by slcvjax export"]
    why = ""
    if range_mm is None:
        range_mm, why = working_range(cal)
    elif not (range_mm > 0 and math.isfinite(range_mm)):
        raise FormatError(f"--range: must be a positive number of mm, got {range_mm}")
    else:
        why = "as asked"

    radii = observed_radii(cal) if mirror else None

    def samples():
        try:
            return field_samples(cal.rig, range_mm, lens=not mirror, radii_px=radii)
        except ValueError as e:
            raise FormatError(str(e)) from None

    if radii is not None:
        why += (
            f"; the field: the annulus {radii[0]:.1f}-{radii[1]:.1f} px from the mirror's centre in the image, "
            "where the calibration has data"
        )

    fit = None
    if fmt in ("opencv", "ros", "mrcal") or (fmt == "kalibr" and not mirror and float(camera.dist[4]) == 0.0):
        what = lens_note if cal.rig.mirror is not None else "the camera (exact)"
        if cal.rig.mirror is not None:
            comments.append(lens_note)
        if fmt == "opencv":
            write_opencv(path, camera, comments)
        elif fmt == "ros":
            write_text_atomic(path, ros_text(camera, comments=comments))
        elif fmt == "mrcal":
            write_text_atomic(path, mrcal_text(camera, comments))
        else:
            _require_pinhole(camera, "kalibr")
            k = camera
            write_text_atomic(
                path,
                kalibr_text(k.width, k.height, "pinhole", [k.fx, k.fy, k.cx, k.cy], np.asarray(k.dist)[:4], comments),
            )
        return ExportReport(Path(path), fmt, what)
    if fmt in ("opencv-omnidir", "kalibr"):
        if not mirror:
            _require_pinhole(camera, fmt)
        # a lens in Kalibr: pinhole-radtan (xi = 0); omnidir or a mirror: xi free
        fit = fit_mei(camera, samples(), xi_free=mirror or fmt == "opencv-omnidir")
        lines = _fit_lines(fit, why)
        what = lines[0] if mirror else f"{'the lens alone: ' if cal.rig.mirror is not None else ''}{lines[0]}"
        fx, fy, cx, cy, xi, k1, k2, p1, p2 = (float(v) for v in fit.intrinsics)
        if fmt == "opencv-omnidir":
            import cv2

            extra = {
                "xi": np.array([[xi]]),
                "central_approximation_rms_px": fit.rms_px,
                "central_approximation_max_px": fit.max_px,
                "R_cam_model": np.asarray(fit.R_cam_model, float),
                "t_cam_model_mm": np.asarray(fit.t_cam_model, float).reshape(3, 1),
            }
            fields = {
                "image_width": int(camera.width),
                "image_height": int(camera.height),
                "camera_matrix": np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]),
                "distortion_coefficients": np.array([[k1, k2, p1, p2]]),
            }
            _filestorage(path, fields | extra, comments + lines, cv2)
        else:
            model = "omni" if mirror else "pinhole"
            intr = [xi, fx, fy, cx, cy] if mirror else [fx, fy, cx, cy]
            text = kalibr_text(camera.width, camera.height, model, intr, [k1, k2, p1, p2], comments + lines)
            write_text_atomic(path, text)
        return ExportReport(Path(path), fmt, what, fit, range_mm, why)
    # ocamcalib
    if not mirror:
        _require_pinhole(camera, fmt)
    fit = fit_ocam(camera, samples())
    lines = _fit_lines(fit, why)
    write_text_atomic(path, ocamcalib_text(fit, camera.width, camera.height, comments + lines))
    return ExportReport(Path(path), fmt, lines[0], fit, range_mm, why)


# --------------------------------------------------------------------------- measured points

POINT_COLUMNS = (
    "view",
    "view_name",
    "laser",
    "spot",
    "x_mm",
    "y_mm",
    "z_mm",
    "std_x_mm",
    "std_y_mm",
    "std_z_mm",
    "angle_deg",
    "gap_mm",
    "nearly_parallel",
    "off_line",
)


def _point_rows(doc: dict):
    """One tuple per point of a ``slcv-points/1`` document, in :data:`POINT_COLUMNS`' order; a
    stripe's point gives its ``sample`` as ``spot`` (its ``stripe`` is its laser's)."""
    for k, view in enumerate(doc["views"]):
        for p in view["points"]:
            std = p.get("std") or [math.nan] * 3
            yield (
                k,
                str(view["name"]),
                int(p["laser"]),
                int(p.get("spot", p.get("sample", -1))),
                *(float(v) for v in p["xyz"]),
                *(math.nan if v is None else float(v) for v in std),
                float(p.get("angle_deg", math.nan)),
                float(p.get("gap_mm", math.nan)),
                int(bool(p.get("nearly_parallel", p.get("grazing", False)))),
                int(bool(p.get("off_line", False))),
            )


def points_csv(doc: dict) -> str:
    """A ``slcv-points/1`` document's points as CSV: a header of :data:`POINT_COLUMNS`, one row per
    point (camera frame, mm; the flags 0 or 1; ``nan`` where a std is unknown)."""
    import csv
    import io

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(POINT_COLUMNS)
    for row in _point_rows(doc):
        w.writerow([repr(v) if isinstance(v, float) else v for v in row])
    return buf.getvalue()


def points_ply(doc: dict) -> str:
    """A ``slcv-points/1`` document's points as an ASCII PLY point cloud: per vertex ``x y z``
    (double, mm, camera frame), ``std_x std_y std_z`` (double, mm), ``view``, ``laser``, ``spot``
    (int) and ``nearly_parallel``, ``off_line`` (uchar 0/1)."""
    rows = list(_point_rows(doc))
    head = [
        "ply",
        "format ascii 1.0",
        "comment slcvjax measure: slcv-points/1, mm, camera frame",
        f"element vertex {len(rows)}",
        *(f"property double {n}" for n in ("x", "y", "z", "std_x", "std_y", "std_z")),
        *(f"property int {n}" for n in ("view", "laser", "spot")),
        "property uchar nearly_parallel",
        "property uchar off_line",
        "end_header",
    ]
    body = [
        " ".join([*(repr(v) for v in r[4:10]), str(r[0]), str(r[2]), str(r[3]), str(r[12]), str(r[13])]) for r in rows
    ]
    return "\n".join(head + body) + "\n"
