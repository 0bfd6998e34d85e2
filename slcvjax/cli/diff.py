"""``slcvjax diff``: two calibrations' difference over the image, beside what their covariances predict."""

import logging
from pathlib import Path

log = logging.getLogger(__name__)


def _fmt(x, unit: str = "") -> str:
    return "-" if x is None else f"{x:.4g}{unit}"


def run(args) -> int:
    from ..experiments.diff import diff_maps, plot_diff
    from ..observations.formats import check_writable

    if args.out:
        check_writable(args.out, (args.a, args.b))
    out = diff_maps(args.a, args.b, range_mm=args.range)
    s = out["summary"]
    d = s["diff_mm"]
    log.info(
        f"rays at {out['range_mm']:.1f} mm ({out['range_why']}), {s['pixels']} pixels of A's mirror image: "
        f"|X_A - X_B| median {_fmt(d['median'], ' mm')}, 95th percentile {_fmt(d['p95'], ' mm')}, "
        f"max {_fmt(d['max'], ' mm')}"
    )
    if out["predicted_mm"] is None:
        log.info(f"no prediction: {out['why_no_prediction']}")
    else:
        p, r = s["predicted_mm"], s["ratio"]
        log.info(
            f"predicted by the covariances: median {_fmt(p['median'], ' mm')}, 95th percentile "
            f"{_fmt(p['p95'], ' mm')}; ratio median {_fmt(r['median'])}, 95th percentile {_fmt(r['p95'])}, "
            f"{100 * (s['share_above_2'] or 0):.0f} % of pixels above 2"
        )
        verdict = (
            "consistent: they differ as their noise predicts (mrcal's rule: up to about 2x is normal)"
            if (r["median"] or 0) <= 2.0
            else "they differ more than their noise predicts: one of them, or the model, is off"
        )
        log.info(verdict)
    if args.out:
        log.info(f"wrote {plot_diff(out, Path(args.a).name, Path(args.b).name, args.out)}")
    return 0
