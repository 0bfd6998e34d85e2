"""What every mirror of revolution shares: its 5-DOF pose increment, its rim circle, a ray's hit."""

from typing import NamedTuple

import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ..support.safe import orthonormal_basis, safe_normalize


def retract_pose(apex: Float[Array, "3"], axis: Float[Array, "3"], delta: Float[Array, "5"]):
    """``(apex + delta[:3], axis tilted by delta[3:])``: the axis tilts (radians) in its tangent plane."""
    e1, e2 = orthonormal_basis(axis)
    return apex + delta[:3], safe_normalize(axis + delta[3] * e1 + delta[4] * e2)


def rim_circle(apex, axis, height, radius, angles: Float[Array, " n"]) -> Float[Array, "n 3"]:
    """Points of the circle of ``radius`` about the axis, ``height`` from the apex along it, at ``angles``."""
    e1, e2 = orthonormal_basis(axis)
    centre = apex + height * axis
    return centre + radius * (jnp.cos(angles)[:, None] * e1 + jnp.sin(angles)[:, None] * e2)


class RayHit(NamedTuple):
    """Where a ray meets the mirror: ray parameter, point, and validity."""

    t: Float[Array, ""]
    point: Float[Array, "3"]
    valid: Bool[Array, ""]
