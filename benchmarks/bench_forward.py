"""Forward-model benchmark: projection throughput and the cost of the paper-sized Jacobian.

Run: ``python benchmarks/bench_forward.py [--points N] [--out FILE]``.  Compile time and run
time are measured apart (run time = median of repeats after the first call).  Each figure is
compared with a baseline measured in the same run:

* projection through the mirror (Newton + implicit derivative) against the closed-form
  back-projection of the same number of pixels (the model's inverse direction);
* the full Jacobian of the paper preset's residuals (camera, mirror, 10 lasers and every
  board pose) with the implicit derivative against differentiating through the unrolled
  Newton iterations.

Results are printed and written as JSON with the machine's description.
"""

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import slcvjax as sj
from slcvjax import Pose, make_scene, simulate
from slcvjax.observations.problem import dot_residuals, pack, spot_residuals, stack_poses


def timed(fn, *args, repeats: int = 5) -> dict:
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        runs.append(time.perf_counter() - t0)
    run = statistics.median(runs)
    return {"compile_s": max(first - run, 0.0), "run_s": run, "runs_s": runs}


def machine() -> dict:
    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
    }


def flat_residual(packed, implicit: bool):
    """All dot and spot residuals of the paper preset as a function of a flat increment."""

    def residual(rig0, poses0, delta):
        rig = rig0.retract(delta[: rig0.tangent_dim])
        pd = delta[rig0.tangent_dim :].reshape(-1, 6)
        poses = jax.vmap(lambda r, t, d: Pose(r, t).retract(d))(poses0.R, poses0.t, pd)
        rd, okd = dot_residuals(rig, poses, packed, implicit=implicit)
        rs, oks = spot_residuals(rig, poses, packed, implicit=implicit)
        return jnp.concatenate([jnp.where(okd[:, None], rd, 0.0).ravel(), jnp.where(oks[:, None], rs, 0.0).ravel()])

    return residual


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=100_000)
    ap.add_argument("--out", default="benchmarks/results/forward.json")
    args = ap.parse_args()

    scene = make_scene("paper")
    obs, truth = simulate(scene, noise=0.0, seed=0)
    rig = truth.rig
    cam, mirror = rig.camera, rig.mirror

    # ---------------------------------------------------------------- throughput
    rng = np.random.default_rng(0)
    n = args.points
    pts = np.concatenate([np.asarray(v.boards[b][0])[v.boards[b][1]] for v in obs.views for b in v.boards])
    pix = jnp.asarray(pts[rng.integers(0, len(pts), n)] + rng.normal(0, 2.0, (n, 2)))
    back = jax.jit(jax.vmap(sj.back_project, in_axes=(None, None, 0)))
    rays = back(cam, mirror, pix)
    depth = jnp.asarray(rng.uniform(50, 400, n))
    world = rays.point + depth[:, None] * rays.direction
    proj = jax.jit(jax.vmap(sj.project_through_mirror, in_axes=(None, None, 0)))
    t_proj = timed(proj, cam, mirror, world)
    t_back = timed(back, cam, mirror, pix)
    thr = {
        "points": n,
        "project_through_mirror": {**t_proj, "points_per_s": n / t_proj["run_s"]},
        "baseline_back_project": {**t_back, "points_per_s": n / t_back["run_s"]},
        "ratio_project_over_back_project_time": t_proj["run_s"] / t_back["run_s"],
    }

    # ---------------------------------------------------------------- Jacobian of the paper problem
    packed = pack(obs)
    poses0 = stack_poses([truth.board_poses[v][b] for v, b in packed.pose_keys])
    n_params = rig.tangent_dim + 6 * len(packed.pose_keys)
    x0 = jnp.zeros(n_params)
    jac = {}
    for name, implicit in [("implicit", True), ("unrolled_baseline", False)]:
        f = flat_residual(packed, implicit)
        jf = jax.jit(jax.jacfwd(lambda d, f=f: f(rig, poses0, d)))
        jac[name] = timed(jf, x0, repeats=3)
        if implicit:
            r = jax.jit(lambda d, f=f: f(rig, poses0, d))(x0)
            jac["residuals"] = int(r.shape[0])
    jac["parameters"] = n_params
    jac["speedup_implicit_vs_unrolled"] = jac["unrolled_baseline"]["run_s"] / jac["implicit"]["run_s"]

    result = {"benchmark": "forward", "machine": machine(), "throughput": thr, "jacobian": jac}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1))
    print(
        f"machine: {result['machine']['processor']}, {result['machine']['cpu_count']} cpus, "
        f"jax {jax.__version__} on {jax.default_backend()}"
    )
    print(
        f"project_through_mirror: {thr['project_through_mirror']['points_per_s']:.3g} points/s "
        f"(compile {t_proj['compile_s']:.2f} s); closed-form back_project baseline "
        f"{thr['baseline_back_project']['points_per_s']:.3g} points/s; "
        f"time ratio {thr['ratio_project_over_back_project_time']:.2f}x"
    )
    print(
        f"paper Jacobian ({jac['residuals']} residuals x {n_params} parameters): implicit "
        f"{jac['implicit']['run_s'] * 1e3:.1f} ms (compile {jac['implicit']['compile_s']:.1f} s), unrolled "
        f"baseline {jac['unrolled_baseline']['run_s'] * 1e3:.1f} ms (compile "
        f"{jac['unrolled_baseline']['compile_s']:.1f} s); speed-up {jac['speedup_implicit_vs_unrolled']:.1f}x"
    )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
