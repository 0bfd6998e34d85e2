"""The cone mirror: ray intersection, back-projection and projection through it.

Geometry (DESIGN section 2): apex ``A`` and unit axis ``a`` in the camera
frame, the axis pointing from the apex into the cone towards the base circle,
base radius ``r`` and height ``h``; with ``k = r/h`` and ``q = X - A`` the
surface is ``|q - (q.a)a|^2 = k^2 (q.a)^2`` with ``0 <= q.a <= h``.  The
outward normal is the normalised gradient ``q - (1 + k^2)(q.a) a`` (see
:func:`surface_normal` for the form in which it is evaluated).

Projection (3D point -> pixel) is not closed form because the camera centre is
not on the axis.  A mirror point is written ``M(s, theta) = A + s a + k s u(theta)``
with ``u(theta) = cos(theta) e1 + sin(theta) e2``; the law of reflection says
that ``(M - O)/|M - O| + (M - P)/|M - P|`` is parallel to the normal, i.e.
orthogonal to both tangents ``t_s`` and ``t_theta`` (Fermat: the optical path
``|M - O| + |M - P|`` is stationary).  Newton solves these two equations from
the on-axis closed form (reflection of the camera across the generatrix in the
axial plane of the target); the derivative is implicit (see ``slcvjax.geometry.newton``).
"""

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ..support.safe import orthonormal_basis, safe_div, safe_norm, safe_normalize, safe_sqrt
from .camera import Camera, in_image, pixel_to_line, project, view_direction
from .conic import KINDS as CONIC_KINDS
from .conic import AsphereMirror, ConicMirror
from .newton import newton_implicit, newton_residual_norm
from .revolution import RayHit, retract_pose, rim_circle


class ConeMirror(eqx.Module):
    """A cone mirror seen from its apex side.

    Attributes:
        apex: (3,) apex in the camera frame, mm.
        axis: (3,) unit axis from the apex towards the base circle.
        radius: base radius r in mm (0-d array; from the datasheet, not estimated).
        height: cone height h in mm (0-d array; from the datasheet, not estimated).

    The pose has 5 degrees of freedom (the cone is symmetric about its axis);
    :meth:`retract` takes a 5-vector.
    """

    apex: Float[Array, "3"]
    axis: Float[Array, "3"]
    radius: Float[Array, ""]
    height: Float[Array, ""]

    @staticmethod
    def create(apex, axis, radius, height) -> "ConeMirror":
        axis = jnp.asarray(axis, dtype=float)
        return ConeMirror(
            jnp.asarray(apex, dtype=float),
            axis / jnp.linalg.norm(axis),
            jnp.asarray(radius, dtype=float),
            jnp.asarray(height, dtype=float),
        )

    @property
    def k(self) -> Float[Array, ""]:
        """The slope ``r / h`` (tangent of the half-angle)."""
        return self.radius / self.height

    def retract(self, delta: Float[Array, " d"]) -> "ConeMirror":
        """``apex += delta[:3]``; the axis tilts by ``delta[3:5]`` (radians) in its tangent plane.
        The cone's shape is given: a sixth component (the rig's shape column) is not used, and
        :func:`slcvjax.calibration.params.make_masks` never frees it for a cone."""
        apex, axis = retract_pose(self.apex, self.axis, delta[:5])
        return ConeMirror(apex, axis, self.radius, self.height)

    def rim_points(self, angles: Float[Array, " n"]) -> Float[Array, "n 3"]:
        """Points of the base circle (the rim) at the given azimuths, camera frame."""
        return rim_circle(self.apex, self.axis, self.height, self.radius, angles)


MIRROR_KINDS = ("cone",) + CONIC_KINDS + ("asphere",)
# every mirror of revolution the forward model takes (an asphere is a conic with terms added)
Mirror = ConeMirror | ConicMirror


def shape_json(mirror) -> dict:
    """A mirror's shape as ``mirror_shape`` writes it: ``{"kind": "cone", "radius", "height"}``, or
    ``{"kind", "vertex_radius", "radius"}`` with ``"conic_constant"`` for a hyperboloid or an
    ellipsoid, and ``"coefficients"`` too for an asphere (:class:`slcvjax.geometry.conic.AsphereMirror`)."""
    if isinstance(mirror, ConeMirror):
        return {"kind": "cone", "radius": float(mirror.radius), "height": float(mirror.height)}
    kind = mirror.kind
    out = {"kind": kind, "vertex_radius": 1.0 / float(mirror.curvature), "radius": float(mirror.radius)}
    if kind in ("hyperboloid", "ellipsoid", "asphere"):
        out["conic_constant"] = float(mirror.conic)
    if kind == "asphere":
        out["coefficients"] = np.asarray(mirror.coefficients, float).tolist()
    return out


