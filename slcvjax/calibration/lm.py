"""Joint Levenberg-Marquardt over the whole rig with a Schur complement over the poses.

Unknowns: the *global* block (camera 9, mirror 6, lasers 4 each) and one 6-DOF *pose
block* per board pose of a catadioptric view and per direct chessboard view.  Every
observation touches the global block and at most one pose block:

=========== ===== ============================================== ==========
observation rows  local parameters                                pose block
=========== ===== ============================================== ==========
dot         2     camera, mirror, board pose (21)                board pose
spot        2     camera, mirror, its laser, board pose (25)     board pose
rim pixel   1     camera, mirror (15)                             none
chess corner 2    camera, direct-view pose (15)                  direct view
=========== ===== ============================================== ==========

so each observation's Jacobian is computed over its few local parameters (forward mode,
with the implicit derivative of the reflection point) and scattered into the normal
equations ``H = J^T W J``, ``g = J^T W r``.  With ``H = [[A, B], [B^T, D]]`` and ``D``
block-diagonal (6x6 per pose) the damped step solves the reduced system

    (A - B D^-1 B^T) dg = -g_g + B D^-1 g_p,      dp = D^-1 (-g_p - B^T dg),

whose cost grows linearly with the number of views.  The rim residual is the signed
first-order (Sampson) distance of a rim pixel to the projected rim curve, in pixels:
``F(uv) / |dF/duv|`` with ``F = |X(uv) - C| - r``, ``X`` the pixel's ray on the rim's
plane and ``C`` the rim's centre.  Within one solve the normalisation ``|dF/duv|`` is held
at its value at the start, so that the cost the steps are judged by is the function
whose Jacobian they use (the global rows are gathered into a dense matrix, so that
``A`` and ``g_g`` are matrix products).

Robust loss (dots and spots): Huber or Cauchy on each observation's 2D residual norm
with scale ``c`` px, by iteratively reweighted least squares inside LM.  The loop is one
``lax.while_loop`` (jit- and vmap-able) and returns a result code, never raises.

Hand-written rather than optimistix's ``LevenbergMarquardt``: on the preset's 16 views from
the same perturbed truth, this solve took 243 ms (6 steps) and optimistix's on the same
residuals (a dense Jacobian) 82 s (124 steps), in one run of ``benchmarks/bench_calibrate.py``
(``benchmarks/results/calibrate_optimistix.json``).
"""

import enum
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ..geometry.camera import Camera, in_image, pixel_to_line, project
from ..geometry.conic import ConicMirror
from ..geometry.lasers import Lasers, line_plane_intersection
from ..geometry.mirror import Mirror, project_through_mirror
from ..geometry.pose import Pose
from ..geometry.rig import CAMERA_DOF, LASER_DOF, MIRROR_DOF, Rig
from ..observations.problem import ROBUST_KINDS, Kind, Layout, Packed, kind_weights, map_rows
from ..support.persist import committed
from ..support.safe import safe_div, safe_norm

N_CAM, N_MIR, N_LAS = CAMERA_DOF, MIRROR_DOF, LASER_DOF
N_CM = N_CAM + N_MIR
LOSSES = ("huber", "cauchy", "linear")
RIM_MARGIN = 0.05  # the cone extended 5 % past its rim for residuals (see solve_mirror_point)
APEX_MARGIN = 0.05  # and 5 % of its height past the apex
INVALID_PX = 30.0  # an invalid observation costs what a residual of this many px costs under the loss


class Outcome(enum.IntEnum):
    """How a solve ended (its ``LMResult.result``): converged (the cost's relative decrease or the
    gradient below the tolerance), stopped at the step limit, or stalled (no step lowers the cost)."""

    CONVERGED = 0
    MAX_STEPS = 1
    STALLED = 2

    @property
    def label(self) -> str:
        """The outcome in the reports' words: ``converged``, ``max_steps``, ``stalled``."""
        return self.name.lower()


CONVERGED, MAX_STEPS, STALLED = Outcome.CONVERGED, Outcome.MAX_STEPS, Outcome.STALLED
# the damping a solve starts with, relative to the normal equations' diagonal: small, as every
# pass but the first starts near its solution (measured over nine 9-15-view scenes: with 1e-3
# the final pass took 9-10 steps to converge, with this 3-6, to the same solution)
LAMBDA_START = 1e-5
# damping under which a step's predicted decrease stands for the Gauss-Newton step's
PREDICT_LAMBDA = 1e-3


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


# ------------------------------------------------------------------ per-observation residuals


def _cm(cam: Camera, mir: Mirror, d):
    return cam.retract(d[:N_CAM]), mir.retract(d[N_CAM:N_CM])


def _mirror_pixel(cam: Camera, mir: Mirror, x, px):
    res = project_through_mirror(cam, mir, x, rim_margin=RIM_MARGIN, apex_margin=APEX_MARGIN)
    return res.uv - px, res.valid


def _spot_point(d_laser, lp, ld, pose: Pose):
    """Where the laser ``(lp, ld)`` moved by ``d_laser`` (4) meets the plane of ``pose``."""
    las = Lasers(lp[None], ld[None]).retract(d_laser[None])
    return line_plane_intersection(las.points[0], las.directions[0], pose, forward_only=False)


def _dot(d, cam, mir, R, t, xb, px):
    """A dot's residual over its local parameters ``d`` (camera, mirror, board pose: 21)."""
    c, m = _cm(cam, mir, d)
    return _mirror_pixel(c, m, Pose(R, t).retract(d[N_CM:]).apply(xb), px)


def _spot(d, cam, mir, lp, ld, R, t, px):
    """A spot's residual over its local parameters ``d`` (camera, mirror, laser, board pose: 25)."""
    c, m = _cm(cam, mir, d)
    x, ok = _spot_point(d[N_CM : N_CM + N_LAS], lp, ld, Pose(R, t).retract(d[N_CM + N_LAS :]))
    r, valid = _mirror_pixel(c, m, x, px)
    return r, ok & valid


def _dot_point(d, R, t, xb):
    """A dot's 3D point (camera frame) over ``d``: laser (4, unused) and board pose (6)."""
    return Pose(R, t).retract(d[N_LAS:]).apply(xb), jnp.asarray(True)


def _spot_point_local(d, lp, ld, R, t):
    """A spot's 3D point over ``d``: its laser (4) and board pose (6)."""
    return _spot_point(d[:N_LAS], lp, ld, Pose(R, t).retract(d[N_LAS:]))


def _box_pose(d, Rv, tv, Rb, tb):
    """``T_cam_box`` (its tangent ``d[6:]``) composed with ``T_box_board`` (``d[:6]``): a board
    pose of the rigid box model."""
    return Pose(Rv, tv).retract(d[6:]) @ Pose(Rb, tb).retract(d[:6])


def _dot_point_box(d, Rv, tv, Rb, tb, xb):
    """:func:`_dot_point` of the rigid box model: ``d`` is laser (4, unused), box pose (6), view pose (6)."""
    return _box_pose(d[N_LAS:], Rv, tv, Rb, tb).apply(xb), jnp.asarray(True)


