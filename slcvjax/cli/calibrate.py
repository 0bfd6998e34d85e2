"""``slcvjax calibrate``: calibrate the rig from observation files or image folders."""

import logging
import sys
import time
from pathlib import Path

from ..observations.formats import FormatError, check_writable, write_calibration
from .common import export_opencv, print_placed, print_report, progress_lines

log = logging.getLogger(__name__)


def _read_inputs(inputs: list[Path], progress: bool = True):
    """Each input as observations: a ``slcv-observations/1`` file, or an image folder (detected here)."""
    from ..images.detect import detect_folder
    from ..observations.formats import read_observations

    out = []
    for p in inputs:
        if p.is_dir():
            obs, rep = detect_folder(p, progress=progress and sys.stderr.isatty())
            bad = {k: v for k, v in rep.problems.items() if v}
            log.info(f"{p}: detected {len(obs.views)} catadioptric and {len(obs.calibration_views)} chessboard images"
                     f" ({len(bad)} with something not found; `slcvjax detect` lists them)")  # fmt: skip
            out.append(obs)
        else:
            out.append(read_observations(p))
    return out


def run(args) -> int:
    from ..calibration.base import CalibrationError
    from ..calibration.report import to_calibration
    from ..images.centroids import calibrate_detected
    from ..observations.formats import read_calibration

    inputs = [Path(p) for p in args.inputs]
    observations = _read_inputs(inputs)  # all read (and image folders detected) before any calibration
    if args.camera and args.start_from:
        raise FormatError("--camera and --from both give the camera: give one")
    if args.camera:
        from ..observations.camera_files import read_camera

        camera = read_camera(args.camera)
    else:
        camera = None
    mirror = None
    if args.start_from:
        start = read_calibration(args.start_from).rig
        if start.mirror is None:
            raise FormatError(f"{args.start_from}: mirror: a camera-only calibration has no mirror to start from")
        camera, mirror = start.camera, start.mirror
    freeze = tuple(f for f in args.freeze.split(",") if f) if args.freeze else None
    options = None
    if args.options:
        import json

        from ..calibration.options import CalibrationOptions

        try:
            doc = json.loads(Path(args.options).read_text())
        except (OSError, ValueError) as e:
            raise FormatError(f"{args.options}: (file): cannot read options ({e})") from None
        options = CalibrationOptions.from_json(doc, args.options)
    out = Path(args.out)
    if len(inputs) == 1 and out.suffix == ".json":
        targets = [out]
    else:
        if out.suffix == ".json":
            raise FormatError(f"{out}: several inputs need an output directory, not a .json file")
        targets = [out / f"{p.stem}.json" for p in inputs]
        if len({t.name for t in targets}) < len(targets):
            raise FormatError("inputs: two inputs share a file name; their outputs would collide")
    read = (*inputs, args.camera, args.start_from, args.options)
    for target in targets + ([Path(args.export_opencv)] if args.export_opencv else []):
        check_writable(target, read)  # before the calibration, not after it
    results = []
    for path, obs in zip(inputs, observations, strict=True):
        t0 = time.perf_counter()
        log.info(f"calibrating {path}: the staged start, then the joint passes")
        try:
            with progress_lines():
                res, obs, notes = calibrate_detected(
                    obs,
                    camera=camera,
                    mirror=mirror,
                    freeze=freeze,
                    loss=args.loss,
                    loss_scale=args.loss_scale,
                    rigid=args.rigid,
                    options=options,
                    correct_centroids=not args.raw_centroids,
                )
        except CalibrationError as e:
            raise FormatError(f"{path}: {e}") from None
        print_placed(notes)
        cal = to_calibration(res, obs)
        results.append((path, cal))
        print_report(cal, f"{path} ({time.perf_counter() - t0:.1f} s)")
    for (path, cal), target in zip(results, targets, strict=True):
        write_calibration(target, cal)
        log.info(f"wrote {target}")
        if args.report:
            from ..experiments.report import write_report
            from .report import report_path

            # an image folder input: the residuals drawn over its images
            out_html = write_report(target, report_path(target), images=path if path.is_dir() else None)
            log.info(f"wrote {out_html}")
    if args.export_opencv:
        export_opencv(args.export_opencv, results[0][1].rig.camera)
        log.info(f"wrote {args.export_opencv}")
    return 0
