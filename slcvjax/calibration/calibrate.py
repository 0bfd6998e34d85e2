"""The whole calibration: staged start, progressive joint refinement, uncertainty, report.

:func:`calibrate` runs the staged pipeline (:mod:`slcvjax.calibration.staged`), then the joint
Levenberg-Marquardt (:mod:`slcvjax.calibration.lm`) in passes:

A. camera, mirror, board and direct-view poses from dots, rim and corners (lasers
   frozen, spots weighted 0): the staged mirror tilt is weakly observable from the rim
   alone and the boards fix it (A2 again where a board's flip changed);
B. the lasers refitted on the refined geometry by consensus (spots that lie on another
   laser's line are given that laser, see :func:`slcvjax.calibration.staged.fit_lasers`), then everything
   jointly with a Huber loss at 3 sigma (sigma estimated robustly from the residuals);
   every board then tries its other starts (flipped twin, carried pose), and the spots the
   consensus set aside that this solution puts on their own line come back;
C. the same with sigma re-estimated at B's solution (the final pass); where a dot or
   spot lies beyond 5 sigma, the gross outliers are found under the Cauchy loss, left
   out, and C runs again (C3, :func:`_leave_out`); where a board still fits badly, its
   other starts again and C again (C2).

Everything changed in the input is listed in :attr:`CalibrationResult.repairs`.  It
returns the joint result with its covariance, and the staged result beside it.
"""

import dataclasses
import functools
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import NamedTuple

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..geometry.camera import Camera
from ..geometry.conic import AsphereMirror, conic_kind
from ..geometry.lasers import Lasers, line_plane_intersection
from ..geometry.pose import Pose
from ..geometry.rig import (
    APEX_COLUMNS,
    CAMERA_COLUMNS,
    CAMERA_NAMES,
    SHAPE_COLUMN,
    TILT_COLUMNS,
    Rig,
    laser_columns,
    project_board_points,
    project_rim,
    project_spots,
)
from ..observations.formats import Calibration, Observations, shape_missing
from ..observations.problem import KIND_NAMES, Kind, Layout, Packed, kind_weights, pack, stack_poses, unstack_poses
from ..support.persist import PersistentJit
from ..support.recent import Recent
from ..support.safe import std_of_variance
from .central import central_start
from .lm import (
    CONVERGED,
    MAX_STEPS,
    Covariance,
    LMResult,
    Masks,
    Outcome,
    Params,
    block_costs,
    covariance_of_linearisation,
    leverage_shares,
    loss_index,
    make_masks,
    pad_masks,
    pad_params,
    pad_problem,
    pooled_noise,
    raw_normal,
    sandwich_covariance,
    solve,
    table_at,
    unpad_params,
)
from .rigid import (
    MISFIT_MIN_PX,
    MISFIT_ROUNDS,
    MISFIT_SIGMAS,
    board_pose_covariances,
    board_poses_of,
    box_model,
    box_pose_std,
    rigid_masks,
    rigid_params,
)
from .staged import (
    CONSENSUS_PX,
    RAYLEIGH_MEDIAN,
    CalibrationError,
    Staged,
    StageReport,
    _flipped,
    aimed_lasers,
    board_poses,
    fit_lasers,
    staged,
)

_solve_jit = PersistentJit(solve, "solve")
_table_jit = PersistentJit(table_at, "observation_table")


def _solve(params: Params, arr: Packed, masks: Masks, loss: str, scale, max_steps: int, rtol=1e-10, kind_weight=None):
    """:func:`slcvjax.calibration.lm.solve` compiled once: the loss, the step limit, the tolerance and the kind
    weights are values, so every pass, the covariance, the bound and the reports share it."""
    return _solve_jit(
        params,
        arr,
        masks,
        jnp.asarray(loss_index(loss)),
        jnp.asarray(scale, dtype=float),
        jnp.asarray(max_steps),
        jnp.asarray(rtol, dtype=float),
        kind_weights(kind_weight),
    )


# The passes before the last only have to bring the next one into its basin; the last
# converges to round-off.  The flipped twins are refined only far enough to compare
# their fit with the poses they may replace (the final pass refines the winners), and
# the first pass only far enough to decide the boards' flips again.
_RTOL_START = 1e-5
_RTOL_TWIN = 1e-4
_RTOL_FINAL = 1e-10
# the step limit of passes A and A2: where a board is flipped wrong, they creep (measured: A took
# 20-43 steps in four of nine 9-15-view scenes and A2 10-15 in six, most of them rejected or
# lowering the cost by a few per cent); with this limit the same boards turned, the same passes
# ran and the solutions agreed to 3e-4 in the camera, mirror and beam directions and to 0.012 mm
# in the beams (benchmarks/bench_compile.py's scenes); the next pass goes on from there
_STEPS_A = 10
AIMED_TURN_DEG = 10.0  # a laser aimed through its spots that turns by more than this is tried as another start


@dataclass(frozen=True)
class PassSpec:
    """One joint pass of :func:`calibrate`'s schedule: what it frees and how it weighs and stops.

    ``lasers_held``: the lasers' columns held (the rest as the calibration frees them);
    ``kind_weight``: the weight of each observation kind (dot, spot, rim, corner; None: all 1);
    ``rtol``: the LM's relative cost tolerance; ``scale_floor``: the loss scale is the user's
    ``loss_scale``, else 3 x the robust noise sigma of the pass's start, at least this many px
    (None: the scale the trial has); ``steps``: a step limit below the calibration's (the pass
    only has to bring the next into its basin); ``loss``: a loss instead of the calibration's.
    """

    name: str
    lasers_held: bool = False
    kind_weight: tuple[float, float, float, float] | None = None
    rtol: float = _RTOL_START
    scale_floor: float | None = None
    steps: int | None = None
    loss: str | None = None


_NO_SPOTS = (1.0, 0.0, 1.0, 1.0)
# the schedule: A (and A2 after the boards are flipped again) fits the geometry without the
# lasers; B everything from lasers refitted on it (B2 from lasers aimed through their spots);
# C the final pass at the re-estimated scale, C3 without the outliers, C2 after boards turned
PASS_A = PassSpec("A: camera, mirror, poses", True, _NO_SPOTS, _RTOL_TWIN, 0.1, _STEPS_A)
PASS_A2 = PassSpec("A2: after re-flipping", True, _NO_SPOTS, _RTOL_START, 0.1, _STEPS_A)
PASS_B = PassSpec("B: joint", scale_floor=0.05)
PASS_B2 = PassSpec("B2: joint (lasers aimed through their spots)")
PASS_C = PassSpec("C: joint (final)", rtol=_RTOL_FINAL)
PASS_C3 = PassSpec("C3: joint (outliers left out)", rtol=_RTOL_FINAL)
PASS_C2 = PassSpec("C2: joint (after turning)", rtol=_RTOL_FINAL)
_covariance_of_linearisation = jax.jit(covariance_of_linearisation)
_block_costs_jit = jax.jit(block_costs, static_argnames=("n_blocks",))

HALF_NORMAL_MEDIAN = 0.6744897501960817  # median of |r| / sigma for 1D Gaussian r


def _linearisation(
    params: Params, pk: Packed, masks: Masks | None = None, loss: str = "huber", scale=1.0, kind_weight=None
):
    """The padded problem's layout and its :class:`slcvjax.calibration.lm.Linearisation` at ``params`` (the
    compiled solve with no step; ``kind_weight``: each kind's weight, None: all 1)."""
    layout, p, arr, m = pad_problem(params, pk, make_masks(params) if masks is None else masks)
    return layout, _solve(p, arr, m, loss, scale, 0, kind_weight=kind_weight).linearisation


_TABLES = Recent(4)  # the last calls of _table


def _table(params: Params, pk: Packed):
    """The padded problem's layout and its :class:`slcvjax.calibration.lm.ObservationTable` at
    ``params`` (the last few kept: a fit looks at one solution's table several times)."""

    def compute():
        layout = Layout.of(pk, n_lasers=params.rig.lasers.n)
        return layout, _table_jit(pad_params(layout, params), layout.pad_packed(pk))

    return _TABLES.get((params, pk), None, compute)