def _spot_point_box(d, lp, ld, Rv, tv, Rb, tb):
    """:func:`_spot_point_local` of the rigid box model: its laser (4), box pose (6), view pose (6)."""
    return _spot_point(d[:N_LAS], lp, ld, _box_pose(d[N_LAS:], Rv, tv, Rb, tb))


def _project_local(d, cam, mir, x, px):
    """The residual of a point ``x`` seen through the mirror over ``d``: camera, mirror (15), the point (3)."""
    c, m = _cm(cam, mir, d)
    return _mirror_pixel(c, m, x + d[N_CM:], px)


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


def _rim(d, cam, mir, uv, norm):
    c, m = _cm(cam, mir, d)
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


def _chess(d, cam, R, t, xb, px):
    c = cam.retract(d[:N_CAM])
    uv, ok = project(c, Pose(R, t).retract(d[N_CAM:]).apply(xb))
    return uv - px, ok & in_image(c, jax.lax.stop_gradient(uv))


# ------------------------------------------------------------------ linearisation


class Rows(NamedTuple):
    """Scalar residual rows with their local Jacobians scattered by index."""

    r: Float[Array, " n"]  # residual
    jg: Float[Array, "n W"]  # Jacobian w.r.t. camera, mirror, (at most) one laser (18), and one box pose (6 more)
    gidx: Int[Array, "n W"]  # global column of each (G = unused)
    jp: Float[Array, "n 6"]  # Jacobian w.r.t. the pose block
    pidx: Int[Array, " n"]  # pose block (NB = none)
    obs: Int[Array, " n"]  # observation id (for robust weights)
    kind: Int[Array, " n"]  # its Kind
    valid: Bool[Array, " n"]  # the model predicts the observation (False for padding too)
    present: Bool[Array, " n"]  # a real observation, not padding (see slcvjax.observations.problem)


# observations per step of the loop in :func:`accumulate`: dots and spots, rim pixels, corners
CHUNKS = (64, 256, 128)


class Chunk(NamedTuple):
    """``k`` observations of one group, ``m`` scalar rows each, with their local Jacobians."""

    r: Float[Array, "k m"]
    jg: Float[Array, "k m W"]  # w.r.t. the global columns ``gidx``
    gidx: Int[Array, "k W"]
    jp: Float[Array, "k m 6"]  # w.r.t. the pose block ``pidx``
    pidx: Int[Array, " k"]
    ok: Bool[Array, " k"]  # the model predicts it
    kind: Int[Array, " k"]


class Group(NamedTuple):
    """Observations that share one residual function: ``fn(*args sliced to k rows, spot_chunk)
    -> Chunk`` (``spot_chunk``: None, or whether a chunk's real rows are spots rather than dots).

    ``regions``: ``(start, count)`` per kind in the group's rows (static start, traced
    count): the real rows of a kind are its first ``count``, the rest is padding.
    """

    fn: object
    args: tuple
    regions: list
    chunk: int  # rows per step of the loop in :func:`accumulate`
    width: int | None = None  # the leading global columns its rows can reach (None: all of the chunk's)
    posed: bool = True  # its rows have a pose block


def _groups(params: Params, pk: Packed, with_jac: bool, rim_norm: Array | None) -> list[Group]:
    """The three groups of observations: dots and spots (one projection through the mirror),
    rim pixels, chessboard corners of the direct views.  A camera-only rig
    (:meth:`slcvjax.geometry.rig.Rig.camera_only`: no mirror) has the corners' group only; its
    problem has no row of the other kinds, and its mirror's columns are held (:func:`make_masks`)."""
    rig = params.rig
    if rig.mirror is None and n_observations(pk) != pk.chess_pose.shape[0]:
        raise ValueError("a camera-only rig (no mirror) sees chessboard corners only: no dots, spots or rim pixels")
    cam, mir, las = rig.camera, rig.mirror, rig.lasers
    g = params.n_global  # the "unused" global column
    nb = params.n_blocks
    n_p = params.poses.t.shape[0]
    box = params.box is not None
    extra = 6 if box else 0  # a box pose's columns
    if box:  # the gauge board and the boards outside the box take the identity (index n_box)
        n_box = params.n_box
        box_R = jnp.concatenate([params.box.R, jnp.eye(3)[None]])
        box_t = jnp.concatenate([params.box.t, jnp.zeros((1, 3))])

    def lin(fun, n_local, *args):
        z = jnp.zeros(n_local)
        if with_jac:

            def f(d):
                r, ok = fun(d, *args)
                return r, (r, ok)

            jac, (r, ok) = jax.jacfwd(f, has_aux=True)(z)
        else:
            r, ok = fun(z, *args)
            jac = jnp.zeros(r.shape + (n_local,))
        return r, jac, ok

    cm_idx = jnp.arange(N_CM)
    unused = jnp.full(N_LAS + extra, g)

    # dots and spots: first each one's 3D point with its derivative in its local laser (4,
    # zero for a dot) and pose (6) parameters, then one projection through the mirror for
    # both kinds, differentiated in camera, mirror and the point (17) and chained: the costly
    # projection is traced once and carries 17 tangents, not 20 or 24
    n_d, n_s = pk.dot_pose.shape[0], pk.spot_pose.shape[0]
    zero = jnp.zeros((), dtype=pk.spot_laser.dtype)

    def points(pose, laser, xb, px, spot, spot_chunk=None):
        if box:
            block, in_box = pk.pair_block[pose], pk.pair_box[pose]
            R, t = params.poses.R[block], params.poses.t[block]
            Rb, tb = box_R[in_box], box_t[in_box]
            x, jx, ok_x = jax.vmap(lambda *a: lin(_dot_point_box, N_LAS + 12, *a))(R, t, Rb, tb, xb)
        else:
            block = pose
            R, t = params.poses.R[pose], params.poses.t[pose]
            x, jx, ok_x = jax.vmap(lambda *a: lin(_dot_point, N_LAS + 6, *a))(R, t, xb)
        if las.n:

            def spot_points():
                if box:
                    return jax.vmap(lambda *a: lin(_spot_point_box, N_LAS + 12, *a))(
                        las.points[laser], las.directions[laser], R, t, Rb, tb
                    )
                return jax.vmap(lambda *a: lin(_spot_point_local, N_LAS + 6, *a))(
                    las.points[laser], las.directions[laser], R, t
                )

            if spot_chunk is not None:  # a chunk of the loop's: its real rows are of one kind
                x, jx, ok_x = jax.lax.cond(spot_chunk, spot_points, lambda: (x, jx, ok_x))
            else:
                s = spot_points()
                x, jx, ok_x = (
                    jnp.where(spot.reshape((-1,) + (1,) * (a.ndim - 1)), b, a)
                    for a, b in zip((x, jx, ok_x), s, strict=True)
                )
        r, j, ok = jax.vmap(lambda x, px: lin(_project_local, N_CM + 3, cam, mir, x, px))(x, px)
        j = jnp.concatenate([j[:, :, :N_CM], j[:, :, N_CM:] @ jx], axis=2)
        lidx = jnp.where(spot[:, None], N_CM + N_LAS * laser[:, None] + jnp.arange(N_LAS)[None, :], g)
        parts = [jnp.broadcast_to(cm_idx, (r.shape[0], N_CM)), lidx]
        if box:
            parts.append(jnp.where((in_box < n_box)[:, None], rig.tangent_dim + 6 * in_box[:, None] + jnp.arange(6), g))
        gidx = jnp.concatenate(parts, axis=1)
        w = N_CM + N_LAS + extra
        return Chunk(r, j[:, :, :w], gidx, j[:, :, w:], block, ok & ok_x, spot.astype(int))

    dots_spots = Group(
        points,
        (
            jnp.concatenate([pk.dot_pose, pk.spot_pose]),
            jnp.concatenate([jnp.broadcast_to(zero, (n_d,)), pk.spot_laser]),
            jnp.concatenate([pk.dot_points, jnp.zeros((n_s, 3))]),
            jnp.concatenate([pk.dot_pixels, pk.spot_pixels]),
            jnp.arange(n_d + n_s) >= n_d,
        ),
        [(0, pk.counts[Kind.DOT]), (n_d, pk.counts[Kind.SPOT])],
        CHUNKS[0],
    )

    def rim(uv, norm, spot_chunk=None):
        r, j, ok = jax.vmap(lambda uv, s: lin(_rim, N_CM, cam, mir, uv, s))(uv, norm)
        k = r.shape[0]
        return Chunk(
            r,
            jnp.concatenate([j, jnp.zeros((k, 1, N_LAS + extra))], axis=2),
            jnp.broadcast_to(jnp.concatenate([cm_idx, unused]), (k, N_CM + N_LAS + extra)),
            jnp.zeros((k, 1, 6)),
            jnp.full(k, nb),
            ok,
            jnp.full(k, 2),
        )

    norm = jax.lax.stop_gradient(rim_norms(rig, pk, real_only=False) if rim_norm is None else rim_norm)
    rim_group = Group(rim, (pk.rim_pixels, norm), [(0, pk.counts[Kind.RIM])], CHUNKS[1], N_CM, posed=False)

    def chess(xb, px, pose, spot_chunk=None):
        R, t = params.chess.R[pose], params.chess.t[pose]
        r, j, ok = jax.vmap(lambda *a: lin(_chess, N_CAM + 6, cam, *a))(R, t, xb, px)
        k = r.shape[0]
        return Chunk(
            r,
            jnp.concatenate([j[:, :, :N_CAM], jnp.zeros((k, 2, N_MIR + N_LAS + extra))], axis=2),
            jnp.broadcast_to(
                jnp.concatenate([jnp.arange(N_CAM), jnp.full(N_MIR + N_LAS + extra, g)]), (k, N_CM + N_LAS + extra)
            ),
            j[:, :, N_CAM:],
            n_p + pose,
            ok,
            jnp.full(k, 3),
        )

    chess_group = Group(
        chess,
        (pk.chess_points, pk.chess_pixels, pk.chess_pose),
        [(0, pk.counts[Kind.CHESS])],
        CHUNKS[2],
        N_CAM,
    )
    if mir is None:  # the other groups have no rows: their rows' offsets are those of the full list
        return [chess_group]
    return [dots_spots, rim_group, chess_group]


