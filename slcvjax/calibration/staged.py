"""The staged calibration (the paper's method), each stage usable alone.

1. :func:`calibrate_intrinsics` -- Zhang's method on the direct chessboard views (OpenCV).
2. :func:`mirror_from_rim` -- the rim circle (known radius) from its edge pixels: every
   rim pixel's ray must meet the circle, so the circle's centre C and normal n minimise
   ``sum (|X_i - C| - r)^2`` with ``X_i`` the ray's point on the plane ``n.(X - C) = 0``.
   A circle seen in perspective has two such poses (the two-fold ambiguity); both are
   returned and :func:`staged` keeps the one under which the boards fit best.
3. :func:`board_poses` -- a generalized (non-central) planar PnP: a DLT on the reflected
   rays about their mean origin, then Gauss-Newton on the true rays' point-to-ray
   distances (divided by range, so the error is an angle).
4. :func:`fit_lasers` -- each spot's reflected ray meets its board's plane at a 3D
   point; a 3D line per laser by consensus over its spots, then least squares; spots
   that lie near another laser's line instead of their own are given that laser, spots
   near none are left out.
"""

import contextlib
import dataclasses
import threading
from dataclasses import dataclass

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from ..geometry.camera import Camera, undistort
from ..geometry.lasers import Lasers
from ..geometry.mirror import Mirror, back_project, mirror_of_shape
from ..geometry.pose import Pose, so3_exp
from ..geometry.rig import Rig
from ..geometry.sheets import Sheets
from ..observations.formats import Observations, SpotObs, StripeObs, ViewObs, shape_missing
from ..observations.problem import (
    POSE_LADDER,
    Packed,
    bucket,
    map_padded,
    map_rows,
    pack,
    pad_rows,
    unstack_poses,
)
from ..support.persist import PersistentJit
from .base import CalibrationError, StageReport, rays_with_pixel_metric
from .laser_fit import fit_lasers
from .options import DEFAULT_POLICY, RobustPolicy
from .sheet_fit import fit_sheets

_CV_LOCK = threading.Lock()


@contextlib.contextmanager
def _opencv_one_thread():
    """OpenCV on one thread while inside: its threaded ``calibrateCamera`` sums in a varying order,
    so the same corners gave intrinsics differing by ~4e-8 px from call to call, and the whole
    calibration was not reproducible.  The lock keeps concurrent calibrations from racing on
    OpenCV's global thread count."""
    with _CV_LOCK:
        n = cv2.getNumThreads()
        cv2.setNumThreads(1)
        try:
            yield
        finally:
            cv2.setNumThreads(n)


_back_many = PersistentJit(map_rows(jax.vmap(back_project, in_axes=(None, None, 0))), "back_project")


_undistort_many = PersistentJit(map_rows(jax.vmap(undistort, in_axes=(None, 0))), "undistort")
_so3_exp_many = PersistentJit(map_rows(jax.vmap(so3_exp)), "so3_exp")


# ----------------------------------------------------------------------------- 1. intrinsics


def calibrate_intrinsics(obs: Observations, flags: int = 0) -> tuple[Camera, dict[int, Pose], StageReport]:
    """Camera intrinsics and direct-view poses from ``obs.calibration_views`` (OpenCV).

    Views with fewer than 6 corners are skipped (listed in the report).  Returns the
    camera, the pose ``T_cam_board`` of each used view (keyed by its index) and a report
    whose ``rms`` is OpenCV's RMS reprojection error in px.
    """
    w, h = obs.image_size
    objp, imgp, used, skipped = [], [], [], []
    for i, cv in enumerate(obs.calibration_views):
        if cv.seen.sum() < 6:
            skipped.append(cv.name)
            continue
        objp.append(obs.boards[cv.board][cv.seen].astype(np.float32))
        imgp.append(cv.pixels[cv.seen].astype(np.float32).reshape(-1, 1, 2))
        used.append(i)
    if len(used) < 3:
        raise CalibrationError(
            f"calibration_views: {len(used)} usable direct chessboard views (need at least 3 with 6 or more corners)"
        )
    with _opencv_one_thread():
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(objp, imgp, (w, h), None, None, flags=flags)
    cam = Camera.create(K[0, 0], K[1, 1], K[0, 2], K[1, 2], dist.ravel()[:5], w, h)
    poses = {i: Pose.from_rvec(r.ravel(), t.ravel()) for i, r, t in zip(used, rvecs, tvecs, strict=True)}
    notes = [f"{len(used)} views"] + ([f"skipped (under 6 corners): {', '.join(skipped)}"] if skipped else [])
    return cam, poses, StageReport("intrinsics", float(rms), "px", notes)


