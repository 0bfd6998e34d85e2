"""Measuring with a calibrated rig: laser spots -> 3D points with uncertainty, circle fits.

A spot's pixel is back-projected through the mirror (closed form) to a reflected
ray; the 3D point is the point of the spot's laser line nearest that ray (the
paper's closest-approach method).  The point is taken on the laser line, not on
the ray: the spot lies on the line by construction, so the across-line component
of the ray would only add pixel noise.  The ray-line distance (``gap``) is kept
as a diagnostic.

Where ray and line are nearly parallel the depth along the line is ill-defined and
its first-order uncertainty is not trustworthy: a point is flagged ``parallel``
when the ray-line angle is below ``PARALLEL_FACTOR`` times its own uncertainty: the
angular standard deviation of the reflected ray caused by the pixel noise (the cone
magnifies it: about 0.3 deg at 0.5 px on the paper's rig) combined with that of the
laser's direction when the calibration's covariance is given.  Below that the angle itself is
uncertain by a sizeable fraction and the error distribution grows heavy tails
(measured on the paper's rig in a pipe at 0.5 px: RMS error / reported std 1.06
over the unflagged points, and 0.004 over all points, where a few near-parallel
points predict metres).

Uncertainty is first-order: the Jacobians of the point with respect to the pixel
and to the rig's tangent parameters (camera 9, mirror 6, lasers 4 N, the order
of the calibration's covariance) propagate the pixel noise and, when given, the
calibration's covariance.  Points of one view share the calibration, so their
joint covariance is kept for the circle fit.

A pipe cross-section is fitted in the plane perpendicular to a given axis (the
camera's z axis by default): an algebraic (Kasa) circle to start, then a
geometric least-squares refinement; the diameter's standard deviation comes
from the points' joint covariance through the implicit-function derivative of
the fit.
"""

from dataclasses import dataclass, field
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ..geometry.mirror import back_project, project_through_mirror
from ..geometry.rig import Rig
from ..observations.problem import bucket, map_padded, map_rows, pad_rows, padded_lasers
from ..support.persist import PersistentJit
from ..support.safe import orthonormal_basis, safe_arccos, safe_div, safe_norm, std_of_variance

PARALLEL_FACTOR = 5.0  # a ray-line angle below this many ray angular stds is "nearly parallel"
GAP_SIGMAS = 5.0  # a ray passing farther than this many stds from its laser's line is "off the line"
GAP_FLOOR_MM = 0.01  # ... and never for less than this (the std is 0 with exact pixels and rig)


class SpotPoints(NamedTuple):
    """Triangulated spots: point on the laser line (mm), ray-line distance (mm), angle (rad), validity."""

    xyz: Float[Array, "n 3"]
    gap: Float[Array, " n"]
    angle: Float[Array, " n"]
    valid: Bool[Array, " n"]


def triangulate_spot(rig: Rig, laser: Int[Array, ""], uv: Float[Array, "2"]) -> SpotPoints:
    """One spot: the point of laser ``laser``'s line nearest the reflected ray of pixel ``uv``.

    ``valid`` is False where the pixel's ray misses the mirror, the ray and the
    line are parallel (within 1e-12), the nearest point lies behind the mirror
    point along the reflected ray, or behind the line's foot of the perpendicular from
    the camera centre (not on the beam: lasers that radiate from a ring have opposite
    neighbours whose lines, continued backwards, run close to each other's beams).
    Values and gradients stay finite everywhere.
    """
    ray = back_project(rig.camera, rig.mirror, uv)
    return _nearest_on_line(ray, rig.lasers.points[laser], rig.lasers.directions[laser])[0]


