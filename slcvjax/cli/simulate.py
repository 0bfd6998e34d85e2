"""``slcvjax simulate``: simulate a rig's observations (and render them) with the truth beside them."""

import logging
import sys
import time
from pathlib import Path

from ..observations.formats import check_writable, write_calibration, write_observations
from .common import summary

log = logging.getLogger(__name__)


def run(args) -> int:
    from ..observations.simulate import make_scene, simulate

    if args.pipe is not None:
        check_writable(Path(args.out) / "pipe_observations.json")
        return _simulate_pipe(args)
    t0 = time.perf_counter()
    # the arguments checked by the (quick) simulation first: a bad one leaves no output folder
    scene = make_scene(args.preset, n_lasers=args.lasers, n_views=args.views)
    obs, truth = simulate(scene, noise=args.noise, seed=args.seed)
    out = Path(args.out)
    check_writable(out / "observations.json")  # before any write and the long rendering
    write_observations(out / "observations.json", obs)
    write_calibration(out / "truth.json", truth)
    log.info(summary(obs, truth))
    log.info(f"wrote {out / 'observations.json'} and {out / 'truth.json'} ({time.perf_counter() - t0:.1f} s)")
    if args.render:
        from ..images.render import render_scene

        opts = _render_options(args)
        t1 = time.perf_counter()
        files = render_scene(scene, out / "images", opts, progress=sys.stderr.isatty())
        log.info(f"wrote {len(files)} images and {out / 'images' / 'setup.json'} ({time.perf_counter() - t1:.1f} s)")
    return 0


def _render_options(args):
    """The image options of ``simulate --render``."""
    from ..images.render import RenderOptions

    return RenderOptions(noise=args.image_noise, blur=args.blur, exposure=args.exposure, seed=args.seed)


def _simulate_pipe(args) -> int:
    """``simulate --pipe D``: the preset's rig inside a pipe, its spots (and images with --render)."""
    from ..images.pipe import pipe_scene, simulate_pipe
    from ..observations.simulate import make_scene

    t0 = time.perf_counter()
    rig = make_scene(args.preset, n_lasers=args.lasers, n_views=1).rig
    scene = pipe_scene(rig, args.pipe, args.views, seed=args.seed)
    obs, _ = simulate_pipe(scene, noise=args.noise, seed=args.seed)
    out = Path(args.out)
    write_observations(out / "pipe_observations.json", obs)
    n = sum(len(v.spots) for v in obs.views)
    log.info(f"pipe {args.pipe:g} mm, {len(obs.views)} poses, {n} spots; the pipe's truth in its simulation.pipe")
    log.info(f"wrote {out / 'pipe_observations.json'} ({time.perf_counter() - t0:.1f} s)")
    if args.render:
        from ..images.render import render_pipe

        opts = _render_options(args)
        t1 = time.perf_counter()
        files = render_pipe(scene, out / "pipe_images", opts, progress=sys.stderr.isatty())
        log.info(f"wrote {len(files)} images in {out / 'pipe_images'} ({time.perf_counter() - t1:.1f} s)")
    return 0
