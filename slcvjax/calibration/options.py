"""The calibration's settings as data: one frozen object that the API, ``calibrate_many``, the CLI
(``slcvjax calibrate --options FILE.json``) and the calibration file share.

:class:`CalibrationOptions` holds the joint fit's settings and a :class:`RobustPolicy`: how the
calibration weighs, repairs and leaves out observations that do not fit.  Every field has a
default that reproduces the calibration as it runs without options.  As JSON (``to_json`` /
``from_json``), an options file is an object with the fields below; ``robust`` an object of the
policy's fields; a field left out takes its default, an unknown field is refused by name.

Example ``options.json``::

    {"max_steps": 300, "rigid": true,
     "robust": {"loss": "cauchy", "outlier_sigmas": 4.0, "consensus_px": 6.0}}
"""

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

from ..observations.formats import FormatError

LOSSES = ("huber", "cauchy", "linear")
FREEZABLE = ("camera", "mirror", "mirror_tilt", "lasers", "poses", "chess_poses")


@dataclass(frozen=True)
class RobustPolicy:
    """How the calibration treats observations that do not fit the model.

    Attributes:
        loss: the robust loss of the dots and spots: ``huber``, ``cauchy`` or ``linear`` (plain
            least squares: no observation is left out as a gross outlier).
        loss_scale: the loss's scale in px; None: ``scale_sigmas`` times the noise sigma estimated
            robustly from the residuals (re-estimated before the final pass).
        scale_sigmas: the loss scale in noise sigmas, where ``loss_scale`` is None.
        outlier_sigmas: a dot or spot whose residual lies beyond this many noise sigmas of its
            kind is a gross outlier: found under the Cauchy loss and left out (also the report's
            outlier threshold).
        min_outlier_px: ... and only beyond this many px (a detector's sub-pixel bias is not an
            outlier, however small the noise).
        min_board_dots: a board pose left with fewer dots than this is left out whole (its pose is
            not determined); also the fewest dots that place a board in the rigid box.
        cauchy_widen: the first outlier-finding pass runs the Cauchy loss at this many loss scales
            (graduated: the good dots of a dragged board still pull), then at one.
        consensus_px: a spot within this many px of a candidate laser line counts for it in the
            lines' consensus, and a spot set aside comes back where its own line predicts it
            within this.
        repair_sigmas: a spot further than this many noise sigmas from its own laser's line is
            given the one other line it lies on, or left out.
        min_repair_px: ... and only further than this many px.
        misfit_sigmas: under the rigid box model, a board pose whose dots' median residual exceeds
            this many noise sigmas does not fit the box and is left out.
        misfit_min_px: ... and only where it exceeds this many px.
        misfit_rounds: the most rounds of leaving misfit board poses out of the box.
        aimed_turn_deg: a laser aimed through its spots that turns by more than this many degrees
            from the joint fit's is tried as another start (kept where it ends at a lower cost).
        min_kept_share: a point laser that keeps fewer than this share of the spots labelled its
            own (the rest left out, given to another laser, or outliers) has its std withdrawn
            in the report: most of its spots disagree with its line, which may rest on a
            consensus of wrong ones.
    """

    loss: str = "huber"
    loss_scale: float | None = None
    scale_sigmas: float = 3.0
    outlier_sigmas: float = 5.0
    min_outlier_px: float = 1.0
    min_board_dots: int = 4
    cauchy_widen: float = 10.0
    consensus_px: float = 10.0
    repair_sigmas: float = 5.0
    min_repair_px: float = 1.0
    misfit_sigmas: float = 5.0
    misfit_min_px: float = 2.0
    misfit_rounds: int = 3
    aimed_turn_deg: float = 10.0
    min_kept_share: float = 0.5

    def __post_init__(self):
        if self.loss not in LOSSES:
            raise ValueError(f"robust.loss: expected one of {', '.join(LOSSES)}, got {self.loss!r}")
        if self.loss_scale is not None and not (math.isfinite(self.loss_scale) and self.loss_scale > 0):
            raise ValueError(f"robust.loss_scale: expected a positive number of px or null, got {self.loss_scale}")
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name in ("loss", "loss_scale"):
                continue
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v < 0:
                raise ValueError(f"robust.{f.name}: expected a non-negative number, got {v!r}")
        for name in ("min_board_dots", "misfit_rounds"):
            if not isinstance(getattr(self, name), int):
                raise ValueError(f"robust.{name}: expected a whole number, got {getattr(self, name)!r}")


