"""Monte Carlo of the pipe experiment: measurement against the truth beside its reported std.

Run: ``python benchmarks/pipe_noise_floor.py [--noise 0.1,0.3,0.5,0.9] [--trials 20] [--rigid]
[--calibrations 4] [--out FILE]``.

The paper preset's true rig sits in a 150 mm pipe at 16 poses; each trial draws new spot noise.
Per noise level the pipe is measured twice: with the exact calibration (the true rig, pixel
noise only in the reported std) and with calibrations made at the same noise (``--calibrations``
simulated box calibrations, each measuring ``trials / calibrations`` pipe trials, its covariance
propagated into every point's std).  Reported per level and calibration: the fraction of points
flagged nearly parallel, the RMS point error against the truth and its ratio to the RMS
reported std with every point counted, the median absolute diameter error, the fraction of
poses whose diameter lies within two reported std of the truth, and the diameters' Monte Carlo
spread beside their RMS reported std.
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np
from bench_forward import machine

from slcvjax import calibrate, measurement_inputs, paper_scene, pipe_experiment, pipe_scene, simulate, to_calibration


def measure(rig, rig_cov, scene, noise: float, seeds) -> dict:
    """The pipe measured by ``rig`` at ``noise`` over the trial ``seeds``: the raw per-point and
    per-circle values (see :func:`figures`)."""
    raw = {"err2": [], "std2": [], "flagged": [], "derr": [], "dstd": []}
    for seed in seeds:
        res = pipe_experiment(rig, scene, noise, seed=int(seed), rig_cov=rig_cov)
        for p in res["poses"]:
            raw["err2"].append(np.sum(p["error"] ** 2, axis=1))
            raw["std2"].append(np.sum(p["points"].std ** 2, axis=1))
            raw["flagged"].append(p["points"].parallel)
        raw["derr"].append(res["diameters"] - scene.diameter)
        raw["dstd"].append(res["diameter_stds"])
    return {k: np.concatenate(v) for k, v in raw.items()} | {"trials": len(seeds)}


def figures(raw: dict) -> dict:
    """Every point counted: flagged fraction, RMS error, its ratio to the RMS reported std; per
    circle: median |error|, the fraction within two reported std, Monte Carlo spread, bias."""
    e2, s2, d, ds = raw["err2"], raw["std2"], raw["derr"], raw["dstd"]
    return {
        "trials": int(raw["trials"]),
        "points": int(e2.size),
        "nearly_parallel_fraction": float(np.mean(raw["flagged"])),
        "point_error_rms_mm": float(np.sqrt(e2.mean())),
        "point_std_rms_mm": float(np.sqrt(s2.mean())),
        "point_error_over_std": float(np.sqrt(e2.mean() / s2.mean())),
        "circles": int(d.size),
        "diameter_median_abs_error_mm": float(np.median(np.abs(d))),
        "diameter_within_two_std_fraction": float(np.mean(np.abs(d) <= 2.0 * ds)),
        "diameter_mc_std_mm": float(np.std(d)),
        "diameter_reported_std_rms_mm": float(np.sqrt(np.mean(ds**2))),
        "diameter_bias_mm": float(np.mean(d)),
    }


def calibrated(noise: float, seed: int, rigid: bool = False):
    """A calibration of the preset's box at ``noise`` px (``rigid``: the rigid box model): rig and covariance."""
    obs, _ = simulate(paper_scene(), noise=noise, seed=seed)
    res = calibrate(obs, rigid=rigid)
    _, cov = measurement_inputs("<calibration>", to_calibration(res, obs))
    return res.rig, cov


def _line(name: str, noise: float, r: dict) -> str:
    return (
        f"{noise:4.2f} px {name:>10s}: {100 * r['nearly_parallel_fraction']:3.0f}% flagged, point err "
        f"{r['point_error_rms_mm']:.3f} mm, err/std {r['point_error_over_std']:.3f}; diameter median |err| "
        f"{r['diameter_median_abs_error_mm']:.3f} mm, {100 * r['diameter_within_two_std_fraction']:.0f}% within "
        f"2 std, MC std {r['diameter_mc_std_mm']:.3f} vs reported {r['diameter_reported_std_rms_mm']:.3f} mm"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--noise", default="0.1,0.3,0.5,0.9")
    ap.add_argument("--trials", type=int, default=20, help="pipe trials per level and calibration kind")
    ap.add_argument("--calibrations", type=int, default=4, help="calibrations per level (the trials split over them)")
    ap.add_argument("--rigid", action="store_true", help="calibrate with the rigid target box model")
    ap.add_argument("--out", default="benchmarks/results/pipe_noise_floor.json")
    args = ap.parse_args()
    if args.trials < args.calibrations or args.calibrations < 1:
        ap.error("--trials must be at least --calibrations, and --calibrations at least 1")
    truth = paper_scene().rig
    scene = pipe_scene(truth, 150.0, 16, seed=0)
    rows = []
    t0 = time.perf_counter()
    for noise in [float(v) for v in args.noise.split(",") if v]:
        seeds = np.arange(args.trials)
        exact = figures(measure(truth, None, scene, noise, seeds))
        print(_line("exact", noise, exact), flush=True)
        parts = []
        for c, chunk in enumerate(np.array_split(seeds, args.calibrations)):
            rig, cov = calibrated(noise, seed=1000 + c, rigid=args.rigid)
            parts.append(measure(rig, cov, scene, noise, chunk))
        pooled = {k: np.concatenate([p[k] for p in parts]) for k in parts[0] if k != "trials"}
        cal = figures(pooled | {"trials": args.trials})
        print(_line("calibrated", noise, cal), flush=True)
        per_cal = [figures(p) for p in parts]
        rows.append({"noise_px": noise, "exact": exact, "calibrated": cal, "per_calibration": per_cal})
    out = {
        "machine": machine(),
        "seconds": time.perf_counter() - t0,
        "pipe_diameter_mm": 150.0,
        "rigid_box": args.rigid,
        "levels": rows,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
