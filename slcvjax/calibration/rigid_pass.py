"""Pass R: a free solution refined under the rigid box model (:mod:`slcvjax.calibration.rigid`)."""

import dataclasses
import time

import numpy as np

from ..geometry.pose import Pose
from ..observations.formats import Observations
from ..observations.problem import KIND_NAMES, Kind, Packed, unstack_poses
from .covariance import (
    Covariance,
    covariance_compiled,
    kind_linearisations,
    robust_sigma_of,
    sandwich_of,
    sigmas_of,
    unpad_covariance,
)
from .evaluate import per_observation, probe_at, solve_compiled
from .lm import Outcome
from .options import RobustPolicy
from .params import Params, pad_masks, pad_problem, unpad_params
from .passes import RTOL_FINAL
from .result import CalibrationResult, JointPass, Repair
from .rigid import (
    board_pose_covariances,
    board_poses_of,
    box_model,
    box_pose_std,
    rigid_masks,
    rigid_params,
)


def _restore_spots(
    params: Params, model, cur: Packed, obs: Observations, left, policy: RobustPolicy
) -> tuple[set, Packed]:
    """The spots of ``obs`` that ``cur`` lacks or carries under another label (the free solve
    relabelled or left them out) whose own label fits at the rigid solution ``params``: within
    ``policy.outlier_sigmas`` of the spots' noise (at least ``policy.min_outlier_px``).

    Under free board poses a board seen by a few dots (a row of four) is placed as much by its
    spots as by its dots, and a spot of its own laser can look like another's; the box places
    that board from its other walls, so the decision is taken again with that evidence.
    Returns the ``(view name, spot index)`` of each spot restored and the problem with them."""
    n_d, n_s = int(cur.counts[Kind.DOT]), int(cur.counts[Kind.SPOT])
    if n_s and not cur.spot_src:
        return set(), cur  # no record of which input spot each row is
    index = {src: i for i, src in enumerate(cur.spot_src)}
    # boards placed by the box only: a pose of its own (outside the box, or with too few dots
    # to be placed) says nothing new about a spot on it
    pose_of = {key: k for k, key in enumerate(cur.pose_keys) if k not in left and k not in model.outside}
    labels = np.asarray(cur.spot_laser)[:n_s]
    cand = []  # (row of cur or None, view, spot index, pose, own label, pixel)
    for v, view in enumerate(obs.views):
        for j, s in enumerate(view.spots):
            if s.board is None or (v, s.board) not in pose_of or not 0 <= s.laser < obs.n_lasers:
                continue
            i = index.get((v, j))
            if i is None or labels[i] != s.laser:
                cand.append((i, v, j, pose_of[(v, s.board)], s.laser, np.asarray(s.pixel, float)))
    if not cand:
        return set(), cur
    pr = model.packed(cur)
    sig = sigmas_of(*per_observation(params, pr))[Kind.SPOT]
    limit = max(policy.outlier_sigmas * sig, policy.min_outlier_px) if np.isfinite(sig) else policy.min_outlier_px
    norm, ok = probe_at(
        params,
        pr,
        Kind.SPOT,
        spot_pose=np.asarray([c[3] for c in cand], np.int64),
        spot_laser=np.asarray([c[4] for c in cand], np.int64),
        spot_pixels=np.stack([c[5] for c in cand]),
    )
    fits = [c for c, good in zip(cand, ok & (norm <= limit), strict=True) if good]
    if not fits:
        return set(), cur
    own = labels.copy()
    for c in fits:
        if c[0] is not None:
            own[c[0]] = c[4]
    out = cur.select(np.ones(n_d, bool), np.ones(n_s, bool), own)
    back = [c for c in fits if c[0] is None]  # spots the free solve left out: appended
    if back:
        out = dataclasses.replace(
            out,
            spot_pose=np.concatenate([out.spot_pose, [c[3] for c in back]]).astype(np.int64),
            spot_laser=np.concatenate([out.spot_laser, [c[4] for c in back]]).astype(np.int64),
            spot_pixels=np.concatenate([out.spot_pixels, np.stack([c[5] for c in back])]),
            spot_src=tuple(out.spot_src) + tuple((c[1], c[2]) for c in back),
            counts=np.asarray(out.counts) + np.array([0, len(back), 0, 0]),
        )
    return {(obs.views[c[1]].name, c[2]) for c in fits}, out


