"""A calibration's report and file content: residuals, uncertainty, stages, reprojections."""

import dataclasses

import jax.numpy as jnp
import numpy as np

from ..geometry.pose import Pose
from ..geometry.rig import (
    APEX_COLUMNS,
    CAMERA_COLUMNS,
    CAMERA_NAMES,
    SHAPE_COLUMN,
    TILT_COLUMNS,
    Rig,
    project_board_points,
    project_rim,
    project_spots,
)
from ..observations.formats import Calibration, Observations
from ..observations.problem import KIND_NAMES, Kind, kinds_of, unstack_poses
from ..support.safe import std_of_variance
from .bound import laser_std, laser_working_points, sheet_std, sheet_working_points
from .consistency import final_check
from .evaluate import per_observation
from .result import CalibrationResult
from .stored import problem_json


def obs_table(result: CalibrationResult):
    """Per observation: kind, 2D residual norm (px; a stripe sample's and a rim pixel's distance
    from their curve), validity, its (view, board, laser) labels (a laser by its index in the
    file) and its index in its view (a dot's in its board, a spot's among the view's spots, a
    stripe sample's in its stripe; -1 where the problem was not packed from observations)."""
    pk = result.packed
    norm, kind, ok = per_observation(result.params, pk)
    n_obs = norm.size
    n_d, n_s, n_r = pk.dot_pose.shape[0], pk.spot_pose.shape[0], pk.rim_pixels.shape[0]
    view = np.full(n_obs, -1)
    board = np.full(n_obs, "", dtype=object)
    laser = np.full(n_obs, -1)
    index = np.full(n_obs, -1)
    keys = pk.pose_keys
    for i, k in enumerate(np.asarray(pk.dot_pose)):
        view[i], board[i] = keys[k]
    for i, (_, _, j) in enumerate(pk.dot_src):
        index[i] = j
    for j, (k, las) in enumerate(zip(np.asarray(pk.spot_pose), np.asarray(pk.spot_laser), strict=True)):
        view[n_d + j], board[n_d + j] = keys[k]
        laser[n_d + j] = las
    for j, (_, i) in enumerate(pk.spot_src):
        index[n_d + j] = i
    if result.rig.kinds:  # the spots' lasers by their index in the file
        sel = laser >= 0
        laser[sel] = result.rig.point_elements[laser[sel]]
    for j, k in enumerate(np.asarray(pk.chess_pose)):
        view[n_d + n_s + n_r + j] = pk.chess_keys[k]
    if pk.has_stripes:
        first = n_d + n_s + n_r + pk.chess_pose.shape[0]
        elements = result.rig.sheet_elements
        for j, (k, sh) in enumerate(zip(np.asarray(pk.stripe_pose), np.asarray(pk.stripe_sheet), strict=True)):
            view[first + j], board[first + j] = keys[k]
            laser[first + j] = elements[sh]
        for j, (_, _, i) in enumerate(pk.stripe_src):
            index[first + j] = i
    return norm, kind, ok, view, board, laser, index


def _finite_or_none(x):
    """A number or array as JSON: its values, with None for a NaN (undetermined) one."""
    a = np.asarray(x, dtype=float)
    out = [float(v) if np.isfinite(v) else None for v in a.ravel()]
    return out[0] if a.ndim == 0 else out


def _rms(x):
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else None


def _observations(result: CalibrationResult, obs: Observations | None) -> Observations:
    """``obs``, else the observations the result was calibrated from."""
    obs = result.observations if obs is None else obs
    if obs is None:
        raise ValueError("the result carries no observations: pass the observations it was calibrated from")
    return obs