def _per_observation(params: Params, pk: Packed) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per observation: its 2D residual norm (px), its kind and whether it is valid."""
    layout, t = _table(params, pk)
    return tuple(layout.unpad_observations(a) for a in (np.sqrt(np.asarray(t.sq)), t.kind, t.valid))


def _block_costs(params: Params, pk: Packed, loss: str, scale: float) -> np.ndarray:
    """Per pose block (board poses, then direct views) the robust cost of its observations."""
    layout, t = _table(params, pk)
    costs = _block_costs_jit(t, n_blocks=layout.cap[4] + layout.cap[5], loss=jnp.asarray(loss_index(loss)), scale=scale)
    return layout.unpad_blocks(costs)


def covariance_of(params: Params, pk: Packed, masks: Masks, loss: str, scale, sigma: float | None = None) -> Covariance:
    """:func:`slcvjax.calibration.lm.covariance_of_linearisation` at ``params`` of the problem ``pk``,
    through its shape buckets (the compiled solve with no step linearises): with one ``sigma``
    given, ``sigma^2 H^-1`` (every kind weighted 1); with one per kind (dot, spot, rim, chess
    corner), ``(sum_k N_k / sigma_k^2)^-1`` (each kind weighted by its noise: the Cramer-Rao
    bound where the kinds' noise differ); otherwise :func:`covariance_and_noise`'s."""
    if sigma is None:
        return covariance_and_noise(params, pk, masks, loss, scale)[0]
    sig = np.asarray(sigma, dtype=float)
    if sig.ndim == 1:
        if sig.shape != (len(Kind),) or not np.all(np.isfinite(sig) & (sig > 0)):
            raise ValueError(
                f"per-kind sigmas: expected {len(Kind)} positive numbers (dot, spot, rim, chess), got {sig}"
            )
        layout, lin = _linearisation(params, pk, masks, loss, scale, kind_weight=tuple(1.0 / sig**2))
        sig = np.asarray(1.0)
    else:
        layout, lin = _linearisation(params, pk, masks, loss, scale)
    cov = _covariance_of_linearisation(lin, pad_masks(layout, masks), jnp.asarray(sig, dtype=float))
    return _unpad_covariance(layout, cov)


def _unpad_covariance(layout: Layout, cov: Covariance) -> Covariance:
    """A covariance of the padded problem restricted to the real lasers and pose blocks."""
    return cov._replace(glob=layout.unpad_glob(cov.glob, (0, 1)), blocks=layout.unpad_blocks(cov.blocks))


def covariance_and_noise(params: Params, pk: Packed, masks: Masks, loss: str, scale) -> "tuple[Covariance, KindNoise]":
    """The covariance of the solution ``params`` where each kind of observation has its own noise
    (:func:`kind_noise`): ``H^-1 (sum_k sigma_k^2 N_k) H^-1`` (``N_k`` the kind's ``J^T W J``;
    :func:`slcvjax.calibration.lm.sandwich_covariance`), the solve having weighted every kind 1.
    Rendered images give the kinds different noise (spots' centroids noisier than dots', the
    rim's fitted edge far less noisy), which one pooled sigma would misstate.  A kind with too
    few free rows for its own sigma takes the pooled one.  With one noise for every kind it is
    ``sigma^2 H^-1``."""
    return _sandwich_of(*_kind_linearisations(params, pk, masks, loss, scale), masks)


def _sandwich_of(layout: Layout, full, parts, masks: Masks) -> "tuple[Covariance, KindNoise]":
    """:func:`covariance_and_noise` of :func:`_kind_linearisations`' linearisations."""
    noise = _noise_of(full, parts)
    padded = pad_masks(layout, masks)
    pooled2 = float(_pooled_noise_jit(full, padded)[0])
    meat = None
    for p, sig, n in zip(parts, noise.sigma, noise.rows, strict=True):
        if n == 0:
            continue
        raw = [np.asarray(a) for a in _raw_normal_jit(p.normal, p.seen_glob, p.seen_blocks)]
        s2 = sig**2 if np.isfinite(sig) else pooled2
        meat = [s2 * a for a in raw] if meat is None else [m + s2 * a for m, a in zip(meat, raw, strict=True)]
    if meat is None:
        raise CalibrationError(
            "the fit ended where it predicts none of the observations (each falls off the mirror or the "
            "sensor): the model does not fit these data (another mirror kind or camera projection may)"
        )
    cov = _sandwich_jit(full, type(full.normal)(*meat), padded)
    return _unpad_covariance(layout, cov), noise


def kind_sigmas(params: Params, pk: Packed, min_count: int = 10) -> np.ndarray:
    """Per kind (dot, spot, rim, chess corner) the noise sigma (px) from its median residual.

    Rim residuals are 1D (a distance to the rim curve), the others 2D.  NaN for a kind
    with fewer than ``min_count`` valid observations.
    """
    return _sigmas_of(*_per_observation(params, pk), min_count)


def _sigmas_of(norm, kind, ok, min_count: int = 10) -> np.ndarray:
    """:func:`kind_sigmas` of a per-observation table (``_per_observation``'s)."""
    out = np.full(len(Kind), np.nan)
    for k in Kind:
        sel = ok & (kind == k)
        if sel.sum() >= min_count:
            out[k] = np.median(norm[sel]) / (HALF_NORMAL_MEDIAN if k == Kind.RIM else RAYLEIGH_MEDIAN)
    return out


_leverage_shares_jit = PersistentJit(leverage_shares, "leverage_shares")
_sandwich_jit = PersistentJit(sandwich_covariance, "sandwich_covariance")
_raw_normal_jit = PersistentJit(raw_normal, "raw_normal")
_pooled_noise_jit = PersistentJit(pooled_noise, "pooled_noise")
MIN_FREE_ROWS = 20  # a kind whose rows leave fewer free than this takes the pooled sigma


class KindNoise(NamedTuple):
    """Per kind (dot, spot, rim, chess corner): its valid scalar rows, the parameters its rows
    fix (the sum of their leverages), and its noise sigma (px) over the rows left free (NaN where
    fewer than :data:`MIN_FREE_ROWS` are)."""

    rows: np.ndarray
    leverage: np.ndarray
    sigma: np.ndarray


def _kind_linearisations(params: Params, pk: Packed, masks: Masks, loss: str, scale):
    """The padded layout, the linearisation at ``params`` with every kind weighted 1 (as the
    solve weighs them), and one per kind with that kind alone (the compiled solve with no
    step: nothing new compiles)."""
    layout, p, padded, m = pad_problem(params, pk, masks)
    full = _solve(p, padded, m, loss, scale, 0).linearisation
    # one kind's rows alone: the others' counted as padding, which the sums skip
    parts = [_solve(p, padded.kinds_only(np.eye(len(Kind))[k]), m, loss, scale, 0).linearisation for k in Kind]
    return layout, full, parts


def _noise_of(full, parts) -> KindNoise:
    t = full.table
    real = np.asarray(t.valid) & np.asarray(t.present)
    kinds = np.asarray(t.kind)
    rows = np.array([(1.0 if k == Kind.RIM else 2.0) * np.sum(real & (kinds == k)) for k in Kind])
    # every kind's share in one call (H^-1 once); a kind without rows fixes nothing
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *((p.normal, p.seen_glob, p.seen_blocks) for p in parts))
    lev = np.where(rows > 0, np.asarray(_leverage_shares_jit(full.normal, *stacked)), 0.0)
    free = rows - lev
    # the plain squared residuals: under the robust loss a kind noisier than its scale would have
    # its large residuals down-weighted and its sigma understated (gross outliers are left out
    # by then)
    sq = np.asarray(t.sq)
    wsq = np.array([float(np.sum(sq[real & (kinds == k)])) for k in Kind])
    sigma = np.where(free >= MIN_FREE_ROWS, np.sqrt(wsq / np.maximum(free, 1.0)), np.nan)
    return KindNoise(rows, lev, sigma)


def kind_noise(params: Params, pk: Packed, masks: Masks | None = None, loss: str = "huber", scale=1.0) -> KindNoise:
    """Each kind's noise sigma at the solution ``params``, from its squared residuals over its
    rows less the parameters they fix (:class:`KindNoise`,
    :func:`slcvjax.calibration.lm.leverage_share`).

    Board poses are fixed by their dots and, where a board shows few dots, by its spots; the
    lasers by the spots: on the paper preset the spots' rows fix about half of what they hold
    (144 of 296), so their residuals understate their noise by about 1.4x.  Over all kinds the
    leverages add up to the number of estimated parameters."""
    masks = make_masks(params) if masks is None else masks
    _, full, parts = _kind_linearisations(params, pk, masks, loss, scale)
    return _noise_of(full, parts)


def robust_sigma(params: Params, pk: Packed) -> float:
    """Noise sigma (px) from the median 2D residual norm of the dots, spots and corners."""
    return _robust_sigma_of(*_per_observation(params, pk))


def _robust_sigma_of(norm, kind, ok) -> float:
    """:func:`robust_sigma` of a per-observation table (``_per_observation``'s)."""
    sel = ok & (kind != 2)
    if not sel.any():
        return 1.0
    return float(np.median(norm[sel]) / RAYLEIGH_MEDIAN)


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
    repairs: list = field(default_factory=list)  # observations relabelled or left out (see :func:`_repair`)
    box: dict | None = None  # the rigid box model's boards, where it was used (see :func:`_rigid_refine`)
    # lasers whose spots cannot fix a line: held at a placeholder, their spots left out (fit_lasers)
    undetermined_lasers: tuple[int, ...] = ()

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


def _chess_start(obs: Observations, pk: Packed, cam: Camera, known: dict[int, Pose]) -> list[Pose]:
    out = []
    for ci in pk.chess_keys:
        if ci in known:
            out.append(known[ci])
            continue
        cv = obs.calibration_views[ci]
        ok, rvec, tvec = cv2.solvePnP(
            obs.boards[cv.board][cv.seen], cv.pixels[cv.seen], np.asarray(cam.K), np.asarray(cam.dist)
        )
        if not ok:
            raise CalibrationError(f"calibration_views[{ci}]: the chessboard's pose could not be found")
        out.append(Pose.from_rvec(rvec.ravel(), tvec.ravel()))
    return out


def calibrate(
    obs: Observations,
    camera: Camera | None = None,
    freeze: tuple[str, ...] | set[str] = (),
    loss: str = "huber",
    loss_scale: float | None = None,
    max_steps: int = 500,
    rigid: "bool | list[str]" = False,
    mirror=None,
) -> CalibrationResult:
    """Calibrate the whole rig from observations (see the module docstring).

    Args:
        obs: the observations.
        camera: a known camera to start from (freeze it with ``freeze={"camera"}``);
            without it the intrinsics come from the direct chessboard views.
        mirror: a known mirror (pose and shape) to start from instead of the rim's
            (freeze it with ``"mirror"``; with the camera frozen too this evaluates a
            calibration on held-out views: only the poses and the lasers are fitted).
        freeze: parameter blocks held fixed: camera, mirror, lasers, poses, chess_poses.
        loss: ``huber`` (default), ``cauchy`` or ``linear`` for the dots and spots; ``linear`` is
            the plain least-squares fit: no observation is left out as a gross outlier.
        loss_scale: the robust loss's scale in px; by default 3 sigma, sigma estimated
            robustly from the residuals.
        max_steps: the most LM linearisations per pass.
        rigid: the rigid target box model (:mod:`slcvjax.calibration.rigid`) for the group of boards the
            observations declare (``rigid_boards``; ``True``) or for these board names:
            one pose per board in the box and one sensor pose per view, refined from the
            free solution (pass R); a board pose that does not fit the box is left out and
            reported.
    """
    group = rigid_group(obs, rigid)
    telecentric = obs.camera_projection == "telecentric"
    through = camera is None and mirror is None and not obs.calibration_views and obs.mirror_shape is not None
    if obs.camera_projection == "auto" and not (through and obs.mirror_shape["kind"] != "cone"):
        raise CalibrationError(
            "camera_projection: auto is chosen from views through a conic mirror alone "
            "(no calibration_views, no camera or mirror to start from, a mirror_shape other than the cone)"
        )
    if camera is not None and camera.telecentric != telecentric:
        raise CalibrationError(
            f"camera_projection: the observations say {obs.camera_projection}, the camera given is {camera.projection}"
        )
    if telecentric and camera is None and (obs.calibration_views or obs.mirror_shape is None):
        raise CalibrationError(
            "camera_projection: a telecentric camera is calibrated through a conic mirror only "
            "(no calibration_views, a mirror_shape of kind sphere, paraboloid, hyperboloid or ellipsoid)"
        )
    auto = obs.mirror_shape is not None and obs.mirror_shape["kind"] == "auto"
    if auto and (camera is not None or mirror is not None or obs.calibration_views):
        raise CalibrationError(
            "mirror_shape.kind: auto is chosen from views through the mirror alone "
            "(no calibration_views, no camera or mirror to start from)"
        )
    if auto:
        res = _auto_kind(obs, freeze, loss, loss_scale, max_steps)
    elif through:
        res = _through_the_mirror(obs, freeze, loss, loss_scale, max_steps)
    else:
        res = _calibrate_lockstep([obs], camera, freeze, loss, loss_scale, max_steps, _solve_loop, mirror=mirror)[0]
    return _rigid_refine(res, obs, group, max_steps) if group else res


AUTO_KINDS = ("hyperboloid", "paraboloid", "sphere")  # a hyperboloid's conic constant may cross to an ellipsoid's
AUTO_FOLDS = 5


def held_out_rms(rig: Rig, held: Observations) -> tuple[float, int, int]:
    """``(RMS px, observations used, left invalid)`` of views a calibrated rig did not see: its
    camera and mirror held, the views' poses (and lasers) fitted by plain least squares."""
    from ..geometry.mirror import shape_json

    held = dataclasses.replace(held, mirror_shape=shape_json(rig.mirror), camera_projection=rig.camera.projection)
    ev = calibrate(held, camera=rig.camera, mirror=rig.mirror, freeze={"camera", "mirror"}, loss="linear")
    r = report(ev, held)["residuals"]
    n = sum(int(s.sum()) for v in held.views for _, s in v.boards.values()) + sum(len(v.spots) for v in held.views)
    return float(r["rms_px"]), n - int(r["invalid"]), int(r["invalid"])


def _auto_kind(obs: Observations, freeze, loss, loss_scale, max_steps) -> "CalibrationResult":
    """``mirror_shape.kind = "auto"``: each of :data:`AUTO_KINDS` fitted on every view, then
    scored by :data:`AUTO_FOLDS`-fold cross-validation over the views (every fifth view held out
    in turn, each fold's fit started from the fit on every view); the kind of the least held-out
    RMS (fewest held-out observations off the model first) is kept; the stage ``mirror_kind``
    reports each kind's figure, and says so where kinds lie within two standard errors of the
    best (the views do not determine the kind: a camera's distortion and the mirror's place
    absorb much of a shape's difference)."""
    from tqdm.auto import tqdm

    n = len(obs.views)
    if n < 2:
        raise CalibrationError("mirror_shape.kind: auto picks the kind by held-out views: it needs at least 2 views")
    k = min(AUTO_FOLDS, n)
    folds = [list(range(i, n, k)) for i in range(k)]
    dims = {key: obs.mirror_shape[key] for key in ("vertex_radius",) if key in obs.mirror_shape}
    scores: dict[str, tuple[int, float]] = {}
    counted: dict[str, int] = {}
    fits: dict[str, CalibrationResult] = {}
    with tqdm(total=len(AUTO_KINDS) * (k + 1), desc="mirror kind (held-out views)", leave=False, disable=None) as bar:
        for kind in AUTO_KINDS:
            o_kind = dataclasses.replace(obs, mirror_shape={"kind": kind} | dims)
            kind_freeze, estimate = _shape_unknowns(o_kind.mirror_shape, freeze)
            sq, used, bad = 0.0, 0, 0
            try:
                # every view from each central start; each fold's fit starts from it (one start:
                # the fold's own minimum, the held-out views' residuals left out of its cost)
                fits[kind] = full = _through_the_mirror(o_kind, freeze, loss, loss_scale, max_steps)
                bar.update(1)
                for fold in folds:
                    train = dataclasses.replace(o_kind, views=[v for i, v in enumerate(obs.views) if i not in fold])
                    held = dataclasses.replace(o_kind, views=[obs.views[i] for i in fold])
                    fit = _calibrate_lockstep(
                        [train],
                        full.rig.camera,
                        kind_freeze,
                        loss,
                        loss_scale,
                        max_steps,
                        _solve_loop,
                        mirror=full.rig.mirror,
                        estimate=estimate,
                    )[0]
                    rms, n_used, n_bad = held_out_rms(fit.rig, held)
                    sq, used, bad = sq + rms * rms * n_used, used + n_used, bad + n_bad
                    bar.update(1)
            except CalibrationError:
                sq, used, bad = np.inf, 1, n
            scores[kind] = (bad, float(np.sqrt(sq / max(used, 1))))
            counted[kind] = used
    best = min(AUTO_KINDS, key=lambda kd: scores[kd])
    if not np.isfinite(scores[best][1]):
        raise CalibrationError("mirror_shape.kind: no kind of mirror fits these views")
    res = fits[best]
    notes = [
        f"{kd}: held-out RMS {scores[kd][1]:.4f} px"
        + (f", {scores[kd][0]} held-out observation(s) off the model" if scores[kd][0] else "")
        for kd in AUTO_KINDS
    ]
    notes.append(f"chosen: {best} (fitted as a {res.rig.mirror.kind}), {k}-fold over {n} views")
    # two standard errors of the held-out RMS (each observation two residuals): kinds within it
    # are not told apart by these views
    margin = 2.0 * scores[best][1] / np.sqrt(2.0 * counted[best])
    tied = [kd for kd in AUTO_KINDS if scores[kd][0] == scores[best][0] and scores[kd][1] <= scores[best][1] + margin]
    if len(tied) > 1:
        notes.append(
            f"not determined: the held-out views do not tell {', '.join(tied)} apart "
            f"(within two standard errors, {margin:.3f} px)"
        )
    res.staged.reports.insert(0, StageReport("mirror_kind", scores[best][1], "px (held out)", notes))
    return res


def _shape_unknowns(shape: dict, freeze) -> tuple[set, set]:
    """``(freeze, estimate)`` for a mirror of ``shape`` seen through only: a sphere's or a
    paraboloid's conic constant is its kind's, a hyperboloid's (or an ellipsoid's) left out is
    estimated; a sphere's axis is held (its vertex slides over it with the axis: only its centre
    is seen)."""
    estimate = {"shape"} if "conic_constant" in shape_missing(shape) else set()
    freeze = set(freeze) | ({"mirror_tilt"} if shape["kind"] == "sphere" else set())
    return freeze, estimate


PROJECTION_TEST_LEVEL = 0.05  # the F-test's level at which the perspective term is kept


def perspective_test(tele: "CalibrationResult", persp: "CalibrationResult") -> tuple[float, int, int]:
    """``(p-value, extra unknowns, dof)`` of the F-test of a telecentric fit against the
    perspective one of the same views: a telecentric camera is a pinhole's limit at an infinite
    distance, so the pinhole's extra unknowns (its depth, held before a telecentric lens: the
    gauge of parallel rays) nest it.  ``F = ((S_t - S_p) / q) / (S_p / dof_p)``, ``S`` the
    weighted squared residuals (``sigma^2 dof``), ``q = dof_t - dof_p``; a small p-value says the
    views need the perspective.  ``(0, q, dof_p)`` where ``q < 1`` and the pinhole fits better."""
    s_t = float(tele.cov.sigma) ** 2 * int(tele.cov.dof)
    s_p = float(persp.cov.sigma) ** 2 * int(persp.cov.dof)
    q, dof = int(tele.cov.dof) - int(persp.cov.dof), int(persp.cov.dof)
    if q < 1 or dof < 1 or s_p <= 0.0:
        return (0.0 if s_p < s_t else 1.0), q, dof
    f = max((s_t - s_p) / q / (s_p / dof), 0.0)
    # P(F(q, dof) > f) = I_x(dof/2, q/2), x = dof / (dof + q f): the regularised incomplete beta
    pval = float(jax.scipy.special.betainc(dof / 2.0, q / 2.0, dof / (dof + q * f)))
    return pval, q, dof


def _through_the_mirror(obs: Observations, freeze, loss, loss_scale, max_steps) -> "CalibrationResult":
    """A rig seen only through its mirror (no direct views): the joint passes from each central
    start (:func:`slcvjax.calibration.central.central_start`), the lowest final cost kept.  Where the shape leaves
    out the conic constant, the start searches it and the joint passes estimate it (the vertex
    radius held: the scale's gauge).  ``camera_projection = "auto"`` fits a telecentric and a
    perspective camera and keeps the perspective one only where :func:`perspective_test` says the
    views need it (p-value below :data:`PROJECTION_TEST_LEVEL`; fewer observations off the model
    first): the pinhole's depth is otherwise a near-gauge that drifts towards the telecentric
    limit and costs held-out accuracy."""
    if obs.camera_projection == "auto":
        return _auto_projection(obs, freeze, loss, loss_scale, max_steps)
    shape = obs.mirror_shape
    freeze, estimate = _shape_unknowns(shape, freeze)
    kind = shape["kind"]
    if kind == "asphere":  # started as its conic, then given its polynomial terms
        kind = conic_kind(shape["conic_constant"])
    starts = central_start(
        pack(obs),
        obs.image_size,
        kind,
        shape.get("vertex_radius"),
        shape.get("conic_constant"),
        shape.get("radius"),
        telecentric=obs.camera_projection == "telecentric",
    )
    if shape["kind"] == "asphere":
        starts = [
            (
                cam,
                AsphereMirror(
                    m.apex, m.axis, m.curvature, m.conic, m.radius, jnp.asarray(shape["coefficients"], float)
                ),
                rep,
            )
            for cam, m, rep in starts
        ]
    best = None
    for cam, mir, rep in starts:
        res = _calibrate_lockstep(
            [obs], cam, freeze, loss, loss_scale, max_steps, _solve_loop, mirror=mir, estimate=estimate
        )[0]
        res.staged.reports.insert(0, rep)
        if best is None or res.passes[-1].cost < best.passes[-1].cost:
            best = res
    if "radius" not in shape:  # the rim bounds nothing: where the estimate closed the conic, inside its widest circle
        mir = best.rig.mirror
        k1, c = 1.0 + float(mir.conic), float(mir.curvature)
        if k1 > 0 and k1 * (c * float(mir.radius)) ** 2 >= 1.0:
            rim = jnp.asarray(0.999 / (c * np.sqrt(k1)))
            best.params = eqx.tree_at(lambda p: p.rig.mirror.radius, best.params, rim)
    return best


def _auto_projection(obs: Observations, freeze, loss, loss_scale, max_steps) -> "CalibrationResult":
    """:func:`_through_the_mirror` for ``camera_projection = "auto"``."""
    fits: dict[str, CalibrationResult] = {}
    failed: dict[str, str] = {}
    for proj in ("telecentric", "perspective"):
        try:
            fits[proj] = _through_the_mirror(
                dataclasses.replace(obs, camera_projection=proj), freeze, loss, loss_scale, max_steps
            )
        except CalibrationError as e:
            failed[proj] = str(e)
    if not fits:
        raise CalibrationError(
            "camera_projection: auto: neither projection fits these views ("
            + "; ".join(f"{k}: {v}" for k, v in failed.items())
            + ")"
        )
    notes = [f"{k}: failed ({v})" for k, v in failed.items()]
    if len(fits) == 1:
        (best,) = fits
    else:
        tele, persp = fits["telecentric"], fits["perspective"]
        off = {k: int(np.sum(~_per_observation(r.params, r.packed)[2])) for k, r in fits.items()}
        pval, q, dof = perspective_test(tele, persp)
        for k, r in fits.items():
            notes.append(
                f"{k}: sigma {float(r.cov.sigma):.4f} px, dof {int(r.cov.dof)}"
                + (f", {off[k]} observation(s) off the model" if off[k] else "")
            )
        if off["telecentric"] != off["perspective"]:
            best = min(fits, key=lambda k: off[k])
            notes.append(f"chosen: {best} (fewer observations off the model)")
        else:
            best = "perspective" if pval < PROJECTION_TEST_LEVEL else "telecentric"
            notes.append(
                f"chosen: {best} (F-test of the perspective's {q} extra unknown(s): p = {pval:.3g}, "
                f"kept below {PROJECTION_TEST_LEVEL:g})"
            )
    res = fits[best]
    res.staged.reports.insert(0, StageReport("camera_projection", float(res.cov.sigma), "px (sigma)", notes))
    return res


def rigid_group(obs: Observations, rigid: "bool | list[str]") -> list[str]:
    """The board names of the rigid box model for ``calibrate(rigid=...)``: none where ``rigid``
    is False, the observations' ``rigid_boards`` where True, else ``rigid`` itself."""
    if rigid is False or rigid is None:
        return []
    if rigid is True:
        group = list(obs.extra.get("rigid_boards") or [])
        if not group:
            raise CalibrationError(
                "rigid: the observations declare no rigid_boards (name the boards fixed in one box, "
                'e.g. "rigid_boards": ["wall0", "wall1"], or pass their names)'
            )
    else:
        group = list(rigid)
    for i, b in enumerate(group):
        if b not in obs.boards:
            raise CalibrationError(f"rigid_boards[{i}]: unknown board {b!r} (known: {', '.join(sorted(obs.boards))})")
    return group


def resolve_batch(batch: str) -> str:
    """``loop`` or ``vmap`` for :func:`calibrate_many`'s ``batch`` (``auto``: ``loop`` on a CPU)."""
    if batch == "auto":
        return "loop" if jax.default_backend() == "cpu" else "vmap"
    if batch not in ("loop", "vmap"):
        raise ValueError(f"batch: expected auto, loop or vmap, got {batch!r}")
    return batch


def calibrate_many(
    observations: list[Observations],
    batch: str = "auto",
    progress: bool = False,
    workers: int = 1,
    *,
    camera: Camera | None = None,
    freeze: tuple[str, ...] | set[str] = (),
    loss: str = "huber",
    loss_scale: float | None = None,
    max_steps: int = 500,
    rigid: "bool | list[str]" = False,
    mirror=None,
) -> list[CalibrationResult]:
    """Calibrate several observation sets (Monte Carlo trials, say) with :func:`calibrate`'s method.

    ``batch``:

    * ``loop``: one calibration after another, each through the compiled solves (fastest
      on a CPU, where a batch would wait for its slowest trial);
    * ``vmap``: every trial in lockstep, each LM pass of all trials one ``vmap``-ped solve
      whose trial axis is sharded over all JAX devices (:func:`jax.devices`); the host
      steps between the passes run trial by trial.  Sets of the same sizes share one
      compilation; the results equal ``loop``'s to round-off;
    * ``auto``: ``vmap`` where the default device is an accelerator, ``loop`` on a CPU.

    ``workers`` (``loop``): calibrations run at once in threads, each one's host steps
    (the staged stages, OpenCV, NumPy) beside another's compiled programs, which run one at
    a time (see ``slcvjax.support.persist``); results equal to round-off.

    ``camera``, ``freeze``, ``loss``, ``loss_scale``, ``max_steps``, ``rigid`` and ``mirror`` are
    :func:`calibrate`'s, the same for every set.  With
    ``progress`` a bar counts the calibrations (in ``vmap`` they finish together, and the
    bar names the pass under way).
    """
    kw = dict(
        camera=camera, freeze=freeze, loss=loss, loss_scale=loss_scale, max_steps=max_steps, rigid=rigid, mirror=mirror
    )
    args = (kw["camera"], kw["freeze"], kw["loss"], kw["loss_scale"], kw["max_steps"])
    groups = [rigid_group(o, kw["rigid"]) for o in observations]

    def rigid(res, o, group):
        return _rigid_refine(res, o, group, kw["max_steps"]) if group else res

    batch = resolve_batch(batch)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(observations), desc="calibrations", unit="calibration")
    try:
        if batch == "loop":
            if workers < 1:
                raise ValueError(f"workers: expected at least 1, got {workers}")

            def one(o, group):
                return rigid(_calibrate_lockstep([o], *args, _solve_loop, mirror=kw["mirror"])[0], o, group)

            out = []
            with ThreadPoolExecutor(workers) as pool:
                for res in pool.map(one, observations, groups) if workers > 1 else map(one, observations, groups):
                    out.append(res)
                    if bar is not None:
                        bar.update(1)
            return out
        out = _calibrate_lockstep(observations, *args, _solve_vmap, bar=bar, mirror=kw["mirror"])
        out = [rigid(res, o, g) for res, o, g in zip(out, observations, groups, strict=True)]
        if bar is not None:
            bar.update(len(out))  # in lockstep they finish together
        return out
    finally:
        if bar is not None:
            bar.close()