def _nearest_on_line(ray, p, d) -> tuple[SpotPoints, Float[Array, ""], Float[Array, ""]]:
    """The point of the line ``(p, d)`` nearest the reflected ``ray`` (see :func:`triangulate_spot`),
    its distance along the ray from the mirror point and along the line from ``p`` (mm)."""
    r = ray.direction
    w = p - ray.point
    b = jnp.dot(d, r)
    det = 1.0 - b * b
    s = safe_div(b * jnp.dot(r, w) - jnp.dot(d, w), det, eps=1e-12)  # along the laser line
    t = safe_div(jnp.dot(r, w) - b * jnp.dot(d, w), det, eps=1e-12)  # along the reflected ray
    xyz = p + s * d
    gap = safe_norm(xyz - (ray.point + t * r))
    angle = safe_arccos(jnp.abs(b))
    valid = ray.valid & (det > 1e-12) & (t > 0.0) & (jnp.dot(xyz, d) > 0.0)
    return SpotPoints(xyz, gap, angle, valid), t, s


def _gaps_to_every_laser(rig: Rig, uv: Float[Array, "n 2"]) -> tuple[Array, Array, Array, Array]:
    """(n, L) per spot and laser: the ray-line distance (mm), the distances along the ray and
    along the line (mm), whether the nearest point is valid."""

    def one(px):
        ray = back_project(rig.camera, rig.mirror, px)
        sp, t, s = jax.vmap(lambda p, d: _nearest_on_line(ray, p, d))(rig.lasers.points, rig.lasers.directions)
        return sp.gap, t, jnp.abs(s), sp.valid

    return jax.vmap(one)(uv)


_gaps_to_every_laser_jit = PersistentJit(map_rows(_gaps_to_every_laser), "gaps_to_every_laser")


def _triangulate(rig: Rig, lasers, uv) -> SpotPoints:
    return jax.vmap(triangulate_spot, in_axes=(None, 0, 0))(rig, lasers, uv)


def _bucketed(rig: Rig) -> Rig:
    """``rig`` with its lasers padded to their bucket (:func:`padded_lasers`), for the compiled
    maps below: one compilation serves every laser count of a bucket.  The padded lines come
    after the real ones, so a spot's laser index and the rig's tangent columns keep their place."""
    return rig.with_lasers(padded_lasers(rig.lasers))


_HERMITE = np.polynomial.hermite_e.hermegauss(7)  # nodes and weights for a unit Gaussian
_LEGENDRE = np.polynomial.legendre.leggauss(4)  # on [-1, 1], for the squared radius across a disk
_DISK_ANGLES = 12  # equally spaced: exact for the disk's angular harmonics below the 12th


def _image_centroid_offset(rig: Rig, x, e1, e2, ab, w) -> Float[Array, "2"]:
    """The centroid of the image of a patch on the plane through ``x`` spanned by ``e1, e2``
    (camera frame, mm) minus the image of ``x``: quadrature points ``ab`` (k, 2) in mm along
    ``e1, e2``, weights ``w`` (k,) per unit area of the patch. Radiance is kept by the mirror, so
    each patch covers the pixels its projection's Jacobian says: the weights are multiplied by it."""

    def proj(q):
        return project_through_mirror(rig.camera, rig.mirror, x + q[0] * e1 + q[1] * e2).uv

    uv = jax.vmap(proj)(ab)
    area = jnp.abs(jnp.linalg.det(jax.vmap(jax.jacfwd(proj))(ab)))
    wa = w * area
    return jnp.sum(wa[:, None] * uv, axis=0) / jnp.sum(wa) - proj(jnp.zeros(2))


def spot_image_offset(rig: Rig, x: Float[Array, "3"], normal: Float[Array, "3"], sigma_mm) -> Float[Array, "2"]:
    """Where the centroid of a laser spot's image lies from the image of its centre (px).

    The spot is a round Gaussian of std ``sigma_mm`` on the surface through ``x`` across
    ``normal`` (camera frame, mm).  Through the mirror its image is squeezed and bent, so the
    centroid a detector measures (the image's intensity-weighted mean) is not the projection of
    ``x`` (:func:`_image_centroid_offset`).  Gauss-Hermite quadrature over the spot (7 x 7 points).
    """
    e1, e2 = orthonormal_basis(normal)
    nodes, weights = (jnp.asarray(a) for a in _HERMITE)
    a, b = (g.ravel() for g in jnp.meshgrid(nodes, nodes))
    w2 = jnp.outer(weights, weights).ravel()
    return _image_centroid_offset(rig, x, e1, e2, sigma_mm * jnp.stack([a, b], axis=1), w2)


