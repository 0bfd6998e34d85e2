"""Joint-solve benchmark: the project's Schur LM against scipy.optimize.least_squares.

Run: ``python benchmarks/bench_calibrate.py [--views 16,64,256,1024] [--no-scipy] [--out FILE]``.

On the paper preset (0.5 px noise) every solver starts from the same perturbed truth and
solves the same least-squares problem (plain squares, no robust loss):

* ``schur_lm``: the project's LM (per-observation Jacobians, implicit derivative, Schur
  complement over the poses), compiled once (compile time reported apart);
* ``scipy_fd``: ``least_squares(method="lm")`` with 2-point finite differences of the same
  jitted residual function (the baseline);
* ``scipy_jac``: the same with the project's dense Jacobian (``jax.jacfwd``);
* ``optimistix_lm``: ``optimistix.least_squares`` with its ``LevenbergMarquardt`` (dense
  Jacobian by forward mode, solved by lineax) on the same jitted residual function, the
  whole solve compiled (compile time apart), at the same tolerances.

The scaling part times the Schur LM over more views (one compilation each).  The batch
part times whole calibrations (``calibrate``: staged pipeline, every joint pass, the
covariance) of ``--batch`` simulated preset observation sets one after another: the first
compiles, the others are what one more calibration in a batch costs (goal: 0.5 s on 2
cores), one at a time and two at a time (``calibrate_many(..., workers=2)``).  Results are
printed and written as JSON with the machine's description.
"""

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from bench_forward import machine
from scipy.optimize import least_squares

from slcvjax import calibrate, calibrate_many, make_scene, simulate
from slcvjax.calibration.linearise import residual_rows
from slcvjax.calibration.lm import Outcome, solve
from slcvjax.calibration.params import Params, make_masks
from slcvjax.observations.problem import pack, stack_poses


def problem(n_views: int, seed: int = 1):
    obs, truth = simulate(make_scene("paper", n_views=n_views), noise=0.5, seed=seed)
    pk = pack(obs)
    poses = stack_poses([truth.board_poses[v][b] for v, b in pk.pose_keys])
    chess = stack_poses([truth.calibration_view_poses[c] for c in pk.chess_keys])
    p_true = Params(truth.rig, poses, chess)
    rng = np.random.default_rng(0)
    dg = rng.normal(0, 1e-3, p_true.n_global)
    dp = rng.normal(0, 1e-3, (p_true.n_blocks, 6))
    start = p_true.retract(jnp.asarray(dg), jnp.asarray(dp))
    return start, pk.arrays(), make_masks(start)


solve = jax.jit(solve, static_argnames=("loss", "max_steps"))


def time_schur(start, pk, masks):
    t0 = time.perf_counter()
    res = solve(start, pk, masks, loss="linear", scale=1.0, max_steps=200)
    jax.block_until_ready(res.cost)
    first = time.perf_counter() - t0
    runs = []
    for _ in range(3):
        t0 = time.perf_counter()
        res = solve(start, pk, masks, loss="linear", scale=1.0, max_steps=200)
        jax.block_until_ready(res.cost)
        runs.append(time.perf_counter() - t0)
    run = float(np.median(runs))
    return {
        "compile_s": first - run,
        "run_s": run,
        "steps": int(res.steps),
        "cost": float(res.cost),
        "result": Outcome(int(res.result)).label,
    }


def time_optimistix(resid, x0) -> dict:
    """optimistix's Levenberg-Marquardt on the flat residual ``resid`` from ``x0``, the whole
    solve jitted: compile time apart from the median of three runs."""
    import optimistix as optx

    solver = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10)

    @jax.jit
    def run(x):
        sol = optx.least_squares(lambda y, _: resid(y), solver, x, max_steps=200, throw=False)
        return sol.value, sol.stats["num_steps"], sol.result == optx.RESULTS.successful

    x0 = jnp.asarray(x0)
    t0 = time.perf_counter()
    jax.block_until_ready(run(x0))
    first = time.perf_counter() - t0
    runs = []
    for _ in range(3):
        t0 = time.perf_counter()
        x, steps, ok = jax.block_until_ready(run(x0))
        runs.append(time.perf_counter() - t0)
    run_s = float(np.median(runs))
    cost = 0.5 * float(jnp.sum(resid(x) ** 2))
    return {"compile_s": first - run_s, "run_s": run_s, "steps": int(steps), "cost": cost, "converged": bool(ok)}


