"""Safe versions of the singular operations used by the forward model.

Every square root, norm, normalisation, division and arccos of the project goes
through this module.  Each helper uses the *double-``where``* pattern: the
singular input is replaced by a harmless value *before* the singular operation,
and the result is selected *after* it.  Values and gradients stay finite
everywhere (a masked branch never multiplies a NaN by zero), which is what
lets invalid geometry be reported through a mask instead of a NaN.
"""

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

_TINY = 1e-300


def safe_sqrt(x: ArrayLike, eps: float = 0.0) -> Array:
    """``sqrt(x)`` for ``x > eps``, ``0`` otherwise; the gradient is 0 where masked."""
    x = jnp.asarray(x)
    ok = x > eps
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, x, 1.0)), 0.0)


def safe_norm(v: ArrayLike, axis: int = -1, keepdims: bool = False) -> Array:
    """Euclidean norm along ``axis``; 0 (with gradient 0) for the zero vector."""
    v = jnp.asarray(v)
    sq = jnp.sum(v * v, axis=axis, keepdims=keepdims)
    return safe_sqrt(sq, eps=_TINY)


def safe_normalize(v: ArrayLike, axis: int = -1) -> Array:
    """``v / |v|`` along ``axis``; the zero vector maps to the zero vector."""
    v = jnp.asarray(v)
    n = safe_norm(v, axis=axis, keepdims=True)
    return v / jnp.where(n > 0.0, n, 1.0)


def safe_div(a: ArrayLike, b: ArrayLike, eps: float = _TINY) -> Array:
    """``a / b`` where ``|b| > eps``, ``0`` elsewhere (finite value and gradient)."""
    a = jnp.asarray(a)
    b = jnp.asarray(b)
    ok = jnp.abs(b) > eps
    return jnp.where(ok, a / jnp.where(ok, b, 1.0), 0.0)


def safe_arccos(x: ArrayLike) -> Array:
    """``arccos`` with its argument clipped just inside [-1, 1] (finite gradient)."""
    x = jnp.asarray(x)
    return jnp.arccos(jnp.clip(x, -1.0 + 1e-15, 1.0 - 1e-15))


def orthonormal_basis(axis: Float[Array, "3"]) -> tuple[Float[Array, "3"], Float[Array, "3"]]:
    """Two unit vectors ``e1, e2`` with ``(e1, e2, axis)`` a right-handed orthonormal frame.

    ``axis`` must be a unit vector.  The helper vector is the coordinate axis
    least aligned with ``axis``, so the construction is smooth wherever the
    choice does not switch (it never degenerates).
    """
    absa = jnp.abs(axis)
    helper = jnp.where(
        (absa[0] <= absa[1]) & (absa[0] <= absa[2]),
        jnp.array([1.0, 0.0, 0.0]),
        jnp.where(absa[1] <= absa[2], jnp.array([0.0, 1.0, 0.0]), jnp.array([0.0, 0.0, 1.0])),
    )
    e1 = safe_normalize(helper - jnp.dot(helper, axis) * axis)
    e2 = jnp.cross(axis, e1)
    return e1, e2


def solve2x2(a: Float[Array, "2 2"], b: Float[Array, "2"]) -> Float[Array, "2"]:
    """Solve a 2x2 linear system by Cramer's rule; a singular matrix gives a zero step."""
    det = a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]
    x0 = a[1, 1] * b[0] - a[0, 1] * b[1]
    x1 = a[0, 0] * b[1] - a[1, 0] * b[0]
    return jnp.stack([safe_div(x0, det), safe_div(x1, det)])


def std_of_variance(var, scale=None) -> np.ndarray:
    """Standard deviations of variances from a covariance (host arrays): NaN for a variance
    that is negative beyond round-off (``1e-9`` of ``scale``, by default the largest
    magnitude among ``var``), where the covariance is not positive and the data do not
    determine the quantity; a report writes that as undetermined, never as 0."""
    var = np.asarray(var, dtype=float)
    tol = 1e-9 * (float(np.max(np.abs(var), initial=0.0)) if scale is None else float(scale))
    return np.where(var >= -tol, np.sqrt(np.maximum(var, 0.0)), np.nan)
