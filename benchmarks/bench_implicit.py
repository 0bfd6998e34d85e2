"""Differentiable calibration: the implicit derivative of the solution against finite differences.

Run: ``python benchmarks/bench_implicit.py [--columns 8] [--out FILE]``.

On the paper preset at 0.5 px (seed 0) after ``calibrate``:

* ``polish``: Newton steps with the exact Hessian from the LM's solution to the exact
  stationary point (:func:`slcvjax.stationary_point`), compilation apart;
* ``sensitivity``: the derivative of every global parameter with respect to every
  observed pixel coordinate (:func:`slcvjax.sensitivity`), run time at warm caches;
* the baseline, finite differences: each pixel coordinate's column by two re-solves on
  perturbed data.  ``--columns`` random columns are computed that way (re-solving to the
  exact stationary point, so the comparison checks the derivative too) and their time
  extrapolated to all columns.
"""

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np
from bench_forward import machine

import slcvjax as sj


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--columns", type=int, default=8)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    obs, _ = sj.simulate(sj.make_scene("paper"), noise=0.5, seed=0)
    res = sj.calibrate(obs)
    arr = res.packed.arrays()

    t0 = time.perf_counter()
    p0, steps = sj.stationary_point(res.params, arr, res.masks, res.loss, res.scale)
    polish_first = time.perf_counter() - t0
    t0 = time.perf_counter()
    sj.stationary_point(res.params, arr, res.masks, res.loss, res.scale)
    polish_s = time.perf_counter() - t0
    sj.sensitivity(res)  # compiles the pixel columns
    t0 = time.perf_counter()
    sens = sj.sensitivity(res)
    sens_s = time.perf_counter() - t0
    n_cols = sens.glob.shape[1]

    # finite differences of a few columns, re-solving to the exact stationary point
    rng = np.random.default_rng(0)
    cols = rng.choice(n_cols, size=args.columns, replace=False)
    fields = ("dot_pixels", "spot_pixels", "rim_pixels", "chess_pixels")
    offsets = np.cumsum([0] + [2 * getattr(arr, f).shape[0] for f in fields])
    eps, worst, scale = 1e-4, 0.0, 0.0
    t0 = time.perf_counter()
    for c in cols:
        k = int(np.searchsorted(offsets, c, side="right") - 1)
        i, a = divmod(int(c - offsets[k]), 2)
        outs = []
        for e in (eps, -eps):
            px = getattr(arr, fields[k]).at[i, a].add(e)
            q, _ = sj.stationary_point(p0, dataclasses.replace(arr, **{fields[k]: px}), res.masks, res.loss, res.scale)
            outs.append(jnp.concatenate([q.rig.lasers.points.ravel(), q.rig.lasers.directions.ravel()]))
        fd = np.asarray(outs[0] - outs[1]) / (2 * eps)
        n_l = p0.rig.lasers.n
        # the same derivative from the sensitivity's local columns
        _, an = _laser_tangent(p0, sens.glob[:, c], n_l)
        worst = max(worst, float(np.max(np.abs(fd - an))))
        scale = max(scale, float(np.max(np.abs(fd))))
    fd_s = (time.perf_counter() - t0) / args.columns

    out = {
        "benchmark": "implicit",
        "machine": machine(),
        "pixel_columns": int(n_cols),
        "polish": {"newton_steps": steps, "compile_s": polish_first - polish_s, "run_s": polish_s},
        "sensitivity_s": sens_s,
        "finite_differences": {
            "columns_checked": args.columns,
            "seconds_per_column": fd_s,
            "all_columns_s_extrapolated": fd_s * n_cols,
            "max_abs_difference": worst,
            "max_abs_derivative": scale,
        },
        "speedup_over_finite_differences": fd_s * n_cols / sens_s,
    }
    print(json.dumps(out, indent=1))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(out, indent=1))


def _laser_tangent(params, dglob, n_l):
    """Laser points and directions (flattened) and their change along a global local-coordinate tangent."""
    import jax

    g = params.n_global

    def f(dg):
        las = params.rig.retract(dg).lasers
        return jnp.concatenate([las.points.ravel(), las.directions.ravel()])

    v, t = jax.jvp(f, (jnp.zeros(g),), (jnp.asarray(dglob),))
    return np.asarray(v), np.asarray(t)


if __name__ == "__main__":
    main()