def _flat(c: Chunk, present: Bool[Array, " k"], first_obs) -> Rows:
    """A chunk's scalar rows (invalid or padded observations zeroed), its observations numbered from ``first_obs``."""
    k, m = c.r.shape
    w = c.jg.shape[-1]
    okm = jnp.broadcast_to((c.ok & present)[:, None], (k, m))

    def per_row(x):
        return jnp.broadcast_to(x[:, None], (k, m)).reshape(-1)

    return Rows(
        jnp.where(okm, c.r, 0.0).reshape(-1),
        jnp.where(okm[..., None], c.jg, 0.0).reshape(-1, w),
        jnp.broadcast_to(c.gidx[:, None, :], (k, m, w)).reshape(-1, w),
        jnp.where(okm[..., None], c.jp, 0.0).reshape(-1, 6),
        per_row(c.pidx),
        per_row(first_obs + jnp.arange(k)),
        per_row(c.kind),
        okm.reshape(-1),
        per_row(present),
    )


def _rows(params: Params, pk: Packed, with_jac: bool = True, rim_norm: Array | None = None) -> Rows:
    """Every residual row with its local Jacobian, padding included (zeroed), in one ``vmap``
    per group (reverse-differentiable; the solver uses :func:`accumulate` instead).

    ``rim_norm``: the rim rows' normalisations (:func:`rim_norms`), held as constants; by
    default those of ``params`` itself, so that the rim rows are the pixels' first-order
    distances from the rim (the Jacobian still holds them constant).  The LM passes the
    normalisation at its start, so that its cost and its Jacobian describe one function.
    """
    parts, offset = [], 0
    for grp in _groups(params, pk, with_jac, rim_norm):
        n = grp.args[0].shape[0]
        present = _present(grp.regions, n)
        parts.append(_flat(grp.fn(*grp.args), present, offset))
        offset += n
    return Rows(*(jnp.concatenate(p) for p in zip(*parts, strict=True)))


def _spans(regions, n: int) -> list[tuple[int, int, Array]]:
    """``(start, end, real_end)`` of each kind's rows in a group of ``n`` rows (see :class:`Group`):
    its rows are ``start:end``, the real ones ``start:real_end``."""
    ends = [s for s, _ in regions[1:]] + [n]
    return [(s, e, s + jnp.minimum(count, e - s)) for (s, count), e in zip(regions, ends, strict=True)]


def _present(regions, n: int) -> Bool[Array, " n"]:
    """Which rows of a group of ``n`` rows are real."""
    idx = jnp.arange(n)
    out = jnp.zeros(n, dtype=bool)
    for start, _, real_end in _spans(regions, n):
        out = out | ((idx >= start) & (idx < real_end))
    return out


def n_observations(pk: Packed) -> int:
    return pk.dot_pose.shape[0] + pk.spot_pose.shape[0] + pk.rim_pixels.shape[0] + pk.chess_pose.shape[0]


# ------------------------------------------------------------------ robust loss


class ObservationTable(NamedTuple):
    """Per observation (in the order of :class:`Rows`' ids): what the robust loss and the reports use."""

    sq: Float[Array, " N"]  # squared residual norm (px^2), 0 where invalid
    kind: Int[Array, " N"]  # its Kind
    valid: Bool[Array, " N"]  # the model predicts it
    present: Bool[Array, " N"]  # real, not padding
    block: Int[Array, " N"]  # its pose block (NB = none)


