"""``slcvjax measure``: 3D laser points (and pipe circles) from spots with a calibration."""

import logging
from pathlib import Path

import numpy as np

from .common import print_points, print_stripes

log = logging.getLogger(__name__)


def _parse_axis(text: str | None):
    if text is None:
        return (0.0, 0.0, 1.0)
    try:
        axis = [float(v) for v in text.split(",")]
    except ValueError:
        raise ValueError(f"--axis: expected three numbers x,y,z, got {text!r}") from None
    if len(axis) != 3 or not np.all(np.isfinite(axis)) or np.linalg.norm(axis) < 1e-12:
        raise ValueError(f"--axis: expected a non-zero finite vector x,y,z, got {text!r}")
    return tuple(axis)


def run(args) -> int:
    from ..images.pipe import measure_observations, measurement_inputs, points_document, view_circle
    from ..observations.formats import (
        check_writable,
        read_calibration,
        read_observations,
        write_json_atomic,
        write_text_atomic,
    )

    cal = read_calibration(args.calibration)
    formats = [f.strip().lower() for f in args.formats.split(",") if f.strip()]
    bad = [f for f in formats if f not in ("json", "csv", "ply")]
    if bad or not formats:
        raise ValueError(f"--format: expected json, csv or ply (comma-separated), got {args.formats!r}")
    extra = [Path(args.out).with_suffix("." + f) for f in dict.fromkeys(formats) if f != "json"]
    for target in [args.out, *extra]:
        check_writable(target, (args.calibration, args.input))
    sigma_cal, cov = measurement_inputs(args.calibration, cal)
    stripe_sigma_cal, _ = measurement_inputs(args.calibration, cal, kind="stripe")
    sigma = args.pixel_sigma if args.pixel_sigma is not None else sigma_cal
    if sigma is None:
        raise ValueError(f"{args.calibration}: residuals: no residual sigma to use; give --pixel-sigma")
    if Path(args.input).is_dir():
        from ..images.pipe import spots_from_images

        obs, problems = spots_from_images(
            args.input, cal.rig, sigma, cov, args.spot_mm, _parse_axis(args.axis), cal.undetermined_lasers
        )
        bad = {k: v for k, v in problems.items() if v}
        n = sum(len(v.spots) for v in obs.views)
        log.info(f"{args.input}: {n} spots in {len(obs.views)} images, labelled by the calibration's laser lines"
                 + (f", centroids corrected for a {args.spot_mm:g} mm spot" if args.spot_mm else ""))  # fmt: skip
        for name, probs in bad.items():
            log.info(f"  {name}: " + "; ".join(probs))
    else:
        obs = read_observations(args.input)
    rig = cal.rig
    if obs.n_lasers != rig.n_elements:
        raise ValueError(
            f"{args.input}: n_lasers: {obs.n_lasers}, but the calibration {args.calibration} has "
            f"{rig.n_elements} lasers"
        )
    axis = _parse_axis(args.axis)
    if cal.undetermined_lasers:
        held = ", ".join(map(str, cal.undetermined_lasers))
        log.info(f"{args.calibration}: laser(s) {held} undetermined (the data did not fix them): no points")
    names = [v.name for v in obs.views]
    has_spots = any(v.spots for v in obs.views)
    views = measure_observations(rig, obs, sigma, cov, cal.undetermined_lasers) if has_spots else None
    circles = None
    if args.fit_circle and views is not None:
        circles = [
            view_circle(vp, axis, name=f"{args.input}: views[{k}] ({names[k]})") if obs.views[k].spots else None
            for k, vp in enumerate(views)
        ]
    stripe_views, rings, stripe_sigma = None, None, None
    if any(v.stripes for v in obs.views):
        from ..measurement.ring import fit_rings
        from ..measurement.stripes import measure_stripe_observations

        stripe_sigma = args.pixel_sigma if args.pixel_sigma is not None else stripe_sigma_cal
        if stripe_sigma is None:
            raise ValueError(f"{args.calibration}: residuals: no stripe sigma to use; give --pixel-sigma")
        stripe_views = measure_stripe_observations(rig, obs, stripe_sigma, cov, cal.undetermined_lasers)
        if args.fit_circle:
            rings = []
            for k, svp in enumerate(stripe_views):
                fits, notes = fit_rings(svp, rig.element_kinds, axis)
                rings.append(fits)
                for note in notes:
                    log.info(f"{args.input}: views[{k}] ({names[k]}): {note}")
    meta = {
        "calibration": str(args.calibration),
        "input": str(args.input),
        "pixel_sigma": sigma if has_spots or stripe_sigma is None else stripe_sigma,
        **({"stripe_pixel_sigma": stripe_sigma} if stripe_sigma is not None else {}),
        "uncertainty": "pixel noise and calibration covariance" if cov is not None else "pixel noise only",
    }
    doc = points_document(names, views, circles, axis if args.fit_circle else None, meta, stripe_views, rings)
    write_json_atomic(args.out, doc)
    for target in extra:
        from ..experiments.export import points_csv, points_ply

        write_text_atomic(target, points_csv(doc) if target.suffix == ".csv" else points_ply(doc))
    if views is not None:
        print_points(names, views, circles)
    if stripe_views is not None:
        print_stripes(names, stripe_views, rings)
    log.info(f"pixel sigma {sigma:.3f} px; uncertainty from {meta['uncertainty']}")
    log.info("wrote " + ", ".join(str(t) for t in [args.out, *extra]))
    return 0
