"""The compiled solve and the per-observation residuals at a solution, through the shape buckets.

:func:`solve_compiled` is :func:`slcvjax.calibration.lm.solve` compiled once (a
:class:`slcvjax.support.persist.PersistentJit`): the loss, the step limit, the tolerance and the
kind weights are values, so every pass, the covariance, the bound and the reports share one
program per shape bucket.  A solve with no step only linearises.  :func:`per_observation`,
:func:`block_costs_at` and :func:`probe_at` read the residual table at a solution (the last few
tables are kept: a fit looks at one solution's table several times).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from ..observations.problem import Kind, Layout, Packed, kind_weights
from ..support.persist import PersistentJit
from ..support.recent import Recent
from .linearise import table_at
from .lm import solve
from .losses import block_costs, loss_index
from .params import Masks, Params, make_masks, pad_params, pad_problem

_solve_jit = PersistentJit(solve, "solve")


_table_jit = PersistentJit(table_at, "observation_table")


def solve_compiled(
    params: Params, arr: Packed, masks: Masks, loss: str, scale, max_steps: int, rtol=1e-10, kind_weight=None
):
    """:func:`slcvjax.calibration.lm.solve` compiled once: the loss, the step limit, the tolerance and the kind
    weights are values, so every pass, the covariance, the bound and the reports share it."""
    return _solve_jit(
        params,
        arr,
        masks,
        jnp.asarray(loss_index(loss)),
        jnp.asarray(scale, dtype=float),
        jnp.asarray(max_steps),
        jnp.asarray(rtol, dtype=float),
        kind_weights(kind_weight),
    )


_block_costs_jit = jax.jit(block_costs, static_argnames=("n_blocks",))


def linearisation_at(
    params: Params, pk: Packed, masks: Masks | None = None, loss: str = "huber", scale=1.0, kind_weight=None
):
    """The padded problem's layout and its :class:`slcvjax.calibration.linearise.Linearisation` at ``params`` (the
    compiled solve with no step; ``kind_weight``: each kind's weight, None: all 1)."""
    layout, p, arr, m = pad_problem(params, pk, make_masks(params) if masks is None else masks)
    return layout, solve_compiled(p, arr, m, loss, scale, 0, kind_weight=kind_weight).linearisation


_TABLES = Recent(4)  # the last calls of table_of
_SOLUTIONS = Recent(2)  # the last calls of solution_linearisation


def solution_linearisation(params: Params, pk: Packed, masks: Masks, loss: str, scale):
    """The padded problem (:func:`slcvjax.calibration.params.pad_problem`: layout, parameters,
    arrays, masks) and its :class:`slcvjax.calibration.linearise.Linearisation` at ``params``
    with every kind weighted 1 (the compiled solve with no step).  The last two are kept: the
    covariance at the end of a calibration and the report's final check linearise the same
    solution (found again by the identity of ``params``, ``pk`` and ``masks``)."""

    def compute():
        layout, p, padded, m = pad_problem(params, pk, masks)
        return layout, p, padded, m, solve_compiled(p, padded, m, loss, scale, 0).linearisation

    return _SOLUTIONS.get((params, pk, masks), (loss, float(scale)), compute)


def table_of(params: Params, pk: Packed):
    """The padded problem's layout and its :class:`slcvjax.calibration.losses.ObservationTable` at
    ``params`` (the last few kept: a fit looks at one solution's table several times)."""

    def compute():
        layout = Layout.of(pk, n_lasers=params.rig.lasers.n, sheet_dim=params.rig.sheet_dim)
        return layout, _table_jit(pad_params(layout, params), layout.pad_packed(pk))

    return _TABLES.get((params, pk), None, compute)


def per_observation(params: Params, pk: Packed) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per observation: its 2D residual norm (px), its kind and whether it is valid."""
    layout, t = table_of(params, pk)
    return tuple(layout.unpad_observations(a) for a in (np.sqrt(np.asarray(t.sq)), t.kind, t.valid))


def block_costs_at(params: Params, pk: Packed, loss: str, scale: float) -> np.ndarray:
    """Per pose block (board poses, then direct views) the robust cost of its observations."""
    layout, t = table_of(params, pk)
    costs = _block_costs_jit(t, n_blocks=layout.cap[4] + layout.cap[5], loss=jnp.asarray(loss_index(loss)), scale=scale)
    return layout.unpad_blocks(costs)


def probe_at(params: Params, pk: Packed, kind: Kind, **rows) -> tuple[np.ndarray, np.ndarray]:
    """Residual norms (px) and validity, at ``params``, of candidate rows of one kind (dots or
    spots; ``rows``: that kind's arrays, of one length) put in place of ``pk``'s own rows of that
    kind: how candidate labels are tried."""
    c = np.asarray(pk.counts).copy()
    c[kind] = len(next(iter(rows.values())))
    probe = dataclasses.replace(pk, counts=c, **{("dot_src", "spot_src")[kind]: ()}, **rows)
    norm, _, ok = per_observation(params, probe)
    first = int(c[Kind.DOT]) if kind == Kind.SPOT else 0
    return norm[first : first + int(c[kind])], ok[first : first + int(c[kind])]
