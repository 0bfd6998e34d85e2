"""The residual of one observation over its few local parameters.

Every observation touches the global block (camera, mirror, at most one laser) and at most one
pose block:

============ ===== ============================================== ==========
observation  rows  local parameters                                pose block
============ ===== ============================================== ==========
dot          2     camera, mirror, board pose (21)                board pose
spot         2     camera, mirror, its laser, board pose (25)     board pose
rim pixel    1     camera, mirror (15)                             none
chess corner 2     camera, direct-view pose (15)                  direct view
stripe       1     camera, mirror, its sheet (6), board pose (27)  board pose
============ ===== ============================================== ==========

Each function here takes the local tangent ``d`` first (zero at the current estimate), so that its
Jacobian is a forward-mode derivative over a few columns.  Pixel residuals are ``model - observed``
in px; a residual comes with a validity flag (the point reflects off the mirror and lands on the
sensor), never a NaN.  The rim residual is the signed first-order (Sampson) distance of a rim
pixel to the projected rim curve, in px: ``F(uv) / |dF/duv|`` with ``F = |X(uv) - C| - r``, ``X``
the pixel's ray on the rim's plane and ``C`` the rim's centre (:func:`rim_value`,
:func:`rim_scale`).

A stripe sample's residual is likewise its signed first-order distance in px from the curve where
its line or ring laser's sheet of light meets its board's plane, as seen through the mirror
(:func:`stripe_value`): the sample's reflected ray (closed form) meets the board's plane at ``X``,
and ``G(X) / |dG/duv|`` with ``G`` the sheet's equation
(:func:`slcvjax.geometry.sheets.sheet_value`).  A sample is a point anywhere on the stripe's centre
line, so only its distance across the curve carries information: the pixel noise across the
stripe, with the curve's first-order geometry, is what the bound sees.  The normalisation is
taken at the current estimate and held in the Jacobian (as the rim's is), so that the Gauss-Newton
step is that of the distances in px.  A sheet's columns are 6 wide here (a plane's 3 first and 3
unused).
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ..geometry.camera import Camera, in_image, pixel_to_line, project
from ..geometry.lasers import Lasers, line_plane_intersection
from ..geometry.mirror import Mirror, back_project, project_through_mirror
from ..geometry.pose import Pose
from ..geometry.rig import Rig
from ..geometry.sheets import CONE_DOF, retract_sheet, sheet_value
from ..observations.problem import Kind, Packed, map_rows
from ..support.safe import safe_div, safe_norm
from .params import N_CAM, N_CM, N_LAS

RIM_MARGIN = 0.05  # the cone extended 5 % past its rim for residuals (see solve_mirror_point)


APEX_MARGIN = 0.05  # and 5 % of its height past the apex


def camera_mirror(cam: Camera, mir: Mirror, d):
    return cam.retract(d[:N_CAM]), mir.retract(d[N_CAM:N_CM])


def mirror_residual(cam: Camera, mir: Mirror, x, px):
    res = project_through_mirror(cam, mir, x, rim_margin=RIM_MARGIN, apex_margin=APEX_MARGIN)
    return res.uv - px, res.valid


def laser_on_board(d_laser, lp, ld, pose: Pose):
    """Where the laser ``(lp, ld)`` moved by ``d_laser`` (4) meets the plane of ``pose``."""
    las = Lasers(lp[None], ld[None]).retract(d_laser[None])
    return line_plane_intersection(las.points[0], las.directions[0], pose, forward_only=False)


def dot_residual(d, cam, mir, R, t, xb, px):
    """A dot's residual over its local parameters ``d`` (camera, mirror, board pose: 21)."""
    c, m = camera_mirror(cam, mir, d)
    return mirror_residual(c, m, Pose(R, t).retract(d[N_CM:]).apply(xb), px)


def spot_residual(d, cam, mir, lp, ld, R, t, px):
    """A spot's residual over its local parameters ``d`` (camera, mirror, laser, board pose: 25)."""
    c, m = camera_mirror(cam, mir, d)
    x, ok = laser_on_board(d[N_CM : N_CM + N_LAS], lp, ld, Pose(R, t).retract(d[N_CM + N_LAS :]))
    r, valid = mirror_residual(c, m, x, px)
    return r, ok & valid


def dot_point(d, R, t, xb):
    """A dot's 3D point (camera frame) over ``d``: laser (4, unused) and board pose (6)."""
    return Pose(R, t).retract(d[N_LAS:]).apply(xb), jnp.asarray(True)


def spot_point(d, lp, ld, R, t):
    """A spot's 3D point over ``d``: its laser (4) and board pose (6)."""
    return laser_on_board(d[:N_LAS], lp, ld, Pose(R, t).retract(d[N_LAS:]))


def box_board_pose(d, Rv, tv, Rb, tb):
    """``T_cam_box`` (its tangent ``d[6:]``) composed with ``T_box_board`` (``d[:6]``): a board
    pose of the rigid box model."""
    return Pose(Rv, tv).retract(d[6:]) @ Pose(Rb, tb).retract(d[:6])


def dot_point_box(d, Rv, tv, Rb, tb, xb):
    """:func:`dot_point` of the rigid box model: ``d`` is laser (4, unused), box pose (6), view pose (6)."""
    return box_board_pose(d[N_LAS:], Rv, tv, Rb, tb).apply(xb), jnp.asarray(True)


def spot_point_box(d, lp, ld, Rv, tv, Rb, tb):
    """:func:`spot_point` of the rigid box model: its laser (4), box pose (6), view pose (6)."""
    return laser_on_board(d[:N_LAS], lp, ld, box_board_pose(d[N_LAS:], Rv, tv, Rb, tb))