def time_batch(n: int) -> dict:
    """Whole calibrations of ``n`` preset observation sets (0.5 px, seeds 100..): first and the rest."""
    scene = make_scene("paper")
    obs = [simulate(scene, noise=0.5, seed=100 + s)[0] for s in range(n)]
    times, staged_s = [], []
    for o in obs:
        t0 = time.perf_counter()
        res = calibrate(o)
        times.append(time.perf_counter() - t0)
        staged_s.append(res.timings["staged_s"])
    rest = np.asarray(times[1:])
    # the same calibrations two at a time (calibrate_many's threads): the batch's time per calibration
    t0 = time.perf_counter()
    calibrate_many(obs[1:], batch="loop", workers=2)
    two = (time.perf_counter() - t0) / (n - 1)
    r = {
        "calibrations": n,
        "first_s": times[0],
        "median_s": float(np.median(rest)),
        "mean_s": float(np.mean(rest)),
        "max_s": float(np.max(rest)),
        "staged_median_s": float(np.median(staged_s[1:])),
        "two_workers_per_calibration_s": two,
        "one_at_a_time_per_calibration_s": float(np.sum(rest) / (n - 1)),
    }
    print(
        f"batch of {n} calibrations (staged + joint + covariance): first {r['first_s']:.1f} s (compiling), "
        f"then median {r['median_s']:.3f} s, mean {r['mean_s']:.3f} s, max {r['max_s']:.3f} s "
        f"(staged median {r['staged_median_s']:.3f} s); two at a time (workers=2): {two:.3f} s per calibration",
        flush=True,
    )
    return r


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", default="16,64,256,1024")
    ap.add_argument("--no-scipy", action="store_true")
    ap.add_argument("--batch", type=int, default=12, help="whole calibrations to time (0: none)")
    ap.add_argument("--out", default="benchmarks/results/calibrate.json")
    args = ap.parse_args()
    out = {"benchmark": "calibrate", "machine": machine()}

    start, pk, masks = problem(16)
    g, nb = start.n_global, start.n_blocks
    n_x = g + 6 * nb
    rows0 = residual_rows(start, pk)
    print(f"paper preset, 16 views: {n_x} parameters, {int(rows0.r.shape[0])} residuals", flush=True)
    ours = time_schur(start, pk, masks)
    out["schur_lm"] = ours
    print(
        f"schur_lm: {ours['run_s'] * 1e3:.0f} ms, {ours['steps']} steps, cost {ours['cost']:.4f} "
        f"(compile {ours['compile_s']:.1f} s)",
        flush=True,
    )

    if not args.no_scipy:

        @jax.jit
        def resid(x):
            p = start.retract(x[:g], x[g:].reshape(nb, 6))
            return residual_rows(p, pk).r

        jac = jax.jit(jax.jacfwd(resid))
        x0 = np.zeros(n_x)
        t0 = time.perf_counter()
        jax.block_until_ready(resid(x0))
        jax.block_until_ready(jac(x0))
        compile_scipy = time.perf_counter() - t0
        for name, kw in [("scipy_jac", {"jac": lambda x: np.asarray(jac(x))}), ("scipy_fd", {"jac": "2-point"})]:
            t0 = time.perf_counter()
            sol = least_squares(lambda x: np.asarray(resid(x)), x0, method="lm", xtol=1e-10, ftol=1e-10, **kw)
            dt = time.perf_counter() - t0
            out[name] = {"run_s": dt, "nfev": int(sol.nfev), "njev": int(sol.njev or 0), "cost": float(sol.cost)}
            print(f"{name}: {dt:.2f} s, {sol.nfev} residual evaluations, cost {sol.cost:.4f}", flush=True)
        out["scipy_compile_s"] = compile_scipy
        out["optimistix_lm"] = time_optimistix(resid, x0)
        o = out["optimistix_lm"]
        print(
            f"optimistix_lm: {o['run_s'] * 1e3:.0f} ms, {o['steps']} steps, cost {o['cost']:.4f} "
            f"(compile {o['compile_s']:.1f} s)",
            flush=True,
        )
        out["speedup_vs_optimistix"] = o["run_s"] / ours["run_s"]
        out["speedup_vs_scipy_fd"] = out["scipy_fd"]["run_s"] / ours["run_s"]
        out["speedup_vs_scipy_jac"] = out["scipy_jac"]["run_s"] / ours["run_s"]
        print(
            f"speed-up of schur_lm: {out['speedup_vs_scipy_fd']:.1f}x over scipy_fd, "
            f"{out['speedup_vs_scipy_jac']:.1f}x over scipy_jac, "
            f"{out['speedup_vs_optimistix']:.1f}x over optimistix_lm",
            flush=True,
        )

    scaling = []
    for n in [int(v) for v in args.views.split(",") if v]:
        s, p, m = problem(n)
        r = time_schur(s, p, m)
        r.update(views=n, per_view_per_step_ms=1e3 * r["run_s"] / (n * max(r["steps"], 1)))
        scaling.append(r)
        print(
            f"views {n:5d}: {r['run_s'] * 1e3:8.0f} ms, {r['steps']} steps, "
            f"{r['per_view_per_step_ms']:.3f} ms per view per step (compile {r['compile_s']:.0f} s)",
            flush=True,
        )
    out["scaling"] = scaling
    if args.batch > 1:
        out["batch"] = time_batch(args.batch)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
