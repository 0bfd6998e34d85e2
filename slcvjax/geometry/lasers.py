"""Laser lines and where their spots fall on a planar board."""

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ..support.safe import orthonormal_basis, safe_div, safe_normalize
from .pose import Pose


class Lasers(eqx.Module):
    """Any number of laser lines ``point + lambda * direction`` (camera frame, mm).

    Attributes:
        points: (N, 3) a point of each line.
        directions: (N, 3) unit direction of each beam (the light travels along +direction).

    A line has 4 degrees of freedom (:data:`DOF`); :meth:`retract` takes an (N, 4) increment:
    two for the point moved across the beam, two for the direction tilted.
    """

    KIND: ClassVar[str] = "point"  # the element kind, as the calibration file names it
    DOF: ClassVar[int] = 4  # unknowns per element: its columns in the rig's tangent

    points: Float[Array, "n 3"]
    directions: Float[Array, "n 3"]

    @staticmethod
    def create(points, directions) -> "Lasers":
        p = jnp.asarray(points, dtype=float).reshape(-1, 3)
        d = jnp.asarray(directions, dtype=float).reshape(-1, 3)
        return Lasers(p, d / jnp.linalg.norm(d, axis=-1, keepdims=True))

    @property
    def n(self) -> int:
        return self.points.shape[0]

    def retract(self, delta: Float[Array, "n 4"]) -> "Lasers":
        def one(p, d, dl):
            e1, e2 = orthonormal_basis(d)
            return p + dl[0] * e1 + dl[1] * e2, safe_normalize(d + dl[2] * e1 + dl[3] * e2)

        p, d = jax.vmap(one)(self.points, self.directions, delta)
        return Lasers(p, d)

    def at_working_point(self, i, x_ref, delta4=None) -> tuple[Float[Array, "3"], Float[Array, "3"]]:
        """Laser ``i`` (moved by the tangent increment ``delta4``, see :meth:`retract`) at the
        working point ``x_ref``: the foot of the perpendicular from ``x_ref`` on its line, and its
        direction.  The one definition behind every laser's position and direction error, its
        standard deviation and its sensitivity."""
        p, d = self.points[i], self.directions[i]
        if delta4 is not None:
            moved = Lasers(p[None], d[None]).retract(jnp.asarray(delta4)[None])
            p, d = moved.points[0], moved.directions[0]
        x_ref = jnp.asarray(x_ref)
        return p + jnp.dot(x_ref - p, d) * d, d

    def canonical(self) -> "Lasers":
        """The same lines with each point moved to the foot of the perpendicular from the origin.

        Computed on the host (concrete arrays only), so a new number of lasers compiles nothing."""
        d = np.asarray(self.directions)
        p = np.asarray(self.points)
        return Lasers(jax.device_put(p - np.sum(p * d, axis=-1, keepdims=True) * d), self.directions)


def line_plane_intersection(
    point: Float[Array, "3"], direction: Float[Array, "3"], T_cam_board: Pose, forward_only: bool = True
) -> tuple[Float[Array, "3"], Bool[Array, ""]]:
    """Where a laser beam meets the plane ``z = 0`` of a board (camera frame).

    ``valid`` is False when the beam is parallel to the plane (within 1e-9) or, with
    ``forward_only``, the plane lies behind ``point`` (the light travels along
    +direction from an emitter at ``point``).  A calibrated line's point is not its
    emitter, so the calibration uses ``forward_only=False``.
    """
    n = T_cam_board.R[:, 2]
    denom = jnp.dot(n, direction)
    lam = safe_div(jnp.dot(n, T_cam_board.t - point), denom, eps=1e-9)
    valid = (jnp.abs(denom) > 1e-9) & ((lam > 0.0) | (not forward_only))
    return point + lam * direction, valid