def mirror_of_shape(shape: dict | None, apex, axis, radius: float | None = None, height: float | None = None):
    """The mirror of a shape (:func:`shape_json`'s form; None: a cone of ``radius`` and ``height``)
    with its vertex at ``apex`` and its axis ``axis``.  Raises ``ValueError`` for a bad shape."""
    if shape is None:
        return ConeMirror.create(apex, axis, radius, height)
    if shape["kind"] == "cone":
        return ConeMirror.create(apex, axis, shape["radius"], shape["height"])
    if shape["kind"] == "asphere":
        if not shape["vertex_radius"] > 0 or not shape["radius"] > 0:
            raise ValueError("the vertex radius and the rim radius must be positive")
        return AsphereMirror.create(
            apex, axis, 1.0 / shape["vertex_radius"], shape["conic_constant"], shape["radius"], shape["coefficients"]
        )
    return ConicMirror.of_kind(
        shape["kind"], apex, axis, shape["vertex_radius"], shape["radius"], shape.get("conic_constant")
    )


def surface_normal(mirror: Mirror, x: Float[Array, "3"]) -> Float[Array, "3"]:
    """Outward unit normal of the cone at a surface point.

    On the surface the quadric's gradient ``q - (1 + k^2)(q.a) a`` has the direction
    ``u - k a`` where ``u`` is the unit radial vector of ``q``; that form is used because
    it does not amplify a point's tiny distance off the surface near the apex.  At the
    apex itself (no radial direction) it returns ``-a``.  Another mirror of revolution
    (``slcvjax.geometry.conic.ConicMirror``) gives its own.
    """
    if not isinstance(mirror, ConeMirror):
        return mirror.surface_normal(x)
    q = x - mirror.apex
    u = safe_normalize(q - jnp.dot(q, mirror.axis) * mirror.axis)
    return safe_normalize(u - mirror.k * mirror.axis)


def reflect(d: Float[Array, "3"], n: Float[Array, "3"]) -> Float[Array, "3"]:
    """Mirror reflection of direction ``d`` about the unit normal ``n``."""
    return d - 2.0 * jnp.dot(d, n) * n


def intersect(mirror: Mirror, origin: Float[Array, "3"], direction: Float[Array, "3"]) -> RayHit:
    """First intersection of the ray ``origin + t d`` (t > 0) with the finite cone.

    The quadric ``|w + t d|^2 - (1 + k^2)((w + t d).a)^2 = 0`` (``w = origin - apex``)
    is solved with the cancellation-free quadratic formula; a root counts where
    ``t > 0`` and ``0 <= s <= h`` (``s`` the axial coordinate).  A miss, a
    tangent ray or a ray parallel to a generatrix gives ``valid = False``.  Another mirror
    of revolution (``slcvjax.geometry.conic.ConicMirror``) intersects itself.
    """
    if not isinstance(mirror, ConeMirror):
        return mirror.intersect(origin, direction)
    a = mirror.axis
    c = 1.0 + mirror.k**2
    w = origin - mirror.apex
    da, wa = jnp.dot(direction, a), jnp.dot(w, a)
    qa = jnp.dot(direction, direction) - c * da * da
    qb = 2.0 * (jnp.dot(w, direction) - c * wa * da)
    qc = jnp.dot(w, w) - c * wa * wa
    disc = qb * qb - 4.0 * qa * qc
    sq = safe_sqrt(disc)
    q = -0.5 * (qb + jnp.where(qb >= 0.0, sq, -sq))
    t1, t2 = safe_div(q, qa), safe_div(qc, q)

    def ok(t):
        s = wa + t * da
        return (disc > 0.0) & (t > 1e-12) & (s >= 0.0) & (s <= mirror.height)

    ok1, ok2 = ok(t1), ok(t2)
    first = jnp.where(ok1 & ok2, jnp.minimum(t1, t2), jnp.where(ok1, t1, t2))
    valid = ok1 | ok2
    t = jnp.where(valid, first, 0.0)
    # one Newton step on the signed distance |q_perp| - k s polishes the root where the
    # quadratic's coefficients cancel (rays near the apex)
    qv = w + t * direction
    s = jnp.dot(qv, a)
    perp = qv - s * a
    rho = safe_norm(perp)
    dist = rho - mirror.k * s
    slope = safe_div(jnp.dot(perp, direction - da * a), rho) - mirror.k * da
    t = t - jnp.where(valid & (jnp.abs(slope) > 1e-6), safe_div(dist, slope), 0.0)
    return RayHit(t, origin + t * direction, valid)


class MirrorRay(NamedTuple):
    """A back-projected pixel: the mirror point, the reflected unit direction, validity."""

    point: Float[Array, "3"]
    direction: Float[Array, "3"]
    valid: Bool[Array, ""]


