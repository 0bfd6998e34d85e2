"""What a calibration returns: its passes, its repairs and its result."""

from dataclasses import dataclass, field
from typing import Literal

from ..geometry.rig import Rig
from ..observations.formats import FormatError, Observations
from ..observations.problem import Packed
from .base import CalibrationError
from .covariance import Covariance
from .lm import CONVERGED, MAX_STEPS, Outcome
from .options import DEFAULT_OPTIONS, CalibrationOptions
from .params import Masks, Params
from .staged import Staged


@dataclass(frozen=True)
class JointPass:
    """One LM pass: its name, steps, costs, loss scale, how it ended (``code``, a
    :class:`slcvjax.calibration.lm.Outcome`), the step limit the schedule gives it where that is
    below the calibration's (``limit``: passes A and A2), and what followed it (``notes``: a
    start kept or not, boards turned after it)."""

    name: str
    steps: int
    cost0: float
    cost: float
    scale: float
    code: Outcome
    limit: int | None = None
    notes: tuple[str, ...] = ()

    @property
    def converged(self) -> bool:
        return self.code == CONVERGED

    @property
    def result(self) -> str:
        """How it ended in words (``converged``, ``stopped at its limit of 10 steps``, ...) and its notes."""
        said = self.code.label
        if self.limit is not None and self.code == MAX_STEPS:
            said = f"stopped at its limit of {self.limit} steps"
        return "; ".join([said, *self.notes])

    def to_json(self) -> dict:
        """The pass as the calibration file's ``stages.joint.passes`` gives it."""
        return {
            "name": self.name,
            "steps": self.steps,
            "result": self.result,
            "outcome": self.code.label,
            "notes": list(self.notes),
            "cost0": self.cost0,
            "cost": self.cost,
            "scale": self.scale,
            "limit": self.limit,
        }

    @property
    def finished(self) -> bool:
        """Converged, or stopped at the step limit the schedule gives the pass (it only has to
        bring the next pass into its basin)."""
        return self.converged or (self.code == MAX_STEPS and self.limit is not None and self.steps >= self.limit)


# the words of the reason of a spot relabelled by the outlier search (the lines' consensus relabels
# with others): :meth:`Repair.from_json` tells the two steps apart by them
AT_THE_FINAL_GEOMETRY = "at the final geometry"


# the fields of a record, in the order of the calibration file's ``residuals.repairs`` (the
# exceptions: :meth:`Repair.to_json`)
_ORDER = (
    "kind",
    "view",
    "index",
    "board",
    "action",
    "laser",
    "new_index",
    "residual_px",
    "new_laser",
    "new_residual_px",
    "reason",
    "whole_board",
)


# written only where they have a value (``whole_board``: where it holds)
_OPTIONAL = ("laser", "new_index", "new_laser", "new_residual_px", "whole_board")


