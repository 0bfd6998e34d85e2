"""``slcvjax camera``: calibrate a plain camera from chessboard images."""

import logging

import numpy as np

from ..observations.formats import FormatError, check_writable, write_calibration
from .common import board_flags, export_opencv

log = logging.getLogger(__name__)


def run(args) -> int:
    from ..calibration.base import CalibrationError
    from ..calibration.chessboard import calibrate_camera_images
    from ..geometry.rig import Rig
    from ..observations.formats import Calibration

    (cols, rows), square = board_flags(args)
    for target in [args.out] + ([args.export_opencv] if args.export_opencv else []):
        check_writable(target, tuple(args.images))
    try:
        res = calibrate_camera_images(args.images, (cols, rows), square)
    except CalibrationError as e:
        raise FormatError(str(e)) from None
    for name, r in res.per_view_rms_px.items():
        log.info(f"{name}: rms {r:.4f} px")
    if res.missing:
        log.info(f"no {cols}x{rows} board found in: {', '.join(res.missing)}")
    c = res.camera
    log.info(
        f"fx {float(c.fx):.4f}  fy {float(c.fy):.4f}  cx {float(c.cx):.4f}  cy {float(c.cy):.4f}  "
        f"dist {np.round(np.asarray(c.dist), 6).tolist()}"
    )
    log.info(f"rms {res.rms_px:.5f} px (OpenCV's calibrateCamera on the same corners: {res.opencv_rms_px:.5f} px)")
    doc = Calibration(
        Rig.camera_only(c),
        extra={
            "residuals": {
                "rms_px": res.rms_px,
                "per_view_rms_px": res.per_view_rms_px,
                "opencv_rms_px": res.opencv_rms_px,
                "images_without_board": res.missing,
            }
        },
    )
    write_calibration(args.out, doc)
    log.info(f"wrote {args.out}")
    if args.export_opencv:
        export_opencv(args.export_opencv, c)
        log.info(f"wrote {args.export_opencv}")
    return 0
