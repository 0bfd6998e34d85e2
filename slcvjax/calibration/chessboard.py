"""Plain camera calibration from chessboard images (the ``camera`` command).

Corners by ``cv2.findChessboardCorners`` + ``cv2.cornerSubPix``; a start by
``cv2.calibrateCamera``; then the project's own Levenberg-Marquardt over the camera and
every board pose (the joint solver with only corner residuals), which minimises the same
reprojection error in float64 to a tight tolerance.
"""

from dataclasses import dataclass
from pathlib import Path

import cv2
import jax.numpy as jnp
import numpy as np

from ..geometry.camera import Camera
from ..geometry.pose import Pose
from ..geometry.rig import Rig
from ..observations.formats import CalibrationViewObs, Observations
from ..observations.problem import Layout, pack, stack_poses, unstack_poses
from .base import CalibrationError
from .staged import calibrate_intrinsics


def board_points(cols: int, rows: int, square: float) -> np.ndarray:
    """Inner-corner positions of a ``cols x rows`` chessboard, OpenCV's order, z = 0 (mm)."""
    x, y = np.meshgrid(np.arange(cols) * square, np.arange(rows) * square)
    return np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)


OMNI_WINDOW = 5  # px: the refiner's half-window through a mirror (which bends the edges within a larger one)


def refine_windows(corners: np.ndarray, pattern: tuple[int, int], largest: int = OMNI_WINDOW) -> np.ndarray:
    """Each corner's refiner half-window (px) in a grid seen through a mirror: ``largest``, or half
    the distance to its nearest grid neighbour where that is less (at least 2), so that its window
    stays inside the squares that meet at it (a board seen through a convex mirror is squeezed
    several times over across the image, and bent within a large window)."""
    cols, rows = pattern
    g = np.asarray(corners, float).reshape(rows, cols, 2)
    near = np.full((rows, cols), np.inf)
    for axis in (0, 1):
        if g.shape[axis] > 1:
            d = np.linalg.norm(np.diff(g, axis=axis), axis=2)
            lo = [slice(None)] * 2
            hi = [slice(None)] * 2
            lo[axis], hi[axis] = slice(None, -1), slice(1, None)
            near[tuple(lo)] = np.minimum(near[tuple(lo)], d)
            near[tuple(hi)] = np.minimum(near[tuple(hi)], d)
    return np.clip(np.where(np.isfinite(near), near // 2, largest), 2, largest).astype(int).ravel()


def detect_corners(
    path: str | Path, pattern: tuple[int, int], window: int | None = 11
) -> tuple[np.ndarray | None, tuple[int, int]]:
    """Sub-pixel inner corners (N, 2) of a chessboard image, or None where none is found.

    ``window``: the refiner's half-window in px (``None``: each corner's own,
    :func:`refine_windows`).  Raises :class:`CalibrationError` for a file that cannot be read as an image.
    """
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise CalibrationError(f"{path}: cannot be read as an image")
    found, corners = cv2.findChessboardCorners(
        img, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    )
    size = (img.shape[1], img.shape[0])
    if not found:
        return None, size
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-3)
    if window is not None:
        corners = cv2.cornerSubPix(img, corners, (int(window), int(window)), (-1, -1), crit)
        return corners.reshape(-1, 2).astype(float), size
    windows = refine_windows(corners.reshape(-1, 2), pattern)
    out = corners.reshape(-1, 2).astype(np.float32)
    for w in np.unique(windows):
        sel = windows == w
        out[sel] = cv2.cornerSubPix(img, out[sel].reshape(-1, 1, 2).copy(), (int(w), int(w)), (-1, -1), crit).reshape(
            -1, 2
        )
    return out.astype(float), size


@dataclass
class CameraCalibration:
    camera: Camera
    poses: list[Pose]
    used: list[str]
    missing: list[str]
    rms_px: float
    per_view_rms_px: dict[str, float]
    opencv_rms_px: float
    corners: list[np.ndarray]


def calibrate_from_corners(
    names: list[str], corners: list[np.ndarray], points: np.ndarray, size: tuple[int, int]
) -> CameraCalibration:
    """Calibrate from detected corners: OpenCV's start, then the joint LM on the corners alone."""
    from .evaluate import per_observation, solve_compiled
    from .params import Params, make_masks, pad_masks, pad_params, unpad_params

    views = [
        CalibrationViewObs(n, "chess", c, np.ones(len(c), dtype=bool)) for n, c in zip(names, corners, strict=True)
    ]
    obs = Observations(size, 1.0, 1.0, 0, {"chess": points}, views, [])
    cam0, poses0, rep = calibrate_intrinsics(obs)
    pk = pack(obs, use_views=False)
    no_poses = Pose(jnp.zeros((0, 3, 3)), jnp.zeros((0, 3)))
    params = Params(Rig.camera_only(cam0), no_poses, stack_poses([poses0[i] for i in pk.chess_keys]))
    masks = make_masks(params, {"mirror"})
    layout = Layout.of(pk)
    res = solve_compiled(
        pad_params(layout, params),
        layout.pad_packed(pk),
        pad_masks(layout, masks),
        loss="linear",
        scale=1.0,
        max_steps=100,
    )
    params = unpad_params(layout, res.params)
    norm, _, _ = per_observation(params, pk)
    per_pt = norm**2
    view_of = np.asarray(pk.chess_pose)
    per_view = {names[pk.chess_keys[k]]: float(np.sqrt(np.mean(per_pt[view_of == k]))) for k in range(pk.n_chess)}
    return CameraCalibration(
        params.rig.camera,
        unstack_poses(params.chess),
        [names[k] for k in pk.chess_keys],
        [],
        float(np.sqrt(np.mean(per_pt))),
        per_view,
        rep.rms,
        corners,
    )


def calibrate_camera_images(paths: list[str | Path], pattern: tuple[int, int], square: float) -> CameraCalibration:
    """Detect the chessboard in every image and calibrate the camera (see the module doc)."""
    names, corners, missing, size = [], [], [], None
    for p in paths:
        c, s = detect_corners(p, pattern)
        if size is not None and s != size:
            raise CalibrationError(f"{p}: image size {s[0]}x{s[1]} differs from the first image's {size[0]}x{size[1]}")
        size = s
        if c is None:
            missing.append(str(p))
        else:
            names.append(str(p))
            corners.append(c)
    if len(corners) < 3:
        raise CalibrationError(
            f"a {pattern[0]}x{pattern[1]} chessboard was found in {len(corners)} image(s); need at least 3"
        )
    result = calibrate_from_corners(names, corners, board_points(*pattern, square), size)
    result.missing = missing
    return result
