"""The ``slcvjax`` command's parser and entry point, apart from the library.

``slcvjax --help``, ``slcvjax CMD --help`` and ``slcvjax --version`` answer from here without
importing the library (importing ``slcvjax`` imports JAX, about 2 s): a command's module under
:mod:`slcvjax.cli` is imported only when that command runs.  The library's own values the parser
shows (the presets, the preset's box) are repeated here; ``tests/test_cli.py`` checks they agree.
"""

import argparse
import contextlib
import importlib
import logging
import os
import signal
import sys
import threading
from importlib import metadata

# repeated from slcvjax.observations.simulate (checked by tests/test_cli.py)
PRESETS = ("paper",)
PAPER_HALF_WIDTH = 140.0

LOGGER = "slcvjax"


def version() -> str:
    """The installed distribution's version (``slcvjax.__version__``), read without importing the library."""
    try:
        return metadata.version("slcvjax")
    except metadata.PackageNotFoundError:
        return "unknown"


def _command(name: str):
    """The command ``name``'s ``run(args)``, its module imported only when it runs."""

    def run(args) -> int:
        return importlib.import_module(f"slcvjax.cli.{name}").run(args)

    return run


def _add(sub, name: str, help: str) -> argparse.ArgumentParser:
    """A command's parser: its one-line help is also its description, and it takes -v/-q too."""
    parser = sub.add_parser(name, help=help, description=help[0].upper() + help[1:] + ".")
    _verbosity(parser, suppress=True)
    return parser


# repeated from slcvjax.experiments.export (checked by tests/test_export.py)
EXPORT_FORMATS = ("opencv", "opencv-omnidir", "ros", "kalibr", "ocamcalib", "mrcal")


def _board_flags(parser: argparse.ArgumentParser) -> None:
    """``--board`` and ``--square``, the same wherever a chessboard is calibrated (``camera``, ``omni``)."""
    parser.add_argument("--board", required=True, help="the chessboard's inner corners COLSxROWS, e.g. 9x6")
    parser.add_argument("--square", type=float, required=True, help="the chessboard's square size in mm")


def _study_flags(parser: argparse.ArgumentParser, what: str) -> None:
    """A study's ``--cluster``, ``--cluster-cache``, ``--chunk``, ``--resume`` and ``--restart``
    (``slcvjax.experiments.cluster``), the same wherever trials are simulated and calibrated."""
    parser.add_argument(
        "--cluster",
        metavar="auto|local:N|ray://HOST:PORT",
        help=f"run the {what} on a Ray cluster, one task per chunk of trials: auto (a running cluster, "
        "else a local one), local:N (N worker processes here) or a cluster's client address; the same "
        "numbers as without it (needs pip install 'slcvjax[cluster]')",
    )
    parser.add_argument(
        "--cluster-cache",
        metavar="DIR",
        help="a folder every worker reaches (a shared file system) for the compilation cache, so the "
        "cluster compiles each program once (default: a local cluster uses this machine's cache)",
    )
    parser.add_argument(
        "--chunk", type=int, metavar="N", help="trials per chunk (default 8; 256 in lockstep on an accelerator)"
    )
    again = parser.add_mutually_exclusive_group()
    again.add_argument(
        "--resume",
        action="store_true",
        help="resume the run in --out (an error if it holds none); without it a run of the same "
        "settings there is resumed too, and a run of other settings refused",
    )
    again.add_argument("--restart", action="store_true", help="discard the run in --out and start again")


def _export_opencv_flag(parser: argparse.ArgumentParser) -> None:
    """``--export-opencv``, wherever a camera is calibrated (``calibrate``, ``camera``, ``omni``)."""
    parser.add_argument(
        "--export-opencv",
        metavar="FILE",
        help="also write the camera (its lens) as OpenCV FileStorage YAML (the same as slcvjax export --format opencv)",
    )


