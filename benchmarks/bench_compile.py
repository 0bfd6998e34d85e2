"""Compilation benchmark: what a user waits for with datasets of their own sizes.

Run: ``python benchmarks/bench_compile.py [--lasers 8] [--views 9,10,11,12,13,14,15,12,11] [--cli | --only-cli]
[--out FILE]``.

Nine scenes of one rig (not the preset's: ``--lasers`` lasers, sensor poses drawn from
their own seeds, so the numbers of dots, spots, rim pixels and board poses differ from
scene to scene) are simulated (0.5 px) and written as observation files; each part reads
them and calibrates (``read_observations``, then ``calibrate``), as ``slcvjax calibrate``
does:

(a) **cold**: a fresh process with an empty compilation cache calibrates the first scene:
    wall time from the start of the process (imports included), with the seconds spent
    compiling (XLA's backend compile, JAX's tracing and lowering) apart;
(b) **one process, every scene**: the same process calibrates the other scenes, each its
    own size; the marginal seconds per scene after the first, against the baseline of the
    same process calibrating the first scene again (nothing left to compile), as a ratio;
(c) **warm cache**: a new process with the cache (a) and (b) left calibrates a scene of
    sizes neither saw: wall time from the start of the process, compile seconds apart;
(d) **padding cost** (the same process as (c)): one linearisation and one cost evaluation
    of the joint problem at its solution with no padding at all, in its shape bucket, and
    padded 4x past it (best of 5 repeats of 8 each), as ratios to the unpadded one: what
    the coarse ladder of ``Layout.of`` costs a dataset.

(e) **the command line, as a user runs it** (``--cli``; ``--only-cli`` runs this part alone):
    scenes of another rig (``user_rig.py``: an 800x600 camera, another cone, eight lasers
    on another ring, another box; 9-15 views, 0.3 px), which no test or benchmark tunes
    to, calibrated by ``slcvjax calibrate FILES... --out DIR`` in new processes with a cache
    folder of its own: cold (an empty cache, wall time of the process), a new process with
    the warm cache on a scene of sizes it has not seen, and one process given eight more
    scenes and the first of them again under another name: the seconds the command
    prints per scene (calibration and report) after the first, against that repeat (the
    baseline: the same process, nothing left to load).  The goals: <= 25 s cold, <= 4 s for
    the warm new process, <= 0.4 s per further scene.

Each part runs in its own ``python`` process (``--part``), with ``SLCVJAX_CACHE_DIR`` set to
a fresh temporary folder for the whole benchmark.  Results are printed and written as
JSON with the machine's description.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

T_START = time.perf_counter()


def scene(n_lasers: int, n_views: int, seed: int):
    """The rig with ``n_lasers`` lasers at ``n_views`` sensor poses drawn from ``seed`` within the preset's range."""
    import numpy as np

    from slcvjax import box_scene, paper_rig
    from slcvjax.observations.simulate import PAPER_ROTATION_DEG, PAPER_TRANSLATION_MM

    rng = np.random.default_rng(seed)
    views = np.zeros((n_views, 6))
    views[1:, :3] = np.radians(rng.uniform(-1, 1, (n_views - 1, 3)) * np.asarray(PAPER_ROTATION_DEG))
    views[1:, 3:] = rng.uniform(-1, 1, (n_views - 1, 3)) * np.asarray(PAPER_TRANSLATION_MM)
    return box_scene(paper_rig(n_lasers), views)


