"""``slcvjax sweep``: the noise-sensitivity sweep: Monte Carlo calibrations beside the bound."""

import logging
import sys

log = logging.getLogger(__name__)


def _parse_levels(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise ValueError(f"--noise: expected comma-separated pixel sigmas such as 0,0.3,0.6, got {text!r}") from None


def run(args) -> int:
    import jax

    from ..calibration.executors import resolve_batch
    from ..experiments.sweep import run_sweep, write_sweep
    from .common import study_options

    levels = _parse_levels(args.noise)
    batch = resolve_batch(args.batch)
    study = study_options(args)

    log.info(
        f"sweep: preset {args.preset}, noise {list(levels)} px, {args.trials} trials per level, "
        f"{args.lasers} lasers, {args.views} views; {batch} over the trials on "
        + (
            f"the Ray cluster {study['cluster']}"
            if study["cluster"]
            else f"{len(jax.devices())} {jax.default_backend()} device(s)"
        )
        + " (with an empty compilation cache the first calibrations wait for it: 15 s on 2 CPU cores); "
        f"each finished chunk of trials is kept in {args.out}",
    )
    doc = run_sweep(
        args.preset, levels, args.trials, args.seed, args.lasers, args.views, progress=sys.stderr.isatty(),
        batch=batch, out_dir=args.out, **study,
    )  # fmt: skip
    m = doc["methods"]
    log.info("noise px   joint pos mm  dir deg   bound pos mm  dir deg   staged pos mm  dir deg")
    for i, s in enumerate(doc["noise"]):
        log.info(
            f"{s:8.3f}   {m['joint']['position_rms_mm'][i]:10.4f} {m['joint']['direction_rms_deg'][i]:8.4f}"
            f"   {m['bound']['position_rms_mm'][i]:10.4f} {m['bound']['direction_rms_deg'][i]:8.4f}"
            f"   {m['staged']['position_rms_mm'][i]:11.4f} {m['staged']['direction_rms_deg'][i]:8.4f}"
        )
    n = len(doc["trials_detail"])
    log.info(f"{doc['converged']} of {n} joint calibrations converged; {doc['seconds']:.1f} s")
    files = write_sweep(doc, args.out)
    log.info(f"wrote {', '.join(str(f) for f in files)}")
    return 0