@dataclass(frozen=True)
class Repair:
    """One change a calibration made to its observations: an observation relabelled or left out
    (:mod:`slcvjax.calibration.repairs`, :mod:`slcvjax.calibration.rigid_pass`).  A record of the
    calibration file's ``residuals.repairs`` (:meth:`to_json`, :meth:`from_json`).

    Fields:
        kind: what was changed: ``"dot"`` (one dot of a board), ``"spot"`` (one laser spot) or
            ``"board"`` (every dot and spot of one board in one view, left out by pass R).
        view: the name of the view it belongs to (None where the problem did not record which
            input observation the row is).
        index: the dot's index among its board's points, or the spot's index among its view's
            spots (-1 for a board, or where the problem did not record it).
        board: the name of the board it lies on (a spot: None where it names no board; a dot of
            an unrecorded row: ``""``).
        action: ``"relabelled"`` (given another laser or grid position, and kept) or
            ``"left out"`` (not fitted by the final pass).
        reason: why, in words, with the threshold that decided it.
        residual_px: its residual norm (px) under its own label when the change was decided (a
            board: the median of its dots'); None where there was none to give (a prediction off
            the mirror or the sensor, a board left out whole).
        laser: a spot's own laser (its label in the input, or the one it had then); None for a
            dot or a board.
        new_index: a relabelled dot's new grid position on its board; None otherwise.
        new_laser: a relabelled spot's new laser; None otherwise.
        new_residual_px: a relabelled observation's residual norm (px) under its new label; None
            otherwise.
        whole_board: it was left out with every other observation of its board in that view (the
            board's pose was not determined, or the board does not fit the rigid box).
        stage: the step that made the change: ``"lines"`` (the laser lines' consensus before
            pass B, :func:`slcvjax.calibration.repairs.relabel_spots`), ``"outliers"`` (the
            outlier search of pass C3, :func:`slcvjax.calibration.repairs.leave_out`) or
            ``"box"`` (pass R, :func:`slcvjax.calibration.rigid_pass.rigid_refine`).  Not a
            field of the file: it sets the order of the record's keys there, and is read back
            from that order.
    """

    kind: Literal["dot", "spot", "board"]
    view: str | None
    index: int
    board: str | None
    action: Literal["relabelled", "left out"]
    reason: str
    residual_px: float | None = None
    laser: int | None = None
    new_index: int | None = None
    new_laser: int | None = None
    new_residual_px: float | None = None
    whole_board: bool = False
    stage: Literal["lines", "outliers", "box"] = "outliers"

    def _order(self) -> tuple[str, ...]:
        """The keys of :meth:`to_json` in the file's order: a board (pass R) names its board
        before its index; a spot left out by the outlier search names its laser before the
        action."""
        if self.stage == "box":
            return ("kind", "view", "board", "index", *_ORDER[4:])
        if self.stage == "outliers" and self.action == "left out":
            return ("kind", "view", "index", "board", "laser", "action", *_ORDER[6:])
        return _ORDER

    def to_json(self) -> dict:
        """The record as the calibration file's ``residuals.repairs`` holds it: ``kind``,
        ``view``, ``index``, ``board``, ``action``, ``residual_px`` and ``reason`` always, the
        other fields where they have a value."""
        out = {}
        for key in self._order():
            value = getattr(self, key)
            if key in _OPTIONAL and (value is None or value is False):
                continue
            out[key] = value
        return out

    @classmethod
    def from_json(cls, doc: dict, where: str = "repair") -> "Repair":
        """The record of a calibration file's ``residuals.repairs`` (``where`` names it in an
        error: the file, the field and the index).  Its :attr:`stage` comes from the order of its
        keys, for a relabelled spot (one order for both of its steps) from its reason's words.

        Raises:
            FormatError: it is not an object, or a field is missing or of the wrong type.
        """
        if not isinstance(doc, dict):
            raise FormatError(f"{where}: expected an object, got {type(doc).__name__}")
        for key in ("kind", "view", "index", "board", "action", "reason"):
            if key not in doc:
                raise FormatError(f"{where}.{key}: missing")
        kind, action, reason = doc["kind"], doc["action"], doc["reason"]
        if kind not in ("dot", "spot", "board"):
            raise FormatError(f"{where}.kind: expected 'dot', 'spot' or 'board', got {kind!r}")
        if action not in ("relabelled", "left out"):
            raise FormatError(f"{where}.action: expected 'relabelled' or 'left out', got {action!r}")
        if not isinstance(reason, str):
            raise FormatError(f"{where}.reason: expected a string, got {reason!r}")

        def number(key, types, optional=True):
            value = doc.get(key)
            ok = (value is None and optional) or (isinstance(value, types) and not isinstance(value, bool))
            if not ok:
                raise FormatError(f"{where}.{key}: expected a number, got {value!r}")
            return value

        keys = list(doc)
        if kind == "board":
            stage = "box"
        elif kind == "spot" and "laser" in doc and keys.index("laser") < keys.index("action"):
            stage = "outliers"  # a spot left out by the outlier search
        elif kind == "spot" and (action == "left out" or AT_THE_FINAL_GEOMETRY not in reason):
            stage = "lines"
        else:
            stage = "outliers"
        return cls(
            kind,
            doc["view"],
            number("index", int, optional=False),
            doc["board"],
            action,
            reason,
            number("residual_px", (int, float)),
            number("laser", int),
            number("new_index", int),
            number("new_laser", int),
            number("new_residual_px", (int, float)),
            bool(doc.get("whole_board", False)),
            stage,
        )


@dataclass(frozen=True)
class CalibrationResult:
    """A calibration: the joint solution, its covariance, the staged start and the passes.
    Immutable: a step that changes it returns a new one (:func:`dataclasses.replace`)."""

    params: Params
    staged: Staged
    packed: Packed
    masks: Masks
    cov: Covariance
    loss: str
    scale: float
    passes: tuple[JointPass, ...]
    timings: dict = field(default_factory=dict)
    kind_sigma: dict = field(default_factory=dict)  # per kind noise sigma (px) over its free rows (kind_noise)
    repairs: tuple[Repair, ...] = ()  # observations relabelled or left out (see :mod:`slcvjax.calibration.repairs`)
    box: dict | None = None  # the rigid box model's boards, where it was used (see :func:`rigid_refine`)
    # lasers whose spots cannot fix a line: held at a placeholder, their spots left out (fit_lasers)
    undetermined_lasers: tuple[int, ...] = ()
    # the observations as given (the report names views, boards and lasers by them)
    observations: Observations | None = None
    # the settings it ran with
    options: CalibrationOptions = DEFAULT_OPTIONS
    # line and ring lasers whose stripes cannot fix their sheet (their index among the rig's
    # sheets): held at a placeholder, their stripes left out (fit_sheets)
    undetermined_sheets: tuple[int, ...] = ()

    @property
    def undetermined_elements(self) -> tuple[int, ...]:
        """Every undetermined laser by its index in the file (point lasers' and sheets' alike)."""
        return self.rig.element_indices(self.undetermined_lasers, self.undetermined_sheets)

    @property
    def rig(self) -> Rig:
        return self.params.rig

    @property
    def converged(self) -> bool:
        """Whether the last pass, the one whose solution this is, converged (not stopped at the
        step limit or stalled): only then are ``params`` a minimum and ``cov`` its covariance."""
        return bool(self.passes) and self.passes[-1].converged


def require_determined(result: CalibrationResult) -> CalibrationResult:
    """``result``, or :class:`CalibrationError` naming its undetermined lasers: for the
    experiments that score every laser against a truth (a held laser has no error to score)."""
    if result.undetermined_lasers:
        held = ", ".join(map(str, result.undetermined_lasers))
        raise CalibrationError(f"laser {held}: undetermined (its spots cannot fix a line)")
    return result
