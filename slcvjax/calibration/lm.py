"""Joint Levenberg-Marquardt over the whole rig with a Schur complement over the poses.

:func:`solve` is one ``lax.while_loop`` (jit- and vmap-able) that linearises at every point it tries
(:func:`slcvjax.calibration.linearise.linearise`), takes the damped Schur step
(:func:`slcvjax.calibration.schur.schur_step`) with Nielsen's damping update, and returns a result
code (:class:`Outcome`), never raising.  Within one solve the rim rows' normalisation is held at
its value at the start, so that the cost the steps are judged by is the function whose Jacobian
they use.

Hand-written rather than optimistix's ``LevenbergMarquardt``: on the preset's 16 views from the
same perturbed truth, this solve took 243 ms (6 steps) and optimistix's on the same residuals (a
dense Jacobian) 82 s (124 steps), in one run of ``benchmarks/bench_calibrate.py``
(``benchmarks/results/calibrate_optimistix.json``).
"""

import enum
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ..observations.problem import (
    Packed,
    kind_weights,
)
from .linearise import Linearisation, linearise
from .losses import loss_index
from .params import Masks, Params
from .residuals import rim_norms
from .schur import predicted_decrease, schur_step


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


class LMState(NamedTuple):
    """The loop's state between two iterations of :func:`solve` (immutable: each iteration
    returns a new one)."""

    params: Params  # the current solution
    lin: Linearisation  # the problem linearised there
    cost: Float[Array, ""]  # its robust cost
    initial_cost: Float[Array, ""]  # the cost at the start
    damping: Float[Array, ""]  # Levenberg-Marquardt's lambda, relative to the normal matrix's diagonal
    steps: Int[Array, ""]  # the steps tried so far
    done: Bool[Array, ""]
    code: Int[Array, ""]  # how it ends (:class:`Outcome`), where done
    trial: Params  # the point the next iteration tries
    dg: Float[Array, " G"]  # the step to it: global block
    dp: Float[Array, "NB 6"]  # and pose blocks
    predicted: Float[Array, ""]  # the cost decrease the quadratic model predicts for that step
    pending: Bool[Array, ""]  # False only before the start has been linearised


class LMResult(NamedTuple):
    params: Params
    cost: Float[Array, ""]
    initial_cost: Float[Array, ""]
    steps: Int[Array, ""]
    result: Int[Array, ""]
    linearisation: Linearisation  # at ``params`` (with the rim normalisation held at the start)


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
    def body(s: LMState) -> LMState:
        p, lin, cost, c0, lam, it, code, q, dg, dp, pred, pending = (
            s.params,
            s.lin,
            s.cost,
            s.initial_cost,
            s.damping,
            s.steps,
            s.code,
            s.trial,
            s.dg,
            s.dp,
            s.predicted,
            s.pending,
        )
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
        return LMState(p, lin, cost, c0, lam, it, done, code, p.retract(dg, dp), dg, dp, pred, jnp.asarray(True))

    lin0 = jax.tree_util.tree_map(jnp.zeros_like, jax.eval_shape(lin_at, params)[0])
    inf = jnp.asarray(jnp.inf)
    state = LMState(
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
    end = jax.lax.while_loop(lambda s: ~s.done, body, state)
    return LMResult(end.params, end.cost, end.initial_cost, end.steps, end.code, end.lin)
