"""How a pass's solves run over several calibrations: one after another, or in lockstep.

A pass of the schedule hands its solves (:class:`SolveJob`) to an executor: :func:`solve_loop`
runs each through the compiled solve (fastest on a CPU), :func:`solve_vmap` stacks the jobs of
equal shapes into one ``vmap``-ped solve whose trial axis is sharded over the JAX devices.
"""

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..observations.problem import Packed, kind_weights
from .evaluate import solve_compiled
from .lm import LMResult, solve
from .losses import loss_index
from .params import Masks, Params


def resolve_batch(batch: str) -> str:
    """``loop`` or ``vmap`` for :func:`calibrate_many`'s ``batch`` (``auto``: ``loop`` on a CPU)."""
    if batch == "auto":
        return "loop" if jax.default_backend() == "cpu" else "vmap"
    if batch not in ("loop", "vmap"):
        raise ValueError(f"batch: expected auto, loop or vmap, got {batch!r}")
    return batch


class SolveJob(NamedTuple):
    """One LM solve of a pass (:func:`solve_job`): its start, problem and masks padded to the trial's
    shape buckets, its loss scale (px), kind weights (None: all 1) and relative cost tolerance."""

    params: Params
    arrays: Packed
    masks: Masks
    scale: float
    kind_weight: tuple[float, float, float, float] | None
    rtol: float

    def shape_key(self) -> tuple:
        """What decides its compilation: the structure and shapes of its arrays."""
        leaves, tree = jax.tree_util.tree_flatten((self.params, self.arrays, self.masks))
        return tree, tuple(jnp.shape(x) for x in leaves)


def solve_loop(jobs: list[SolveJob], loss: str, max_steps: int, size: int | None = None) -> list[LMResult]:
    """Each job through the compiled solve, one after the other (``size``: unused)."""
    return [solve_compiled(j.params, j.arrays, j.masks, loss, j.scale, max_steps, j.rtol, j.kind_weight) for j in jobs]


@jax.jit
def solve_batched(params, arr, masks, scale, kind_weight, rtol, loss, max_steps):
    def one(p, a, m, sc, kw, rt):
        # a loop over the real rows under vmap runs slowly (measured: the sharded lockstep test
        # ran past its 15-minute limit), so the trials' layouts are fine and every row is visited
        return solve(p, a, m, loss=loss, scale=sc, max_steps=max_steps, rtol=rt, kind_weight=kw, real_only=False)

    return jax.vmap(one)(params, arr, masks, scale, kind_weight, rtol)


def _trial_sharding(n: int):
    """``(padded size, sharding)`` for a trial axis of ``n`` over all devices (None for one)."""
    devices = jax.devices()
    if len(devices) == 1:
        return n, None
    mesh = jax.sharding.Mesh(np.asarray(devices), ("trials",))
    return -(-n // len(devices)) * len(devices), jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("trials"))


def _place(x, sharding):
    """``x`` (the same on every process) as a global array laid out by ``sharding``."""
    host = np.asarray(x)
    return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])


def solve_vmap(jobs: list[SolveJob], loss: str, max_steps: int, size: int | None = None) -> list[LMResult]:
    """The jobs as ``vmap``-ped solves, one per group of equal sizes, sharded over the devices.

    Each group is padded to ``size`` (the number of trials; and to a multiple of the
    device count) by repeating its last job, so that every pass of a lockstep
    calibration reuses one compilation.
    """
    shapes = [j.shape_key() for j in jobs]
    out: list = [None] * len(jobs)
    for key in dict.fromkeys(shapes):
        idx = [i for i, k in enumerate(shapes) if k == key]
        n, sharding = _trial_sharding(max(size or 0, len(idx)))
        group = [jobs[i] for i in idx + [idx[-1]] * (n - len(idx))]

        def stacked(*trees):
            return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *trees)

        batch = (
            stacked(*(j.params for j in group)),
            stacked(*(j.arrays for j in group)),
            stacked(*(j.masks for j in group)),
            jnp.asarray([j.scale for j in group], dtype=float),
            jnp.stack([kind_weights(j.kind_weight) for j in group]),
            jnp.asarray([j.rtol for j in group], dtype=float),
        )
        if sharding is not None:
            # every process holds the whole batch (the same on each): each device takes its rows
            batch = jax.tree_util.tree_map(functools.partial(_place, sharding=sharding), batch)
        res = solve_batched(*batch, loss=jnp.asarray(loss_index(loss)), max_steps=jnp.asarray(max_steps))
        if not res.cost.is_fully_addressable:  # several hosts: every process gets every trial
            from jax.experimental import multihost_utils

            res = multihost_utils.process_allgather(res, tiled=True)
        for j, i in enumerate(idx):
            out[i] = jax.tree_util.tree_map(lambda x, j=j: x[j], res)
    return out
