"""Laser design for measurement on the preset: predicted diameter std against Monte Carlo.

Run: ``python benchmarks/laser_design.py [--trials 60] [--diameters 100,150,200,250,300]
[--out FILE]``.

Designs the preset's lasers (each beam's elevation, the ring's radius and height) for the
pipes (:func:`slcvjax.experiments.laser_design.optimise_lasers`, the preset's 16 box views at 0.5 px), then
confirms both mountings by simulation (:func:`slcvjax.experiments.laser_design.confirm_lasers`: ``trials``
box calibrations each, every calibration measuring every pipe with the sensor on its axis).
Reported per pipe and mounting: the predicted diameter std, the Monte Carlo RMS diameter error
and their ratio (the ratio's sampling error is about ``1 / sqrt(2 trials)``), the spots seen
and the smallest beam-ray angle.
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np
from bench_forward import machine

from slcvjax import (
    MeasurePlan,
    Plan,
    box_scene,
    confirm_lasers,
    laser_design_document,
    optimise_lasers,
    paper_rig,
    paper_views,
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=60, help="calibrations per mounting (default 60)")
    ap.add_argument("--diameters", default="100,150,200,250,300", help="pipes in mm")
    ap.add_argument("--out", default="benchmarks/results/laser_design.json")
    args = ap.parse_args()
    t0 = time.perf_counter()
    rig, views = paper_rig(), paper_views(16)
    plan = Plan.from_scene(box_scene(rig, views), views, noise=0.5)
    mp = MeasurePlan(plan, np.array([float(x) for x in args.diameters.split(",")]))
    res = optimise_lasers(mp)
    confirmed = {
        "before": confirm_lasers(mp, res.rig_before, args.trials, seed=0),
        "after": confirm_lasers(mp, res.rig_after, args.trials, seed=0),
    }
    doc = laser_design_document(res, confirmed)
    rows = []
    print("pipe mm  mounting  predicted std mm  simulated rms mm  ratio  spots  min angle deg")
    for name, pred in (("before", res.predicted_before), ("after", res.predicted_after)):
        mc = confirmed[name]["diameter_error_rms_mm"]
        for k, d in enumerate(mp.diameters):
            p = float(pred.diameter_std_mm[k])
            ratio = mc[k] / p if (mc[k] is not None and np.isfinite(p)) else None
            rows.append({"diameter_mm": float(d), "mounting": name, "predicted_std_mm": p if np.isfinite(p) else None,
                         "simulated_rms_error_mm": mc[k], "simulated_over_predicted": ratio,
                         "spots_seen": int(pred.spots_seen[k])})  # fmt: skip
            sim = "-" if mc[k] is None else f"{mc[k]:.3f}"
            rat = "-" if ratio is None else f"{ratio:.2f}"
            print(
                f"{d:7g}  {name:8s}  {p:16.3f}  {sim:>16s}  {rat:>5s}  {pred.spots_seen[k]:5d}  "
                f"{pred.min_angle_deg[k]:13.1f}"
            )
    out = {"machine": machine(), "seconds": time.perf_counter() - t0, "trials": args.trials, "rows": rows,
           "design": doc}  # fmt: skip
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out} ({out['seconds']:.0f} s)")


if __name__ == "__main__":
    main()
