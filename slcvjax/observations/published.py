"""Published catadioptric calibration sets as observations, and OCamCalib's model to compare with.

Two JSON forms of third-party data (see each data folder's SOURCE.md):

- an OCamCalib result (``<name>_reference.json``): per method the corners its fit used (MATLAB
  1-based ``row``/``col``), its polynomial model and extrinsics; :func:`ocam_observations` reads
  a method's corners, :func:`ocam_project` is its projection (Scaramuzza's model: the centre
  ``(xc, yc)`` as (row, col), the affine ``[[c, d], [e, 1]]``, the polynomial ``ss`` in ascending
  powers; a board point's pixel from the smallest positive root of ``f(rho) = (Z / n) rho``);
- Mei's corner file (``x_image_points_1based`` [x = column, y = row] and ``X_board_points_mm``
  per image): :func:`mei_observations`;
- OpenCV omnidir's calibration data (an OpenCV FileStorage XML of ``objectPoints``,
  ``imagePoints`` and ``imageSize``, pixels already 0-based): :func:`omnidir_observations`.

Pixels become this project's (OpenCV's, 0-based: ``u = col - 1``, ``v = row - 1``); every
image is a catadioptric view with one chessboard seen through the mirror, no rim, no lasers,
no direct views.
"""

import json
from pathlib import Path

import numpy as np

from .formats import Observations, ViewObs


def _view(name: str, board: str, px: np.ndarray) -> ViewObs:
    return ViewObs(name, {board: (px, np.ones(len(px), bool))}, [], np.zeros((0, 2)))


def ocam_observations(path: str | Path, method: str = "2") -> tuple[Observations, dict]:
    """The corners of one OCamCalib method as observations, and the method's record."""
    doc = json.loads(Path(path).read_text())
    m = doc["methods"][method]
    if "per_image" not in m:
        raise ValueError(f"{path}: methods.{method} has no corners (per_image)")
    b = doc["board"]
    pts = np.stack([b["Xt_mm"], b["Yt_mm"], np.zeros(len(b["Xt_mm"]))], axis=1)
    views = []
    for img in m["images_used"]:
        e = m["per_image"][img]
        px = np.stack([np.asarray(e["Yp_abs_col_1based"]) - 1.0, np.asarray(e["Xp_abs_row_1based"]) - 1.0], axis=1)
        views.append(_view(img, "chess", px))
    size = (int(m["ocam_model"]["width"][0]), int(m["ocam_model"]["height"][0]))
    return Observations(size, 0.0, 0.0, 0, {"chess": pts}, [], views), m


def ocam_project(model: dict, rr: np.ndarray, board: np.ndarray) -> np.ndarray:
    """OCamCalib's pixels (0-based ``u, v``) of board points ``(M, 2 or 3)`` at its extrinsics
    ``rr`` = ``[r1 r2 t]`` (3x3, mm)."""
    ss = np.asarray(model["ss"], float)
    xc, yc = float(np.ravel(model["xc"])[0]), float(np.ravel(model["yc"])[0])
    c, d, e = (float(np.ravel(model[k])[0]) for k in "cde")
    p = np.asarray(rr, float) @ np.stack([board[:, 0], board[:, 1], np.ones(len(board))])
    X, Y, Z = p
    n = np.hypot(X, Y)
    rho = np.empty(len(n))
    for i in range(len(n)):
        poly = ss.copy()  # a0 + a1 rho + ... - (Z / n) rho = 0
        poly[1] -= Z[i] / n[i]
        roots = np.roots(poly[::-1])
        real = roots[(np.abs(roots.imag) < 1e-9) & (roots.real > 0)].real
        rho[i] = real.min() if real.size else np.nan
    x, y = X * rho / n, Y * rho / n
    row, col = c * x + d * y + xc, e * x + y + yc
    return np.stack([col - 1.0, row - 1.0], axis=1)


def ocam_residuals(path: str | Path, method: str = "2") -> dict[str, np.ndarray]:
    """Per image, OCamCalib's own residual vectors (px) of a method: its projection at its
    extrinsics against the corners it used."""
    obs, m = ocam_observations(path, method)
    out = {}
    for v in obs.views:
        rr = np.asarray(m["per_image"][v.name]["RRfin_r1_r2_t_rowmajor"], float).reshape(3, 3)
        out[v.name] = ocam_project(m["ocam_model"], rr, obs.boards["chess"]) - v.boards["chess"][0]
    return out


def mei_observations(path: str | Path, image_size: tuple[int, int]) -> Observations:
    """Mei's corner file as observations (one board per distinct grid orientation); the file does
    not give the images' ``(width, height)``."""
    doc = json.loads(Path(path).read_text())
    boards: dict[str, np.ndarray] = {}
    views = []
    for img in doc["images"]:
        x = np.asarray(doc["x_image_points_1based"][img], float)
        X = np.asarray(doc["X_board_points_mm"][img], float)
        x = x.T if x.shape[0] == 2 else x
        X = X.T if X.shape[0] == 3 and X.shape[1] != 3 else X
        key = next((k for k, P in boards.items() if P.shape == X.shape and np.allclose(P, X)), None)
        if key is None:
            key = f"chess{len(boards)}"
            boards[key] = X
        views.append(_view(img, key, x - 1.0))
    return Observations(tuple(image_size), 0.0, 0.0, 0, boards, [], views)


def omnidir_observations(path: str | Path, unit_mm: float = 100.0) -> Observations:
    """OpenCV omnidir's calibration data (``objectPoints``, ``imagePoints`` per view and
    ``imageSize``, as its tutorial's ``omni_calib_data.xml``) as observations, one board per
    distinct grid.  ``unit_mm``: the grid's unit in mm (the tutorial's file does not say; a fit
    from views through the mirror alone holds the mirror's vertex radius as the scale's gauge,
    so this sets only the boards' distances in that gauge).  Raises ``ValueError`` naming the
    file and field where they are missing or do not match."""
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise ValueError(f"{path}: cannot be read as an OpenCV FileStorage file")
    nodes = {k: fs.getNode(k) for k in ("objectPoints", "imagePoints", "imageSize")}
    for k, n in nodes.items():
        if n.empty():
            raise ValueError(f"{path}: {k}: missing")
    obj, img = nodes["objectPoints"], nodes["imagePoints"]
    if obj.size() != img.size():
        raise ValueError(f"{path}: objectPoints has {obj.size()} views, imagePoints {img.size()}")
    size_node = nodes["imageSize"]
    size = tuple(int(size_node.at(i).real()) for i in range(size_node.size()))
    if len(size) != 2:
        raise ValueError(f"{path}: imageSize: expected width and height, got {size}")
    boards: dict[str, np.ndarray] = {}
    views = []
    for i in range(obj.size()):
        X = np.asarray(obj.at(i).mat(), float).reshape(-1, 3) * unit_mm
        x = np.asarray(img.at(i).mat(), float).reshape(-1, 2)
        if len(X) != len(x):
            raise ValueError(f"{path}: view {i}: {len(X)} objectPoints against {len(x)} imagePoints")
        key = next((k for k, P in boards.items() if P.shape == X.shape and np.allclose(P, X)), None)
        if key is None:
            key = f"chess{len(boards)}"
            boards[key] = X
        views.append(_view(f"view{i:02d}", key, x))
    return Observations(size, 0.0, 0.0, 0, boards, [], views)
