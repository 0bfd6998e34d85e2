"""The public file formats ``slcv-observations/1`` and ``slcv-calibration/1`` (DESIGN section 3).

Readers validate everything and raise :class:`FormatError` with a one-line
message naming the file, the field and the index (``obs.json: views[3].spots[2].laser:
...``).  Writers are atomic: the file is written beside its target and renamed
into place, so a failure never leaves a half-written file.  Extra fields are
kept in ``extra`` and ignored.
"""

import json
import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from ..geometry.camera import Camera
from ..geometry.lasers import Lasers
from ..geometry.mirror import mirror_of_shape, shape_json
from ..geometry.pose import Pose
from ..geometry.rig import Rig
from ..geometry.sheets import Sheets

OBSERVATIONS_FORMAT = "slcv-observations/1"
CALIBRATION_FORMAT = "slcv-calibration/1"


class FormatError(ValueError):
    """Bad input file: the message names the file, the field and the index."""


MAX_FLOAT = 1.7976931348623157e308  # the largest float64: an integer past it has no float
MAX_INT = 2**31 - 1  # the largest integer (a size, a count, an index) a file may give


# --------------------------------------------------------------------------- validation helpers


class ReadContext:
    def __init__(self, path: str):
        self.path = path

    def fail(self, where: str, msg: str):
        raise FormatError(f"{self.path}: {where}: {msg}")

    def get(self, obj: Any, key: str, where: str, kind: type | tuple = object, optional: bool = False):
        if not isinstance(obj, dict):
            self.fail(where or "(top level)", f"expected an object, got {type(obj).__name__}")
        full = f"{where}.{key}" if where else key
        if key not in obj or obj[key] is None:
            if optional:
                return None
            self.fail(full, "missing")
        val = obj[key]
        if kind is not object and not isinstance(val, kind):
            names = kind.__name__ if isinstance(kind, type) else "/".join(k.__name__ for k in kind)
            self.fail(full, f"expected {names}, got {type(val).__name__}")
        return val

    def number(self, val: Any, where: str) -> float:
        if isinstance(val, bool) or not isinstance(val, (int, float)):
            self.fail(where, f"expected a number, got {json.dumps(val)[:40]}")
        if isinstance(val, int) and abs(val) > MAX_FLOAT:  # an integer beyond float64: no float
            self.fail(where, f"number out of range ({len(str(abs(val)))} digits)")
        if not math.isfinite(val):
            self.fail(where, f"non-finite number {val}")
        return float(val)

    def positive(self, val: Any, where: str) -> float:
        x = self.number(val, where)
        if x <= 0.0:
            self.fail(where, f"must be positive, got {x:g}")
        return x

    def integer(self, val: Any, where: str, lo: int | None = None, hi: int | None = None) -> int:
        if isinstance(val, bool) or not isinstance(val, int):
            self.fail(where, f"expected an integer, got {json.dumps(val)[:40]}")
        shown = str(val) if abs(val) < 10**20 else f"an integer of {len(str(abs(val)))} digits"
        if lo is not None and val < lo:
            self.fail(where, f"{shown} is out of range (minimum {lo})")
        if hi is not None and val >= hi:
            self.fail(where, f"{shown} is out of range [0, {hi})")
        if abs(val) > MAX_INT:  # a count or size past int32: no array holds it
            self.fail(where, f"{shown} is out of range (at most {MAX_INT})")
        return val

    def vector(self, val: Any, n: int, where: str) -> np.ndarray:
        if not isinstance(val, list) or len(val) != n:
            got = f"length {len(val)}" if isinstance(val, list) else type(val).__name__
            self.fail(where, f"expected a list of {n} numbers, got {got}")
        return np.array([self.number(v, f"{where}[{i}]") for i, v in enumerate(val)])

    def matrix(self, val: Any, rows: int, cols: int, where: str) -> np.ndarray:
        if not isinstance(val, list) or len(val) != rows:
            self.fail(where, f"expected {rows} rows of {cols} numbers")
        return np.stack([self.vector(r, cols, f"{where}[{i}]") for i, r in enumerate(val)])

    def list_of(self, obj: Any, key: str, where: str, optional: bool = False) -> list:
        val = self.get(obj, key, where, list, optional=optional)
        return [] if val is None else val


def load_json(path: str | os.PathLike) -> tuple[ReadContext, Any]:
    ctx = ReadContext(str(path))
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        ctx.fail("(file)", "no such file")
    except (OSError, UnicodeDecodeError) as e:
        ctx.fail("(file)", f"cannot read: {e}")
    try:
        return ctx, json.loads(text)
    except json.JSONDecodeError as e:
        ctx.fail("(file)", f"not valid JSON ({e.msg} at line {e.lineno} column {e.colno}; truncated?)")
    except RecursionError:
        ctx.fail("(file)", "not a file of this format (JSON nested too deeply to read)")


def _check_format(ctx: ReadContext, doc: Any, expected: str):
    fmt = ctx.get(doc, "format", "", str)
    if fmt != expected:
        ctx.fail("format", f"expected {expected!r}, got {fmt!r}")


class OutputError(OSError):
    """An output that cannot be written: the message names the file and why (one line)."""


