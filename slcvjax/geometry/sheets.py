"""Sheets of light: line lasers (planes) and ring lasers (cones), camera frame, mm.

A line laser fans its light in one plane; a ring laser spreads it on a cone (a diode aimed at a
small conical reflector, or a diffractive element).  Both are one surface,

    ``G(x) = (x - p) . a - |x - p| cos(theta) = 0``,

with ``p`` the apex, ``a`` the unit axis and ``theta`` the half-angle (DESIGN section 2): the
points seen from the apex at the angle ``theta`` from the axis.  ``theta = 90 deg`` is the plane
through ``p`` with normal ``a``, which is how a line laser is stored (``p`` a point of the plane
near the emitter); ``theta < 90 deg`` opens towards ``+a`` and ``theta > 90 deg`` towards ``-a``.

Unknowns (the element's columns in the rig's tangent, :class:`slcvjax.geometry.rig.TangentLayout`):

========= ==== =====================================================================
kind      DOF  tangent (in order)
========= ==== =====================================================================
plane     3    the plane moved along its normal (mm), the normal tilted along e1, e2 (rad)
cone      6    the apex moved along e1, e2, a (mm), the axis tilted along e1, e2 (rad),
               the half-angle (rad)
========= ==== =====================================================================

with ``(e1, e2, a)`` the right-handed frame of :func:`slcvjax.support.safe.orthonormal_basis`.

Every function returns a validity flag where the geometry can fail, never a NaN.
"""

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ..support.safe import orthonormal_basis, safe_div, safe_norm, safe_normalize, safe_sqrt
from .pose import Pose

PLANE_DOF = 3
CONE_DOF = 6
KIND_DOF = {"plane": PLANE_DOF, "cone": CONE_DOF}


class Sheets(eqx.Module):
    """Any number of sheets of light, planes and cones in any order.

    Attributes:
        apex: (N, 3) mm, camera frame: a cone's apex, or a point of a plane (near its emitter).
        axis: (N, 3) unit: a cone's axis (the light opens towards ``+axis`` for a half-angle
            under 90 deg), or a plane's normal.
        half_angle: (N,) rad in (0, pi): a cone's half-angle; pi / 2 for a plane.
        kinds: (N,) static, ``"plane"`` or ``"cone"`` per element.

    :meth:`retract` takes the flat increment of every element's own columns, in order (3 per
    plane, 6 per cone; the module docstring gives their meaning).
    """

    KINDS: ClassVar[tuple[str, ...]] = ("plane", "cone")

    apex: Float[Array, "n 3"]
    axis: Float[Array, "n 3"]
    half_angle: Float[Array, " n"]
    kinds: tuple[str, ...] = eqx.field(static=True, default=())

    def __check_init__(self):
        if len(self.kinds) != self.apex.shape[0]:
            raise ValueError(f"Sheets: {self.apex.shape[0]} sheets but {len(self.kinds)} kinds")
        bad = [k for k in self.kinds if k not in KIND_DOF]
        if bad:
            raise ValueError(f"Sheets: unknown kind {bad[0]!r} (known: plane, cone)")

    @staticmethod
    def create(kinds, apex, axis, half_angle=None) -> "Sheets":
        """Sheets from host values: ``kinds`` (N,) names, ``apex`` (N, 3) mm, ``axis`` (N, 3)
        (normalised here), ``half_angle`` (N,) rad (a plane's is set to pi / 2; None: every
        sheet a plane)."""
        kinds = tuple(str(k) for k in kinds)
        p = np.asarray(apex, dtype=float).reshape(-1, 3)
        a = np.asarray(axis, dtype=float).reshape(-1, 3)
        a = a / np.linalg.norm(a, axis=-1, keepdims=True)
        th = np.full(len(kinds), np.pi / 2) if half_angle is None else np.asarray(half_angle, float).reshape(-1)
        th = np.where(np.asarray([k == "plane" for k in kinds], bool), np.pi / 2, th) if kinds else th
        return Sheets(jnp.asarray(p), jnp.asarray(a), jnp.asarray(th), kinds)

    @staticmethod
    def empty() -> "Sheets":
        return Sheets(jnp.zeros((0, 3)), jnp.zeros((0, 3)), jnp.zeros(0), ())

    @property
    def n(self) -> int:
        return len(self.kinds)

    @property
    def dofs(self) -> tuple[int, ...]:
        """Each sheet's number of unknowns."""
        return tuple(KIND_DOF[k] for k in self.kinds)

    @property
    def is_cone(self) -> np.ndarray:
        """(N,) bool, host: which sheets are cones."""
        return np.asarray([k == "cone" for k in self.kinds], dtype=bool)

    def retract(self, delta: Float[Array, " d"]) -> "Sheets":
        """The sheets moved by ``delta``: each element's own columns in order (see the module)."""
        if not self.n:
            return self
        starts = np.cumsum((0,) + self.dofs)[:-1]
        # each sheet's columns as a (N, 6) block, a plane's 3 in front and zeros after
        idx = np.asarray([[s + min(j, d - 1) for j in range(CONE_DOF)] for s, d in zip(starts, self.dofs, strict=True)])
        used = np.asarray([[j < d for j in range(CONE_DOF)] for d in self.dofs])
        d6 = jnp.where(used, delta[idx], 0.0)
        apex, axis, th = jax.vmap(retract_sheet)(self.apex, self.axis, self.half_angle, d6, jnp.asarray(self.is_cone))
        return Sheets(apex, axis, th, self.kinds)

    def at_working_point(self, i: int, x_ref, delta=None):
        """Sheet ``i`` (moved by its own tangent increment ``delta``) at the working point
        ``x_ref`` (3,): the point of the sheet nearest ``x_ref`` along its normal there (first
        order), and the sheet's unit normal there.  For a cone also its apex, axis and
        half-angle: ``(point, normal, apex, axis, half_angle)``."""
        p, a, th = self.apex[i], self.axis[i], self.half_angle[i]
        if delta is not None:
            p, a, th = retract_sheet(p, a, th, _six(delta, self.kinds[i]), self.kinds[i] == "cone")
        x_ref = jnp.asarray(x_ref, dtype=float)
        g, n = sheet_value(x_ref, p, a, th), sheet_gradient(x_ref, p, a, th)
        n2 = jnp.dot(n, n)
        foot = x_ref - safe_div(g, n2) * n
        return foot, safe_normalize(n), p, a, th


