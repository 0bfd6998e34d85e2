"""The whole calibration: staged start, progressive joint refinement, uncertainty, report.

:func:`calibrate` runs the staged pipeline (:mod:`._staged`), then the joint
Levenberg-Marquardt (:mod:`._lm`) in three passes:

A. camera, mirror, board and direct-view poses from dots, rim and corners (lasers
   frozen, spots weighted 0): the staged mirror tilt is weakly observable from the rim
   alone and the boards fix it;
B. the lasers refitted on the refined geometry, then everything jointly with a Huber
   loss at 3 sigma (sigma estimated robustly from the residuals);
C. the same with sigma re-estimated at B's solution (the final pass).

It returns the joint result with its covariance, and the staged result beside it.
"""

import dataclasses
import time
from dataclasses import dataclass, field

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from ._camera import Camera
from ._io import Calibration, Observations
from ._lasers import Lasers, line_plane_intersection
from ._lm import (
    KIND_NAMES,
    RESULT_NAMES,
    Covariance,
    Masks,
    Params,
    block_costs_of_rows,
    covariance,
    make_masks,
    n_observations,
    residual_rows,
    solve,
)
from ._pose import Pose
from ._problem import Packed, pack, stack_poses
from ._rig import Rig, project_board_points, project_rim, project_spots
from ._staged import CalibrationError, Staged, _flipped, board_poses, fit_lasers, staged

_solve = jax.jit(solve, static_argnames=("loss", "max_steps"))
# The passes before the last only have to bring the next one into its basin; the last
# converges to round-off.
_RTOL_START = 1e-6
_RTOL_FINAL = 1e-10
_covariance = jax.jit(covariance, static_argnames=("loss",))
_rows = jax.jit(residual_rows)

RAYLEIGH_MEDIAN = float(np.sqrt(2.0 * np.log(2.0)))  # median of |r| / sigma for 2D Gaussian r
HALF_NORMAL_MEDIAN = 0.6744897501960817  # median of |r| / sigma for 1D Gaussian r


def _arrays(pk: Packed) -> Packed:
    """``pk`` without its static keys, so problems of the same sizes share one compilation."""
    return dataclasses.replace(pk, pose_keys=(), chess_keys=())


