"""Renderer benchmark: seconds per 640x480 catadioptric image and per direct chessboard image.

Run: ``python benchmarks/bench_render.py [--repeats N] [--out FILE]``.  Compile time and run
time are apart (run time = median of repeats after the first call).  Baseline, measured in
the same run: tracing every sample's ray through the camera and the mirror again for each
image (what a renderer without the per-rig ray cache does), against shading the cached rays.
"""

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import slcvjax  # noqa: F401  (float64)
from slcvjax import Renderer, RenderOptions, make_scene
from slcvjax.observations.simulate import visible_spots


def _median_time(f, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        f()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default="benchmarks/results/render.json")
    args = ap.parse_args()
    scene = make_scene("paper")
    rig = scene.rig
    opts = RenderOptions()
    walls = [b for b in scene.boards if b != scene.chess_board]
    spots = [(w, x) for _, w, x, _ in visible_spots(scene, 0)]
    poses = {b: scene.box_poses[0][b] for b in walls}

    t0 = time.perf_counter()
    r = Renderer(rig.camera, rig.mirror, opts)
    t_rays_first = time.perf_counter() - t0
    t0 = time.perf_counter()
    r.catadioptric(poses, scene.boards, spots)
    t_cata_first = time.perf_counter() - t0
    t_cata = _median_time(lambda: r.catadioptric(poses, scene.boards, spots), args.repeats)
    t0 = time.perf_counter()
    r.chessboard(scene.chess_poses[0], 9, 6, 25.0)
    t_chess_first = time.perf_counter() - t0
    t_chess = _median_time(lambda: r.chessboard(scene.chess_poses[0], 9, 6, 25.0), args.repeats)

    def uncached():
        Renderer(rig.camera, rig.mirror, opts).catadioptric(poses, scene.boards, spots)

    t_base = _median_time(uncached, args.repeats)
    res = {
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "processor": platform.processor()},
        "image": [rig.camera.width, rig.camera.height],
        "supersample": opts.supersample,
        "refine": opts.refine,
        "rays_first_call_s (compile + run)": t_rays_first,
        "catadioptric_first_call_s (compile + run)": t_cata_first,
        "catadioptric_s": t_cata,
        "chessboard_first_call_s (compile + run, with its rays)": t_chess_first,
        "chessboard_s": t_chess,
        "baseline_retrace_per_image_s": t_base,
        "speedup_vs_baseline": t_base / t_cata,
    }
    for k, v in res.items():
        print(f"{k:55s} {v:.3f}" if isinstance(v, float) else f"{k:55s} {v}")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
