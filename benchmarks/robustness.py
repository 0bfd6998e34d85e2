"""Robustness of the calibration to wrong spot labels: laser error against the bound, and the flags.

Run: ``python benchmarks/robustness.py [--seeds 3] [--shares 0,0.05,0.1,0.2] [--noise 0.3] [--out FILE]``.

Scenes: the paper preset (10 lasers, 16 views) and an 8-laser rig at 12 views.  For each seed a
scene is simulated at ``--noise`` px and a share of its laser spots is given the label of the
laser next to it in azimuth (what a detector does when two beams' spots lie close); the pixels
stay true.  The corrupted observations are calibrated (``calibrate``) and compared with:

* the truth, per laser, over the bound of the clean scene (``cramer_rao``): position and
  direction error at the working point over the bound's standard deviation, RMS over the
  lasers and the worst laser;
* the calibration's own claim: the worst laser's error over its reported standard deviation
  (a confident wrong answer is a large ratio);
* the observations it flags (the report's outliers: residual above 5 sigma), against the spots
  that were relabelled: precision and recall.

Goals (issue 17): 5 % wrong labels -> error <= 1.2x the bound, 10 % -> <= 1.5x, 20 % -> <= 2x or a
refusal naming the lasers; flag precision and recall >= 0.95.  Writes JSON with the machine.
"""

import argparse
import copy
import json
import time
from pathlib import Path

import numpy as np
from bench_forward import machine

from slcvjax._calibrate import _obs_table, calibrate, cramer_rao, laser_errors, laser_std, laser_working_points
from slcvjax._simulate import make_scene, simulate

RIGS = {"paper_10x16": (10, 16), "lasers8_views12": (8, 12)}


def relabel(obs, share: float, n_lasers: int, rng) -> tuple[object, set]:
    """``obs`` with ``share`` of its spots labelled as the laser next in azimuth (the preset's
    lasers go round the ring in index order); the pixels of
    the relabelled spots (as tuples), to find them again after packing."""
    spots = [(v, j) for v, view in enumerate(obs.views) for j in range(len(view.spots))]
    k = int(round(share * len(spots)))
    picked = rng.choice(len(spots), size=k, replace=False) if k else []
    wrong = set()
    for i in picked:
        v, j = spots[i]
        s = obs.views[v].spots[j]
        s.laser = (s.laser + 1) % n_lasers
        wrong.add(tuple(np.round(s.pixel, 9)))
    return obs, wrong


def one(n_lasers: int, n_views: int, share: float, seed: int, noise: float) -> dict:
    scene = make_scene("paper", n_lasers=n_lasers, n_views=n_views)
    clean, truth = simulate(scene, noise=noise, seed=seed)
    bound = cramer_rao(truth, clean, noise)
    obs, wrong = relabel(copy.deepcopy(clean), share, n_lasers, np.random.default_rng(1000 + seed))
    t0 = time.perf_counter()
    res = calibrate(obs)
    seconds = time.perf_counter() - t0
    pos, ang = laser_errors(res.rig, truth.rig, bound["x_ref"])
    p_ratio, a_ratio = pos / bound["position_std_mm"], ang / bound["direction_std_rad"]
    x_ref = laser_working_points(res.rig, res.params.poses, res.packed)
    sd_p, sd_a = laser_std(res.rig, np.asarray(res.cov.glob), x_ref)
    norm, kind, ok, *_ = _obs_table(res)
    flagged_rows = np.flatnonzero(ok & (kind == 1) & (norm > 5.0 * float(res.cov.sigma)))
    n_d = res.packed.dot_pose.shape[0]
    px = np.asarray(res.packed.spot_pixels)
    flagged = {tuple(np.round(px[i - n_d], 9)) for i in flagged_rows}
    hit = len(flagged & wrong)
    return {
        "share": share,
        "seed": seed,
        "wrong_spots": len(wrong),
        "spots": int(px.shape[0]),
        "seconds": seconds,
        "final_pass": res.passes[-1].result,
        "position_over_bound_rms": float(np.sqrt(np.mean(p_ratio**2))),
        "direction_over_bound_rms": float(np.sqrt(np.mean(a_ratio**2))),
        "worst_laser_over_bound": float(max(p_ratio.max(), a_ratio.max())),
        "worst_laser_over_reported_std": float(max((pos / sd_p).max(), (ang / sd_a).max())),
        "flagged_spots": len(flagged),
        "flag_precision": hit / len(flagged) if flagged else None,
        "flag_recall": hit / len(wrong) if wrong else None,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--shares", default="0,0.05,0.1,0.2")
    ap.add_argument("--noise", type=float, default=0.3)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    shares = [float(s) for s in args.shares.split(",")]
    rows = []
    for rig, (n_lasers, n_views) in RIGS.items():
        for share in shares:
            for seed in range(args.seeds):
                r = one(n_lasers, n_views, share, seed, args.noise) | {"rig": rig}
                rows.append(r)
                print(
                    f"{rig:16s} {share:4.0%} seed {seed}: error/bound rms {r['position_over_bound_rms']:6.2f} "
                    f"{r['direction_over_bound_rms']:6.2f}, worst laser {r['worst_laser_over_bound']:6.1f}x bound, "
                    f"{r['worst_laser_over_reported_std']:6.1f}x its std; flagged {r['flagged_spots']:3d} of "
                    f"{r['wrong_spots']:3d} wrong (precision {r['flag_precision']}, recall {r['flag_recall']})",
                    flush=True,
                )
    summary = []
    for rig in RIGS:
        for share in shares:
            rs = [r for r in rows if r["rig"] == rig and r["share"] == share]

            def rms(key, rs=rs):
                return float(np.sqrt(np.mean([r[key] ** 2 for r in rs])))

            def mean(key, rs=rs):
                vals = [r[key] for r in rs if r[key] is not None]
                return float(np.mean(vals)) if vals else None

            summary.append(
                {
                    "rig": rig,
                    "share": share,
                    "position_over_bound": rms("position_over_bound_rms"),
                    "direction_over_bound": rms("direction_over_bound_rms"),
                    "worst_laser_over_bound": max(r["worst_laser_over_bound"] for r in rs),
                    "worst_laser_over_reported_std": max(r["worst_laser_over_reported_std"] for r in rs),
                    "flag_precision": mean("flag_precision"),
                    "flag_recall": mean("flag_recall"),
                }
            )
    print("rig              share  pos/bound dir/bound  worst/bound  worst/std  precision recall")
    for s in summary:
        prec = "-" if s["flag_precision"] is None else f"{s['flag_precision']:.2f}"
        rec = "-" if s["flag_recall"] is None else f"{s['flag_recall']:.2f}"
        print(
            f"{s['rig']:16s} {s['share']:5.0%} {s['position_over_bound']:9.2f} {s['direction_over_bound']:9.2f} "
            f"{s['worst_laser_over_bound']:11.1f} {s['worst_laser_over_reported_std']:10.1f} {prec:>9s} {rec:>6s}"
        )
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        doc = {"benchmark": "robustness", "machine": machine(), "noise_px": args.noise, "summary": summary}
        args.out.write_text(json.dumps(doc | {"runs": rows}, indent=1))
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
