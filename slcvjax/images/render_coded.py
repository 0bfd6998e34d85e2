"""Printed targets on the renderer's walls: each wall shaded from its board's :class:`Drawing`.

A wall of a dot grid is shaded by :mod:`slcvjax.images.render` from its dot centres (a disc of
``dot_radius_mm`` at each).  A coded board (ChArUco, AprilGrid, or any drawing) is shaded from
its print instead: :func:`slcvjax.images.printable.board_drawing`'s black rectangles and discs in
the board's own frame (mm).  A sample whose reflected ray meets a wall at board coordinates
``(x, y)`` is ink where ``(x, y)`` lies in one of that wall's rectangles (``x0 <= x < x0 + w``,
``y0 <= y < y0 + h``) or discs (``|xy - c| < r``), else white paper; around the print the wall is
paper too.  The sample is exact (a point test, no texture): the renderer's supersampling and its
refinement of the cells an edge crosses give each pixel its area's mean, as for the dots.

:func:`pack_drawings` pads the walls' drawings to one array shape (a few buckets, so one
compilation serves boards of similar size); :func:`drawing_albedo` is the shader's test, written
for one sample and batched by the renderer's ``vmap``.
"""

import jax.numpy as jnp
import numpy as np

INK = 0.06  # the albedo of the printed black (the dots' DOT)
PAPER = 0.72  # white paper (the walls' WALL)


def _bucket(n: int) -> int:
    """``n`` rounded up to a power of two (at least 8): one compiled shape per bucket."""
    return max(8, 1 << max(0, int(n) - 1).bit_length())


def pack_drawings(drawings: list) -> tuple[jnp.ndarray, jnp.ndarray]:
    """The walls' drawings (in the renderer's wall order) as padded arrays.

    Returns ``(rects (W, K, 4), discs (W, D, 3))``: each wall's ``(x, y, w, h)`` rectangles and
    ``(x, y, r)`` discs in its board frame (mm); padding rectangles have zero size and padding
    discs zero radius (never ink).  A wall without a drawing (None) is plain paper.
    """
    rects = [np.zeros((0, 4)) if d is None else np.asarray(d.rects, float).reshape(-1, 4) for d in drawings]
    discs = [np.zeros((0, 3)) if d is None else np.asarray(d.discs, float).reshape(-1, 3) for d in drawings]
    k, m = _bucket(max(len(r) for r in rects)), _bucket(max(len(c) for c in discs))
    out_r = np.zeros((len(drawings), k, 4))
    out_r[:, :, :2] = 1e9  # far away, and of zero size
    out_d = np.zeros((len(drawings), m, 3))
    out_d[:, :, :2] = 1e9
    for i, (r, c) in enumerate(zip(rects, discs, strict=True)):
        out_r[i, : len(r)] = r
        out_d[i, : len(c)] = c
    return jnp.asarray(out_r), jnp.asarray(out_d)


def drawing_albedo(wall, xy, drawing):
    """The albedo at board point ``xy`` (2,) mm of wall ``wall`` (an index into ``drawing``'s walls).

    ``drawing``: :func:`pack_drawings`'s ``(rects, discs)``.  Ink (``INK``) inside a rectangle
    (half-open: its lower edges in, its upper edges out, so that two rectangles sharing an edge
    leave no seam and do not overlap) or strictly inside a disc; paper (``PAPER``) elsewhere.
    Returns a 0-d array.
    """
    rects, discs = drawing
    r = rects[wall]
    in_rect = (xy[0] >= r[:, 0]) & (xy[0] < r[:, 0] + r[:, 2]) & (xy[1] >= r[:, 1]) & (xy[1] < r[:, 1] + r[:, 3])
    d = discs[wall]
    in_disc = jnp.sum((d[:, :2] - xy) ** 2, axis=1) < d[:, 2] ** 2
    return jnp.where(jnp.any(in_rect) | jnp.any(in_disc), INK, PAPER)
