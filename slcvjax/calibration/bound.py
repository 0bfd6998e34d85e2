"""The lasers at their working range: working points, their std from a covariance, their errors
against a truth, and the Cramer-Rao bound of a scene."""

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..geometry.lasers import Lasers, line_plane_intersection
from ..geometry.pose import Pose
from ..geometry.rig import (
    Rig,
)
from ..geometry.sheets import Sheets, sheet_gradient, sheet_value
from ..observations.formats import Calibration, Observations
from ..observations.problem import Packed, pack, stack_poses, unstack_poses
from ..support.safe import std_of_variance
from .covariance import covariance_of
from .params import Params, make_masks
from .rigid import (
    box_model,
    rigid_group,
    rigid_masks,
    rigid_params,
)


def laser_working_points(rig: Rig, poses: Pose, pk: Packed) -> np.ndarray:
    """Per laser, the point of its line nearest the mean of its spots on their boards (mm)."""
    n = rig.lasers.n
    out = np.zeros((n, 3))
    laser_of, pose_of = np.asarray(pk.spot_laser), np.asarray(pk.spot_pose)
    for l_idx in range(n):
        p, d = rig.lasers.points[l_idx], rig.lasers.directions[l_idx]
        pts = [
            np.asarray(line_plane_intersection(p, d, Pose(poses.R[k], poses.t[k]))[0])
            for k in pose_of[laser_of == l_idx]
        ]
        c = np.mean(pts, axis=0) if pts else np.asarray(p)
        pn, dn = np.asarray(p), np.asarray(d)
        out[l_idx] = pn + ((c - pn) @ dn) * dn
    return out


def laser_offset(lasers: Lasers, i: int, x_ref, delta4):
    """Laser ``i`` moved by ``delta4``: its foot at ``x_ref`` less ``x_ref`` (mm)."""
    return lasers.at_working_point(i, x_ref, delta4)[0] - x_ref


def laser_variance(lasers: Lasers, i, x_ref, block) -> tuple[jax.Array, jax.Array]:
    """Laser ``i``'s position variance (mm^2) at the working point ``x_ref`` (3,) and its
    direction variance (rad^2), from its block of a covariance (its tangent columns, (4, 4):
    point offset e1, e2, direction tilt e1, e2).  In JAX: the report's :func:`laser_std` and the
    design's prediction (differentiated) both use it; ``i`` may be traced."""
    j = jax.jacfwd(lambda d: laser_offset(lasers, i, x_ref, d))(jnp.zeros(block.shape[0]))
    return jnp.trace(j @ block @ j.T), block[2, 2] + block[3, 3]


_laser_variance = jax.jit(laser_variance)