def rigid_refine(res: CalibrationResult, obs: Observations, group: list[str]) -> CalibrationResult:
    """Pass R: the free solution ``res`` refined under the rigid box model
    (:mod:`slcvjax.calibration.rigid`) of the boards ``group``; a board pose whose dots' median
    residual exceeds ``misfit_sigmas`` noise sigmas (and ``misfit_min_px``, the result's
    :class:`slcvjax.calibration.options.RobustPolicy`) does not fit the box: its dots and spots
    are left out (recorded in the repairs) and R runs again.  Once no board misfits, the spots
    the free solve relabelled or left out are judged again at R's solution
    (:func:`_restore_spots`): those whose own label fits come back with it (their repairs
    dropped, ``box["spots_restored"]`` naming them) and R runs again.

    The result's board poses are the box's (every board pose of the box, the left-out ones
    included, at ``T_cam_box @ T_box_board``), its covariance the rig's block of the rigid
    model's, and ``box`` holds the boards' poses in the box with their std."""
    t0 = time.perf_counter()
    policy = res.options.robust
    pk = res.packed
    n_d = int(pk.counts[Kind.DOT])
    dots_per_pose = np.bincount(np.asarray(pk.dot_pose)[:n_d], minlength=pk.n_poses)
    model = box_model(pk, group, usable=np.flatnonzero(dots_per_pose >= policy.min_board_dots))
    params = rigid_params(model, pk.pose_keys, unstack_poses(res.params.poses), res.rig, res.params.chess)
    masks = rigid_masks(model, res.masks, pk.n_poses)
    passes, repairs = list(res.passes), list(res.repairs)
    left: list[int] = []
    cur = pk
    reexamined, restored_names, misfit_rounds = False, [], 0
    while True:
        pr = model.packed(cur)
        layout, p, arr, m = pad_problem(params, pr, masks)
        out = solve_compiled(p, arr, m, res.loss, res.scale, res.options.max_steps, RTOL_FINAL)
        params = unpad_params(layout, out.params)
        name = "R: rigid box" + (f" (after leaving out {len(left)} board pose(s))" if left else "")
        if restored_names:
            name += f" ({len(restored_names)} spot(s) back with their own labels)"
        passes.append(
            JointPass(
                name,
                int(out.steps),
                float(out.initial_cost),
                float(out.cost),
                float(res.scale),
                Outcome(int(out.result)),
            )
        )
        norm, kind, ok = per_observation(params, pr)
        n_d = int(cur.counts[Kind.DOT])
        pose_d = np.asarray(cur.dot_pose)[:n_d]
        dot_norm = np.where(ok[:n_d], norm[:n_d], np.inf)
        limit = max(policy.misfit_sigmas * robust_sigma_of(norm, kind, ok), policy.misfit_min_px)
        medians = {int(k): float(np.median(dot_norm[pose_d == k])) for k in np.unique(pose_d)}
        new = [k for k, m in medians.items() if m > limit and k not in model.outside]
        if not new and not reexamined:
            # the spots the free solve relabelled or left out, judged again under the box
            reexamined = True
            restored, cur_new = _restore_spots(params, model, cur, obs, left, policy)
            if restored:
                repairs = [r for r in repairs if not (r.kind == "spot" and (r.view, r.index) in restored)]
                restored_names += sorted(restored)
                cur = cur_new
                continue
        if not new or misfit_rounds == policy.misfit_rounds:
            break
        misfit_rounds += 1
        for k in new:
            v, b = pk.pose_keys[k]
            repairs.append(
                Repair(
                    kind="board",
                    view=obs.views[v].name,
                    index=-1,
                    board=b,
                    action="left out",
                    reason=f"does not fit the rigid box: its dots' median residual {medians[k]:.3g} px "
                    f"beyond {limit:.3g} px ({policy.misfit_sigmas:g} sigma, at least {policy.misfit_min_px:g} px)",
                    residual_px=medians[k],
                    whole_board=True,
                    stage="box",
                )
            )
        left += new
        n_s = int(cur.counts[Kind.SPOT])
        cur = cur.select(~np.isin(pose_d, left), ~np.isin(np.asarray(cur.spot_pose)[:n_s], left))
    # linearised again at the solution: the rim rows normalised there, as the free covariance is
    layout, lin, parts = kind_linearisations(params, model.packed(cur), masks, res.loss, res.scale)
    pooled = covariance_compiled(lin, pad_masks(layout, masks), None)
    pooled = unpad_covariance(layout, pooled)
    # the rig's covariance with each kind's own noise; the boards' poses (in the box and per
    # view, which need the box's cross covariances) with the pooled sigma
    cov, noise = sandwich_of(layout, lin, parts, masks)
    pose_cov = board_pose_covariances(model, params, lin, masks, pooled, layout)
    g = res.rig.tangent_dim
    glob = np.asarray(pooled.glob)
    cov_out = Covariance(
        np.asarray(cov.glob)[:g, :g],
        np.concatenate([pose_cov, np.asarray(pooled.blocks)[model.n_blocks :]]),
        cov.sigma,
        cov.dof,
    )
    out_params = Params(params.rig, board_poses_of(model, params), params.chess)
    std = box_pose_std(params, glob, model)
    box_poses = {model.gauge: Pose(np.eye(3), np.zeros(3))} | {
        b: Pose(np.asarray(params.box.R)[i], np.asarray(params.box.t)[i]) for i, b in enumerate(model.boards)
    }
    box = {
        "gauge": model.gauge,
        "boards": {b: {"pose": box_poses[b], **std[b]} for b in (model.gauge, *model.boards)},
        "views": len(model.views),
        "free_board_poses": len(model.outside),
        "left_out": [{"view": obs.views[pk.pose_keys[k][0]].name, "board": pk.pose_keys[k][1]} for k in left],
        "spots_restored": [{"view": v, "index": j} for v, j in restored_names],
        "notes": list(model.notes),
    }
    timings = dict(res.timings)
    timings["rigid_s"] = time.perf_counter() - t0
    timings["total_s"] = timings.get("total_s", 0.0) + timings["rigid_s"]
    return dataclasses.replace(
        res,
        params=out_params,
        packed=cur,
        cov=cov_out,
        passes=tuple(passes),
        repairs=tuple(repairs),
        timings=timings,
        kind_sigma=dict(zip(KIND_NAMES, noise.sigma.tolist(), strict=False)),
        box=box,
    )