def report(result: CalibrationResult, obs: Observations | None = None) -> dict:
    """The ``residuals`` and ``uncertainty`` sections of the output (plain JSON types).

    ``obs``: the observations the result was calibrated from, which name its views, boards and
    lasers (default: those the result carries, ``result.observations``)."""
    obs = _observations(result, obs)
    norm, kind, ok, view, board, laser, index = obs_table(result)
    sigma = float(result.cov.sigma)
    point = (kind == Kind.DOT) | (kind == Kind.SPOT) | (kind == Kind.STRIPE)
    # beyond the policy's outlier sigmas of its own kind (the pooled sigma where the kind has none)
    n_sig = result.options.robust.outlier_sigmas
    kinds = kinds_of(result.packed)
    own = np.array([result.kind_sigma.get(k.label) for k in Kind], dtype=float)  # None: NaN
    own = np.where(np.isfinite(own), own, sigma)
    outlier = ok & point & (norm > n_sig * own[kind])
    per_view = {obs.views[v].name: _rms(norm[ok & point & (view == v)]) for v in range(len(obs.views))}
    boards = sorted({b for b in board if b})
    per_board = {b: _rms(norm[ok & (kind == Kind.DOT) & (board == b)]) for b in boards}
    structured = (kind == Kind.SPOT) | (kind == Kind.STRIPE)
    per_laser = {str(i): _rms(norm[ok & structured & (laser == i)]) for i in range(obs.n_lasers)}
    per_direct = {
        obs.calibration_views[c].name: _rms(norm[ok & (kind == Kind.CHESS) & (view == c)])
        for c in result.packed.chess_keys
    }
    check = final_check(result, (norm, kind, ok, view, board, laser, index), outlier)
    outliers = []
    for i in np.flatnonzero(outlier):
        item = {
            "kind": KIND_NAMES[kind[i]],
            "view": obs.views[view[i]].name,
            "board": board[i],
            "index": int(index[i]),
            "residual_px": float(norm[i]),
        }
        if kind[i] in (Kind.SPOT, Kind.STRIPE):
            item["laser"] = int(laser[i])
        outliers.append(item)
    residuals = {
        "rms_px": _rms(norm[ok]),
        "sigma_px": sigma,
        "dof": int(result.cov.dof),
        "by_kind_rms_px": {k.label: _rms(norm[ok & (kind == k)]) for k in kinds},
        "by_kind_sigma_px": {k: (None if not np.isfinite(v) else v) for k, v in result.kind_sigma.items()},
        "per_view_rms_px": per_view,
        "per_board_rms_px": per_board,
        "per_laser_rms_px": per_laser,
        "per_direct_view_rms_px": per_direct,
        "invalid": int(np.sum(~ok)),
        "outliers": outliers,
        "repairs": [r.to_json() for r in result.repairs],
        "rim_outliers": int(np.sum(ok & (kind == Kind.RIM) & (norm > n_sig * (result.kind_sigma.get("rim") or sigma)))),
        "loss": {"kind": result.loss, "scale_px": result.scale},
    }
    cov = np.asarray(result.cov.glob)
    sd = std_of_variance(np.diag(cov))
    x_ref = laser_working_points(result.rig, result.params.poses, result.packed)
    pos, ang = laser_std(result.rig, cov, x_ref)
    held = list(result.undetermined_lasers)
    pos[held], ang[held] = np.nan, np.nan  # held at a placeholder: a std of 0 would claim it known
    last = result.passes[-1] if result.passes else None
    status = []
    if not result.converged and last is not None:
        status.append(
            f"not a minimum: the last pass ({last.name}) {last.result} after {last.steps} steps; "
            "the std below are those of the point where it stopped"
        )
    if check["failed"]:
        status.append(_check_status(check))
    lasers = _element_uncertainty(result, cov, x_ref, pos, ang, held)
    for i, factor in check["laser_scale"].items():
        _scale_laser(lasers[i], factor)
    thin = _thin_lasers(obs, result, kind, ok, outlier, laser)
    for i, (kept, labelled) in thin.items():
        _withdraw_laser(lasers[i], kept, labelled)
    if thin:
        status.append(
            f"{len(thin)} laser(s) kept fewer than {result.options.robust.min_kept_share:.0%} of their spots "
            "after the repairs "
            f"({', '.join(f'laser {i}: {k} of {n}' for i, (k, n) in thin.items())}): what is left may be a wrong "
            "consensus, so their std are withdrawn"
        )
    uncertainty = {
        "converged": result.converged,
        **({"status": "; ".join(status)} if status else {}),
        "consistency": {k: check[k] for k in ("level", "tests", "failed", "shape")},
        "sigma_px": sigma,
        "camera_std": dict(zip(CAMERA_NAMES, _finite_or_none(sd[CAMERA_COLUMNS]), strict=True)),
        "mirror_std": {
            "apex_mm": _finite_or_none(sd[APEX_COLUMNS]),
            "axis_tilt_deg": _finite_or_none(np.degrees(sd[TILT_COLUMNS])),
        }
        | ({"conic_constant": _finite_or_none(sd[SHAPE_COLUMN])} if float(result.masks.glob[SHAPE_COLUMN]) else {}),
        "lasers": lasers,
        "covariance": {
            "parameters": f"camera ({', '.join(CAMERA_NAMES)}), mirror (apex dx, dy, dz mm; axis tilt "
            "e1, e2 rad; conic constant, 0 where the shape is given), then per laser (point offset e1, e2 mm; "
            "direction tilt e1, e2 rad) with (e1, e2) the orthonormal basis of slcvjax.support.safe.orthonormal_basis "
            "about the axis / laser direction"
            + (
                "; a line laser's plane (offset along its normal mm; normal tilt e1, e2 rad), a ring laser's cone "
                "(apex e1, e2, along the axis mm; axis tilt e1, e2 rad; half-angle rad), each in the lasers' order"
                if result.rig.has_sheets
                else ""
            ),
            "matrix": cov.tolist(),
        },
    }
    if result.box is not None:
        uncertainty["rigid_box"] = _box_json(result.box)
    return {"residuals": residuals, "uncertainty": uncertainty}