# ----------------------------------------------------------------------------- 2. mirror from the rim


def _circle_normal(c, tilt):
    """The rim circle's normal: the line of sight to its centre ``c`` tilted by ``tilt`` (2,)
    along the basis ``(e1, e2)`` across it (``e1`` across the image's y axis)."""
    n0 = c / jnp.linalg.norm(c)
    e1 = jnp.cross(n0, jnp.array([0.0, 1.0, 0.0]))
    e1 = e1 / jnp.linalg.norm(e1)
    e2 = jnp.cross(n0, e1)
    n = n0 + tilt[0] * e1 + tilt[1] * e2
    return n / jnp.linalg.norm(n)


def _rim_residual(y, args):
    rays, radius, scale, weight = args
    c = y[:3]
    n = _circle_normal(c, y[3:])
    lam = jnp.dot(c, n) / (rays @ n)
    x = lam[:, None] * rays
    return (jnp.linalg.norm(x - c, axis=1) - radius) * scale * weight


def _small_lm(res, retract, x0, dim: int, steps: int):
    """``steps`` Levenberg-Marquardt steps on a small problem (jit- and vmap-friendly).

    ``res(x)`` is the residual vector, ``retract(x, delta)`` moves ``x`` (any pytree) by a
    tangent step of size ``dim``.  A fixed count, so that a batch of problems runs in
    lockstep.  Returns ``x`` and its sum of squares.

    Kept over optimistix's ``LevenbergMarquardt``: on the preset's rim circle (nine starts in
    one vmapped call) it ran 29 ms against optimistix's 185 ms (16-80 steps) to the same best
    RMS, in one run of ``benchmarks/bench_solvers.py`` (``benchmarks/results/solvers.json``).
    """

    def body(_, s):
        x, lam, cost = s
        r = res(x)
        jac = jax.jacfwd(lambda d: res(retract(x, d)))(jnp.zeros(dim))
        h = jac.T @ jac
        step = jnp.linalg.solve(h + lam * jnp.diag(jnp.diag(h) + 1e-12), -jac.T @ r)
        x2 = retract(x, step)
        c2 = jnp.sum(res(x2) ** 2)
        ok = c2 < cost
        x = jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), x2, x)
        return x, jnp.where(ok, lam / 3, lam * 4), jnp.where(ok, c2, cost)

    x, _, cost = jax.lax.fori_loop(0, steps, body, (x0, jnp.asarray(1e-3), jnp.sum(res(x0) ** 2)))
    return x, cost


def _fit_circle(y0, rays, weight, radius, scale):
    """The rim circle from one start: 15 LM steps (the preset's fits settle to 6 digits within 10).

    ``weight`` (R,): 1 for a ray, 0 for padding."""
    y, cost = _small_lm(lambda y: _rim_residual(y, (rays, radius, scale, weight)), lambda y, d: y + d, y0, 5, 15)
    return y, jnp.sqrt(cost / jnp.maximum(jnp.sum(weight), 1.0))


# all starts in one call
_fit_circles = PersistentJit(jax.vmap(_fit_circle, in_axes=(0, None, None, None, None)), "fit_circles")


def _circle_pose(y):
    y = np.asarray(y)
    return y[:3], np.asarray(_circle_normal(jnp.asarray(y[:3]), jnp.asarray(y[3:])))