def _six(delta, kind: str):
    """A sheet's own tangent increment as its 6-column block (a plane's 3 first)."""
    d = jnp.asarray(delta, dtype=float)
    return d if kind == "cone" else jnp.concatenate([d, jnp.zeros(CONE_DOF - PLANE_DOF)])


def retract_sheet(p, a, th, d, cone):
    """One sheet moved by its 6-column block ``d`` (a plane's 3 first; ``cone`` traced or not)."""
    e1, e2 = orthonormal_basis(a)
    plane_p = p + d[0] * a
    plane_a = safe_normalize(a + d[1] * e1 + d[2] * e2)
    cone_p = p + d[0] * e1 + d[1] * e2 + d[2] * a
    cone_a = safe_normalize(a + d[3] * e1 + d[4] * e2)
    return (
        jnp.where(cone, cone_p, plane_p),
        jnp.where(cone, cone_a, plane_a),
        jnp.where(cone, th + d[5], th),
    )


def sheet_value(x: Float[Array, "3"], apex, axis, half_angle) -> Float[Array, ""]:
    """``G(x) = (x - p).a - |x - p| cos(theta)`` (mm): zero on the sheet, of the sign of the side."""
    q = x - apex
    return jnp.dot(q, axis) - safe_norm(q) * jnp.cos(half_angle)


def sheet_gradient(x: Float[Array, "3"], apex, axis, half_angle) -> Float[Array, "3"]:
    """``dG/dx``: ``a - cos(theta) q / |q|`` (its norm is ``sin(theta)`` on a cone)."""
    q = x - apex
    return axis - jnp.cos(half_angle) * safe_normalize(q)


