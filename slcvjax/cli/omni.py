"""``slcvjax omni``: calibrate a catadioptric camera from chessboard images seen through its mirror."""

import logging
import time
from pathlib import Path

from ..observations.formats import FormatError, check_writable, write_calibration, write_observations
from .common import board_flags, export_opencv, print_report, progress_lines

log = logging.getLogger(__name__)


def run(args) -> int:
    from ..calibration.base import CalibrationError
    from ..calibration.calibrate import calibrate
    from ..calibration.report import to_calibration
    from ..experiments.omni import omni_observations, plot_residuals

    pattern, square = board_flags(args)
    for target in [args.out, args.observations, args.export_opencv]:
        if target:
            check_writable(target, tuple(args.images))
    shape: dict = {"kind": args.mirror}
    for key, val in (("vertex_radius", args.vertex_radius), ("conic_constant", args.conic), ("radius", args.rim)):
        if val is not None:
            shape[key] = val
    obs, missing = omni_observations(
        args.images, pattern, square, shape, "telecentric" if args.telecentric else args.projection
    )
    n = len(obs.views)
    log.info(f"{n} of {len(args.images)} images show the {pattern[0]}x{pattern[1]} board")
    if missing:
        log.info(f"no board found in: {', '.join(missing)}")
    if args.observations:
        write_observations(args.observations, obs)
        log.info(f"wrote {args.observations}")
    t0 = time.perf_counter()
    try:
        log.info(f"calibrating {n} views: the staged start, then the joint passes")
        with progress_lines():
            res = calibrate(obs, loss=args.loss)
    except CalibrationError as e:
        raise FormatError(str(e)) from None
    cal = to_calibration(res, obs)
    cal.extra["images_without_board"] = missing
    print_report(cal, f"{n} views through the mirror ({time.perf_counter() - t0:.1f} s)")
    write_calibration(args.out, cal)
    log.info(f"wrote {args.out}")
    if args.export_opencv:
        export_opencv(args.export_opencv, cal.rig.camera)
        log.info(f"wrote {args.export_opencv} (the camera behind the mirror, its lens alone)")
    if not args.no_plot:
        out = Path(args.plot) if args.plot else Path(args.out).with_name(Path(args.out).stem + "_residuals.png")
        log.info(f"wrote {plot_residuals(args.images, cal, obs, out)}")
    return 0
