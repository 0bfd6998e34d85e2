"""The joint passes of the schedule: what each frees, how it weighs and when it stops.

The passes before the last only have to bring the next one into its basin; the last converges to
round-off.  The flipped twins are refined only far enough to compare their fit with the poses they
may replace (the final pass refines the winners), and the first pass only far enough to decide
the boards' flips again.
"""

import dataclasses
import logging
import time
from dataclasses import dataclass

import numpy as np

from .executors import SolveJob
from .lm import Outcome
from .params import Masks, Params, pad_masks, pad_params
from .result import JointPass
from .trial import Trial

RTOL_START = 1e-5


RTOL_TWIN = 1e-4


RTOL_FINAL = 1e-10


# the step limit of passes A and A2: where a board is flipped wrong, they creep (measured: A took
# 20-43 steps in four of nine 9-15-view scenes and A2 10-15 in six, most of them rejected or
# lowering the cost by a few per cent); with this limit the same boards turned, the same passes
# ran and the solutions agreed to 3e-4 in the camera, mirror and beam directions and to 0.012 mm
# in the beams (benchmarks/bench_compile.py's scenes); the next pass goes on from there
STEPS_A = 10


@dataclass(frozen=True)
class PassSpec:
    """One joint pass of :func:`calibrate`'s schedule: what it frees and how it weighs and stops.

    ``lasers_held``: the lasers' columns held (the rest as the calibration frees them);
    ``kind_weight``: the weight of each observation kind (dot, spot, rim, corner; None: all 1);
    ``rtol``: the LM's relative cost tolerance; ``scale_floor``: the loss scale is the user's
    ``loss_scale``, else ``scale_sigmas`` x the robust noise sigma of the pass's start, at least
    this many px (None: the scale the trial has); ``steps``: a step limit below the calibration's
    (the pass only has to bring the next into its basin); ``loss``: a loss instead of the
    calibration's; ``rig_held``: its solves free the board poses only.
    """

    name: str
    lasers_held: bool = False
    kind_weight: tuple[float, float, float, float] | None = None
    rtol: float = RTOL_START
    scale_floor: float | None = None
    steps: int | None = None
    loss: str | None = None
    rig_held: bool = False  # only the board poses are freed (its solves come with masks that say so)

    def describe(self) -> str:
        """What the pass frees, weighs and stops at, in words (the formulation page's table)."""
        frees = "everything but the lasers" if self.lasers_held else "everything"
        if self.rig_held:
            frees = "the board poses only (the rig held)"
        kw = self.kind_weight or (1.0, 1.0, 1.0, 1.0)
        weights = ", ".join(f"{k} {w:g}" for k, w in zip(("dots", "spots", "rim", "corners"), kw, strict=True))
        scale = "the trial's" if self.scale_floor is None else f"re-estimated (at least {self.scale_floor:g} px)"
        limit = f"; at most {self.steps} steps" if self.steps is not None else ""
        loss = f"; {self.loss} loss" if self.loss else ""
        return f"frees {frees}; weights {weights}; loss scale {scale}; rtol {self.rtol:g}{limit}{loss}"


_NO_SPOTS = (1.0, 0.0, 1.0, 1.0)


# the schedule: A (and A2 after the boards are flipped again) fits the geometry without the
# lasers; B everything from lasers refitted on it (B2 from lasers aimed through their spots);
# C the final pass at the re-estimated scale, C3 without the outliers, C2 after boards turned
PASS_A = PassSpec("A: camera, mirror, poses", True, _NO_SPOTS, RTOL_TWIN, 0.1, STEPS_A)


PASS_A2 = PassSpec("A2: after re-flipping", True, _NO_SPOTS, RTOL_START, 0.1, STEPS_A)


PASS_B = PassSpec("B: joint", scale_floor=0.05)


PASS_B2 = PassSpec("B2: joint (lasers aimed through their spots)")


PASS_C = PassSpec("C: joint (final)", rtol=RTOL_FINAL)


PASS_C3 = PassSpec("C3: joint (outliers left out)", rtol=RTOL_FINAL)


PASS_C2 = PassSpec("C2: joint (after turning)", rtol=RTOL_FINAL)


def solve_job(tr: "Trial", params: Params, spec: PassSpec, masks: Masks | None = None) -> SolveJob:
    """A solve of trial ``tr`` from ``params`` by the pass ``spec`` (``masks``: what it frees instead of what
    ``spec`` says), padded to the trial's shape buckets.  Where the masks hold the rig, the rim's
    rows (and the direct views' corners, where their poses are held too) are constant: the
    solve leaves them out, as padding."""
    if masks is None:
        masks = tr.mask_a if spec.lasers_held else tr.masks
    arrays = tr.arr
    if not np.any(masks.glob):
        n_p = params.poses.t.shape[0]
        arrays = arrays.kinds_only([1, 1, 0, np.any(np.asarray(masks.blocks)[n_p:])])
    return SolveJob(
        pad_params(tr.layout, params), arrays, pad_masks(tr.layout, masks), tr.scale, spec.kind_weight, spec.rtol
    )


# the other starts of the boards' poses (:func:`other_starts_of`, each with its own masks)
TWIN_SOLVE = PassSpec("other starts", rtol=RTOL_TWIN, rig_held=True)


# the passes as they end, with their timings: quiet unless a command turns it on (``slcvjax calibrate``, ``omni``)
progress = logging.getLogger("slcvjax.progress")
progress.setLevel(logging.WARNING)


def record_pass(tr: "Trial", name: str, res, limit: int | None, note: str = "") -> "Trial":
    """The trial with the pass ``name``'s solve ``res`` added to its passes (``limit``: the pass's
    own step limit; ``note``: what followed it), said on the ``slcvjax.progress`` logger with the
    seconds since the trial's previous pass (or its staged start)."""
    now = time.perf_counter()
    since = tr.t_last or tr.t0 + tr.t_staged
    progress.info(
        f"  pass {name}: {int(res.steps)} steps, cost {float(res.initial_cost):.4g} -> {float(res.cost):.4g}, "
        f"{Outcome(int(res.result)).name.lower()}, {now - since:.1f} s"
    )
    tr = dataclasses.replace(tr, t_last=now)
    return tr.with_pass(
        JointPass(
            name,
            int(res.steps),
            float(res.initial_cost),
            float(res.cost),
            float(tr.scale),
            Outcome(int(res.result)),
            limit,
            (note,) if note else (),
        )
    )