class SolveJob(NamedTuple):
    """One LM solve of a pass (:func:`_job`): its start, problem and masks padded to the trial's
    shape buckets, its loss scale (px), kind weights (None: all 1) and relative cost tolerance."""

    params: Params
    arrays: Packed
    masks: Masks
    scale: float
    kind_weight: tuple[float, float, float, float] | None
    rtol: float

    def shape_key(self) -> tuple:
        """What decides its compilation: the structure and shapes of its arrays."""
        leaves, tree = jax.tree_util.tree_flatten((self.params, self.arrays, self.masks))
        return tree, tuple(jnp.shape(x) for x in leaves)


def _solve_loop(jobs: list[SolveJob], loss: str, max_steps: int, size: int | None = None) -> list[LMResult]:
    """Each job through the compiled solve, one after the other (``size``: unused)."""
    return [_solve(j.params, j.arrays, j.masks, loss, j.scale, max_steps, j.rtol, j.kind_weight) for j in jobs]


@jax.jit
def _solve_batched(params, arr, masks, scale, kind_weight, rtol, loss, max_steps):
    def one(p, a, m, sc, kw, rt):
        # a loop over the real rows under vmap runs slowly (measured: the sharded lockstep test
        # ran past its 15-minute limit), so the trials' layouts are fine and every row is visited
        return solve(p, a, m, loss=loss, scale=sc, max_steps=max_steps, rtol=rt, kind_weight=kw, real_only=False)

    return jax.vmap(one)(params, arr, masks, scale, kind_weight, rtol)


def _trial_sharding(n: int):
    """``(padded size, sharding)`` for a trial axis of ``n`` over all devices (None for one)."""
    devices = jax.devices()
    if len(devices) == 1:
        return n, None
    mesh = jax.sharding.Mesh(np.asarray(devices), ("trials",))
    return -(-n // len(devices)) * len(devices), jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("trials"))


def _place(x, sharding):
    """``x`` (the same on every process) as a global array laid out by ``sharding``."""
    host = np.asarray(x)
    return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])


