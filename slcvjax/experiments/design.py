"""Experiment design: the predicted laser accuracy of a planned calibration, and better sensor poses.

A plan is the rig, the box (four walls with 3x3 dot grids, half width ``w``), the
direct chessboard views and ``V`` sensor poses in the box, ``T_box_cam`` of view ``v``
given as a rotation vector and a translation (mm).  Its **prediction** is the
Cramer-Rao bound of the calibration it would give: ``sigma^2 (J^T J)^-1`` at the true
parameters (camera, mirror, lasers, every board pose, every chessboard pose), with
``J`` the Jacobian of the joint problem's residuals (:mod:`slcvjax.calibration.lm`) over every dot that is
visible, each laser's spot on the wall its beam meets first where it is visible, the
rim's edge pixels and the chessboard corners, propagated to each laser's position error
at its working point and its direction error (as :func:`slcvjax.calibration.bound.cramer_rao`).

The **design** moves the sensor poses within a motion range to minimise the predicted
error, by gradient descent through the bound.  Each coordinate of a pose is
``range * tanh(u)``, so every iterate stays in range.  The gradient differentiates the
Jacobian itself, so the reflection point's second derivatives enter (exact: see
:mod:`slcvjax.geometry.newton`).  Which points are visible and which wall a beam
meets are decided at the current poses and held while differentiating (they change
discretely); a step is accepted only when the bound, re-evaluated with the new
visibility, goes down (Adam steps with a backtracking length; a view whose visibility a
trial step changes is held in place for that step).

The objective is the mean over lasers of the predicted direction variance divided by
its value at the start, plus (``position_weight``) the same for the position variance:
a direction-only design may trade position for direction.
"""

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Bool

from ..calibration.bound import laser_variance
from ..calibration.linearise import rows_at
from ..calibration.params import N_LAS, Params, make_masks
from ..calibration.schur import normal_equations, schur_inverse
from ..geometry.lasers import line_plane_intersection
from ..geometry.mirror import project_through_mirror
from ..geometry.pose import Pose, so3_exp
from ..geometry.rig import Rig, project_rim
from ..observations.problem import Packed, bucket, pad_rows
from ..observations.simulate import PAPER_HALF_WIDTH, PAPER_ROTATION_DEG, PAPER_TRANSLATION_MM, Scene, box_walls
from ..support.persist import PersistentJit
from .descent import Accepted, adam_descent

N_RIM = 90  # rim edge pixels per view, as the simulator writes
MIN_DOTS = 4  # visible dots a board needs in a view for its pose
MIN_SPOTS = 3  # spots each laser needs over the plan: with fewer its prediction is infinite


@dataclass
class Plan:
    """A planned calibration: the sensor's poses in the box and what is known around them.

    ``views`` (V, 6): ``T_box_cam`` of each view (rotation vector in rad, translation in mm).
    ``rotation_range`` (rad) and ``translation_range`` (mm): the allowed motion, per axis
    (roll, pitch, yaw; x, y, z of the box frame).
    """

    rig: Rig
    views: np.ndarray
    half_width: float = PAPER_HALF_WIDTH
    rotation_range: np.ndarray = field(default_factory=lambda: np.radians(PAPER_ROTATION_DEG))
    translation_range: np.ndarray = field(default_factory=lambda: np.asarray(PAPER_TRANSLATION_MM, dtype=float))
    noise: float = 0.5
    chess_poses: list[Pose] = field(default_factory=list)
    chess_board: np.ndarray | None = None

    def __post_init__(self):
        self.views = np.asarray(self.views, dtype=float)
        self.rotation_range = np.asarray(self.rotation_range, dtype=float)
        self.translation_range = np.asarray(self.translation_range, dtype=float)
        if self.views.ndim != 2 or self.views.shape[1] != 6 or self.views.shape[0] < 1:
            raise ValueError(f"views must be an (n, 6) array with n >= 1, got shape {self.views.shape}")
        if self.rotation_range.shape != (3,) or self.translation_range.shape != (3,):
            raise ValueError("rotation_range and translation_range need 3 values each")
        if np.any(self.rotation_range < 0) or np.any(self.translation_range < 0):
            raise ValueError("the motion range must not be negative")
        if not (np.isfinite(self.noise) and self.noise > 0):
            raise ValueError(f"noise must be a positive number of pixels, got {self.noise}")
        if not (np.isfinite(self.half_width) and self.half_width > 0):
            raise ValueError(f"half_width must be positive, got {self.half_width}")

    @staticmethod
    def from_scene(scene: Scene, views: np.ndarray, noise: float = 0.5, **kw) -> "Plan":
        """A plan with the scene's rig, chessboard views and box, at the given sensor poses."""
        return Plan(
            scene.rig,
            views,
            half_width=float(scene.info.get("box_half_width_mm", PAPER_HALF_WIDTH)),
            noise=noise,
            chess_poses=list(scene.chess_poses),
            chess_board=np.asarray(scene.boards[scene.chess_board]),
            **kw,
        )

    @property
    def scale(self) -> np.ndarray:
        return np.concatenate([self.rotation_range, self.translation_range])


