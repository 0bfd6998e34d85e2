"""``slcvjax design``: plan a calibration, or design the lasers for measuring pipes."""

import logging
import sys
from pathlib import Path

import numpy as np

from .common import fmt, fmt_finite, study_options

log = logging.getLogger(__name__)


def _parse_triple(text: str, name: str) -> np.ndarray:
    try:
        vals = [float(x) for x in text.split(",")]
    except ValueError:
        raise ValueError(f"--{name}: expected three comma-separated numbers, got {text!r}") from None
    if len(vals) != 3 or not all(np.isfinite(vals)) or min(vals) < 0:
        raise ValueError(f"--{name}: expected three non-negative numbers, got {text!r}")
    return np.asarray(vals)


def run(args) -> int:
    from ..experiments.design import Plan, confirm, design_document, optimise, plot_design
    from ..observations.formats import write_json_atomic
    from ..observations.simulate import box_scene, paper_rig, paper_views

    if args.views < 1:
        raise ValueError(f"--views must be at least 1, got {args.views}")
    if not (np.isfinite(args.box) and args.box > 0):
        raise ValueError(f"--box must be a positive width in mm, got {args.box}")
    rot = np.radians(_parse_triple(args.rotation, "rotation"))
    tra = _parse_triple(args.translation, "translation")
    rig = paper_rig(args.lasers)
    # the start: the preset's random motions, scaled from the preset's range to this one
    base = paper_views(args.views)
    preset = Plan(rig, base)
    start = base * np.where(preset.scale > 0, np.concatenate([rot, tra]) / preset.scale, 0.0)
    scene = box_scene(rig, start, args.box / 2.0)
    plan = Plan.from_scene(scene, start, noise=args.noise, rotation_range=rot, translation_range=tra)
    study = study_options(args)
    if args.measure:
        if args.cluster is not None or args.resume or args.chunk is not None:
            raise ValueError("--cluster, --chunk and --resume: not with --measure yet (its confirmation runs here)")
        return _design_lasers(args, plan)
    log.info(
        f"design: {args.views} views in a {args.box:g} mm box, motion +-{np.degrees(rot).round(2).tolist()} deg, "
        f"+-{tra.tolist()} mm, {args.noise} px (compiling the bound's gradient takes about 30 s)",
    )
    res = optimise(plan, steps=args.steps, position_weight=args.position_weight, progress=sys.stderr.isatty())
    b, a = res.predicted_before, res.predicted_after
    log.info("predicted (Cramer-Rao)   position rms mm   direction rms deg   dots  spots")
    for name, x in (("before", b), ("after", a)):
        log.info(
            f"  {name:22s} {x.position_rms_mm:15.4f}   {x.direction_rms_deg:17.4f}   {x.n_dots:4d}  {x.n_spots:5d}"
        )
    log.info(
        f"  ratio                  {a.position_rms_mm / b.position_rms_mm:15.3f}   "
        f"{a.direction_rms_deg / b.direction_rms_deg:17.3f}   "
        f"({len(res.history) - 1} steps, {res.timings['total_s']:.1f} s)"
    )
    confirmed = None
    if args.confirm:
        where = f" on the Ray cluster {study['cluster']}" if study["cluster"] else ""
        log.info(
            f"confirming by simulation: {args.confirm} calibrations of each plan{where} (each compiles once); "
            f"each finished chunk is kept in {Path(args.out) / 'confirm-before'} and confirm-after"
        )
        confirmed = {}
        for name, p in (("before", res.before), ("after", res.after)):
            folder = Path(args.out) / f"confirm-{name}"
            confirmed[name] = confirm(p, args.confirm, args.seed, progress=sys.stderr.isatty(), out_dir=folder, **study)
            c = confirmed[name]
            log.info(
                f"  {name:6s} simulated rms: position {fmt(c['position_rms_mm'], 4)} mm, direction "
                f"{fmt(c['direction_rms_deg'], 4)} deg ({c['converged']}/{c['trials']} converged"
                + (f", {c['failed']} could not be calibrated: {c['first_failure']}" if c["failed"] else "")
                + ")",
            )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "design.json", design_document(res, confirmed))
    png = plot_design(res, out / "design.png")
    log.info(f"wrote {out / 'design.json'}, {png}")
    return 0


def _design_lasers(args, plan) -> int:
    from ..experiments.laser_design import (
        MeasurePlan,
        confirm_lasers,
        laser_design_document,
        optimise_lasers,
        plot_laser_design,
    )
    from ..observations.formats import write_json_atomic

    diameters = _parse_numbers(args.diameters, "diameters")
    mp = MeasurePlan(
        plan, diameters, elevation_range_deg=args.elevation_range, ring_radius_range_mm=args.ring_radius_range,
        ring_z_range_mm=args.ring_z_range,
    )  # fmt: skip
    log.info(
        f"laser design for pipes of {', '.join(f'{x:g}' for x in diameters)} mm: elevations +-{args.elevation_range:g} "
        f"deg, ring radius +-{args.ring_radius_range:g} mm, height +-{args.ring_z_range:g} mm "
        "(compiling the prediction and its gradient takes about a minute)",
    )
    res = optimise_lasers(mp, steps=args.steps, progress=sys.stderr.isatty())
    log.info("pipe mm    predicted diameter std mm (before -> after)   spots seen   smallest beam-ray angle deg")
    b, a = res.predicted_before, res.predicted_after
    for k, d in enumerate(diameters):
        std_b = "not measurable" if not np.isfinite(b.diameter_std_mm[k]) else f"{b.diameter_std_mm[k]:.3f}"
        std_a = "not measurable" if not np.isfinite(a.diameter_std_mm[k]) else f"{a.diameter_std_mm[k]:.3f}"
        log.info(
            f"{d:7g}    {std_b:>14s} -> {std_a:<14s}                  {b.spots_seen[k]:2d} -> {a.spots_seen[k]:2d}"
            f"      {fmt_finite(b.min_angle_deg[k])} -> {fmt_finite(a.min_angle_deg[k])}"
        )
    if not res.feasible:
        log.info(
            "no mounting in the range sees every spot in every pipe and keeps the lasers on the calibration walls: "
            "widen the range (--ring-z-range, --elevation-range) or narrow the pipes (--diameters); "
            "the mounting that sees the most spots is written"
        )
    confirmed = None
    if args.confirm:
        log.info(f"confirming by simulation: {args.confirm} calibrations of each mounting, each measuring every pipe")
        confirmed = {}
        for name, rig in (("before", res.rig_before), ("after", res.rig_after)):
            c = confirm_lasers(mp, rig, args.confirm, args.seed, progress=sys.stderr.isatty())
            confirmed[name] = c
            errs = ", ".join(fmt(x) for x in c["diameter_error_rms_mm"])
            log.info(
                f"  {name:6s} simulated rms diameter error mm: {errs}"
                + (f" ({c['failed']} could not be calibrated: {c['first_failure']})" if c["failed"] else ""),
            )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "laser_design.json", laser_design_document(res, confirmed))
    png = plot_laser_design(res, out / "laser_design.png", confirmed)
    log.info(f"wrote {out / 'laser_design.json'}, {png}")
    return 0 if res.feasible else 1


def _parse_numbers(text: str, name: str) -> np.ndarray:
    try:
        vals = np.array([float(x) for x in text.split(",")])
    except ValueError:
        raise ValueError(f"--{name}: expected comma-separated numbers, got {text!r}") from None
    if vals.size < 1 or not np.all(np.isfinite(vals)) or np.any(vals <= 0):
        raise ValueError(f"--{name}: expected positive numbers, got {text!r}")
    return vals
