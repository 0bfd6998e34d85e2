"""The project's small hand-written solvers against optimistix's on the same problems.

Run: ``python benchmarks/bench_solvers.py [--repeats 20] [--out FILE]``.

Each case solves one problem with both, compiled once (compile time reported apart), and
reports the run time (median of ``--repeats``), the steps and the final cost, so that the
speed is compared at an equal solution:

* ``rim_circle``: the staged rim-circle fit of the paper preset (the rim pixels of its
  16 views, nine starting tilts in one vmapped call): the project's fixed-step batched LM
  (``slcvjax.calibration.staged._small_lm``, 15 steps) against
  ``optimistix.least_squares`` with ``LevenbergMarquardt`` (vmapped over the starts);
* ``pipe_circle``: the pipe's circle fit (``slcvjax.fit_circle``: an algebraic start, then
  Gauss-Newton in NumPy) of 16 poses' points (10 points each, on a 150 mm circle with
  0.5 mm noise) against optimistix's LM from the same start, jitted, one pose per call as
  ``measure`` fits them, and all 16 in one vmapped call;
* ``stationary_point``: Newton from a calibration's LM solution to its exact stationary point
  (``slcvjax.stationary_point``: each step one Schur solve of the problem's own second-order
  linearisation) against ``optimistix.root_find`` with ``Newton`` on the masked gradient of
  the same robust cost in the tangent at that solution (a dense Jacobian of the gradient), for
  a 4-laser, 5-view scene and the preset (10 lasers, 16 views), both to a step of 1e-10.

The joint Schur LM's comparison with optimistix is in ``benchmarks/bench_calibrate.py``.
"""

import argparse
import json
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from bench_forward import machine

import slcvjax as sj
from slcvjax.calibration import staged
from slcvjax.calibration.linearise import cost_at
from slcvjax.calibration.losses import loss_index
from slcvjax.calibration.residuals import rim_norms
from slcvjax.observations.problem import kind_weights


def timed(fn, repeats: int) -> tuple[dict, object]:
    """``fn()`` once (compiling), then ``repeats`` times: compile and run time apart."""
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        runs.append(time.perf_counter() - t0)
    run = statistics.median(runs)
    return {"compile_s": max(first - run, 0.0), "run_s": run}, out


def rim_circle(repeats: int) -> dict:
    obs, truth = sj.simulate(sj.make_scene("paper"), noise=0.5, seed=0)
    rim = np.concatenate([v.rim for v in obs.views])
    y0, rays, weight, radius, scale = staged.rim_circle_problem(truth.rig.camera, rim, obs.mirror_radius)
    n = float(jnp.sum(weight))

    ours_t, (ys, rms) = timed(lambda: staged._fit_circles(y0, rays, weight, radius, scale), repeats)
    ours = ours_t | {"steps": 15, "rms_px": [float(v) for v in rms]}

    solver = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10)

    @jax.jit
    def theirs_fn(y0):
        def one(y):
            sol = optx.least_squares(
                lambda y, a: staged._rim_residual(y, a), solver, y, args=(rays, radius, scale, weight), throw=False
            )
            return sol.value, sol.stats["num_steps"]

        return jax.vmap(one)(y0)

    theirs_t, (ys2, steps2) = timed(lambda: theirs_fn(y0), repeats)
    rms2 = [float(jnp.sqrt(jnp.sum(staged._rim_residual(y, (rays, radius, scale, weight)) ** 2) / n)) for y in ys2]
    theirs = theirs_t | {"steps": [int(s) for s in steps2], "rms_px": rms2}
    return {
        "rim_pixels": int(n),
        "starts": int(y0.shape[0]),
        "ours": ours,
        "optimistix_lm": theirs,
        "best_rms_px": {"ours": min(ours["rms_px"]), "optimistix_lm": min(rms2)},
        "speedup": theirs["run_s"] / ours["run_s"],
    }


def pipe_circle(repeats: int) -> dict:
    rng = np.random.default_rng(0)
    n_poses, n_pts, radius = 16, 10, 75.0
    ang = rng.uniform(0, 2 * np.pi, (n_poses, n_pts))
    centre = rng.normal(0, 5.0, (n_poses, 1, 2))
    q = centre + radius * np.stack([np.cos(ang), np.sin(ang)], -1) + rng.normal(0, 0.5, (n_poses, n_pts, 2))

    def ours_all():
        return np.array([sj.fit_circle(p).diameter for p in q])

    ours_t, d_ours = timed(ours_all, repeats)

    def residual(theta, p):
        return jnp.linalg.norm(p - theta[:2], axis=1) - theta[2]

    solver = optx.LevenbergMarquardt(rtol=1e-12, atol=1e-12)

    def start(p):  # the same algebraic (Kasa) start as fit_circle's
        a = jnp.concatenate([2.0 * p, jnp.ones((p.shape[0], 1))], axis=1)
        sol = jnp.linalg.lstsq(a, jnp.sum(p**2, axis=1))[0]
        return jnp.array([sol[0], sol[1], jnp.sqrt(jnp.maximum(sol[2] + sol[:2] @ sol[:2], 0.0))])

    def one(p):
        sol = optx.least_squares(residual, solver, start(p), args=p, throw=False)
        return 2.0 * sol.value[2], sol.stats["num_steps"]

    one_jit, all_jit = jax.jit(one), jax.jit(jax.vmap(one))
    qj = jnp.asarray(q)
    each_t, _ = timed(lambda: [one_jit(p) for p in qj], repeats)
    batch_t, (d_theirs, steps) = timed(lambda: all_jit(qj), repeats)
    return {
        "poses": n_poses,
        "points_per_pose": n_pts,
        "ours": ours_t,
        "optimistix_lm_per_pose": each_t,
        "optimistix_lm_vmapped": batch_t | {"steps": [int(s) for s in steps]},
        "max_diameter_difference_mm": float(np.max(np.abs(d_ours - np.asarray(d_theirs)))),
        "speedup_vs_per_pose": each_t["run_s"] / ours_t["run_s"],
        "speedup_vs_vmapped": batch_t["run_s"] / ours_t["run_s"],
    }


