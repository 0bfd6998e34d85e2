"""Throughput: joint solves and whole calibrations per second by batch size, loop against vmap.

Run: ``python benchmarks/bench_throughput.py [--devices 1,2] [--solve-batches 1,2,4,...]
[--whole-batches 1,2,4,8] [--out FILE]``.  On an accelerator, ``--solve-batches`` and
``--whole-batches`` up to 4096 (the goals there: 2,000 joint solves/s, 200 calibrations/s on
one H100).

Two rigs, each trial its own noise seed (so every trial of a rig has the same sizes):
``preset`` (the paper's 10 lasers, 16 views, 0.5 px) and ``rig8x12`` (``user_rig.py``'s
other rig: an 800x600 camera, 8 lasers, 12 views, 0.3 px).  For each batch size B:

* **joint solves**: the joint LM (plain squares, at most 200 steps) from the perturbed
  truth (as ``bench_sweep.py``): ``loop``, the jitted solve called trial by trial;
  ``vmap``, one jitted ``vmap`` of the solve over the B trials (it runs until its slowest
  trial stops: ``vmap_wait`` is ``1 - mean steps / max steps``, the share of the batch's
  work spent waiting);
* **whole calibrations**: ``calibrate_many(obs, batch=...)`` (the staged stages, every
  joint pass, the covariance) with ``loop`` and ``vmap`` (every pass in lockstep, the trial
  axis sharded over ``jax.devices()``).  Each batch size is run twice and the second timed:
  compilation apart (its seconds are the first run's excess).  Where the time goes is
  measured, not assumed: seconds inside the executors' solves (the compiled LM), in the
  staged stages (OpenCV, NumPy and the compiled staged maps, trial by trial), and the rest
  (the host steps between passes, the covariance); for vmap, per pass, the steps of the
  slowest trial against the mean.

Each ``--devices`` count K runs in its own process with ``JAX_NUM_CPU_DEVICES=K`` (read before
JAX is imported; only the CPU backend obeys it).  The JSON names the device, platform and
versions.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _trials(rig: str, n: int):
    """``n`` trials of ``rig``: observations, and the perturbed-truth starts of the joint solve."""
    from bench_sweep import perturbed_truth  # imports JAX: here, once the devices are set

    from slcvjax import make_scene, simulate
    from slcvjax.observations.problem import pack

    if rig == "preset":
        scene, noise = make_scene("paper"), 0.5
    else:
        from user_rig import user_scene

        scene, noise = user_scene(12, 612), 0.3
    obs, starts, packs = [], [], []
    for seed in range(n):
        o, truth = simulate(scene, noise=noise, seed=seed)
        pk = pack(o)
        obs.append(o)
        starts.append(perturbed_truth(truth, pk, seed))
        packs.append(pk.arrays())
    return obs, starts, packs


def joint_solves(starts, packs, batches: list[int]) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from slcvjax.calibration.lm import solve
    from slcvjax.calibration.params import make_masks

    masks, kw = make_masks(starts[0]), jnp.ones(4)

    def one(p, pk):
        return solve(p, pk, masks, loss="linear", scale=1.0, max_steps=200, kind_weight=kw)

    loop = jax.jit(one)
    t0 = time.perf_counter()
    jax.block_until_ready(loop(starts[0], packs[0]).cost)
    out = {"loop_compile_s": time.perf_counter() - t0, "by_batch": []}
    batched = jax.jit(jax.vmap(one))

    def stack(xs):
        return jax.tree_util.tree_map(lambda *a: jnp.stack(a), *xs)

    for b in batches:
        t0 = time.perf_counter()
        steps = [int(loop(p, k).steps) for p, k in zip(starts[:b], packs[:b], strict=True)]
        loop_s = time.perf_counter() - t0
        bp, bk = stack(starts[:b]), stack(packs[:b])
        t0 = time.perf_counter()
        jax.block_until_ready(batched(bp, bk).cost)
        first = time.perf_counter() - t0
        t0 = time.perf_counter()
        res = jax.block_until_ready(batched(bp, bk))
        vmap_s = time.perf_counter() - t0
        vsteps = np.asarray(res.steps)
        row = {
            "batch": b,
            "loop_solves_per_s": b / loop_s,
            "vmap_solves_per_s": b / vmap_s,
            "vmap_compile_s": first - vmap_s,
            "steps": {"mean": float(np.mean(steps)), "max": int(np.max(steps))},
            "vmap_wait": float(1.0 - np.mean(vsteps) / max(int(np.max(vsteps)), 1)),
        }
        out["by_batch"].append(row)
        print(
            f"  joint solves B={b:4d}: loop {row['loop_solves_per_s']:7.1f}/s  vmap {row['vmap_solves_per_s']:7.1f}/s "
            f"(compile {row['vmap_compile_s']:.1f} s, waiting {row['vmap_wait']:.0%})",
            flush=True,
        )
    return out


class _Timed:
    """An executor of :mod:`slcvjax.calibration.executors` that adds up its seconds and steps."""

    def __init__(self, fn):
        self.fn, self.seconds, self.calls = fn, 0.0, 0

    def __call__(self, jobs, loss, max_steps, size=None):
        t0 = time.perf_counter()
        out = self.fn(jobs, loss, max_steps, size=size)
        self.seconds += time.perf_counter() - t0
        self.calls += 1
        return out


def whole(obs, batches: list[int]) -> dict:
    """Whole calibrations by ``calibrate_many``, loop and vmap, by batch size (see the module docstring)."""
    import numpy as np

    import slcvjax.calibration.calibrate as cal_mod
    import slcvjax.calibration.schedule as sched_mod
    from slcvjax import calibrate_many

    timed = {"loop": _Timed(cal_mod.solve_loop), "vmap": _Timed(cal_mod.solve_vmap)}
    # the schedule tells the vmap executor by identity (its fine shape buckets): both see the wrapper
    cal_mod.solve_loop, cal_mod.solve_vmap = timed["loop"], timed["vmap"]
    sched_mod.solve_vmap = timed["vmap"]
    rows = []
    for b in batches:
        row: dict = {"batch": b}
        for mode in ("loop", "vmap"):
            t0 = time.perf_counter()
            calibrate_many(obs[:b], batch=mode)
            first = time.perf_counter() - t0
            timed[mode].seconds = 0.0
            t0 = time.perf_counter()
            res = calibrate_many(obs[:b], batch=mode)
            run = time.perf_counter() - t0
            staged = sum(r.timings["staged_s"] for r in res)
            solves = timed[mode].seconds
            passes: dict = {}
            for r in res:
                for p in r.passes:
                    passes.setdefault(p.name.split(":")[0], []).append(p.steps)
            steps = {k: {"mean": float(np.mean(v)), "max": int(np.max(v))} for k, v in passes.items()}
            row[mode] = {
                "calibrations_per_s": b / run,
                "run_s": run,
                "compile_s": max(first - run, 0.0),
                "solves_s": solves,
                "staged_s": staged,
                "other_host_s": run - solves - staged,
                "pass_steps": steps,
                "converged": int(sum(r.converged for r in res)),
            }
        rows.append(row)
        lo, vm = row["loop"], row["vmap"]
        print(
            f"  whole B={b:3d}: loop {lo['calibrations_per_s']:.2f}/s (solves {lo['solves_s']:.1f} s, staged "
            f"{lo['staged_s']:.1f} s, other {lo['other_host_s']:.1f} s); vmap {vm['calibrations_per_s']:.2f}/s "
            f"(solves {vm['solves_s']:.1f} s, staged {vm['staged_s']:.1f} s, other {vm['other_host_s']:.1f} s, "
            f"compile {vm['compile_s']:.0f} s)",
            flush=True,
        )
    return {"by_batch": rows}


def part(rigs: list[str], solve_batches: list[int], whole_batches: list[int]) -> dict:
    """This process's share: every rig on the devices ``JAX_NUM_CPU_DEVICES`` gave it."""
    import jax

    import slcvjax  # noqa: F401  (x64, the caches)

    sys.path.insert(0, str(Path(__file__).parent))
    import jaxlib
    import numpy as np
    from bench_forward import machine

    out = {
        "machine": machine()
        | {"python": sys.version.split()[0], "jaxlib": jaxlib.__version__, "numpy": np.__version__},
        "device_kind": jax.devices()[0].device_kind,
        "n_devices": len(jax.devices()),
    }
    for rig in rigs:
        n = max(solve_batches + whole_batches)
        print(f"{rig}: {len(jax.devices())} device(s), simulating {n} trials", flush=True)
        obs, starts, packs = _trials(rig, n)
        out[rig] = {
            "joint_solves": joint_solves(starts, packs, solve_batches),
            "whole": whole(obs, whole_batches) if whole_batches else None,
        }
    return out


