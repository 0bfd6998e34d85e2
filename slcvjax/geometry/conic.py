"""Conic mirrors of revolution: sphere, paraboloid, hyperboloid, ellipsoid.

Geometry: vertex ``A`` and unit axis ``a`` in the camera frame, the axis pointing from the
vertex away from the camera (the mirror's convex side faces the camera, as in
catadioptric cameras), vertex curvature ``c = 1/R`` and conic constant ``kappa``; with
``q = X - A``, ``s = q.a`` (the sag) and ``rho = |q - s a|`` the surface is

    c (rho^2 + (1 + kappa) s^2) = 2 s,   0 <= s,   rho <= r,

that is ``s = c rho^2 / (1 + sqrt(1 - (1 + kappa) c^2 rho^2))``: ``kappa = 0`` a sphere,
``-1`` a paraboloid, ``< -1`` a hyperboloid, ``> -1`` (not 0) an ellipsoid.  The rim is the
circle ``rho = r`` at the sag ``h = s(r)``.  The camera-facing unit normal is
``(2 s' q_perp - a) / |.|`` with ``s' = ds/d(rho^2) = c / (2 sqrt(1 - (1 + kappa) c^2 rho^2))``.

Projection (3D point -> pixel): the mirror point is written ``M(x, y) = A + x e1 + y e2 +
s(x^2 + y^2) a`` (smooth through the vertex, unlike polar coordinates) and Newton solves the
law of reflection, the bisector ``(M - O)/|M - O| + (M - P)/|M - P|`` orthogonal to both
tangents, with an implicit derivative (``slcvjax.geometry.newton``).  The start is the least optical path
``|M - O| + |M - P|`` over a few points of the target's axial half-plane (for a mirror
convex towards both points the reflection point is that path's minimum).  A telecentric
camera's rays are parallel to +z: the direction to the camera is then ``-z`` and the optical
path from its image plane ``M_z + |M - P|``.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ..support.safe import orthonormal_basis, safe_div, safe_norm, safe_normalize, safe_sqrt
from .camera import view_direction
from .newton import newton_implicit, newton_residual_norm
from .revolution import RayHit, retract_pose, rim_circle

KINDS = ("sphere", "paraboloid", "hyperboloid", "ellipsoid")
START_SAMPLES = 24  # points of the axial half-plane the projection's start is chosen from


def conic_kind(conic: float) -> str:
    """The kind a conic constant makes: ``sphere`` (0), ``paraboloid`` (-1), ``hyperboloid``
    (below -1) or ``ellipsoid``."""
    if conic == 0.0:
        return "sphere"
    if conic == -1.0:
        return "paraboloid"
    return "hyperboloid" if conic < -1.0 else "ellipsoid"


class ConicMirror(eqx.Module):
    """A conic mirror of revolution (see the module docstring), convex side to the camera.

    Attributes:
        apex: (3,) the vertex in the camera frame, mm.
        axis: (3,) unit axis from the vertex away from the camera.
        curvature: vertex curvature ``c = 1/R`` (1/mm, > 0).
        conic: the conic constant ``kappa``.
        radius: the rim's radius ``r`` (mm).

    Like the cone, its pose has 5 degrees of freedom (:meth:`retract`); the conic constant is a
    sixth, estimated only where asked (``estimate={"shape"}`` of :func:`slcvjax.calibration.params.make_masks`).
    """

    apex: Float[Array, "3"]
    axis: Float[Array, "3"]
    curvature: Float[Array, ""]
    conic: Float[Array, ""]
    radius: Float[Array, ""]

    @staticmethod
    def create(apex, axis, curvature, conic, radius) -> "ConicMirror":
        axis = jnp.asarray(axis, dtype=float)
        return ConicMirror(
            jnp.asarray(apex, dtype=float),
            axis / jnp.linalg.norm(axis),
            jnp.asarray(curvature, dtype=float),
            jnp.asarray(conic, dtype=float),
            jnp.asarray(radius, dtype=float),
        )

    @staticmethod
    def of_kind(kind: str, apex, axis, vertex_radius: float, radius: float, conic: float | None = None):
        """A mirror by name: ``sphere`` / ``paraboloid`` fix the conic constant (0 / -1);
        ``hyperboloid`` (< -1) and ``ellipsoid`` (> -1, not 0) need ``conic``."""
        fixed = {"sphere": 0.0, "paraboloid": -1.0}
        if kind not in KINDS:
            raise ValueError(f"unknown mirror kind {kind!r} (known: cone, {', '.join(KINDS)})")
        if kind in fixed:
            if conic is not None and conic != fixed[kind]:
                raise ValueError(f"a {kind} has conic constant {fixed[kind]:g}, got {conic}")
            conic = fixed[kind]
        elif conic is None:
            raise ValueError(f"a {kind} needs its conic constant")
        elif kind == "hyperboloid" and not conic < -1.0:
            raise ValueError(f"a hyperboloid's conic constant is below -1, got {conic}")
        elif kind == "ellipsoid" and not (conic > -1.0 and conic != 0.0):
            raise ValueError(f"an ellipsoid's conic constant is above -1 and not 0, got {conic}")
        if not vertex_radius > 0 or not radius > 0:
            raise ValueError(f"the vertex radius and the rim radius must be positive, got {vertex_radius}, {radius}")
        c = 1.0 / vertex_radius
        if (1.0 + conic) * (c * radius) ** 2 >= 1.0:
            raise ValueError(f"a rim of radius {radius} mm lies past the {kind}'s widest circle")
        return ConicMirror.create(apex, axis, c, conic, radius)

    @property
    def kind(self) -> str:
        """``sphere``, ``paraboloid``, ``hyperboloid`` or ``ellipsoid`` (host values only)."""
        return conic_kind(float(self.conic))

    def sag(self, rho2: Float[Array, "..."]) -> Float[Array, "..."]:
        """The axial coordinate ``s`` of the surface at squared radius ``rho2``."""
        c, k1 = self.curvature, 1.0 + self.conic
        return c * rho2 / (1.0 + safe_sqrt(1.0 - k1 * c * c * rho2))

    def sag_slope(self, rho2: Float[Array, "..."]) -> Float[Array, "..."]:
        """``ds / d(rho^2)``."""
        c, k1 = self.curvature, 1.0 + self.conic
        return 0.5 * c / safe_sqrt(jnp.maximum(1.0 - k1 * c * c * rho2, 1e-300))

    @property
    def height(self) -> Float[Array, ""]:
        """The rim's sag ``h = s(r^2)`` (mm): the rim circle's distance from the vertex along the axis."""
        return self.sag(self.radius**2)

    def retract(self, delta: Float[Array, " d"]) -> "ConicMirror":
        """``apex += delta[:3]``; the axis tilts by ``delta[3:5]`` (radians) in its tangent plane;
        a sixth component adds to the conic constant (the vertex radius stays: it is the scale's
        gauge where the shape is estimated)."""
        apex, axis = retract_pose(self.apex, self.axis, delta[:5])
        conic = self.conic + delta[5] if delta.shape[0] > 5 else self.conic
        return ConicMirror(apex, axis, self.curvature, conic, self.radius)

    def rim_points(self, angles: Float[Array, " n"]) -> Float[Array, "n 3"]:
        """Points of the rim circle at the given azimuths, camera frame."""
        return rim_circle(self.apex, self.axis, self.height, self.radius, angles)

    # ------------------------------------------------------------------ geometry

    def surface_normal(self, x: Float[Array, "3"]) -> Float[Array, "3"]:
        """Camera-facing unit normal at a surface point (``-axis`` at the vertex)."""
        q = x - self.apex
        perp = q - jnp.dot(q, self.axis) * self.axis
        return safe_normalize(2.0 * self.sag_slope(jnp.dot(perp, perp)) * perp - self.axis)

    def intersect(self, origin: Float[Array, "3"], direction: Float[Array, "3"], rim_margin: float = 0.0):
        """First intersection of the ray ``origin + t d`` (t > 0) with the mirror (a :class:`~.revolution.RayHit`).

        The quadric ``c (|q|^2 + kappa s^2) - 2 s = 0`` along the ray is a quadratic in ``t``,
        solved without cancellation; a root counts on the vertex's sheet (``0 <= s``,
        ``(1 + kappa) c s < 1``) within the rim (``rho <= r (1 + rim_margin)``)."""
        a, c, kap = self.axis, self.curvature, self.conic
        w = origin - self.apex
        da, wa = jnp.dot(direction, a), jnp.dot(w, a)
        qa = c * (jnp.dot(direction, direction) + kap * da * da)
        qb = 2.0 * (c * (jnp.dot(w, direction) + kap * wa * da) - da)
        qc = c * (jnp.dot(w, w) + kap * wa * wa) - 2.0 * wa
        disc = qb * qb - 4.0 * qa * qc
        sq = safe_sqrt(disc)
        qq = -0.5 * (qb + jnp.where(qb >= 0.0, sq, -sq))
        t1, t2 = safe_div(qq, qa), safe_div(qc, qq)
        # a ray along the axis of a paraboloid meets it once: the quadratic is then linear
        lin = jnp.abs(qa) <= 1e-12 * jnp.abs(qb)
        t_lin = safe_div(-qc, qb)
        t1, t2 = jnp.where(lin, t_lin, t1), jnp.where(lin, t_lin, t2)
        r_max = self.radius * (1.0 + rim_margin)

        def ok(t):
            q = w + t * direction
            s = jnp.dot(q, a)
            rho2 = jnp.dot(q, q) - s * s
            return (
                ((disc >= 0.0) | lin)
                & (t > 1e-12)
                & (s >= -1e-12)
                & ((1.0 + kap) * c * s < 1.0)
                & (rho2 <= r_max * r_max)
            )

        ok1, ok2 = ok(t1), ok(t2)
        t = jnp.where(ok1 & ok2, jnp.minimum(t1, t2), jnp.where(ok1, t1, t2))
        valid = ok1 | ok2
        t = jnp.where(valid, t, 0.0)
        return RayHit(t, origin + t * direction, valid)

    def _point(self, xy, e1, e2):
        rho2 = xy[0] * xy[0] + xy[1] * xy[1]
        return self.apex + xy[0] * e1 + xy[1] * e2 + self.sag(rho2) * self.axis, rho2

    def solve_mirror_point(
        self,
        p_cam: Float[Array, "3"],
        iters: int = 12,
        implicit: bool = True,
        rim_margin: float = 0.0,
        apex_margin: float = 0.0,
        telecentric: bool = False,
    ) -> tuple[Float[Array, "3"], Bool[Array, ""]]:
        """The mirror point whose reflection sends the camera's ray through ``p_cam`` (see
        ``slcvjax.geometry.mirror.solve_mirror_point``; ``apex_margin`` is unused: the vertex is smooth)."""
        del apex_margin
        e1, e2 = orthonormal_basis(self.axis)
        x0 = _start(self, p_cam, e1, e2, telecentric)
        params = (self, p_cam)
        residual = _reflection_residual_telecentric if telecentric else _reflection_residual
        x = newton_implicit(residual, x0, params, iters, implicit=implicit)
        m, rho2 = self._point(x, e1, e2)
        n = self.surface_normal(m)
        c, k1 = self.curvature, 1.0 + self.conic
        r_max = self.radius * (1.0 + rim_margin)
        rho2_sg = jax.lax.stop_gradient(rho2)
        valid = (
            (newton_residual_norm(residual, x, params) < 1e-9)
            & (rho2_sg <= r_max * r_max * (1.0 + 1e-12))
            & (k1 * c * c * rho2_sg < 1.0)
            & (jnp.dot(n, -view_direction(m, telecentric)) > 0.0)
            & (jnp.dot(n, p_cam - m) > 0.0)
        )
        return m, valid


def _reflection_residual(x, params, telecentric: bool = False):
    """The bisector of the directions to the camera and to the target, along the two tangents at ``M(x, y)``."""
    mirror, target = params
    e1, e2 = orthonormal_basis(mirror.axis)
    m, rho2 = mirror._point(x, e1, e2)
    slope2 = 2.0 * mirror.sag_slope(rho2)
    bis = view_direction(m, telecentric) + safe_normalize(m - target)
    t_x = e1 + slope2 * x[0] * mirror.axis
    t_y = e2 + slope2 * x[1] * mirror.axis
    return jnp.stack([jnp.dot(bis, t_x), jnp.dot(bis, t_y)])


def _reflection_residual_telecentric(x, params):
    """:func:`_reflection_residual` for a telecentric camera."""
    return _reflection_residual(x, params, telecentric=True)


def _start(mirror: ConicMirror, target, e1, e2, telecentric: bool = False):
    """The least optical path over points of the target's axial half-plane (inside the rim)."""
    q = target - mirror.apex
    radial = q - jnp.dot(q, mirror.axis) * mirror.axis
    u = safe_normalize(radial)
    u = jnp.where(safe_norm(radial) > 1e-9, u, e1)
    rho = mirror.radius * jnp.linspace(0.0, 1.0, START_SAMPLES)
    # where the conic closes before the rim (an ellipsoid), stay on its vertex's half
    c, k1 = mirror.curvature, 1.0 + mirror.conic
    rho_max = jnp.where(k1 > 0, 0.999 / (c * safe_sqrt(jnp.maximum(k1, 1e-300))), jnp.inf)
    rho = jnp.minimum(rho, rho_max)
    pts = mirror.apex + rho[:, None] * u + mirror.sag(rho * rho)[:, None] * mirror.axis
    to_camera = pts[:, 2] if telecentric else jnp.linalg.norm(pts, axis=1)
    path = to_camera + jnp.linalg.norm(pts - target, axis=1)
    best = rho[jnp.argmin(path)]
    return jax.lax.stop_gradient(best * jnp.stack([jnp.dot(u, e1), jnp.dot(u, e2)]))


