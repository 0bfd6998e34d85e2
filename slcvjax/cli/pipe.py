"""``slcvjax pipe``: the paper's pipe experiment on the simulated rig."""

import logging
import time
from pathlib import Path

from .common import pipe_report, print_points, write_pipe

log = logging.getLogger(__name__)


def run(args) -> int:
    from ..images.pipe import measurement_inputs, pipe_experiment, pipe_scene
    from ..observations.formats import read_calibration
    from ..observations.simulate import paper_rig

    t0 = time.perf_counter()
    out = Path(args.out)
    if getattr(args, "laser", "point") == "ring":
        return run_ring(args, out, t0)
    rig_cov, undetermined = None, ()
    if args.calibration:
        cal = read_calibration(args.calibration)
        _, rig_cov = measurement_inputs(args.calibration, cal)
        rig, undetermined = cal.rig, cal.undetermined_lasers
        truth = paper_rig(rig.lasers.n)
        log.info(f"measuring with {args.calibration}; the pipe is simulated with the true paper rig")
    else:
        truth = paper_rig(args.lasers)
        rig = truth
        log.info("measuring with the true paper rig (give --calibration to use a calibration)")
    scene = pipe_scene(truth, args.diameter, args.poses, args.offset, args.tilt, seed=args.seed)
    res = pipe_experiment(rig, scene, args.noise, seed=args.seed, rig_cov=rig_cov, undetermined=undetermined)
    files = write_pipe(out, res, "points.json", args.noise)
    names = [v.name for v in res["observations"].views]
    print_points(names, [p["points"] for p in res["poses"]], [p["circle"] for p in res["poses"]])
    pipe_report(res)
    log.info(f"wrote {out}/ ({', '.join(files)}) in {time.perf_counter() - t0:.1f} s")
    return 0


def run_ring(args, out: Path, t0: float) -> int:
    """``slcvjax pipe --laser ring``: the ring + point rig's stripes in the pipe, from exact
    observations (:func:`slcvjax.images.ring_pipe.ring_pipe_experiment`)."""
    from ..images.pipe import measurement_inputs, pipe_scene, points_document
    from ..images.ring_pipe import RING_KINDS, ring_pipe_experiment
    from ..observations.formats import read_calibration, write_json_atomic, write_observations
    from ..observations.simulate import paper_rig, sheet_rig
    from .common import print_stripes

    truth = sheet_rig(paper_rig(), RING_KINDS)[0]
    rig, rig_cov, undetermined, sigma = truth, None, (), None
    if args.calibration:
        cal = read_calibration(args.calibration)
        if cal.rig.element_kinds != RING_KINDS:
            raise ValueError(f"{args.calibration}: lasers: expected {RING_KINDS}, got {cal.rig.element_kinds}")
        sigma, rig_cov = measurement_inputs(args.calibration, cal, kind="stripe")
        rig, undetermined = cal.rig, cal.undetermined_lasers
        log.info(f"measuring with {args.calibration}; the pipe is simulated with the true ring rig")
    scene = pipe_scene(truth, args.diameter, args.poses, args.offset, args.tilt, seed=args.seed)
    res = ring_pipe_experiment(
        rig, scene, args.noise, seed=args.seed, pixel_sigma=sigma, rig_cov=rig_cov, undetermined=undetermined
    )
    out.mkdir(parents=True, exist_ok=True)
    obs = res["observations"]
    write_observations(out / "pipe_observations.json", obs)
    names = [v.name for v in obs.views]
    stripes = [p["stripes"] for p in res["poses"]]
    rings = [{e: (f["circle"], f["ellipse"]) for e, f in p["rings"].items()} for p in res["poses"]]
    spots = [p["spots"] for p in res["poses"]] if res["poses"] and res["poses"][0]["spots"] is not None else None
    meta = {
        "pixel_sigma": args.noise if sigma is None else sigma,
        "simulation": obs.extra["simulation"],
        "summary": res["summary"],
    }
    doc = points_document(names, spots, None, (0.0, 0.0, 1.0), meta, stripes, rings)
    write_json_atomic(out / "points.json", doc)
    print_stripes(names, stripes, rings)
    s = res["summary"]
    log.info(
        f"pipe {s['true_diameter_mm']:g} mm, {s['poses']} poses, ring circles {s['circles']}: mean diameter "
        f"{s['mean_diameter_mm']:.4f} mm, largest |error| {s['max_abs_diameter_error_mm']:.4f} mm, rms reported std "
        f"{s['rms_diameter_std_mm']:.4f} mm"
    )
    log.info(f"wrote {out}/ (pipe_observations.json, points.json) in {time.perf_counter() - t0:.1f} s")
    return 0