def _ints(s: str) -> list[int]:
    return [int(x) for x in s.split(",") if x]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rigs", default="preset,rig8x12")
    ap.add_argument("--devices", default="1,2", help="JAX_NUM_CPU_DEVICES of each run (one process each)")
    ap.add_argument("--solve-batches", default="1,2,4,8,16,32,64")
    ap.add_argument("--whole-batches", default="1,2,4,8")
    ap.add_argument("--part", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    rigs, sb, wb = args.rigs.split(","), _ints(args.solve_batches), _ints(args.whole_batches)
    if args.part:
        print("RESULT " + json.dumps(part(rigs, sb, wb)))
        return
    runs = {}
    for k in _ints(args.devices):
        env = dict(os.environ, JAX_NUM_CPU_DEVICES=str(k))
        cmd = [sys.executable, __file__, "--part", "--rigs", args.rigs, "--solve-batches", args.solve_batches]
        cmd += ["--whole-batches", args.whole_batches]
        with tempfile.TemporaryFile("w+") as log:
            proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=log, text=True)
            result = None
            for line in proc.stdout:
                if line.startswith("RESULT "):
                    result = json.loads(line[7:])
                else:
                    print(f"[{k} device(s)] {line}", end="", flush=True)
            if proc.wait() != 0 or result is None:
                log.seek(0)
                sys.exit(f"the run with {k} device(s) failed:\n{log.read()[-3000:]}")
        runs[f"{k}_devices"] = result
        if args.out:  # after each run: a later one that fails leaves the earlier ones written
            first = next(iter(runs.values()))
            out = {
                "benchmark": "throughput",
                "command": " ".join(["python", "benchmarks/bench_throughput.py", *sys.argv[1:]]),
                "machine": first["machine"],
                "device_kind": first["device_kind"],
                "runs": runs,
            }
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(json.dumps(out, indent=1))
            print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
