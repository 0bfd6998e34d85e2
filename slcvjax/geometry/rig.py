"""The rig: camera, cone mirror and lasers as one pytree, and its forward model."""

import functools
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .camera import Camera, in_image, project
from .lasers import Lasers, line_plane_intersection
from .mirror import Mirror, project_through_mirror
from .pose import Pose
from .sheets import KIND_DOF, Sheets

CAMERA_DOF = 9
MIRROR_DOF = 6  # the pose (vertex 3, axis tilt 2) and one of the shape (see the mirrors' retract)
# the rig's tangent, column by column (:meth:`Rig.retract`'s order; the calibration's covariance
# and every Jacobian over the rig): the camera (fx, fy, cx, cy, then the distortion, ``slcvjax.observations.formats``'s
# order), the mirror's vertex (mm), its axis tilt (rad), its shape, then the structured-light
# elements (:class:`TangentLayout`)
CAMERA_COLUMNS = slice(0, CAMERA_DOF)
CAMERA_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
APEX_COLUMNS = slice(CAMERA_DOF, CAMERA_DOF + 3)
TILT_COLUMNS = slice(CAMERA_DOF + 3, CAMERA_DOF + 5)
SHAPE_COLUMN = CAMERA_DOF + MIRROR_DOF - 1  # the mirror's shape (a conic's constant)
POSE_DOF = 6


class TangentLayout(NamedTuple):
    """Where each part of a rig sits in its flat tangent (:meth:`Rig.retract`'s order): the camera,
    the mirror, then each structured-light element with as many columns as its kind has unknowns
    (a point laser 4: its point moved across the beam e1, e2, mm, and its direction tilted e1, e2,
    rad).  The calibration's covariance, the bound, the report, measurement, design and the sweep
    take an element's columns from here.

    Attributes:
        camera: the camera's columns (9).
        mirror: the mirror's columns (6: vertex 3, axis tilt 2, shape 1).
        elements: each element's columns, in the rig's order.
    """

    camera: slice
    mirror: slice
    elements: tuple[slice, ...]

    @property
    def dim(self) -> int:
        """The tangent's length."""
        return self.elements[-1].stop if self.elements else self.mirror.stop

    @property
    def element_starts(self) -> np.ndarray:
        """(N,) each element's first column (int64; for a traced element index)."""
        return np.asarray([sl.start for sl in self.elements], dtype=np.int64)

    @property
    def element_dofs(self) -> np.ndarray:
        """(N,) each element's number of columns (int64)."""
        return np.asarray([sl.stop - sl.start for sl in self.elements], dtype=np.int64)


def tangent_layout(element_dofs) -> TangentLayout:
    """The :class:`TangentLayout` of a rig whose elements have ``element_dofs`` unknowns each."""
    start, elements = CAMERA_DOF + MIRROR_DOF, []
    for dof in element_dofs:
        elements.append(slice(start, start + int(dof)))
        start += int(dof)
    return TangentLayout(CAMERA_COLUMNS, slice(CAMERA_DOF, CAMERA_DOF + MIRROR_DOF), tuple(elements))


ELEMENT_DOF = {"point": Lasers.DOF, **KIND_DOF}  # unknowns per structured-light element kind


