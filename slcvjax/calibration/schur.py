"""Normal equations in Schur form, their damped solve, and the blocks of their inverse.

The rows (:class:`Rows`) are scattered into ``H = J^T W J`` and ``g = J^T W r``.  With
``H = [[A, B], [B^T, D]]``, ``A`` over the global block and ``D`` block-diagonal (6 x 6 per pose),
the damped step solves the reduced system

    (A - B D^-1 B^T) dg = -g_g + B D^-1 g_p,      dp = D^-1 (-g_p - B^T dg),

whose cost grows linearly with the number of views (:func:`schur_step`; :func:`dense_step` is the
same step from the dense system, for tests).  :func:`schur_inverse` gives the global block of
``H^-1`` and the pieces of the pose blocks', which the covariance and the leverages use.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int


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


def raw_normal(part: Normal, seen_glob, seen_blocks) -> Normal:
    """``part`` (:func:`finish_normal`'s) without the unit diagonals it gave what its rows do not
    reach (``seen_*``): the plain sums ``J^T W J`` of its rows."""
    return part._replace(
        A=part.A - jnp.diag(1.0 - seen_glob), D=part.D - (1.0 - seen_blocks)[:, None, None] * jnp.eye(6)
    )
