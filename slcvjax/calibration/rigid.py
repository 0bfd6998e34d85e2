"""The rigid target box as a model: one pose per board in the box, one sensor pose per view.

The paper's targets stand still in one box while the sensor moves.  Where the observations
declare such a group (``"rigid_boards": ["wall0", ...]``), each board pose of the box is

    T_cam_board(v, b) = T_cam_box(v) @ T_box_board(b),

with the box's frame that of its *gauge* board (the one seen in the most views:
``T_box_board = I``, no unknowns, so that the normal equations stay regular).  The unknowns
are then the rig, ``T_box_board`` of every other board of the box (6 global parameters
each) and one ``T_cam_box`` per view (a pose block: the Schur elimination still runs over
the views), instead of a free pose per board and view.  Boards outside the group, or not
linked to the gauge through the views, keep their free pose per view.

A board pose that does not fit the box (a grid labelled one row off, a target that moved)
no longer vanishes into a free pose: after the rigid solve its dots' median residual stands
out, it is left out (dots and spots), reported in the repairs, and the solve runs again.
The spots the free solve relabelled or left out are judged again at the box's geometry (under a
free pose a board seen by a row of a few dots is placed by its spots as much as by its dots, so
their labels were weakly tested there): each whose own label fits comes back with it.
"""

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..geometry.pose import Pose
from ..observations.formats import Observations
from ..observations.problem import Layout, Packed, bucket, stack_poses
from .base import CalibrationError
from .covariance import Covariance
from .params import Masks, Params, pad_masks
from .schur import schur_inverse


@dataclass(frozen=True)
class BoxModel:
    """Which unknowns each board pose of a packed problem is made of (see the module docstring).

    Attributes:
        gauge: the board whose frame is the box's.
        boards: the box's other boards, in the order of ``Params.box``.
        views: the view of each view pose block (the first ``len(views)`` pose blocks).
        outside: the board poses (indices into ``Packed.pose_keys``) that keep their own pose
            block (after the view blocks).
        pair_block, pair_box: per board pose, its pose block and its box board (an index into
            ``boards``, or ``n_box`` for the gauge and the boards outside: the identity).
        n_box: the box poses' padded count (:func:`slcvjax.observations.problem.bucket`).
        notes: boards of the group that could not be linked to the gauge.
    """

    gauge: str
    boards: tuple[str, ...]
    views: tuple[int, ...]
    outside: tuple[int, ...]
    pair_block: np.ndarray
    pair_box: np.ndarray
    n_box: int
    notes: tuple[str, ...]

    @property
    def n_blocks(self) -> int:
        return len(self.views) + len(self.outside)

    def packed(self, pk: Packed) -> Packed:
        """``pk`` with its board poses mapped onto this model's unknowns."""
        return dataclasses.replace(pk, pair_block=self.pair_block, pair_box=self.pair_box)


def box_model(pk: Packed, group, usable=None) -> BoxModel:
    """The rigid box model of ``pk``'s board poses for the board names ``group`` (known boards:
    ``slcvjax.calibration.rigid.rigid_group`` checks the names).

    ``usable``: the board poses (indices into ``pose_keys``) with observations to place them
    (by default all); the others keep their own pose block, which nothing moves.
    """
    group = list(group)
    all_keys = pk.pose_keys
    use = set(range(len(all_keys))) if usable is None else set(usable)
    keys = [k for i, k in enumerate(all_keys) if i in use]
    posed = [b for b in group if any(kb == b for _, kb in keys)]
    if not posed:
        raise ValueError(f"rigid_boards: none of {', '.join(group) or '(none)'} has a pose in any view")
    seen_in = {b: {v for v, kb in keys if kb == b} for b in posed}
    gauge = max(posed, key=lambda b: (len(seen_in[b]), -posed.index(b)))
    # the boards linked to the gauge through views that see two of them
    linked, grow = {gauge}, True
    while grow:
        views = set().union(*(seen_in[b] for b in linked))
        new = {b for b in posed if b not in linked and seen_in[b] & views}
        grow = bool(new)
        linked |= new
    notes = tuple(
        f"{b}: seen in no view with a board linked to the gauge {gauge}: its poses stay free per view"
        for b in posed
        if b not in linked
    )
    boards = tuple(b for b in posed if b in linked and b != gauge)
    views = tuple(sorted({v for v, b in keys if b in linked}))
    view_block = {v: i for i, v in enumerate(views)}
    n_box = bucket(len(boards)) if boards else 0
    pair_block, pair_box, outside = [], [], []
    for k, (v, b) in enumerate(all_keys):
        if b in linked and k in use:
            pair_block.append(view_block[v])
            pair_box.append(boards.index(b) if b != gauge else n_box)
        else:
            pair_block.append(len(views) + len(outside))
            pair_box.append(n_box)
            outside.append(k)
    return BoxModel(
        gauge,
        boards,
        views,
        tuple(outside),
        np.asarray(pair_block, np.int64),
        np.asarray(pair_box, np.int64),
        n_box,
        notes,
    )