def _check_status(check: dict) -> str:
    """``uncertainty.status``'s line for a failed final check."""
    names = ", ".join(
        f"{f['group']} ({f['ratio']:.2f}x the variance of the rest of its kind)" for f in check["failed"][:6]
    )
    more = f" and {len(check['failed']) - 6} more" if len(check["failed"]) > 6 else ""
    return (
        f"inconsistent: {len(check['failed'])} of {check['tests']} final checks fail at level {check['level']:g} "
        f"({names}{more}): the residuals do not follow the noise model there, and the std assume they do; "
        "a laser's std is scaled by the root of its spread ratio"
    )


def _thin_lasers(obs: Observations, result: CalibrationResult, kind, ok, outlier, laser) -> dict[int, tuple[int, int]]:
    """Point lasers (by their index in the file) that kept fewer than ``min_kept_share``
    (:class:`slcvjax.calibration.options.RobustPolicy`) of their spots: of the spots that ended
    with its label (given to it by a repair included) or were lost from it (left out while its
    own, or outliers of its line), those kept.  A spot given to another laser is not counted: it
    was never this laser's.  ``{laser: (kept, kept + lost)}``: most of the spots once its own
    disagree with the line it ended on, which may rest on a consensus of wrong ones."""
    n = obs.n_lasers
    spot = ok & (kind == Kind.SPOT)
    kept = np.bincount(laser[spot & ~outlier], minlength=n)[:n]
    lost = np.bincount(laser[spot & outlier], minlength=n)[:n]
    for r in result.repairs:
        if r.kind == "spot" and r.action == "left out" and r.laser is not None and 0 <= r.laser < n:
            lost[r.laser] += 1
    held = set(result.rig.element_indices(result.undetermined_lasers))
    share = result.options.robust.min_kept_share
    return {
        int(i): (int(kept[i]), int(kept[i] + lost[i]))
        for i in np.flatnonzero(kept < share * (kept + lost))
        if int(i) not in held
    }