def disk_image_offset(rig: Rig, x: Float[Array, "3"], e1, e2, radius_mm) -> Float[Array, "2"]:
    """Where the centroid of a printed dot's image lies from the image of its centre (px).

    The dot is a uniform disk of ``radius_mm`` about ``x`` in the plane spanned by the unit
    vectors ``e1, e2`` (camera frame); the detector's darkness-weighted centroid is the mean of
    its image (:func:`_image_centroid_offset`; a symmetric blur does not move it). Quadrature:
    Gauss-Legendre in the squared radius (4 nodes; the area element is uniform in it) times 12
    equally spaced angles.
    """
    s_nodes = 0.5 * (jnp.asarray(_LEGENDRE[0]) + 1.0)  # the squared radius over [0, 1]
    s_weights = 0.5 * jnp.asarray(_LEGENDRE[1])
    th = jnp.asarray(np.arange(_DISK_ANGLES) * (2 * np.pi / _DISK_ANGLES))
    rho = radius_mm * jnp.sqrt(s_nodes)
    ab = jnp.stack([jnp.outer(rho, jnp.cos(th)).ravel(), jnp.outer(rho, jnp.sin(th)).ravel()], axis=1)
    w = jnp.repeat(s_weights, _DISK_ANGLES)
    return _image_centroid_offset(rig, x, e1, e2, ab, w)


def _spot_offsets(rig: Rig, rows):
    """(n, 2) :func:`spot_image_offset` of rows ``[x (3), normal (3), sigma_mm]``."""
    return jax.vmap(lambda r: spot_image_offset(rig, r[:3], r[3:6], r[6]))(rows)


_spot_offsets_jit = PersistentJit(map_rows(_spot_offsets), "spot_image_offsets")


def _points_of(rig: Rig, rows):
    """Triangulated points and validity of rows ``[laser, u, v]``."""
    sp = _triangulate(rig, rows[:, 0].astype(jnp.int32), rows[:, 1:3])
    return sp.xyz, sp.valid


_points_of_jit = PersistentJit(map_rows(_points_of), "triangulate_rows")


def corrected_spot_pixels(
    rig: Rig, lasers: np.ndarray, pixels: np.ndarray, sigma_mm: float, axis=(0.0, 0.0, 1.0), rounds: int = 2
) -> np.ndarray:
    """Spot centroids corrected for the mirror's distortion of each spot's image
    (:func:`spot_image_offset`) on a surface of revolution about ``axis`` through the camera
    centre (each spot's surface across its radial direction, as a pipe's wall): triangulate,
    subtract the predicted offset from the detected centroid, again from the corrected one
    (``rounds`` times).  Spots that cannot be triangulated keep their pixel."""
    px0 = np.asarray(pixels, float).reshape(-1, 2)
    if not len(px0):
        return px0.copy()
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    px = px0.copy()
    for _ in range(rounds):
        rows = np.concatenate([np.asarray(lasers, float).reshape(-1, 1), px], axis=1)
        xyz, ok = map_padded(_points_of_jit, _bucketed(rig), rows=rows)
        radial = xyz - (xyz @ a)[:, None] * a
        norm = np.linalg.norm(radial, axis=1, keepdims=True)
        ok = ok & (norm[:, 0] > 1e-9)
        off = spot_image_offsets(rig, xyz, radial / np.where(norm > 1e-9, norm, 1.0), sigma_mm)
        px = np.where(ok[:, None] & np.all(np.isfinite(off), axis=1, keepdims=True), px0 - off, px0)
    return px


