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