def stationary_point(repeats: int, n_lasers: int, n_views: int) -> dict:
    obs, _ = sj.simulate(sj.make_scene("paper", n_lasers=n_lasers, n_views=n_views), noise=0.3, seed=0)
    res = sj.calibrate(obs)
    p0, pk, m = jax.tree_util.tree_map(jnp.asarray, (res.params, res.packed, res.masks))
    loss, kw, norm = loss_index(res.loss), kind_weights(None), rim_norms(p0.rig, pk)
    g, nb = p0.n_global, p0.n_blocks
    mg, mb = m.glob, jnp.repeat(m.blocks, 6)
    mask = jnp.concatenate([mg, mb])

    def at(d):
        return p0.retract(d[:g] * mg, (d[g:] * mb).reshape(nb, 6))

    def cost(d):
        return cost_at(at(d), pk, loss, res.scale, kw, norm, real_only=False)

    def gradient(d, _):  # held columns: the identity, so that the Jacobian is regular
        return mask * jax.grad(cost)(d) + (1.0 - mask) * d

    solver = optx.Newton(rtol=1e-10, atol=1e-10, cauchy_termination=False)

    @jax.jit
    def theirs_fn():
        sol = optx.root_find(gradient, solver, jnp.zeros(g + 6 * nb), throw=False)
        return sol.value, sol.stats["num_steps"], sol.result == optx.RESULTS.successful

    def ours_fn():
        return sj.stationary_point(res.params, res.packed, res.masks, res.loss, res.scale)

    ours_t, (q, steps) = timed(ours_fn, repeats)
    theirs_t, (d, steps2, ok) = timed(theirs_fn, repeats)
    q = jax.tree_util.tree_map(jnp.asarray, q)
    diff = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(jax.tree.leaves(at(d)), jax.tree.leaves(q), strict=True))
    c_ours = float(cost_at(q, pk, loss, res.scale, kw, norm, real_only=False))
    return {
        "lasers": n_lasers,
        "views": n_views,
        "unknowns": g + 6 * nb,
        "ours": ours_t | {"steps": int(steps), "cost": c_ours},
        "optimistix_newton": theirs_t | {"steps": int(steps2), "successful": bool(ok), "cost": float(cost(d))},
        "cost_at_lm_solution": float(cost(jnp.zeros(g + 6 * nb))),
        "max_parameter_difference": diff,
        "speedup": theirs_t["run_s"] / ours_t["run_s"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    out = {"benchmark": "solvers", "machine": machine() | {"optimistix": optx.__version__}}
    out["rim_circle"] = r = rim_circle(args.repeats)
    print(
        f"rim circle ({r['rim_pixels']} rim pixels, {r['starts']} starts): ours {r['ours']['run_s'] * 1e3:.2f} ms "
        f"(compile {r['ours']['compile_s']:.2f} s), optimistix {r['optimistix_lm']['run_s'] * 1e3:.2f} ms "
        f"(compile {r['optimistix_lm']['compile_s']:.2f} s, steps {r['optimistix_lm']['steps']}); best RMS "
        f"{r['best_rms_px']['ours']:.6f} / {r['best_rms_px']['optimistix_lm']:.6f} px; ours {r['speedup']:.1f}x faster",
        flush=True,
    )
    out["pipe_circle"] = c = pipe_circle(args.repeats)
    print(
        f"pipe circle ({c['poses']} poses x {c['points_per_pose']} points): ours {c['ours']['run_s'] * 1e3:.2f} ms, "
        f"optimistix {c['optimistix_lm_per_pose']['run_s'] * 1e3:.2f} ms one pose per call, "
        f"{c['optimistix_lm_vmapped']['run_s'] * 1e3:.2f} ms vmapped (compile "
        f"{c['optimistix_lm_vmapped']['compile_s']:.2f} s); diameters agree to "
        f"{c['max_diameter_difference_mm']:.1e} mm; ours {c['speedup_vs_per_pose']:.1f}x / "
        f"{c['speedup_vs_vmapped']:.1f}x faster",
        flush=True,
    )
    out["stationary_point"] = []
    for n_l, n_v in ((4, 5), (10, 16)):
        out["stationary_point"].append(s := stationary_point(min(args.repeats, 5), n_l, n_v))
        print(
            f"stationary point ({n_l} lasers, {n_v} views, {s['unknowns']} unknowns): ours "
            f"{s['ours']['run_s'] * 1e3:.0f} ms ({s['ours']['steps']} steps, compile {s['ours']['compile_s']:.1f} s), "
            f"optimistix Newton {s['optimistix_newton']['run_s'] * 1e3:.0f} ms ({s['optimistix_newton']['steps']} "
            f"steps, compile {s['optimistix_newton']['compile_s']:.1f} s, successful "
            f"{s['optimistix_newton']['successful']}); parameters agree to {s['max_parameter_difference']:.1e}; "
            f"ours {s['speedup']:.1f}x faster",
            flush=True,
        )
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(out, indent=1))
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