def _withdraw_laser(item: dict, kept: int, labelled: int) -> None:
    """Withdraw a laser's std in ``uncertainty.lasers[i]`` (None) and say why."""
    for key in ("position_std_mm", "direction_std_deg", "half_angle_std_deg"):
        if key in item:
            item[key] = None
    item.pop("std_scale", None)
    note = (
        f"suspect: only {kept} of the {labelled} spots once its own are left after the repairs; its line "
        "may rest on a consensus of wrong spots, so no std is given"
    )
    item["status"] = f"{item['status']}; {note}" if item.get("status") else note


def _scale_laser(item: dict, factor: float) -> None:
    """Scale a laser's std in ``uncertainty.lasers[i]`` by ``factor`` (>= 1) and say so."""
    for key in ("position_std_mm", "direction_std_deg", "half_angle_std_deg"):
        if item.get(key) is not None:
            item[key] = item[key] * factor
    item["std_scale"] = factor
    note = f"inconsistent: its residuals spread {factor:.2f}x their noise; its std are scaled by {factor:.2f}"
    item["status"] = f"{item['status']}; {note}" if item.get("status") else note


def _point_uncertainty(i, x_ref, pos, ang, held) -> dict:
    """``uncertainty.lasers[k]`` of point laser ``i`` (its index among the point lasers)."""
    item = {
        "working_point": None if i in held else x_ref[i].tolist(),
        "working_range_mm": None if i in held else float(np.linalg.norm(x_ref[i])),
        "position_std_mm": _finite_or_none(pos[i]),
        "direction_std_deg": _finite_or_none(np.degrees(ang[i])),
    }
    if i in held:
        item["status"] = "undetermined: its spots cannot fix a line (held; its spots are left out)"
    elif not (np.isfinite(pos[i]) and np.isfinite(ang[i])):
        item["status"] = "undetermined: its covariance is not positive (the data do not fix this laser)"
    return item


def _element_uncertainty(result: CalibrationResult, cov, x_ref, pos, ang, held) -> list[dict]:
    """``uncertainty.lasers``: per laser in the file's order, its errors at its working range (a
    point laser's line; a line or ring laser's sheet: its position along its normal and its normal
    at its working point, and a cone's half-angle)."""
    rig = result.rig
    if not rig.kinds:
        return [_point_uncertainty(i, x_ref, pos, ang, held) for i in range(rig.lasers.n)]
    xs = sheet_working_points(rig, result.params.poses, result.packed)
    sp, sn, sa = sheet_std(rig, cov, xs)
    held_s = set(result.undetermined_sheets)
    sp[list(held_s)], sn[list(held_s)], sa[list(held_s)] = np.nan, np.nan, np.nan
    local, out = rig.local_index, []
    for e, kind in enumerate(rig.element_kinds):
        j = int(local[e])
        if kind == "point":
            out.append(_point_uncertainty(j, x_ref, pos, ang, held) | {"kind": "point"})
            continue
        item = {
            "kind": kind,
            "working_point": None if j in held_s else xs[j].mean(axis=0).tolist(),
            "working_range_mm": None if j in held_s else float(np.mean(np.linalg.norm(xs[j], axis=1))),
            "position_std_mm": _finite_or_none(sp[j]),
            "direction_std_deg": _finite_or_none(np.degrees(sn[j])),
        }
        if kind == "cone":
            item["half_angle_std_deg"] = _finite_or_none(np.degrees(sa[j]))
        if j in held_s:
            item["status"] = "undetermined: its stripes cannot fix its sheet (held; its stripes are left out)"
        elif not np.isfinite(sp[j]):
            item["status"] = "undetermined: its covariance is not positive (the data do not fix this laser)"
        out.append(item)
    return out


