"""Batched joint solves for sweeps: a plain loop over the compiled solve against ``vmap`` over trials.

Run: ``python benchmarks/bench_sweep.py [--trials 16] [--out FILE]``.

Each trial is the paper preset at 0.5 px with its own noise seed, started from the
perturbed truth (as in ``bench_calibrate.py``), solved by the project's Schur LM with
plain squares.  Every trial has the same shapes, so both ways compile once:

* ``loop``: the jitted solve called once per trial;
* ``vmap``: one jitted ``vmap`` of the solve over all trials (the batch runs until its
  slowest trial converges, and under ``vmap`` both branches of every ``cond`` run).

Reports calibrations (joint solves) per second for each, compilation apart, on the
default JAX device; run it where a GPU is present to time both there.

``--whole N`` also times N whole calibrations (staged pipeline, every joint pass, the
covariance) through ``calibrate_many`` with ``batch="loop"`` and ``batch="vmap"`` (the
passes of all trials in lockstep, the trial axis sharded over ``jax.devices()``; force
several CPU devices with ``XLA_FLAGS=--xla_force_host_platform_device_count=K``).
"""

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from bench_forward import machine

from slcvjax import calibrate_many, make_scene, simulate
from slcvjax.calibration.params import Params, make_masks
from slcvjax.observations.problem import pack, stack_poses


def perturbed_truth(truth, pk, seed: int) -> Params:
    """The joint solve's start of trial ``seed``: the simulated truth (rig, board and direct-view
    poses of the packed problem ``pk``) moved by 1e-3 in every tangent coordinate."""
    poses = stack_poses([truth.board_poses[v][b] for v, b in pk.pose_keys])
    chess = stack_poses([truth.calibration_view_poses[c] for c in pk.chess_keys])
    p_true = Params(truth.rig, poses, chess)
    rng = np.random.default_rng(10_000 + seed)
    dg = rng.normal(0, 1e-3, p_true.n_global)
    dp = rng.normal(0, 1e-3, (p_true.n_blocks, 6))
    return p_true.retract(jnp.asarray(dg), jnp.asarray(dp))


def trials(n: int):
    scene = make_scene("paper")
    starts, packs = [], []
    for seed in range(n):
        obs, truth = simulate(scene, noise=0.5, seed=seed)
        pk = pack(obs)
        starts.append(perturbed_truth(truth, pk, seed))
        packs.append(pk.arrays())
    masks = make_masks(starts[0])
    return starts, packs, masks


def whole(n: int) -> dict:
    """Whole calibrations of ``n`` preset trials (0.5 px) by ``calibrate_many``: loop against vmap."""
    scene = make_scene("paper")
    obs = [simulate(scene, noise=0.5, seed=seed)[0] for seed in range(n)]
    out = {"trials": n, "devices": [str(d) for d in jax.devices()]}
    for mode in ("loop", "vmap"):
        t0 = time.perf_counter()
        calibrate_many(obs[:1] if mode == "loop" else obs, batch=mode)  # compiles (vmap: for n trials)
        first = time.perf_counter() - t0
        t0 = time.perf_counter()
        res = calibrate_many(obs, batch=mode)
        run = time.perf_counter() - t0
        out[mode] = {
            "compile_s": first - (run / n if mode == "loop" else run),
            "run_s": run,
            "calibrations_per_s": n / run,
            "converged": sum(r.passes[-1].converged for r in res),
        }
        print(f"whole calibrations, {mode}: {n / run:.2f} per s ({run:.1f} s for {n})", flush=True)
    out["vmap_over_loop"] = out["vmap"]["calibrations_per_s"] / out["loop"]["calibrations_per_s"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=16)
    ap.add_argument("--whole", type=int, default=0, help="also time this many whole calibrations (0: none)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    starts, packs, masks = trials(args.trials)
    kw = jnp.ones(4)

    def one(p, pk):
        return solve(p, pk, masks, loss="linear", scale=1.0, max_steps=200, kind_weight=kw)

    solve = jax.jit(one)
    t0 = time.perf_counter()
    jax.block_until_ready(solve(starts[0], packs[0]).cost)
    loop_compile = time.perf_counter() - t0
    t0 = time.perf_counter()
    steps = []
    for p, pk in zip(starts, packs, strict=True):
        r = solve(p, pk)
        steps.append(int(r.steps))
    loop_s = time.perf_counter() - t0

    stack = lambda xs: jax.tree_util.tree_map(lambda *a: jnp.stack(a), *xs)  # noqa: E731
    bp, bk = stack(starts), stack(packs)
    batched = jax.jit(jax.vmap(one))
    t0 = time.perf_counter()
    jax.block_until_ready(batched(bp, bk).cost)
    vmap_first = time.perf_counter() - t0
    t0 = time.perf_counter()
    rb = batched(bp, bk)
    jax.block_until_ready(rb.cost)
    vmap_s = time.perf_counter() - t0
    loop_costs = np.array([float(solve(p, k).cost) for p, k in zip(starts, packs, strict=True)])
    same = float(np.max(np.abs(np.asarray(rb.cost) - loop_costs) / loop_costs))
    out = {
        "benchmark": "sweep",
        "machine": machine(),
        "trials": args.trials,
        "loop": {"compile_s": loop_compile, "run_s": loop_s, "calibrations_per_s": args.trials / loop_s},
        "vmap": {"compile_s": vmap_first - vmap_s, "run_s": vmap_s, "calibrations_per_s": args.trials / vmap_s},
        "steps": {"min": min(steps), "median": float(np.median(steps)), "max": max(steps)},
        "max_relative_cost_difference": same,
    }
    out["vmap_over_loop"] = out["vmap"]["calibrations_per_s"] / out["loop"]["calibrations_per_s"]
    if args.whole > 0:
        out["whole"] = whole(args.whole)
    print(json.dumps(out, indent=1))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
