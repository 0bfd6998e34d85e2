"""Other starts for the board poses: each pose's flipped twin and its pose carried over from
another view, refined with the rig held and swapped in where they fit better.  A planar board
seen through a convex mirror has two poses that fit its dots nearly equally (the flip); a wrong
one is found by its fit once the rig is right."""

import numpy as np

from ..geometry.pose import Pose
from ..observations.problem import Packed
from .evaluate import block_costs_at
from .params import Masks, Params
from .staged import flipped
from .trial import Trial


def twin_poses(params: Params, arr: Packed, masks: Masks) -> tuple[Params, Masks]:
    """Every board pose's flipped twin, and the masks that refine the twins with the rig held."""
    R, t = np.asarray(params.poses.R), np.asarray(params.poses.t)
    n_p = R.shape[0]
    xb = np.zeros((n_p, 1, 3))
    dp, pts = np.asarray(arr.dot_pose), np.asarray(arr.dot_points)
    for k in range(n_p):
        if np.any(dp == k):
            xb[k, 0] = pts[dp == k].mean(axis=0)
    R2, t2 = flipped(R, t, xb, np.ones((n_p, 1)))
    twin = Params(params.rig, Pose(R2, t2), params.chess)
    return twin, _hold_rig(params, masks)


def carried_poses(params: Params, pk: Packed, masks: Masks) -> tuple[Params, Masks]:
    """Every board pose carried over rigidly from another view, and the masks that refine them.

    Pose ``(v, b)`` becomes ``T_a(v) T_a(v0)^-1 T_b(v0)``: board ``a`` of view ``v`` and
    view ``v0 != v`` chosen so that the fewest dots of ``a`` in ``v`` and of ``a`` and
    ``b`` in ``v0`` is largest.  Poses with no such pair are kept.
    """
    R, t = np.asarray(params.poses.R), np.asarray(params.poses.t)
    keys = pk.pose_keys
    n_p = len(keys)
    n_dots = np.bincount(np.asarray(pk.dot_pose), minlength=n_p)
    by_view: dict[int, dict[str, int]] = {}
    for k, (v, b) in enumerate(keys):
        by_view.setdefault(v, {})[b] = k
    R2, t2 = R.copy(), t.copy()
    for k, (v, b) in enumerate(keys):
        # the neighbour seen by the most dots, and the other view where it and b are best seen
        best = (0, -1, -1, -1)  # (fewer dots of the pair in view v0, pose a in v, a in v0, b in v0)
        for a, ka in by_view[v].items():
            if a == b:
                continue
            for v0, boards in by_view.items():
                if v0 != v and a in boards and b in boards:
                    m = min(n_dots[ka], n_dots[boards[a]], n_dots[boards[b]])
                    if m > best[0]:
                        best = (m, ka, boards[a], boards[b])
        _, ka, ka0, kb0 = best
        if ka >= 0:  # T_b(v) = T_a(v) T_a(v0)^-1 T_b(v0)
            r_ab = R[ka0].T @ R[kb0]
            t_ab = R[ka0].T @ (t[kb0] - t[ka0])
            R2[k], t2[k] = R[ka] @ r_ab, R[ka] @ t_ab + t[ka]
    carried = Params(params.rig, Pose(R2, t2), params.chess)
    return carried, _hold_rig(params, masks)


def misfit_boards(tr: "Trial", loss: str) -> int:
    """How many board poses of a calibration fit badly: a mean robust cost per dot and spot
    above ``scale^2`` (with the Huber loss, a pixel error of 1.5 scales = 4.5 sigma on average;
    a fitting one costs about ``sigma^2 = scale^2 / 9``)."""
    n_p = tr.pk.n_poses
    cost = block_costs_at(tr.params, tr.pk, loss, tr.scale)[:n_p]
    n = np.bincount(np.asarray(tr.pk.dot_pose), minlength=n_p) + np.bincount(np.asarray(tr.pk.spot_pose), minlength=n_p)
    return int(np.sum(cost > tr.scale**2 * np.maximum(n, 1)))


def _hold_rig(params: Params, masks: Masks) -> Masks:
    """Masks that refine the board poses alone."""
    n_p = params.poses.t.shape[0]
    blocks = np.asarray(masks.blocks)
    return Masks(
        np.zeros_like(np.asarray(masks.glob)), np.concatenate([blocks[:n_p], np.zeros(params.chess.t.shape[0])])
    )


def other_starts_of(params: Params, pk: Packed, masks: Masks) -> list[tuple[Params, Masks]]:
    """Other starts for every board pose, each with its masks: the flipped twin, the carried pose."""
    return [twin_poses(params, pk, masks), carried_poses(params, pk, masks)]


def keep_better(
    params: Params, other: Params, pk: Packed, loss: str, scale: float, turned_only: bool = False
) -> tuple[Params, int]:
    """``params`` with each board pose whose refined other start fits better swapped (``turned_only``:
    only those turned by it); how many turned."""
    n_p = params.poses.t.shape[0]
    c_now = block_costs_at(params, pk, loss, scale)[:n_p]
    c_other = block_costs_at(other, pk, loss, scale)[:n_p]
    better = c_other < c_now - 1e-9
    if turned_only:
        better &= turned(other.poses, params.poses)
    if not better.any():
        return params, 0
    poses = Pose(
        np.where(better[:, None, None], np.asarray(other.poses.R), np.asarray(params.poses.R)),
        np.where(better[:, None], np.asarray(other.poses.t), np.asarray(params.poses.t)),
    )
    return Params(params.rig, poses, params.chess), int(np.sum(better & turned(other.poses, params.poses)))


def turned(a: Pose, b: Pose, degrees: float = 10.0) -> np.ndarray:
    """Per stacked pose: whether the board normals of ``a`` and ``b`` differ by more than ``degrees``."""
    cos = np.sum(np.asarray(a.R)[:, :, 2] * np.asarray(b.R)[:, :, 2], axis=1)
    return cos < np.cos(np.radians(degrees))
