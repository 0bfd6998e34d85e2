"""``slcvjax target``: a true-scale PDF per board of a ``setup.json`` and the box's build sheet."""

import logging
from pathlib import Path

log = logging.getLogger(__name__)


def run(args) -> int:
    from ..images.detect import read_setup
    from ..images.targetbox import write_targets

    setup = read_setup(args.setup)
    pages, sheet = write_targets(setup, args.out, source=Path(args.setup).name)
    for name, path, plan in pages:
        w, h = plan.size_mm
        paper = f"{plan.paper}{' landscape' if plan.landscape else ''}"
        log.info(f"{name}: {path} ({paper}, {w:g} x {h:g} mm)")
    log.info(f"build sheet: {sheet} (and {Path(sheet).with_suffix('.png').name})")
    log.info("print at 100 % (actual size) and check each page's 100 mm scale bar")
    return 0