def back_project(cam: Camera, mirror: Mirror, uv: Float[Array, "2"]) -> MirrorRay:
    """Pixel -> reflected ray (closed form): undistort, intersect the cone, reflect.

    Camera frame, mm.  ``valid`` is False where the pixel's ray misses the
    mirror, meets it from inside, or the undistortion did not converge.
    """
    origin, d, ok_cam = pixel_to_line(cam, uv)
    hit = intersect(mirror, origin, d)
    n = surface_normal(mirror, hit.point)
    out = reflect(d, n)
    valid = ok_cam & hit.valid & (jnp.dot(d, n) < 0.0)
    return MirrorRay(hit.point, out, valid)


def _mirror_point(s, theta, apex, axis, k):
    e1, e2 = orthonormal_basis(axis)
    u = jnp.cos(theta) * e1 + jnp.sin(theta) * e2
    return apex + s * axis + k * s * u, u, e1, e2


def _reflection_residual(x, params, telecentric: bool = False):
    """The two tangential components of ``(M-O)/|M-O| + (M-P)/|M-P|`` at ``M(s, theta)``
    (``+z`` for the first where the camera is telecentric)."""
    apex, axis, k, target = params
    s, theta = x[0], x[1]
    m, u, e1, e2 = _mirror_point(s, theta, apex, axis, k)
    bis = view_direction(m, telecentric) + safe_normalize(m - target)
    t_s = (axis + k * u) / jnp.sqrt(1.0 + k * k)
    t_th = -jnp.sin(theta) * e1 + jnp.cos(theta) * e2
    return jnp.stack([jnp.dot(bis, t_s), jnp.dot(bis, t_th)])


def _reflection_residual_telecentric(x, params):
    """:func:`_reflection_residual` for a telecentric camera."""
    return _reflection_residual(x, params, telecentric=True)


def _initial_guess(mirror: ConeMirror, target, telecentric: bool = False):
    """On-axis closed form: reflect the camera across the generatrix in the target's axial plane
    (a telecentric camera: its viewing direction, which a generatrix reflects into one direction)."""
    if telecentric:
        return _initial_guess_telecentric(mirror, target)
    a, k = mirror.axis, mirror.k
    e1, e2 = orthonormal_basis(a)
    z_cam = jnp.dot(-mirror.apex, a)  # the camera centre's axial coordinate (< 0)
    q = target - mirror.apex
    z_p = jnp.dot(q, a)
    radial = q - z_p * a
    rho_p = jnp.sqrt(jnp.sum(radial**2) + 1e-30)
    theta = jnp.arctan2(jnp.dot(radial, e2), jnp.dot(radial, e1))
    g = jnp.stack([k, jnp.ones_like(k)]) / jnp.sqrt(1.0 + k * k)  # generatrix in (rho, z)
    cam2 = jnp.stack([jnp.zeros_like(z_cam), z_cam])
    img = 2.0 * jnp.dot(cam2, g) * g - cam2
    delta = jnp.stack([rho_p, z_p]) - img
    lam = safe_div(-(img[0] - k * img[1]), delta[0] - k * delta[1])
    s0 = img[1] + lam * delta[1]
    s0 = jnp.clip(s0, 0.02 * mirror.height, 1.5 * mirror.height)
    return jnp.stack([s0, theta])


def _initial_guess_telecentric(mirror: ConeMirror, target):
    a, k = mirror.axis, mirror.k
    e1, e2 = orthonormal_basis(a)
    q = target - mirror.apex
    z_p = jnp.dot(q, a)
    radial = q - z_p * a
    rho_p = jnp.sqrt(jnp.sum(radial**2) + 1e-30)
    u = radial / rho_p
    theta = jnp.arctan2(jnp.dot(radial, e2), jnp.dot(radial, e1))
    view = jnp.array([0.0, 0.0, 1.0])
    v = jnp.stack([jnp.dot(view, u), jnp.dot(view, a)])  # the viewing direction in (rho, z)
    g = jnp.stack([k, jnp.ones_like(k)]) / jnp.sqrt(1.0 + k * k)
    out = 2.0 * jnp.dot(v, g) * g - v  # every point of the generatrix reflects it so
    # M = s (k, 1) with P - M along ``out``
    s0 = safe_div(rho_p * out[1] - z_p * out[0], k * out[1] - out[0])
    s0 = jnp.clip(s0, 0.02 * mirror.height, 1.5 * mirror.height)
    return jax.lax.stop_gradient(jnp.stack([s0, theta]))


class MirrorProjection(NamedTuple):
    """A point projected through the mirror: pixel, mirror point, and validity flags."""

    uv: Float[Array, "2"]
    mirror_point: Float[Array, "3"]
    valid: Bool[Array, ""]