def ray_meets_sheet(
    origin: Float[Array, "3"], direction: Float[Array, "3"], apex, axis, half_angle, cone, forward_only: bool = True
) -> tuple[Float[Array, ""], Float[Array, "3"], Bool[Array, ""]]:
    """Where the ray ``origin + lam * direction`` meets a sheet: ``(lam, point, valid)``.

    A plane: ``lam = (p - o).a / (d.a)``.  A cone: the quadratic
    ``((q + lam d).a)^2 = cos^2(theta) |q + lam d|^2`` (``q = o - p``) solved without
    cancellation; a root counts on the cone's own nappe (``(x - p).a`` of the sign of
    ``cos(theta)``) and, with ``forward_only``, at ``lam > 0``; the smallest such ``lam`` wins.
    ``valid`` is False for a miss, a ray in the plane or (within 1e-12) a tangent ray.
    ``cone``: bool (traced or not).
    """
    d, a, c = direction, axis, jnp.cos(half_angle)
    q = origin - apex
    da, qa = jnp.dot(d, a), jnp.dot(q, a)
    # the plane
    lam_p = safe_div(-qa, da, eps=1e-12)
    ok_p = (jnp.abs(da) > 1e-12) & ((lam_p > 0.0) | (not forward_only))
    # the cone
    c2 = c * c
    qa2 = da * da - c2 * jnp.dot(d, d)
    qb = 2.0 * (qa * da - c2 * jnp.dot(q, d))
    qc = qa * qa - c2 * jnp.dot(q, q)
    disc = qb * qb - 4.0 * qa2 * qc
    sq = safe_sqrt(disc)
    s = -0.5 * (qb + jnp.where(qb >= 0.0, sq, -sq))
    roots = jnp.stack([safe_div(s, qa2, eps=1e-300), safe_div(qc, s, eps=1e-300)])
    lin = safe_div(-qc, qb, eps=1e-300)  # a quadratic with no square term (d on the cone's slope)
    roots = jnp.where(jnp.abs(qa2) > 1e-12 * jnp.dot(d, d), roots, jnp.stack([lin, lin]))

    def good(lam):
        side = (qa + lam * da) * c
        return (disc >= 0.0) & (side >= 0.0) & ((lam > 0.0) | (not forward_only)) & (jnp.abs(s) > 0.0)

    ok1, ok2 = good(roots[0]), good(roots[1])
    if forward_only:
        lam_c = jnp.where(ok1 & ok2, jnp.minimum(roots[0], roots[1]), jnp.where(ok1, roots[0], roots[1]))
    else:  # the root nearest the origin
        near = jnp.where(jnp.abs(roots[0]) <= jnp.abs(roots[1]), roots[0], roots[1])
        far = jnp.where(jnp.abs(roots[0]) <= jnp.abs(roots[1]), roots[1], roots[0])
        ok_near = jnp.where(jnp.abs(roots[0]) <= jnp.abs(roots[1]), ok1, ok2)
        lam_c = jnp.where(ok_near, near, far)
    ok_c = ok1 | ok2
    lam = jnp.where(cone, lam_c, lam_p)
    ok = jnp.where(cone, ok_c, ok_p)
    lam = jnp.where(ok, lam, 0.0)
    return lam, origin + lam * direction, ok


def sheet_on_board(
    sheets: Sheets, i: int, T_cam_board: Pose, angles: Float[Array, " m"]
) -> tuple[Float[Array, "m 3"], Bool[Array, " m"]]:
    """Where sheet ``i``'s light meets a board's plane ``z = 0`` (camera frame), one point per
    emission angle: the ray from the apex at the angle ``angles`` (rad) about the axis (a
    cone: along the cone, ``cos(theta) a + sin(theta) (cos(phi) e1 + sin(phi) e2)``; a plane:
    in the plane, ``cos(phi) e1 + sin(phi) e2``) meets the board's plane in front of it.

    The light's own parametrisation: equal steps in ``angles`` are equal steps of the emitter's
    fan.  ``valid`` is False where the ray runs parallel to the board or away from it.
    """
    p, a, th = sheets.apex[i], sheets.axis[i], sheets.half_angle[i]
    e1, e2 = orthonormal_basis(a)
    n, t = T_cam_board.R[:, 2], T_cam_board.t

    def one(phi):
        u = jnp.cos(phi) * e1 + jnp.sin(phi) * e2
        d = jnp.cos(th) * a + jnp.sin(th) * u
        den = jnp.dot(n, d)
        lam = safe_div(jnp.dot(n, t - p), den, eps=1e-12)
        return p + lam * d, (jnp.abs(den) > 1e-12) & (lam > 0.0)

    return jax.vmap(one)(jnp.asarray(angles, dtype=float))