def _solve_vmap(jobs: list[SolveJob], loss: str, max_steps: int, size: int | None = None) -> list[LMResult]:
    """The jobs as ``vmap``-ped solves, one per group of equal sizes, sharded over the devices.

    Each group is padded to ``size`` (the number of trials; and to a multiple of the
    device count) by repeating its last job, so that every pass of a lockstep
    calibration reuses one compilation.
    """
    shapes = [j.shape_key() for j in jobs]
    out: list = [None] * len(jobs)
    for key in dict.fromkeys(shapes):
        idx = [i for i, k in enumerate(shapes) if k == key]
        n, sharding = _trial_sharding(max(size or 0, len(idx)))
        group = [jobs[i] for i in idx + [idx[-1]] * (n - len(idx))]

        def stacked(*trees):
            return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *trees)

        batch = (
            stacked(*(j.params for j in group)),
            stacked(*(j.arrays for j in group)),
            stacked(*(j.masks for j in group)),
            jnp.asarray([j.scale for j in group], dtype=float),
            jnp.stack([kind_weights(j.kind_weight) for j in group]),
            jnp.asarray([j.rtol for j in group], dtype=float),
        )
        if sharding is not None:
            # every process holds the whole batch (the same on each): each device takes its rows
            batch = jax.tree_util.tree_map(functools.partial(_place, sharding=sharding), batch)
        res = _solve_batched(*batch, loss=jnp.asarray(loss_index(loss)), max_steps=jnp.asarray(max_steps))
        if not res.cost.is_fully_addressable:  # several hosts: every process gets every trial
            from jax.experimental import multihost_utils

            res = multihost_utils.process_allgather(res, tiled=True)
        for j, i in enumerate(idx):
            out[i] = jax.tree_util.tree_map(lambda x, j=j: x[j], res)
    return out


class _Trial:
    """One calibration's state between the passes of :func:`_calibrate_lockstep`."""

    def __init__(self, obs, camera, freeze, t0, fine: bool = False, mirror=None, estimate=()):
        self.obs, self.t0 = obs, t0
        st = staged(obs, camera=camera, pk=pack(obs), mirror=mirror)
        self.st, self.pk = st, st.packed  # spots without a board have one now
        self.t_staged = time.perf_counter() - t0
        if camera is not None and not st.chess_poses:
            st.chess_poses = {}
        chess = _chess_start(obs, self.pk, st.camera, st.chess_poses)
        if not chess:
            chess_stack = Pose(jnp.zeros((0, 3, 3)), jnp.zeros((0, 3)))
            if camera is None:
                raise CalibrationError("calibration_views: no direct views and no camera given")
        else:
            chess_stack = stack_poses(chess)
        self.params = Params(st.rig, stack_poses(st.poses), chess_stack)
        self.freeze, self.estimate = set(freeze), estimate
        # lasers held because their spots cannot fix a line (found again where B refits the lasers)
        self.undetermined: tuple[int, ...] = st.undetermined
        self.masks = make_masks(self.params, set(freeze), estimate, held_lasers=st.undetermined)
        self.mask_a = make_masks(self.params, set(freeze) | {"lasers"}, estimate)
        self.fine = fine
        if st.undetermined and "lasers" in freeze:  # no refit: their spots go now
            n_d, n_s = int(self.pk.counts[Kind.DOT]), int(self.pk.counts[Kind.SPOT])
            held = np.isin(np.asarray(self.pk.spot_laser)[:n_s], st.undetermined)
            self.pk = self.pk.select(np.ones(n_d, bool), ~held)
        self.use(self.pk)
        self.passes: list[JointPass] = []
        self.repairs: list[dict] = []
        self.scale = 1.0
        # the problem before spots were set aside by their lines (:func:`_relabel_spots`), and
        # which of its rows were: the outlier check looks at them again on the final geometry
        self.set_aside: tuple[Packed, np.ndarray] | None = None

    def use(self, pk: Packed) -> None:
        """Solve the problem ``pk`` from now on (the same poses; fewer or relabelled observations)."""
        self.pk = pk
        self.layout = Layout.of(pk, fine=self.fine, n_lasers=self.params.rig.lasers.n)
        self.arr = self.layout.pad_packed(pk)


class _Lockstep:
    """The trials of :func:`_calibrate_lockstep` and how a pass's solves run over them: the driver
    that :data:`SCHEDULE`'s steps call (``solver`` runs a pass's solves, all trials' at once)."""

    def __init__(self, trials: list[_Trial], solver, freeze: set, loss: str, loss_scale, max_steps: int, bar=None):
        self.trials, self.solver, self.freeze = trials, solver, freeze
        self.loss, self.loss_scale, self.max_steps, self.bar = loss, loss_scale, max_steps, bar
        self.every = list(range(len(trials)))

    def solve(self, spec: PassSpec, chosen: list[int], scale: float | None = None) -> None:
        """The pass ``spec`` of the ``chosen`` trials from where they are (``scale``: its loss
        scale instead of the one ``spec`` gives)."""
        trials = self.trials
        for i in chosen:
            tr = trials[i]
            if scale is not None:
                tr.scale = scale
            elif spec.scale_floor is not None:
                self.rescale(tr, spec.scale_floor)
        jobs = [_job(trials[i], trials[i].params, spec) for i in chosen]
        own = spec.steps if spec.steps is not None and spec.steps < self.max_steps else None  # the pass's own limit
        solved = self.solver(jobs, spec.loss or self.loss, own or self.max_steps, size=len(trials))
        for i, res in zip(chosen, solved, strict=True):
            _record(trials[i], spec.name, res, own)
            trials[i].params = unpad_params(trials[i].layout, res.params)
        if self.bar is not None:
            self.bar.set_postfix_str(spec.name.split(":")[0])

    def rescale(self, tr: _Trial, floor: float) -> None:
        """The trial's loss scale where it stands: the user's, else 3 x the robust noise sigma,
        at least ``floor`` px."""
        tr.scale = self.loss_scale or 3.0 * max(robust_sigma(tr.params, tr.pk), floor)

    def other_starts(self, chosen: list[int], turned_only: bool, pass_loss: str | None = None) -> list[int]:
        """Each board pose of the ``chosen`` trials swapped for its flipped twin, or for its pose
        carried over from another view (:func:`_carried`), where that fits better, both refined
        with the rig held (``turned_only``: only swaps that turn the board; ``pass_loss``: a loss
        for this instead of the calibration's).  Returns the trials where any board turned."""
        trials, this_loss = self.trials, pass_loss or self.loss
        chosen = [i for i in chosen if trials[i].pk.n_poses]
        starts = [_candidates(trials[i].params, trials[i].pk, trials[i].masks) for i in chosen]
        # one solve per kind of start over the chosen trials: the batch shapes of a pass
        solved = [
            self.solver(
                [_job(trials[i], c, _TWIN_SOLVE, hold) for i, (c, hold) in zip(chosen, kind, strict=True)],
                this_loss,
                self.max_steps,
                size=len(trials),
            )
            for kind in zip(*starts, strict=True)
        ]
        turned = []
        for n_i, i in enumerate(chosen):
            tr = trials[i]
            n_moved = 0
            for res in (kind[n_i] for kind in solved):
                other = unpad_params(tr.layout, res.params)
                tr.params, n = _keep_better(tr.params, other, tr.pk, this_loss, tr.scale, turned_only)
                n_moved += n
            if n_moved:
                tr.passes[-1].notes.append(f"{n_moved} board pose(s) turned after it")
                turned.append(i)
        return turned

    def aimed_starts(self, chosen: list[int]) -> None:
        """B again from every laser aimed from the camera's centre through its spots
        (:func:`slcvjax.calibration.staged.aimed_lasers`) where that turns a laser by more than
        :data:`AIMED_TURN_DEG`; kept where it ends at a lower cost.  A laser whose spots lie
        along a few mm of its line at 140 mm (measured: the preset at 0.9 px, seeds 12 and 14)
        went from B into a line nearly along its boards, 82 degrees off, while a start near
        the truth ended at a lower cost."""
        trials, picked, starts = self.trials, [], []
        for i in chosen:
            tr = trials[i]
            p = tr.params
            if p.rig.lasers.n == 0:
                continue
            aimed = aimed_lasers(p.rig.camera, p.rig.mirror, tr.pk, unstack_poses(p.poses), p.rig.lasers)
            cos = np.abs(np.sum(np.asarray(aimed.directions) * np.asarray(p.rig.lasers.directions), axis=1))
            if np.any(cos < np.cos(np.radians(AIMED_TURN_DEG))):
                picked.append(i)
                starts.append(Params(p.rig.with_lasers(aimed), p.poses, p.chess))
        if not picked:
            return
        jobs = [_job(trials[i], st, PASS_B2) for i, st in zip(picked, starts, strict=True)]
        now = [_job(trials[i], trials[i].params, PASS_B2) for i in picked]
        solved = self.solver(jobs, self.loss, self.max_steps, size=len(trials))
        # B's own final cost held the rim rows' normalisation of B's start: the cost at B's
        # solution is taken again with the one the aimed solve started from (the same rig)
        current = self.solver(now, self.loss, 0, size=len(trials))
        for i, res, cur in zip(picked, solved, current, strict=True):
            tr = trials[i]
            kept = float(res.cost) < float(cur.cost)
            _record(tr, PASS_B2.name, res, None, "kept: a lower cost than B's" if kept else "B's cost is lower")
            if kept:
                tr.params = unpad_params(tr.layout, res.params)

    def result(self, tr: _Trial) -> CalibrationResult:
        """A trial's result at the end of the schedule: its solution, covariance and passes."""
        cov, noise = covariance_and_noise(tr.params, tr.pk, tr.masks, self.loss, tr.scale)
        return CalibrationResult(
            tr.params,
            tr.st,
            tr.pk,
            tr.masks,
            cov,
            self.loss,
            float(tr.scale),
            tr.passes,
            {"staged_s": tr.t_staged, "total_s": time.perf_counter() - tr.t0},
            dict(zip(KIND_NAMES, noise.sigma.tolist(), strict=True)),
            tr.repairs,
            undetermined_lasers=tr.undetermined,
        )


def _first_pass(d: _Lockstep) -> None:
    """A: the geometry without the lasers, only far enough to decide the boards' flips again
    (to the start's tolerance where the poses are held: no flip is decided again)."""
    d.solve(PASS_A if "poses" not in d.freeze else dataclasses.replace(PASS_A, rtol=_RTOL_START), d.every)


def _reflip(d: _Lockstep) -> None:
    """The boards' flips decided again on the refined geometry, then A2 where any board turned
    (otherwise pass A's poses already fit the dots on this geometry).  Where a board's dots no
    longer back-project onto the mirror at A's solution, the trial keeps A's poses (noted)."""
    again = []
    for i, tr in enumerate(d.trials):
        p = tr.params
        try:
            poses = stack_poses(board_poses(p.rig.camera, p.rig.mirror, tr.pk, start=p.poses)[0])
        except CalibrationError as e:
            tr.passes[-1].notes.append(f"the boards' flips not decided again: {e}")
            continue
        if np.any(_turned(poses, p.poses)):
            tr.params = Params(p.rig, poses, p.chess)
            again.append(i)
    if again:
        d.solve(PASS_A2, again)


def _refit_lasers(d: _Lockstep) -> None:
    """The lasers refitted on the refined geometry (:func:`slcvjax.calibration.staged.fit_lasers`):
    spots relabelled or left out where they fit another laser's line or none, and a laser whose
    spots cannot fix a line held (undetermined)."""
    for tr in d.trials:
        p = tr.params
        fit = fit_lasers(p.rig.camera, p.rig.mirror, tr.pk, unstack_poses(p.poses), tr.obs.n_lasers)
        tr.params = Params(p.rig.with_lasers(fit.lasers), p.poses, p.chess)
        tr.undetermined = fit.held
        tr.masks = make_masks(tr.params, tr.freeze, tr.estimate, held_lasers=tr.undetermined)
        _relabel_spots(tr, fit)


def _rescale(d: _Lockstep) -> None:
    """The loss scale re-estimated at B's solution: the user's, else 3 x the robust noise sigma."""
    for tr in d.trials:
        d.rescale(tr, PASS_B.scale_floor)


def _readmit_set_aside(d: _Lockstep) -> None:
    """The spots set aside by their lines (:func:`_relabel_spots`) that the joint solution so far
    predicts near their own line (:func:`_predicted_fit`) come back before C, which then fits
    them (rather than C again once they are judged on C's solution: :func:`_leave_out` judges
    those still aside there)."""
    for tr in d.trials:
        if tr.set_aside is None:
            continue
        full, aside = tr.set_aside
        back = _predicted_fit(tr, full, aside)
        if not back.any():
            continue
        _take_spot_records(tr, full, np.flatnonzero(back))
        tr.set_aside = (full, aside & ~back)
        _use_all_but(tr, full, aside & ~back)


def _leave_outliers(d: _Lockstep) -> None:
    """Observations far beyond the noise (gross outliers: a wrong dot, a reflection taken for a
    spot) left out and C run again (C3), so that none is spread over good ones (:func:`_leave_out`)."""
    for i in d.every:

        def rerun(pass_loss, scale, i=i):
            spec = PASS_C3
            if pass_loss:
                name = f"C3: joint (Cauchy loss at {scale:.3g} px, to find the outliers)"
                spec = dataclasses.replace(PASS_C3, name=name, loss=pass_loss)
            d.solve(spec, [i], scale)

        _leave_out(
            d.trials[i],
            lambda i=i: d.other_starts([i], turned_only=False, pass_loss="cauchy"),
            rerun,
            find=d.loss != "linear",
        )


def _turn_misfits(d: _Lockstep, rounds: int = 3) -> None:
    """A pose carried after B from a board still wrong then may be wrong yet: where a board fits
    badly the other starts again, and C again (C2) where a board turned, until none turns (at
    most ``rounds`` times)."""
    again = [i for i in d.every if _misfit_boards(d.trials[i], d.loss)]
    for _ in range(rounds):
        again = d.other_starts(again, turned_only=True)
        if not again:
            break
        d.solve(PASS_C2, again)