def _why(e: OSError) -> str:
    return e.strerror or str(e)


def temp_name_pattern(path: str | os.PathLike) -> str:
    """The glob of the temporary files an atomic write of ``path`` makes beside it: hidden,
    named after the target and ending in ``.tmp`` (or ``.tmp<suffix>``).  A write that fails
    (an exception) deletes its own, and the command line deletes those under way when SIGINT or
    SIGTERM stops it (:func:`discard_temporaries`); only a process killed outright (SIGKILL, a
    power cut) can leave one behind, never the target half written."""
    return f".{Path(path).name}.*.tmp*"


_ACTIVE: set[Path] = set()  # the temporaries of the atomic writes under way in this process


def discard_temporaries() -> None:
    """Delete the temporaries of the atomic writes under way (their targets untouched): what a
    process stopped by a signal does before it exits."""
    for tmp in list(_ACTIVE):
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass


def abandon_target(tmp: Path) -> None:
    """Delete the temporary ``tmp`` of an atomic write that failed."""
    _ACTIVE.discard(tmp)
    tmp.unlink(missing_ok=True)


def _cannot_write(path: Path, e: OSError) -> OutputError:
    """The one-line error of an output that cannot be written, naming a file in the way."""
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                return OutputError(f"{path}: cannot write: {parent} is a file, not a directory")
            break
    return OutputError(f"{path}: cannot write: {_why(e)}")


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and a.samefile(b)
    except OSError:
        return False


def check_writable(path: str | os.PathLike, inputs: tuple = ()) -> None:
    """Raise :class:`OutputError` where ``path`` cannot be written (its folder cannot be made
    or takes no file, it is a folder, or it is one of the ``inputs``): a command checks its
    outputs before a long run."""
    path = Path(path)
    for inp in inputs:
        if inp is not None and _same_file(path, Path(inp)):
            raise OutputError(f"{path}: would overwrite the input {inp}; give another output")
    if path.is_dir():
        raise OutputError(f"{path}: cannot write: it is a directory")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        os.close(fd)
        os.unlink(tmp)
    except OSError as e:
        raise _cannot_write(path, e) from None
    _CHECKED.add(path.parent.absolute())


# the folders :func:`check_writable` found or made: one that has vanished by the time of the
# write is not made again (an unmounted drive's folder would be made on the disk below it)
_CHECKED: set[Path] = set()


def forget_checked_folders() -> None:
    """Forget the folders :func:`check_writable` found (a command's end: the next command in the
    same process checks its own)."""
    _CHECKED.clear()


def atomic_target(path: str | os.PathLike, suffix: str = "") -> tuple[Path, Path]:
    """``(path, temporary)``: a fresh temporary file beside ``path`` (see
    :func:`temp_name_pattern`) for a writer to fill and :func:`commit_target` to rename into
    place; :class:`OutputError` where the folder cannot take it."""
    path = Path(path)
    if path.parent.absolute() in _CHECKED and not path.parent.is_dir():
        raise OutputError(f"{path}: cannot write: its folder {path.parent} has vanished since the command started")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + suffix, dir=path.parent)
        os.close(fd)
    except OSError as e:
        raise _cannot_write(path, e) from None
    _ACTIVE.add(Path(tmp))
    return path, Path(tmp)