# ----------------------------------------------------------------------------- the bound as a function of the poses


VIEW_LADDER = (4, 2)  # the plan's views padded to 4, 8, 16, ... (see :func:`design_problem`)


class Present(NamedTuple):
    """Which rows of a padded plan are real: per view, per rim row, per corner row."""

    views: Bool[Array, " V"]
    rim: Bool[Array, " R"]
    chess: Bool[Array, " C"]


def design_problem(plan: Plan, pad: bool = True):
    """The fixed structure of the plan's joint problem: every dot, every (view, laser, wall) spot,
    the rim's pixels and the direct views' corners, with the numbers of views and of direct
    views padded by :data:`VIEW_LADDER` (``pad=False``: as they are).

    The padded views are copies of the first and their rows, the padded rim rows and the
    padded direct views' corners weigh nothing (:class:`Present`): every plan whose counts fall
    in the same buckets shares one compilation of the bound and its gradient.
    Returns ``(pk, T_bw, chess, present)``."""
    boards, T_box_walls = box_walls(plan.half_width)
    walls = [boards[f"wall{j}"] for j in range(4)]
    n_v, n_l, n_d = plan.views.shape[0], plan.rig.lasers.n, walls[0].shape[0]
    cap = bucket(n_v, *VIEW_LADDER) if pad else n_v
    dot_pose = np.repeat(np.arange(4 * cap), n_d)
    dot_points = np.tile(np.concatenate(walls), (cap, 1))
    vv, ll, jj = np.meshgrid(np.arange(cap), np.arange(n_l), np.arange(4), indexing="ij")
    spot_pose, spot_laser = (4 * vv + jj).ravel(), ll.ravel()
    n_ang = N_RIM * cap
    angles = pad_rows(np.linspace(0.0, 2 * np.pi, N_RIM * n_v, endpoint=False), n_ang)
    rim, ok = project_rim(plan.rig, jnp.asarray(angles))
    rim, rim_ok = np.asarray(rim), np.asarray(ok) & (np.arange(n_ang) < N_RIM * n_v)
    if pad:  # the rows kept in place, those off the rim weighing nothing (a valid pixel in them)
        rim = np.where(rim_ok[:, None], rim, rim[np.argmax(rim_ok)])
    else:
        rim, rim_ok = rim[rim_ok], rim_ok[rim_ok]
    if plan.chess_poses:
        board = np.asarray(plan.chess_board)
        n_c = len(plan.chess_poses)
        cap_c = bucket(n_c, *VIEW_LADDER) if pad else n_c
        chess_pose = np.repeat(np.arange(cap_c), board.shape[0])
        chess_points = np.tile(board, (cap_c, 1))
        chess_present = chess_pose < n_c
        R = pad_rows(np.stack([np.asarray(p.R) for p in plan.chess_poses]), cap_c)
        t = pad_rows(np.stack([np.asarray(p.t) for p in plan.chess_poses]), cap_c)
        chess = Pose(jnp.asarray(R), jnp.asarray(t))
    else:
        chess_pose, chess_points, chess_present = np.zeros(0, int), np.zeros((0, 3)), np.zeros(0, bool)
        chess = Pose(jnp.zeros((0, 3, 3)), jnp.zeros((0, 3)))
    pk = Packed(
        jnp.asarray(dot_pose),
        jnp.asarray(dot_points),
        jnp.zeros((dot_pose.size, 2)),
        jnp.asarray(spot_pose),
        jnp.asarray(spot_laser),
        jnp.zeros((spot_pose.size, 2)),
        jnp.asarray(rim),
        jnp.asarray(chess_pose),
        jnp.asarray(chess_points),
        jnp.zeros((chess_pose.size, 2)),
        jnp.asarray([dot_pose.size, spot_pose.size, rim.shape[0], chess_pose.size], dtype=jnp.int64),
        (),
        (),
    )
    T_bw = Pose(jnp.stack([p.R for p in T_box_walls]), jnp.stack([p.t for p in T_box_walls]))
    present = Present(jnp.asarray(np.arange(cap) < n_v), jnp.asarray(rim_ok), jnp.asarray(chess_present))
    return pk, T_bw, chess, present


