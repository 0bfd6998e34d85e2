"""``slcvjax detect``: detect spots, dots, rim and corners in an image folder."""

import logging
import sys
import time
from pathlib import Path

from ..observations.formats import check_writable, write_observations

log = logging.getLogger(__name__)


def run(args) -> int:
    from ..images.detect import detect_folder

    check_writable(args.out, (Path(args.folder) / "setup.json",))
    t0 = time.perf_counter()
    obs, rep = detect_folder(args.folder, progress=sys.stderr.isatty())
    for line in rep.lines():
        log.info(line)
    write_observations(args.out, obs)
    n_dots = sum(int(s.sum()) for v in obs.views for _, s in v.boards.values())
    n_spots = sum(len(v.spots) for v in obs.views)
    n_corners = sum(int(c.seen.sum()) for c in obs.calibration_views)
    log.info(
        f"{n_dots} dots, {n_spots} spots, {sum(len(v.rim) for v in obs.views)} rim pixels, {n_corners} corners; "
        f"wrote {args.out} ({time.perf_counter() - t0:.1f} s)"
    )
    return 0
