"""Newton root finding with an implicit (IFT) derivative.

``newton_implicit(f, x0, theta)`` solves ``f(x, theta) = 0`` for a small
``x`` (a 2-vector here) by a fixed number of Newton steps taken under
``stop_gradient``, then applies one more Newton step whose Jacobian is held
constant:

    x* = x_k - J(x_k)^-1 f(x_k, theta),    J = df/dx at x_k (no gradient).

At convergence ``f(x_k, theta) = 0`` so the value does not move, while the
derivative of that last step with respect to ``theta`` is exactly the implicit
function theorem's ``dx*/dtheta = -J^-1 df/dtheta``.  The cost of a Jacobian is
therefore one Newton step, not the unrolled loop.  ``implicit=False`` instead
differentiates through every iteration (kept for the benchmark's baseline).
"""

from collections.abc import Callable

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PyTree

from ._safe import solve2x2


def _step(f, x, theta):
    fx = f(x, theta)
    jac = jax.jacfwd(f)(x, theta)
    return x - solve2x2(jac, fx)


def newton_implicit(
    f: Callable[[Float[Array, "2"], PyTree], Float[Array, "2"]],
    x0: Float[Array, "2"],
    theta: PyTree,
    iters: int,
    implicit: bool = True,
) -> Float[Array, "2"]:
    """Root of ``f(., theta)`` near ``x0`` with implicit derivatives; see the module doc."""
    if not implicit:
        x = x0
        for _ in range(iters + 1):
            x = _step(f, x, theta)
        return x
    theta_sg = jax.lax.stop_gradient(theta)
    x = jax.lax.fori_loop(0, iters, lambda _, x: _step(f, x, theta_sg), jax.lax.stop_gradient(x0))
    x = jax.lax.stop_gradient(x)
    jac = jax.lax.stop_gradient(jax.jacfwd(f)(x, theta_sg))
    return x - solve2x2(jac, f(x, theta))


def newton_residual_norm(f, x, theta) -> Array:
    """``|f(x, theta)|``, the convergence check used for the validity mask."""
    return jnp.sqrt(jnp.sum(jnp.square(jax.lax.stop_gradient(f(x, theta)))))