def observation_table(rows: Rows, n_obs: int) -> ObservationTable:
    """:class:`ObservationTable` of residual rows."""

    def seg(x, op):
        return op(x, rows.obs, num_segments=n_obs)

    return ObservationTable(
        seg(rows.r**2, jax.ops.segment_sum),
        seg(rows.kind, jax.ops.segment_max),
        seg(rows.valid.astype(jnp.int32), jax.ops.segment_min) > 0,
        seg(rows.present.astype(jnp.int32), jax.ops.segment_max) > 0,
        seg(rows.pidx, jax.ops.segment_max),
    )


def block_costs(table: ObservationTable, n_blocks: int, loss: str, scale) -> Float[Array, " NB"]:
    """The robust cost of the observations of each pose block (dots and spots of a board)."""
    _, rho = robust_observations(table, loss, jnp.asarray(scale, dtype=float), kind_weights())
    return jax.ops.segment_sum(rho, table.block, num_segments=n_blocks + 1)[:n_blocks]


def robust_weights(rows: Rows, n_obs: int, loss: str, scale, kind_weight=None) -> tuple[Array, Array]:
    """Per-row IRLS weights and the total robust cost (dots and spots robust, the rest plain).

    ``kind_weight`` (4,) weighs each kind (dot, spot, rim, chess); 0 drops it.  A weight
    ``(sigma / sigma_kind)^2`` whitens a kind to the noise ``sigma`` before the robust loss,
    so that ``scale`` (in units of ``sigma``) suits every kind.
    """
    kw = kind_weights(kind_weight)
    w, rho = robust_observations(observation_table(rows, n_obs), loss, scale, kw)
    return w[rows.obs], jnp.sum(rho)


def loss_index(loss: "str | int | Array") -> "int | Array":
    """The index in :data:`LOSSES` of a loss given by name (an index passes through).

    Compiled functions take the index as a value, so that every loss shares one compilation.
    """
    if isinstance(loss, str):
        if loss not in LOSSES:
            raise ValueError(f"unknown loss {loss!r} (known: {', '.join(LOSSES)})")
        return LOSSES.index(loss)
    return loss


def robust_cost(sq, loss: "str | int | Array", c):
    """``(rho, w)`` of whitened squared residual norms ``sq``: the robust cost and its IRLS
    weight ``2 rho'(sq)``; smooth enough to be differentiated twice (``sq = 0`` included).

    ``loss``: a name of :data:`LOSSES` or its index (a traced index selects among all three).
    """
    loss = loss_index(loss)
    norm = jnp.sqrt(jnp.maximum(sq, 1e-300))
    inside = norm <= c
    huber = jnp.where(inside, 0.5 * sq, c * norm - 0.5 * c * c), jnp.where(inside, 1.0, c / norm)
    cauchy = 0.5 * c * c * jnp.log1p(sq / (c * c)), 1.0 / (1.0 + sq / (c * c))
    linear = 0.5 * sq, jnp.ones_like(sq)
    if isinstance(loss, int):
        return (huber, cauchy, linear)[loss]
    return tuple(
        jnp.where(loss == 0, h, jnp.where(loss == 1, ca, li)) for h, ca, li in zip(huber, cauchy, linear, strict=True)
    )


def robust_observations(t: ObservationTable, loss: str, scale, kw) -> tuple[Array, Array]:
    """Per observation: its IRLS weight and its cost (an invalid one at a fixed penalty, padding 0)."""
    k = kw[t.kind]
    sq = k * t.sq  # whitened
    robust = jnp.asarray(ROBUST_KINDS)[t.kind]  # dots and spots (Kind.robust)
    rho, w = robust_cost(sq, loss, scale)
    w = jnp.where(robust, w, 1.0) * k
    rho = jnp.where(robust, rho, 0.5 * sq)
    # an invalid prediction (off the mirror, off the sensor) costs what a residual of
    # INVALID_PX costs under the same loss: a step cannot lower the cost by pushing a fitting
    # observation out of the model's reach, while a gross outlier beyond that is free to go
    # (a fixed plain penalty kept it at the edge of validity, its board's pose dragged with it)
    sq_invalid = k * INVALID_PX**2
    penalty = jnp.where(robust, robust_cost(sq_invalid, loss, scale)[0], 0.5 * sq_invalid)
    rho = jnp.where(t.valid, rho, jnp.where(t.present, penalty, 0.0))
    return jnp.where(t.present, w, 0.0), rho


# ------------------------------------------------------------------ normal equations


class Normal(NamedTuple):
    A: Float[Array, "G G"]
    bg: Float[Array, " G"]
    B: Float[Array, "NB G 6"]
    D: Float[Array, "NB 6 6"]
    bp: Float[Array, "NB 6"]


def zero_normal(g: int, nb: int) -> Normal:
    """Empty sums for :func:`add_rows`: one spare column ``g`` and block ``nb`` take the rows'
    "none" entries (unused global columns, observations without a pose block)."""
    return Normal(
        jnp.zeros((g + 1, g + 1)),
        jnp.zeros(g + 1),
        jnp.zeros((nb + 1, g + 1, 6)),
        jnp.zeros((nb + 1, 6, 6)),
        jnp.zeros((nb + 1, 6)),
    )


def add_rows(ne: Normal, rows: Rows, w, gmask, pmask, posed: bool = True) -> Normal:
    """``ne`` (from :func:`zero_normal`) plus the rows' ``J^T W J`` and ``J^T W r``; frozen
    columns (``gmask``, ``pmask`` 0) get no entries.  ``posed`` False: the rows have no pose
    block (their pose sums, scattered into the spare block, are skipped)."""
    jg = rows.jg * jnp.concatenate([gmask, jnp.zeros(1)])[rows.gidx]
    jp = rows.jp * jnp.concatenate([pmask, jnp.zeros(1)])[rows.pidx][:, None]
    wr = w * rows.r
    # the global columns as one dense (rows, G) matrix: its products are matrix products,
    # three times faster on a CPU than scattering each row's 18 x 18 outer product
    n = rows.r.shape[0]
    J = jnp.zeros((n, ne.A.shape[0])).at[jnp.arange(n)[:, None], rows.gidx].add(jg)
    if not posed:
        return ne._replace(A=ne.A + (J * w[:, None]).T @ J, bg=ne.bg + J.T @ wr)
    return Normal(
        ne.A + (J * w[:, None]).T @ J,
        ne.bg + J.T @ wr,
        ne.B.at[rows.pidx[:, None], rows.gidx].add(w[:, None, None] * jg[:, :, None] * jp[:, None, :]),
        ne.D.at[rows.pidx].add(w[:, None, None] * jp[:, :, None] * jp[:, None, :]),
        ne.bp.at[rows.pidx].add(wr[:, None] * jp),
    )