def spot_image_offsets(rig: Rig, xyz: np.ndarray, normals: np.ndarray, sigma_mm: float) -> np.ndarray:
    """(n, 2) :func:`spot_image_offset` for many spots, one compilation for every count."""
    xyz = np.asarray(xyz, float).reshape(-1, 3)
    if not len(xyz):
        return np.zeros((0, 2))
    rows = np.concatenate([xyz, np.asarray(normals, float).reshape(-1, 3), np.full((len(xyz), 1), sigma_mm)], 1)
    return np.asarray(map_padded(_spot_offsets_jit, _bucketed(rig), rows=rows))


def _ray_rate(rig: Rig, px: Float[Array, "2"]) -> Float[Array, ""]:
    """The reflected ray's largest angular change per pixel at ``px`` (rad/px)."""
    j_dir = jax.jacfwd(lambda px: back_project(rig.camera, rig.mirror, px).direction)(px)
    return jnp.sqrt(jnp.linalg.eigvalsh(j_dir.T @ j_dir)[-1])


_ray_rate_jit = PersistentJit(map_rows(lambda rig, uv: jax.vmap(lambda px: _ray_rate(rig, px))(uv)), "ray_rate")


def _with_jacobians(rig: Rig, lasers, uv):
    """Points, their Jacobians wrt the pixel (n, 3, 2) and the rig's tangent (n, 3, G), and the
    reflected ray's largest angular change per pixel (n,) (rad/px)."""
    g = rig.tangent_dim

    def one(laser, px):
        def f(delta, px):
            return triangulate_spot(rig.retract(delta), laser, px).xyz

        z = jnp.zeros(g)
        j_rig, j_px = jax.jacfwd(f, argnums=(0, 1))(z, px)
        return j_rig, j_px, _ray_rate(rig, px)

    j_rig, j_px, ray_rate = jax.vmap(one)(lasers, uv)
    return _triangulate(rig, lasers, uv), j_px, j_rig, ray_rate


def _jacobian_rows(rig: Rig, rows):
    """:func:`_with_jacobians` of rows ``[laser, u, v]``."""
    return _with_jacobians(rig, rows[:, 0].astype(jnp.int32), rows[:, 1:3])


triangulate_spots = jax.jit(_triangulate)
_with_jacobians_jit = PersistentJit(map_rows(_jacobian_rows), "spot_jacobians")


@dataclass
class ViewPoints:
    """The measured points of one view.

    Attributes:
        lasers: (n,) laser index of each point.
        spot_index: (n,) index of each point's spot among the view's spots (in input order).
        xyz: (n, 3) points in the camera frame (mm).
        cov: (3n, 3n) joint covariance of the points (mm^2).
        gap: (n,) distance between the reflected ray and the laser line (mm).
        angle: (n,) angle between the reflected ray and the laser line (rad).
        ray_std: (n,) angular std of the reflected ray from the pixel noise (rad).
        parallel: (n,) the ray and the line are nearly parallel given the pixel noise and
            the laser's direction uncertainty (see the module's notes).
        off_line: (n,) the ray passes farther from the laser's line than ``GAP_SIGMAS`` times
            the gap's first-order std: the spot is not this laser's (a wrong label, a stray
            reflection); its point is not to be used.
        fits_laser: (n,) for a point off its line, the one other laser whose line its ray
            meets within the same bound, else -1.
        missing: spots that gave no point: ``(spot_index, laser, reason)``.
    """

    lasers: np.ndarray
    spot_index: np.ndarray
    xyz: np.ndarray
    cov: np.ndarray
    gap: np.ndarray
    angle: np.ndarray
    ray_std: np.ndarray
    parallel: np.ndarray
    off_line: np.ndarray
    fits_laser: np.ndarray
    missing: list[tuple[int, int, str]] = field(default_factory=list)

    @property
    def std(self) -> np.ndarray:
        """(n, 3) standard deviation of each coordinate (mm); NaN where the covariance is not positive."""
        return std_of_variance(np.diag(self.cov)).reshape(-1, 3)