def point_residual(d, cam, mir, x, px):
    """The residual of a point ``x`` seen through the mirror over ``d``: camera, mirror (15), the point (3)."""
    c, m = camera_mirror(cam, mir, d)
    return mirror_residual(c, m, x + d[N_CM:], px)


def rim_value(cam: Camera, mir: Mirror, uv: Float[Array, "2"]) -> tuple[Float[Array, ""], Bool[Array, ""]]:
    """``F(uv) = |X(uv) - C| - r`` (mm): the pixel's ray on the rim's plane against the rim circle."""
    o, d, ok = pixel_to_line(cam, uv)
    centre = mir.apex + mir.height * mir.axis
    lam = safe_div(jnp.dot(centre - o, mir.axis), jnp.dot(d, mir.axis))
    return safe_norm(o + lam * d - centre) - mir.radius, ok & (lam > 0.0)


def rim_scale(cam: Camera, mir: Mirror, uv: Float[Array, "2"]) -> Float[Array, ""]:
    """``|dF/duv|`` (mm per px): ``F / |dF/duv|`` is a pixel's first-order (Sampson) distance
    from the projected rim circle, in px."""
    return safe_norm(jax.jacfwd(lambda u: rim_value(cam, mir, u)[0])(uv))


def rim_residual(d, cam, mir, uv, norm):
    c, m = camera_mirror(cam, mir, d)
    val, ok = rim_value(c, m, uv)
    return safe_div(val, norm)[None], ok & (norm > 0.0)


def rim_norms(rig: Rig, pk: Packed, real_only: bool = True) -> Float[Array, " R"]:
    """Each rim pixel's ``|dF/duv|`` (:func:`rim_scale`) on ``rig``: the rim rows' normalisation
    (none for a camera-only rig, which has no rim).  ``real_only``: the real rows only
    (``pk.counts``; the padded rows' norm is 0, which leaves them invalid), in a loop that
    cannot be differentiated in reverse mode; ``False``: every row, differentiable."""
    if rig.mirror is None:
        return jnp.zeros(pk.rim_pixels.shape[0])
    norms = jax.vmap(lambda uv: rim_scale(rig.camera, rig.mirror, uv))
    if not real_only:
        return norms(pk.rim_pixels)
    return map_rows(norms)(pk.rim_pixels, pk.counts[Kind.RIM])


def chess_residual(d, cam, R, t, xb, px):
    c = cam.retract(d[:N_CAM])
    uv, ok = project(c, Pose(R, t).retract(d[N_CAM:]).apply(xb))
    return uv - px, ok & in_image(c, jax.lax.stop_gradient(uv))


def stripe_value(cam: Camera, mir: Mirror, p, a, th, pose: Pose, uv: Float[Array, "2"]):
    """``G(X(uv))`` (mm): the sample's reflected ray meets the board's plane at ``X``, weighed by
    the sheet ``(p, a, th)``'s equation; and whether that is defined (a valid ray that meets the
    plane ahead of the mirror)."""
    ray = back_project(cam, mir, uv)
    n = pose.R[:, 2]
    den = jnp.dot(n, ray.direction)
    lam = safe_div(jnp.dot(n, pose.t - ray.point), den, eps=1e-9)
    x = ray.point + lam * ray.direction
    return sheet_value(x, p, a, th), ray.valid & (jnp.abs(den) > 1e-9) & (lam > 0.0)


def stripe_distance(cam: Camera, mir: Mirror, p, a, th, pose: Pose, uv: Float[Array, "2"]):
    """A sample's signed first-order distance (px) from its stripe's predicted curve:
    ``G / |dG/duv|`` (:func:`stripe_value`).  The normalisation is differentiated with the rest:
    held constant, the fixed point of the steps would weigh each sample by it at the solution and
    move every parameter it depends on by O(sigma^2), whatever the number of samples
    (``benchmarks/sheet_lasers.py``: a cone's half-angle 6x its bound at 0.3 px)."""
    g, ok = stripe_value(cam, mir, p, a, th, pose, uv)
    grad = jax.jacfwd(lambda u: stripe_value(cam, mir, p, a, th, pose, u)[0])(uv)
    norm = safe_norm(grad)
    return safe_div(g, norm), ok & (norm > 0.0)


def stripe_residual(d, cam, mir, p, a, th, cone, R, t, uv):
    """A stripe sample's residual over its local parameters ``d``: camera, mirror (15), its sheet
    (6: a plane's 3 first), board pose (6)."""
    c, m = camera_mirror(cam, mir, d)
    p2, a2, th2 = retract_sheet(p, a, th, d[N_CM : N_CM + CONE_DOF], cone)
    r, ok = stripe_distance(c, m, p2, a2, th2, Pose(R, t).retract(d[N_CM + CONE_DOF :]), uv)
    return r[None], ok


def stripe_residual_box(d, cam, mir, p, a, th, cone, Rv, tv, Rb, tb, uv):
    """:func:`stripe_residual` of the rigid box model: its board pose is the box's (6) and the view's (6)."""
    c, m = camera_mirror(cam, mir, d)
    p2, a2, th2 = retract_sheet(p, a, th, d[N_CM : N_CM + CONE_DOF], cone)
    pose = box_board_pose(d[N_CM + CONE_DOF :], Rv, tv, Rb, tb)
    r, ok = stripe_distance(c, m, p2, a2, th2, pose, uv)
    return r[None], ok
