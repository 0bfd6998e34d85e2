"""``slcvjax simulate``: simulate a rig's observations (and render them) with the truth beside them."""

import logging
import sys
import time
from pathlib import Path

from ..observations.formats import check_writable, write_calibration, write_observations
from .common import summary

log = logging.getLogger(__name__)


def run(args) -> int:
    from ..observations.simulate import simulate

    if args.pipe is not None:
        check_writable(Path(args.out) / "pipe_observations.json")
        return _simulate_pipe(args)
    t0 = time.perf_counter()
    # the arguments checked by the (quick) simulation first: a bad one leaves no output folder
    setup = None
    if args.target is not None:
        scene, setup = _own_box_scene(args)
    else:
        scene = _preset_scene(args)
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
        if setup is None:
            files = render_scene(scene, out / "images", opts, progress=sys.stderr.isatty())
        else:
            from ..images.own_box import render_own_box

            files = render_own_box(scene, setup, out / "images", opts, progress=sys.stderr.isatty())
        log.info(f"wrote {len(files)} images and {out / 'images' / 'setup.json'} ({time.perf_counter() - t1:.1f} s)")
    return 0


def _rig(args):
    """The simulated rig: the preset's, or (with --mirror, --mirror-distance, --image-size or --laser-tilt) the
    reference rig resized (:func:`slcvjax.images.own_box.sized_rig`)."""
    from ..images.own_box import PAPER_CONE, sized_rig
    from ..observations.simulate import make_scene
    from .setup import image_size, mirror_distance, mirror_size

    if args.mirror is None and args.mirror_distance is None and args.image_size is None and not args.laser_tilt:
        return make_scene(args.preset, n_lasers=args.lasers, n_views=1).rig
    radius, height = PAPER_CONE[:2] if args.mirror is None else mirror_size(args.mirror)
    size, dist = image_size(args.image_size), mirror_distance(args.mirror_distance)
    return sized_rig(size, radius, height, dist, args.lasers, args.laser_tilt)


def _preset_scene(args):
    """The preset's box of dot targets, the rig (resized where asked) at the preset's poses."""
    from ..observations.simulate import PAPER_HALF_WIDTH, box_scene, make_scene, paper_views

    if args.direct_views < 0:
        raise ValueError(f"--direct-views: must be at least 0, got {args.direct_views}")
    make_scene(args.preset, n_lasers=1, n_views=1)  # the preset's name checked
    return box_scene(_rig(args), paper_views(args.views), PAPER_HALF_WIDTH, n_chess_views=args.direct_views)


def _own_box_scene(args):
    """``--target``: the box ``slcvjax setup init`` lays out for the rig, the sensor at the preset's poses;
    returns the scene and the setup (``setup init``'s, from the same flags)."""
    from ..images.coded_box import coded_box_scene
    from ..observations.simulate import paper_views
    from .setup import box_options, rig_box_setup

    if args.direct_views < 0:
        raise ValueError(f"--direct-views: must be at least 0, got {args.direct_views}")
    if args.mirror is None:
        args.mirror = "cone:20x10"
    rig = _rig(args)
    setup, warnings = rig_box_setup(args, args.target)
    for w in warnings:
        log.warning(f"warning: {w}")
    box = box_options(args)
    chess = box.pop("chessboard")
    if chess is None and args.direct_views:
        raise ValueError("--chessboard none: no board for --direct-views (give --direct-views 0)")
    scene = coded_box_scene(
        rig,
        paper_views(args.views),
        args.target,
        n_chess_views=args.direct_views if chess else 0,
        mirror_distance_mm=setup.extra["box"]["mirror_distance_mm"],
        chessboard=chess or (9, 6, 25.0),
        **box,
    )
    return scene, setup


def _render_options(args):
    """The image options of ``simulate --render``."""
    from ..images.render import RenderOptions

    return RenderOptions(noise=args.image_noise, blur=args.blur, exposure=args.exposure, seed=args.seed)


def _simulate_pipe(args) -> int:
    """``simulate --pipe D``: the preset's rig inside a pipe, its spots (and images with --render)."""
    from ..images.pipe import pipe_scene, simulate_pipe

    t0 = time.perf_counter()
    rig = _rig(args)
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