ASPHERE_NEWTON = 8  # Newton steps of a ray's intersection from the conic's


class AsphereMirror(ConicMirror):
    """A general smooth mirror of revolution: a conic plus even polynomial terms (an optician's
    even asphere), for mirrors that are no conic (an equiangular one, say):

        s(rho^2) = c rho^2 / (1 + sqrt(1 - (1 + kappa) c^2 rho^2)) + sum_j a_j rho^(2 j),  j = 2, 3, ...

    ``coefficients`` holds ``a_2, a_3, ...`` (1/mm^3, 1/mm^5, ...).  The projection is the
    conic's (Newton on the law of reflection over ``M(x, y)``, the start the least optical
    path); a ray's intersection is Newton's along the ray from the conic's closed form.
    """

    coefficients: Float[Array, " k"]

    @staticmethod
    def create(apex, axis, curvature, conic, radius, coefficients=()) -> "AsphereMirror":
        base = ConicMirror.create(apex, axis, curvature, conic, radius)
        coefficients = jnp.asarray(coefficients, dtype=float).reshape(-1)
        m = AsphereMirror(base.apex, base.axis, base.curvature, base.conic, base.radius, coefficients)
        c, k1 = float(base.curvature), 1.0 + float(base.conic)
        if k1 * (c * float(base.radius)) ** 2 >= 1.0:
            raise ValueError(f"a rim of radius {float(base.radius)} mm lies past the asphere's conic's widest circle")
        rho2 = np.linspace(0.0, float(base.radius) ** 2, 257)
        if not np.all(np.asarray(m.sag_slope(jnp.asarray(rho2))) > 0.0):
            raise ValueError("an asphere's sag must grow with the radius up to the rim (its coefficients turn it back)")
        return m

    @property
    def kind(self) -> str:
        return "asphere"

    def sag(self, rho2):
        poly = jnp.zeros_like(rho2)
        for a in self.coefficients[::-1]:  # Horner in rho^2, from the highest power
            poly = (poly + a) * rho2
        return ConicMirror.sag(self, rho2) + poly * rho2

    def sag_slope(self, rho2):
        n = self.coefficients.shape[0]
        slope = jnp.zeros_like(rho2)
        for j in range(n + 1, 1, -1):  # d/d(rho^2) of a_j rho^(2j) = j a_j rho^(2(j-1))
            slope = slope * rho2 + j * self.coefficients[j - 2]
        return ConicMirror.sag_slope(self, rho2) + slope * rho2

    def retract(self, delta):
        m = ConicMirror.retract(self, delta)
        return AsphereMirror(m.apex, m.axis, m.curvature, m.conic, m.radius, self.coefficients)

    def intersect(self, origin, direction, rim_margin: float = 0.0):
        """The conic's intersection, then Newton along the ray on ``s - sag(rho^2) = 0``."""
        hit = ConicMirror.intersect(self, origin, direction, rim_margin=1.0)
        a = self.axis

        def gap(t):
            q = origin + t * direction - self.apex
            s = jnp.dot(q, a)
            return s - self.sag(jnp.dot(q, q) - s * s)

        t = hit.t
        for _ in range(ASPHERE_NEWTON):
            t = t - safe_div(gap(t), jax.grad(gap)(t))
        q = origin + t * direction - self.apex
        s = jnp.dot(q, a)
        rho2 = jnp.dot(q, q) - s * s
        r_max = self.radius * (1.0 + rim_margin)
        valid = (
            hit.valid
            & (jnp.abs(gap(t)) < 1e-9)
            & (t > 1e-12)
            & (rho2 <= r_max * r_max)
            & ((1.0 + self.conic) * self.curvature**2 * rho2 < 1.0)
        )
        t = jnp.where(valid, t, 0.0)
        return RayHit(t, origin + t * direction, valid)