def _per_observation(params: Params, pk: Packed) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per observation: its 2D residual norm (px), its kind and whether it is valid."""
    rows = _rows(params, _arrays(pk))
    n_obs = int(rows.obs.max()) + 1 if rows.r.size else 0
    r2 = np.asarray(jax.ops.segment_sum(rows.r**2, rows.obs, num_segments=n_obs))
    kind = np.asarray(jax.ops.segment_max(rows.kind, rows.obs, num_segments=n_obs))
    ok = np.asarray(jax.ops.segment_min(rows.valid.astype(int), rows.obs, num_segments=n_obs)) > 0
    return np.sqrt(r2), kind, ok


def kind_sigmas(params: Params, pk: Packed, min_count: int = 10) -> np.ndarray:
    """Per kind (dot, spot, rim, chess corner) the noise sigma (px) from its median residual.

    Rim residuals are 1D (a distance to the rim curve), the others 2D.  NaN for a kind
    with fewer than ``min_count`` valid observations.
    """
    norm, kind, ok = _per_observation(params, pk)
    out = np.full(4, np.nan)
    for k in range(4):
        sel = ok & (kind == k)
        if sel.sum() >= min_count:
            out[k] = np.median(norm[sel]) / (HALF_NORMAL_MEDIAN if k == 2 else RAYLEIGH_MEDIAN)
    return out


def robust_sigma(params: Params, pk: Packed) -> float:
    """Noise sigma (px) from the median 2D residual norm of the dots, spots and corners."""
    norm, kind, ok = _per_observation(params, pk)
    sel = ok & (kind != 2)
    if not sel.any():
        return 1.0
    return float(np.median(norm[sel]) / RAYLEIGH_MEDIAN)


@dataclass
class JointPass:
    name: str
    steps: int
    result: str
    cost0: float
    cost: float
    scale: float


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
    kind_sigma: dict = field(default_factory=dict)  # per kind noise sigma (px) from its median residual

    @property
    def rig(self) -> Rig:
        return self.params.rig


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
    max_steps: int = 200,
) -> CalibrationResult:
    """Calibrate the whole rig from observations (see the module docstring).

    Args:
        obs: the observations.
        camera: a known camera to start from (freeze it with ``freeze={"camera"}``);
            without it the intrinsics come from the direct chessboard views.
        freeze: parameter blocks held fixed: camera, mirror, lasers, poses, chess_poses.
        loss: ``huber`` (default), ``cauchy`` or ``linear`` for the dots and spots.
        loss_scale: the robust loss's scale in px; by default 3 sigma, sigma estimated
            robustly from the residuals.
        max_steps: the most LM linearisations per pass.
    """
    t0 = time.perf_counter()
    st = staged(obs, camera=camera, pk=pack(obs))
    pk = st.packed  # spots without a board have one now
    t_staged = time.perf_counter() - t0
    if camera is not None and not st.chess_poses:
        st.chess_poses = {}
    chess = _chess_start(obs, pk, st.camera, st.chess_poses)
    if not chess:
        chess_stack = Pose(jnp.zeros((0, 3, 3)), jnp.zeros((0, 3)))
        if camera is None:
            raise CalibrationError("calibration_views: no direct views and no camera given")
    else:
        chess_stack = stack_poses(chess)
    params = Params(Rig(st.camera, st.mirror, st.lasers), stack_poses(st.poses), chess_stack)
    masks = make_masks(params, set(freeze))
    arr = _arrays(pk)
    passes = []

    def run(name, p, m, scale, kind_weight=None, rtol=_RTOL_START):
        res = _solve(
            p,
            arr,
            m,
            loss=loss,
            scale=scale,
            max_steps=max_steps,
            rtol=rtol,
            kind_weight=jnp.asarray([1.0] * 4 if kind_weight is None else kind_weight, dtype=float),
        )
        passes.append(
            JointPass(
                name,
                int(res.steps),
                RESULT_NAMES[int(res.result)],
                float(res.initial_cost),
                float(res.cost),
                float(scale),
            )
        )
        return res.params

    # A: geometry without the lasers
    mask_a = make_masks(params, set(freeze) | {"lasers"})
    sig = robust_sigma(params, pk)
    params = run("A: camera, mirror, poses", params, mask_a, loss_scale or 3.0 * max(sig, 0.1), [1.0, 0.0, 1.0, 1.0])
    # the boards' flips decided again on the refined geometry, then A once more
    if "poses" not in freeze:
        poses, _ = board_poses(params.rig.camera, params.rig.mirror, pk, start=params.poses)
        params = Params(params.rig, stack_poses(poses), params.chess)
        sig = robust_sigma(params, pk)
        params = run("A2: after re-flipping", params, mask_a, loss_scale or 3.0 * max(sig, 0.1), [1.0, 0.0, 1.0, 1.0])
    # B: lasers refitted, then everything
    if "lasers" not in freeze:
        lasers, rep = fit_lasers(
            params.rig.camera,
            params.rig.mirror,
            pk,
            [Pose(params.poses.R[k], params.poses.t[k]) for k in range(pk.n_poses)],
            obs.n_lasers,
        )
        params = Params(Rig(params.rig.camera, params.rig.mirror, lasers), params.poses, params.chess)
    sig = robust_sigma(params, pk)
    params = run("B: joint", params, masks, loss_scale or 3.0 * max(sig, 0.05))
    # boards whose flipped twin (refined with dots and spots, the rig held) fits better are swapped
    sig = robust_sigma(params, pk)
    scale = loss_scale or 3.0 * max(sig, 0.05)
    if "poses" not in freeze and pk.n_poses:
        params, n_flipped = _reflip_with_spots(params, arr, masks, loss, scale, max_steps)
        if n_flipped:
            passes[-1].result += f"; {n_flipped} board pose(s) flipped after it"
    # C: final pass at the re-estimated scale.  Every kind keeps weight 1: weighting each by
    # its own noise (the rim's is larger in rendered images) made the lasers worse from images
    # (benchmarks/images_vs_file.py), where the dots' errors are mostly systematic
    params = run("C: joint (final)", params, masks, scale, rtol=_RTOL_FINAL)
    cov = _covariance(params, arr, masks, loss, scale, kind_weight=jnp.ones(4, dtype=float))
    sigmas = kind_sigmas(params, pk)
    t_total = time.perf_counter() - t0
    return CalibrationResult(
        params,
        st,
        pk,
        masks,
        cov,
        loss,
        float(scale),
        passes,
        {"staged_s": t_staged, "total_s": t_total},
        dict(zip(KIND_NAMES, sigmas.tolist(), strict=True)),
    )


_costs_of_rows = jax.jit(block_costs_of_rows, static_argnames=("n_obs", "n_blocks", "loss"))


def _block_costs(params: Params, arr: Packed, loss: str, scale: float):
    """Per pose block robust cost, through the residual function compiled for the reports."""
    return _costs_of_rows(_rows(params, arr), n_observations(arr), params.n_blocks, loss, scale)


def _reflip_with_spots(params: Params, arr: Packed, masks: Masks, loss: str, scale: float, max_steps: int):
    """Try every board pose's flipped twin with the rig held fixed; keep the twins that fit better."""
    R, t = np.asarray(params.poses.R), np.asarray(params.poses.t)
    n_p = R.shape[0]
    xb = np.zeros((n_p, 1, 3))
    dp, pts = np.asarray(arr.dot_pose), np.asarray(arr.dot_points)
    for k in range(n_p):
        if np.any(dp == k):
            xb[k, 0] = pts[dp == k].mean(axis=0)
    R2, t2 = _flipped(R, t, xb, np.ones((n_p, 1)))
    twin = Params(params.rig, Pose(jnp.asarray(R2), jnp.asarray(t2)), params.chess)
    hold = Masks(jnp.zeros_like(masks.glob), jnp.concatenate([masks.blocks[:n_p], jnp.zeros(params.chess.t.shape[0])]))
    kw = jnp.ones(4, dtype=float)  # the arguments' types as in calibrate()'s passes: one compilation
    twin = _solve(twin, arr, hold, loss=loss, scale=scale, max_steps=max_steps, rtol=_RTOL_START, kind_weight=kw).params
    c_now = np.asarray(_block_costs(params, arr, loss, scale))[:n_p]
    c_twin = np.asarray(_block_costs(twin, arr, loss, scale))[:n_p]
    better = c_twin < c_now - 1e-9
    if not better.any():
        return params, 0
    b = jnp.asarray(better)
    poses = Pose(
        jnp.where(b[:, None, None], twin.poses.R, params.poses.R), jnp.where(b[:, None], twin.poses.t, params.poses.t)
    )
    turned = np.sum(np.asarray(twin.poses.R)[:, :, 2] * R[:, :, 2], axis=1) < np.cos(np.radians(10.0))
    return Params(params.rig, poses, params.chess), int(np.sum(better & turned))


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
    las = Lasers(lasers.points[i][None], lasers.directions[i][None]).retract(delta4[None])
    p, d = las.points[0], las.directions[0]
    foot = p + jnp.dot(x_ref - p, d) * d
    return foot - x_ref