def _rig_flags(parser: argparse.ArgumentParser, simulate: bool) -> None:
    """The rig's sizes: ``--mirror``, ``--lasers``, ``--mirror-distance`` and ``--image-size``, the same in
    ``setup init`` (a user's rig) and ``simulate`` (a simulated rig of that size; default the preset's)."""
    if simulate:
        parser.add_argument(
            "--mirror",
            help="a rig of another size: its cone mirror, cone:RADIUSxHEIGHT in mm (default the preset's cone:20x10)",
        )
        parser.add_argument("--lasers", type=int, default=10, help="number of lasers (default 10)")
    else:
        parser.add_argument("--mirror", required=True, help="the mirror, cone:RADIUSxHEIGHT in mm, e.g. cone:20x10")
        parser.add_argument("--lasers", type=int, required=True, help="number of lasers")
    parser.add_argument(
        "--mirror-distance", type=float, default=None, help="the mirror's apex in front of the lens, mm (default 48)"
    )
    parser.add_argument("--image-size", default=None, help="the camera's image, WIDTHxHEIGHT px (default 640x480)")


def _box_flags(parser: argparse.ArgumentParser) -> None:
    """The box of targets ``setup init`` lays out (and ``simulate --target`` renders)."""
    parser.add_argument("--box", type=float, default=280.0, help="the box's inner width in mm (default 280)")
    parser.add_argument("--walls", type=int, default=4, help="wall targets around the sensor (default 4)")
    parser.add_argument(
        "--squares", help="per wall: charuco squares, aprilgrid tags or dots, COLSxROWS (default 8x3, 6x2, 3x3)"
    )
    parser.add_argument(
        "--square-mm", type=float, help="charuco square, aprilgrid tag or dots' x pitch, mm (default 18, 18, 50)"
    )
    parser.add_argument("--marker-mm", type=float, help="charuco marker or dots' y pitch, mm (default 13.5, -, 20)")
    parser.add_argument("--spacing", type=float, default=0.3, help="aprilgrid: the gap over the tag (default 0.3)")
    parser.add_argument(
        "--board-z", type=float, help="the boards' centre along the axis, mm (default: the middle of the mirror's view)"
    )
    parser.add_argument(
        "--chessboard",
        default="9x6x20",
        help="the direct-view chessboard, COLSxROWSxSQUARE_MM inner corners (default 9x6x20; 'none': without)",
    )


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="slcvjax", description="Calibrate and measure with a structured-light catadioptric vision sensor."
    )
    p.add_argument("--version", action="version", version=f"%(prog)s {version()}")
    _verbosity(p, suppress=False)
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    s = _add(sub, "simulate", help="simulate a rig's observations and write them with the truth")
    s.add_argument("--preset", default="paper", help="scene preset (default: paper)")
    s.add_argument("--noise", type=float, default=0.0, help="Gaussian pixel noise sigma in px (default 0)")
    s.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    s.add_argument("--views", type=int, default=16, help="number of catadioptric views (default 16)")
    _rig_flags(s, simulate=True)
    s.add_argument(
        "--target",
        choices=("charuco-box", "aprilgrid-box"),
        help="instead of the preset's box of dots: the box of coded targets that slcvjax setup init lays out for "
        "this rig (the same flags: --box, --walls, --squares, ..., --chessboard); --render writes DIR/images/"
        "setup.json as setup init and setup images would",
    )
    s.add_argument(
        "--laser-tilt",
        type=float,
        default=0.0,
        metavar="DEG",
        help="each beam turned this many degrees towards the camera (default 0: nearly across the mirror's axis)",
    )
    s.add_argument(
        "--direct-views", type=int, default=12, help="direct views of the chessboard, for the intrinsics (default 12)"
    )
    s.add_argument("--out", required=True, help="output directory")
    s.add_argument("--render", action="store_true", help="also render DIR/images/ (PNG per view) and setup.json")
    s.add_argument(
        "--pipe",
        type=float,
        default=None,
        metavar="D",
        help="instead: the rig inside a pipe of inner diameter D mm at --views poses (DIR/pipe_observations.json; "
        "--render: DIR/pipe_images/)",
    )
    s.add_argument("--image-noise", type=float, default=1.0, help="sensor noise of rendered images, grey levels")
    s.add_argument("--blur", type=float, default=0.6, help="optical blur of rendered images, px (default 0.6)")
    s.add_argument("--exposure", type=float, default=1.0, help="exposure gain of rendered images (default 1)")
    box = s.add_argument_group("with --target: the box of targets (as slcvjax setup init)")
    _box_flags(box)
    s.set_defaults(func=_command("simulate"))

    t = _add(sub, "detect", help="detect spots, dots, rim and corners in an image folder (with setup.json)")
    t.add_argument("folder", help="image folder holding setup.json (slcv-setup/1)")
    t.add_argument("--out", required=True, help="output slcv-observations/1 file")
    t.set_defaults(func=_command("detect"))

    c = _add(sub, "calibrate", help="calibrate the rig from observation files or image folders")
    c.add_argument("inputs", nargs="+", help="slcv-observations/1 file(s) or image folder(s) with setup.json")
    c.add_argument("--out", required=True, help="output file (one input) or directory (several)")
    c.add_argument(
        "--camera",
        help="a camera that starts the calibration: a slcv-calibration/1 file, OpenCV FileStorage YAML "
        "(camera_matrix, distortion_coefficients, image_width, image_height) or ROS camera_info YAML",
    )
    c.add_argument(
        "--from",
        dest="start_from",
        help="a slcv-calibration/1 file whose camera and mirror start the calibration (with --freeze camera,mirror: "
        "only the poses and lasers are fitted, the held-out evaluation of that calibration)",
    )
    c.add_argument(
        "--options",
        help="a JSON file of calibration options (max_steps, freeze, rigid, robust: loss, outlier_sigmas, "
        "consensus_px, ...; see the formulation page); the flags below override it",
    )
    c.add_argument("--freeze", help="comma-separated blocks to hold fixed: camera, mirror, lasers, poses, chess_poses")
    c.add_argument(
        "--loss",
        default=None,
        choices=["huber", "cauchy", "linear"],
        help="robust loss (default huber); linear: plain least squares, no outlier left out",
    )
    c.add_argument("--loss-scale", type=float, default=None, help="robust loss scale in px (default 3 sigma)")
    c.add_argument(
        "--rigid",
        action="store_const",
        const=True,
        default=None,
        help="the targets the observations declare fixed in one box (rigid_boards) as one pose per board in the "
        "box and one sensor pose per view; a board pose that does not fit the box is left out and reported",
    )
    c.add_argument(
        "--raw-centroids",
        action="store_true",
        help="image folders: calibrate from the centroids as detected (default: each dot's and spot's centroid "
        "corrected for the mirror's distortion of its image at a first calibration, then calibrated again)",
    )
    _export_opencv_flag(c)
    c.add_argument(
        "--report",
        action="store_true",
        help="also write each calibration's HTML report beside it (<out stem>_report.html; see slcvjax report)",
    )
    c.set_defaults(func=_command("calibrate"))

    r = _add(sub, "report", help="write a calibration's report: one self-contained HTML file of figures and tables")
    r.add_argument(
        "calibration", help="a slcv-calibration/1 file written by slcvjax calibrate (one that carries its problem)"
    )
    r.add_argument("--out", required=True, help="output HTML file")
    r.add_argument(
        "--images",
        help="the image folder the observations were detected in (its setup.json names the files): the residuals "
        "are drawn over the images",
    )
    r.add_argument(
        "--range",
        type=float,
        default=None,
        metavar="MM",
        help="range of the projection uncertainty map, mm from the camera (default: the lasers' mean working range)",
    )
    r.set_defaults(func=_command("report"))

    k = _add(sub, "camera", help="calibrate a plain camera from chessboard images")
    k.add_argument("images", nargs="+")
    _board_flags(k)
    k.add_argument("--out", required=True, help="output slcv-calibration/1 file (camera only)")
    _export_opencv_flag(k)
    k.set_defaults(func=_command("camera"))

    o = _add(sub, "omni", help="calibrate a catadioptric camera from chessboard images seen through its mirror")
    o.add_argument("images", nargs="+")
    _board_flags(o)
    o.add_argument("--out", required=True, help="output slcv-calibration/1 file")
    _export_opencv_flag(o)
    o.add_argument(
        "--mirror",
        default="hyperboloid",
        choices=["hyperboloid", "paraboloid", "sphere", "ellipsoid", "auto"],
        help="the mirror's kind (default hyperboloid: its conic constant estimated unless --conic; "
        "auto: the kind of the least held-out error, by 5-fold cross-validation over the images)",
    )
    o.add_argument("--vertex-radius", type=float, help="the mirror's vertex radius in mm (default: 20, the gauge)")
    o.add_argument("--conic", type=float, help="the mirror's conic constant, where known")
    o.add_argument("--rim", type=float, help="the mirror's rim radius in mm, where known")
    o.add_argument(
        "--projection",
        default="auto",
        choices=["auto", "perspective", "telecentric"],
        help="the camera's lens: a pinhole (perspective), telecentric (orthographic), or auto (default: both "
        "fitted, the perspective kept where an F-test of its depth says the images need it)",
    )
    o.add_argument("--telecentric", action="store_true", help="the same as --projection telecentric")
    o.add_argument("--loss", default="huber", choices=["huber", "cauchy", "linear"])
    o.add_argument("--observations", help="also write the detected corners as slcv-observations/1")
    o.add_argument("--plot", help="the residual plot's PNG (default: OUT's name with _residuals.png)")
    o.add_argument("--no-plot", action="store_true")
    o.set_defaults(func=_command("omni"))

    m = _add(sub, "measure", help="3D laser points (and pipe circles) from spots with a calibration")
    m.add_argument("calibration", help="slcv-calibration/1 file")
    m.add_argument(
        "input",
        help="slcv-observations/1 file whose views carry spots (their board may be absent), or a folder of "
        "images (each a view; spots labelled by the calibration's laser lines)",
    )
    m.add_argument("--out", required=True, help="output slcv-points/1 file")
    m.add_argument(
        "--format",
        dest="formats",
        default="json",
        help="comma-separated: json (always written, --out), csv and ply beside it (OUT's name with .csv, .ply; "
        "their columns: see the formats page); default json",
    )
    m.add_argument("--fit-circle", action="store_true", help="fit a circle per view across the axis")
    m.add_argument("--pixel-sigma", type=float, default=None, help="spot pixel noise in px (default: calibration's)")
    m.add_argument("--axis", default=None, help="pipe axis x,y,z in the camera frame (default 0,0,1)")
    m.add_argument(
        "--spot-mm",
        type=float,
        default=None,
        help="images only: the laser spot's Gaussian std on the surface (mm); corrects each centroid for the "
        "mirror's distortion of the spot's image (the surface taken as a pipe's wall about --axis)",
    )
    m.set_defaults(func=_command("measure"))

    x = _add(sub, "export", help="write a calibration's camera in another tool's format")
    x.add_argument("calibration", help="a slcv-calibration/1 file")
    x.add_argument(
        "--format",
        required=True,
        choices=EXPORT_FORMATS,
        help="opencv (FileStorage YAML, K and 5 coefficients), opencv-omnidir (Mei's model: K, D, xi), ros "
        "(camera_info YAML), kalibr (camchain YAML: pinhole or omni, radtan), ocamcalib (calib_results.txt), mrcal "
        "(.cameramodel, LENSMODEL_OPENCV5). With a mirror, opencv-omnidir, kalibr and ocamcalib write the best "
        "central approximation of the rig, fitted over the mirror's field (its RMS and worst pixel error are "
        "printed and written in the file); the others the camera's lens alone",
    )
    x.add_argument("--out", required=True, help="output file")
    x.add_argument(
        "--lens",
        action="store_true",
        help="the camera's lens alone even where the calibration has a mirror (kalibr: pinhole)",
    )
    x.add_argument(
        "--range",
        type=float,
        default=None,
        metavar="MM",
        help="the working range the approximation is fitted about (points at 0.5, 1 and 2 times it, mm from the "
        "camera; default: the lasers' mean working range, else the boards' mean distance)",
    )
    x.set_defaults(func=_command("export"))

    df = _add(sub, "diff", help="compare two calibrations: their difference over the image beside the predicted one")
    df.add_argument("a", metavar="A.json", help="a slcv-calibration/1 file")
    df.add_argument("b", metavar="B.json", help="another calibration of the same sensor")
    df.add_argument("--out", help="also write the maps (difference, predicted, ratio) as a PNG")
    df.add_argument(
        "--range",
        type=float,
        default=None,
        metavar="MM",
        help="the range, mm from the camera, where the two calibrations' rays are compared (default: A's lasers' "
        "mean working range, else its boards' mean distance)",
    )
    df.set_defaults(func=_command("diff"))

    w = _add(sub, "sweep", help="noise-sensitivity sweep: Monte Carlo calibrations beside the bound")
    w.add_argument("--preset", default="paper", choices=PRESETS, help="simulated scene (default paper)")
    w.add_argument("--noise", default="0,0.3,0.6,0.9", help="pixel noise levels, px (default 0,0.3,0.6,0.9)")
    w.add_argument("--trials", type=int, default=8, help="trials per level (default 8)")
    w.add_argument("--seed", type=int, default=0, help="first seed (trial t of level l uses seed + 1000 l + t)")
    w.add_argument("--lasers", type=int, default=10, help="lasers (default 10)")
    w.add_argument("--views", type=int, default=16, help="catadioptric views (default 16)")
    w.add_argument(
        "--batch",
        default="auto",
        choices=("auto", "loop", "vmap"),
        help="trials one after another (loop) or in lockstep, vmap-ped and sharded over the devices "
        "(default auto: loop on a CPU, vmap on an accelerator)",
    )
    w.add_argument(
        "--out", default="slcvjax-sweep", help="output directory, also of each finished chunk (default ./slcvjax-sweep)"
    )
    _study_flags(w, "trials")
    w.set_defaults(func=_command("sweep"))

    g = _add(sub, "design", help="plan a calibration: predict the lasers' accuracy and optimise the sensor poses")
    g.add_argument("--views", type=int, default=16, help="catadioptric views (default 16)")
    g.add_argument(
        "--box",
        type=float,
        default=2 * PAPER_HALF_WIDTH,
        help=f"box width in mm (default {2 * PAPER_HALF_WIDTH:g}, the preset's)",
    )
    g.add_argument(
        "--rotation", default="3,3,20", help="allowed roll,pitch,yaw of the sensor in the box, +- deg (default 3,3,20)"
    )
    g.add_argument("--translation", default="25,25,8", help="allowed x,y,z motion in the box, +- mm (default 25,25,8)")
    g.add_argument("--noise", type=float, default=0.5, help="pixel noise in px (default 0.5)")
    g.add_argument("--lasers", type=int, default=10, help="lasers (default 10)")
    g.add_argument("--steps", type=int, default=60, help="most gradient steps (default 60)")
    g.add_argument(
        "--position-weight", type=float, default=0.5, help="weight of the position error beside the direction's (0.5)"
    )
    g.add_argument(
        "--measure",
        action="store_true",
        help="design the lasers (elevations, ring radius and height) for measuring pipes instead of the poses",
    )
    g.add_argument(
        "--diameters", default="100,150,200,250,300", help="with --measure: the pipes in mm (default 100,...,300)"
    )
    g.add_argument("--elevation-range", type=float, default=20.0, help="with --measure: +- deg per beam (20)")
    g.add_argument("--ring-radius-range", type=float, default=10.0, help="with --measure: +- mm (10)")
    g.add_argument("--ring-z-range", type=float, default=25.0, help="with --measure: +- mm along the axis (25)")
    g.add_argument("--confirm", type=int, default=0, help="simulate and calibrate each plan N times")
    g.add_argument("--seed", type=int, default=0, help="first seed of the confirmation")
    g.add_argument("--out", default="slcvjax-design", help="output directory (default ./slcvjax-design)")
    _study_flags(g, "--confirm calibrations")
    g.set_defaults(func=_command("design"))

    q = _add(sub, "pipe", help="the paper's pipe experiment on the simulated rig")
    q.add_argument("--calibration", help="measure with this calibration (default: the true rig)")
    q.add_argument("--noise", type=float, default=0.5, help="spot pixel noise in px (default 0.5)")
    q.add_argument("--diameter", type=float, default=150.0, help="pipe diameter in mm (default 150)")
    q.add_argument("--poses", type=int, default=16, help="sensor poses in the pipe (default 16)")
    q.add_argument("--offset", type=float, default=10.0, help="largest offset of the pipe's axis in mm (default 10)")
    q.add_argument("--tilt", type=float, default=0.0, help="pipe axis tilt from the camera z axis in deg (default 0)")
    q.add_argument("--lasers", type=int, default=10, help="lasers of the simulated rig (default 10)")
    q.add_argument(
        "--laser",
        choices=["point", "ring"],
        default="point",
        help="point: the paper's point lasers; ring: a ring laser and 4 point lasers "
        "(sheet_rig(paper_rig(), cone, point x4)), its stripe measured and a circle and ellipse fitted per view",
    )
    q.add_argument("--seed", type=int, default=0)
    q.add_argument("--out", default="slcvjax-pipe", help="output directory (default ./slcvjax-pipe)")
    q.set_defaults(func=_command("pipe"))

    tg = _add(sub, "target", help="write a true-scale PDF per board of a setup.json and the box's build sheet")
    tg.add_argument("setup", help="a slcv-setup/1 file (setup.json)")
    tg.add_argument("--out", required=True, help="output directory (BOARD.pdf per board, build_sheet.md and .png)")
    tg.set_defaults(func=_command("target"))

    su = _add(sub, "setup", help="write a setup.json for your own rig")
    su_sub = su.add_subparsers(dest="setup_command", required=True)
    si = su_sub.add_parser(
        "init", help="a setup.json for a box of printed targets around the sensor (then: slcvjax target)"
    )
    _rig_flags(si, simulate=False)
    si.add_argument(
        "--target",
        default="charuco-box",
        choices=("charuco-box", "aprilgrid-box", "dots-box"),
        help="the wall targets (default charuco-box)",
    )
    si.add_argument("--out", default="setup.json", help="output file (default ./setup.json)")
    _box_flags(si)
    si.set_defaults(func=_command("setup"))
    sm = su_sub.add_parser(
        "images",
        help="after the photos: write IMAGE_DIR/setup.json, the setup with the images listed (then: slcvjax detect)",
    )
    sm.add_argument("setup", help="the slcv-setup/1 file setup init wrote")
    sm.add_argument("folder", help="the image folder (its setup.json is written; the images are named relative to it)")
    sm.add_argument(
        "--views",
        default="view*.png",
        metavar="GLOB",
        help="the catadioptric images (the sensor in the box), a pattern in the folder (default view*.png)",
    )
    sm.add_argument(
        "--direct",
        default="chess*.png",
        metavar="GLOB",
        help="the direct views of the chessboard (for the intrinsics), a pattern in the folder (default chess*.png; "
        "'none': without)",
    )
    sm.set_defaults(func=_command("setup"))

    d = _add(sub, "demo", help="the main job on the simulated reference rig")
    d.add_argument(
        "--noise",
        type=float,
        default=0.5,
        help="pixel noise of the pipe spots (and of --no-images), px (default 0.5)",
    )
    d.add_argument("--image-noise", type=float, default=1.0, help="sensor noise of the images, grey levels (default 1)")
    d.add_argument(
        "--no-images", action="store_true", help="calibrate the simulated observations directly (no render or detect)"
    )
    poses = d.add_mutually_exclusive_group()
    poses.add_argument(
        "--rigid",
        action="store_true",
        help="calibrate with the rigid target box model (one pose per wall, one sensor pose per view): the default",
    )
    poses.add_argument(
        "--free-poses",
        action="store_true",
        help="calibrate with a free pose per wall and view instead of the rigid target box",
    )
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--views", type=int, default=16, help="catadioptric views (default 16)")
    d.add_argument("--lasers", type=int, default=10, help="lasers (default 10)")
    d.add_argument("--out", default="slcvjax-demo", help="output directory (default ./slcvjax-demo)")
    d.set_defaults(func=_command("demo"))
    return p


