"""A camera read from a file of any of the formats a user may hold: ``slcv-calibration/1`` JSON,
OpenCV FileStorage YAML (``camera_matrix``, ``distortion_coefficients``, ``image_width`` and
``image_height``, as ``cv2.calibrateCamera``'s samples and ``slcvjax export --format opencv`` write
it) or ROS ``camera_info`` YAML (``camera_matrix`` and ``distortion_coefficients`` as
``{rows, cols, data}``, ``distortion_model: plumb_bob``).

YAML is parsed by OpenCV's FileStorage (a dependency already), which reads both.
"""

import os
from pathlib import Path

import numpy as np

from ..geometry.camera import Camera
from .formats import FormatError, read_calibration


def _matrix(node, where: str, source: str) -> np.ndarray:
    """A FileStorage node as an array: an ``!!opencv-matrix``, a ``{rows, cols, data}`` map (ROS)
    or a sequence of numbers."""
    if node.isNone():
        raise FormatError(f"{source}: {where}: missing")
    if node.isMap() and not node.getNode("data").isNone():
        if not node.getNode("dt").isNone():  # an !!opencv-matrix
            return np.asarray(node.mat(), float)
        data = node.getNode("data")
        vals = [data.at(i).real() for i in range(data.size())]
        rows, cols = int(node.getNode("rows").real()), int(node.getNode("cols").real())
        if rows * cols != len(vals):
            raise FormatError(f"{source}: {where}.data: {len(vals)} numbers for {rows}x{cols}")
        return np.asarray(vals, float).reshape(rows, cols)
    if node.isSeq():
        return np.asarray([node.at(i).real() for i in range(node.size())], float)
    raise FormatError(f"{source}: {where}: expected a matrix")


def read_camera(path: str | os.PathLike) -> Camera:
    """The camera of ``path``: a ``slcv-calibration/1`` JSON (``.json``; its camera), else OpenCV
    or ROS YAML. Raises :class:`FormatError` naming the file and the field where the file is
    unreadable, a field is missing, ``K`` is not 3x3 with ``[0, 0, 1]`` as its last row, there are
    not 4, 5 (``k3 = 0`` where 4) coefficients, a value is not finite, or the distortion model is
    not ``plumb_bob`` (ROS)."""
    import cv2

    source = str(path)
    if Path(path).suffix.lower() == ".json":
        return read_calibration(path).rig.camera
    if not Path(path).is_file():
        raise FormatError(f"{source}: (file): not found")
    try:
        fs = cv2.FileStorage(source, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_FORMAT_YAML)
    except cv2.error as e:
        raise FormatError(f"{source}: (file): not OpenCV or ROS YAML ({(e.err or str(e)).strip()})") from None
    try:
        if not fs.isOpened():
            raise FormatError(f"{source}: (file): OpenCV cannot read it")
        model = fs.getNode("distortion_model")
        if not model.isNone() and model.string() not in ("plumb_bob", "rational_polynomial"):
            raise FormatError(f"{source}: distortion_model: {model.string()!r} is not plumb_bob (k1, k2, p1, p2, k3)")
        k = _matrix(fs.getNode("camera_matrix"), "camera_matrix", source)
        dist = _matrix(fs.getNode("distortion_coefficients"), "distortion_coefficients", source).reshape(-1)
        size = []
        for key in ("image_width", "image_height"):
            node = fs.getNode(key)
            if node.isNone():
                raise FormatError(f"{source}: {key}: missing")
            size.append(node.real())
    finally:
        fs.release()
    if k.shape != (3, 3):
        raise FormatError(f"{source}: camera_matrix: expected 3x3, got shape {k.shape}")
    if not np.all(np.isfinite(k)):
        i = int(np.flatnonzero(~np.isfinite(k.reshape(-1)))[0])
        raise FormatError(f"{source}: camera_matrix[{i // 3}][{i % 3}]: not a finite number")
    if not np.allclose(k[2], [0, 0, 1]) or k[1, 0] != 0 or k[0, 1] != 0:
        raise FormatError(f"{source}: camera_matrix: expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]")
    if len(dist) == 8 and np.all(dist[5:] == 0):  # rational_polynomial with its extra terms zero
        dist = dist[:5]
    if len(dist) == 4:
        dist = np.concatenate([dist, [0.0]])
    if len(dist) != 5:
        raise FormatError(f"{source}: distortion_coefficients: expected 4 or 5 (k1, k2, p1, p2, k3), got {len(dist)}")
    for i, v in enumerate(dist):
        if not np.isfinite(v):
            raise FormatError(f"{source}: distortion_coefficients[{i}]: not a finite number")
    w, h = size
    if not (w >= 1 and h >= 1 and w == int(w) and h == int(h)):
        raise FormatError(f"{source}: image_width, image_height: expected positive integers, got {w}, {h}")
    return Camera.create(k[0, 0], k[1, 1], k[0, 2], k[1, 2], dist, int(w), int(h))
