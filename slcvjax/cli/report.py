"""``slcvjax report``: a calibration's report as one self-contained HTML file."""

import logging
from pathlib import Path

log = logging.getLogger(__name__)


def run(args) -> int:
    from ..experiments.report import write_report

    out = write_report(args.calibration, args.out, images=args.images, range_mm=args.range)
    log.info(f"wrote {out}")
    return 0


def report_path(calibration: Path) -> Path:
    """Where ``slcvjax calibrate --report`` writes the report of ``calibration``: beside it,
    ``<stem>_report.html``."""
    return calibration.with_name(f"{calibration.stem}_report.html")