def pad_views(views, cap: int) -> np.ndarray:
    """(V, 6) views (or design variables) padded to ``cap`` rows with copies of the first."""
    return pad_rows(np.asarray(views, dtype=float), cap)


def _poses(views, T_bw: Pose) -> Pose:
    """``T_cam_wall`` of every (view, wall), index ``4 v + j``."""
    R_bc = jax.vmap(so3_exp)(views[:, :3])
    t_bc = views[:, 3:]
    R_cb = jnp.swapaxes(R_bc, 1, 2)
    t_cb = -jnp.einsum("vij,vj->vi", R_cb, t_bc)
    R = jnp.einsum("vij,wjk->vwik", R_cb, T_bw.R).reshape(-1, 3, 3)
    t = (jnp.einsum("vij,wj->vwi", R_cb, T_bw.t) + t_cb[:, None, :]).reshape(-1, 3)
    return Pose(R, t)


def _weights(rig: Rig, poses: Pose, pk: Packed, present: Present):
    """Per observation, 1 where it would be observed: dots visible, spots on their first wall and
    visible (none in a padded view)."""
    cam, mir, las = rig.camera, rig.mirror, rig.lasers
    n_v = poses.t.shape[0] // 4

    def dot_ok(R, t, xb):
        return project_through_mirror(cam, mir, Pose(R, t).apply(xb)).valid

    w_dot = jax.vmap(dot_ok)(poses.R[pk.dot_pose], poses.t[pk.dot_pose], pk.dot_points)
    w_dot = w_dot & present.views[pk.dot_pose // 4]

    def spot(R, t, li):
        p, d = las.points[li], las.directions[li]
        x, ahead = line_plane_intersection(p, d, Pose(R, t))
        lam = jnp.where(ahead, jnp.dot(x - p, d), -1.0)  # along the beam (unit direction); -1 behind it
        return lam, x, project_through_mirror(cam, mir, x).valid

    # a board needs 4 visible dots for its pose (the staged calibration's PnP): with fewer,
    # neither its dots nor its spots can be used
    usable = jax.ops.segment_sum(w_dot.astype(int), pk.dot_pose, num_segments=poses.t.shape[0]) >= MIN_DOTS
    w_dot = w_dot & usable[pk.dot_pose]
    lam, x, vis = jax.vmap(spot)(poses.R[pk.spot_pose], poses.t[pk.spot_pose], pk.spot_laser)
    lam4 = jax.lax.stop_gradient(jnp.where(lam > 0.0, lam, jnp.inf).reshape(n_v, las.n, 4))
    first = (jnp.arange(4)[None, None, :] == jnp.argmin(lam4, axis=2)[..., None]) & jnp.isfinite(lam4)
    w_spot = first.reshape(-1) & vis & usable[pk.spot_pose]
    # each laser's working point: the mean of its spots
    xs = x.reshape(n_v, las.n, 4, 3)
    ws = w_spot.reshape(n_v, las.n, 4, 1).astype(float)
    x_ref = jnp.sum(ws * xs, axis=(0, 2)) / jnp.maximum(jnp.sum(ws, axis=(0, 2)), 1.0)
    return w_dot, w_spot, x_ref


def calibration_covariance(views, rig, T_bw, chess, pk, sigma, present: Present):
    """The plan's bound on the rig's tangent (camera, mirror, lasers: ``rig.tangent_dim`` square,
    px^2 scaled by ``sigma^2``), which dots and spots are observed, and each laser's working point.
    ``views`` padded as ``pk`` (:func:`design_problem`)."""
    poses = _poses(views, T_bw)
    # which points are seen is held while differentiating; the working points move with the poses
    w_dot, w_spot, x_ref = _weights(rig, poses, pk, present)
    w_dot, w_spot = jax.lax.stop_gradient(w_dot), jax.lax.stop_gradient(w_spot)
    params = Params(rig, poses, chess)
    rows = rows_at(params, pk)  # differentiated in reverse mode
    w_obs = jnp.concatenate([w_dot, w_spot, present.rim, present.chess]).astype(float)
    g, nb = params.n_global, params.n_blocks
    masks = make_masks(params)
    ne = normal_equations(rows, w_obs[rows.obs], g, nb, masks.glob, masks.blocks)
    cov = sigma**2 * schur_inverse(ne)[0]
    return cov, w_dot, w_spot, x_ref


def _predict(views, rig, T_bw, chess, pk, sigma, present):
    """Per laser: predicted position variance (mm^2) at the working point and direction variance (rad^2)."""
    cov, w_dot, w_spot, x_ref = calibration_covariance(views, rig, T_bw, chess, pk, sigma, present)

    starts = jnp.asarray(rig.layout.element_starts)

    def laser(i):
        s = starts[i]  # a traced index: the block by a dynamic slice
        return laser_variance(rig.lasers, i, x_ref[i], jax.lax.dynamic_slice(cov, (s, s), (N_LAS, N_LAS)))

    pos, ang = jax.vmap(laser)(jnp.arange(rig.lasers.n))
    # a laser with too few spots seen cannot be calibrated at all (its line needs spots on
    # boards at different distances): no finite prediction
    per_laser = jax.ops.segment_sum(w_spot.astype(int), pk.spot_laser, num_segments=rig.lasers.n)
    enough = jnp.min(per_laser) >= MIN_SPOTS
    pos, ang = jnp.where(enough, pos, jnp.inf), jnp.where(enough, ang, jnp.inf)
    return pos, ang, jnp.sum(w_dot), jnp.sum(w_spot)


@dataclass
class Prediction:
    """A plan's predicted laser accuracy: per laser std at the working point (mm) and of the direction (rad)."""

    position_std_mm: np.ndarray
    direction_std_rad: np.ndarray
    n_dots: int
    n_spots: int

    @property
    def position_rms_mm(self) -> float:
        return float(np.sqrt(np.mean(self.position_std_mm**2)))

    @property
    def direction_rms_deg(self) -> float:
        return float(np.degrees(np.sqrt(np.mean(self.direction_std_rad**2))))

    def to_json(self) -> dict:
        """JSON-ready; a prediction the plan cannot support (infinite: a laser without enough
        spots) is written as null, with ``status`` saying so."""

        def num(x):
            return float(x) if np.isfinite(x) else None

        out = {
            "position_rms_mm": num(self.position_rms_mm),
            "direction_rms_deg": num(self.direction_rms_deg),
            "position_std_mm": [num(x) for x in self.position_std_mm],
            "direction_std_deg": [num(x) for x in np.degrees(self.direction_std_rad)],
            "dots": self.n_dots,
            "spots": self.n_spots,
        }
        if not np.all(np.isfinite(self.position_std_mm)):
            out["status"] = f"undetermined: a laser is left with fewer than {MIN_SPOTS} spots"
        return out


_predict_jit = PersistentJit(_predict, "design_predict")


def _objective(u, scale, rig, T_bw, chess, pk, sigma, present, ref_pos, ref_ang, pw):
    pos, ang, _, _ = _predict(scale * jnp.tanh(u), rig, T_bw, chess, pk, sigma, present)
    return jnp.mean(ang / ref_ang) + pw * jnp.mean(pos / ref_pos)


@jax.jit
def _visible(u, scale, rig, T_bw, pk, present):
    """Whether each dot, then each spot, would be observed at the poses ``scale * tanh(u)``."""
    w_dot, w_spot, _ = _weights(rig, _poses(scale * jnp.tanh(u), T_bw), pk, present)
    return jnp.concatenate([w_dot, w_spot])


_value_and_grad_jit = PersistentJit(jax.value_and_grad(_objective), "design_value_and_grad")


class Compiled:
    """A plan's fixed problem, padded (:func:`design_problem`): the bound and its gradient are compiled
    once per bucket of view counts.  Its design variables ``u`` have the padded views' rows
    (copies of the first view's, whose gradient is zero: they move nowhere)."""

    def __init__(self, plan: Plan, pad: bool = True):
        self.pk, self.T_bw, self.chess, self.present = design_problem(plan, pad)
        self.scale = jnp.asarray(np.maximum(plan.scale, 1e-12))
        self.n_v = plan.views.shape[0]
        self.cap = int(self.present.views.shape[0])
        self.real = np.asarray(self.present.views)
        # the view of each dot, then of each spot (poses are indexed 4 v + wall)
        self.obs_view = np.concatenate([np.asarray(self.pk.dot_pose), np.asarray(self.pk.spot_pose)]) // 4
        self.args = (plan.rig, self.T_bw, self.chess, self.pk, jnp.asarray(float(plan.noise)), self.present)

    def predict(self, views):
        """The prediction at (V, 6) views, padded here."""
        return _predict_jit(jnp.asarray(pad_views(views, self.cap)), *self.args)

    def visible(self, u) -> np.ndarray:
        return np.asarray(_visible(u, self.scale, self.args[0], self.T_bw, self.pk, self.present))

    def value_and_grad(self, u, ref_pos, ref_ang, pw):
        return _value_and_grad_jit(u, self.scale, *self.args, ref_pos, ref_ang, pw)

    def u_of(self, views: np.ndarray) -> jnp.ndarray:
        """The padded design variables of (V, 6) views."""
        x = np.clip(np.asarray(views) / np.asarray(self.scale), -1.0 + 1e-9, 1.0 - 1e-9)
        return jnp.asarray(pad_views(np.arctanh(x), self.cap))

    def views_of(self, u) -> np.ndarray:
        """The (V, 6) real views of padded design variables."""
        return np.asarray(self.scale * jnp.tanh(u))[: self.n_v]


def predict(plan: Plan) -> Prediction:
    """The predicted (Cramer-Rao) laser accuracy of a planned calibration."""
    c = Compiled(plan)
    return _prediction(c, plan.views)


def _prediction(c: Compiled, views) -> Prediction:
    pos, ang, nd, ns = c.predict(views)
    return Prediction(np.sqrt(np.asarray(pos)), np.sqrt(np.asarray(ang)), int(nd), int(ns))


@dataclass
class DesignResult:
    """The poses before and after, their predictions, and the objective at each accepted step."""

    before: Plan
    after: Plan
    predicted_before: Prediction
    predicted_after: Prediction
    history: list[float]
    timings: dict


def _line_search(c: "Compiled", u, step, lr, f0, ref_pos, ref_ang, pw):
    """A step ``u - a * step`` (a <= lr) that lowers the objective: ``(u, f, gradient, a)``, or
    Nones.  Each try evaluates the objective with its gradient (one compiled program serves the
    search and the steps; an accepted try, most of them, is not evaluated again).

    A trial step that changes what a view sees (a dot leaving the image, a beam meeting
    another wall) may raise the bound although the gradient, blind to visibility, says it
    falls: such views are held in place and the step is tried again; otherwise the length
    is halved (at most 8 tries).
    """
    held = np.zeros(c.cap, dtype=bool)
    seen = None
    for _ in range(8):
        u_new = u - lr * step * jnp.asarray(~held, dtype=float)[:, None]
        value, g_new = c.value_and_grad(u_new, ref_pos, ref_ang, pw)
        f_new = float(value)
        if np.isfinite(f_new) and f_new < f0:
            return u_new, f_new, g_new, lr
        if seen is None:
            seen = c.visible(u)
        changed = np.zeros(c.cap, dtype=bool)
        np.logical_or.at(changed, c.obs_view, c.visible(u_new) != seen)
        if changed.any() and not (held | changed | ~c.real).all():
            held |= changed
        else:
            lr *= 0.5
    return None, None, None, None


def optimise(
    plan: Plan,
    steps: int = 60,
    learning_rate: float = 0.3,
    position_weight: float = 0.5,
    progress: bool = False,
) -> DesignResult:
    """Sensor poses within the plan's motion range that minimise the predicted laser error.

    Adam (:func:`slcvjax.experiments.descent.adam_descent`) on ``u`` (pose = range * tanh(u)), each
    step shortened until the objective, re-evaluated at the new poses (visibility included), goes
    down, views whose visibility the step changes held in place (:func:`_line_search`); where no
    step helps, Adam starts afresh once.  Stops after ``steps`` accepted steps or when a fresh start does not help.
    """
    t0 = time.perf_counter()
    c = Compiled(plan)
    u = c.u_of(plan.views)
    pos0, ang0, _, _ = c.predict(c.views_of(u))
    ref_pos, ref_ang = jnp.maximum(pos0, 1e-30), jnp.maximum(ang0, 1e-30)
    pw = jnp.asarray(float(position_weight))
    f, grad = c.value_and_grad(u, ref_pos, ref_ang, pw)
    t_compile = time.perf_counter() - t0

    def search(u, step, lr, f0):
        u_new, f_new, g_new, lr_used = _line_search(c, u, step, lr, f0, ref_pos, ref_ang, pw)
        return None if u_new is None else Accepted(u_new, f_new, g_new, lr_used)

    d = adam_descent(
        u,
        float(f),
        grad,
        search,
        steps,
        learning_rate,
        optax.scale_by_adam(b1=0.9, b2=0.999, eps=1e-12),
        grow=1.2,
        restart=True,
        progress="design" if progress else None,
        postfix=lambda v: {"objective": f"{v:.3f}"},
    )
    u, history = d.u, d.history
    after = dataclasses.replace(plan, views=c.views_of(u))
    before_pred = _prediction(c, plan.views)
    after_pred = _prediction(c, after.views)
    timings = {"compile_s": t_compile, "total_s": time.perf_counter() - t0}
    return DesignResult(plan, after, before_pred, after_pred, history, timings)


# ----------------------------------------------------------------------------- confirmation, output


def confirm(
    plan: Plan,
    trials: int,
    seed: int = 0,
    progress: bool = False,
    *,
    out_dir=None,
    resume: str = "auto",
    chunk: int | None = None,
    cluster=None,
    cache_dir=None,
    on_chunk=None,
) -> dict:
    """Monte Carlo check of a plan: simulate and calibrate it ``trials`` times at its noise.

    Returns the RMS over trials and lasers of the joint calibration's position error at
    each laser's true working point (mm) and of its direction error (deg), how many
    calibrations converged, and how many could not be made at all (``failed``, with the
    first reason: a plan whose views leave a laser without usable spots); the RMS figures
    are None when every trial failed.

    Trial ``t`` simulates with seed ``seed + t``.  The trials run in chunks of ``chunk`` (default 8)
    through :func:`slcvjax.experiments.cluster.run_chunks`, here or on the Ray cluster ``cluster``
    (``cache_dir``: the workers' shared compilation cache), with the same numbers either way; with
    ``out_dir`` each finished chunk is kept there and a run of the same plan resumes it
    (``resume``, ``on_chunk``: as :func:`slcvjax.experiments.sweep.run_sweep`'s).
    """
    from .cluster import run_chunks

    if trials < 1:
        raise ValueError(f"trials must be at least 1, got {trials}")
    scene = _plan_scene(plan)
    payload = {"plan": plan, "scene": scene, "x_ref": _true_working_points(scene)}
    items = [{"trial": t, "seed": seed + t} for t in range(trials)]
    records = run_chunks(
        confirm_chunk, payload, items, study="design-confirm", settings={"plan": plan, "trials": trials, "seed": seed},
        chunk_size=chunk, folder=out_dir, resume=resume, cluster=cluster, cache_dir=cache_dir, progress=progress,
        desc="confirm", on_chunk=on_chunk,
    )  # fmt: skip
    failed = [r["error"] for r in records if "error" in r]
    ok = [r for r in records if "error" not in r]
    out = {"trials": trials, "converged": sum(r["converged"] for r in ok), "failed": len(failed)}
    if failed:
        out["first_failure"] = failed[0]
    if not ok:
        return out | {"position_rms_mm": None, "direction_rms_deg": None}
    pos = np.concatenate([r["pos"] for r in ok])
    ang = np.concatenate([r["ang"] for r in ok])
    return out | {
        "position_rms_mm": float(np.sqrt(np.mean(pos**2))),
        "direction_rms_deg": float(np.degrees(np.sqrt(np.mean(ang**2)))),
    }


def confirm_chunk(payload: dict, items: list[dict]) -> list[dict]:
    """Simulate and calibrate a chunk of a confirmation's trials (the task of :func:`confirm`'s
    :func:`~slcvjax.experiments.cluster.run_chunks`).

    Args:
        payload: ``plan`` (:class:`Plan`), ``scene`` (its box scene) and ``x_ref`` (N, 3) the
            lasers' true working points (mm).
        items: one per trial, ``{"seed": int, ...}``.

    Returns:
        One record per trial: ``pos`` (N,) mm and ``ang`` (N,) rad, the joint calibration's
        errors (:func:`slcvjax.calibration.bound.laser_errors`), and ``converged``; or
        ``{"error": reason}`` where the trial could not be calibrated.
    """
    from ..calibration.bound import laser_errors

    out = []
    for it in items:
        _, truth, res, error = _simulated_calibration(payload["scene"], payload["plan"].noise, it["seed"])
        if res is None:
            out.append({"error": error})
            continue
        pos, ang = laser_errors(res.rig, truth.rig, payload["x_ref"])
        out.append({"converged": bool(res.passes[-1].converged), "pos": pos.tolist(), "ang": ang.tolist()})
    return out


def _plan_scene(plan: Plan) -> Scene:
    from ..observations.simulate import box_scene

    return box_scene(plan.rig, plan.views, plan.half_width, n_chess_views=len(plan.chess_poses) or 12)


def _simulated_calibration(scene: Scene, noise: float, seed: int):
    """``(obs, truth, result, None)`` of one simulation of ``scene`` calibrated from its usable
    observations, or ``(obs, truth, None, reason)`` where a calibration cannot be made."""
    from ..calibration.base import CalibrationError
    from ..calibration.calibrate import calibrate
    from ..calibration.result import require_determined
    from ..observations.simulate import simulate

    obs, truth = simulate(scene, noise=noise, seed=seed)
    try:
        return obs, truth, require_determined(calibrate(usable_observations(obs))), None
    except CalibrationError as e:
        return obs, truth, None, str(e)


def simulated_calibrations(plan: Plan, trials: int, seed: int = 0, progress: bool = False):
    """``trials`` simulations of the plan's box calibration at its noise (trial ``t``: seed
    ``seed + t``), each calibrated from its usable observations: yields ``(obs, truth, result,
    None)``, or ``(obs, truth, None, reason)`` where a calibration cannot be made."""
    if trials < 1:
        raise ValueError(f"trials must be at least 1, got {trials}")
    scene = _plan_scene(plan)
    it = range(trials)
    if progress:
        from tqdm import tqdm

        it = tqdm(it, desc="confirm", unit="calibration")
    for t in it:
        yield _simulated_calibration(scene, plan.noise, seed + t)


def usable_observations(obs):
    """``obs`` without the boards seen by fewer than 4 dots in a view (and without their spots), as predicted."""
    views = []
    for v in obs.views:
        keep = {b for b, (_, seen) in v.boards.items() if int(seen.sum()) >= MIN_DOTS}
        boards = {b: (px, seen if b in keep else np.zeros_like(seen)) for b, (px, seen) in v.boards.items()}
        views.append(dataclasses.replace(v, boards=boards, spots=[s for s in v.spots if s.board in keep]))
    return dataclasses.replace(obs, views=views)


def _true_working_points(scene: Scene) -> np.ndarray:
    from ..observations.simulate import visible_spots

    n = scene.rig.lasers.n
    acc, cnt = np.zeros((n, 3)), np.zeros(n)
    for v in range(len(scene.box_poses)):
        for laser, _, x, _ in visible_spots(scene, v):
            acc[laser] += x
            cnt[laser] += 1
    pts = np.asarray(scene.rig.lasers.points)
    return np.where(cnt[:, None] > 0, acc / np.maximum(cnt, 1)[:, None], pts)


def _views_json(views: np.ndarray) -> list[dict]:
    return [{"rvec_deg": np.degrees(v[:3]).tolist(), "t_mm": v[3:].tolist()} for v in views]


def design_document(res: DesignResult, confirmed: dict | None = None) -> dict:
    """The ``slcv-design/1`` document: the plan, the poses before and after, the predictions."""
    p = res.before
    return {
        "format": "slcv-design/1",
        "units": "mm",
        "box_width_mm": 2.0 * p.half_width,
        "noise_px": p.noise,
        "motion_range": {
            "rotation_deg": np.degrees(p.rotation_range).tolist(),
            "translation_mm": p.translation_range.tolist(),
        },
        "views_frame": "T_box_cam per view: rotation vector (deg) and translation (mm) of the sensor in the box",
        "views_before": _views_json(p.views),
        "views_after": _views_json(res.after.views),
        "predicted": {"before": res.predicted_before.to_json(), "after": res.predicted_after.to_json()},
        "objective_history": res.history,
        "confirmed": confirmed,
        "timings": res.timings,
    }


def plot_design(res: DesignResult, path) -> Path:
    """Per-laser predicted std before and after, and the sensor positions in the box (top view)."""
    from ..plots import pyplot

    plt = pyplot()
    path = Path(path)
    b, a = res.predicted_before, res.predicted_after
    n = b.position_std_mm.size
    x = np.arange(n)
    fig, axs = plt.subplots(1, 3, figsize=(15, 4.5))
    axs[0].bar(x - 0.2, np.degrees(b.direction_std_rad), 0.4, label=f"before (rms {b.direction_rms_deg:.3f} deg)")
    axs[0].bar(x + 0.2, np.degrees(a.direction_std_rad), 0.4, label=f"after (rms {a.direction_rms_deg:.3f} deg)")
    axs[0].set_ylabel("predicted direction std (deg)")
    axs[1].bar(x - 0.2, b.position_std_mm, 0.4, label=f"before (rms {b.position_rms_mm:.3f} mm)")
    axs[1].bar(x + 0.2, a.position_std_mm, 0.4, label=f"after (rms {a.position_rms_mm:.3f} mm)")
    axs[1].set_ylabel("predicted position std at the working point (mm)")
    for ax in axs[:2]:
        ax.set_xlabel("laser")
        ax.set_xticks(x)
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3, axis="y")
    ax = axs[2]
    tr = res.before.translation_range
    ax.plot([-tr[0], tr[0], tr[0], -tr[0], -tr[0]], [-tr[1], -tr[1], tr[1], tr[1], -tr[1]], "k:", lw=1)
    lim = 1.4 * max(tr[0], tr[1], 1.0)
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-lim, lim)
    for views, style, name in ((res.before.views, "o", "before"), (res.after.views, "^", "after")):
        t, yaw = views[:, 3:], views[:, 2]
        ax.quiver(t[:, 0], t[:, 1], np.cos(yaw), np.sin(yaw), angles="xy", width=0.004, alpha=0.6)
        ax.plot(t[:, 0], t[:, 1], style, ms=5, label=name)
    ax.set_aspect("equal")
    ax.set_xlabel("x in the box (mm)")
    ax.set_ylabel("y in the box (mm)")
    ax.set_title("sensor positions and yaw (arrows)\ndotted: the motion range")
    ax.legend(fontsize=8)
    fig.suptitle(f"Experiment design: {res.before.views.shape[0]} views, noise {res.before.noise} px")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