def rim_circle_problem(camera: Camera, rim: np.ndarray, radius: float) -> tuple:
    """The rim circle's fit as :func:`_fit_circle` takes it: ``(y0, rays, weight, radius, scale)``
    with nine starting tilts ``y0`` (9, 5) about the circle of the rim pixels' ellipse, the
    undistorted rays padded to a bucket (``weight`` 1 for a ray, 0 for padding) and the
    residual's scale (px per mm at the rim's distance)."""
    xy, ok = map_padded(_undistort_many, camera, rows=rim)
    xy = np.asarray(xy)[np.asarray(ok)]
    rays = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    f = float(camera.fx)
    (cx, cy), (aw, ah), _ = cv2.fitEllipse((xy * f).astype(np.float32))
    semi = (aw + ah) / 4.0 / f
    d0 = radius / semi
    c0 = np.array([cx / f, cy / f, 1.0])
    c0 = c0 / np.linalg.norm(c0) * d0
    scale = f / d0
    tilts = np.radians(4.0) * np.array([(0, 0), (1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, -1), (1, -1), (-1, 1)])
    y0 = np.concatenate([np.broadcast_to(c0, (len(tilts), 3)), tilts], axis=1)
    # every start's LM visits every ray, padding included: a finer ladder than the loops'
    # (measured, benchmarks/bench_calibrate.py: with 4096 rays here and 64 slots per board
    # below, the preset's staged stages took 0.36 s; with these, 0.16 s)
    size = bucket(len(rays), 2048, 2)
    padded = pad_rows(rays, size, np.array([0.0, 0.0, 1.0]))
    weight = (np.arange(size) < len(rays)).astype(float)
    return jnp.asarray(y0), jnp.asarray(padded), jnp.asarray(weight), float(radius), float(scale)


def mirror_from_rim(
    camera: Camera, rim_pixels: np.ndarray, radius: float, height: float, shape: dict | None = None
) -> tuple[list[Mirror], StageReport]:
    """Candidate mirror poses (one or two) from the rim's edge pixels: the rim circle of
    ``radius`` at the sag ``height`` from the vertex, of a mirror of ``shape`` (None: the cone).

    The circle is fitted from nine starting tilts; distinct solutions whose RMS is
    within 1.5x of the best are returned, best first.  ``rms`` is in px (first order).
    """
    rim = np.asarray(rim_pixels, float).reshape(-1, 2)
    if len(rim) < 5:
        raise CalibrationError(f"views[*].rim: {len(rim)} rim pixels in all (need at least 5 to fit the rim circle)")
    ys, rmss = (np.asarray(a) for a in _fit_circles(*rim_circle_problem(camera, rim, radius)))
    sols = [
        (float(rms), _circle_pose(y))
        for y, rms in zip(ys, rmss, strict=True)
        if np.all(np.isfinite(y)) and np.isfinite(rms)
    ]
    if not sols:
        raise CalibrationError("views[*].rim: the rim circle could not be fitted")
    sols.sort(key=lambda s: s[0])
    best = sols[0][0]
    distinct: list[tuple[float, tuple]] = []
    for rms, (c, n) in sols:
        if rms > 1.5 * best + 1e-9:
            continue
        if all(np.degrees(np.arccos(np.clip(abs(n @ n2), -1, 1))) > 0.05 for _, (_, n2) in distinct):
            distinct.append((rms, (c, n)))
    mirrors = []
    for _, (c, n) in distinct[:2]:
        if n @ c < 0:  # the axis points away from the camera, towards the rim
            n = -n
        mirrors.append(mirror_of_shape(shape, c - height * n, n, radius, height))
    note = f"{len(rim)} rim pixels, {len(mirrors)} candidate pose(s)"
    return mirrors, StageReport("mirror", best, "px", [note])


# ----------------------------------------------------------------------------- 3. board poses


def _dlt_planar(xb, d, m, mask):
    """Batched planar DLT about the rays' mean origin: (P, M, .) arrays -> R (P,3,3), t (P,3)."""
    w = mask[..., None]
    c = np.sum(m * w, axis=1) / np.maximum(np.sum(w, axis=1), 1)
    z = np.zeros(d.shape[:2])
    hx = np.stack(
        [
            np.stack([z, -d[..., 2], d[..., 1]], -1),
            np.stack([d[..., 2], z, -d[..., 0]], -1),
            np.stack([-d[..., 1], d[..., 0], z], -1),
        ],
        axis=-2,
    )  # (P, M, 3, 3)
    a = np.concatenate([xb[..., 0, None, None] * hx, xb[..., 1, None, None] * hx, hx], axis=-1)  # (P,M,3,9)
    a = (a * mask[..., None, None]).reshape(a.shape[0], -1, 9)
    h = np.linalg.svd(a)[2][:, -1]
    r1, r2, tp = h[:, :3], h[:, 3:6], h[:, 6:9]
    s = 2.0 / (np.linalg.norm(r1, axis=1) + np.linalg.norm(r2, axis=1))
    r1, r2, tp = r1 * s[:, None], r2 * s[:, None], tp * s[:, None]
    front = np.einsum("pmi,pmi->pm", xb[..., :1] * r1[:, None] + xb[..., 1:2] * r2[:, None] + tp[:, None], d)
    sign = np.where(np.sum(front * mask, axis=1) < 0, -1.0, 1.0)[:, None]
    r1, r2, tp = r1 * sign, r2 * sign, tp * sign
    u, _, vt = np.linalg.svd(np.stack([r1, r2, np.cross(r1, r2)], axis=2))
    det = np.linalg.det(u @ vt)
    R = u @ (np.eye(3)[None] * np.stack([np.ones_like(det), np.ones_like(det), det], 1)[:, None, :]) @ vt
    return R, tp + c