class _Stdout(logging.Handler):
    """Writes each record's message to the ``sys.stdout`` of the moment (a test's capture included)."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            stream = sys.stderr if record.levelno >= logging.WARNING else sys.stdout
            stream.write(self.format(record) + "\n")
            stream.flush()
        except Exception:
            self.handleError(record)


def configure_logging(verbose: int = 0, quiet: int = 0) -> logging.Logger:
    """The ``slcvjax`` logger at the level the flags ask: default INFO (the commands' reports),
    ``-q`` WARNING (only warnings and errors; progress bars off), ``-v`` DEBUG."""
    log = logging.getLogger(LOGGER)
    for h in [h for h in log.handlers if isinstance(h, _Stdout)]:
        log.removeHandler(h)
    handler = _Stdout()
    handler.setFormatter(logging.Formatter("%(message)s"))
    log.addHandler(handler)
    log.propagate = False
    level = logging.INFO + 10 * (quiet - verbose)
    log.setLevel(min(max(level, logging.DEBUG), logging.ERROR))
    if quiet:
        os.environ["TQDM_DISABLE"] = "1"  # read by tqdm when it is first imported (the commands import it late)
    return log


# the commands' helpers (slcvjax.cli.common) report through the logger even when called directly
configure_logging()


def _verbosity(parser: argparse.ArgumentParser, suppress: bool) -> None:
    default = argparse.SUPPRESS if suppress else 0
    parser.add_argument(
        "-v", "--verbose", action="count", default=default, help="more output (debug messages); repeatable"
    )
    parser.add_argument("-q", "--quiet", action="count", default=default, help="less output: only warnings and errors")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    tqdm_disable = os.environ.get("TQDM_DISABLE")
    log = configure_logging(getattr(args, "verbose", 0), getattr(args, "quiet", 0))
    try:
        return _run(args, log)
    finally:  # a caller in the same process (a test, a notebook) gets the defaults back
        configure_logging()
        if tqdm_disable is None:
            os.environ.pop("TQDM_DISABLE", None)


def _run(args: argparse.Namespace, log: logging.Logger) -> int:
    from slcvjax import FormatError  # the library, and JAX, from here on

    if log.isEnabledFor(logging.DEBUG):
        import jax

        from slcvjax import compilation_cache_dir

        log.debug(
            f"slcvjax {version()}, JAX {jax.__version__} on {jax.default_backend()}, "
            f"compilation cache {compilation_cache_dir()}"
        )
    from slcvjax.observations.formats import OutputError, forget_checked_folders

    try:
        with stop_on_signals(args.command):
            return args.func(args)
    except (FormatError, ValueError) as e:
        print(f"slcvjax {args.command}: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # an output that cannot be written, another file-system error: one line
        text = str(e) if isinstance(e, OutputError) or e.filename is None else f"{e.filename}: {e.strerror or e}"
        print(f"slcvjax {args.command}: error: {text}", file=sys.stderr)
        return 2
    finally:
        forget_checked_folders()  # the folders this command checked (a vanished one is not made again)


@contextlib.contextmanager
def stop_on_signals(command: str):
    """While it lasts (in the main thread), SIGINT and SIGTERM stop the process at once: the
    temporaries of the atomic writes under way are deleted (their targets stay absent or as
    they were), one line goes to stderr, and the exit status is 128 + the signal (130, 143).

    Not an exception: one raised from a signal handler is lost where the handler runs inside a
    callback (JAX's garbage-collection callback swallowed it, and a calibration stopped by
    SIGTERM went on to write its output)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum, frame):
        from slcvjax.observations.formats import discard_temporaries

        discard_temporaries()
        try:
            sys.stdout.flush()
            print(f"slcvjax {command}: stopped by signal {signum}; no output was left half written", file=sys.stderr)
            sys.stderr.flush()
            study = sys.modules.get("slcvjax.experiments.cluster")
            if study is not None:  # a local Ray cluster it started goes with it
                study.shutdown_started()
        finally:
            os._exit(128 + signum)

    previous = {s: signal.signal(s, stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, signal.SIG_DFL if handler is None else handler)
