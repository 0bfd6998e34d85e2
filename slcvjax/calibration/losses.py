"""Robust losses and the per-observation table they act on.

Dots and spots are weighed by a robust loss (Huber or Cauchy with scale ``c`` px, or plain least
squares) on each observation's 2D residual norm, by iteratively reweighted least squares; the rim
and the direct views' corners are plain.  An observation the model cannot predict (off the mirror
or the sensor) costs what a residual of :data:`INVALID_PX` costs.  The loss is a value, not a
compile-time constant (:func:`loss_index`), so that every loss shares one compilation.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ..observations.problem import ROBUST_KINDS, kind_weights
from .options import LOSSES
from .schur import Rows

INVALID_PX = 30.0  # an invalid observation costs what a residual of this many px costs under the loss


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