def _laser_stds(rig: Rig, rig_cov: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Each laser's offset (mm) and direction (rad) std from the calibration's covariance (its
    (e1, e2) blocks); zeros without one."""
    off_std, dir_std = np.zeros(rig.lasers.n), np.zeros(rig.lasers.n)
    if rig_cov is not None:
        elements = rig.point_elements  # a point laser's columns are its element's
        for k in range(rig.lasers.n):
            c = np.diag(rig_cov)[rig.layout.elements[elements[k]]]
            off_std[k], dir_std[k] = std_of_variance(c[0] + c[1]), std_of_variance(c[2] + c[3])
    return off_std, dir_std


def spots_on_lines(
    rig: Rig, pixels: np.ndarray, pixel_sigma: float, rig_cov: np.ndarray | None = None, ray_rate=None
) -> np.ndarray:
    """(n, L): which laser lines each spot's reflected ray passes within ``GAP_SIGMAS`` times
    the distance's first-order std (the pixel noise along the ray, the line's offset and
    direction from ``rig_cov``), or within ``GAP_FLOOR_MM``, ahead of the mirror and on the
    beam.  ``ray_rate`` (n,): each ray's angular change per pixel, computed when not given."""
    pixels = np.asarray(pixels, dtype=float).reshape(-1, 2)
    n_las = rig.lasers.n
    if not len(pixels):
        return np.zeros((0, n_las), bool)
    padded = _bucketed(rig)
    if ray_rate is None:
        ray_rate = np.asarray(map_padded(_ray_rate_jit, padded, rows=pixels))
    off_std, dir_std = _laser_stds(rig, rig_cov)
    out = map_padded(_gaps_to_every_laser_jit, padded, rows=pixels)
    gaps, along, reach, near_ok = (a[:, :n_las] for a in out)
    gap_std = np.hypot(along * pixel_sigma * ray_rate[:, None], np.hypot(off_std, dir_std * reach))
    return near_ok & (gaps <= np.maximum(GAP_SIGMAS * gap_std, GAP_FLOOR_MM))


def label_by_lines(
    rig: Rig,
    pixels: np.ndarray,
    pixel_sigma: float,
    rig_cov: np.ndarray | None = None,
    undetermined: tuple[int, ...] = (),
) -> np.ndarray:
    """(n,): the laser of each unlabelled spot, the one line its ray passes near
    (:func:`spots_on_lines`); -1 where it passes near none, or near more than one.  No spot
    is given an ``undetermined`` laser (its line is a placeholder)."""
    on_line = spots_on_lines(rig, pixels, pixel_sigma, rig_cov)
    on_line[:, list(undetermined)] = False
    return np.where(on_line.sum(axis=1) == 1, np.argmax(on_line, axis=1), -1)


