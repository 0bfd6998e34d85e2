"""Monte Carlo of the pipe experiment: the measurement's noise floor beside its reported std.

Run: ``python benchmarks/pipe_noise_floor.py [--noise 0.05,0.5] [--trials 50] [--out FILE]``.

The paper preset's true rig measures a 150 mm pipe at 16 poses; each trial draws new spot
noise.  Per noise level it reports, over the points used (not nearly parallel): the RMS point
error divided by the RMS reported std; over the fitted diameters: their Monte Carlo spread, the
RMS reported std, the mean bias and the median absolute error (the noise floor a single
measurement sits at).  Optionally ``--calibration FILE`` measures with a calibration instead
(the pipe is still simulated with the true rig; its covariance is propagated).
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np
from bench_forward import machine

from slcvjax._io import read_calibration
from slcvjax._pipe import measurement_inputs, pipe_experiment, pipe_scene
from slcvjax._simulate import paper_rig


def run(noise: float, trials: int, rig, rig_cov, scene) -> dict:
    err2, std2, diam, dstd, flagged, n_pts = [], [], [], [], 0, 0
    for seed in range(trials):
        res = pipe_experiment(rig, scene, noise, seed=seed, rig_cov=rig_cov)
        for p in res["poses"]:
            use = ~p["points"].parallel
            err2.append(np.sum(p["error"][use] ** 2, axis=1))
            std2.append(np.sum(p["points"].std[use] ** 2, axis=1))
            flagged += int(np.sum(~use))
            n_pts += use.size
        diam.append(res["diameters"])
        dstd.append(res["diameter_stds"])
    e2, s2 = np.concatenate(err2), np.concatenate(std2)
    d, ds = np.concatenate(diam) - scene.diameter, np.concatenate(dstd)
    return {
        "noise_px": noise,
        "trials": trials,
        "points": n_pts,
        "nearly_parallel_fraction": flagged / max(n_pts, 1),
        "point_error_rms_mm": float(np.sqrt(e2.mean())),
        "point_error_over_std": float(np.sqrt(e2.mean() / s2.mean())),
        "diameter_mc_std_mm": float(np.std(d)),
        "diameter_reported_std_rms_mm": float(np.sqrt(np.mean(ds**2))),
        "diameter_bias_mm": float(np.mean(d)),
        "diameter_median_abs_error_mm": float(np.median(np.abs(d))),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--noise", default="0.05,0.5")
    ap.add_argument("--trials", type=int, default=50)
    ap.add_argument("--calibration", default=None)
    ap.add_argument("--out", default="benchmarks/results/pipe_noise_floor.json")
    args = ap.parse_args()
    truth = paper_rig()
    rig, rig_cov = truth, None
    if args.calibration:
        cal = read_calibration(args.calibration)
        _, rig_cov = measurement_inputs(args.calibration, cal)
        rig = cal.rig
    scene = pipe_scene(truth, 150.0, 16, seed=0)
    rows = []
    t0 = time.perf_counter()
    for noise in [float(v) for v in args.noise.split(",") if v]:
        r = run(noise, args.trials, rig, rig_cov, scene)
        rows.append(r)
        print(
            f"noise {noise:5.2f} px: point err/std {r['point_error_over_std']:.3f} "
            f"(rms err {r['point_error_rms_mm']:.2f} mm, {100 * r['nearly_parallel_fraction']:.0f}% nearly parallel); "
            f"diameter MC std {r['diameter_mc_std_mm']:.3f} mm vs reported {r['diameter_reported_std_rms_mm']:.3f}, "
            f"bias {r['diameter_bias_mm']:+.3f}, median |err| {r['diameter_median_abs_error_mm']:.3f} mm",
            flush=True,
        )
    out = {"machine": machine(), "calibration": args.calibration, "seconds": time.perf_counter() - t0, "levels": rows}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
