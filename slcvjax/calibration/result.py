"""What a calibration returns: its passes and its result."""

from dataclasses import dataclass, field

from ..geometry.rig import Rig
from ..observations.formats import Observations
from ..observations.problem import Packed
from .base import CalibrationError
from .covariance import Covariance
from .lm import CONVERGED, MAX_STEPS, Outcome
from .options import DEFAULT_OPTIONS, CalibrationOptions
from .params import Masks, Params
from .staged import Staged


@dataclass
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
    notes: list[str] = field(default_factory=list)

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
            "notes": self.notes,
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


@dataclass
class CalibrationResult:
    """A calibration: the joint solution, its covariance, the staged start and the passes."""

    params: Params
    staged: Staged
    packed: Packed
    masks: Masks
    cov: Covariance
    loss: str
    scale: float
    passes: list[JointPass]
    timings: dict = field(default_factory=dict)
    kind_sigma: dict = field(default_factory=dict)  # per kind noise sigma (px) over its free rows (kind_noise)
    repairs: list = field(
        default_factory=list
    )  # observations relabelled or left out (see :mod:`slcvjax.calibration.repairs`)
    box: dict | None = None  # the rigid box model's boards, where it was used (see :func:`rigid_refine`)
    # lasers whose spots cannot fix a line: held at a placeholder, their spots left out (fit_lasers)
    undetermined_lasers: tuple[int, ...] = ()
    # the observations as given (the report names views, boards and lasers by them)
    observations: Observations | None = None
    # the settings it ran with
    options: CalibrationOptions = DEFAULT_OPTIONS

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