def measure_spots(
    rig: Rig,
    lasers: np.ndarray,
    pixels: np.ndarray,
    view_of: np.ndarray,
    n_views: int,
    pixel_sigma: float,
    rig_cov: np.ndarray | None = None,
    undetermined: tuple[int, ...] = (),
) -> list[ViewPoints]:
    """Triangulate every spot of several views in one compiled call.

    Args:
        rig: the calibrated rig.
        lasers: (N,) laser index of each spot (all views together).
        pixels: (N, 2) spot pixels.
        view_of: (N,) view index of each spot.
        n_views: number of views.
        pixel_sigma: per-coordinate pixel noise (px) of a spot.
        rig_cov: optional (G, G) covariance of the rig's tangent parameters (camera 9,
            mirror 6, lasers 4 N), as written by the calibration.
        undetermined: lasers the calibration could not fix
            (``Calibration.undetermined_lasers``): their spots give no point (each is listed in
            ``missing``) and no spot is said to fit their placeholder lines.

    Returns one :class:`ViewPoints` per view.
    """
    if not np.isfinite(pixel_sigma) or pixel_sigma < 0:
        raise ValueError(f"pixel sigma must be a non-negative number of pixels, got {pixel_sigma}")
    if rig_cov is not None and rig_cov.shape != (rig.tangent_dim, rig.tangent_dim):
        raise ValueError(f"rig covariance has shape {rig_cov.shape}, expected {(rig.tangent_dim,) * 2}")
    lasers = np.asarray(lasers, dtype=np.int64)
    pixels = np.asarray(pixels, dtype=float).reshape(-1, 2)
    view_of = np.asarray(view_of, dtype=np.int64)
    if lasers.shape != (len(pixels),) or view_of.shape != (len(pixels),):
        raise ValueError(
            f"{len(pixels)} pixels need as many laser and view indices, got {lasers.shape} and {view_of.shape}"
        )
    bad = np.flatnonzero((lasers < 0) | (lasers >= rig.lasers.n))
    if bad.size:
        raise ValueError(f"spot {bad[0]}'s laser index {lasers[bad[0]]} is not one of the rig's {rig.lasers.n} lasers")
    if lasers.size:
        rows = np.concatenate([lasers[:, None].astype(float), pixels], axis=1)
        sp, j_px, j_rig, ray_rate = map_padded(_with_jacobians_jit, _bucketed(rig), rows=rows)
        xyz, gap, angle, valid = sp
        j_rig = j_rig[:, :, : rig.tangent_dim]  # the padded lasers' columns come last
    else:
        xyz, gap, angle, valid = np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0, bool)
        j_px, j_rig, ray_rate = np.zeros((0, 3, 2)), np.zeros((0, 3, rig.tangent_dim)), np.zeros(0)
    _, dir_std = _laser_stds(rig, rig_cov)
    # every spot's ray against every laser's line: is it off its own, and on which other?
    on_line = spots_on_lines(rig, pixels, pixel_sigma, rig_cov, ray_rate)
    own = on_line[np.arange(lasers.size), lasers] if lasers.size else np.zeros(0, bool)
    others = on_line.copy()
    others[np.arange(lasers.size), lasers] = False
    held = np.isin(np.arange(rig.lasers.n), np.asarray(undetermined, int))
    others[:, held] = False
    fits = np.where(~own & (others.sum(axis=1) == 1), np.argmax(others, axis=1), -1)
    usable = np.asarray(valid, bool) & ~held[lasers]
    out = []
    for v in range(n_views):
        idx = np.flatnonzero(view_of == v)  # spots of view v, in their order
        ok = usable[idx]
        good = idx[ok]
        missing = [
            (
                int(k),
                int(lasers[i]),
                f"laser {lasers[i]} is undetermined in the calibration (the data did not fix its line)"
                if held[lasers[i]]
                else "its reflected ray misses the mirror or is parallel to the laser line",
            )
            for k, i in zip(np.flatnonzero(~ok), idx[~ok], strict=True)
        ]
        n = good.size
        jp = j_px[good]
        cov = np.zeros((3 * n, 3 * n))
        for k in range(n):
            cov[3 * k : 3 * k + 3, 3 * k : 3 * k + 3] = pixel_sigma**2 * jp[k] @ jp[k].T
        if rig_cov is not None and n:
            jr = j_rig[good].reshape(3 * n, -1)
            cov += jr @ rig_cov @ jr.T
        out.append(
            ViewPoints(
                lasers=lasers[good],
                spot_index=np.flatnonzero(ok),
                xyz=xyz[good],
                cov=cov,
                gap=gap[good],
                angle=angle[good],
                ray_std=pixel_sigma * ray_rate[good],
                parallel=angle[good] < PARALLEL_FACTOR * np.hypot(pixel_sigma * ray_rate[good], dir_std[lasers[good]]),
                off_line=~own[good],
                fits_laser=fits[good],
                missing=missing,
            )
        )
    return out


