"""Rigid transforms ``T_a_b`` (points of frame b into frame a) and SO(3) helpers.

Rotations are optimised as tangent increments around a reference:
``R <- exp(omega) R``.  ``so3_exp`` switches to its Taylor series near zero
with a safe ``where`` so value and gradient are exact at ``omega = 0``.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ..support.safe import safe_sqrt


def hat(w: Float[Array, "3"]) -> Float[Array, "3 3"]:
    """The skew matrix ``[w]_x`` with ``hat(w) @ v == cross(w, v)``."""
    z = jnp.zeros_like(w[0])
    return jnp.array([[z, -w[2], w[1]], [w[2], z, -w[0]], [-w[1], w[0], z]])


def so3_exp(w: Float[Array, "3"]) -> Float[Array, "3 3"]:
    """Rodrigues' formula, ``exp([w]_x)``; Taylor series below ``|w| = 1e-4``."""
    th2 = jnp.sum(w * w)
    small = th2 < 1e-8
    th2_safe = jnp.where(small, 1.0, th2)
    th = jnp.sqrt(th2_safe)
    a = jnp.where(small, 1.0 - th2 / 6.0 + th2 * th2 / 120.0, jnp.sin(th) / th)
    b = jnp.where(small, 0.5 - th2 / 24.0 + th2 * th2 / 720.0, (1.0 - jnp.cos(th)) / th2_safe)
    k = hat(w)
    return jnp.eye(3) + a * k + b * (k @ k)


def so3_log(r: Float[Array, "3 3"]) -> Float[Array, "3"]:
    """Inverse of :func:`so3_exp` for rotation angles below pi (the tangent at identity)."""
    c = jnp.clip((jnp.trace(r) - 1.0) / 2.0, -1.0, 1.0)
    v = jnp.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    s = safe_sqrt(1.0 - c * c)
    th = jnp.arctan2(s, c)
    small = s < 1e-7
    factor = jnp.where(small, 0.5 + (1.0 - c) / 12.0, th / (2.0 * jnp.where(small, 1.0, s)))
    return factor * v


_so3_exp_jit = jax.jit(so3_exp)  # host callers: one dispatch instead of a dozen eager operations


class Pose(eqx.Module):
    """A rigid transform ``T_a_b``: ``p_a = R @ p_b + t`` (mm).

    Attributes:
        R: (..., 3, 3) rotation matrix.
        t: (..., 3) translation in mm.
    """

    R: Float[Array, "... 3 3"]
    t: Float[Array, "... 3"]

    @staticmethod
    def identity() -> "Pose":
        return Pose(jnp.eye(3), jnp.zeros(3))

    @staticmethod
    def from_rvec(rvec: ArrayLike, t: ArrayLike) -> "Pose":
        """From an axis-angle vector (OpenCV's ``rvec``) and a translation (one compiled call)."""
        return Pose(_so3_exp_jit(jnp.asarray(rvec, dtype=float)), jnp.asarray(t, dtype=float))

    def apply(self, p_b: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
        """Map points of frame b into frame a."""
        return jnp.einsum("ij,...j->...i", self.R, p_b) + self.t

    def rotate(self, v_b: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
        """Rotate directions of frame b into frame a (no translation)."""
        return jnp.einsum("ij,...j->...i", self.R, v_b)

    def inverse(self) -> "Pose":
        """``T_b_a`` from ``T_a_b``."""
        rt = jnp.swapaxes(self.R, -1, -2)
        return Pose(rt, -jnp.einsum("...ij,...j->...i", rt, self.t))

    def __matmul__(self, other: "Pose") -> "Pose":
        """Composition: ``T_a_b @ T_b_c == T_a_c``."""
        return Pose(self.R @ other.R, self.apply(other.t))

    def retract(self, delta: Float[Array, "6"]) -> "Pose":
        """Tangent increment ``delta = (omega, dt)``: ``R <- exp(omega) R``, ``t <- t + dt``."""
        return Pose(so3_exp(delta[:3]) @ self.R, self.t + delta[3:])

    def rvec(self) -> Float[Array, "3"]:
        """The rotation as an axis-angle vector (OpenCV's ``rvec``)."""
        return so3_log(self.R)