def solve_mirror_point(
    mirror: Mirror,
    p_cam: Float[Array, "3"],
    iters: int = 6,
    implicit: bool = True,
    rim_margin: float = 0.0,
    apex_margin: float = 0.0,
    telecentric: bool = False,
) -> tuple[Float[Array, "3"], Bool[Array, ""]]:
    """The mirror point whose reflection sends the camera's ray through ``p_cam``.

    Returns ``(M, valid)`` where ``valid`` says Newton converged to a point of
    the finite cone (``0 < s <= h (1 + rim_margin)``) that faces both the camera
    and the target.  ``rim_margin > 0`` extends the surface past the rim, which a
    calibration uses so that a point observed at the rim's edge keeps a residual
    while the estimate is still off.  ``apex_margin > 0`` likewise extends each
    generatrix's tangent plane past the apex (``s > -h apex_margin``): the solution
    in ``(s, theta)`` and its pixel continue smoothly through the apex, so a point
    seen right at the apex is not lost when the estimate moves it a hair across.
    Implicit derivative (``implicit=True``) or unrolled (baseline).  ``telecentric``: the
    camera's rays are parallel to +z (:class:`slcvjax.geometry.camera.Camera`).  Another mirror of
    revolution (``slcvjax.geometry.conic.ConicMirror``) solves its own reflection.
    """
    if not isinstance(mirror, ConeMirror):
        return mirror.solve_mirror_point(
            p_cam,
            iters=max(iters, 12),
            implicit=implicit,
            rim_margin=rim_margin,
            apex_margin=apex_margin,
            telecentric=telecentric,
        )
    params = (mirror.apex, mirror.axis, mirror.k, p_cam)
    x0 = _initial_guess(mirror, p_cam, telecentric)
    residual = _reflection_residual_telecentric if telecentric else _reflection_residual
    x = newton_implicit(residual, x0, params, iters, implicit=implicit)
    m, u, _, _ = _mirror_point(x[0], x[1], mirror.apex, mirror.axis, mirror.k)
    n = safe_normalize(u - mirror.k * mirror.axis)  # the generatrix's normal (surface_normal for s > 0)
    s = jax.lax.stop_gradient(x[0])
    s_min = jnp.where(apex_margin > 0, -apex_margin * mirror.height, 1e-9)
    valid = (
        (newton_residual_norm(residual, x, params) < 1e-9)
        & (s > s_min)
        & (s <= mirror.height * (1.0 + 1e-12 + rim_margin))
        & (jnp.dot(n, -view_direction(m, telecentric)) > 0.0)
        & (jnp.dot(n, p_cam - m) > 0.0)
    )
    return m, valid


BODY_CLEAR_FAR = 1e3  # the body clearance of a ray that never reaches the body's plane (mm)


def body_clearance(origin, direction, mirror: ConeMirror, radius, gap) -> Float[Array, ""]:
    """How far (mm) a ray from ``origin`` along ``direction`` passes outside the sensor's body: a
    disc of ``radius`` across the mirror's axis, ``gap`` before the apex (its radial distance
    from the axis where it crosses the disc's plane, less ``radius``; negative: the body hides
    it). ``BODY_CLEAR_FAR`` where it never reaches that plane ahead."""
    a = mirror.axis
    plane = mirror.apex - gap * a
    denom = jnp.dot(direction, a)
    lam = jnp.dot(plane - origin, a) / jnp.where(jnp.abs(denom) > 1e-12, denom, 1e-12)
    x = origin + lam * direction - plane
    rho = safe_norm(x - jnp.dot(x, a) * a)
    return jnp.where((jnp.abs(denom) > 1e-12) & (lam > 0), rho - radius, BODY_CLEAR_FAR)


def project_through_mirror(
    cam: Camera,
    mirror: Mirror,
    p_cam: Float[Array, "3"],
    iters: int = 6,
    implicit: bool = True,
    rim_margin: float = 0.0,
    apex_margin: float = 0.0,
) -> MirrorProjection:
    """Pixel at which a 3D point (camera frame, mm) is seen through the mirror.

    ``valid`` is False where no reflection path exists on the finite cone (see
    :func:`solve_mirror_point` for ``rim_margin``), the point is behind the
    mirror's tangent plane, or the pixel is off the sensor;
    ``uv`` is then finite but meaningless, and gradients stay finite.
    """
    m, ok = solve_mirror_point(
        mirror,
        p_cam,
        iters=iters,
        implicit=implicit,
        rim_margin=rim_margin,
        apex_margin=apex_margin,
        telecentric=cam.telecentric,
    )
    uv, ok_cam = project(cam, m)
    valid = ok & ok_cam & in_image(cam, jax.lax.stop_gradient(uv))
    return MirrorProjection(jnp.where(valid, uv, 0.0), m, valid)