def finish_normal(ne: Normal, gmask, pmask) -> tuple[Normal, Array, Array]:
    """The normal equations of the sums ``ne`` (spare column and block cut), which estimated
    global parameters and pose blocks the weighted rows reach (a nonzero diagonal), and a
    unit diagonal for the frozen parameters and the pose blocks without any observation."""
    g, nb = ne.A.shape[0] - 1, ne.D.shape[0] - 1
    A, bg, B, D, bp = ne.A[:g, :g], ne.bg[:g], ne.B[:nb, :g], ne.D[:nb], ne.bp[:nb]
    empty = jnp.trace(D, axis1=1, axis2=2) <= 0.0
    seen_glob = jnp.diag(A) > 0.0
    A = A + jnp.diag(jnp.where(seen_glob, 1.0 - gmask, 1.0))
    D = D + jnp.where(empty | (pmask <= 0.0), 1.0, 0.0)[:, None, None] * jnp.eye(6)
    return Normal(A, bg, B, D, bp), seen_glob, ~empty


def normal_equations(rows: Rows, w, g: int, nb: int, gmask, pmask) -> Normal:
    """``J^T W J`` and ``J^T W r`` of ``rows`` in Schur form; frozen parameters get a unit diagonal."""
    return finish_normal(add_rows(zero_normal(g, nb), rows, w, gmask, pmask), gmask, pmask)[0]


def _chunk_bounds(spans, n: int, k: int, i, n_chunks):
    """Chunk ``i`` of a group (``spans`` from :func:`_spans`): where it starts (moved back to
    fit, as the slice is), the row it was meant to start at, and the end of its kind's real rows."""
    meant, real_end, first = spans[0][0] + i * k, spans[0][2], 0
    for (s, _, e), n_prev in zip(spans[1:], n_chunks[:-1], strict=True):
        first = first + n_prev
        here = i >= first
        meant = jnp.where(here, s + (i - first) * k, meant)
        real_end = jnp.where(here, e, real_end)
    return jnp.clip(meant, 0, n - k), meant, real_end


class Sums(NamedTuple):
    """What :func:`accumulate` sums over the observations."""

    normal: Normal  # raw sums with one spare row/column for "none" (see :func:`finish_normal`)
    sq: Float[Array, " N"]  # per observation: squared residual norm
    valid: Bool[Array, " N"]  # per observation: the model predicts it
    cost: Float[Array, ""]  # robust cost
    n_valid: Float[Array, ""]  # valid scalar rows
    weighted_sq: Float[Array, ""]  # sum of w r^2