def laser_std(rig: Rig, cov_glob: np.ndarray, x_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per laser: position std (mm) of the line at ``x_ref`` and direction std (rad)
    (:func:`laser_variance`); NaN for a laser whose covariance block is not positive
    (undetermined)."""
    n = rig.lasers.n
    pos, ang = np.zeros(n), np.zeros(n)
    cov_glob = np.asarray(cov_glob)
    element = rig.point_elements
    for i in range(n):
        sl = rig.layout.elements[int(element[i])]
        c = cov_glob[sl, sl]
        # a block that is not positive: the data do not determine this laser (NaN, not 0)
        definite = bool(np.all(np.isfinite(c))) and (
            np.linalg.eigvalsh(0.5 * (c + c.T)).min() >= -1e-9 * max(np.abs(c).max(), 1e-300)
        )
        if definite:
            var_p, var_a = _laser_variance(rig.lasers, i, jnp.asarray(x_ref[i]), jnp.asarray(c))
            pos[i], ang[i] = std_of_variance(float(var_p)), std_of_variance(float(var_a))
        else:
            pos[i] = ang[i] = np.nan
    return pos, ang


RING_POINTS = 36  # a ring laser's working points: its cone at its working range, every 10 deg round its axis


def sheet_working_points(rig: Rig, poses: Pose, pk: Packed) -> np.ndarray:
    """Per line or ring laser, :data:`RING_POINTS` points of its sheet where it is used (mm, camera
    frame), (S, K, 3): a line laser's plane at the point nearest the mean of its stripe samples'
    points (the samples' reflected rays on their boards' planes, by ``rig``), repeated; a ring
    laser's cone at the mean distance of those points from its apex, every 10 deg round its axis
    (a ring's mean point lies on its axis, where the cone is not).  A sheet without samples takes
    100 mm from its apex."""
    from .sheet_fit import stripe_points

    n = rig.sheets.n if rig.has_sheets else 0
    out = np.zeros((n, RING_POINTS, 3))
    if not n:
        return out
    pts, usable = stripe_points(rig.camera, rig.mirror, pk, unstack_poses(poses))
    sheet_of = np.asarray(pk.stripe_sheet)[: pts.shape[0]]
    sh = rig.sheets
    for i in range(n):
        sel = usable & (sheet_of == i)
        p, a, th = (np.asarray(x, float) for x in (sh.apex[i], sh.axis[i], sh.half_angle[i]))
        if sh.kinds[i] == "plane":
            c = pts[sel].mean(axis=0) if sel.any() else p + 100.0 * _across(a)
            out[i] = c - ((c - p) @ a) * a
            continue
        rho = float(np.mean(np.linalg.norm(pts[sel] - p, axis=1))) if sel.any() else 100.0
        e1 = _across(a)
        e2 = np.cross(a, e1)
        phi = np.linspace(0.0, 2 * np.pi, RING_POINTS, endpoint=False)
        u = np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2
        out[i] = p + rho * (np.cos(th) * a + np.sin(th) * u)
    return out


def _across(a: np.ndarray) -> np.ndarray:
    """A unit vector across the unit vector ``a``."""
    h = np.eye(3)[int(np.argmin(np.abs(a)))]
    e = h - (h @ a) * a
    return e / np.linalg.norm(e)


def sheet_variance(sheets: Sheets, i, x_ref, block) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Sheet ``i``'s variances at its working points ``x_ref`` (K, 3) on it, from its block of a
    covariance (its own tangent columns: 3 for a plane, 6 for a cone), each the mean over the
    points: of its position along its normal (mm^2), of its normal's direction (rad^2), and of its
    half-angle (rad^2; 0 for a plane)."""

    def at(x):
        n0 = sheets.at_working_point(i, x)[1]

        def moved(d):
            foot, normal, *_ = sheets.at_working_point(i, x, d)
            return jnp.dot(foot - x, n0), normal

        d0 = jnp.zeros(block.shape[0])
        jp = jax.jacfwd(lambda d: moved(d)[0])(d0)
        jn = jax.jacfwd(lambda d: moved(d)[1])(d0)
        return jp @ block @ jp, jnp.trace(jn @ block @ jn.T)

    vp, vn = jax.vmap(at)(jnp.asarray(x_ref).reshape(-1, 3))
    var_angle = block[5, 5] if block.shape[0] == 6 else jnp.zeros(())
    return jnp.mean(vp), jnp.mean(vn), var_angle


def sheet_std(rig: Rig, cov_glob: np.ndarray, x_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per line or ring laser (:func:`sheet_variance` at its working points ``x_ref`` (S, K, 3)):
    the std of its position along its normal (mm), of its normal (rad) and of its half-angle
    (rad; 0 for a plane), RMS over the points; NaN where its covariance block is not positive
    (undetermined)."""
    n = rig.sheets.n if rig.has_sheets else 0
    pos, nrm, ang = np.zeros(n), np.zeros(n), np.zeros(n)
    cov_glob = np.asarray(cov_glob)
    for i, e in enumerate(rig.sheet_elements):
        sl = rig.layout.elements[int(e)]
        c = cov_glob[sl, sl]
        definite = bool(np.all(np.isfinite(c))) and (
            np.linalg.eigvalsh(0.5 * (c + c.T)).min() >= -1e-9 * max(np.abs(c).max(), 1e-300)
        )
        if not definite:
            pos[i] = nrm[i] = ang[i] = np.nan
            continue
        vp, vn, va = (float(v) for v in sheet_variance(rig.sheets, i, jnp.asarray(x_ref[i]), jnp.asarray(c)))
        pos[i], nrm[i], ang[i] = std_of_variance(vp), std_of_variance(vn), std_of_variance(va)
    return pos, nrm, ang


def sheet_errors(est: Rig, truth: Rig, x_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per line or ring laser, against the truth at its working points ``x_ref`` (S, K, 3) on the
    true sheet: the distance (mm) from each point to the estimated sheet (first order, along its
    normal) and the angle (rad) between the two sheets' normals there, each RMS over the points,
    and the half-angle's error (rad; 0 for a plane)."""
    n = truth.sheets.n
    pos, nrm, ang = np.zeros(n), np.zeros(n), np.zeros(n)
    e, t = est.sheets, truth.sheets
    for i in range(n):
        x = jnp.asarray(x_ref[i]).reshape(-1, 3)
        pe, ae, the = e.apex[i], e.axis[i], e.half_angle[i]
        pt, at, tht = t.apex[i], t.axis[i], t.half_angle[i]
        g = jax.vmap(sheet_value, in_axes=(0, None, None, None))(x, pe, ae, the)
        ge = np.asarray(jax.vmap(sheet_gradient, in_axes=(0, None, None, None))(x, pe, ae, the))
        gt = np.asarray(jax.vmap(sheet_gradient, in_axes=(0, None, None, None))(x, pt, at, tht))
        ne = ge / np.linalg.norm(ge, axis=1, keepdims=True)
        nt = gt / np.linalg.norm(gt, axis=1, keepdims=True)
        d = np.asarray(g) / np.linalg.norm(ge, axis=1)
        a = np.arctan2(np.linalg.norm(np.cross(ne, nt), axis=1), np.abs(np.sum(ne * nt, axis=1)))
        pos[i], nrm[i] = np.sqrt(np.mean(d**2)), np.sqrt(np.mean(a**2))
        ang[i] = abs(float(e.half_angle[i]) - float(t.half_angle[i]))
    return pos, nrm, ang


def laser_errors(est: Rig, truth: Rig, x_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per laser: distance (mm) from the true working point to the estimated line, and angle (rad)."""
    p, d = np.asarray(est.lasers.points), np.asarray(est.lasers.directions)
    v = x_ref - p
    pos = np.linalg.norm(v - np.sum(v * d, axis=1, keepdims=True) * d, axis=1)
    dt = np.asarray(truth.lasers.directions)
    # atan2 keeps full precision near zero, where arccos of a dot product bottoms out at ~1.5e-8 rad
    ang = np.arctan2(np.linalg.norm(np.cross(d, dt), axis=1), np.abs(np.sum(d * dt, axis=1)))
    return pos, ang


def cramer_rao(
    truth: Calibration,
    obs: Observations,
    sigma: "float | Sequence[float]",
    packed: Packed | None = None,
    rigid: "bool | list[str]" = False,
) -> dict:
    """The Cramer-Rao bound of a scene: ``sigma^2 (J^T J)^-1`` at the true parameters; with
    ``sigma`` one per kind (dot, spot, rim, chess corner), ``(sum_k N_k / sigma_k^2)^-1``.

    Returns the covariance and, per laser, the bound's position std at the working
    point (mm) and direction std (rad), with their RMS over lasers.  ``packed``: the
    observations as a calibration packed them (``CalibrationResult.packed``: spots
    detected without a board have the board the staged stage gave them); by default
    ``pack(obs)``, which leaves such spots out.  ``rigid``: the bound of the rigid box
    model (as :func:`calibrate`'s ``rigid``; the truth's board poses must be rigid);
    its covariance is then the rig's block, and ``box_cov`` the whole global block
    (rig, then 6 per box board but the gauge, ``box_model``'s order).
    """
    pk = pack(obs) if packed is None else packed
    poses = stack_poses([truth.board_poses[v][b] for v, b in pk.pose_keys])
    chess = [truth.calibration_view_poses[c] for c in pk.chess_keys] if truth.calibration_view_poses else []
    chess_stack = stack_poses(chess) if chess else Pose(jnp.zeros((0, 3, 3)), jnp.zeros((0, 3)))
    params = Params(truth.rig, poses, chess_stack)
    masks = make_masks(params)
    out = {}
    group = rigid_group(obs, rigid)
    if group:
        model = box_model(pk, group)
        params = rigid_params(model, pk.pose_keys, unstack_poses(poses), truth.rig, chess_stack)
        masks = rigid_masks(model, masks, pk.n_poses)
        pk = model.packed(pk)
    # plain least squares (Huber at 1e9 px), sharing the compiled covariance of calibrate()
    cov = covariance_of(params, pk, masks, "huber", 1e9, sigma=sigma)
    if group:
        g = truth.rig.tangent_dim
        out["box_cov"] = np.asarray(cov.glob)
        out["box_model"] = model
        cov = cov._replace(glob=np.asarray(cov.glob)[:g, :g])
    x_ref = laser_working_points(truth.rig, poses, pk)
    pos, ang = laser_std(truth.rig, np.asarray(cov.glob), x_ref)
    if truth.rig.has_sheets:
        xs = sheet_working_points(truth.rig, poses, pk)
        sp, sn, sa = sheet_std(truth.rig, np.asarray(cov.glob), xs)
        out |= {
            "sheet_x_ref": xs,
            "sheet_position_std_mm": sp,
            "sheet_normal_std_rad": sn,
            "sheet_angle_std_rad": sa,
        }
    return out | {
        "cov": cov,
        "x_ref": x_ref,
        "position_std_mm": pos,
        "direction_std_rad": ang,
        "position_rms_mm": float(np.sqrt(np.mean(pos**2))) if pos.size else float("nan"),
        "direction_rms_rad": float(np.sqrt(np.mean(ang**2))) if ang.size else float("nan"),
    }