@dataclass(frozen=True)
class Step:
    """One step of :data:`SCHEDULE`: what it does, the function that does it over the trials, and
    the parameter block whose freezing skips it (None: it always runs)."""

    does: str
    run: Callable[[_Lockstep], None]
    unless_frozen: str | None = None


# :func:`calibrate`'s schedule after the staged start, in order.  C keeps every kind at weight 1:
# weighting each by its own noise (the rim's is larger in rendered images) made the lasers worse
# from images (benchmarks/images_vs_file.py), where the dots' errors are mostly systematic.
SCHEDULE: tuple[Step, ...] = (
    Step("A: camera, mirror and poses, the lasers held and the spots unweighted", _first_pass),
    Step("the boards' flips decided again; A2 where any turned", _reflip, "poses"),
    Step("the lasers refitted on that geometry, their spots relabelled", _refit_lasers, "lasers"),
    Step("B: everything", lambda d: d.solve(PASS_B, d.every)),
    Step("B2: B from lasers aimed through their spots, kept where better", lambda d: d.aimed_starts(d.every), "lasers"),
    Step("the loss scale re-estimated", _rescale),
    Step("every board's other starts, swapped in where better", lambda d: d.other_starts(d.every, False), "poses"),
    Step("the spots set aside by their lines that fit now readmitted", _readmit_set_aside),
    Step("C: the final pass", lambda d: d.solve(PASS_C, d.every)),
    Step("C3: the gross outliers left out, C again", _leave_outliers),
    Step("C2: badly fitting boards' other starts, C again where one turned", _turn_misfits, "poses"),
)


def _calibrate_lockstep(
    obs_list, camera, freeze, loss, loss_scale, max_steps, solver, bar=None, mirror=None, estimate=()
):
    """:func:`calibrate`'s :data:`SCHEDULE` for every observation set in step; ``solver`` runs a pass's solves."""
    freeze = set(freeze)
    trials = [
        _Trial(o, camera, freeze, time.perf_counter(), fine=solver is _solve_vmap, mirror=mirror, estimate=estimate)
        for o in obs_list
    ]
    d = _Lockstep(trials, solver, freeze, loss, loss_scale, max_steps, bar)
    for step in SCHEDULE:
        if step.unless_frozen not in freeze:
            step.run(d)
    return [d.result(tr) for tr in trials]


def _restore_spots(params: Params, model, cur: Packed, obs: Observations, left) -> tuple[set, Packed]:
    """The spots of ``obs`` that ``cur`` lacks or carries under another label (the free solve
    relabelled or left them out) whose own label fits at the rigid solution ``params``: within
    :data:`OUTLIER_SIGMAS` of the spots' noise (at least :data:`MIN_OUTLIER_PX`).

    Under free board poses a board seen by a few dots (a row of four) is placed as much by its
    spots as by its dots, and a spot of its own laser can look like another's; the box places
    that board from its other walls, so the decision is taken again with that evidence.
    Returns the ``(view name, spot index)`` of each spot restored and the problem with them."""
    n_d, n_s = int(cur.counts[Kind.DOT]), int(cur.counts[Kind.SPOT])
    if n_s and not cur.spot_src:
        return set(), cur  # no record of which input spot each row is
    index = {src: i for i, src in enumerate(cur.spot_src)}
    # boards placed by the box only: a pose of its own (outside the box, or with too few dots
    # to be placed) says nothing new about a spot on it
    pose_of = {key: k for k, key in enumerate(cur.pose_keys) if k not in left and k not in model.outside}
    labels = np.asarray(cur.spot_laser)[:n_s]
    cand = []  # (row of cur or None, view, spot index, pose, own label, pixel)
    for v, view in enumerate(obs.views):
        for j, s in enumerate(view.spots):
            if s.board is None or (v, s.board) not in pose_of or not 0 <= s.laser < obs.n_lasers:
                continue
            i = index.get((v, j))
            if i is None or labels[i] != s.laser:
                cand.append((i, v, j, pose_of[(v, s.board)], s.laser, np.asarray(s.pixel, float)))
    if not cand:
        return set(), cur
    pr = model.packed(cur)
    sig = _sigmas_of(*_per_observation(params, pr))[Kind.SPOT]
    limit = max(OUTLIER_SIGMAS * sig, MIN_OUTLIER_PX) if np.isfinite(sig) else MIN_OUTLIER_PX
    norm, ok = _probe_at(
        params,
        pr,
        Kind.SPOT,
        spot_pose=np.asarray([c[3] for c in cand], np.int64),
        spot_laser=np.asarray([c[4] for c in cand], np.int64),
        spot_pixels=np.stack([c[5] for c in cand]),
    )
    fits = [c for c, good in zip(cand, ok & (norm <= limit), strict=True) if good]
    if not fits:
        return set(), cur
    own = labels.copy()
    for c in fits:
        if c[0] is not None:
            own[c[0]] = c[4]
    out = cur.select(np.ones(n_d, bool), np.ones(n_s, bool), own)
    back = [c for c in fits if c[0] is None]  # spots the free solve left out: appended
    if back:
        out = dataclasses.replace(
            out,
            spot_pose=np.concatenate([out.spot_pose, [c[3] for c in back]]).astype(np.int64),
            spot_laser=np.concatenate([out.spot_laser, [c[4] for c in back]]).astype(np.int64),
            spot_pixels=np.concatenate([out.spot_pixels, np.stack([c[5] for c in back])]),
            spot_src=tuple(out.spot_src) + tuple((c[1], c[2]) for c in back),
            counts=np.asarray(out.counts) + np.array([0, len(back), 0, 0]),
        )
    return {(obs.views[c[1]].name, c[2]) for c in fits}, out


def _rigid_refine(res: CalibrationResult, obs: Observations, group: list[str], max_steps: int) -> CalibrationResult:
    """Pass R: the free solution ``res`` refined under the rigid box model (:mod:`slcvjax.calibration.rigid`) of
    the boards ``group``; a board pose whose dots' median residual exceeds
    :data:`slcvjax.calibration.rigid.MISFIT_SIGMAS` noise sigmas (and
    :data:`slcvjax.calibration.rigid.MISFIT_MIN_PX`) does not fit the box: its dots and spots are
    left out (recorded in the repairs) and R runs again.  Once no board misfits, the spots
    the free solve relabelled or left out are judged again at R's solution
    (:func:`_restore_spots`): those whose own label fits come back with it (their repairs
    dropped, ``box["spots_restored"]`` naming them) and R runs again.

    The result's board poses are the box's (every board pose of the box, the left-out ones
    included, at ``T_cam_box @ T_box_board``), its covariance the rig's block of the rigid
    model's, and ``box`` holds the boards' poses in the box with their std."""
    t0 = time.perf_counter()
    pk = res.packed
    n_d = int(pk.counts[Kind.DOT])
    dots_per_pose = np.bincount(np.asarray(pk.dot_pose)[:n_d], minlength=pk.n_poses)
    model = box_model(pk, group, usable=np.flatnonzero(dots_per_pose >= MIN_BOARD_DOTS))
    params = rigid_params(model, pk.pose_keys, unstack_poses(res.params.poses), res.rig, res.params.chess)
    masks = rigid_masks(model, res.masks, pk.n_poses)
    passes, repairs = list(res.passes), list(res.repairs)
    left: list[int] = []
    cur = pk
    reexamined, restored_names, misfit_rounds = False, [], 0
    while True:
        pr = model.packed(cur)
        layout, p, arr, m = pad_problem(params, pr, masks)
        out = _solve(p, arr, m, res.loss, res.scale, max_steps, _RTOL_FINAL)
        params = unpad_params(layout, out.params)
        name = "R: rigid box" + (f" (after leaving out {len(left)} board pose(s))" if left else "")
        if restored_names:
            name += f" ({len(restored_names)} spot(s) back with their own labels)"
        passes.append(
            JointPass(
                name,
                int(out.steps),
                float(out.initial_cost),
                float(out.cost),
                float(res.scale),
                Outcome(int(out.result)),
            )
        )
        norm, kind, ok = _per_observation(params, pr)
        n_d = int(cur.counts[Kind.DOT])
        pose_d = np.asarray(cur.dot_pose)[:n_d]
        dot_norm = np.where(ok[:n_d], norm[:n_d], np.inf)
        limit = max(MISFIT_SIGMAS * _robust_sigma_of(norm, kind, ok), MISFIT_MIN_PX)
        medians = {int(k): float(np.median(dot_norm[pose_d == k])) for k in np.unique(pose_d)}
        new = [k for k, m in medians.items() if m > limit and k not in model.outside]
        if not new and not reexamined:
            # the spots the free solve relabelled or left out, judged again under the box
            reexamined = True
            restored, cur_new = _restore_spots(params, model, cur, obs, left)
            if restored:
                repairs = [r for r in repairs if not (r["kind"] == "spot" and (r["view"], r["index"]) in restored)]
                restored_names += sorted(restored)
                cur = cur_new
                continue
        if not new or misfit_rounds == MISFIT_ROUNDS:
            break
        misfit_rounds += 1
        for k in new:
            v, b = pk.pose_keys[k]
            repairs.append(
                {
                    "kind": "board",
                    "view": obs.views[v].name,
                    "board": b,
                    "index": -1,
                    "action": "left out",
                    "residual_px": medians[k],
                    "reason": f"does not fit the rigid box: its dots' median residual {medians[k]:.3g} px "
                    f"beyond {limit:.3g} px ({MISFIT_SIGMAS:g} sigma, at least {MISFIT_MIN_PX:g} px)",
                    "whole_board": True,
                }
            )
        left += new
        n_s = int(cur.counts[Kind.SPOT])
        cur = cur.select(~np.isin(pose_d, left), ~np.isin(np.asarray(cur.spot_pose)[:n_s], left))
    # linearised again at the solution: the rim rows normalised there, as the free covariance is
    layout, lin, parts = _kind_linearisations(params, model.packed(cur), masks, res.loss, res.scale)
    pooled = _covariance_of_linearisation(lin, pad_masks(layout, masks), None)
    pooled = _unpad_covariance(layout, pooled)
    # the rig's covariance with each kind's own noise; the boards' poses (in the box and per
    # view, which need the box's cross covariances) with the pooled sigma
    cov, noise = _sandwich_of(layout, lin, parts, masks)
    pose_cov = board_pose_covariances(model, params, lin, masks, pooled, layout)
    g = res.rig.tangent_dim
    glob = np.asarray(pooled.glob)
    cov_out = Covariance(
        np.asarray(cov.glob)[:g, :g],
        np.concatenate([pose_cov, np.asarray(pooled.blocks)[model.n_blocks :]]),
        cov.sigma,
        cov.dof,
    )
    out_params = Params(params.rig, board_poses_of(model, params), params.chess)
    std = box_pose_std(params, glob, model)
    box_poses = {model.gauge: Pose(np.eye(3), np.zeros(3))} | {
        b: Pose(np.asarray(params.box.R)[i], np.asarray(params.box.t)[i]) for i, b in enumerate(model.boards)
    }
    box = {
        "gauge": model.gauge,
        "boards": {b: {"pose": box_poses[b], **std[b]} for b in (model.gauge, *model.boards)},
        "views": len(model.views),
        "free_board_poses": len(model.outside),
        "left_out": [{"view": obs.views[pk.pose_keys[k][0]].name, "board": pk.pose_keys[k][1]} for k in left],
        "spots_restored": [{"view": v, "index": j} for v, j in restored_names],
        "notes": list(model.notes),
    }
    timings = dict(res.timings)
    timings["rigid_s"] = time.perf_counter() - t0
    timings["total_s"] = timings.get("total_s", 0.0) + timings["rigid_s"]
    return dataclasses.replace(
        res,
        params=out_params,
        packed=cur,
        cov=cov_out,
        passes=passes,
        repairs=repairs,
        timings=timings,
        kind_sigma=dict(zip(KIND_NAMES, noise.sigma.tolist(), strict=True)),
        box=box,
    )


OUTLIER_SIGMAS = 5.0  # a dot or spot with a residual beyond this many sigmas of its kind is left out,
MIN_OUTLIER_PX = 1.0  # ... and beyond this (a gross error, not a detector's sub-pixel bias)
MIN_BOARD_DOTS = 4  # a board pose with fewer dots than this left is left out whole
CAUCHY_WIDEN = 10.0  # the first outlier-finding pass's Cauchy scale, in loss scales


def _dot_source(tr: "_Trial", i: int, pk: Packed) -> dict:
    """Dot row ``i`` of ``pk`` as the report names it."""
    if not pk.dot_src:
        return {"kind": "dot", "view": None, "index": -1, "board": ""}
    v, b, j = pk.dot_src[i]
    return {"kind": "dot", "view": tr.obs.views[v].name, "index": j, "board": b}


def _spot_source(tr: "_Trial", i: int, pk: Packed | None = None) -> dict:
    """Spot row ``i`` of ``pk`` (the trial's problem by default) as the report names it."""
    pk = tr.pk if pk is None else pk
    if not pk.spot_src:
        return {"kind": "spot", "view": None, "index": -1, "board": None}
    v, j = pk.spot_src[i]
    return {"kind": "spot", "view": tr.obs.views[v].name, "index": j, "board": tr.obs.views[v].spots[j].board}


