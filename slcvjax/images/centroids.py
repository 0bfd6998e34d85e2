"""Detected centroids corrected for the mirror's distortion of each dot's and spot's image.

Through the cone a printed dot's image is squeezed and bent: the centroid a detector
measures is not the image of the dot's centre, by up to about half a pixel on the squeezed
rows near the apex. The same holds for a laser spot's Gaussian profile. With a calibration at
hand the offset of every centroid is predicted (:func:`slcvjax.measurement.measure.disk_image_offset`,
:func:`slcvjax.measurement.measure.spot_image_offset`: each image integrated through the calibrated mirror) and
subtracted from the detected pixel; calibrating again from the corrected pixels removes the
bias to first order (:func:`calibrate_detected`). The sizes come from the detection's
``setup.json``: each board's ``dot_radius_mm`` and the lasers' ``spot_sigma_mm``.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ..geometry.lasers import line_plane_intersection
from ..geometry.mirror import project_through_mirror
from ..geometry.pose import Pose
from ..geometry.rig import Rig
from ..measurement.measure import disk_image_offset, spot_image_offsets
from ..observations.formats import Observations
from ..observations.problem import map_padded, map_rows
from ..support.persist import PersistentJit


def _disk_offsets(rig: Rig, rows):
    """(n, 2) :func:`disk_image_offset` of rows ``[x (3), e1 (3), e2 (3), radius_mm]``."""
    return jax.vmap(lambda r: disk_image_offset(rig, r[:3], r[3:6], r[6:9], r[9]))(rows)


_disk_offsets_jit = PersistentJit(map_rows(_disk_offsets), "disk_image_offsets")


def _project_posed(rig: Rig, rows):
    """Pixels and validity of rows ``[R (9, row-major), t (3), board point (3)]`` seen through the mirror."""

    def one(r):
        x = r[:9].reshape(3, 3) @ r[12:15] + r[9:12]
        res = project_through_mirror(rig.camera, rig.mirror, x)
        return res.uv, res.valid

    return jax.vmap(one)(rows)


_project_posed_jit = PersistentJit(map_rows(_project_posed), "project_posed_points")


CENTROIDS_NOTE = "centroids corrected"  # how calibrate_detected's note on the correction begins


def detection_sizes(obs: Observations) -> tuple[dict[str, float], float | None]:
    """The dots' radius per board and the spots' std (mm) that the detection recorded (from
    ``setup.json``); empty and None where it did not."""
    det = obs.extra.get("detection") or {}
    radii = {k: float(v) for k, v in (det.get("dot_radius_mm") or {}).items() if v is not None}
    sigma = det.get("spot_sigma_mm")
    return radii, (None if sigma is None else float(sigma))


def corrected_observations(
    rig: Rig,
    board_poses: list[dict[str, Pose]],
    obs: Observations,
    dot_radius_mm: dict[str, float],
    spot_sigma_mm: float | None,
) -> tuple[Observations, dict]:
    """``obs`` with each dot's pixel (boards with a radius) and each board spot's pixel (with a
    spot std) moved by minus its predicted centroid offset, at the calibration ``rig`` and its
    ``board_poses`` (per view, per board: ``T_cam_board``). Points without a pose, or whose
    offset cannot be computed (their image leaves the mirror), keep their pixel. Returns the
    observations and counts with the RMS offset (px). A spot that names no board is taken on the
    first board plane its reflected ray meets, as the calibration takes it
    (:func:`slcvjax.calibration.staged.assign_spot_boards`)."""
    planes = obs
    if spot_sigma_mm is not None and any(s.board is None for v in obs.views for s in v.spots):
        from ..calibration.staged import assign_spot_boards

        planes, _ = assign_spot_boards(obs, rig.camera, rig.mirror, board_poses)
    dot_rows, dot_at, spot_x, spot_n, spot_at = [], [], [], [], []
    for v, view in enumerate(obs.views):
        poses = board_poses[v] if v < len(board_poses) else {}
        for b, (_, seen) in view.boards.items():
            if b not in poses or b not in dot_radius_mm or not seen.any():
                continue
            R, t = np.asarray(poses[b].R), np.asarray(poses[b].t)
            pts = np.asarray(obs.boards[b], float)[seen]
            x = pts @ R.T + t
            k = len(x)
            dot_rows.append(np.column_stack([x, np.tile(R[:, 0], (k, 1)), np.tile(R[:, 1], (k, 1)),
                                             np.full(k, dot_radius_mm[b])]))  # fmt: skip
            dot_at.extend((v, b, int(i)) for i in np.flatnonzero(seen))
        if spot_sigma_mm is None:
            continue
        for j, s in enumerate(planes.views[v].spots):
            if s.board is None or s.board not in poses:
                continue
            x, ok = line_plane_intersection(rig.lasers.points[s.laser], rig.lasers.directions[s.laser], poses[s.board],
                                            forward_only=False)  # fmt: skip
            if bool(ok):
                spot_x.append(np.asarray(x))
                spot_n.append(np.asarray(poses[s.board].R)[:, 2])
                spot_at.append((v, j))
    views = [dataclasses.replace(vw, boards={b: (px.copy(), seen) for b, (px, seen) in vw.boards.items()},
                                 spots=list(vw.spots)) for vw in obs.views]  # fmt: skip
    moved = []
    if dot_rows:
        off = np.asarray(map_padded(_disk_offsets_jit, rig, rows=np.concatenate(dot_rows)))
        for (v, b, i), o in zip(dot_at, off, strict=True):
            if np.all(np.isfinite(o)):
                views[v].boards[b][0][i] -= o
                moved.append(o)
    n_dots = len(moved)
    if spot_x:
        off = spot_image_offsets(rig, np.stack(spot_x), np.stack(spot_n), spot_sigma_mm)
        for (v, j), o in zip(spot_at, off, strict=True):
            if np.all(np.isfinite(o)):
                s = views[v].spots[j]
                views[v].spots[j] = dataclasses.replace(s, pixel=np.asarray(s.pixel, float) - o)
                moved.append(o)
    moved = np.asarray(moved).reshape(-1, 2)
    info = {
        "dots": n_dots,
        "spots": len(moved) - n_dots,
        "rms_offset_px": float(np.sqrt(np.mean(np.sum(moved**2, axis=1)))) if len(moved) else 0.0,
    }
    return dataclasses.replace(obs, views=views), info


def _mean_pose(poses: list[Pose]) -> Pose:
    """The rotation nearest the mean of the rotations (SVD), the mean translation."""
    m = np.sum([np.asarray(p.R) for p in poses], axis=0)
    u, _, vt = np.linalg.svd(m)
    r = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return Pose(jnp.asarray(r), jnp.asarray(np.mean([np.asarray(p.t) for p in poses], axis=0)))


def resolve_ambiguous_boards(
    rig: Rig, board_poses: list[dict[str, Pose]], obs: Observations, ratio: float = 0.3, max_px: float = 5.0
) -> tuple[Observations, list[str]]:
    """Place the targets the detector left out (it could not tell which dot is which), by the
    box's rigidity.

    For a target of the ``rigid_boards`` group seen in view ``v`` with candidate placements
    (``extra["detection"]["ambiguous_boards"]``), each other target of the group with a pose in
    ``v`` predicts its pose: ``T_cam_k(v)`` times the relative pose of the two targets, averaged
    over the views where both have one. A candidate's misfit is the largest distance between
    its dots and their projections at the predicted pose (infinite where one would not be seen);
    the candidate with the smallest (median over the predicting targets) is placed when it is
    within ``max_px`` and below ``ratio`` times the next candidate's; otherwise the target stays
    out.
    Returns the observations and one line per ambiguous target saying what was decided."""
    rigid = list(obs.extra.get("rigid_boards") or [])
    amb = (obs.extra.get("detection") or {}).get("ambiguous_boards") or []
    views = [dataclasses.replace(vw, boards=dict(vw.boards)) for vw in obs.views]
    lines = []
    for entry in amb:
        v, b = int(entry["view"]), str(entry["board"])
        name = obs.views[v].name if v < len(obs.views) else f"view {v}"
        if b not in rigid:
            lines.append(f"{name}: {b}: not in a rigid group, left out")
            continue
        if len(entry["candidates"][0]["indices"]) < 4:
            lines.append(f"{name}: {b}: fewer than 4 dots, too few for a pose, left out")
            continue
        scores = []
        for k in rigid:
            if k == b or k not in board_poses[v]:
                continue
            both = [u for u, bp in enumerate(board_poses) if u != v and k in bp and b in bp]
            rel = [board_poses[u][k].inverse() @ board_poses[u][b] for u in both]
            if not rel:
                continue
            pred = board_poses[v][k] @ _mean_pose(rel)
            pose_row = np.concatenate([np.asarray(pred.R).ravel(), np.asarray(pred.t)])
            pts = [np.asarray(obs.boards[b], float)[np.asarray(c["indices"], int)] for c in entry["candidates"]]
            rows = np.concatenate([np.column_stack([np.tile(pose_row, (len(q), 1)), q]) for q in pts])
            uv, ok = (np.asarray(x) for x in map_padded(_project_posed_jit, rig, rows=rows))
            per, at = [], 0
            for c, q in zip(entry["candidates"], pts, strict=True):
                d = np.linalg.norm(uv[at : at + len(q)] - np.asarray(c["pixels"], float), axis=1)
                per.append(float(np.max(d)) if np.all(ok[at : at + len(q)]) else np.inf)
                at += len(q)
            scores.append(per)
        if not scores:
            lines.append(f"{name}: {b}: no other target of its box has a pose in this view, left out")
            continue
        med = np.median(np.asarray(scores), axis=0)
        order = np.argsort(med)
        best, second = med[order[0]], med[order[1]]
        if best <= max_px and best < ratio * second:
            c = entry["candidates"][int(order[0])]
            n = len(obs.boards[b])
            px, seen = np.zeros((n, 2)), np.zeros(n, bool)
            px[c["indices"]], seen[c["indices"]] = np.asarray(c["pixels"], float), True
            views[v].boards[b] = (px, seen)
            lines.append(f"{name}: {b}: placed by the box ({best:.2f} px, the next placement {second:.2f} px)")
        else:
            lines.append(f"{name}: {b}: the box cannot tell ({best:.2f} px against {second:.2f} px), left out")
    return dataclasses.replace(obs, views=views), lines


def calibrate_detected(obs: Observations, correct_centroids: bool = True, **kwargs):
    """:func:`slcvjax.calibration.calibrate.calibrate` of detected observations, then again with the targets the
    detector left out for ambiguous rows placed by the box's rigidity
    (:func:`resolve_ambiguous_boards`) when any is, and (``correct_centroids``) from the
    centroids corrected at the calibration (:func:`corrected_observations`) when the detection
    recorded the dots' or spots' sizes: the centroids as detected hold the mirror's offsets
    (0.045 px per axis RMS in noise-free images of the preset), which a calibration from them
    keeps in its lasers but not in its std. Observations that are not a detection's (no sizes
    recorded) are calibrated once. Returns the result, the observations it was made from, and a
    list of what was decided."""
    from ..calibration.calibrate import calibrate
    from ..calibration.report import to_calibration

    res = calibrate(obs, **kwargs)
    used, notes = obs, []
    if (obs.extra.get("detection") or {}).get("ambiguous_boards") and obs.extra.get("rigid_boards"):
        used, notes = resolve_ambiguous_boards(res.rig, to_calibration(res, obs).board_poses, obs)
        if any("placed by the box" in n for n in notes):
            res = calibrate(used, **kwargs)
    radii, sigma = detection_sizes(obs)
    if correct_centroids and (radii or sigma is not None):
        used, info = corrected_observations(res.rig, to_calibration(res, used).board_poses, used, radii, sigma)
        notes.append(
            f"{CENTROIDS_NOTE}: {info['dots']} dots, {info['spots']} spots, {info['rms_offset_px']:.3f} px RMS"
        )
        res = calibrate(used, **kwargs)
    return res, used, notes
