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
        pose_keys: ``(view index, board name)`` of each board pose (static).
    """

    dot_pose: Int[Array, " D"]
    dot_points: Float[Array, "D 3"]
    dot_pixels: Float[Array, "D 2"]
    spot_pose: Int[Array, " S"]
    spot_laser: Int[Array, " S"]
    spot_pixels: Float[Array, "S 2"]
    pose_keys: tuple = eqx.field(static=True)


def pack(obs: Observations) -> Packed:
    """Pack the catadioptric views of ``obs``; a board pose exists per (view, board) seen."""
    keys: list[tuple[int, str]] = []
    index: dict[tuple[int, str], int] = {}

    def key(vi, b):
        if (vi, b) not in index:
            index[(vi, b)] = len(keys)
            keys.append((vi, b))
        return index[(vi, b)]

    dp, dpts, dpx, sp, sl, spx = [], [], [], [], [], []
    for vi, v in enumerate(obs.views):
        for b, (px, seen) in v.boards.items():
            if not seen.any():
                continue
            k = key(vi, b)
            dp.extend([k] * int(seen.sum()))
            dpts.append(obs.boards[b][seen])
            dpx.append(px[seen])
        for s in v.spots:
            if s.board is None:
                continue
            sp.append(key(vi, s.board))
            sl.append(s.laser)
            spx.append(s.pixel)
    return Packed(
        jnp.asarray(np.array(dp, dtype=np.int32)),
        jnp.asarray(np.concatenate(dpts) if dpts else np.zeros((0, 3))),
        jnp.asarray(np.concatenate(dpx) if dpx else np.zeros((0, 2))),
        jnp.asarray(np.array(sp, dtype=np.int32)),
        jnp.asarray(np.array(sl, dtype=np.int32)),
        jnp.asarray(np.array(spx, dtype=float).reshape(-1, 2)),
        tuple(keys),
    )


def stack_poses(poses: list[Pose]) -> Pose:
    """A list of poses as one :class:`Pose` with leading axis (P, ...)."""
    return Pose(jnp.stack([p.R for p in poses]), jnp.stack([p.t for p in poses]))


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
        x, ok = line_plane_intersection(rig.lasers.points[laser], rig.lasers.directions[laser], pose)
        res = project_through_mirror(rig.camera, rig.mirror, x, implicit=implicit)
        return res.uv - px, ok & res.valid

    return jax.vmap(one)(packed.spot_pose, packed.spot_laser, packed.spot_pixels)
