"""Accuracy of the calibration against the Cramer-Rao bound (Monte Carlo over noise seeds).

Run: ``python benchmarks/accuracy.py --noise 0.5 --seeds 20 [--out FILE]``.  For each seed the
paper preset is simulated at the given pixel noise and calibrated (staged, then joint); the
lasers' errors at their working points are compared with the bound of the same scene
(``sigma^2 (J^T J)^-1`` at the truth).  A calibration counts as converged when its final LM
pass reports convergence, no observation was left invalid, and its noise estimate is within
25 % of the true sigma.  Writes JSON.
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from slcvjax import calibrate, cramer_rao, laser_errors, make_scene, report, simulate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--noise", type=float, default=0.5)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    scene = make_scene("paper")
    obs, truth = simulate(scene, noise=args.noise, seed=0)
    bound = cramer_rao(truth, obs, args.noise)
    joint_p, joint_a, staged_p, staged_a, rows = [], [], [], [], []
    for seed in tqdm(range(args.first_seed, args.first_seed + args.seeds), desc=f"noise {args.noise} px"):
        obs, truth = simulate(scene, noise=args.noise, seed=seed)
        t0 = time.perf_counter()
        res = calibrate(obs)
        dt = time.perf_counter() - t0
        p, a = laser_errors(res.rig, truth.rig, bound["x_ref"])
        st = res.staged
        ps, as_ = laser_errors(st.rig, truth.rig, bound["x_ref"])
        rep = report(res, obs)["residuals"]
        ok = res.passes[-1].converged and rep["invalid"] == 0 and abs(rep["sigma_px"] / args.noise - 1) < 0.25
        joint_p.append(p), joint_a.append(a), staged_p.append(ps), staged_a.append(as_)
        rows.append(
            {
                "seed": seed,
                "seconds": dt,
                "converged": bool(ok),
                "sigma_px": rep["sigma_px"],
                "invalid": rep["invalid"],
                "passes": [q.to_json() for q in res.passes],
                "position_rms_mm": float(np.sqrt(np.mean(p**2))),
                "direction_rms_deg": float(np.degrees(np.sqrt(np.mean(a**2)))),
            }
        )

    def rms(x):
        return float(np.sqrt(np.mean(np.square(x))))

    out = {
        "noise_px": args.noise,
        "seeds": args.seeds,
        "bound": {
            "position_rms_mm": bound["position_rms_mm"],
            "direction_rms_deg": float(np.degrees(bound["direction_rms_rad"])),
        },
        "joint": {"position_rms_mm": rms(joint_p), "direction_rms_deg": float(np.degrees(rms(joint_a)))},
        "staged": {"position_rms_mm": rms(staged_p), "direction_rms_deg": float(np.degrees(rms(staged_a)))},
        "converged": int(sum(r["converged"] for r in rows)),
        "per_seed": rows,
    }
    out["joint_over_bound"] = {
        "position": out["joint"]["position_rms_mm"] / out["bound"]["position_rms_mm"],
        "direction": out["joint"]["direction_rms_deg"] / out["bound"]["direction_rms_deg"],
    }
    print(json.dumps({k: v for k, v in out.items() if k != "per_seed"}, indent=1))
    bad = [r["seed"] for r in rows if not r["converged"]]
    print(f"not converged: {bad}")
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