def _distance(a: Pose, b: Pose) -> float:
    """A pose distance (mm): translation apart plus 100 mm per radian of rotation apart."""
    c = np.clip((np.trace(np.asarray(a.R).T @ np.asarray(b.R)) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.linalg.norm(np.asarray(a.t) - np.asarray(b.t)) + 100.0 * np.arccos(c))


def _medoid(candidates: list[Pose]) -> Pose:
    """The candidate with the smallest median distance to the others (robust to a wrong one)."""
    if len(candidates) <= 2:
        return candidates[0]
    d = [np.median([_distance(a, b) for b in candidates]) for a in candidates]
    return candidates[int(np.argmin(d))]


def _host(p: Pose) -> Pose:
    return Pose(np.asarray(p.R, float), np.asarray(p.t, float))


def box_start(model: BoxModel, keys, poses: list[Pose]) -> tuple[dict[int, Pose], dict[str, Pose]]:
    """``T_cam_box`` per view and ``T_box_board`` per box board from free board poses
    (``poses[k]`` of ``keys[k]``), each the medoid of what the views and boards linked to it
    say (a board pose wrong in one view does not spread)."""
    in_box = set(model.boards) | {model.gauge}
    outside = set(model.outside)
    pairs = {(v, b): _host(poses[k]) for k, (v, b) in enumerate(keys) if b in in_box and k not in outside}
    box: dict[str, Pose] = {model.gauge: Pose(np.eye(3), np.zeros(3))}
    cams: dict[int, Pose] = {}

    def cam_of(v):
        c = [pairs[(v, b)] @ box[b].inverse() for b in box if (v, b) in pairs]
        return _host(_medoid(c)) if c else None

    def board_of(b):
        c = [cams[v].inverse() @ pairs[(v, b)] for v in cams if (v, b) in pairs]
        return _host(_medoid(c)) if c else None

    while len(cams) < len(model.views) or len(box) < len(in_box):
        grew = False
        for v in model.views:
            if v not in cams and (p := cam_of(v)) is not None:
                cams[v], grew = p, True
        for b in model.boards:
            if b not in box and (p := board_of(b)) is not None:
                box[b], grew = p, True
        if not grew:
            raise ValueError("rigid box: a view or board is not linked to the gauge")  # box_model links them all
    # once every unknown has a start, each again from all that is linked to it
    for b in model.boards:
        box[b] = board_of(b)
    for v in model.views:
        cams[v] = cam_of(v)
    return cams, box


def rigid_params(model: BoxModel, keys, poses: list[Pose], rig, chess: Pose) -> Params:
    """The rigid model's :class:`slcvjax.calibration.params.Params` started from free board poses
    (:func:`box_start`)."""
    cams, box = box_start(model, keys, poses)
    blocks = [cams[v] for v in model.views] + [_host(poses[k]) for k in model.outside]
    box_list = [box[b] for b in model.boards] + [Pose(np.eye(3), np.zeros(3))] * (model.n_box - len(model.boards))
    box_stack = stack_poses(box_list) if box_list else Pose(np.zeros((0, 3, 3)), np.zeros((0, 3)))
    return Params(rig, stack_poses(blocks), chess, box_stack)


def rigid_masks(model: BoxModel, free: Masks, n_pairs: int) -> Masks:
    """The rigid model's masks from the free model's: the box poses estimated where the board
    poses were, a view block where any of its board poses was."""
    pair_mask = np.asarray(free.blocks)[:n_pairs]
    est = float(pair_mask.max(initial=0.0))
    box = np.zeros(6 * model.n_box)
    box[: 6 * len(model.boards)] = est
    blocks = np.zeros(model.n_blocks)
    for k in range(n_pairs):
        blocks[model.pair_block[k]] = max(blocks[model.pair_block[k]], pair_mask[k])
    return Masks(
        np.concatenate([np.asarray(free.glob, float), box]),
        np.concatenate([blocks, np.asarray(free.blocks, float)[n_pairs:]]),
    )


def board_poses_of(model: BoxModel, params: Params) -> Pose:
    """Every board pose (in ``pose_keys``' order) of the rigid model's ``params``."""
    R, t = np.asarray(params.poses.R), np.asarray(params.poses.t)
    n_box = params.n_box
    bR = np.concatenate([np.asarray(params.box.R), np.eye(3)[None]]) if n_box else np.eye(3)[None]
    bt = np.concatenate([np.asarray(params.box.t), np.zeros((1, 3))]) if n_box else np.zeros((1, 3))
    k, b = model.pair_block, np.minimum(model.pair_box, n_box)
    return Pose(R[k] @ bR[b], np.einsum("kij,kj->ki", R[k], bt[b]) + t[k])


def _skew(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def board_pose_covariances(model: BoxModel, params: Params, lin, masks: Masks, cov: Covariance, layout: Layout):
    """Each board pose's 6x6 covariance (its tangent, as :meth:`Pose.retract`'s) in the rigid
    model: from its view's block, its box pose and their cross covariance.

    ``T = T_v exp(d_v) @ T_b exp(d_b)`` moves to first order by ``w = w_v + R_v w_b`` and
    ``dt = dt_v - [R_v t_b]x w_v + R_v dt_b``.
    """
    s2 = float(cov.sigma) ** 2
    Sinv, _, Dinv_Bt = (np.asarray(x) for x in schur_inverse(lin.normal))
    Sinv, Dinv_Bt = layout.unpad_glob(Sinv, (0, 1)), layout.unpad_glob(Dinv_Bt, (2,))  # the real lasers' columns
    g_rig = params.rig.tangent_dim
    pmask = np.asarray(pad_masks(layout, masks).blocks) * np.asarray(lin.seen_blocks)
    gmask = np.asarray(masks.glob) * layout.unpad_glob(lin.seen_glob)
    blocks_cov = np.asarray(cov.blocks)  # real blocks (unpadded): view blocks, outside, chess
    R, bt = np.asarray(params.poses.R), np.asarray(params.box.t) if params.n_box else None
    out = np.zeros((model.pair_block.size, 6, 6))
    for k, (blk, bx) in enumerate(zip(model.pair_block, model.pair_box, strict=True)):
        Cvv = blocks_cov[blk]
        if bx >= params.n_box:
            out[k] = Cvv
            continue
        cols = slice(g_rig + 6 * bx, g_rig + 6 * bx + 6)
        m = gmask[cols]
        Cbb = s2 * Sinv[cols, cols] * m[:, None] * m[None, :]
        Cvb = -s2 * (Dinv_Bt[blk] @ Sinv[:, cols]) * pmask[blk] * m[None, :]
        Rv = R[blk]
        Jv = np.eye(6)
        Jv[3:, :3] = -_skew(Rv @ bt[bx])
        Jb = np.zeros((6, 6))
        Jb[:3, :3] = Jb[3:, 3:] = Rv
        cross = Jv @ Cvb @ Jb.T
        out[k] = Jv @ Cvv @ Jv.T + Jb @ Cbb @ Jb.T + cross + cross.T
    return out


def box_pose_std(params: Params, cov_glob: np.ndarray, model: BoxModel) -> dict[str, dict]:
    """Per box board (the gauge's are zero): its rotation std (deg) and translation std (mm) in the box frame."""
    g_rig = params.rig.tangent_dim
    out = {model.gauge: {"rotation_deg": [0.0] * 3, "translation_mm": [0.0] * 3}}
    var = np.diag(cov_glob)
    for i, b in enumerate(model.boards):
        v = var[g_rig + 6 * i : g_rig + 6 * i + 6]
        sd = np.sqrt(np.where(v > 0, v, np.nan))
        out[b] = {"rotation_deg": np.degrees(sd[:3]).tolist(), "translation_mm": sd[3:].tolist()}
    return out


def rigid_group(obs: Observations, rigid: "bool | list[str]") -> list[str]:
    """The board names of the rigid box model for ``calibrate(rigid=...)``: none where ``rigid``
    is False, the observations' ``rigid_boards`` where True, else ``rigid`` itself."""
    if rigid is False or rigid is None:
        return []
    if rigid is True:
        group = list(obs.extra.get("rigid_boards") or [])
        if not group:
            raise CalibrationError(
                "rigid: the observations declare no rigid_boards (name the boards fixed in one box, "
                'e.g. "rigid_boards": ["wall0", "wall1"], or pass their names)'
            )
    else:
        group = list(rigid)
    for i, b in enumerate(group):
        if b not in obs.boards:
            raise CalibrationError(f"rigid_boards[{i}]: unknown board {b!r} (known: {', '.join(sorted(obs.boards))})")
    return group
