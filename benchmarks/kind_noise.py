"""Each kind's own noise: its sigma estimated over its free rows, and the lasers' reported std
against the Monte Carlo error where the kinds' noise differ.

Run: ``python benchmarks/kind_noise.py [--seeds 20] [--sigmas 0.02,0.04,0.008,0.025] [--out FILE]``.

The paper preset is simulated with white noise of a different sigma per kind (dots,
spots, rim pixels, chessboard corners; by default in the proportions rendered images give:
spots' centroids the noisiest, the rim's fitted edge the least noisy) and are calibrated.  Per
seed: each kind's estimated sigma (:func:`slcvjax.calibration.covariance.kind_noise`: its weighted
squared residuals over its rows less the parameters they fix) and, as the residuals give it
without that correction, the median-based one; the lasers' errors at their working points
against the truth, beside their reported std (the covariance with each kind's own sigma) and the
std one pooled sigma would give (``sigma^2 H^-1``).  Writes JSON.
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np
from bench_forward import machine
from tqdm import tqdm

from slcvjax import calibrate, cramer_rao, laser_errors, make_scene, simulate
from slcvjax.calibration.bound import laser_std
from slcvjax.calibration.covariance import covariance_of, kind_sigmas


def rms(x) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--sigmas", default="0.02,0.04,0.008,0.025", help="dots, spots, rim, corners (px)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    sig = np.array([float(x) for x in args.sigmas.split(",")])
    scene = make_scene("paper")
    exact, truth = simulate(scene, noise=0.0)
    x_ref = cramer_rao(truth, exact, 1.0)["x_ref"]
    rows = []
    for seed in tqdm(range(args.seeds), desc="seeds"):
        obs, _ = simulate(scene, noise=sig, seed=seed)
        t0 = time.perf_counter()
        res = calibrate(obs)
        dt = time.perf_counter() - t0
        p, a = laser_errors(res.rig, truth.rig, x_ref)
        sp, sa = laser_std(res.rig, np.asarray(res.cov.glob), x_ref)
        pooled = covariance_of(res.params, res.packed, res.masks, res.loss, res.scale, sigma=float(res.cov.sigma))
        pp, pa = laser_std(res.rig, np.asarray(pooled.glob), x_ref)
        rows.append(
            {
                "seed": seed,
                "seconds": dt,
                "converged": bool(res.passes[-1].converged),
                "kind_sigma_px": [res.kind_sigma[k] for k in ("dot", "spot", "rim", "chess")],
                "median_sigma_px": kind_sigmas(res.params, res.packed).tolist(),
                "pooled_sigma_px": float(res.cov.sigma),
                "position_err_mm": p.tolist(),
                "direction_err_rad": a.tolist(),
                "position_std_mm": sp.tolist(),
                "direction_std_rad": sa.tolist(),
                "pooled_position_std_mm": pp.tolist(),
                "pooled_direction_std_rad": pa.tolist(),
            }
        )
    col = {k: np.array([r[k] for r in rows]) for k in rows[0] if k not in ("seed", "converged")}
    summary = {
        "true_sigma_px": sig.tolist(),
        "kind_sigma_over_true": (col["kind_sigma_px"].mean(0) / sig).tolist(),
        "median_sigma_over_true": (col["median_sigma_px"].mean(0) / sig).tolist(),
        "position_err_rms_mm": rms(col["position_err_mm"]),
        "direction_err_rms_deg": float(np.degrees(rms(col["direction_err_rad"]))),
        "position_std_rms_mm": rms(col["position_std_mm"]),
        "direction_std_rms_deg": float(np.degrees(rms(col["direction_std_rad"]))),
        "pooled_position_std_rms_mm": rms(col["pooled_position_std_mm"]),
        "pooled_direction_std_rms_deg": float(np.degrees(rms(col["pooled_direction_std_rad"]))),
        "error_over_std": [
            rms(col["position_err_mm"] / col["position_std_mm"]),
            rms(col["direction_err_rad"] / col["direction_std_rad"]),
        ],
        "error_over_pooled_std": [
            rms(col["position_err_mm"] / col["pooled_position_std_mm"]),
            rms(col["direction_err_rad"] / col["pooled_direction_std_rad"]),
        ],
        "converged": sum(r["converged"] for r in rows),
        "seconds_median": float(np.median(col["seconds"])),
    }
    print(json.dumps(summary, indent=1))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(
            json.dumps({"machine": machine(), "seeds": args.seeds, "summary": summary, "rows": rows}, indent=1)
        )


if __name__ == "__main__":
    main()