def _relabel_spots(tr: "_Trial", fit) -> None:
    """Give the trial's spots the labels of :func:`slcvjax.calibration.staged.fit_lasers` (another laser, or
    left out), recording each change in ``tr.repairs``."""
    own = np.asarray(tr.pk.spot_laser)[: fit.labels.shape[0]]
    changed = np.flatnonzero(fit.labels != own)
    if not changed.size:
        return
    for i in changed:
        new = int(fit.labels[i])
        r_own = fit.residual[i, own[i]]
        item = _spot_source(tr, i) | {
            "action": "relabelled" if new >= 0 else "left out",
            "laser": int(own[i]),
            "residual_px": float(r_own) if np.isfinite(r_own) else None,
        }
        if new >= 0:
            item |= {"new_laser": new, "new_residual_px": float(fit.residual[i, new])}
            item["reason"] = f"lies on laser {new}'s line, not on its own (threshold {fit.threshold:.3g} px)"
        elif fit.undetermined[own[i]]:
            item["reason"] = f"laser {own[i]} is undetermined: its spots cannot fix a line"
        else:
            item["reason"] = f"lies on no laser's line, or on more than one (threshold {fit.threshold:.3g} px)"
        tr.repairs.append(item)
    n_d, keep = int(tr.pk.counts[Kind.DOT]), fit.labels >= 0
    every = tr.pk.select(np.ones(n_d, bool), np.ones(keep.size, bool), np.where(keep, fit.labels, own))
    tr.set_aside = (every, np.concatenate([np.zeros(n_d, bool), ~keep]))
    tr.use(every.select(np.ones(n_d, bool), keep))


def _outliers(tr: "_Trial", pk: Packed) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Which dots and spots of ``pk`` lie beyond :data:`OUTLIER_SIGMAS` sigmas of their kind (and
    beyond :data:`MIN_OUTLIER_PX`) at the trial's solution (each kind's sigma from the median
    residual of the observations the trial keeps, corrected for the degrees of freedom), or
    whose prediction is not valid (off the mirror or the sensor), with every observation's
    residual norm and kind, the thresholds (px) per kind and the validity."""
    norm, kind, ok = _per_observation(tr.params, pk)
    # the sigmas of what the trial keeps: this table where ``pk`` is that problem
    sig = _sigmas_of(norm, kind, ok) if pk is tr.pk else kind_sigmas(tr.params, tr.pk)
    n_d, n_s = int(pk.counts[Kind.DOT]), int(pk.counts[Kind.SPOT])
    bad = np.zeros(n_d + n_s, bool)
    # the residuals are smaller than the noise by the parameters they fix: the dots the board
    # poses (6 each), the spots the lasers (4 each); the median's sigma is scaled back up
    kept_d, kept_s = int(tr.pk.counts[Kind.DOT]), int(tr.pk.counts[Kind.SPOT])
    sig[Kind.DOT] *= np.sqrt(2 * kept_d / max(2 * kept_d - 6 * tr.pk.n_poses, 1))
    sig[Kind.SPOT] *= np.sqrt(2 * kept_s / max(2 * kept_s - 4 * tr.obs.n_lasers, 1))
    limit = np.maximum(OUTLIER_SIGMAS * sig, MIN_OUTLIER_PX)
    for k in (Kind.DOT, Kind.SPOT):
        if np.isfinite(sig[k]):
            bad |= (ok & (kind == k) & (norm > limit[k]))[: n_d + n_s]
    bad |= ~ok[: n_d + n_s]  # predicted off the mirror or the sensor: out of the model's reach
    return bad, norm, kind, limit, ok


def _leave_out(tr: "_Trial", starts, rerun, rounds: int = 3, find: bool = True) -> None:
    """Leave out the trial's gross outliers: the dots and spots beyond :data:`OUTLIER_SIGMAS`
    sigmas (:func:`_outliers`).  Where there are any, the final pass runs first with the
    redescending Cauchy loss (``rerun("cauchy", scale)``, first at :data:`CAUCHY_WIDEN` times the
    loss scale, then at it), under which a gross outlier no longer drags
    its board's pose, so that the outliers found then are the wrong observations, not the good
    ones of a dragged board (and every board tries its other starts under that loss,
    ``starts()``: a board whose own dots are a third wrong is found again from its neighbours);
    those are left out and the final pass runs again with the
    calibration's loss (``rerun(None, scale)``); observations left out that fit the new solution come
    back, until the set left out stays the same (at most ``rounds`` times).  A board left with
    fewer than :data:`MIN_BOARD_DOTS` dots is left out whole (its pose is not determined).
    Spots set aside earlier by their lines (``tr.set_aside``) are predictions at this geometry,
    not fitted residuals: those predicted near their line (:func:`_predicted_fit`) come back
    and are judged with the rest (a board pose wrong when the lines were fitted made them look
    wrong), before the outliers are looked for and again once they are out (:func:`_bring_back`).  What stays
    left out is recorded in ``tr.repairs``.  ``find=False`` (the linear loss: a plain least-squares
    fit) looks for no outlier; only the spots set aside by their lines are judged again."""
    scale = tr.scale
    none_aside = np.zeros(int(tr.pk.counts[Kind.DOT]) + int(tr.pk.counts[Kind.SPOT]), bool)
    full, aside = tr.set_aside if tr.set_aside is not None else (tr.pk, none_aside)
    out = aside & ~_predicted_fit(tr, full, aside)
    if not np.array_equal(out, aside):
        _use_all_but(tr, full, out)
        rerun(None, scale)
    whole = np.zeros_like(out)
    if find and not np.array_equal(_outliers(tr, full)[0], out):  # more than what stays set aside
        out, whole = _robust_rounds(tr, full, out, starts, rerun, scale, rounds)
    _readmit(tr, full, aside, out)
    if not out.any():
        return
    # the residuals that left them out, for the records
    _, norm, kind, limit, valid = _outliers(tr, full)
    full, out = _bring_back(tr, full, aside, out, whole, rerun, scale)
    n_d = int(full.counts[Kind.DOT])
    for i in np.flatnonzero(out & ~aside):  # those set aside and still out have their record
        if i < n_d:
            item = _dot_source(tr, i, full)
        else:
            src = _spot_source(tr, i - n_d, full)
            item = src | {"laser": int(np.asarray(full.spot_laser)[i - n_d])}
        k = int(kind[i])
        if whole[i]:
            why = f"its board's pose in this view is not determined: fewer than {MIN_BOARD_DOTS} of its dots agree"
        elif not valid[i]:
            why = "its prediction falls off the mirror or the sensor (out of the model's reach)"
        else:
            why = f"residual {norm[i]:.3g} px beyond {limit[k]:.3g} px ({OUTLIER_SIGMAS:g} sigma of the "
            why += f"{KIND_NAMES[k]}s, at least {MIN_OUTLIER_PX:g} px)"
        tr.repairs.append(
            item
            | {"action": "left out", "residual_px": float(norm[i]) if valid[i] and not whole[i] else None}
            | {"reason": why}
            | ({"whole_board": True} if whole[i] else {})
        )


def _use_all_but(tr: "_Trial", full: Packed, out: np.ndarray) -> None:
    """The trial solves ``full`` without the rows where ``out`` holds (dots, then spots)."""
    n_d = int(full.counts[Kind.DOT])
    tr.use(full.select(~out[:n_d], ~out[n_d:]))


def _predicted_fit(tr: "_Trial", full: Packed, rows: np.ndarray) -> np.ndarray:
    """Where ``rows`` holds: the observation of ``full`` is predicted, at the trial's solution,
    within :data:`CONSENSUS_PX` (elsewhere False).  A left-out spot's residual is a prediction,
    which the spot's own weight would shrink: a laser with few spots predicts a good one several
    noise sigmas off, so it is judged as the lines' consensus judges a spot, then refitted."""
    if not rows.any():
        return np.zeros_like(rows)
    n = rows.size
    norm, _, valid = _per_observation(tr.params, full)
    return rows & valid[:n] & (norm[:n] <= CONSENSUS_PX)


def _robust_rounds(tr: "_Trial", full: Packed, out, starts, rerun, scale: float, rounds: int):
    """The outliers of ``full`` found under the Cauchy loss, left out, and the final pass run
    again on the rest until the set stays the same (see :func:`_leave_out`); ``out``: the rows
    left out so far.  Returns the rows left out and those of boards left out whole."""
    n_d = int(full.counts[Kind.DOT])
    # graduated: at a wide scale first, where the good observations of a dragged board still
    # pull (at the final scale they may already count as outliers: a local minimum)
    rerun("cauchy", CAUCHY_WIDEN * scale)
    rerun("cauchy", scale)
    starts()
    rerun("cauchy", scale)
    ran = False  # the final pass run again with the calibration's loss on what is kept
    whole = np.zeros_like(out)
    for _ in range(rounds):
        bad = _outliers(tr, full)[0]
        # a board with too few dots left: every dot and spot of it out
        pose_d, pose_s = np.asarray(full.dot_pose)[:n_d], np.asarray(full.spot_pose)[: len(out) - n_d]
        kept = np.bincount(pose_d[~bad[:n_d]], minlength=full.n_poses)
        weak = (kept < MIN_BOARD_DOTS) & (np.bincount(pose_d, minlength=full.n_poses) >= MIN_BOARD_DOTS)
        whole = np.concatenate([weak[pose_d], weak[pose_s]])
        bad |= whole
        if ran and np.array_equal(bad, out):
            break
        out = bad
        _use_all_but(tr, full, out)
        rerun(None, scale)
        ran = True
    return out, whole


def _bring_back(tr: "_Trial", full: Packed, aside, out, whole, rerun, scale: float) -> tuple[Packed, np.ndarray]:
    """Observations left out that fit once the outliers are gone come back: a dot that lies on
    another grid position of its board (one not seen in that view) with that position, a spot
    that lies on exactly one other laser's line (within :data:`CONSENSUS_PX`, as the consensus
    looks for it: a left-out spot's residual is a prediction) with that laser, and a spot set
    aside by its lines that its own line now predicts (:func:`_predicted_fit`).  The spots are
    kept only if they fit once refitted.  Records the changes; returns the problem (with the
    new labels) and the rows still left out."""
    n_d, n_s = int(full.counts[Kind.DOT]), int(full.counts[Kind.SPOT])
    _, norm, _, limit, valid = _outliers(tr, full)
    cand = out & ~whole
    own = _predicted_fit(tr, full, cand & aside)
    moved = _regrid(tr, full, cand, limit[0])
    lasers = {i: k for i, k in _relaser(tr, full, cand, CONSENSUS_PX).items() if not own[i]}
    if not (moved or lasers or own.any()):
        return full, out
    old_full, old_labels = full, np.asarray(full.spot_laser)[:n_s]
    labels = old_labels.copy()
    for i, k in lasers.items():
        labels[i - n_d] = k
    full = _with_dot_labels(full, tr.obs, moved).select(np.ones(n_d, bool), np.ones(n_s, bool), labels)
    out = out & ~own
    out[list(moved) + list(lasers)] = False
    _use_all_but(tr, full, out)
    rerun(None, scale)
    still_bad = _outliers(tr, full)[0]
    misfit = [i for i in lasers if still_bad[i]]
    if misfit or (own & still_bad).any():  # still beyond the noise: out again, with its own label
        for i in misfit:
            labels[i - n_d] = old_labels[i - n_d]
            del lasers[i]
        full = full.select(np.ones(n_d, bool), np.ones(n_s, bool), labels)
        out[misfit] = True
        out |= own & still_bad
        _use_all_but(tr, full, out)
        rerun(None, scale)
    _take_spot_records(tr, full, np.flatnonzero(own & ~out))
    norm_new = _per_observation(tr.params, full)[0]
    for i, k in moved.items():
        tr.repairs.append(
            _dot_source(tr, i, old_full)
            | {"action": "relabelled", "new_index": k, "residual_px": float(norm[i]) if valid[i] else None}
            | {"new_residual_px": float(norm_new[i])}
            | {"reason": f"lies on grid position {k} of its board (not seen otherwise), not on its own"}
        )
    for i, k in lasers.items():
        # its residual under its own label: now, else where the lines set it aside
        before = [r.get("residual_px") for r in _take_spot_records(tr, full, [i])]
        tr.repairs.append(
            _spot_source(tr, i - n_d, full)
            | {"action": "relabelled", "laser": int(old_labels[i - n_d])}
            | {"residual_px": float(norm[i]) if valid[i] else (before[0] if before else None)}
            | {"new_laser": k, "new_residual_px": float(norm_new[i])}
            | {"reason": f"lies on laser {k}'s line at the final geometry, not on its own"}
        )
    return full, out


def _take_spot_records(tr: "_Trial", full: Packed, rows) -> list[dict]:
    """Remove from ``tr.repairs`` the records of the spots in ``rows`` of ``full`` (counted
    after the dots) and return them."""
    n_d = int(full.counts[Kind.DOT])
    keys = {(src["view"], src["index"]) for src in (_spot_source(tr, i - n_d, full) for i in rows)}
    mine = [r["kind"] == "spot" and (r["view"], r["index"]) in keys for r in tr.repairs]
    taken = [r for r, m in zip(tr.repairs, mine, strict=True) if m]
    tr.repairs = [r for r, m in zip(tr.repairs, mine, strict=True) if not m]
    return taken


def _readmit(tr: "_Trial", full: Packed, aside: np.ndarray, out: np.ndarray) -> None:
    """Drop the records of the spots set aside by their lines that are no longer left out."""
    _take_spot_records(tr, full, np.flatnonzero(aside & ~out))


