"""Catadioptric cameras from chessboard images seen through the mirror (the ``omni`` command).

Corners: OpenCV's chessboard detector, refined with a window fitted to each image's grid
(:func:`slcvjax.calibration.chessboard.refine_window`: a board seen through a convex mirror is squeezed several
times over across the image).  The board's points are taken in OpenCV's corner order: the
mirror turns the board's image over, but a planar board's pose is a proper rotation whichever
way the grid's indices run on it (its normal may face the camera or away), so a reflected image
needs no relabelling.  The calibration is :func:`slcvjax.calibration.calibrate.calibrate`'s through the mirror
alone: central starts, then the joint passes over the camera, the mirror's pose (and shape,
where not given) and every board's pose.
"""

from pathlib import Path

import jax.numpy as jnp
import numpy as np

from ..calibration.base import CalibrationError
from ..calibration.chessboard import board_points, detect_corners
from ..geometry.rig import project_board_points
from ..observations.formats import Calibration, FormatError, Observations, ViewObs

BOARD = "chess"


def omni_observations(
    images: list[str | Path],
    pattern: tuple[int, int],
    square: float,
    mirror_shape: dict,
    projection: str = "perspective",
) -> tuple[Observations, list[str]]:
    """Observations of a ``cols x rows`` (inner corners) chessboard of ``square`` mm seen
    through the mirror in each image, and the images where no board was found.

    ``mirror_shape`` is an observation file's (its dimensions may be left out); ``projection``
    the camera's (``perspective`` or ``telecentric``).  Raises :class:`slcvjax.observations.formats.FormatError` naming
    the file where an image cannot be read or differs in size from the first, or where no image
    shows the board.
    """
    if not images:
        raise FormatError("images: none given")
    views, missing, size = [], [], None
    n = pattern[0] * pattern[1]
    for path in images:
        try:
            corners, wh = detect_corners(path, pattern, window=None)
        except CalibrationError as e:
            raise FormatError(str(e)) from None
        if size is None:
            size = wh
        elif wh != size:
            raise FormatError(f"{path}: {wh[0]}x{wh[1]} pixels, the first image has {size[0]}x{size[1]}")
        if corners is None:
            missing.append(str(path))
            continue
        views.append(ViewObs(Path(path).name, {BOARD: (corners, np.ones(n, bool))}, [], np.zeros((0, 2))))
    if not views:
        raise FormatError(f"images: no {pattern[0]}x{pattern[1]} chessboard found in any of {len(images)} image(s)")
    boards = {BOARD: board_points(pattern[0], pattern[1], square)}
    obs = Observations(size, 0.0, 0.0, 0, boards, [], views, mirror_shape=mirror_shape, camera_projection=projection)
    return obs, missing


def view_residuals(cal: Calibration, obs: Observations) -> list[dict[str, np.ndarray]]:
    """Per view and board: the observed pixels (M, 2), the residuals predicted - observed (M, 2;
    NaN where the prediction falls off the mirror or the sensor) of the seen points."""
    out = []
    for v, poses in zip(obs.views, cal.board_poses, strict=True):
        per = {}
        for b, (px, seen) in v.boards.items():
            if b not in poses:
                continue
            uv, ok = project_board_points(cal.rig, poses[b], jnp.asarray(obs.boards[b], float))
            r = np.where(np.asarray(ok)[:, None], np.asarray(uv) - px, np.nan)
            per[b] = {"pixels": px[seen], "residuals": r[seen]}
        out.append(per)
    return out


def plot_residuals(images: list[str | Path], cal: Calibration, obs: Observations, path: str | Path) -> Path:
    """One panel per view: its image about the board, the corners and their residual vectors
    (magnified, the scale in the title) and the view's RMS; written as a PNG."""
    import cv2

    from ..plots import pyplot

    plt = pyplot()
    by_name = {Path(p).name: p for p in images}
    res = view_residuals(cal, obs)
    n = len(obs.views)
    cols = min(n, 4)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 4 * rows + 0.4), squeeze=False)
    norms = np.concatenate([np.linalg.norm(d["residuals"], axis=1) for per in res for d in per.values()])
    typical = float(np.nanpercentile(norms, 90)) if np.isfinite(norms).any() else 1.0
    spans = [np.ptp(d["pixels"], axis=0).max() for per in res for d in per.values() if len(d["pixels"])]
    extent = float(np.median(spans)) if spans else float(max(obs.image_size))
    mag = float(10 ** np.round(np.log10(0.08 * extent / max(typical, 1e-6))))
    for k, (v, per) in enumerate(zip(obs.views, res, strict=True)):
        ax = axes[k // cols][k % cols]
        img = cv2.imread(str(by_name[v.name]), cv2.IMREAD_GRAYSCALE) if v.name in by_name else None
        if img is not None:
            ax.imshow(img, cmap="gray", vmin=0, vmax=255)
        errs = []
        for d in per.values():
            px, r = d["pixels"], d["residuals"]
            ok = np.isfinite(r).all(axis=1)
            ax.plot(px[:, 0], px[:, 1], "+", color="tab:cyan", ms=3)
            ax.quiver(px[ok, 0], px[ok, 1], mag * r[ok, 0], mag * r[ok, 1], color="tab:red",
                      angles="xy", scale_units="xy", scale=1.0, width=0.004)  # fmt: skip
            errs.append(np.linalg.norm(r[ok], axis=1))
            if (~ok).any():
                ax.plot(px[~ok, 0], px[~ok, 1], "x", color="tab:orange", ms=5)
        e = np.concatenate(errs) if errs else np.zeros(0)
        rms = float(np.sqrt(np.mean(e * e))) if e.size else float("nan")
        ax.set_title(f"{v.name}: rms {rms:.3f} px", fontsize=9)
        seen = np.concatenate([d["pixels"] for d in per.values()]) if per else np.zeros((0, 2))
        if len(seen):  # about the board, square
            c, half = 0.5 * (seen.min(0) + seen.max(0)), 0.65 * np.ptp(seen, axis=0).max() + 10.0
            ax.set_xlim(c[0] - half, c[0] + half)
            ax.set_ylim(c[1] + half, c[1] - half)
        ax.set_xticks([])
        ax.set_yticks([])
    for k in range(n, rows * cols):
        axes[k // cols][k % cols].axis("off")
    fig.suptitle(f"residuals (predicted - detected) x {mag:g}; orange x: predicted off the mirror or the sensor")
    fig.tight_layout(h_pad=1.2)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