@dataclass(frozen=True)
class CalibrationOptions:
    """Everything :func:`slcvjax.calibrate` can be told, besides a starting camera or mirror.

    Attributes:
        robust: the :class:`RobustPolicy`.
        max_steps: the most Levenberg-Marquardt linearisations per pass.
        freeze: parameter blocks held fixed: ``camera``, ``mirror``, ``mirror_tilt``, ``lasers``,
            ``poses``, ``chess_poses``.
        rigid: the rigid target box model: False (a pose per board and view), True (the boards the
            observations declare in ``rigid_boards``), or a list of board names.
        projection_test_level: ``camera_projection = "auto"``: the F-test's level below which the
            perspective camera is kept over the telecentric one.
        auto_folds: ``mirror_shape.kind = "auto"``: the folds of the cross-validation over the
            views that picks the mirror's kind.
        consistency_level: the final check's family-wise false-alarm level: the chance that
            residuals which do follow the noise model fail it (:mod:`slcvjax.calibration.consistency`).
    """

    robust: RobustPolicy = field(default_factory=RobustPolicy)
    max_steps: int = 500
    freeze: tuple[str, ...] = ()
    rigid: bool | tuple[str, ...] = False
    projection_test_level: float = 0.05
    auto_folds: int = 5
    consistency_level: float = 0.01

    def __post_init__(self):
        object.__setattr__(self, "freeze", tuple(sorted(set(self.freeze))))
        bad = [b for b in self.freeze if b not in FREEZABLE]
        if bad:
            raise ValueError(f"freeze: unknown block {bad[0]!r} (known: {', '.join(FREEZABLE)})")
        if not isinstance(self.rigid, bool):
            object.__setattr__(self, "rigid", tuple(self.rigid))
        if isinstance(self.max_steps, bool) or not isinstance(self.max_steps, int) or self.max_steps < 1:
            raise ValueError(f"max_steps: expected a whole number of at least 1, got {self.max_steps!r}")
        if not 0.0 < self.consistency_level < 1.0:
            raise ValueError(f"consistency_level: expected a level in (0, 1), got {self.consistency_level}")
        if not 0.0 < self.projection_test_level < 1.0:
            raise ValueError(f"projection_test_level: expected a level in (0, 1), got {self.projection_test_level}")
        if isinstance(self.auto_folds, bool) or not isinstance(self.auto_folds, int) or self.auto_folds < 2:
            raise ValueError(f"auto_folds: expected a whole number of at least 2, got {self.auto_folds!r}")

    def replace(self, **changes) -> "CalibrationOptions":
        """These options with some fields changed (``robust=`` a policy, or a dict of its fields)."""
        if isinstance(changes.get("robust"), dict):
            changes["robust"] = dataclasses.replace(self.robust, **changes["robust"])
        return dataclasses.replace(self, **changes)

    def to_json(self) -> dict:
        """The options as a JSON object (what ``--options`` reads and the calibration file keeps)."""
        doc = dataclasses.asdict(self)
        doc["freeze"] = list(self.freeze)
        doc["rigid"] = self.rigid if isinstance(self.rigid, bool) else list(self.rigid)
        return doc

    @classmethod
    def from_json(cls, doc: Any, source: str) -> "CalibrationOptions":
        """Options from a JSON object; :class:`slcvjax.FormatError` naming ``source`` and the field
        for an unknown field or a bad value."""
        if not isinstance(doc, dict):
            raise FormatError(f"{source}: (top level): expected an object of options")
        _refuse_unknown(doc, cls, "", source)
        robust = doc.get("robust") or {}
        if not isinstance(robust, dict):
            raise FormatError(f"{source}: robust: expected an object")
        _refuse_unknown(robust, RobustPolicy, "robust.", source)
        try:
            policy = RobustPolicy(**robust)
            rest = {k: v for k, v in doc.items() if k != "robust"}
            if "freeze" in rest and not isinstance(rest["freeze"], list):
                raise ValueError(f"freeze: expected a list of block names, got {rest['freeze']!r}")
            if "rigid" in rest and not isinstance(rest["rigid"], bool | list):
                raise ValueError(f"rigid: expected true, false or a list of board names, got {rest['rigid']!r}")
            return cls(robust=policy, **rest)
        except (TypeError, ValueError) as e:
            raise FormatError(f"{source}: {e}") from None


DEFAULT_POLICY = RobustPolicy()
DEFAULT_OPTIONS = CalibrationOptions()


def _refuse_unknown(doc: dict, cls, prefix: str, source: str) -> None:
    """:class:`FormatError` naming the first field of ``doc`` that ``cls`` does not have."""
    known = {f.name for f in dataclasses.fields(cls)}
    for k in doc:
        if k not in known:
            raise FormatError(f"{source}: {prefix}{k}: unknown option (known: {', '.join(sorted(known))})")


def merged_options(
    options: CalibrationOptions | None, freeze=None, loss=None, loss_scale=None, max_steps=None, rigid=None
) -> CalibrationOptions:
    """``options`` (default: :data:`DEFAULT_OPTIONS`) with the keyword arguments of
    :func:`slcvjax.calibrate` that were given (not None) in place of its fields."""
    options = DEFAULT_OPTIONS if options is None else options
    robust = {k: v for k, v in (("loss", loss), ("loss_scale", loss_scale)) if v is not None}
    rest = {k: v for k, v in (("freeze", freeze), ("max_steps", max_steps), ("rigid", rigid)) if v is not None}
    if rest.get("rigid") is not None and not isinstance(rest["rigid"], bool):
        rest["rigid"] = tuple(rest["rigid"])
    return options.replace(**rest, **({"robust": robust} if robust else {})) if robust or rest else options


def policy_table() -> str:
    """:class:`RobustPolicy`'s fields as a Markdown table: name, default and meaning (from its
    docstring; the formulation page holds it, and a test keeps them equal)."""
    doc = RobustPolicy.__doc__.split("Attributes:")[1]
    meaning: dict[str, str] = {}
    name = None
    for line in doc.splitlines():
        head, _, rest = line.strip().partition(": ")
        if line.startswith("        ") and not line.startswith("            ") and head.isidentifier():
            name, meaning[head] = head, rest
        elif name and line.strip():
            meaning[name] += " " + line.strip()
    rows = ["| field | default | meaning |", "| --- | --- | --- |"]
    for f in dataclasses.fields(RobustPolicy):
        rows.append(f"| `{f.name}` | `{json_value(f.default)}` | {meaning[f.name]} |")
    return "\n".join(rows) + "\n"


def json_value(v) -> str:
    """A default as the options file writes it."""
    return "null" if v is None else str(v).lower() if isinstance(v, bool) else str(v)