def _umask() -> int:
    try:  # Linux: read without changing it (os.umask would, for every thread)
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def commit_target(path: Path, tmp: Path) -> None:
    """Rename the filled temporary ``tmp`` onto ``path`` (atomic), with the mode an ordinary
    write would give it (the old file's, else 0666 less the umask; the temporary is 0600);
    :class:`OutputError` where it fails."""
    try:
        os.chmod(tmp, path.stat().st_mode & 0o7777 if path.is_file() else 0o666 & ~_umask())
        os.replace(tmp, path)
        _ACTIVE.discard(tmp)
    except OSError as e:
        abandon_target(tmp)
        raise (
            OutputError(f"{path}: cannot write: it is a directory") if path.is_dir() else _cannot_write(path, e)
        ) from None


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Write a text file atomically: a temporary file beside the target (:func:`temp_name_pattern`),
    flushed to disk, then renamed onto it, so the target is either absent, as it was, or whole.
    Raises :class:`OutputError` (one line naming the file) where it cannot be written, leaving
    no temporary file."""
    path, tmp = atomic_target(path)
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
    except BaseException as e:
        abandon_target(tmp)
        if isinstance(e, OSError):
            raise _cannot_write(path, e) from None
        raise
    commit_target(path, tmp)


def write_json_atomic(path: str | os.PathLike, doc: Any) -> None:
    """Write JSON atomically (temporary file beside the target, then rename); rejects NaN."""
    write_text_atomic(path, json.dumps(doc, indent=1, allow_nan=False) + "\n")


# --------------------------------------------------------------------------- observations


@dataclass
class CalibrationViewObs:
    """A direct (mirror-free) chessboard view: pixels (M, 2) and which are seen (M,)."""

    name: str
    board: str
    pixels: np.ndarray
    seen: np.ndarray


@dataclass
class SpotObs:
    """One laser spot: the laser index, the board whose plane it lies on (or None), the pixel."""

    laser: int
    board: str | None
    pixel: np.ndarray


@dataclass
class StripeObs:
    """One laser stripe: the laser (a line or ring laser's index in the file), the board whose
    plane it lies on (or None), and its sub-pixel centre-line samples (M, 2) px, each an
    independent measurement."""

    laser: int
    board: str | None
    pixels: np.ndarray


@dataclass
class ViewObs:
    """A catadioptric view: per board the pixels (M, 2) and seen mask (M,), spots, rim pixels
    (R, 2), and the stripes of its line and ring lasers."""

    name: str
    boards: dict[str, tuple[np.ndarray, np.ndarray]]
    spots: list[SpotObs]
    rim: np.ndarray
    stripes: list[StripeObs] = field(default_factory=list)


@dataclass
class Observations:
    """Everything a calibration consumes (``slcv-observations/1``)."""

    image_size: tuple[int, int]
    mirror_radius: float
    mirror_height: float
    n_lasers: int
    boards: dict[str, np.ndarray]
    calibration_views: list[CalibrationViewObs]
    views: list[ViewObs]
    extra: dict = field(default_factory=dict)
    # the mirror's shape (``slcvjax.geometry.mirror.shape_json``'s form) where it is not the cone of
    # ``mirror_radius`` and ``mirror_height`` (the rim circle's radius and sag, for every kind)
    mirror_shape: dict | None = None
    # ``perspective`` (a pinhole), ``telecentric`` (orthographic: see ``slcvjax.geometry.camera``)
    # or ``auto`` (chosen by the calibration: ``slcvjax.calibration.model_selection.perspective_test``)
    camera_projection: str = "perspective"
    # each typed board's ``type`` and fields (``slcvjax.observations.targets.read_board``'s spec);
    # a board absent here is ``dots``, given by its points alone
    board_types: dict[str, dict] = field(default_factory=dict)
    # each laser's kind (``point``, ``plane``, ``cone``) in order; empty: every laser a point laser
    laser_kinds: tuple[str, ...] = ()

    @property
    def element_kinds(self) -> tuple[str, ...]:
        """Each laser's kind in order (``point`` where the file names none)."""
        return tuple(self.laser_kinds) if self.laser_kinds else ("point",) * self.n_lasers

    @property
    def n_points(self) -> int:
        """The number of point lasers (spots' lasers)."""
        return sum(k == "point" for k in self.element_kinds)

    @property
    def n_sheets(self) -> int:
        """The number of line and ring lasers (stripes' lasers)."""
        return self.n_lasers - self.n_points

    def local_index(self) -> np.ndarray:
        """(n_lasers,) int64: each laser's index among the lasers of its own collection (point
        lasers, or line and ring lasers), see :attr:`slcvjax.geometry.rig.Rig.local_index`."""
        kinds = self.element_kinds
        return np.asarray(
            [sum((k == "point") == (kinds[i] == "point") for k in kinds[:i]) for i in range(len(kinds))],
            dtype=np.int64,
        )


LASER_KINDS = ("point", "plane", "cone")
PROJECTIONS = ("perspective", "telecentric")


def _pixels(ctx: ReadContext, val: Any, n: int, where: str) -> tuple[np.ndarray, np.ndarray]:
    if not isinstance(val, list):
        ctx.fail(where, f"expected a list of {n} pixels, got {type(val).__name__}")
    if len(val) != n:
        ctx.fail(where, f"{len(val)} pixels for a board of {n} points")
    px = np.zeros((n, 2))
    seen = np.zeros(n, dtype=bool)
    for i, p in enumerate(val):
        if p is None:
            continue
        px[i] = ctx.vector(p, 2, f"{where}[{i}]")
        seen[i] = True
    return px, seen


def shape_keys(kind: str) -> list[str]:
    """The dimensions a conic mirror of ``kind`` is given by (``auto``: none)."""
    if kind == "auto":
        return []
    if kind == "asphere":
        return ["vertex_radius", "radius", "conic_constant", "coefficients"]
    return ["vertex_radius", "radius"] + (["conic_constant"] if kind in ("hyperboloid", "ellipsoid") else [])


def shape_missing(shape: dict | None) -> list[str]:
    """The dimensions a (conic) ``mirror_shape`` leaves out; none for a cone (None)."""
    return [] if shape is None else [k for k in shape_keys(shape["kind"]) if k not in shape]


def read_shape(ctx: "ReadContext", shape: Any, where: str, partial: bool = False) -> tuple[float, float, dict | None]:
    """A mirror's shape (``mirror_shape``, or a calibration's ``mirror``): the rim's radius and
    sag, and the shape (None for a cone).  ``kind``: cone (``radius``, ``height``), sphere or
    paraboloid (``vertex_radius``, ``radius``), hyperboloid or ellipsoid (those and
    ``conic_constant``), asphere (those and ``coefficients``).  ``partial`` (observations): a
    conic mirror's dimensions may be left out, for a calibration from views through the mirror
    alone (the vertex radius is then the scale's gauge, ``slcvjax.calibration.central.GAUGE_VERTEX_RADIUS``, the
    conic constant is estimated and the rim bounds nothing); the rim's radius and sag are then 0
    where not known."""
    from ..geometry.mirror import MIRROR_KINDS, mirror_of_shape

    kind = ctx.get(shape, "kind", where, str)
    if partial and kind == "auto":  # the kind chosen by held-out views (``slcvjax.calibration.calibrate.calibrate``)
        auto: dict = {"kind": "auto"}
        if "vertex_radius" in shape:
            auto["vertex_radius"] = ctx.positive(shape["vertex_radius"], f"{where}.vertex_radius")
        return 0.0, 0.0, auto
    if kind not in MIRROR_KINDS:
        known = ", ".join(MIRROR_KINDS + (("auto",) if partial else ()))
        ctx.fail(f"{where}.kind", f"unknown mirror kind {kind!r} (known: {known})")
    if kind == "cone":
        radius = ctx.positive(ctx.get(shape, "radius", where), f"{where}.radius")
        height = ctx.positive(ctx.get(shape, "height", where), f"{where}.height")
        if not math.isfinite(radius / height):  # the slope r / h every ray meets
            ctx.fail(f"{where}.height", f"the slope radius / height is not finite ({radius:g} / {height:g})")
        return radius, height, None
    out: dict = {"kind": kind}
    keys = shape_keys(kind)
    for key in keys:
        if partial and key not in shape:
            continue
        val = ctx.get(shape, key, where)
        if key == "coefficients":
            if not isinstance(val, list):
                ctx.fail(f"{where}.{key}", f"expected a list of numbers, got {type(val).__name__}")
            out[key] = [ctx.number(v, f"{where}.{key}[{i}]") for i, v in enumerate(val)]
        elif key == "conic_constant":
            out[key] = ctx.number(val, f"{where}.{key}")
        else:
            out[key] = ctx.positive(val, f"{where}.{key}")
    if kind == "asphere" and shape_missing(out):
        ctx.fail(f"{where}.{shape_missing(out)[0]}", "an asphere is given by all its dimensions (none is estimated)")
    if shape_missing(out):  # dimensions left out: checked where they are estimated
        return out.get("radius", 0.0), 0.0, out
    try:
        mirror = mirror_of_shape(out, [0.0, 0.0, 1.0], [0.0, 0.0, 1.0])
        sag = float(mirror.height)
    except ValueError as e:
        ctx.fail(where, str(e))
    except ArithmeticError as e:  # a dimension too large for float64 overflows
        ctx.fail(where, f"dimensions out of range ({e})")
    if not math.isfinite(sag):
        ctx.fail(where, f"dimensions out of range (the rim's sag is {sag})")
    return out["radius"], sag, out


def read_sensor_fields(ctx: ReadContext, doc: Any) -> tuple[tuple[int, int], float, float, int, dict | None]:
    """``image_size``, ``mirror_shape`` (the rim's radius and sag, and the shape: None for a
    cone) and ``n_lasers``, shared by the input formats."""
    size = ctx.get(doc, "image_size", "", list)
    if len(size) != 2:
        ctx.fail("image_size", f"expected [width, height], got {len(size)} values")
    w = ctx.integer(size[0], "image_size[0]", lo=1)
    h = ctx.integer(size[1], "image_size[1]", lo=1)
    radius, height, shape = read_shape(ctx, ctx.get(doc, "mirror_shape", "", dict), "mirror_shape", partial=True)
    n_lasers = ctx.integer(ctx.get(doc, "n_lasers", ""), "n_lasers", lo=0)
    return (w, h), radius, height, n_lasers, shape


def read_observations(path: str | os.PathLike) -> Observations:
    """Read and validate a ``slcv-observations/1`` file (raises :class:`FormatError`)."""
    return _observations_of(*load_json(path))


def observations_from_json(doc: Any, source: str) -> Observations:
    """The :class:`Observations` of a ``slcv-observations/1`` document already parsed (``source``
    names it in errors, e.g. ``"cal.json: problem.observations"``); validated as
    :func:`read_observations` validates a file."""
    return _observations_of(ReadContext(source), doc)


def _observations_of(ctx: ReadContext, doc: Any) -> Observations:
    _check_format(ctx, doc, OBSERVATIONS_FORMAT)
    units = ctx.get(doc, "units", "", str, optional=True)
    if units is not None and units != "mm":
        ctx.fail("units", f"expected 'mm', got {units!r}")
    (w, h), radius, height, n_lasers, shape = read_sensor_fields(ctx, doc)
    projection = ctx.get(doc, "camera_projection", "", str, optional=True) or "perspective"
    if projection not in PROJECTIONS + ("auto",):
        ctx.fail("camera_projection", f"expected one of {', '.join(PROJECTIONS)} or auto, got {projection!r}")

    from .targets import check_disjoint_ids, read_board

    boards_doc = ctx.get(doc, "boards", "", dict)
    boards: dict[str, np.ndarray] = {}
    board_types: dict[str, dict] = {}
    for name, b in boards_doc.items():
        boards[name], spec = read_board(ctx, b, f"boards.{name}")  # points given or generated by type
        if spec is not None:
            board_types[name] = spec
    check_disjoint_ids(ctx, board_types)

    def board_points(name: Any, where: str) -> np.ndarray:
        if not isinstance(name, str) or name not in boards:
            ctx.fail(where, f"unknown board {json.dumps(name)} (known: {', '.join(sorted(boards)) or 'none'})")
        return boards[name]

    cal_views = []
    for i, v in enumerate(ctx.list_of(doc, "calibration_views", "", optional=True)):
        where = f"calibration_views[{i}]"
        name = ctx.get(v, "name", where, str)
        board = ctx.get(v, "board", where, str)
        pts = board_points(board, f"{where}.board")
        px, seen = _pixels(ctx, ctx.get(v, "pixels", where), len(pts), f"{where}.pixels")
        cal_views.append(CalibrationViewObs(name, board, px, seen))

    laser_kinds: tuple[str, ...] = ()
    kinds_doc = ctx.list_of(doc, "laser_kinds", "", optional=True)
    if kinds_doc:
        if len(kinds_doc) != n_lasers:
            ctx.fail("laser_kinds", f"expected {n_lasers} kinds (n_lasers), got {len(kinds_doc)}")
        for j, k in enumerate(kinds_doc):
            if k not in LASER_KINDS:
                ctx.fail(f"laser_kinds[{j}]", f"expected one of {', '.join(LASER_KINDS)}, got {json.dumps(k)[:40]}")
        if any(k != "point" for k in kinds_doc):
            laser_kinds = tuple(kinds_doc)
    kinds = laser_kinds or ("point",) * n_lasers

    views = []
    for i, v in enumerate(ctx.list_of(doc, "views", "")):
        where = f"views[{i}]"
        name = ctx.get(v, "name", where, str)
        vb = ctx.get(v, "boards", where, dict, optional=True) or {}
        per_board = {}
        for bname, pix in vb.items():
            pts = board_points(bname, f"{where}.boards.{bname}")
            per_board[bname] = _pixels(ctx, pix, len(pts), f"{where}.boards.{bname}")
        spots = []
        for j, s in enumerate(ctx.list_of(v, "spots", where, optional=True)):
            sw = f"{where}.spots[{j}]"
            laser = ctx.integer(ctx.get(s, "laser", sw), f"{sw}.laser", lo=0, hi=n_lasers)
            board = ctx.get(s, "board", sw, optional=True)
            if board is not None:
                board_points(board, f"{sw}.board")
            if kinds[laser] != "point":
                ctx.fail(
                    f"{sw}.laser", f"laser {laser} is a {kinds[laser]} laser (laser_kinds): it draws stripes, not spots"
                )
            spots.append(SpotObs(laser, board, ctx.vector(ctx.get(s, "pixel", sw), 2, f"{sw}.pixel")))
        stripes = []
        for j, s in enumerate(ctx.list_of(v, "stripes", where, optional=True)):
            sw = f"{where}.stripes[{j}]"
            laser = ctx.integer(ctx.get(s, "laser", sw), f"{sw}.laser", lo=0, hi=n_lasers)
            if kinds[laser] == "point":
                ctx.fail(
                    f"{sw}.laser",
                    f"laser {laser} is a point laser: a stripe needs a line or ring laser (name each laser's kind "
                    "in laser_kinds: point, plane or cone)",
                )
            board = ctx.get(s, "board", sw, optional=True)
            if board is not None:
                board_points(board, f"{sw}.board")
            pix_doc = ctx.list_of(s, "pixels", sw)
            pix = np.zeros((len(pix_doc), 2))
            for k, p in enumerate(pix_doc):
                pix[k] = ctx.vector(p, 2, f"{sw}.pixels[{k}]")
            stripes.append(StripeObs(laser, board, pix))
        rim_doc = ctx.list_of(v, "rim", where, optional=True)
        rim = np.zeros((len(rim_doc), 2))
        for j, p in enumerate(rim_doc):
            rim[j] = ctx.vector(p, 2, f"{where}.rim[{j}]")
        views.append(ViewObs(name, per_board, spots, rim, stripes))

    # fields kept in ``extra`` that a calibration reads: checked here, kept as they are
    for i, b in enumerate(ctx.list_of(doc, "rigid_boards", "", optional=True)):
        board_points(b, f"rigid_boards[{i}]")
    det = ctx.get(doc, "detection", "", dict, optional=True)
    if det is not None:
        _check_detection(ctx, det, boards, len(views))

    known = {
        "format",
        "units",
        "image_size",
        "mirror_shape",
        "n_lasers",
        "boards",
        "calibration_views",
        "views",
        "camera_projection",
        "laser_kinds",
    }
    extra = {k: v for k, v in doc.items() if k not in known}
    return Observations(
        (w, h), radius, height, n_lasers, boards, cal_views, views, extra, shape, projection, board_types, laser_kinds
    )


def _check_detection(ctx: ReadContext, det: dict, boards: dict[str, np.ndarray], n_views: int) -> None:
    """The ``detection`` record of detected observations, as far as a calibration reads it
    (:mod:`slcvjax.images.centroids`): ``dot_radius_mm`` (per board, a positive number or null),
    ``spot_sigma_mm`` (positive or null) and ``ambiguous_boards`` (per target left out, its
    view, board and two or more candidate placements: pixels and the board points' indices)."""

    def known_board(name: Any, where: str) -> int:
        if not isinstance(name, str) or name not in boards:
            ctx.fail(where, f"unknown board {json.dumps(name)[:40]} (known: {', '.join(sorted(boards)) or 'none'})")
        return len(boards[name])

    radii = ctx.get(det, "dot_radius_mm", "detection", dict, optional=True) or {}
    for b, r in radii.items():
        known_board(b, f"detection.dot_radius_mm.{b}")
        if r is not None:
            ctx.positive(r, f"detection.dot_radius_mm.{b}")
    sigma = ctx.get(det, "spot_sigma_mm", "detection", optional=True)
    if sigma is not None:
        ctx.positive(sigma, "detection.spot_sigma_mm")
    for i, e in enumerate(ctx.list_of(det, "ambiguous_boards", "detection", optional=True)):
        where = f"detection.ambiguous_boards[{i}]"
        ctx.integer(ctx.get(e, "view", where), f"{where}.view", lo=0, hi=n_views)
        n = known_board(ctx.get(e, "board", where), f"{where}.board")
        cands = ctx.list_of(e, "candidates", where)
        if len(cands) < 2:
            ctx.fail(f"{where}.candidates", f"an ambiguous target has two or more placements, got {len(cands)}")
        for j, c in enumerate(cands):
            cw = f"{where}.candidates[{j}]"
            idx = [
                ctx.integer(k, f"{cw}.indices[{m}]", lo=0, hi=n) for m, k in enumerate(ctx.list_of(c, "indices", cw))
            ]
            if len(set(idx)) < len(idx):
                ctx.fail(f"{cw}.indices", "a board point is listed twice")
            pixels = ctx.list_of(c, "pixels", cw)
            if len(pixels) != len(idx):
                ctx.fail(f"{cw}.pixels", f"{len(pixels)} pixels for {len(idx)} indices")
            for m, px in enumerate(pixels):
                ctx.vector(px, 2, f"{cw}.pixels[{m}]")


def _px_list(px: np.ndarray, seen: np.ndarray) -> list:
    return [[float(p[0]), float(p[1])] if s else None for p, s in zip(px, seen, strict=True)]


def observations_to_json(obs: Observations) -> dict:
    """The ``slcv-observations/1`` document of an :class:`Observations`."""
    doc = {
        "format": OBSERVATIONS_FORMAT,
        "units": "mm",
        "image_size": [int(obs.image_size[0]), int(obs.image_size[1])],
        "mirror_shape": obs.mirror_shape or {"kind": "cone", "radius": obs.mirror_radius, "height": obs.mirror_height},
        "n_lasers": int(obs.n_lasers),
        **({"laser_kinds": list(obs.laser_kinds)} if obs.laser_kinds else {}),
        **({} if obs.camera_projection == "perspective" else {"camera_projection": obs.camera_projection}),
        "boards": {
            n: {**obs.board_types.get(n, {}), "points": np.asarray(p, float).tolist()} for n, p in obs.boards.items()
        },
        "calibration_views": [
            {"name": v.name, "board": v.board, "pixels": _px_list(v.pixels, v.seen)} for v in obs.calibration_views
        ],
        "views": [
            {
                "name": v.name,
                "boards": {b: _px_list(px, seen) for b, (px, seen) in v.boards.items()},
                "spots": [
                    {"laser": int(s.laser), "board": s.board, "pixel": [float(s.pixel[0]), float(s.pixel[1])]}
                    for s in v.spots
                ],
                "rim": np.asarray(v.rim, float).reshape(-1, 2).tolist(),
                **(
                    {
                        "stripes": [
                            {"laser": int(s.laser), "board": s.board, "pixels": np.asarray(s.pixels, float).tolist()}
                            for s in v.stripes
                        ]
                    }
                    if v.stripes
                    else {}
                ),
            }
            for v in obs.views
        ],
    }
    doc.update(obs.extra)
    return doc


def write_observations(path: str | os.PathLike, obs: Observations) -> None:
    """Write ``slcv-observations/1`` atomically."""
    write_json_atomic(path, observations_to_json(obs))


# --------------------------------------------------------------------------- calibration


@dataclass
class Calibration:
    """A calibrated rig with its board poses (``slcv-calibration/1``).

    ``board_poses[i][board]`` is ``T_cam_board`` in view ``i``;
    ``calibration_view_poses[j]`` is ``T_cam_board`` of direct view ``j`` (or None).
    ``extra`` holds ``uncertainty``, ``residuals``, ``stages`` and unknown fields.
    ``undetermined_lasers``: lasers the data could not fix (written with a null ``point`` and
    ``direction``; the rig holds a placeholder line for each, which nothing may use).
    """

    rig: Rig
    board_poses: list[dict[str, Pose]] = field(default_factory=list)
    calibration_view_poses: list[Pose | None] | None = None
    extra: dict = field(default_factory=dict)
    undetermined_lasers: tuple[int, ...] = ()


def _pose_json(p: Pose) -> dict:
    return {"R": np.asarray(p.R, float).tolist(), "t": np.asarray(p.t, float).tolist()}


def _read_pose(ctx: ReadContext, val: Any, where: str) -> Pose:
    r = ctx.matrix(ctx.get(val, "R", where), 3, 3, f"{where}.R")
    t = ctx.vector(ctx.get(val, "t", where), 3, f"{where}.t")
    if np.abs(r.T @ r - np.eye(3)).max() > 1e-6 or np.linalg.det(r) < 0:
        ctx.fail(f"{where}.R", "not a rotation matrix (R^T R != I or det < 0)")
    return Pose(jnp.asarray(r), jnp.asarray(t))


def _unit(ctx: ReadContext, v: np.ndarray, where: str) -> np.ndarray:
    m = float(np.max(np.abs(v)))  # scaled first: the norm of [1e308, 1e308, 0] is not inf
    if m < 1e-12 or m * np.linalg.norm(v / m) < 1e-12:
        ctx.fail(where, "zero vector")
    u = v / m
    return u / np.linalg.norm(u)


UNDETERMINED_LASER = "undetermined: the data do not fix this laser's line (see uncertainty.lasers)"
UNDETERMINED_SHEET = "undetermined: the data do not fix this laser's sheet of light (see uncertainty.lasers)"
# each kind's fields in ``lasers[i]`` (a point laser's written without ``kind``, as before kinds existed)
SHEET_FIELDS = {"plane": ("point", "normal"), "cone": ("apex", "axis", "half_angle_deg")}


def _lasers_json(rig: Rig, undetermined) -> list:
    """``lasers``: each element of ``rig`` in order, by kind (see DESIGN section 3)."""
    las, out = rig.lasers, []
    pts, dirs = np.asarray(las.points, float), np.asarray(las.directions, float)
    sheets = rig.sheets
    local = rig.local_index
    for i, kind in enumerate(rig.element_kinds):
        j = int(local[i])
        if kind == "point":
            if i in undetermined:
                out.append({"point": None, "direction": None, "status": UNDETERMINED_LASER})
            else:
                out.append({"point": pts[j].tolist(), "direction": dirs[j].tolist()})
            continue
        if i in undetermined:
            out.append({"kind": kind, **dict.fromkeys(SHEET_FIELDS[kind]), "status": UNDETERMINED_SHEET})
            continue
        p, a = np.asarray(sheets.apex[j], float).tolist(), np.asarray(sheets.axis[j], float).tolist()
        if kind == "plane":
            out.append({"kind": "plane", "point": p, "normal": a})
        else:
            th = float(np.degrees(float(sheets.half_angle[j])))
            out.append({"kind": "cone", "apex": p, "axis": a, "half_angle_deg": th})
    return out


def calibration_to_json(cal: Calibration) -> dict:
    """The ``slcv-calibration/1`` document of a :class:`Calibration` (camera only where the rig has no mirror)."""
    rig = cal.rig
    cam, mir = rig.camera, rig.mirror
    doc: dict[str, Any] = {
        "format": CALIBRATION_FORMAT,
        "camera": {
            "width": cam.width,
            "height": cam.height,
            "K": np.asarray(cam.K, float).tolist(),
            "dist": np.asarray(cam.dist, float).tolist(),
            **({"projection": "telecentric", "unit_mm": cam.unit} if cam.telecentric else {}),
        },
    }
    if mir is None:  # a camera-only calibration (``slcvjax camera``)
        doc.update(cal.extra)
        return doc
    doc.update(
        {
            "mirror": shape_json(mir)
            | {
                "apex": np.asarray(mir.apex, float).tolist(),
                "axis": np.asarray(mir.axis, float).tolist(),
            },
            "lasers": _lasers_json(rig, cal.undetermined_lasers),
            "board_poses": [{b: _pose_json(p) for b, p in view.items()} for view in cal.board_poses],
        }
    )
    if cal.calibration_view_poses is not None:
        doc["calibration_view_poses"] = [None if p is None else _pose_json(p) for p in cal.calibration_view_poses]
    doc.update(cal.extra)
    return doc


def write_calibration(path: str | os.PathLike, cal: Calibration) -> None:
    """Write ``slcv-calibration/1`` atomically."""
    write_json_atomic(path, calibration_to_json(cal))


def read_calibration(path: str | os.PathLike) -> Calibration:
    """Read and validate a ``slcv-calibration/1`` file (raises :class:`FormatError`).

    A file with a camera only (from ``slcvjax camera``) gives a rig whose
    mirror and lasers are absent: ``rig.mirror`` is None and ``rig.lasers`` has 0 lines.
    """
    return _calibration_of(*load_json(path))


def calibration_from_json(doc: Any, source: str) -> Calibration:
    """The :class:`Calibration` of a ``slcv-calibration/1`` document already parsed (``source``
    names it in errors); validated as :func:`read_calibration` validates a file."""
    return _calibration_of(ReadContext(source), doc)


def _calibration_of(ctx: ReadContext, doc: Any) -> Calibration:
    _check_format(ctx, doc, CALIBRATION_FORMAT)
    c = ctx.get(doc, "camera", "", dict)
    w = ctx.integer(ctx.get(c, "width", "camera"), "camera.width", lo=1)
    h = ctx.integer(ctx.get(c, "height", "camera"), "camera.height", lo=1)
    K = ctx.matrix(ctx.get(c, "K", "camera"), 3, 3, "camera.K")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        ctx.fail("camera.K", "focal lengths must be positive")
    dist = ctx.vector(ctx.get(c, "dist", "camera"), 5, "camera.dist")
    projection = ctx.get(c, "projection", "camera", str, optional=True) or "perspective"
    if projection not in PROJECTIONS:
        ctx.fail("camera.projection", f"expected one of {', '.join(PROJECTIONS)}, got {projection!r}")
    unit = 1.0
    if projection == "telecentric":
        unit = float(ctx.number(ctx.get(c, "unit_mm", "camera"), "camera.unit_mm"))
        if not unit > 0:
            ctx.fail("camera.unit_mm", f"must be positive, got {unit:g}")
    cam = Camera.create(K[0, 0], K[1, 1], K[0, 2], K[1, 2], dist, w, h, projection == "telecentric", unit)

    m = ctx.get(doc, "mirror", "", dict, optional=True)
    mirror = None
    if m is not None:
        radius, height, shape = read_shape(ctx, m, "mirror")
        apex = ctx.vector(ctx.get(m, "apex", "mirror"), 3, "mirror.apex")
        axis = _unit(ctx, ctx.vector(ctx.get(m, "axis", "mirror"), 3, "mirror.axis"), "mirror.axis")
        mirror = mirror_of_shape(shape, apex, axis, radius, height)

    pts, dirs, undetermined = [], [], []
    kinds, s_kind, s_apex, s_axis, s_angle = [], [], [], [], []
    for i, las in enumerate(ctx.list_of(doc, "lasers", "", optional=True)):
        kind = las.get("kind", "point") if isinstance(las, dict) else "point"
        if kind is None:
            kind = "point"
        if kind not in LASER_KINDS:
            ctx.fail(f"lasers[{i}].kind", f"expected one of {', '.join(LASER_KINDS)}, got {json.dumps(kind)[:40]}")
        kinds.append(kind)
        if kind != "point":
            where = f"lasers[{i}]"
            fields = SHEET_FIELDS[kind]
            s_kind.append(kind)
            if all(las.get(f, 0) is None for f in fields):
                undetermined.append(i)  # a placeholder sheet that nothing uses
                s_apex.append(np.zeros(3))
                s_axis.append(np.array([0.0, 0.0, 1.0]))
                s_angle.append(np.pi / 2 if kind == "plane" else np.pi / 4)
                continue
            s_apex.append(ctx.vector(ctx.get(las, fields[0], where), 3, f"{where}.{fields[0]}"))
            ax = ctx.vector(ctx.get(las, fields[1], where), 3, f"{where}.{fields[1]}")
            s_axis.append(_unit(ctx, ax, f"{where}.{fields[1]}"))
            if kind == "cone":
                th = ctx.number(ctx.get(las, "half_angle_deg", where), f"{where}.half_angle_deg")
                if not 0.0 < th < 180.0:
                    ctx.fail(f"{where}.half_angle_deg", f"must lie strictly between 0 and 180, got {th:g}")
                s_angle.append(np.radians(th))
            else:
                s_angle.append(np.pi / 2)
            continue
        if isinstance(las, dict) and las.get("point", 0) is None and las.get("direction", 0) is None:
            undetermined.append(i)  # the data did not fix it: a placeholder line that nothing uses
            pts.append(np.zeros(3))
            dirs.append(np.array([0.0, 0.0, 1.0]))
            continue
        pts.append(ctx.vector(ctx.get(las, "point", f"lasers[{i}]"), 3, f"lasers[{i}].point"))
        d = ctx.vector(ctx.get(las, "direction", f"lasers[{i}]"), 3, f"lasers[{i}].direction")
        dirs.append(_unit(ctx, d, f"lasers[{i}].direction"))
    lasers = Lasers.create(np.reshape(pts, (-1, 3)), np.reshape(dirs, (-1, 3)))

    board_poses = []
    for i, view in enumerate(ctx.list_of(doc, "board_poses", "", optional=True)):
        if not isinstance(view, dict):
            ctx.fail(f"board_poses[{i}]", "expected an object of board poses")
        board_poses.append({b: _read_pose(ctx, p, f"board_poses[{i}].{b}") for b, p in view.items()})

    cvp = None
    if doc.get("calibration_view_poses") is not None:
        cvp = [
            None if p is None else _read_pose(ctx, p, f"calibration_view_poses[{i}]")
            for i, p in enumerate(ctx.list_of(doc, "calibration_view_poses", ""))
        ]
    known = {"format", "camera", "mirror", "lasers", "board_poses", "calibration_view_poses"}
    extra = {k: v for k, v in doc.items() if k not in known}
    sheets = (
        Sheets.create(s_kind, np.reshape(s_apex, (-1, 3)), np.reshape(s_axis, (-1, 3)), s_angle) if s_kind else None
    )
    rig = Rig.of_elements(cam, mirror, lasers, sheets, kinds)
    return Calibration(rig, board_poses, cvp, extra, tuple(undetermined))
