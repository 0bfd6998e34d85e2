"""Observations packed into flat arrays, and the vectorised residuals of the forward model.

A :class:`Packed` problem lists every observation once with the index of the pose it
depends on, so the residuals of any number of views, boards and lasers are one
``vmap`` (no Python loop in the traced graph, one compilation per problem size).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ._io import Observations
from ._lasers import line_plane_intersection
from ._mirror import project_through_mirror
from ._pose import Pose
from ._rig import Rig


class Packed(eqx.Module):
    """Flat observation arrays of a calibration.

    Attributes:
        dot_pose: (D,) index into the board poses of each dot seen through the mirror.
        dot_points: (D, 3) the dot in its board's frame.
        dot_pixels: (D, 2) its observed pixel.
        spot_pose: (S,) board pose index of each spot's plane.
        spot_laser: (S,) laser index of each spot.
        spot_pixels: (S, 2) observed pixels.
        rim_pixels: (R, 2) rim edge pixels of all views (the mirror is fixed to the camera).
        chess_pose: (C,) index into the direct-view poses of each chessboard corner.
        chess_points: (C, 3) the corner in its board's frame.
        chess_pixels: (C, 2) its observed pixel.
        pose_keys: ``(view index, board name)`` of each board pose (static).
        chess_keys: index of the calibration view of each direct-view pose (static).
    """

    dot_pose: Int[Array, " D"]
    dot_points: Float[Array, "D 3"]
    dot_pixels: Float[Array, "D 2"]
    spot_pose: Int[Array, " S"]
    spot_laser: Int[Array, " S"]
    spot_pixels: Float[Array, "S 2"]
    rim_pixels: Float[Array, "R 2"]
    chess_pose: Int[Array, " C"]
    chess_points: Float[Array, "C 3"]
    chess_pixels: Float[Array, "C 2"]
    pose_keys: tuple = eqx.field(static=True)
    chess_keys: tuple = eqx.field(static=True)

    @property
    def n_poses(self) -> int:
        return len(self.pose_keys)

    @property
    def n_chess(self) -> int:
        return len(self.chess_keys)


def pack(obs: Observations, use_views: bool = True, use_direct: bool = True) -> Packed:
    """Pack ``obs``: a board pose per (view, board) seen, a pose per direct view with corners."""
    keys: list[tuple[int, str]] = []
    index: dict[tuple[int, str], int] = {}

    def key(vi, b):
        if (vi, b) not in index:
            index[(vi, b)] = len(keys)
            keys.append((vi, b))
        return index[(vi, b)]

    dp, dpts, dpx, sp, sl, spx, rim = [], [], [], [], [], [], []
    for vi, v in enumerate(obs.views if use_views else []):
        for b, (px, seen) in v.boards.items():
            if not seen.any():
                continue
            k = key(vi, b)
            dp.extend([k] * int(seen.sum()))
            dpts.append(obs.boards[b][seen])
            dpx.append(px[seen])
        for s in v.spots:
            if s.board is None or (vi, s.board) not in index:
                continue  # no plane for it: no board, or a board with no dots (so no pose) in this view
            sp.append(key(vi, s.board))
            sl.append(s.laser)
            spx.append(s.pixel)
        rim.append(np.asarray(v.rim, float).reshape(-1, 2))
    cp, cpts, cpx, ckeys = [], [], [], []
    for ci, cv in enumerate(obs.calibration_views if use_direct else []):
        if not cv.seen.any():
            continue
        cp.extend([len(ckeys)] * int(cv.seen.sum()))
        ckeys.append(ci)
        cpts.append(obs.boards[cv.board][cv.seen])
        cpx.append(cv.pixels[cv.seen])

    def cat(parts, width):
        return jnp.asarray(np.concatenate(parts) if parts else np.zeros((0, width)))

    return Packed(
        jnp.asarray(np.array(dp, dtype=np.int64)),
        cat(dpts, 3),
        cat(dpx, 2),
        jnp.asarray(np.array(sp, dtype=np.int64)),
        jnp.asarray(np.array(sl, dtype=np.int64)),
        jnp.asarray(np.array(spx, dtype=float).reshape(-1, 2)),
        cat(rim, 2),
        jnp.asarray(np.array(cp, dtype=np.int64)),
        cat(cpts, 3),
        cat(cpx, 2),
        tuple(keys),
        tuple(ckeys),
    )


def stack_poses(poses: list[Pose]) -> Pose:
    """A list of poses as one :class:`Pose` with leading axis (P, ...), stacked on the host.

    Host code only (not under ``jit``): one copy to the device instead of one operation per pose.
    """
    return Pose(
        jnp.asarray(np.stack([np.asarray(p.R) for p in poses])), jnp.asarray(np.stack([np.asarray(p.t) for p in poses]))
    )


def unstack_poses(poses: Pose) -> list[Pose]:
    """Stacked poses (P, ...) as a list of P poses, copied to the host once (numpy fields).

    Indexing a device array pose by pose costs a dispatch each; host code that loops
    over the poses reads them from this list instead.
    """
    R, t = np.asarray(poses.R), np.asarray(poses.t)
    return [Pose(R[k], t[k]) for k in range(R.shape[0])]


def dot_residuals(
    rig: Rig, poses: Pose, packed: Packed, implicit: bool = True
) -> tuple[Float[Array, "D 2"], Bool[Array, " D"]]:
    """Predicted minus observed pixel of every dot, and whether the prediction is valid."""

    def one(k, x_board, px):
        pose = Pose(poses.R[k], poses.t[k])
        res = project_through_mirror(rig.camera, rig.mirror, pose.apply(x_board), implicit=implicit)
        return res.uv - px, res.valid

    return jax.vmap(one)(packed.dot_pose, packed.dot_points, packed.dot_pixels)


def spot_residuals(
    rig: Rig, poses: Pose, packed: Packed, implicit: bool = True
) -> tuple[Float[Array, "S 2"], Bool[Array, " S"]]:
    """Predicted minus observed pixel of every laser spot, and validity."""

    def one(k, laser, px):
        pose = Pose(poses.R[k], poses.t[k])
        x, ok = line_plane_intersection(
            rig.lasers.points[laser], rig.lasers.directions[laser], pose, forward_only=False
        )
        res = project_through_mirror(rig.camera, rig.mirror, x, implicit=implicit)
        return res.uv - px, ok & res.valid

    return jax.vmap(one)(packed.spot_pose, packed.spot_laser, packed.spot_pixels)
