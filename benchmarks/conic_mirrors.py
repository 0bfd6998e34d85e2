"""The whole calibration with conic mirrors (sphere, paraboloid, hyperboloid, ellipsoid) against the bound.

Run: ``python benchmarks/conic_mirrors.py [--seeds 10] [--noise 0.3] [--out FILE]``.

The preset's camera and six of its lasers, with the cone replaced by a conic mirror of each
kind (vertex 40 mm in front of the camera, slightly off its axis and tilted, rim radius 20 mm),
in the preset's box at 12 sensor poses; each seed simulated at ``--noise`` px and calibrated as
any observation file is (staged from the rim, the PnP through the mirror, the joint passes).
Reports per kind the lasers' RMS errors at their working points against the Cramer-Rao bound of
the same scene, the mirror's vertex error, and the median time per calibration.  Writes JSON
naming the machine.
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np
from bench_forward import machine
from tqdm import tqdm

from slcvjax import ConicMirror, Rig, box_scene, calibrate, cramer_rao, laser_errors, paper_rig, paper_views, simulate

# (kind, vertex radius mm, conic constant)
MIRRORS = [("sphere", 30.0, None), ("paraboloid", 20.0, None), ("hyperboloid", 15.0, -2.0), ("ellipsoid", 30.0, -0.5)]


def rms(x) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--noise", type=float, default=0.3)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    base = paper_rig(6)
    out = {"machine": machine(), "noise_px": args.noise, "seeds": args.seeds, "kinds": {}}
    for kind, R, conic in MIRRORS:
        mirror = ConicMirror.of_kind(kind, [0.6, -0.4, 40.0], [0.02, -0.015, 1.0], R, 20.0, conic)
        scene = box_scene(Rig(base.camera, mirror, base.lasers), paper_views(12), n_chess_views=8)
        obs, truth = simulate(scene, noise=args.noise, seed=0)
        bound = cramer_rao(truth, obs, args.noise)
        p_err, a_err, apex_err, secs, converged = [], [], [], [], 0
        for seed in tqdm(range(args.seeds), desc=kind):
            obs, truth = simulate(scene, noise=args.noise, seed=seed)
            t0 = time.perf_counter()
            res = calibrate(obs)
            secs.append(time.perf_counter() - t0)
            p, a = laser_errors(res.rig, truth.rig, bound["x_ref"])
            p_err.append(p)
            a_err.append(a)
            apex_err.append(np.linalg.norm(np.asarray(res.rig.mirror.apex) - np.asarray(truth.rig.mirror.apex)))
            converged += int(res.passes[-1].converged)
        dots = sum(int(s.sum()) for v in obs.views for _, s in v.boards.values())
        row = {
            "vertex_radius_mm": R,
            "conic_constant": float(mirror.conic),
            "rim_sag_mm": float(mirror.height),
            "dots_per_scene": dots,
            "bound": {
                "position_rms_mm": bound["position_rms_mm"],
                "direction_rms_deg": float(np.degrees(bound["direction_rms_rad"])),
            },
            "monte_carlo": {"position_rms_mm": rms(p_err), "direction_rms_deg": float(np.degrees(rms(a_err)))},
            "vertex_error_rms_mm": rms(apex_err),
            "converged": converged,
            "median_seconds": float(np.median(secs[1:] or secs)),
        }
        row["monte_carlo_over_bound"] = {
            "position": row["monte_carlo"]["position_rms_mm"] / row["bound"]["position_rms_mm"],
            "direction": row["monte_carlo"]["direction_rms_deg"] / row["bound"]["direction_rms_deg"],
        }
        out["kinds"][kind] = row
        print(kind, json.dumps(row))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
