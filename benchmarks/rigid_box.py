"""The rigid target box model against free board poses: the bound and Monte Carlo, side by side.

Run: ``python benchmarks/rigid_box.py [--seeds 20] [--noise 0.5] [--views 16] [--lasers 10] [--out FILE]``.

A box scene (the paper preset's box and motion range, ``--views`` sensor poses, ``--lasers``
lasers) is simulated at ``--noise`` px for each seed and calibrated twice: with a free pose per
board and view (``calibrate(obs)``) and with the rigid box model (``calibrate(obs, rigid=True)``:
one pose per wall in the box, one sensor pose per view).  The lasers' errors at the working
points are compared with each model's Cramer-Rao bound at the truth (``cramer_rao(...,
rigid=...)``).  A third part gives the board poses' errors against the truth under each model.
Writes JSON naming the machine.
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np
from bench_forward import machine
from tqdm import tqdm

from slcvjax import box_scene, calibrate, cramer_rao, laser_errors, paper_rig, paper_views, simulate
from slcvjax.observations.problem import unstack_poses


def rms(x) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def pose_errors(res, truth) -> tuple[np.ndarray, np.ndarray]:
    """Per board pose of the result: translation error (mm) and rotation error (deg) against the truth."""
    dt, dr = [], []
    for (v, b), p in zip(res.packed.pose_keys, unstack_poses(res.params.poses), strict=True):
        q = truth.board_poses[v][b]
        dt.append(np.linalg.norm(np.asarray(p.t) - np.asarray(q.t)))
        c = (np.trace(np.asarray(p.R).T @ np.asarray(q.R)) - 1) / 2
        dr.append(np.degrees(np.arccos(np.clip(c, -1, 1))))
    return np.asarray(dt), np.asarray(dr)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--noise", type=float, default=0.5)
    ap.add_argument("--views", type=int, default=16)
    ap.add_argument("--lasers", type=int, default=10)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    scene = box_scene(paper_rig(args.lasers), paper_views(args.views))
    obs, truth = simulate(scene, noise=args.noise, seed=0)
    bound = {m: cramer_rao(truth, obs, args.noise, rigid=m == "rigid") for m in ("free", "rigid")}
    x_ref = bound["free"]["x_ref"]
    err = {m: {"p": [], "a": [], "pose_t": [], "pose_r": [], "seconds": [], "converged": 0} for m in bound}
    t_start = time.perf_counter()
    for seed in tqdm(range(args.seeds), desc="seeds"):
        obs, truth = simulate(scene, noise=args.noise, seed=seed)
        for m in bound:
            t0 = time.perf_counter()
            res = calibrate(obs, rigid=m == "rigid")
            e = err[m]
            e["seconds"].append(time.perf_counter() - t0)
            p, a = laser_errors(res.rig, truth.rig, x_ref)
            e["p"].append(p)
            e["a"].append(a)
            pt, pr = pose_errors(res, truth)
            e["pose_t"].append(pt)
            e["pose_r"].append(pr)
            e["converged"] += int(res.passes[-1].converged)
    out = {
        "machine": machine(),
        "noise_px": args.noise,
        "seeds": args.seeds,
        "views": args.views,
        "lasers": args.lasers,
        "seconds_total": time.perf_counter() - t_start,
    }
    for m, b in bound.items():
        e = err[m]
        out[m] = {
            "bound": {
                "position_rms_mm": b["position_rms_mm"],
                "direction_rms_deg": float(np.degrees(b["direction_rms_rad"])),
            },
            "monte_carlo": {
                "position_rms_mm": rms(e["p"]),
                "direction_rms_deg": float(np.degrees(rms(e["a"]))),
            },
            "board_pose_rms": {
                "translation_mm": rms(np.concatenate(e["pose_t"])),
                "rotation_deg": rms(np.concatenate(e["pose_r"])),
            },
            "converged": e["converged"],
            "median_seconds": float(np.median(e["seconds"][1:] or e["seconds"])),
        }
        out[m]["monte_carlo_over_bound"] = {
            "position": out[m]["monte_carlo"]["position_rms_mm"] / out[m]["bound"]["position_rms_mm"],
            "direction": out[m]["monte_carlo"]["direction_rms_deg"] / out[m]["bound"]["direction_rms_deg"],
        }
    out["rigid_over_free"] = {
        "bound_position": out["rigid"]["bound"]["position_rms_mm"] / out["free"]["bound"]["position_rms_mm"],
        "bound_direction": out["rigid"]["bound"]["direction_rms_deg"] / out["free"]["bound"]["direction_rms_deg"],
        "mc_position": out["rigid"]["monte_carlo"]["position_rms_mm"] / out["free"]["monte_carlo"]["position_rms_mm"],
        "mc_direction": out["rigid"]["monte_carlo"]["direction_rms_deg"]
        / out["free"]["monte_carlo"]["direction_rms_deg"],
    }
    print(json.dumps({k: v for k, v in out.items() if k != "machine"}, indent=1))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