def _compile_seconds():
    import jax

    totals = {"backend_compile": 0.0, "trace": 0.0, "lower": 0.0, "compilations": 0}
    names = {
        "/jax/core/compile/backend_compile_duration": "backend_compile",
        "/jax/core/compile/jaxpr_trace_duration": "trace",
        "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    }

    def listen(event, duration, **kw):
        if event in names:
            totals[names[event]] += duration
            totals["compilations"] += event.endswith("backend_compile_duration")

    jax.monitoring.register_event_duration_secs_listener(listen)
    return totals


def part(name: str, files: list[Path]) -> dict:
    """One process's part of the benchmark (see the module docstring)."""
    totals = _compile_seconds()
    import slcvjax as sj
    from slcvjax.observations.problem import Layout, pack

    t_import = time.perf_counter() - T_START

    def one(path: Path) -> dict:
        before = dict(totals)
        obs = sj.read_observations(path)
        t0 = time.perf_counter()
        res = sj.calibrate(obs)
        wall = time.perf_counter() - t0
        lay = Layout.of(pack(obs))
        return {
            "file": path.name,
            "views": len(obs.views),
            "sizes": dict(zip(["dots", "spots", "rim", "corners", "board_poses", "direct_poses"], lay.n, strict=True)),
            "buckets": list(lay.cap),
            "seconds": wall,
            "compile_seconds": {k: totals[k] - before[k] for k in totals},
            "converged": res.converged,
            "lm_steps": sum(p.steps for p in res.passes),
            "passes": [[p.name.split(":")[0], p.steps] for p in res.passes],
        }

    out: dict = {"import_seconds": t_import}
    out["first"] = one(files[0])
    out["first_wall_from_process_start"] = time.perf_counter() - T_START
    if name == "cold":
        out["others"] = [one(f) for f in files[1:]]
        out["first_again"] = one(files[0])
    else:
        out["padding"] = padding_cost(files[0])
    return out


def padding_cost(path: Path) -> dict:
    """(d): the joint problem's linearisation and cost at no padding, in its bucket, and 4x past it."""
    import jax
    import jax.numpy as jnp

    import slcvjax as sj
    from slcvjax.calibration.linearise import cost_at, linearise
    from slcvjax.calibration.params import pad_masks, pad_params
    from slcvjax.calibration.residuals import rim_norms
    from slcvjax.observations.problem import Layout

    res = sj.calibrate(sj.read_observations(path))
    lay = Layout.of(res.packed)
    kw = jnp.ones(4)

    def lin(p, pk, m, norm):
        return linearise(p, pk, m, 0, 1.0, kw, norm)

    def cost(p, pk, norm):
        return cost_at(p, pk, 0, 1.0, kw, norm)

    lin, cost, norms = jax.jit(lin), jax.jit(cost), jax.jit(rim_norms)

    def best_ms(f, *a):
        jax.block_until_ready(f(*a))
        times = []
        for _ in range(5):
            t0 = time.perf_counter()
            for _ in range(8):
                r = f(*a)
            jax.block_until_ready(r)
            times.append((time.perf_counter() - t0) / 8 * 1e3)
        return min(times)

    out = {}
    for name, cap in (("none", lay.n), ("bucket", lay.cap), ("bucket_x4", tuple(4 * c for c in lay.cap))):
        pl = Layout(lay.n, cap)
        pk, p, m = pl.pad_packed(res.packed), pad_params(pl, res.params), pad_masks(pl, res.masks)
        norm = norms(p.rig, pk)
        out[name] = {
            "sizes": list(cap),
            "linearise_ms": best_ms(lin, p, pk, m, norm),
            "cost_ms": best_ms(cost, p, pk, norm),
        }
    for name in ("bucket", "bucket_x4"):
        for k in ("linearise_ms", "cost_ms"):
            out[name][k.replace("_ms", "_ratio")] = out[name][k] / out["none"][k]
    return out


CLI = "import sys, slcvjax_cli; sys.argv[0] = 'slcvjax'; sys.exit(slcvjax_cli.main())"
GOALS = {"cold_s": 25.0, "warm_new_process_s": 4.0, "per_further_scene_s": 0.4}


def _cli(files: list[Path], out: Path, env: dict) -> tuple[float, list[float]]:
    """``slcvjax calibrate FILES --out OUT`` in a new process: its wall seconds and the seconds it
    printed for each scene (``== FILE (S s)``)."""
    import re

    cmd = [sys.executable, "-c", CLI, "calibrate", *map(str, files), "--out", str(out)]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
    wall = time.perf_counter() - t0
    return wall, [float(x) for x in re.findall(r"^== .* \(([0-9.]+) s\)$", proc.stderr + proc.stdout, re.M)]


def cli_rows(tmp: Path) -> dict:
    """(e): the command line in new processes on ``user_rig.py``'s scenes (see the module docstring)."""
    import shutil
    import statistics

    sys.path.insert(0, str(Path(__file__).parent))
    from user_rig import write_scenes

    folder = tmp / "user_scenes"
    folder.mkdir()
    files = write_scenes(folder, [12, 9, 10, 11, 13, 14, 15, 12, 11, 14])
    again = folder / "again_of_scene01.json"
    shutil.copy(files[1], again)
    env = dict(os.environ, SLCVJAX_CACHE_DIR=str(tmp / "cli_cache"))
    outs = tmp / "cli_out"
    outs.mkdir()
    cold_wall, cold = _cli(files[:1], outs / "cold.json", env)
    warm_wall, warm = _cli(files[-1:], outs / "warm.json", env)
    many_wall, many = _cli([*files[1:9], again], outs, env)
    further = many[1:-1]  # after the process's first scene, before the repeat
    marginal = statistics.median(further)
    row = {
        "rig": "user_rig.py: 800x600, 8 lasers, 9-15 views, 0.3 px",
        "cold": {"wall_s": cold_wall, "scene_s": cold[0]},
        "warm_new_process": {"wall_s": warm_wall, "scene_s": warm[0]},
        "one_process": {
            "wall_s": many_wall,
            "first_scene_s": many[0],
            "further_scene_s": further,
            "median_further_scene_s": marginal,
            "baseline_repeat_s": many[-1],
            "ratio_to_baseline": marginal / many[-1],
        },
        "goals": GOALS,
    }
    row["met"] = {
        "cold_s": cold_wall <= GOALS["cold_s"],
        "warm_new_process_s": warm_wall <= GOALS["warm_new_process_s"],
        "per_further_scene_s": marginal <= GOALS["per_further_scene_s"],
    }
    return row


def _print_cli(e: dict) -> None:
    o = e["one_process"]
    print(
        f"(e) CLI, {e['rig']}: cold {e['cold']['wall_s']:.1f} s (goal {GOALS['cold_s']:g}); warm new process "
        f"{e['warm_new_process']['wall_s']:.1f} s (goal {GOALS['warm_new_process_s']:g}); per further scene "
        f"{o['median_further_scene_s']:.2f} s median of {len(o['further_scene_s'])} (goal "
        f"{GOALS['per_further_scene_s']:g}; {o['ratio_to_baseline']:.2f}x the repeat, {o['baseline_repeat_s']:.2f} s)"
    )


def _first(run: dict) -> dict:
    """A part's first calibration: wall time from the process start, imports, compile seconds, sizes."""
    first = run["first"]
    return {
        "wall_seconds_from_process_start": run["first_wall_from_process_start"],
        "import_seconds": run["import_seconds"],
        "calibration_seconds": first["seconds"],
        "compile_seconds": first["compile_seconds"],
        "sizes": first["sizes"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lasers", type=int, default=8)
    ap.add_argument("--views", default="12,9,10,11,13,14,15,12,11", help="views of each scene (first: the cold one)")
    ap.add_argument("--unseen-views", type=int, default=14, help="views of the warm-cache scene (c)")
    ap.add_argument("--part", choices=["cold", "warm"], help=argparse.SUPPRESS)
    ap.add_argument("--files", nargs="*", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--cli", action="store_true", help="also (e): the command line in new processes, another rig")
    ap.add_argument("--only-cli", action="store_true", help="(e) alone")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    if args.part:
        print(json.dumps(part(args.part, args.files)))
        return
    if args.only_cli:
        from bench_forward import machine

        with tempfile.TemporaryDirectory(prefix="slcvjax-bench-") as tmp:
            result = {"benchmark": "compile_cli", "machine": machine(), "e_cli": cli_rows(Path(tmp))}
        _print_cli(result["e_cli"])
        if args.out:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(json.dumps(result, indent=1))
            print(f"wrote {args.out}")
        return
    views = [int(v) for v in args.views.split(",")]
    with tempfile.TemporaryDirectory(prefix="slcvjax-bench-") as tmp:
        from slcvjax import simulate, write_observations

        files = []
        for i, n_v in enumerate(views + [args.unseen_views]):
            obs, _ = simulate(scene(args.lasers, n_v, 100 + i), noise=0.5, seed=100 + i)
            files.append(Path(tmp) / f"scene{i:02d}_{n_v}views.json")
            write_observations(files[-1], obs)
        env = dict(os.environ, SLCVJAX_CACHE_DIR=str(Path(tmp) / "cache"))
        runs = {}
        for name, fs in (("cold", files[:-1]), ("warm", files[-1:])):
            cmd = [sys.executable, __file__, "--part", name, "--files", *map(str, fs)]
            t0 = time.perf_counter()
            proc = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
            runs[name] = json.loads(proc.stdout.strip().splitlines()[-1])
            runs[name]["process_wall_seconds"] = time.perf_counter() - t0
        cli = cli_rows(Path(tmp)) if args.cli else None
    cold, warm = runs["cold"], runs["warm"]
    others = cold["others"]
    marginal = sum(o["seconds"] for o in others) / len(others)
    baseline = cold["first_again"]["seconds"]
    from bench_forward import machine

    result = {
        "benchmark": "compile",
        "machine": machine(),
        "lasers": args.lasers,
        "a_cold": _first(cold),
        "b_one_process": {
            "marginal_seconds_per_scene": marginal,
            "baseline_repeat_seconds": baseline,
            "ratio_to_baseline": marginal / baseline,
            "scenes_that_compiled": sum(o["compile_seconds"]["compilations"] > 0 for o in others),
            "scenes": others,
        },
        "c_warm_cache": _first(warm),
        "d_padding": warm["padding"],
        "all_converged": all(o["converged"] for o in [cold["first"], warm["first"], *others]),
    }
    if cli is not None:
        result["e_cli"] = cli
    a, b, c = result["a_cold"], result["b_one_process"], result["c_warm_cache"]
    print(
        f"(a) cold: {a['wall_seconds_from_process_start']:.1f} s from process start "
        f"(imports {a['import_seconds']:.1f} s, XLA compile {a['compile_seconds']['backend_compile']:.1f} s, "
        f"tracing {a['compile_seconds']['trace']:.1f} s, lowering {a['compile_seconds']['lower']:.1f} s)"
    )
    print(
        f"(b) {len(others)} more scenes: {marginal:.2f} s per scene, {b['ratio_to_baseline']:.2f}x the repeat of "
        f"the first ({baseline:.2f} s); {b['scenes_that_compiled']} of them compiled something"
    )
    for o in others:
        print(
            f"    {o['views']:2d} views {o['sizes']}: {o['seconds']:.2f} s "
            f"(compile {o['compile_seconds']['backend_compile']:.2f} s, "
            f"{o['compile_seconds']['compilations']} programs)"
        )
    print(
        f"(c) warm cache, unseen sizes {c['sizes']}: {c['wall_seconds_from_process_start']:.1f} s from process start "
        f"(imports {c['import_seconds']:.1f} s, XLA compile {c['compile_seconds']['backend_compile']:.1f} s, "
        f"tracing {c['compile_seconds']['trace']:.1f} s)"
    )
    d = result["d_padding"]
    print(
        f"(d) padding: linearisation {d['none']['linearise_ms']:.1f} ms unpadded {d['none']['sizes']}; "
        f"{d['bucket']['linearise_ratio']:.2f}x in its bucket {d['bucket']['sizes']}, "
        f"{d['bucket_x4']['linearise_ratio']:.2f}x at 4x the bucket; cost evaluation "
        f"{d['bucket']['cost_ratio']:.2f}x, {d['bucket_x4']['cost_ratio']:.2f}x"
    )
    if cli is not None:
        _print_cli(cli)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1))
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