def _probe(tr: "_Trial", kind: Kind, **rows) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_probe_at` the trial's solution and problem."""
    return _probe_at(tr.params, tr.pk, kind, **rows)


def _probe_at(params: Params, pk: Packed, kind: Kind, **rows) -> tuple[np.ndarray, np.ndarray]:
    """Residual norms (px) and validity, at ``params``, of candidate rows of one kind (dots or
    spots; ``rows``: that kind's arrays, of one length) put in place of ``pk``'s own rows of that
    kind: how candidate labels are tried."""
    c = np.asarray(pk.counts).copy()
    c[kind] = len(next(iter(rows.values())))
    probe = dataclasses.replace(pk, counts=c, **{("dot_src", "spot_src")[kind]: ()}, **rows)
    norm, _, ok = _per_observation(params, probe)
    first = int(c[Kind.DOT]) if kind == Kind.SPOT else 0
    return norm[first : first + int(c[kind])], ok[first : first + int(c[kind])]


def _relaser(tr: "_Trial", full: Packed, candidates: np.ndarray, limit: float) -> dict[int, int]:
    """For the spot rows of ``full`` where ``candidates`` holds: the one other laser whose spot on
    the row's board, at the trial's solution, lies within ``limit`` px of its pixel (row, counted
    after the dots, -> laser); rows with none or several are not listed."""
    n_d, n_s = int(full.counts[Kind.DOT]), int(full.counts[Kind.SPOT])
    rows = np.flatnonzero(candidates[n_d : n_d + n_s])
    if not rows.size or tr.obs.n_lasers < 2:
        return {}
    own = np.asarray(full.spot_laser)[:n_s]
    cand = [(j, k) for j in rows for k in range(tr.obs.n_lasers) if k != own[j]]
    norm, ok = _probe(
        tr,
        Kind.SPOT,
        spot_pose=np.asarray([full.spot_pose[j] for j, _ in cand], np.int64),
        spot_laser=np.asarray([k for _, k in cand], np.int64),
        spot_pixels=np.asarray([full.spot_pixels[j] for j, _ in cand], float),
    )
    near = ok & (norm <= limit)
    out = {}
    for j in rows:
        hits = [k for m, (jj, k) in enumerate(cand) if jj == j and near[m]]
        if len(hits) == 1:
            out[n_d + int(j)] = hits[0]
    return out


def _regrid(tr: "_Trial", full: Packed, candidates: np.ndarray, limit: float) -> dict[int, int]:
    """For the dot rows of ``full`` where ``candidates`` holds: the one grid position of its
    board, not seen in its view, whose projection at the trial's solution lies within ``limit``
    px of its pixel (row -> position index); rows with none or several are not listed."""
    n_d = int(full.counts[Kind.DOT])
    rows = [i for i in np.flatnonzero(candidates[:n_d])]
    if not rows or not full.dot_src:
        return {}
    seen: dict[tuple[int, str], set[int]] = {}
    for i, (v, b, j) in enumerate(full.dot_src):
        if not candidates[i]:
            seen.setdefault((v, b), set()).add(j)
    cand_row, cand_k, pose, pts, pix = [], [], [], [], []
    for i in rows:
        v, b, j = full.dot_src[i]
        grid = tr.obs.boards[b]
        for k in range(grid.shape[0]):
            if k != j and k not in seen.get((v, b), ()):
                cand_row.append(i), cand_k.append(k), pose.append(full.dot_pose[i])
                pts.append(grid[k]), pix.append(full.dot_pixels[i])
    if not cand_row or len(cand_row) > 4 * n_d:
        return {}
    norm, ok = _probe(
        tr,
        Kind.DOT,
        dot_pose=np.asarray(pose, np.int64),
        dot_points=np.asarray(pts, float),
        dot_pixels=np.asarray(pix, float),
    )
    near = ok & (norm <= limit)
    out = {}
    for i in rows:
        hits = [cand_k[m] for m in np.flatnonzero(near) if cand_row[m] == i]
        if len(hits) == 1:
            out[i] = hits[0]
    # two dots given one position: neither
    taken = [(full.dot_src[i][0], full.dot_src[i][1], k) for i, k in out.items()]
    return {i: k for (i, k), t in zip(out.items(), taken, strict=True) if taken.count(t) == 1}


def _with_dot_labels(pk: Packed, obs: Observations, moved: dict[int, int]) -> Packed:
    """``pk`` with dot row ``i`` labelled as grid position ``moved[i]`` of its board."""
    pts, src = np.array(pk.dot_points, float), list(pk.dot_src)
    for i, k in moved.items():
        v, b, _ = src[i]
        pts[i], src[i] = obs.boards[b][k], (v, b, k)
    return dataclasses.replace(pk, dot_points=pts, dot_src=tuple(src))


def _job(tr: "_Trial", params: Params, spec: PassSpec, masks: Masks | None = None) -> SolveJob:
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


# the other starts of the boards' poses (:func:`_candidates`, each with its own masks)
_TWIN_SOLVE = PassSpec("other starts", rtol=_RTOL_TWIN)


def _record(tr: "_Trial", name: str, res, limit: int | None, note: str = "") -> None:
    """Add the pass ``name``'s solve ``res`` to the trial's passes (``limit``: the pass's own step limit;
    ``note``: what followed it)."""
    tr.passes.append(
        JointPass(
            name,
            int(res.steps),
            float(res.initial_cost),
            float(res.cost),
            float(tr.scale),
            Outcome(int(res.result)),
            limit,
            [note] if note else [],
        )
    )


def _twin(params: Params, arr: Packed, masks: Masks) -> tuple[Params, Masks]:
    """Every board pose's flipped twin, and the masks that refine the twins with the rig held."""
    R, t = np.asarray(params.poses.R), np.asarray(params.poses.t)
    n_p = R.shape[0]
    xb = np.zeros((n_p, 1, 3))
    dp, pts = np.asarray(arr.dot_pose), np.asarray(arr.dot_points)
    for k in range(n_p):
        if np.any(dp == k):
            xb[k, 0] = pts[dp == k].mean(axis=0)
    R2, t2 = _flipped(R, t, xb, np.ones((n_p, 1)))
    twin = Params(params.rig, Pose(R2, t2), params.chess)
    return twin, _hold_rig(params, masks)


def _carried(params: Params, pk: Packed, masks: Masks) -> tuple[Params, Masks]:
    """Every board pose carried over rigidly from another view, and the masks that refine them.

    Pose ``(v, b)`` becomes ``T_a(v) T_a(v0)^-1 T_b(v0)``: board ``a`` of view ``v`` and
    view ``v0 != v`` chosen so that the fewest dots of ``a`` in ``v`` and of ``a`` and
    ``b`` in ``v0`` is largest.  Poses with no such pair are kept.
    """
    R, t = np.asarray(params.poses.R), np.asarray(params.poses.t)
    keys = pk.pose_keys
    n_p = len(keys)
    n_dots = np.bincount(np.asarray(pk.dot_pose), minlength=n_p)
    by_view: dict[int, dict[str, int]] = {}
    for k, (v, b) in enumerate(keys):
        by_view.setdefault(v, {})[b] = k
    R2, t2 = R.copy(), t.copy()
    for k, (v, b) in enumerate(keys):
        # the neighbour seen by the most dots, and the other view where it and b are best seen
        best = (0, -1, -1, -1)  # (fewer dots of the pair in view v0, pose a in v, a in v0, b in v0)
        for a, ka in by_view[v].items():
            if a == b:
                continue
            for v0, boards in by_view.items():
                if v0 != v and a in boards and b in boards:
                    m = min(n_dots[ka], n_dots[boards[a]], n_dots[boards[b]])
                    if m > best[0]:
                        best = (m, ka, boards[a], boards[b])
        _, ka, ka0, kb0 = best
        if ka >= 0:  # T_b(v) = T_a(v) T_a(v0)^-1 T_b(v0)
            r_ab = R[ka0].T @ R[kb0]
            t_ab = R[ka0].T @ (t[kb0] - t[ka0])
            R2[k], t2[k] = R[ka] @ r_ab, R[ka] @ t_ab + t[ka]
    carried = Params(params.rig, Pose(R2, t2), params.chess)
    return carried, _hold_rig(params, masks)


def _misfit_boards(tr: "_Trial", loss: str) -> int:
    """How many board poses of a calibration fit badly: a mean robust cost per dot and spot
    above ``scale^2`` (with the Huber loss, a pixel error of 1.5 scales = 4.5 sigma on average;
    a fitting one costs about ``sigma^2 = scale^2 / 9``)."""
    n_p = tr.pk.n_poses
    cost = _block_costs(tr.params, tr.pk, loss, tr.scale)[:n_p]
    n = np.bincount(np.asarray(tr.pk.dot_pose), minlength=n_p) + np.bincount(np.asarray(tr.pk.spot_pose), minlength=n_p)
    return int(np.sum(cost > tr.scale**2 * np.maximum(n, 1)))


def _hold_rig(params: Params, masks: Masks) -> Masks:
    """Masks that refine the board poses alone."""
    n_p = params.poses.t.shape[0]
    blocks = np.asarray(masks.blocks)
    return Masks(
        np.zeros_like(np.asarray(masks.glob)), np.concatenate([blocks[:n_p], np.zeros(params.chess.t.shape[0])])
    )


def _candidates(params: Params, pk: Packed, masks: Masks) -> list[tuple[Params, Masks]]:
    """Other starts for every board pose, each with its masks: the flipped twin, the carried pose."""
    return [_twin(params, pk, masks), _carried(params, pk, masks)]


def _keep_better(
    params: Params, other: Params, pk: Packed, loss: str, scale: float, turned_only: bool = False
) -> tuple[Params, int]:
    """``params`` with each board pose whose refined other start fits better swapped (``turned_only``:
    only those turned by it); how many turned."""
    n_p = params.poses.t.shape[0]
    c_now = _block_costs(params, pk, loss, scale)[:n_p]
    c_other = _block_costs(other, pk, loss, scale)[:n_p]
    better = c_other < c_now - 1e-9
    if turned_only:
        better &= _turned(other.poses, params.poses)
    if not better.any():
        return params, 0
    poses = Pose(
        np.where(better[:, None, None], np.asarray(other.poses.R), np.asarray(params.poses.R)),
        np.where(better[:, None], np.asarray(other.poses.t), np.asarray(params.poses.t)),
    )
    return Params(params.rig, poses, params.chess), int(np.sum(better & _turned(other.poses, params.poses)))


def _turned(a: Pose, b: Pose, degrees: float = 10.0) -> np.ndarray:
    """Per stacked pose: whether the board normals of ``a`` and ``b`` differ by more than ``degrees``."""
    cos = np.sum(np.asarray(a.R)[:, :, 2] * np.asarray(b.R)[:, :, 2], axis=1)
    return cos < np.cos(np.radians(degrees))


# ----------------------------------------------------------------------------- lasers at their working range


def laser_working_points(rig: Rig, poses: Pose, pk: Packed) -> np.ndarray:
    """Per laser, the point of its line nearest the mean of its spots on their boards (mm)."""
    n = rig.lasers.n
    out = np.zeros((n, 3))
    laser_of, pose_of = np.asarray(pk.spot_laser), np.asarray(pk.spot_pose)
    for l_idx in range(n):
        p, d = rig.lasers.points[l_idx], rig.lasers.directions[l_idx]
        pts = [
            np.asarray(line_plane_intersection(p, d, Pose(poses.R[k], poses.t[k]))[0])
            for k in pose_of[laser_of == l_idx]
        ]
        c = np.mean(pts, axis=0) if pts else np.asarray(p)
        pn, dn = np.asarray(p), np.asarray(d)
        out[l_idx] = pn + ((c - pn) @ dn) * dn
    return out


def _laser_offset(lasers: Lasers, i: int, x_ref, delta4):
    """Laser ``i`` moved by ``delta4``: its foot at ``x_ref`` less ``x_ref`` (mm)."""
    return lasers.at_working_point(i, x_ref, delta4)[0] - x_ref


def laser_std(rig: Rig, cov_glob: np.ndarray, x_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per laser: position std (mm) of the line at ``x_ref`` and direction std (rad); NaN for a
    laser whose covariance block is not positive (undetermined)."""
    n = rig.lasers.n
    pos, ang = np.zeros(n), np.zeros(n)
    cov_glob = np.asarray(cov_glob)
    for i in range(n):
        sl = laser_columns(i)
        c = cov_glob[sl, sl]
        j = np.asarray(jax.jacfwd(lambda d, i=i: _laser_offset(rig.lasers, i, jnp.asarray(x_ref[i]), d))(jnp.zeros(4)))
        # a block that is not positive: the data do not determine this laser (NaN, not 0)
        definite = bool(np.all(np.isfinite(c))) and (
            np.linalg.eigvalsh(0.5 * (c + c.T)).min() >= -1e-9 * max(np.abs(c).max(), 1e-300)
        )
        pos[i] = std_of_variance(np.trace(j @ c @ j.T)) if definite else np.nan
        ang[i] = std_of_variance(c[2, 2] + c[3, 3]) if definite else np.nan
    return pos, ang


def laser_errors(est: Rig, truth: Rig, x_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per laser: distance (mm) from the true working point to the estimated line, and angle (rad)."""
    p, d = np.asarray(est.lasers.points), np.asarray(est.lasers.directions)
    v = x_ref - p
    pos = np.linalg.norm(v - np.sum(v * d, axis=1, keepdims=True) * d, axis=1)
    dt = np.asarray(truth.lasers.directions)
    # atan2 keeps full precision near zero, where arccos of a dot product bottoms out at ~1.5e-8 rad
    ang = np.arctan2(np.linalg.norm(np.cross(d, dt), axis=1), np.abs(np.sum(d * dt, axis=1)))
    return pos, ang


def cramer_rao(
    truth: Calibration,
    obs: Observations,
    sigma: "float | Sequence[float]",
    packed: Packed | None = None,
    rigid: "bool | list[str]" = False,
) -> dict:
    """The Cramer-Rao bound of a scene: ``sigma^2 (J^T J)^-1`` at the true parameters; with
    ``sigma`` one per kind (dot, spot, rim, chess corner), ``(sum_k N_k / sigma_k^2)^-1``.

    Returns the covariance and, per laser, the bound's position std at the working
    point (mm) and direction std (rad), with their RMS over lasers.  ``packed``: the
    observations as a calibration packed them (``CalibrationResult.packed``: spots
    detected without a board have the board the staged stage gave them); by default
    ``pack(obs)``, which leaves such spots out.  ``rigid``: the bound of the rigid box
    model (as :func:`calibrate`'s ``rigid``; the truth's board poses must be rigid);
    its covariance is then the rig's block, and ``box_cov`` the whole global block
    (rig, then 6 per box board but the gauge, ``box_model``'s order).
    """
    pk = pack(obs) if packed is None else packed
    poses = stack_poses([truth.board_poses[v][b] for v, b in pk.pose_keys])
    chess = [truth.calibration_view_poses[c] for c in pk.chess_keys] if truth.calibration_view_poses else []
    chess_stack = stack_poses(chess) if chess else Pose(jnp.zeros((0, 3, 3)), jnp.zeros((0, 3)))
    params = Params(truth.rig, poses, chess_stack)
    masks = make_masks(params)
    out = {}
    group = rigid_group(obs, rigid)
    if group:
        model = box_model(pk, group)
        params = rigid_params(model, pk.pose_keys, unstack_poses(poses), truth.rig, chess_stack)
        masks = rigid_masks(model, masks, pk.n_poses)
        pk = model.packed(pk)
    # plain least squares (Huber at 1e9 px), sharing the compiled covariance of calibrate()
    cov = covariance_of(params, pk, masks, "huber", 1e9, sigma=sigma)
    if group:
        g = truth.rig.tangent_dim
        out["box_cov"] = np.asarray(cov.glob)
        out["box_model"] = model
        cov = cov._replace(glob=np.asarray(cov.glob)[:g, :g])
    x_ref = laser_working_points(truth.rig, poses, pk)
    pos, ang = laser_std(truth.rig, np.asarray(cov.glob), x_ref)
    return out | {
        "cov": cov,
        "x_ref": x_ref,
        "position_std_mm": pos,
        "direction_std_rad": ang,
        "position_rms_mm": float(np.sqrt(np.mean(pos**2))),
        "direction_rms_rad": float(np.sqrt(np.mean(ang**2))),
    }


# ----------------------------------------------------------------------------- report and output


def _obs_table(result: CalibrationResult):
    """Per observation: kind, 2D residual norm (px), validity, its (view, board, laser) labels
    and its index in its view (a dot's in its board, a spot's among the view's spots; -1 where
    the problem was not packed from observations)."""
    pk = result.packed
    norm, kind, ok = _per_observation(result.params, pk)
    n_obs = norm.size
    n_d, n_s, n_r = pk.dot_pose.shape[0], pk.spot_pose.shape[0], pk.rim_pixels.shape[0]
    view = np.full(n_obs, -1)
    board = np.full(n_obs, "", dtype=object)
    laser = np.full(n_obs, -1)
    index = np.full(n_obs, -1)
    keys = pk.pose_keys
    for i, k in enumerate(np.asarray(pk.dot_pose)):
        view[i], board[i] = keys[k]
    for i, (_, _, j) in enumerate(pk.dot_src):
        index[i] = j
    for j, (k, las) in enumerate(zip(np.asarray(pk.spot_pose), np.asarray(pk.spot_laser), strict=True)):
        view[n_d + j], board[n_d + j] = keys[k]
        laser[n_d + j] = las
    for j, (_, i) in enumerate(pk.spot_src):
        index[n_d + j] = i
    for j, k in enumerate(np.asarray(pk.chess_pose)):
        view[n_d + n_s + n_r + j] = pk.chess_keys[k]
    return norm, kind, ok, view, board, laser, index


def _finite_or_none(x):
    """A number or array as JSON: its values, with None for a NaN (undetermined) one."""
    a = np.asarray(x, dtype=float)
    out = [float(v) if np.isfinite(v) else None for v in a.ravel()]
    return out[0] if a.ndim == 0 else out


def _rms(x):
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else None


def report(result: CalibrationResult, obs: Observations) -> dict:
    """The ``residuals`` and ``uncertainty`` sections of the output (plain JSON types)."""
    norm, kind, ok, view, board, laser, index = _obs_table(result)
    sigma = float(result.cov.sigma)
    point = (kind == Kind.DOT) | (kind == Kind.SPOT)
    # beyond 5 sigmas of its own kind (the pooled sigma where the kind has none)
    own = np.array([result.kind_sigma.get(k.label) for k in Kind], dtype=float)  # None: NaN
    own = np.where(np.isfinite(own), own, sigma)
    outlier = ok & point & (norm > 5.0 * own[kind])
    per_view = {obs.views[v].name: _rms(norm[ok & point & (view == v)]) for v in range(len(obs.views))}
    boards = sorted({b for b in board if b})
    per_board = {b: _rms(norm[ok & (kind == Kind.DOT) & (board == b)]) for b in boards}
    per_laser = {str(i): _rms(norm[ok & (kind == Kind.SPOT) & (laser == i)]) for i in range(obs.n_lasers)}
    per_direct = {
        obs.calibration_views[c].name: _rms(norm[ok & (kind == Kind.CHESS) & (view == c)])
        for c in result.packed.chess_keys
    }
    outliers = []
    for i in np.flatnonzero(outlier):
        item = {
            "kind": KIND_NAMES[kind[i]],
            "view": obs.views[view[i]].name,
            "board": board[i],
            "index": int(index[i]),
            "residual_px": float(norm[i]),
        }
        if kind[i] == Kind.SPOT:
            item["laser"] = int(laser[i])
        outliers.append(item)
    residuals = {
        "rms_px": _rms(norm[ok]),
        "sigma_px": sigma,
        "dof": int(result.cov.dof),
        "by_kind_rms_px": {k.label: _rms(norm[ok & (kind == k)]) for k in Kind},
        "by_kind_sigma_px": {k: (None if not np.isfinite(v) else v) for k, v in result.kind_sigma.items()},
        "per_view_rms_px": per_view,
        "per_board_rms_px": per_board,
        "per_laser_rms_px": per_laser,
        "per_direct_view_rms_px": per_direct,
        "invalid": int(np.sum(~ok)),
        "outliers": outliers,
        "repairs": result.repairs,
        "rim_outliers": int(np.sum(ok & (kind == Kind.RIM) & (norm > 5.0 * (result.kind_sigma.get("rim") or sigma)))),
        "loss": {"kind": result.loss, "scale_px": result.scale},
    }
    cov = np.asarray(result.cov.glob)
    sd = std_of_variance(np.diag(cov))
    x_ref = laser_working_points(result.rig, result.params.poses, result.packed)
    pos, ang = laser_std(result.rig, cov, x_ref)
    held = list(result.undetermined_lasers)
    pos[held], ang[held] = np.nan, np.nan  # held at a placeholder: a std of 0 would claim it known
    last = result.passes[-1] if result.passes else None
    uncertainty = {
        "converged": result.converged,
        **(
            {}
            if result.converged or last is None
            else {
                "status": f"not a minimum: the last pass ({last.name}) {last.result} after {last.steps} steps; "
                "the std below are those of the point where it stopped"
            }
        ),
        "sigma_px": sigma,
        "camera_std": dict(zip(CAMERA_NAMES, _finite_or_none(sd[CAMERA_COLUMNS]), strict=True)),
        "mirror_std": {
            "apex_mm": _finite_or_none(sd[APEX_COLUMNS]),
            "axis_tilt_deg": _finite_or_none(np.degrees(sd[TILT_COLUMNS])),
        }
        | ({"conic_constant": _finite_or_none(sd[SHAPE_COLUMN])} if float(result.masks.glob[SHAPE_COLUMN]) else {}),
        "lasers": [
            {
                "working_point": None if i in held else x_ref[i].tolist(),
                "working_range_mm": None if i in held else float(np.linalg.norm(x_ref[i])),
                "position_std_mm": _finite_or_none(pos[i]),
                "direction_std_deg": _finite_or_none(np.degrees(ang[i])),
            }
            | (
                {"status": "undetermined: its spots cannot fix a line (held; its spots are left out)"}
                if i in held
                else {}
                if np.isfinite(pos[i]) and np.isfinite(ang[i])
                else {"status": "undetermined: its covariance is not positive (the data do not fix this laser)"}
            )
            for i in range(result.rig.lasers.n)
        ],
        "covariance": {
            "parameters": f"camera ({', '.join(CAMERA_NAMES)}), mirror (apex dx, dy, dz mm; axis tilt "
            "e1, e2 rad; conic constant, 0 where the shape is given), then per laser (point offset e1, e2 mm; "
            "direction tilt e1, e2 rad) with (e1, e2) the orthonormal basis of slcvjax.support.safe.orthonormal_basis "
            "about the axis / laser direction",
            "matrix": cov.tolist(),
        },
    }
    if result.box is not None:
        uncertainty["rigid_box"] = _box_json(result.box)
    return {"residuals": residuals, "uncertainty": uncertainty}


def _box_json(box: dict) -> dict:
    """``uncertainty.rigid_box`` of a result with the rigid box model."""
    boards = {
        b: {
            "R": np.asarray(d["pose"].R).tolist(),
            "t": np.asarray(d["pose"].t).tolist(),
            "rotation_std_deg": _finite_or_none(d["rotation_deg"]),
            "translation_std_mm": _finite_or_none(d["translation_mm"]),
        }
        for b, d in box["boards"].items()
    }
    return {"gauge": box["gauge"], "boards": boards} | {
        k: box[k] for k in ("views", "free_board_poses", "left_out", "spots_restored", "notes")
    }


def _rig_json(rig: Rig, undetermined: tuple[int, ...] = ()) -> dict:
    from ..observations.formats import calibration_to_json

    doc = calibration_to_json(Calibration(rig, undetermined_lasers=undetermined))
    return {k: doc[k] for k in ("camera", "mirror", "lasers")}


def to_calibration(result: CalibrationResult, obs: Observations) -> Calibration:
    """The ``slcv-calibration/1`` content of a result (joint solution, staged beside it)."""
    pk = result.packed
    board_poses: list[dict[str, Pose]] = [{} for _ in obs.views]
    for (v, b), pose in zip(pk.pose_keys, unstack_poses(result.params.poses), strict=True):
        board_poses[v][b] = pose
    cvp: list[Pose | None] = [None] * len(obs.calibration_views)
    for c, pose in zip(pk.chess_keys, unstack_poses(result.params.chess), strict=True):
        cvp[c] = pose
    rep = report(result, obs)
    st = result.staged
    stages = {
        "staged": {
            **_rig_json(st.rig, st.undetermined),
            "reports": [
                {"stage": r.name, "rms": _finite_or_none(r.rms), "unit": r.unit, "notes": r.notes} for r in st.reports
            ],
        },
        "joint": {"passes": [p.to_json() for p in result.passes], "timings_s": result.timings},
    }
    return Calibration(result.rig, board_poses, cvp, {**rep, "stages": stages}, result.undetermined_lasers)


def reprojections(cal: Calibration, obs: Observations, view: int, rim_points: int = 360) -> dict:
    """The calibrated model's pixels for one catadioptric view (for plots and checks).

    Returns ``{"dots": {board: (M, 2)}, "spots": (S, 2), "rim": (K, 2)}``: the board
    points through the mirror at the view's board poses, each detected spot's laser on
    its board's plane (NaN where the spot has no posed board or the model has no pixel)
    and the rim curve.  Invalid model pixels are NaN.
    """
    rig, poses, v = cal.rig, cal.board_poses[view], obs.views[view]
    dots = {}
    for b in v.boards:
        if b in poses:
            uv, ok = project_board_points(rig, poses[b], jnp.asarray(obs.boards[b], dtype=float))
            dots[b] = np.where(np.asarray(ok)[:, None], np.asarray(uv), np.nan)
    spots = np.full((len(v.spots), 2), np.nan)
    for i, s in enumerate(v.spots):
        if s.board in poses:
            uv, ok = project_spots(rig, poses[s.board], jnp.asarray([s.laser]))
            if bool(ok[0]):
                spots[i] = np.asarray(uv[0])
    uv, ok = project_rim(rig, jnp.linspace(0.0, 2 * np.pi, rim_points, endpoint=False))
    return {"dots": dots, "spots": spots, "rim": np.asarray(uv)[np.asarray(ok)]}