# ----------------------------------------------------------------------------- circle fit


def plane_basis(axis) -> np.ndarray:
    """(2, 3) orthonormal basis of the plane perpendicular to ``axis``.

    The first vector is the camera's x axis projected onto the plane (its y axis
    when ``axis`` is nearly x), the second completes a right-handed frame with
    ``axis``; for the default axis (0, 0, 1) the basis is (x, y).
    """
    a = np.asarray(axis, dtype=float)
    n = np.linalg.norm(a)
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError(f"axis must be a non-zero finite vector, got {list(np.asarray(axis).tolist())}")
    a = a / n
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = helper - (helper @ a) * a
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(a, e1)])


@dataclass
class Circle:
    """A fitted circle in a plane (coordinates of :func:`plane_basis`), sizes in mm."""

    center: np.ndarray
    diameter: float
    diameter_std: float | None
    residuals: np.ndarray
    rms: float
    center_std: np.ndarray | None = None
    nearly_parallel_used: int = 0


def _circle_cost(theta, q, w):
    rho = safe_norm(q - theta[:2], axis=-1)
    return 0.5 * jnp.sum(w * (rho - theta[2]) ** 2)


@jax.jit
def circle_sensitivity(theta, q, w):
    """d theta / d q (3, n, 2) at a minimum, by the implicit-function theorem."""
    h = jax.hessian(_circle_cost, argnums=0)(theta, q, w)
    b = jax.jacfwd(jax.grad(_circle_cost, argnums=0), argnums=1)(theta, q, w)
    return -jnp.linalg.solve(h, b.reshape(3, -1)).reshape(b.shape)


def fit_circle_theta(q: np.ndarray, blocks: np.ndarray | None, iters: int) -> tuple[np.ndarray, np.ndarray]:
    """The circle ``(cx, cy, R)`` through 2D points ``q`` (n, 2) and the weights it used (n,):
    an algebraic (Kasa) start weighted by each point's overall variance, then Gauss-Newton on the
    radial residuals weighted by the inverse of each point's radial variance (``blocks`` (n, 2, 2):
    each point's own covariance; None: unweighted).  Raises ``ValueError`` for fewer than 3
    points, collinear points, or a fit that does not converge."""
    n = q.shape[0]
    if n < 3:
        raise ValueError(f"a circle needs at least 3 points, got {n}")
    a = np.column_stack([2.0 * q, np.ones(n)])
    if np.linalg.matrix_rank(a) < 3:
        raise ValueError("the points are collinear: no circle")
    w0 = np.ones(n)
    if blocks is not None:
        tr = np.trace(blocks, axis1=1, axis2=2)
        if np.all(tr > 0) and np.all(np.isfinite(tr)):
            w0 = np.min(tr) / tr  # the start weighs points by their overall variance
    sw0 = np.sqrt(w0)
    sol, *_ = np.linalg.lstsq(a * sw0[:, None], sw0 * np.sum(q**2, axis=1), rcond=None)
    theta = np.array([sol[0], sol[1], np.sqrt(max(sol[2] + sol[:2] @ sol[:2], 0.0))])
    w = np.ones(n)
    if blocks is not None:
        u = q - theta[:2]
        u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-300)
        var = np.einsum("ni,nij,nj->n", u, blocks, u)
        if np.all(var > 0):
            w = np.min(var) / var
    sw = np.sqrt(w)
    for _ in range(iters):  # Gauss-Newton on sqrt(w_i) (|q_i - c| - R)
        d = q - theta[:2]
        rho = np.linalg.norm(d, axis=1)
        if np.any(rho < 1e-12):
            break
        jac = np.column_stack([-d / rho[:, None], -np.ones(n)]) * sw[:, None]
        step, *_ = np.linalg.lstsq(jac, -sw * (rho - theta[2]), rcond=None)
        theta = theta + step
        if np.max(np.abs(step)) < 1e-13 * max(1.0, abs(theta[2])):
            break
    if not np.all(np.isfinite(theta)) or not np.all(np.isfinite(np.linalg.norm(q - theta[:2], axis=1))):
        raise ValueError("the circle fit did not converge (non-finite centre or radius)")
    return theta, w


