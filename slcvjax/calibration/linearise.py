"""The joint problem linearised: residual rows with their local Jacobians, summed into the normal
equations chunk by chunk.

The observations fall into groups, each with one residual function (:func:`observation_groups`):
dots and spots (a 3D point, then one projection through the mirror), rim pixels, the direct views'
chessboard corners, and the samples of line and ring lasers' stripes.  :func:`accumulate` loops over chunks of each
group's real rows (:data:`CHUNKS`), so that a shape bucket's padding costs only memory, and sums the
normal equations (:mod:`slcvjax.calibration.schur`), the robust cost
(:mod:`slcvjax.calibration.losses`) and the per-observation table.  :func:`rows_at` gives every row
at once, reverse-differentiable (the design's bound and the implicit derivative use it).
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ..geometry.sheets import CONE_DOF
from ..observations.problem import Kind, Packed, kind_weights
from .losses import ObservationTable, robust_observations
from .params import N_CAM, N_CM, N_LAS, N_MIR, Masks, Params, element_columns
from .residuals import (
    chess_residual,
    dot_point,
    dot_point_box,
    point_residual,
    rim_norms,
    rim_residual,
    spot_point,
    spot_point_box,
    stripe_residual,
    stripe_residual_box,
)
from .schur import Normal, Rows, add_rows, finish_normal, zero_normal

# observations per step of the loop in :func:`accumulate`: dots and spots, rim pixels, corners, stripe samples
CHUNKS = (64, 256, 128, 128)


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


def observation_groups(params: Params, pk: Packed, with_jac: bool, rim_norm: Array | None) -> list[Group]:
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

    # an element's columns in every row: a point laser's 4, or 6 where the rig has sheets (a cone's 6)
    n_el = CONE_DOF if rig.has_sheets else N_LAS
    cm_idx = jnp.arange(N_CM)
    unused = jnp.full(n_el + extra, g)
    point_elements = jnp.asarray(rig.point_elements) if rig.kinds and las.n else None

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
            x, jx, ok_x = jax.vmap(lambda *a: lin(dot_point_box, N_LAS + 12, *a))(R, t, Rb, tb, xb)
        else:
            block = pose
            R, t = params.poses.R[pose], params.poses.t[pose]
            x, jx, ok_x = jax.vmap(lambda *a: lin(dot_point, N_LAS + 6, *a))(R, t, xb)
        if las.n:

            def spot_points():
                if box:
                    return jax.vmap(lambda *a: lin(spot_point_box, N_LAS + 12, *a))(
                        las.points[laser], las.directions[laser], R, t, Rb, tb
                    )
                return jax.vmap(lambda *a: lin(spot_point, N_LAS + 6, *a))(
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
        r, j, ok = jax.vmap(lambda x, px: lin(point_residual, N_CM + 3, cam, mir, x, px))(x, px)
        j = jnp.concatenate([j[:, :, :N_CM], j[:, :, N_CM:] @ jx], axis=2)
        if n_el > N_LAS:  # the element's unused columns
            j = jnp.concatenate(
                [j[:, :, : N_CM + N_LAS], jnp.zeros(j.shape[:2] + (n_el - N_LAS,)), j[:, :, N_CM + N_LAS :]], axis=2
            )
        element = laser if point_elements is None else point_elements[laser]
        lidx = jnp.where(spot[:, None], element_columns(rig, element, n_el, g), g)
        parts = [jnp.broadcast_to(cm_idx, (r.shape[0], N_CM)), lidx]
        if box:
            parts.append(jnp.where((in_box < n_box)[:, None], rig.tangent_dim + 6 * in_box[:, None] + jnp.arange(6), g))
        gidx = jnp.concatenate(parts, axis=1)
        w = N_CM + n_el + extra
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
        r, j, ok = jax.vmap(lambda uv, s: lin(rim_residual, N_CM, cam, mir, uv, s))(uv, norm)
        k = r.shape[0]
        return Chunk(
            r,
            jnp.concatenate([j, jnp.zeros((k, 1, n_el + extra))], axis=2),
            jnp.broadcast_to(jnp.concatenate([cm_idx, unused]), (k, N_CM + n_el + extra)),
            jnp.zeros((k, 1, 6)),
            jnp.full(k, nb),
            ok,
            jnp.full(k, 2),
        )

    norm = jax.lax.stop_gradient(rim_norms(rig, pk, real_only=False) if rim_norm is None else rim_norm)
    rim_group = Group(rim, (pk.rim_pixels, norm), [(0, pk.counts[Kind.RIM])], CHUNKS[1], N_CM, posed=False)

    def chess(xb, px, pose, spot_chunk=None):
        R, t = params.chess.R[pose], params.chess.t[pose]
        r, j, ok = jax.vmap(lambda *a: lin(chess_residual, N_CAM + 6, cam, *a))(R, t, xb, px)
        k = r.shape[0]
        return Chunk(
            r,
            jnp.concatenate([j[:, :, :N_CAM], jnp.zeros((k, 2, N_MIR + n_el + extra))], axis=2),
            jnp.broadcast_to(
                jnp.concatenate([jnp.arange(N_CAM), jnp.full(N_MIR + n_el + extra, g)]), (k, N_CM + n_el + extra)
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
    if not pk.has_stripes:
        return [dots_spots, rim_group, chess_group]

    sh = rig.sheets
    sheet_elements = jnp.asarray(rig.sheet_elements)
    is_cone = jnp.asarray(sh.is_cone)

    def stripes(pose, sheet, uv, spot_chunk=None):
        p, a, th, cone = sh.apex[sheet], sh.axis[sheet], sh.half_angle[sheet], is_cone[sheet]
        if box:
            block, in_box = pk.pair_block[pose], pk.pair_box[pose]
            R, t = params.poses.R[block], params.poses.t[block]
            Rb, tb = box_R[in_box], box_t[in_box]
            r, j, ok = jax.vmap(lambda *a: lin(stripe_residual_box, N_CM + CONE_DOF + 12, cam, mir, *a))(
                p, a, th, cone, R, t, Rb, tb, uv
            )
        else:
            block = pose
            R, t = params.poses.R[pose], params.poses.t[pose]
            r, j, ok = jax.vmap(lambda *a: lin(stripe_residual, N_CM + CONE_DOF + 6, cam, mir, *a))(
                p, a, th, cone, R, t, uv
            )
        k = r.shape[0]
        parts = [jnp.broadcast_to(cm_idx, (k, N_CM)), element_columns(rig, sheet_elements[sheet], CONE_DOF, g)]
        if box:
            parts.append(jnp.where((in_box < n_box)[:, None], rig.tangent_dim + 6 * in_box[:, None] + jnp.arange(6), g))
        w = N_CM + CONE_DOF + extra
        return Chunk(
            r, j[:, :, :w], jnp.concatenate(parts, axis=1), j[:, :, w:], block, ok, jnp.full(k, int(Kind.STRIPE))
        )

    stripe_group = Group(
        stripes,
        (pk.stripe_pose, pk.stripe_sheet, pk.stripe_pixels),
        [(0, pk.counts[Kind.STRIPE])],
        CHUNKS[3],
    )
    return [dots_spots, rim_group, chess_group, stripe_group]


def flat_rows(c: Chunk, present: Bool[Array, " k"], first_obs) -> Rows:
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


def rows_at(params: Params, pk: Packed, with_jac: bool = True, rim_norm: Array | None = None) -> Rows:
    """Every residual row with its local Jacobian, padding included (zeroed), in one ``vmap``
    per group (reverse-differentiable; the solver uses :func:`accumulate` instead).

    ``rim_norm``: the rim rows' normalisations (:func:`rim_norms`), held as constants; by
    default those of ``params`` itself, so that the rim rows are the pixels' first-order
    distances from the rim (the Jacobian still holds them constant).  The LM passes the
    normalisation at its start, so that its cost and its Jacobian describe one function.
    """
    parts, offset = [], 0
    for grp in observation_groups(params, pk, with_jac, rim_norm):
        n = grp.args[0].shape[0]
        present = present_rows(grp.regions, n)
        parts.append(flat_rows(grp.fn(*grp.args), present, offset))
        offset += n
    return Rows(*(jnp.concatenate(p) for p in zip(*parts, strict=True)))


def kind_spans(regions, n: int) -> list[tuple[int, int, Array]]:
    """``(start, end, real_end)`` of each kind's rows in a group of ``n`` rows (see :class:`Group`):
    its rows are ``start:end``, the real ones ``start:real_end``."""
    ends = [s for s, _ in regions[1:]] + [n]
    return [(s, e, s + jnp.minimum(count, e - s)) for (s, count), e in zip(regions, ends, strict=True)]


def present_rows(regions, n: int) -> Bool[Array, " n"]:
    """Which rows of a group of ``n`` rows are real."""
    idx = jnp.arange(n)
    out = jnp.zeros(n, dtype=bool)
    for start, _, real_end in kind_spans(regions, n):
        out = out | ((idx >= start) & (idx < real_end))
    return out


def n_observations(pk: Packed) -> int:
    n = pk.dot_pose.shape[0] + pk.spot_pose.shape[0] + pk.rim_pixels.shape[0] + pk.chess_pose.shape[0]
    return n + (pk.stripe_pose.shape[0] if pk.has_stripes else 0)


def chunk_bounds(spans, n: int, k: int, i, n_chunks):
    """Chunk ``i`` of a group (``spans`` from :func:`kind_spans`): where it starts (moved back to
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
    chunks of each group's observations (:data:`CHUNKS`; see :func:`observation_groups`).

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
    for grp in observation_groups(params, pk, with_jac and masks is not None, rim_norm):
        n = grp.args[0].shape[0]
        if n == 0:
            sq_parts.append(jnp.zeros(0))
            valid_parts.append(jnp.zeros(0, dtype=bool))
            continue
        k = min(grp.chunk, n)
        spans = kind_spans(grp.regions, n)
        n_chunks = [((r if real_only else e) - s + k - 1) // k for s, e, r in spans]

        def body(i, carry, grp=grp, n=n, k=k, spans=spans, n_chunks=n_chunks):
            ne, sq, valid, cost, n_valid, wsq = carry
            start, meant, real_end = chunk_bounds(spans, n, k, i, n_chunks)
            idx = start + jnp.arange(k)
            present = (idx >= meant) & (idx < real_end)
            c = grp.fn(
                *(jax.lax.dynamic_slice_in_dim(a, start, k) for a in grp.args), spot_chunk=meant >= grp.regions[-1][0]
            )
            rows = flat_rows(c, present, 0)
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


class Linearisation(NamedTuple):
    """The problem linearised at a point: the normal equations and what the covariance and reports need."""

    normal: Normal
    table: ObservationTable
    seen_glob: Float[Array, " G"]  # 1 where an estimated global parameter has a weighted observation
    seen_blocks: Float[Array, " NB"]  # 1 where an estimated pose block has one
    n_valid: Float[Array, ""]  # valid scalar residuals
    weighted_sq: Float[Array, ""]  # sum of w r^2


def cost_at(params, pk, loss, scale, kind_weight, rim_norm=None, real_only=True) -> Float[Array, ""]:
    """The robust cost alone at ``params`` (no Jacobian): the cost :func:`solve` judges its
    steps by, which its linearisation returns with the normal equations."""
    return accumulate(params, pk, None, loss, scale, kind_weight, rim_norm, False, real_only).cost


def table_arrays(params: Params, pk: Packed) -> tuple[Array, Array, Array]:
    """Per observation (dots, spots, rim pixels, corners, stripe samples): its kind, whether it is
    real, its pose block."""
    sizes = [pk.dot_pose.shape[0], pk.spot_pose.shape[0], pk.rim_pixels.shape[0], pk.chess_pose.shape[0]]
    if pk.has_stripes:
        sizes.append(pk.stripe_pose.shape[0])
    kind = jnp.concatenate([jnp.full(n, k, dtype=int) for n, k in zip(sizes, Kind, strict=False)])
    dot_block, spot_block = pk.dot_pose, pk.spot_pose
    stripe_block = pk.stripe_pose
    if params.box is not None:
        dot_block, spot_block = pk.pair_block[dot_block], pk.pair_block[spot_block]
        stripe_block = None if stripe_block is None else pk.pair_block[stripe_block]
    parts = [dot_block, spot_block, jnp.full(sizes[2], params.n_blocks), params.poses.t.shape[0] + pk.chess_pose]
    if pk.has_stripes:
        parts.append(stripe_block)
    block = jnp.concatenate(parts)
    return kind, jnp.concatenate(pk.present()), block


def table_at(params: Params, pk: Packed) -> ObservationTable:
    """The per-observation table at ``params`` without the normal equations (the cost's pass
    over the real observations): what :class:`Linearisation` ``.table`` holds after a solve with
    no step, for a fraction of its work (the rim rows normalised at ``params``, as there)."""
    s = accumulate(params, pk, None, 0, 1.0, None, rim_norms(params.rig, pk), False)
    kind, present, block = table_arrays(params, pk)
    return ObservationTable(s.sq, kind, s.valid, present, block)


def linearise(params: Params, pk: Packed, masks: Masks, loss: str, scale, kind_weight, rim_norm=None, real_only=True):
    """:class:`Linearisation` at ``params`` and the robust cost there (``real_only``: see :func:`accumulate`)."""
    s = accumulate(params, pk, masks, loss, scale, kind_weight, rim_norm, True, real_only)
    # what the weighted rows reach, from the diagonals (with every kind weighted, as the
    # covariance is, that is every parameter with a valid observation)
    ne, seen_glob, seen_blocks = finish_normal(s.normal, masks.glob, masks.blocks)
    kind, present, block = table_arrays(params, pk)
    table = ObservationTable(s.sq, kind, s.valid, present, block)
    return Linearisation(
        ne, table, seen_glob.astype(float), seen_blocks.astype(float), s.n_valid, s.weighted_sq
    ), s.cost


def residual_rows(params: Params, pk: Packed) -> Rows:
    """The residual rows at ``params`` without Jacobians (for reports)."""
    return rows_at(params, pk, with_jac=False)