def laser_std(rig: Rig, cov_glob: np.ndarray, x_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per laser: position std (mm) of the line at ``x_ref`` and direction std (rad)."""
    n = rig.lasers.n
    pos, ang = np.zeros(n), np.zeros(n)
    cov_glob = np.asarray(cov_glob)
    for i in range(n):
        sl = slice(14 + 4 * i, 18 + 4 * i)
        c = cov_glob[sl, sl]
        j = np.asarray(jax.jacfwd(lambda d, i=i: _laser_offset(rig.lasers, i, jnp.asarray(x_ref[i]), d))(jnp.zeros(4)))
        pos[i] = np.sqrt(max(np.trace(j @ c @ j.T), 0.0))
        ang[i] = np.sqrt(max(c[2, 2] + c[3, 3], 0.0))
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


def cramer_rao(truth: Calibration, obs: Observations, sigma: float) -> dict:
    """The Cramer-Rao bound of a scene: ``sigma^2 (J^T J)^-1`` at the true parameters.

    Returns the covariance and, per laser, the bound's position std at the working
    point (mm) and direction std (rad), with their RMS over lasers.
    """
    pk = pack(obs)
    poses = stack_poses([truth.board_poses[v][b] for v, b in pk.pose_keys])
    chess = [truth.calibration_view_poses[c] for c in pk.chess_keys] if truth.calibration_view_poses else []
    chess_stack = stack_poses(chess) if chess else Pose(jnp.zeros((0, 3, 3)), jnp.zeros((0, 3)))
    params = Params(truth.rig, poses, chess_stack)
    masks = make_masks(params)
    # plain least squares (Huber at 1e9 px), sharing the compiled covariance of calibrate()
    cov = _covariance(params, _arrays(pk), masks, "huber", 1e9, sigma=sigma, kind_weight=jnp.ones(4, dtype=float))
    x_ref = laser_working_points(truth.rig, poses, pk)
    pos, ang = laser_std(truth.rig, np.asarray(cov.glob), x_ref)
    return {
        "cov": cov,
        "x_ref": x_ref,
        "position_std_mm": pos,
        "direction_std_rad": ang,
        "position_rms_mm": float(np.sqrt(np.mean(pos**2))),
        "direction_rms_rad": float(np.sqrt(np.mean(ang**2))),
    }


# ----------------------------------------------------------------------------- report and output


def _obs_table(result: CalibrationResult):
    """Per observation: kind, 2D residual norm (px), validity, and its (view, board, laser) labels."""
    pk = result.packed
    norm, kind, ok = _per_observation(result.params, pk)
    n_obs = norm.size
    n_d, n_s, n_r = pk.dot_pose.shape[0], pk.spot_pose.shape[0], pk.rim_pixels.shape[0]
    view = np.full(n_obs, -1)
    board = np.full(n_obs, "", dtype=object)
    laser = np.full(n_obs, -1)
    keys = pk.pose_keys
    for i, k in enumerate(np.asarray(pk.dot_pose)):
        view[i], board[i] = keys[k]
    for j, (k, las) in enumerate(zip(np.asarray(pk.spot_pose), np.asarray(pk.spot_laser), strict=True)):
        view[n_d + j], board[n_d + j] = keys[k]
        laser[n_d + j] = las
    for j, k in enumerate(np.asarray(pk.chess_pose)):
        view[n_d + n_s + n_r + j] = pk.chess_keys[k]
    return norm, kind, ok, view, board, laser


def _rms(x):
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else None


def report(result: CalibrationResult, obs: Observations) -> dict:
    """The ``residuals`` and ``uncertainty`` sections of the output (plain JSON types)."""
    norm, kind, ok, view, board, laser = _obs_table(result)
    sigma = float(result.cov.sigma)
    outlier = ok & (kind <= 1) & (norm > 5.0 * sigma)
    per_view = {obs.views[v].name: _rms(norm[ok & (kind <= 1) & (view == v)]) for v in range(len(obs.views))}
    boards = sorted({b for b in board if b})
    per_board = {b: _rms(norm[ok & (kind == 0) & (board == b)]) for b in boards}
    per_laser = {str(i): _rms(norm[ok & (kind == 1) & (laser == i)]) for i in range(obs.n_lasers)}
    per_direct = {
        obs.calibration_views[c].name: _rms(norm[ok & (kind == 3) & (view == c)]) for c in result.packed.chess_keys
    }
    outliers = []
    for i in np.flatnonzero(outlier):
        item = {
            "kind": KIND_NAMES[kind[i]],
            "view": obs.views[view[i]].name,
            "board": board[i],
            "residual_px": float(norm[i]),
        }
        if kind[i] == 1:
            item["laser"] = int(laser[i])
        outliers.append(item)
    residuals = {
        "rms_px": _rms(norm[ok]),
        "sigma_px": sigma,
        "dof": int(result.cov.dof),
        "by_kind_rms_px": {KIND_NAMES[k]: _rms(norm[ok & (kind == k)]) for k in range(4)},
        "by_kind_sigma_px": {k: (None if not np.isfinite(v) else v) for k, v in result.kind_sigma.items()},
        "per_view_rms_px": per_view,
        "per_board_rms_px": per_board,
        "per_laser_rms_px": per_laser,
        "per_direct_view_rms_px": per_direct,
        "invalid": int(np.sum(~ok)),
        "outliers": outliers,
        "rim_outliers": int(np.sum(ok & (kind == 2) & (norm > 5.0 * (result.kind_sigma.get("rim") or sigma)))),
        "loss": {"kind": result.loss, "scale_px": result.scale},
    }
    cov = np.asarray(result.cov.glob)
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    x_ref = laser_working_points(result.rig, result.params.poses, result.packed)
    pos, ang = laser_std(result.rig, cov, x_ref)
    uncertainty = {
        "sigma_px": sigma,
        "camera_std": dict(zip(["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"], sd[:9].tolist(), strict=True)),
        "mirror_std": {"apex_mm": sd[9:12].tolist(), "axis_tilt_deg": np.degrees(sd[12:14]).tolist()},
        "lasers": [
            {
                "working_point": x_ref[i].tolist(),
                "working_range_mm": float(np.linalg.norm(x_ref[i])),
                "position_std_mm": float(pos[i]),
                "direction_std_deg": float(np.degrees(ang[i])),
            }
            for i in range(result.rig.lasers.n)
        ],
        "covariance": {
            "parameters": "camera (fx, fy, cx, cy, k1, k2, p1, p2, k3), mirror (apex dx, dy, dz mm; axis tilt "
            "e1, e2 rad), then per laser (point offset e1, e2 mm; direction tilt e1, e2 rad) with (e1, e2) "
            "the orthonormal basis of slcvjax._safe.orthonormal_basis about the axis / laser direction",
            "matrix": cov.tolist(),
        },
    }
    return {"residuals": residuals, "uncertainty": uncertainty}


def _rig_json(rig: Rig) -> dict:
    from ._io import calibration_to_json

    doc = calibration_to_json(Calibration(rig))
    return {k: doc[k] for k in ("camera", "mirror", "lasers")}


def to_calibration(result: CalibrationResult, obs: Observations) -> Calibration:
    """The ``slcv-calibration/1`` content of a result (joint solution, staged beside it)."""
    pk = result.packed
    board_poses: list[dict[str, Pose]] = [{} for _ in obs.views]
    for k, (v, b) in enumerate(pk.pose_keys):
        board_poses[v][b] = Pose(result.params.poses.R[k], result.params.poses.t[k])
    cvp: list[Pose | None] = [None] * len(obs.calibration_views)
    for k, c in enumerate(pk.chess_keys):
        cvp[c] = Pose(result.params.chess.R[k], result.params.chess.t[k])
    rep = report(result, obs)
    st = result.staged
    stages = {
        "staged": {
            **_rig_json(Rig(st.camera, st.mirror, st.lasers)),
            "reports": [{"stage": r.name, "rms": r.rms, "unit": r.unit, "notes": r.notes} for r in st.reports],
        },
        "joint": {"passes": [p.__dict__ for p in result.passes], "timings_s": result.timings},
    }
    return Calibration(result.rig, board_poses, cvp, {**rep, "stages": stages})


_project_board = jax.jit(project_board_points)
_project_spots = jax.jit(project_spots)
_project_rim = jax.jit(project_rim)


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
            uv, ok = _project_board(rig, poses[b], jnp.asarray(obs.boards[b], dtype=float))
            dots[b] = np.where(np.asarray(ok)[:, None], np.asarray(uv), np.nan)
    spots = np.full((len(v.spots), 2), np.nan)
    for i, s in enumerate(v.spots):
        if s.board in poses:
            uv, ok = _project_spots(rig, poses[s.board], jnp.asarray([s.laser]))
            if bool(ok[0]):
                spots[i] = np.asarray(uv[0])
    uv, ok = _project_rim(rig, jnp.linspace(0.0, 2 * np.pi, rim_points, endpoint=False))
    return {"dots": dots, "spots": spots, "rim": np.asarray(uv)[np.asarray(ok)]}
