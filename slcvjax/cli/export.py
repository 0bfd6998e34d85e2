"""``slcvjax export``: a calibration's camera in another tool's format."""

import logging

log = logging.getLogger(__name__)


def run(args) -> int:
    from ..experiments.export import export
    from ..observations.formats import check_writable, read_calibration

    cal = read_calibration(args.calibration)
    check_writable(args.out, (args.calibration,))
    rep = export(cal, args.format, args.out, range_mm=args.range, lens=args.lens)
    if rep.fit is not None:
        fit = rep.fit
        log.info(rep.what)
        log.info(
            "  per range: "
            + ", ".join(f"{r:g} mm RMS {v:.3f} px" for r, v in zip(fit.ranges_mm, fit.per_range_rms_px, strict=True))
            + f" (working range: {rep.range_why})"
        )
        if fit.pol_consistency_px is not None:
            log.info(f"  cam2world's polynomial against world2cam: worst {fit.pol_consistency_px:.3f} px")
        if fit.mirror:
            log.info(
                "  the model's viewpoint in the camera frame: "
                + ", ".join(f"{v:.2f}" for v in fit.t_cam_model)
                + " mm (its frame: R_cam_model, t in the file)"
            )
    else:
        log.info(rep.what)
    log.info(f"wrote {rep.path} ({args.format})")
    return 0