def _box_json(box: dict) -> dict:
    """``uncertainty.rigid_box`` of a result with the rigid box model."""
    boards = {
        b: {
            "R": np.asarray(d["pose"].R).tolist(),
            "t": np.asarray(d["pose"].t).tolist(),
            "rotation_std_deg": _finite_or_none(d["rotation_deg"]),
            "translation_std_mm": _finite_or_none(d["translation_mm"]),
        }
        for b, d in box["boards"].items()
    }
    return {"gauge": box["gauge"], "boards": boards} | {
        k: box[k] for k in ("views", "free_board_poses", "left_out", "spots_restored", "notes")
    }


def _rig_json(rig: Rig, undetermined: tuple[int, ...] = ()) -> dict:
    from ..observations.formats import calibration_to_json

    doc = calibration_to_json(Calibration(rig, undetermined_lasers=undetermined))
    return {k: doc[k] for k in ("camera", "mirror", "lasers")}


def to_calibration(result: CalibrationResult, obs: Observations | None = None) -> Calibration:
    """The ``slcv-calibration/1`` content of a result: the joint solution, its report, the staged
    result beside it, and the problem it solved (``problem``: :mod:`slcvjax.calibration.stored`;
    :func:`slcvjax.calibration.stored.load_result` reads it back).  ``obs``: as :func:`report`'s."""
    obs = _observations(result, obs)
    pk = result.packed
    board_poses: list[dict[str, Pose]] = [{} for _ in obs.views]
    for (v, b), pose in zip(pk.pose_keys, unstack_poses(result.params.poses), strict=True):
        board_poses[v][b] = pose
    cvp: list[Pose | None] = [None] * len(obs.calibration_views)
    for c, pose in zip(pk.chess_keys, unstack_poses(result.params.chess), strict=True):
        cvp[c] = pose
    rep = report(result, obs)
    st = result.staged
    stages = {
        "staged": {
            **_rig_json(st.rig, st.rig.element_indices(st.undetermined, st.undetermined_sheets)),
            "reports": [
                {"stage": r.name, "rms": _finite_or_none(r.rms), "unit": r.unit, "notes": r.notes} for r in st.reports
            ],
        },
        "joint": {"passes": [p.to_json() for p in result.passes], "timings_s": result.timings},
    }
    if result.observations is None:
        result = dataclasses.replace(result, observations=obs)
    extra = {**rep, "stages": stages, "problem": problem_json(result)}
    return Calibration(result.rig, board_poses, cvp, extra, result.undetermined_elements)


def reprojections(cal: Calibration, obs: Observations, view: int, rim_points: int = 360) -> dict:
    """The calibrated model's pixels for one catadioptric view (for plots and checks).

    Returns ``{"dots": {board: (M, 2)}, "spots": (S, 2), "rim": (K, 2)}``: the board
    points through the mirror at the view's board poses, each detected spot's laser on
    its board's plane (NaN where the spot has no posed board or the model has no pixel)
    and the rim curve.  Invalid model pixels are NaN.
    """
    rig, poses, v = cal.rig, cal.board_poses[view], obs.views[view]
    dots = {}
    for b in v.boards:
        if b in poses:
            uv, ok = project_board_points(rig, poses[b], jnp.asarray(obs.boards[b], dtype=float))
            dots[b] = np.where(np.asarray(ok)[:, None], np.asarray(uv), np.nan)
    spots = np.full((len(v.spots), 2), np.nan)
    for i, s in enumerate(v.spots):
        if s.board in poses:
            uv, ok = project_spots(rig, poses[s.board], jnp.asarray([s.laser]))
            if bool(ok[0]):
                spots[i] = np.asarray(uv[0])
    uv, ok = project_rim(rig, jnp.linspace(0.0, 2 * np.pi, rim_points, endpoint=False))
    return {"dots": dots, "spots": spots, "rim": np.asarray(uv)[np.asarray(ok)]}