class Rig(eqx.Module):
    """Everything calibrated about the sensor: camera, mirror and its structured-light elements.

    The elements are the rig's lasers in the calibration file's order (``lasers[i]``): point
    lasers (beams, :class:`Lasers`) and sheets of light (line lasers' planes and ring lasers'
    cones, :class:`slcvjax.geometry.sheets.Sheets`).  ``kinds`` names each element's kind in
    that order (empty: every element a point laser); ``lasers`` holds the point lasers and
    ``sheets`` the sheets, each in the order they appear.

    ``tangent_dim`` is ``9 + 6`` plus each element's unknowns (:attr:`layout`); :meth:`retract`
    takes a flat increment in the order camera (9), mirror (6: vertex, axis tilt, shape), then
    the elements in order, each its own columns (a point laser 4, a plane 3, a cone 6).
    A camera-only rig (:meth:`camera_only`: a plain camera's calibration) has no mirror and
    no lasers; the functions that look through the mirror need one.
    """

    camera: Camera
    mirror: Mirror | None
    lasers: Lasers
    sheets: Sheets | None = None
    kinds: tuple[str, ...] = eqx.field(static=True, default=())

    def __check_init__(self):
        if not self.kinds:
            if self.sheets is not None and self.sheets.n:
                raise ValueError("Rig: sheets of light need the elements' kinds in order")
            return
        n_p = self.lasers.n if self.lasers is not None else 0
        n_s = self.sheets.n if self.sheets is not None else 0
        if sum(k == "point" for k in self.kinds) != n_p or len(self.kinds) != n_p + n_s:
            raise ValueError(f"Rig: kinds {self.kinds} do not match {n_p} point lasers and {n_s} sheets")
        if tuple(k for k in self.kinds if k != "point") != (self.sheets.kinds if n_s else ()):
            raise ValueError(f"Rig: kinds {self.kinds} do not list the sheets' kinds in their order")

    @classmethod
    def camera_only(cls, camera: Camera) -> "Rig":
        """The rig of a plain camera: no mirror, no lasers."""
        return cls(camera, None, Lasers.create(np.zeros((0, 3)), np.zeros((0, 3))))

    @classmethod
    def of_elements(cls, camera: Camera, mirror, lasers: Lasers, sheets: Sheets | None, kinds) -> "Rig":
        """A rig from its point lasers and sheets, and every element's kind in order (a rig of
        point lasers alone keeps the short form, with no ``kinds``)."""
        kinds = tuple(kinds)
        if all(k == "point" for k in kinds):
            return cls(camera, mirror, lasers)
        return cls(camera, mirror, lasers, sheets, kinds)

    @property
    def element_kinds(self) -> tuple[str, ...]:
        """Each element's kind in order (``point``, ``plane`` or ``cone``)."""
        if self.kinds:
            return self.kinds
        return ("point",) * (self.lasers.n if self.lasers is not None else 0)

    @property
    def n_elements(self) -> int:
        return len(self.element_kinds)

    @property
    def has_sheets(self) -> bool:
        return self.sheets is not None and self.sheets.n > 0

    @property
    def sheet_dim(self) -> int:
        """The tangent columns of the rig's sheets (3 per plane, 6 per cone)."""
        return int(sum(self.sheets.dofs)) if self.has_sheets else 0

    @property
    def point_elements(self) -> np.ndarray:
        """(P,) int64: the element index of each point laser."""
        return np.asarray([i for i, k in enumerate(self.element_kinds) if k == "point"], dtype=np.int64)

    @property
    def sheet_elements(self) -> np.ndarray:
        """(S,) int64: the element index of each sheet."""
        return np.asarray([i for i, k in enumerate(self.element_kinds) if k != "point"], dtype=np.int64)

    @property
    def local_index(self) -> np.ndarray:
        """(N,) int64: each element's index among the elements of its own collection (a point
        laser's in :attr:`lasers`, a sheet's in :attr:`sheets`)."""
        out, counts = [], {"point": 0, "sheet": 0}
        for k in self.element_kinds:
            key = "point" if k == "point" else "sheet"
            out.append(counts[key])
            counts[key] += 1
        return np.asarray(out, dtype=np.int64)

    def element_indices(self, points=(), sheets=()) -> tuple[int, ...]:
        """Point lasers (their indices among :attr:`lasers`) and sheets (among :attr:`sheets`) by
        their elements' indices in the file's order, sorted."""
        if not self.kinds:
            return tuple(int(i) for i in points)
        held = [int(self.point_elements[i]) for i in points] + [int(self.sheet_elements[i]) for i in sheets]
        return tuple(sorted(held))

    def with_lasers(self, lasers: Lasers) -> "Rig":
        """This rig's camera, mirror and sheets with other point lasers (more of them are added
        as the last elements, fewer drop the last point lasers)."""
        if not self.kinds:
            return Rig(self.camera, self.mirror, lasers)
        kinds, n_p = list(self.kinds), sum(k == "point" for k in self.kinds)
        while n_p > lasers.n:
            last = len(kinds) - 1 - kinds[::-1].index("point")
            del kinds[last]
            n_p -= 1
        kinds += ["point"] * (lasers.n - n_p)
        return Rig(self.camera, self.mirror, lasers, self.sheets, tuple(kinds))

    def with_sheets(self, sheets: Sheets) -> "Rig":
        """This rig with other sheets of the same kinds."""
        return Rig(self.camera, self.mirror, self.lasers, sheets, self.kinds)

    @property
    def layout(self) -> TangentLayout:
        """Where the camera, the mirror and each element sit in the tangent."""
        return tangent_layout(tuple(ELEMENT_DOF[k] for k in self.element_kinds))

    @property
    def tangent_dim(self) -> int:
        return self.layout.dim

    def retract(self, delta: Float[Array, " d"]) -> "Rig":
        c, m = CAMERA_DOF, CAMERA_DOF + MIRROR_DOF
        camera = self.camera.retract(delta[:c])
        mirror = None if self.mirror is None else self.mirror.retract(delta[c:m])
        if not self.kinds:
            return Rig(camera, mirror, self.lasers.retract(delta[m:].reshape(-1, self.lasers.DOF)))
        lay = self.layout
        pts = [lay.elements[i] for i in self.point_elements]
        lasers = self.lasers
        if pts:
            idx = np.asarray([np.arange(sl.start, sl.stop) for sl in pts])
            lasers = lasers.retract(delta[idx])
        sheets = self.sheets
        if self.has_sheets:
            idx = np.concatenate([np.arange(lay.elements[i].start, lay.elements[i].stop) for i in self.sheet_elements])
            sheets = sheets.retract(delta[idx])
        return Rig(camera, mirror, lasers, sheets, self.kinds)