def accumulate(
    params: Params,
    pk: Packed,
    masks: "Masks | None",
    loss,
    scale,
    kind_weight,
    rim_norm: Array | None = None,
    with_jac: bool = True,
    real_only: bool = True,
) -> Sums:
    """The normal equations, the robust cost and the per-observation residuals, summed over
    chunks of each group's observations (:data:`CHUNKS`; see :func:`_groups`).

    ``real_only``: the loop visits only the chunks that hold real rows (its trip count is
    a traced value), so the padding of a shape bucket costs nothing but memory; ``False``
    visits every chunk (a static loop, reverse-differentiable).  ``masks`` None: no normal
    equations (the cost alone).
    """
    g, nb = params.n_global, params.n_blocks
    kind_weight = kind_weights(kind_weight)
    ne = zero_normal(g, nb)
    sq_parts, valid_parts = [], []
    cost = n_valid = wsq = jnp.asarray(0.0)
    for grp in _groups(params, pk, with_jac and masks is not None, rim_norm):
        n = grp.args[0].shape[0]
        if n == 0:
            sq_parts.append(jnp.zeros(0))
            valid_parts.append(jnp.zeros(0, dtype=bool))
            continue
        k = min(grp.chunk, n)
        spans = _spans(grp.regions, n)
        n_chunks = [((r if real_only else e) - s + k - 1) // k for s, e, r in spans]

        def body(i, carry, grp=grp, n=n, k=k, spans=spans, n_chunks=n_chunks):
            ne, sq, valid, cost, n_valid, wsq = carry
            start, meant, real_end = _chunk_bounds(spans, n, k, i, n_chunks)
            idx = start + jnp.arange(k)
            present = (idx >= meant) & (idx < real_end)
            c = grp.fn(
                *(jax.lax.dynamic_slice_in_dim(a, start, k) for a in grp.args), spot_chunk=meant >= grp.regions[-1][0]
            )
            rows = _flat(c, present, 0)
            k_, m_ = c.r.shape
            t = ObservationTable(jnp.sum(rows.r.reshape(k_, m_) ** 2, axis=1), c.kind, c.ok & present, present, c.pidx)
            w_obs, rho = robust_observations(t, loss, scale, kind_weight)
            w = w_obs[rows.obs]
            if masks is not None and with_jac:
                # only the columns the group's rows reach: the scatters cost by the entry
                wide = rows._replace(jg=rows.jg[:, : grp.width], gidx=rows.gidx[:, : grp.width])
                ne = add_rows(ne, wide, w, masks.glob, masks.blocks, grp.posed)

            def put(out, new):
                return jax.lax.dynamic_update_slice_in_dim(
                    out, jnp.where(present, new, jax.lax.dynamic_slice_in_dim(out, start, k)), start, 0
                )

            return (
                ne,
                put(sq, t.sq),
                put(valid, t.valid),
                cost + jnp.sum(rho),
                n_valid + jnp.sum(rows.valid.astype(float)),
                wsq + jnp.sum(w * rows.r**2),
            )

        carry = (ne, jnp.zeros(n), jnp.zeros(n, dtype=bool), cost, n_valid, wsq)
        ne, sq, valid, cost, n_valid, wsq = jax.lax.fori_loop(0, sum(n_chunks), body, carry)
        sq_parts.append(sq)
        valid_parts.append(valid)
    return Sums(ne, jnp.concatenate(sq_parts), jnp.concatenate(valid_parts), cost, n_valid, wsq)


def schur_complement(A, B, D) -> tuple[Array, Array]:
    """``(S, D^-1 B^T)`` of a Schur-form matrix ``[[A, B^T], [B, D]]`` whose pose part ``D`` is
    block-diagonal: ``S = A - sum_k B_k D_k^-1 B_k^T`` (``B`` (NB, G, 6) holds each block's
    coupling to the global columns, ``D`` (NB, 6, 6) the blocks)."""
    Dinv_Bt = jnp.linalg.solve(D, jnp.swapaxes(B, 1, 2))  # (NB, 6, G)
    return A - jnp.einsum("kgi,kih->gh", B, Dinv_Bt), Dinv_Bt


def schur_solve(A, B, D, rg, rp) -> tuple[Array, Array]:
    """Solve ``[[A, B^T], [B, D]] x = r`` for ``k`` right-hand sides ``r = (rg (G, k), rp (NB, 6, k))``
    by eliminating the pose blocks (:func:`schur_complement`): the LM's step, the implicit
    derivative's Newton step, tangents and pixel columns all solve through it."""
    S, Dinv_Bt = schur_complement(A, B, D)
    Dinv_rp = jnp.linalg.solve(D, rp)  # (NB, 6, k)
    xg = jnp.linalg.solve(S, rg - jnp.einsum("kgi,kij->gj", B, Dinv_rp))
    return xg, Dinv_rp - jnp.einsum("kig,gj->kij", Dinv_Bt, xg)


def damping_diagonal(ne: Normal) -> tuple[Array, Array]:
    """Marquardt's scaling: the normal matrix's diagonal (floored at 1e-9), global ``(G,)`` and
    per pose block ``(NB, 6)``; the step damps by ``lam`` times it."""
    return jnp.maximum(jnp.diag(ne.A), 1e-9), jnp.maximum(jnp.diagonal(ne.D, axis1=1, axis2=2), 1e-9)


def schur_step(ne: Normal, lam) -> tuple[Array, Array]:
    """The damped Gauss-Newton step by the Schur complement over the pose blocks."""
    da, dd = damping_diagonal(ne)
    A = ne.A + lam * jnp.diag(da)
    D = ne.D + lam * jax.vmap(jnp.diag)(dd)
    dg, dp = schur_solve(A, ne.B, D, -ne.bg[:, None], -ne.bp[..., None])
    return dg[:, 0], dp[..., 0]


def predicted_decrease(ne: Normal, lam, dg: Array, dp: Array) -> Array:
    """The cost decrease the Gauss-Newton model predicts for the damped step ``(dg, dp)`` of
    :func:`schur_step`: ``-(g.d + d.H d / 2) = d.(lam M d - g) / 2``, with ``M`` the damping's
    diagonal (:func:`damping_diagonal`)."""
    da, dd = damping_diagonal(ne)
    return 0.5 * (jnp.dot(dg, lam * da * dg - ne.bg) + jnp.sum(dp * (lam * dd * dp - ne.bp)))


def dense_step(ne: Normal, lam) -> tuple[Array, Array]:
    """The same step from the full dense system (for tests and small problems)."""
    g, nb = ne.A.shape[0], ne.D.shape[0]
    H = jnp.zeros((g + 6 * nb, g + 6 * nb))
    H = H.at[:g, :g].set(ne.A)
    Bf = jnp.swapaxes(ne.B, 0, 1).reshape(g, 6 * nb)
    H = H.at[:g, g:].set(Bf).at[g:, :g].set(Bf.T)
    H = H.at[g:, g:].set(jax.scipy.linalg.block_diag(*ne.D) if nb else jnp.zeros((0, 0)))
    H = H + lam * jnp.diag(jnp.maximum(jnp.diag(H), 1e-9))
    x = jnp.linalg.solve(H, -jnp.concatenate([ne.bg, ne.bp.reshape(-1)]))
    return x[:g], x[g:].reshape(nb, 6)


# ------------------------------------------------------------------ the solver


class Masks(eqx.Module):
    """1 = estimated, 0 = frozen; ``glob`` over the global block, ``blocks`` over the pose blocks."""

    glob: Float[Array, " G"]
    blocks: Float[Array, " NB"]


def make_masks(
    params: Params,
    freeze: frozenset | set | tuple = (),
    estimate: frozenset | set | tuple = (),
    held_lasers: tuple[int, ...] = (),
) -> Masks:
    """Freeze masks from block names: camera, mirror, mirror_tilt (the mirror's axis only),
    lasers, poses, chess_poses; ``held_lasers``: the indices of single lasers held besides
    (undetermined ones: :func:`slcvjax.calibration.staged.fit_lasers`).  The mirror's shape
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
    las = np.full((n_l, N_LAS), 0.0 if "lasers" in freeze else 1.0)
    las[list(held_lasers)] = 0.0
    glob = np.concatenate(
        [
            np.full(N_CAM, 0.0 if "camera" in freeze else 1.0),
            np.full(2, 0.0 if "mirror" in freeze else 1.0),
            [0.0 if "mirror" in freeze or params.rig.camera.telecentric else 1.0],
            np.full(2, 0.0 if {"mirror", "mirror_tilt"} & set(freeze) else 1.0),
            [1.0 if shape_free else 0.0],
            las.ravel(),
        ]
    )
    p, c = params.poses.t.shape[0], params.chess.t.shape[0]
    blocks = np.concatenate(
        [np.full(p, 0.0 if "poses" in freeze else 1.0), np.full(c, 0.0 if "chess_poses" in freeze else 1.0)]
    )
    return Masks(glob, blocks)  # float64 host arrays: strongly typed, so every pass shares one compilation


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
        pk, n_poses=params.poses.t.shape[0], n_chess=params.chess.t.shape[0], n_lasers=params.rig.lasers.n
    )
    return layout, pad_params(layout, params), layout.pad_packed(pk), pad_masks(layout, masks)


class Linearisation(NamedTuple):
    """The problem linearised at a point: the normal equations and what the covariance and reports need."""

    normal: Normal
    table: ObservationTable
    seen_glob: Float[Array, " G"]  # 1 where an estimated global parameter has a weighted observation
    seen_blocks: Float[Array, " NB"]  # 1 where an estimated pose block has one
    n_valid: Float[Array, ""]  # valid scalar residuals
    weighted_sq: Float[Array, ""]  # sum of w r^2


class LMResult(NamedTuple):
    params: Params
    cost: Float[Array, ""]
    initial_cost: Float[Array, ""]
    steps: Int[Array, ""]
    result: Int[Array, ""]
    linearisation: Linearisation  # at ``params`` (with the rim normalisation held at the start)


def cost_at(params, pk, loss, scale, kind_weight, rim_norm=None, real_only=True) -> Float[Array, ""]:
    """The robust cost alone at ``params`` (no Jacobian): the cost :func:`solve` judges its
    steps by, which its linearisation returns with the normal equations."""
    return accumulate(params, pk, None, loss, scale, kind_weight, rim_norm, False, real_only).cost


def _table_arrays(params: Params, pk: Packed) -> tuple[Array, Array, Array]:
    """Per observation (dots, spots, rim pixels, corners): its kind, whether it is real, its pose block."""
    n_d, n_s, n_r, n_c = pk.dot_pose.shape[0], pk.spot_pose.shape[0], pk.rim_pixels.shape[0], pk.chess_pose.shape[0]
    kind = jnp.concatenate([jnp.full(n, k, dtype=int) for n, k in zip((n_d, n_s, n_r, n_c), Kind, strict=True)])
    dot_block, spot_block = pk.dot_pose, pk.spot_pose
    if params.box is not None:
        dot_block, spot_block = pk.pair_block[dot_block], pk.pair_block[spot_block]
    block = jnp.concatenate(
        [dot_block, spot_block, jnp.full(n_r, params.n_blocks), params.poses.t.shape[0] + pk.chess_pose]
    )
    return kind, jnp.concatenate(pk.present()), block


def table_at(params: Params, pk: Packed) -> ObservationTable:
    """The per-observation table at ``params`` without the normal equations (the cost's pass
    over the real observations): what :class:`Linearisation` ``.table`` holds after a solve with
    no step, for a fraction of its work (the rim rows normalised at ``params``, as there)."""
    s = accumulate(params, pk, None, 0, 1.0, None, rim_norms(params.rig, pk), False)
    kind, present, block = _table_arrays(params, pk)
    return ObservationTable(s.sq, kind, s.valid, present, block)


def linearise(params: Params, pk: Packed, masks: Masks, loss: str, scale, kind_weight, rim_norm=None, real_only=True):
    """:class:`Linearisation` at ``params`` and the robust cost there (``real_only``: see :func:`accumulate`)."""
    s = accumulate(params, pk, masks, loss, scale, kind_weight, rim_norm, True, real_only)
    # what the weighted rows reach, from the diagonals (with every kind weighted, as the
    # covariance is, that is every parameter with a valid observation)
    ne, seen_glob, seen_blocks = finish_normal(s.normal, masks.glob, masks.blocks)
    kind, present, block = _table_arrays(params, pk)
    table = ObservationTable(s.sq, kind, s.valid, present, block)
    return Linearisation(
        ne, table, seen_glob.astype(float), seen_blocks.astype(float), s.n_valid, s.weighted_sq
    ), s.cost


def solve(
    params: Params,
    pk: Packed,
    masks: Masks,
    loss: "str | int | Array" = "huber",
    scale: float | Array = 1.0,
    max_steps: int | Array = 100,
    rtol: float | Array = 1e-10,
    kind_weight: Array | None = None,
    real_only: bool = True,
) -> LMResult:
    """Levenberg-Marquardt from ``params``; returns the solution and a result code.

    Stops when an accepted step lowers the cost by less than ``rtol`` (relative) or
    moves no parameter noticeably, when the next step (damped by at most
    :data:`PREDICT_LAMBDA`) is predicted to lower it by less than that, when the damping
    saturates (stalled), or after
    ``max_steps`` steps tried; the result's ``linearisation`` is at the solution.
    ``max_steps = 0`` only linearises at ``params``: the
    covariance, the bound and the reports use that, so that one compiled solve serves
    them all (``max_steps`` and ``rtol`` are values, not compile-time constants).
    ``kind_weight`` (4,) weighs dots, spots, rim and chess corners (0 drops a kind;
    freeze what it alone determines).  ``real_only``: see :func:`accumulate` (under
    ``vmap`` the loops run to the longest trial's real rows).
    """
    loss = loss_index(loss)
    scale = jnp.asarray(scale, dtype=float)
    kw = kind_weights(kind_weight)

    # the rim rows' normalisation is held at its value at the start: with it varying, the
    # cost would not be the function whose Jacobian the steps use, and near the minimum
    # every step was rejected (measured: 20-30 wasted linearisations per pass)
    rim_norm = rim_norms(params.rig, pk)

    def lin_at(p):
        return linearise(p, pk, masks, loss, scale, kw, rim_norm, real_only)

    # Every iteration linearises at the point it tries (the start first), and the cost comes
    # with it: an accepted step, most of them (measured: 77-100 % of a calibration's steps),
    # needs no other evaluation, a rejected one wastes the Jacobian.  The residual function
    # with derivatives is traced once, in this one place.
    def body(s):
        p, lin, cost, c0, lam, it, _, code, q, dg, dp, pred, pending = s
        lin_q, c_q = lin_at(q)
        ok = jnp.isfinite(c_q) & (c_q < cost)
        rho = (cost - c_q) / jnp.maximum(pred, 1e-300)
        small = (cost - c_q) <= rtol * cost
        tiny = jnp.maximum(jnp.max(jnp.abs(dg)), jnp.max(jnp.abs(dp), initial=0.0)) < 1e-12
        # Nielsen's update: an accepted step that the quadratic model predicted well lowers the
        # damping by up to 3x, a poorly predicted one keeps it (a fixed /3 on every acceptance
        # made the damping oscillate in curved, nearly flat valleys: accepted and rejected
        # steps alternating for hundreds of iterations)
        shrink = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * jnp.clip(rho, 0.0, 1.0) - 1.0) ** 3)
        lam_next = jnp.where(ok, jnp.maximum(lam * shrink, 1e-12), lam * 4.0)
        # at the minimum every step is rejected with a cost equal up to round-off
        flat = jnp.abs(cost - c_q) <= 1e-12 * cost
        converged = (ok & (small | tiny)) | (~ok & (tiny | flat))
        stalled = lam_next > 1e10
        it_next = it + 1
        # the start is taken as it is (no step was tried yet)
        take = ok | ~pending
        p = jax.tree_util.tree_map(lambda a, b: jnp.where(take, a, b), q, p)
        lin = jax.tree_util.tree_map(lambda a, b: jnp.where(take, a, b), lin_q, lin)
        cost = jnp.where(take, c_q, cost)
        c0 = jnp.where(pending, c0, c_q)
        lam = jnp.where(pending, lam_next, lam)
        it = jnp.where(pending, it_next, it)
        code = jnp.where(pending, jnp.where(converged, CONVERGED, jnp.where(stalled, STALLED, MAX_STEPS)), code)
        dg, dp = schur_step(lin.normal, lam)
        pred = predicted_decrease(lin.normal, lam, dg, dp)
        # at a point just taken, a near-Gauss-Newton step whose predicted decrease is under the
        # tolerance is not tried: it would be accepted with a decrease under rtol and end the
        # solve one linearisation later
        settled = take & jnp.isfinite(cost) & (lam <= PREDICT_LAMBDA) & (it < max_steps) & (pred <= rtol * cost)
        code = jnp.where(settled, CONVERGED, code)
        done = (pending & (converged | stalled)) | settled | (it >= max_steps)
        return p, lin, cost, c0, lam, it, done, code, p.retract(dg, dp), dg, dp, pred, jnp.asarray(True)

    lin0 = jax.tree_util.tree_map(jnp.zeros_like, jax.eval_shape(lin_at, params)[0])
    inf = jnp.asarray(jnp.inf)
    state = (
        params,
        lin0,
        inf,
        inf,
        jnp.asarray(LAMBDA_START),
        jnp.asarray(0),
        jnp.asarray(False),
        jnp.asarray(MAX_STEPS),
        params,
        jnp.zeros(params.n_global),
        jnp.zeros((params.n_blocks, 6)),
        jnp.asarray(1.0),  # the start's: no step was tried
        jnp.asarray(False),
    )
    p, lin, cost, c0, _, it, _, code, *_ = jax.lax.while_loop(lambda s: ~s[6], body, state)
    return LMResult(p, cost, c0, it, code, lin)


class Covariance(NamedTuple):
    """Covariance at a solution: global block, per-pose marginals, and the noise estimate."""

    glob: Float[Array, "G G"]
    blocks: Float[Array, "NB 6 6"]
    sigma: Float[Array, ""]
    dof: Int[Array, ""]


def schur_inverse(ne: Normal) -> tuple[Array, Array, Array]:
    """``(S^-1, D^-1, D^-1 B^T)``: the global block of ``H^-1`` (``S`` the Schur complement over
    the poses) and the pose blocks' pieces that give theirs."""
    S, Dinv_Bt = schur_complement(ne.A, ne.B, ne.D)
    return jnp.linalg.inv(S), jnp.linalg.inv(ne.D), Dinv_Bt


def leverage_share(full: Normal, part: Normal, part_seen_glob, part_seen_blocks) -> Array:
    """``tr(H^-1 N)``: the parameters' share taken from the rows whose normal equations are
    ``part`` (:func:`finish_normal`'s, ``part_seen_*`` its reach), ``H`` being ``full``'s.

    Summed over the rows it is the sum of their leverages (the diagonal of ``W J H^-1 J^T``):
    how many of the estimated parameters those rows fix, so that their residuals are smaller
    than their noise by that many squared sigmas.  Over a partition of all the rows the
    shares add up to the number of estimated parameters.  ``finish_normal``'s unit diagonals
    of what ``part`` does not reach are taken off first."""
    return _share(schur_inverse(full), part, part_seen_glob, part_seen_blocks)


def leverage_shares(full: Normal, parts: Normal, parts_seen_glob, parts_seen_blocks) -> Array:
    """:func:`leverage_share` of each of several parts (their arrays stacked on a leading
    axis), ``H^-1`` taken once."""
    inv = schur_inverse(full)
    return jax.vmap(lambda p, g, b: _share(inv, p, g, b))(parts, parts_seen_glob, parts_seen_blocks)


def _share(inv, part: Normal, part_seen_glob, part_seen_blocks) -> Array:
    Sinv, Dinv, Dinv_Bt = inv
    raw = raw_normal(part, part_seen_glob, part_seen_blocks)
    A, D = raw.A, raw.D
    # the blocks of H^-1: S^-1; -S^-1 (D_k^-1 B_k^T)^T; D_k^-1 + D_k^-1 B_k^T S^-1 B_k D_k^-1
    t = jnp.trace(Sinv @ A)
    t = t - 2.0 * jnp.einsum("gh,kih,kgi->", Sinv, Dinv_Bt, part.B)
    t = t + jnp.einsum("kij,kji->", Dinv, D)
    return t + jnp.einsum("kig,gh,kjh,kji->", Dinv_Bt, Sinv, Dinv_Bt, D)


def pooled_noise(lin: Linearisation, masks: Masks) -> tuple[Array, Array]:
    """The pooled noise variance ``sum(w r^2) / (n - k)`` over the valid scalar residuals (``n``)
    and the estimated parameters the weighted rows reach (``k``), and ``n - k``."""
    k = jnp.sum(masks.glob * lin.seen_glob) + 6 * jnp.sum(masks.blocks * lin.seen_blocks)
    dof = (lin.n_valid - k).astype(jnp.int64)
    return lin.weighted_sq / jnp.maximum(dof, 1).astype(float), dof


def covariance_of_linearisation(lin: Linearisation, masks: Masks, sigma: float | Array | None = None) -> Covariance:
    """``sigma^2 (J^T W J)^-1`` by the Schur complement; ``sigma`` from the residuals when None.

    The residual estimate is ``sum(w r^2) / (n - k)`` over the valid scalar residuals
    (``n``) and the estimated parameters (``k``).  Frozen parameters get zero variance.
    """
    pooled, dof = pooled_noise(lin, masks)
    s2 = pooled if sigma is None else jnp.asarray(sigma, dtype=float) ** 2
    Sinv, Dinv, Dinv_Bt = schur_inverse(lin.normal)
    cov_p = s2 * (Dinv + jnp.einsum("kig,gh,kjh->kij", Dinv_Bt, Sinv, Dinv_Bt))
    return _estimated_only(lin, masks, Covariance(s2 * Sinv, cov_p, jnp.sqrt(s2), dof))


def _estimated_only(lin: Linearisation, masks: Masks, cov: Covariance) -> Covariance:
    """``cov`` with zero (co)variance for the frozen parameters and those no weighted row reaches."""
    mg = masks.glob * lin.seen_glob
    return cov._replace(
        glob=cov.glob * mg[:, None] * mg[None, :], blocks=cov.blocks * (masks.blocks * lin.seen_blocks)[:, None, None]
    )


def raw_normal(part: Normal, seen_glob, seen_blocks) -> Normal:
    """``part`` (:func:`finish_normal`'s) without the unit diagonals it gave what its rows do not
    reach (``seen_*``): the plain sums ``J^T W J`` of its rows."""
    return part._replace(
        A=part.A - jnp.diag(1.0 - seen_glob), D=part.D - (1.0 - seen_blocks)[:, None, None] * jnp.eye(6)
    )


def sandwich_covariance(lin: Linearisation, meat: Normal, masks: Masks) -> Covariance:
    """``H^-1 M H^-1`` by the Schur complement: the covariance of the solution of the normal
    equations ``H`` (``lin``'s) when its rows' noise gives ``J^T W Cov(r) W J = M`` (``meat``, a
    plain sum in Schur form, :func:`raw_normal`), as where each kind of observation has its own
    noise sigma and ``M = sum_k sigma_k^2 N_k``.  With ``M = sigma^2 H`` it is
    :func:`covariance_of_linearisation`'s.  ``sigma`` and ``dof`` are the pooled ones.

    With ``E_k = D_k^-1 B_k^T`` the global block is ``S^-1 (A_M - sum_k (C_k E_k + E_k^T C_k^T)
    + sum_k E_k^T D_Mk E_k) S^-1`` (``C_k`` block ``k``'s coupling in ``M``) and pose block ``k``'s
    ``E_k G E_k^T - E_k S^-1 F_k D_k^-1 - (..)^T + D_k^-1 D_Mk D_k^-1`` with
    ``F_k = C_k - E_k^T D_Mk``."""
    Sinv, Dinv, E = schur_inverse(lin.normal)
    C = meat.B  # (NB, G, 6)
    CE = jnp.einsum("kgi,kih->gh", C, E)
    inner = meat.A - CE - CE.T + jnp.einsum("kig,kij,kjh->gh", E, meat.D, E)
    cov_g = Sinv @ inner @ Sinv
    F = C - jnp.einsum("kig,kij->kgj", E, meat.D)  # (NB, G, 6)
    cross = jnp.einsum("kig,gh,khj,kjl->kil", E, Sinv, F, Dinv)
    cov_p = (
        jnp.einsum("kig,gh,kjh->kij", E, cov_g, E)
        - cross
        - jnp.swapaxes(cross, 1, 2)
        + jnp.einsum("kij,kjl,klm->kim", Dinv, meat.D, Dinv)
    )
    s2, dof = pooled_noise(lin, masks)
    return _estimated_only(lin, masks, Covariance(cov_g, cov_p, jnp.sqrt(s2), dof))


def residual_rows(params: Params, pk: Packed) -> Rows:
    """The residual rows at ``params`` without Jacobians (for reports)."""
    return _rows(params, pk, with_jac=False)