def circle_sensitivities(theta: np.ndarray, q: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(3, n, 2): the derivative of the fitted ``(cx, cy, R)`` with respect to each point of
    ``q`` (n, 2) fitted with weights ``w`` (n,) (:func:`circle_sensitivity`, padded to a bucket
    with points of weight 0: one compilation per bucket)."""
    n = q.shape[0]
    size = bucket(n)
    qp, wp = pad_rows(q, size), pad_rows(w, size, 0.0)
    sens = np.asarray(circle_sensitivity(jax.device_put(theta), jax.device_put(qp), jax.device_put(wp)))
    return sens[:, :n]


def fit_circle(q: np.ndarray, cov_q: np.ndarray | None = None, weighted: bool = True, iters: int = 50) -> Circle:
    """Fit a circle to 2D points ``q`` (n, 2): algebraic (Kasa) start, geometric refinement.

    ``cov_q`` (2n, 2n), when given, is the points' joint covariance: the diameter's
    and centre's standard deviations are propagated from it, and with ``weighted``
    each point's radial residual is weighted by the inverse of its radial variance
    (from its own 2x2 block, along the direction from the algebraic centre).
    Raises ``ValueError`` for fewer than 3 points or collinear points.

    Gauss-Newton in NumPy rather than a compiled solver: 16 poses' fits took 4.5 ms in all,
    optimistix's jitted LM 0.95 ms after a 0.72 s compilation that each new process pays
    (``benchmarks/bench_solvers.py``, ``benchmarks/results/solvers.json``).
    """
    q = np.asarray(q, dtype=float).reshape(-1, 2)
    n = q.shape[0]
    blocks = None
    if cov_q is not None and weighted and n >= 3:
        blocks = np.stack([np.asarray(cov_q)[2 * i : 2 * i + 2, 2 * i : 2 * i + 2] for i in range(n)])
    theta, w = fit_circle_theta(q, blocks, iters)
    res = np.linalg.norm(q - theta[:2], axis=1) - theta[2]
    d_std = c_std = None
    if cov_q is not None:
        sens = circle_sensitivities(theta, q, w).reshape(3, 2 * n)
        ct = sens @ np.asarray(cov_q) @ sens.T
        if not np.all(np.isfinite(ct)):
            raise ValueError("the circle's covariance is not finite (a point's uncertainty is unbounded)")
        d_std = float(2.0 * np.sqrt(max(ct[2, 2], 0.0)))
        c_std = np.sqrt(np.maximum(np.diag(ct)[:2], 0.0))
    return Circle(theta[:2], float(2.0 * theta[2]), d_std, res, float(np.sqrt(np.mean(res**2))), c_std)


def fit_circle_3d(
    xyz: np.ndarray, cov: np.ndarray | None = None, axis=(0.0, 0.0, 1.0), weighted: bool = True
) -> Circle:
    """Fit a circle to 3D points projected on the plane perpendicular to ``axis``.

    ``cov`` (3n, 3n) is the points' joint covariance (see :func:`fit_circle`); the
    returned centre is in the coordinates of :func:`plane_basis` (x, y for the
    default axis).
    """
    basis = plane_basis(axis)
    xyz = np.asarray(xyz, dtype=float).reshape(-1, 3)
    q = xyz @ basis.T
    cov_q = None
    if cov is not None:
        p = np.kron(np.eye(xyz.shape[0]), basis)
        cov_q = p @ cov @ p.T
    return fit_circle(q, cov_q, weighted=weighted)