# The projections below are compiled (jax.jit): called op by op, as a script or the pipeline's
# host steps call them, each compiled a program per operation for every new rig type and size.


@functools.partial(jax.jit, static_argnames="implicit")
def project_board_points(
    rig: Rig, T_cam_board: Pose, points_board: Float[Array, "m 3"], implicit: bool = True
) -> tuple[Float[Array, "m 2"], Bool[Array, " m"]]:
    """Pixels of board points seen through the mirror, and their validity."""
    points_cam = T_cam_board.apply(points_board)
    res = jax.vmap(lambda p: project_through_mirror(rig.camera, rig.mirror, p, implicit=implicit))(points_cam)
    return res.uv, res.valid


@functools.partial(jax.jit, static_argnames="implicit")
def project_spots(
    rig: Rig, T_cam_board: Pose, laser_ids: Float[Array, " s"], implicit: bool = True
) -> tuple[Float[Array, "s 2"], Bool[Array, " s"]]:
    """Pixels of the spots that the given lasers make on a board's plane (through the mirror)."""

    def one(i):
        x, ok = line_plane_intersection(rig.lasers.points[i], rig.lasers.directions[i], T_cam_board)
        res = project_through_mirror(rig.camera, rig.mirror, x, implicit=implicit)
        return res.uv, ok & res.valid

    return jax.vmap(one)(laser_ids)


@jax.jit
def project_rim(rig: Rig, angles: Float[Array, " n"]) -> tuple[Float[Array, "n 2"], Bool[Array, " n"]]:
    """Pixels of rim points (seen directly, not through the mirror)."""

    def one(p):
        uv, ok = project(rig.camera, p)
        return uv, ok & in_image(rig.camera, uv)

    return jax.vmap(one)(rig.mirror.rim_points(angles))


def distance_to_rim(rig: Rig, pixels: np.ndarray, n: int = 20000) -> np.ndarray:
    """Each pixel's distance (px) to the image of the mirror's rim: ``pixels`` (k, 2) against
    the rim's projection at ``n`` equally spaced angles joined by straight segments (the curve
    bends by well under a thousandth of a pixel between them at the default ``n``), nearest
    segment. Pixels where the rim is out of the image are measured to what is in it."""
    uv, ok = project_rim(rig, jnp.linspace(0.0, 2 * np.pi, n, endpoint=False))
    uv, ok = np.asarray(uv), np.asarray(ok)
    start, end = uv, np.roll(uv, -1, axis=0)
    keep = ok & np.roll(ok, -1)
    start, seg = start[keep], (end - start)[keep]
    pixels = np.asarray(pixels, float).reshape(-1, 2)
    out = np.empty(len(pixels))
    for i in range(0, len(pixels), 256):  # (256, segments) at a time
        q = pixels[i : i + 256, None, :] - start[None]
        t = np.clip(np.sum(q * seg, axis=2) / np.sum(seg * seg, axis=1), 0.0, 1.0)
        out[i : i + 256] = np.min(np.linalg.norm(q - t[..., None] * seg, axis=2), axis=1)
    return out


@jax.jit
def project_direct(
    camera: Camera, T_cam_board: Pose, points_board: Float[Array, "m 3"]
) -> tuple[Float[Array, "m 2"], Bool[Array, " m"]]:
    """Pixels of board points seen directly (a mirror-free calibration view)."""

    def one(p):
        uv, ok = project(camera, p)
        return uv, ok & in_image(camera, uv)

    return jax.vmap(one)(T_cam_board.apply(points_board))


def laser_spot_cam(rig: Rig, laser: int, T_cam_board: Pose) -> tuple[Array, Array]:
    """3D spot (camera frame) of one laser on a board's plane."""
    return line_plane_intersection(rig.lasers.points[laser], rig.lasers.directions[laser], T_cam_board)
