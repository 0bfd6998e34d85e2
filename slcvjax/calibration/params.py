"""The unknowns of the joint problem and which of them are estimated.

:class:`Params` holds every unknown: the rig (camera, mirror, lasers), one 6-DOF pose block per
board pose of a catadioptric view and per direct chessboard view, and for the rigid box model the
boards' poses in the box.  Its tangent is the *global* block (the rig's tangent layout, from its
elements: :attr:`slcvjax.geometry.rig.Rig.tangent_dim`, then 6 per box pose) and the pose blocks.
:class:`Masks` says which tangent columns are estimated (1) or held (0); :func:`make_masks` builds
them from block names.  :func:`pad_problem` pads a problem to its shape buckets
(:class:`slcvjax.observations.problem.Layout`) so that datasets of one bucket share a compilation.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..geometry.conic import ConicMirror
from ..geometry.lasers import Lasers
from ..geometry.pose import Pose
from ..geometry.rig import CAMERA_DOF, MIRROR_DOF, Rig
from ..observations.problem import Layout, Packed
from ..support.persist import committed

N_CAM, N_MIR = CAMERA_DOF, MIRROR_DOF
N_LAS = Lasers.DOF  # a point laser's unknowns: the local columns of its spots' residuals


N_CM = N_CAM + N_MIR


class Params(eqx.Module):
    """All unknowns: the rig, the pose blocks (P,), the direct-view poses (C,) and, for the
    rigid box model (:mod:`slcvjax.calibration.rigid`), the boards' poses in the box.

    Without ``box`` each pose block is a board pose ``T_cam_board`` of one view.  With it
    (K,) a pose block is a view's ``T_cam_box`` (or a board pose outside the box), ``box``
    holds ``T_box_board`` of the box's boards but the gauge (whose frame is the box's), and
    the global block is the rig's tangent followed by 6 per box pose (``Packed.pair_block``
    and ``pair_box`` say which of them each board pose is made of).
    """

    rig: Rig
    poses: Pose
    chess: Pose
    box: Pose | None = None

    @property
    def n_box(self) -> int:
        return 0 if self.box is None else self.box.t.shape[0]

    @property
    def n_global(self) -> int:
        return self.rig.tangent_dim + 6 * self.n_box

    @property
    def n_blocks(self) -> int:
        return self.poses.t.shape[0] + self.chess.t.shape[0]

    def retract(self, dg: Float[Array, " G"], dp: Float[Array, "NB 6"]) -> "Params":
        p = self.poses.t.shape[0]
        g = self.rig.tangent_dim
        rp = jax.vmap(lambda R, t, d: Pose(R, t).retract(d))
        box = None if self.box is None else rp(self.box.R, self.box.t, dg[g:].reshape(-1, 6))
        return Params(
            self.rig.retract(dg[:g]),
            rp(self.poses.R, self.poses.t, dp[:p]),
            rp(self.chess.R, self.chess.t, dp[p:]),
            box,
        )


class Masks(eqx.Module):
    """1 = estimated, 0 = frozen; ``glob`` over the global block, ``blocks`` over the pose blocks."""

    glob: Float[Array, " G"]
    blocks: Float[Array, " NB"]


def make_masks(
    params: Params,
    freeze: frozenset | set | tuple = (),
    estimate: frozenset | set | tuple = (),
    held_lasers: tuple[int, ...] = (),
    held_sheets: tuple[int, ...] = (),
) -> Masks:
    """Freeze masks from block names: camera, mirror, mirror_tilt (the mirror's axis only),
    lasers, poses, chess_poses; ``held_lasers``: the indices of single point lasers held besides
    (undetermined ones: :func:`slcvjax.calibration.laser_fit.fit_lasers`), ``held_sheets``: of
    single line and ring lasers (their indices among the rig's sheets).  The mirror's shape
    column (its conic constant) is estimated only
    where ``estimate`` names ``shape``, the mirror is not frozen and is a conic one.  Before a
    telecentric camera the mirror's depth (its apex's z) is held: it is the gauge of a view
    along parallel rays (mirror and boards slide along them together unseen)."""
    known = {"camera", "mirror", "mirror_tilt", "lasers", "poses", "chess_poses"}
    bad = set(freeze) - known
    if bad:
        raise ValueError(
            f"unknown parameter block(s) to freeze: {', '.join(sorted(bad))} (known: {', '.join(sorted(known))})"
        )
    bad = set(estimate) - {"shape"}
    if bad:
        raise ValueError(f"unknown parameter block(s) to estimate: {', '.join(sorted(bad))} (known: shape)")
    shape_free = "shape" in estimate and "mirror" not in freeze and isinstance(params.rig.mirror, ConicMirror)
    n_l = params.rig.lasers.n
    bad_l = [i for i in held_lasers if not 0 <= i < n_l]
    if bad_l:
        raise ValueError(f"held laser {bad_l[0]} is not one of the rig's {n_l} lasers")
    n_s = params.rig.sheets.n if params.rig.has_sheets else 0
    bad_s = [i for i in held_sheets if not 0 <= i < n_s]
    if bad_s:
        raise ValueError(f"held sheet {bad_s[0]} is not one of the rig's {n_s} line and ring lasers")
    held = set(held_lasers)
    if params.rig.kinds:  # the point lasers' and the sheets' own indices as the elements'
        held = {int(params.rig.point_elements[i]) for i in held_lasers}
        held |= {int(params.rig.sheet_elements[i]) for i in held_sheets}
    dofs = params.rig.layout.element_dofs
    las = [np.full(dof, 0.0 if "lasers" in freeze or i in held else 1.0) for i, dof in enumerate(dofs)]
    glob = np.concatenate(
        [
            np.full(N_CAM, 0.0 if "camera" in freeze else 1.0),
            np.full(2, 0.0 if "mirror" in freeze else 1.0),
            [0.0 if "mirror" in freeze or params.rig.camera.telecentric else 1.0],
            np.full(2, 0.0 if {"mirror", "mirror_tilt"} & set(freeze) else 1.0),
            [1.0 if shape_free else 0.0],
            *las,
        ]
    )
    p, c = params.poses.t.shape[0], params.chess.t.shape[0]
    blocks = np.concatenate(
        [np.full(p, 0.0 if "poses" in freeze else 1.0), np.full(c, 0.0 if "chess_poses" in freeze else 1.0)]
    )
    return Masks(glob, blocks)  # float64 host arrays: strongly typed, so every pass shares one compilation


def element_columns(rig: Rig, element, width: int, none: int):
    """The global columns of each row's structured-light element, from the rig's tangent layout
    (:attr:`slcvjax.geometry.rig.Rig.layout`): ``element`` (K,) element indices (traced or not),
    returns (K, ``width``) int columns, the element's own columns first and ``none`` (the
    normal equations' spare column) past its unknowns."""
    lay = rig.layout
    starts = jnp.asarray(np.append(lay.element_starts, none))  # a spare entry: no gather from an empty array
    dofs = jnp.asarray(np.append(lay.element_dofs, 0))
    k = jnp.arange(width)[None, :]
    e = jnp.asarray(element)[:, None]
    return jnp.where(k < dofs[e], starts[e] + k, none)


def pad_params(layout: Layout, params: Params) -> Params:
    """``params`` with its board and direct-view poses and its lasers padded to ``layout``'s
    bucket sizes (the box poses as they are: :mod:`slcvjax.calibration.rigid` pads them)."""
    rig = params.rig.with_lasers(layout.pad_lasers(params.rig.lasers))
    return Params(rig, layout.pad_poses(params.poses), layout.pad_poses(params.chess, chess=True), params.box)


def unpad_params(layout: Layout, params: Params) -> Params:
    """The real poses and lasers of padded ``params`` (host arrays; the box poses all kept)."""
    box = None if params.box is None else Pose(np.asarray(params.box.R), np.asarray(params.box.t))
    rig = params.rig.with_lasers(layout.unpad_lasers(params.rig.lasers))
    return Params(rig, layout.unpad_poses(params.poses), layout.unpad_poses(params.chess, chess=True), box)


def pad_masks(layout: Layout, masks: Masks) -> Masks:
    """``masks`` over padded lasers and pose blocks: a padded laser or block is frozen (and has no observation)."""
    glob, blocks = layout.pad_glob(masks.glob), layout.pad_blocks(masks.blocks)
    return committed(Masks(np.asarray(glob, dtype=float), np.asarray(blocks, dtype=float)))


def pad_problem(params: Params, pk: Packed, masks: Masks) -> tuple[Layout, Params, Packed, Masks]:
    """The problem padded to its shape buckets (:meth:`Layout.of`: observations, the pose blocks
    of ``params``, its lasers), so that every dataset of a bucket shares one compilation: its
    layout, parameters, arrays and masks (padded lasers and pose blocks held, padded rows
    adding nothing)."""
    layout = Layout.of(
        pk,
        n_poses=params.poses.t.shape[0],
        n_chess=params.chess.t.shape[0],
        n_lasers=params.rig.lasers.n,
        sheet_dim=params.rig.sheet_dim,
    )
    return layout, pad_params(layout, params), layout.pad_packed(pk), pad_masks(layout, masks)
