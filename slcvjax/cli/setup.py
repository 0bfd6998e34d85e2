"""``slcvjax setup``: ``init`` writes a ``setup.json`` for a box of printed targets around one's own
rig; ``images`` lists the photos in it once they are taken (``IMAGE_DIR/setup.json``)."""

import logging
from pathlib import Path

log = logging.getLogger(__name__)


def _pair(text: str, what: str, kind=int) -> tuple:
    parts = text.lower().split("x")
    try:
        return tuple(kind(p) for p in parts)
    except ValueError:
        raise ValueError(f"{what}: expected numbers separated by 'x', got {text!r}") from None


def mirror_size(text: str) -> tuple[float, float]:
    """``--mirror cone:RADIUSxHEIGHT`` as ``(radius, height)`` in mm."""
    kind, _, dims = text.partition(":")
    if kind != "cone":
        raise ValueError(f"--mirror: the detector supports the cone only (cone:RADIUSxHEIGHT), got {text!r}")
    size = _pair(dims, "--mirror cone:RADIUSxHEIGHT", float)
    if len(size) != 2 or min(size) <= 0:
        raise ValueError(f"--mirror: expected cone:RADIUSxHEIGHT with positive sizes in mm, got {text!r}")
    return size


def image_size(text: str | None) -> tuple[int, int]:
    """``--image-size WIDTHxHEIGHT`` (default 640x480)."""
    size = _pair(text or "640x480", "--image-size")
    if len(size) != 2 or min(size) < 16:
        raise ValueError(f"--image-size: expected WIDTHxHEIGHT in px, got {text!r}")
    return size


def mirror_distance(value: float | None) -> float:
    """``--mirror-distance`` (default 48 mm, the reference rig's)."""
    d = 48.0 if value is None else float(value)
    if not d > 0:
        raise ValueError(f"--mirror-distance: must be positive, got {value}")
    return d


def box_options(args) -> dict:
    """The box flags (``--box``, ``--walls``, ``--squares``, ..., ``--chessboard``) as keyword arguments of
    :func:`slcvjax.images.targetbox.box_setup`: the same in ``setup init`` and ``simulate --target``."""
    squares = None if args.squares is None else _pair(args.squares, "--squares")
    if squares is not None and (len(squares) != 2 or min(squares) < 1):
        raise ValueError(f"--squares: expected COLSxROWS, got {args.squares!r}")
    chess = None
    if args.chessboard.lower() != "none":
        c = _pair(args.chessboard, "--chessboard COLSxROWSxSQUARE_MM", float)
        if len(c) != 3 or c[0] < 2 or c[1] < 2 or c[2] <= 0 or c[0] % 1 or c[1] % 1:
            raise ValueError(f"--chessboard: expected COLSxROWSxSQUARE_MM, got {args.chessboard!r}")
        chess = (int(c[0]), int(c[1]), c[2])
    return {
        "width_mm": args.box,
        "n_walls": args.walls,
        "squares": squares,
        "square_mm": args.square_mm,
        "marker_mm": args.marker_mm,
        "spacing": args.spacing,
        "chessboard": chess,
        "board_z_mm": args.board_z,
    }


def rig_box_setup(args, target: str):
    """``box_setup`` of the rig and box flags: ``(setup, warnings)``, as ``setup init`` writes it."""
    from ..images.targetbox import box_setup

    radius, height = mirror_size(args.mirror)
    if args.lasers < 0:
        raise ValueError(f"--lasers: must be at least 0, got {args.lasers}")
    return box_setup(
        radius,
        height,
        args.lasers,
        target=target,
        mirror_distance_mm=mirror_distance(args.mirror_distance),
        image_size=image_size(args.image_size),
        **box_options(args),
    )


def run(args) -> int:
    if args.setup_command == "images":
        return _images(args)
    from ..images.detect import read_setup, setup_to_json
    from ..observations.formats import write_json_atomic

    setup, warnings = rig_box_setup(args, args.target)
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


def _images(args) -> int:
    from ..images.detect import read_setup, setup_to_json
    from ..images.targetbox import with_images
    from ..observations.formats import FormatError, write_json_atomic

    setup = read_setup(args.setup)
    folder = Path(args.folder)
    if not folder.is_dir():
        raise FormatError(f"{folder}: not a folder")

    def matches(pattern: str) -> list[str]:
        return sorted(p.relative_to(folder).as_posix() for p in folder.glob(pattern) if p.is_file())

    views = matches(args.views)
    if not views:
        raise FormatError(f"{folder}: no image matches --views {args.views!r}")
    direct = [] if args.direct.lower() == "none" else matches(args.direct)
    if args.direct.lower() != "none" and not direct:
        log.warning(f"warning: no image matches --direct {args.direct!r}: without direct views, give the camera's "
                    "intrinsics to slcvjax calibrate with --camera")  # fmt: skip
    out = folder / "setup.json"
    write_json_atomic(out, setup_to_json(with_images(setup, views, direct)))
    read_setup(out)
    log.info(f"{len(views)} views through the mirror, {len(direct)} direct views; wrote {out}")
    log.info(f"next: slcvjax detect {folder} --out detected.json")
    return 0