def flipped(R: np.ndarray, t: np.ndarray, xb: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mirror-image pose of each planar board: normal reflected about the line of sight to its centre."""
    w = mask[..., None]
    xbar = np.sum(xb * w, axis=1) / np.maximum(np.sum(w, axis=1), 1)
    centre = np.einsum("pij,pj->pi", R, xbar) + t
    v = centre / np.linalg.norm(centre, axis=1, keepdims=True)
    n = R[:, :, 2]
    n2 = 2 * np.sum(n * v, axis=1, keepdims=True) * v - n
    axis = np.cross(n, n2)
    s = np.linalg.norm(axis, axis=1, keepdims=True)
    ang = np.arctan2(s[:, 0], np.sum(n * n2, axis=1))
    axis = np.where(s > 1e-12, axis / np.maximum(s, 1e-300), 0.0)
    Q = map_padded(_so3_exp_many, rows=axis * ang[:, None]).reshape(-1, 3, 3)
    R2 = Q @ R
    return R2, centre - np.einsum("pij,pj->pi", R2, xbar)


def _pose_resid(R, t, xb, m, proj):
    v = xb @ R.T + t - m
    # range along the ray: proj rows are orthogonal to the ray, so use |v| as the range
    rng = jnp.maximum(jnp.linalg.norm(v, axis=-1), 1e-6)
    return jnp.einsum("nij,nj->ni", proj, v) / rng[:, None]


def _refine_poses(R, t, xb, m, d, metric, mask):
    """Batched Levenberg-Marquardt (20 steps) of planar poses on pixel-weighted ray distances."""

    def one(R, t, xb, m, d, metric, mask):
        proj = metric @ (jnp.eye(3)[None] - d[:, :, None] * d[:, None, :]) * mask[:, None, None]
        (R, t), cost = _small_lm(
            lambda x: _pose_resid(x[0], x[1], xb, m, proj).ravel(),
            lambda x, dl: (so3_exp(dl[:3]) @ x[0], x[1] + dl[3:]),
            (R, t),
            6,
            20,
        )
        return R, t, jnp.sqrt(cost / jnp.maximum(jnp.sum(mask), 1))

    return jax.vmap(one)(R, t, xb, m, d, metric, mask)


# the boards refined BOARD_CHUNK at a time in one compiled loop (:func:`map_rows`): one
# compilation for every number of boards in a bucket of the pose ladder, and the padded boards
# skipped, so the work follows the boards there are (10 boards are one chunk, not 64 boards)
BOARD_CHUNK = 16
_refine_boards = PersistentJit(map_rows(lambda rows: _refine_poses(*rows), BOARD_CHUNK), "refine_poses")


MIN_POSE_DOTS = 4  # the fewest dots whose rays fix a board's pose (planar PnP)


def dots_on_mirror(camera: Camera, mirror: Mirror, pk: Packed) -> np.ndarray:
    """Per (view, board) pose of ``pk``: how many of its dots back-project onto ``mirror`` (n_poses,)."""
    rays, _ = map_padded(rays_with_pixel_metric, camera, mirror, rows=pk.dot_pixels)
    return np.bincount(np.asarray(pk.dot_pose)[np.asarray(rays.valid)], minlength=pk.n_poses)


def without_boards(obs: Observations, keys: set[tuple[int, str]]) -> Observations:
    """``obs`` with the boards ``keys`` ((view, board name)) left out of their views: their dots
    dropped, and the spots and stripes on them left without a board (placed again later on the
    first board plane their ray meets)."""
    views = []
    for vi, v in enumerate(obs.views):
        gone = {b for (w, b) in keys if w == vi}
        if not gone:
            views.append(v)
            continue
        views.append(
            dataclasses.replace(
                v,
                boards={b: x for b, x in v.boards.items() if b not in gone},
                spots=[dataclasses.replace(s, board=None) if s.board in gone else s for s in v.spots],
                stripes=[dataclasses.replace(s, board=None) if s.board in gone else s for s in v.stripes],
            )
        )
    return dataclasses.replace(obs, views=views)


def board_poses(
    camera: Camera, mirror: Mirror, pk: Packed, start: Pose | None = None, flips: bool = True
) -> tuple[list[Pose], StageReport]:
    """The pose of every (view, board) of ``pk`` from its dots, by generalized planar PnP.

    ``start`` (stacked poses): refine from these instead of the DLT (both the start and
    its flipped twin are tried).  ``flips=False``: the flipped twins are not tried (half the
    work, for a search that scores many rigs).
    """
    rays, metric = map_padded(rays_with_pixel_metric, camera, mirror, rows=pk.dot_pixels)
    org, dirs, ok = np.asarray(rays.point), np.asarray(rays.direction), np.asarray(rays.valid)
    metric = np.asarray(metric)
    idx = np.asarray(pk.dot_pose)
    pts = np.asarray(pk.dot_points)
    n_p = pk.n_poses
    counts = np.bincount(idx[ok], minlength=n_p)
    for k in np.flatnonzero(counts < MIN_POSE_DOTS):
        vi, b = pk.pose_keys[k]
        raise CalibrationError(
            f"views[{vi}].boards.{b}: {int(counts[k])} dots back-project onto the mirror (need at least 4 for its pose)"
        )
    mx = bucket(int(np.bincount(idx, minlength=n_p).max()), 16, 2)  # each board's LM visits every slot
    shape = (bucket(n_p, *POSE_LADDER), mx)  # padded boards have no point (mask 0) and are skipped
    xb, m, d = np.zeros(shape + (3,)), np.zeros(shape + (3,)), np.tile([0.0, 0.0, 1.0], shape + (1,))
    met, mask = np.zeros(shape + (2, 3)), np.zeros(shape)
    # each board's dots in its slots 0, 1, ... in their order in pk
    rows = np.flatnonzero(ok)
    rows = rows[np.argsort(idx[rows], kind="stable")]
    k = idx[rows]
    j = np.arange(len(rows)) - np.searchsorted(k, k)
    xb[k, j], m[k, j], d[k, j], met[k, j], mask[k, j] = pts[rows], org[rows], dirs[rows], metric[rows], 1.0
    data = (xb, m, d, met, mask)

    def refine(R, t):  # the real boards' poses refined from (R, t); padded boards are skipped
        R, t = pad_rows(R, shape[0], np.eye(3)), pad_rows(t, shape[0], np.array([0.0, 0.0, 1.0]))
        return tuple(np.asarray(a)[:n_p] for a in _refine_boards((R, t, *data), n_p))

    starts = [_dlt_planar(xb[:n_p], d[:n_p], m[:n_p], mask[:n_p])]
    if start is not None:
        starts.append((np.asarray(start.R), np.asarray(start.t)))
    R = t = errs = None
    for R0, t0 in starts:
        R1, t1, e1 = refine(R0, t0)
        # a small planar target has a second, flipped pose (its normal mirrored about the
        # line of sight); refine that one too and keep the best fit of all candidates
        found = [(R1, t1, e1)]
        if flips:
            found.append(refine(*flipped(R1, t1, xb[:n_p], mask[:n_p])))
        for Rc, tc, ec in found:
            ec = np.where(np.isfinite(ec), ec, np.inf)
            if R is None:
                R, t, errs = Rc, tc, ec
                continue
            better = ec < errs
            R = np.where(better[:, None, None], Rc, R)
            t = np.where(better[:, None], tc, t)
            errs = np.where(better, ec, errs)
    poses = unstack_poses(Pose(R, t))
    rms = float(np.sqrt(np.mean(np.square(errs)))) if errs.size else 0.0
    return poses, StageReport("board_poses", rms, "px (first order)", [f"{len(poses)} board poses"])


# ----------------------------------------------------------------------------- the whole staged pipeline


@dataclass
class Staged:
    """The staged result: camera, mirror, lasers, board poses, direct-view poses, reports."""

    camera: Camera
    mirror: Mirror
    lasers: Lasers
    poses: list[Pose]
    chess_poses: dict[int, Pose]
    reports: list[StageReport]
    packed: Packed | None = None
    undetermined: tuple[int, ...] = ()  # lasers whose spots cannot fix a line (see fit_lasers)
    sheets: Sheets | None = None  # the line and ring lasers (see fit_sheets)
    kinds: tuple[str, ...] = ()  # every laser's kind in order (empty: point lasers only)
    undetermined_sheets: tuple[int, ...] = ()  # sheets whose stripes cannot fix them (see fit_sheets)

    @property
    def rig(self) -> Rig:
        """The staged camera, mirror and lasers as one rig."""
        if self.kinds:
            return Rig.of_elements(self.camera, self.mirror, self.lasers, self.sheets, self.kinds)
        return Rig(self.camera, self.mirror, self.lasers)


def staged(
    obs: Observations,
    camera: Camera | None = None,
    pk: Packed | None = None,
    mirror=None,
    policy: RobustPolicy = DEFAULT_POLICY,
) -> Staged:
    """Run the four stages.  ``camera``: a known camera (skips the intrinsics stage);
    ``mirror``: a known mirror pose and shape (skips the rim stage); ``policy``: the lasers'
    consensus and repair thresholds (:class:`slcvjax.calibration.options.RobustPolicy`)."""
    pk = pack(obs) if pk is None else pk
    if not obs.views:
        raise CalibrationError("views: no catadioptric views")
    if pk.n_poses == 0:
        raise CalibrationError("views[*].boards: no board dots seen in any view")
    reports = []
    chess: dict[int, Pose] = {}
    if camera is None:
        camera, chess, rep = calibrate_intrinsics(obs)
        reports.append(rep)
    if mirror is not None:
        mirrors, rep_m = [mirror], StageReport("mirror", float("nan"), "px", ["given (not estimated from the rim)"])
    else:
        missing = shape_missing(obs.mirror_shape)
        if missing:
            raise CalibrationError(
                f"mirror_shape: the rim stage needs the {obs.mirror_shape['kind']}'s {', '.join(missing)} (left out, "
                "they are estimated only from views through the mirror alone: no calibration_views, no camera given)"
            )
        rim = np.concatenate([v.rim for v in obs.views]) if obs.views else np.zeros((0, 2))
        mirrors, rep_m = mirror_from_rim(camera, rim, obs.mirror_radius, obs.mirror_height, obs.mirror_shape)
    # a board whose dots mostly miss a staged mirror cannot be posed: left out, not the whole calibration
    short = {k for m in mirrors for k in np.flatnonzero(dots_on_mirror(camera, m, pk) < MIN_POSE_DOTS)}
    left_out = []
    if short and len(short) < pk.n_poses:
        keys = {tuple(pk.pose_keys[k]) for k in sorted(short)}
        obs = without_boards(obs, keys)
        pk = pack(obs)
        left_out = [f"views[{vi}].boards.{b}" for vi, b in sorted(keys)]
    best = None
    for i, m in enumerate(mirrors):
        poses, rep_p = board_poses(camera, m, pk)
        if best is None or rep_p.rms < best[2].rms:
            best = (m, poses, rep_p, i)
    mirror, poses, rep_p, chosen = best
    if len(mirrors) > 1:
        rep_m.notes.append(f"two-fold ambiguity resolved by the boards' fit: candidate {chosen + 1} kept")
    if left_out:
        rep_p.notes.append(
            f"{len(left_out)} board(s) left out, fewer than {MIN_POSE_DOTS} of their dots back-project onto the "
            f"staged mirror: {', '.join(left_out)}"
        )
    n_open = sum(s.board is None for v in obs.views for s in v.spots)
    n_open_t = sum(len(s.pixels) for v in obs.views for s in v.stripes if s.board is None)
    if n_open or n_open_t:
        view_poses: list[dict[str, Pose]] = [{} for _ in obs.views]
        for (vi, b), pose in zip(pk.pose_keys, poses, strict=True):
            view_poses[vi][b] = pose
        obs, n_set = assign_spot_boards(obs, camera, mirror, view_poses)
        pk = pack(obs)
        if n_open:
            msg = "spots without a board put on the first board plane their ray meets"
            rep_p.notes.append(f"{n_set} of {n_open} {msg}")
        if n_open_t:
            n_t = n_open_t - sum(len(s.pixels) for v in obs.views for s in v.stripes if s.board is None)
            rep_p.notes.append(
                f"{n_t} of {n_open_t} stripe samples without a board put on the first board plane their ray meets"
            )
    fit = fit_lasers(camera, mirror, pk, poses, obs.n_points, policy=policy)
    reports += [rep_m, rep_p, fit.report]
    if not obs.n_sheets:
        return Staged(camera, mirror, fit.lasers, poses, chess, reports, pk, fit.held)
    kinds = obs.element_kinds
    sf = fit_sheets(camera, mirror, pk, poses, tuple(k for k in kinds if k != "point"))
    return Staged(
        camera, mirror, fit.lasers, poses, chess, reports + [sf.report], pk, fit.held, sf.sheets, kinds, sf.held
    )


def assign_spot_boards(
    obs: Observations, camera: Camera, mirror: Mirror, view_poses: list[dict[str, Pose]]
) -> tuple[Observations, int]:
    """Give each spot that names no board the board whose plane its reflected ray meets first.

    The camera sees the first surface along the reflected ray, so of the boards
    with a pose in that view (``view_poses[v]``: ``T_cam_board`` by board), the nearest
    plane ahead of the mirror is the one the spot lies on (this settles spots near the
    corner of two walls, which the image alone cannot).  That holds only where every
    board posed in some view has a pose in this one; a spot in a view where some board
    is missing keeps no board (and is not used).
    Returns new observations and how many spots got a board.

    A stripe that names no board is split likewise, sample by sample: one stripe per board its
    samples' rays meet first (in the order of its samples), and the samples that get none in a
    stripe that still names no board.
    """
    walls = {b for poses in view_poses for b in poses}
    open_px = [s.pixel for v in obs.views for s in v.spots if s.board is None]
    open_px += [p for v in obs.views for s in v.stripes if s.board is None for p in np.reshape(s.pixels, (-1, 2))]
    rays = map_padded(_back_many, camera, mirror, rows=np.reshape(np.asarray(open_px, dtype=float), (-1, 2)))
    orgs, dirs, oks = (np.asarray(a) for a in (rays.point, rays.direction, rays.valid))
    views, n_set, k = [], 0, 0

    def first_plane(k, cands, n_walls):
        org, d, ok = orgs[k], dirs[k], oks[k]
        best, lam_best = None, np.inf
        # only where every wall has a pose here: otherwise the first plane met may not be the right one
        if ok and len(cands) == n_walls:
            for b, pose in cands:
                n, t = np.asarray(pose.R[:, 2]), np.asarray(pose.t)
                den = n @ d
                if abs(den) > 1e-9:
                    lam = n @ (t - org) / den
                    if 0 < lam < lam_best:
                        best, lam_best = b, lam
        return best

    for vi, v in enumerate(obs.views):
        spots = []
        here = view_poses[vi] if vi < len(view_poses) else {}
        cands = [(b, here[b]) for b in sorted(walls) if b in here]
        for s in v.spots:
            if s.board is not None:
                spots.append(s)
                continue
            best = first_plane(k, cands, len(walls))
            k += 1
            if best is not None:
                s = SpotObs(s.laser, best, s.pixel)
                n_set += 1
            spots.append(s)
        views.append([v, spots, cands])
    out = []
    for v, spots, cands in views:
        stripes = []
        for s in v.stripes:
            if s.board is not None:
                stripes.append(s)
                continue
            px = np.reshape(s.pixels, (-1, 2))
            got = [first_plane(k + j, cands, len(walls)) for j in range(len(px))]
            k += len(px)
            for b in dict.fromkeys(got):
                stripes.append(StripeObs(s.laser, b, px[[g == b for g in got]]))
        out.append(ViewObs(v.name, v.boards, spots, v.rim, stripes))
    return dataclasses.replace(obs, views=out), n_set
