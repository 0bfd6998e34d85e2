"""``slcvjax setup init``: a ``setup.json`` for a box of printed targets around one's own rig."""

import logging
from pathlib import Path

log = logging.getLogger(__name__)


def _pair(text: str, what: str, kind=int) -> tuple:
    parts = text.lower().split("x")
    try:
        return tuple(kind(p) for p in parts)
    except ValueError:
        raise ValueError(f"{what}: expected numbers separated by 'x', got {text!r}") from None


def run(args) -> int:
    from ..images.detect import read_setup, setup_to_json
    from ..images.targetbox import box_setup
    from ..observations.formats import write_json_atomic

    kind, _, dims = args.mirror.partition(":")
    if kind != "cone":
        raise ValueError(f"--mirror: the detector supports the cone only (cone:RADIUSxHEIGHT), got {args.mirror!r}")
    size = _pair(dims, "--mirror cone:RADIUSxHEIGHT", float)
    if len(size) != 2 or min(size) <= 0:
        raise ValueError(f"--mirror: expected cone:RADIUSxHEIGHT with positive sizes in mm, got {args.mirror!r}")
    if args.lasers < 0:
        raise ValueError(f"--lasers: must be at least 0, got {args.lasers}")
    image = _pair(args.image_size, "--image-size")
    squares = None if args.squares is None else _pair(args.squares, "--squares")
    if squares is not None and (len(squares) != 2 or min(squares) < 1):
        raise ValueError(f"--squares: expected COLSxROWS, got {args.squares!r}")
    chess = None
    if args.chessboard.lower() != "none":
        c = _pair(args.chessboard, "--chessboard COLSxROWSxSQUARE_MM", float)
        if len(c) != 3 or c[0] < 2 or c[1] < 2 or c[2] <= 0 or c[0] % 1 or c[1] % 1:
            raise ValueError(f"--chessboard: expected COLSxROWSxSQUARE_MM, got {args.chessboard!r}")
        chess = (int(c[0]), int(c[1]), c[2])
    setup, warnings = box_setup(
        size[0],
        size[1],
        args.lasers,
        target=args.target,
        width_mm=args.box,
        mirror_distance_mm=args.mirror_distance,
        n_walls=args.walls,
        squares=squares,
        square_mm=args.square_mm,
        marker_mm=args.marker_mm,
        spacing=args.spacing,
        image_size=image,
        chessboard=chess,
        board_z_mm=args.board_z,
    )
    out = Path(args.out)
    write_json_atomic(out, setup_to_json(setup))
    read_setup(out)  # what we wrote, the readers accept
    for w in warnings:
        log.warning(f"warning: {w}")
    band = setup.extra["box"]["mirror_band_z_mm"]
    log.info(
        f"{len(setup.boards)} boards ({args.target}, {args.walls} walls of a {args.box:g} mm box; the mirror sees "
        f"z {band[0]:.0f}..{band[1]:.0f} mm); wrote {out}"
    )
    log.info(f"next: slcvjax target {out} --out targets/  (the prints and the build sheet)")
    return 0
