"""The ``slcvjax`` command line."""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from ._io import FormatError, write_calibration, write_observations


def _summary(obs, truth) -> str:
    rig = truth.rig
    n_dots = sum(int(s.sum()) for v in obs.views for _, s in v.boards.values())
    n_dots_all = sum(s.size for v in obs.views for _, s in v.boards.values())
    n_spots = sum(len(v.spots) for v in obs.views)
    n_rim = sum(len(v.rim) for v in obs.views)
    n_corners = sum(int(c.seen.sum()) for c in obs.calibration_views)
    cam = rig.camera
    tilt = np.degrees(np.arccos(np.clip(float(rig.mirror.axis[2]), -1, 1)))
    lines = [
        f"camera   {cam.width}x{cam.height}  fx {float(cam.fx):.3f}  fy {float(cam.fy):.3f}  "
        f"cx {float(cam.cx):.3f}  cy {float(cam.cy):.3f}  dist {np.round(np.asarray(cam.dist), 4).tolist()}",
        f"mirror   cone r {float(rig.mirror.radius):g} mm  h {float(rig.mirror.height):g} mm  "
        f"apex {np.round(np.asarray(rig.mirror.apex), 3).tolist()} mm  axis tilt {tilt:.2f} deg",
        f"lasers   {rig.lasers.n}",
        f"views    {len(obs.views)} catadioptric: {n_dots}/{n_dots_all} dots visible, "
        f"{n_spots}/{len(obs.views) * rig.lasers.n} spots, {n_rim} rim pixels",
        f"direct   {len(obs.calibration_views)} chessboard views, {n_corners} corners",
    ]
    return "\n".join(lines)


def _cmd_simulate(args) -> int:
    from ._simulate import make_scene, simulate

    t0 = time.perf_counter()
    scene = make_scene(args.preset, n_lasers=args.lasers, n_views=args.views)
    obs, truth = simulate(scene, noise=args.noise, seed=args.seed)
    out = Path(args.out)
    write_observations(out / "observations.json", obs)
    write_calibration(out / "truth.json", truth)
    print(_summary(obs, truth))
    print(f"wrote {out / 'observations.json'} and {out / 'truth.json'} ({time.perf_counter() - t0:.1f} s)")
    return 0


def _cmd_demo(args) -> int:
    from ._simulate import make_scene, simulate

    t0 = time.perf_counter()
    print("slcvjax demo: the simulated reference rig (paper preset)", flush=True)
    scene = make_scene("paper")
    obs, truth = simulate(scene, noise=args.noise, seed=args.seed)
    out = Path(args.out)
    write_observations(out / "observations.json", obs)
    write_calibration(out / "truth.json", truth)
    print(_summary(obs, truth))
    print(f"wrote {out}/ ({time.perf_counter() - t0:.1f} s)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="slcvjax", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("simulate", help="simulate a rig's observations and write them with the truth")
    s.add_argument("--preset", default="paper", help="scene preset (default: paper)")
    s.add_argument("--noise", type=float, default=0.0, help="Gaussian pixel noise sigma in px (default 0)")
    s.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    s.add_argument("--lasers", type=int, default=10, help="number of lasers (default 10)")
    s.add_argument("--views", type=int, default=16, help="number of catadioptric views (default 16)")
    s.add_argument("--out", required=True, help="output directory")
    s.set_defaults(func=_cmd_simulate)

    d = sub.add_parser("demo", help="the main job on the simulated reference rig")
    d.add_argument("--noise", type=float, default=0.5, help="pixel noise sigma in px (default 0.5)")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--out", default="slcvjax-demo", help="output directory (default ./slcvjax-demo)")
    d.set_defaults(func=_cmd_demo)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (FormatError, ValueError) as e:
        print(f"slcvjax {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
