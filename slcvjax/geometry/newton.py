"""Newton root finding with an implicit (IFT) derivative.

``newton_implicit(f, x0, theta)`` solves ``f(x, theta) = 0`` for a small
``x`` (a 2-vector here) by a fixed number of Newton steps taken under
``stop_gradient``, then applies one more Newton step whose Jacobian is held
constant:

    x* = x_k - J(x_k)^-1 f(x_k, theta),    J = df/dx at x_k (no gradient).

At convergence ``f(x_k, theta) = 0`` so the value does not move, while the
derivative of that last step with respect to ``theta`` is exactly the implicit
function theorem's ``dx*/dtheta = -J^-1 df/dtheta``.  The cost of a Jacobian is
therefore one Newton step, not the unrolled loop.  The last step carries a custom JVP
written with the root itself, so that derivatives of every order are exact (the second
derivatives that the implicit derivative of a calibration's solution and the bound's
gradient in experiment design need), while a first derivative costs what the plain frozen
step costs.  ``implicit=False`` instead differentiates through every iteration (kept for
the benchmark's baseline).
"""

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PyTree

from ..support.safe import solve2x2


def _step(f, x, theta):
    fx = f(x, theta)
    jac = jax.jacfwd(f)(x, theta)
    return x - solve2x2(jac, fx)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _exact_root(f, x, theta):
    """``x`` (a converged root of ``f(., theta)``), differentiable to any order in ``theta``."""
    return x


@_exact_root.defjvp
def _exact_root_jvp(f, primals, tangents):
    x, theta = primals
    _, dtheta = tangents
    # the rule is itself differentiable: ``x`` below carries this same rule, so a second
    # derivative picks up the root's curvature through the Jacobian's dependence on it
    x = _exact_root(f, x, theta)
    _, fdot = jax.jvp(lambda th: f(x, th), (theta,), (dtheta,))
    return x, -solve2x2(jax.jacfwd(f)(x, theta), fdot)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _last_step(f, x, theta):
    """One Newton step ``x - J^-1 f(x, theta)`` from a converged ``x`` (which carries no
    derivative): its derivative in ``theta`` is the implicit function theorem's,
    ``-J^-1 df/dtheta``, to every order."""
    return _step(f, x, theta)


@_last_step.defjvp
def _last_step_jvp(f, primals, tangents):
    x, theta = primals
    _, dtheta = tangents
    # the Jacobian and the residual once, for the value and the derivative alike (the cost
    # of the plain frozen step); ``xr`` is ``x`` with the root's own derivative, which only a
    # second derivative sees
    xr = _exact_root(f, x, theta)
    jac = jax.jacfwd(f)(xr, theta)
    fx, fdot = jax.jvp(lambda th: f(xr, th), (theta,), (dtheta,))
    return xr - solve2x2(jac, fx), -solve2x2(jac, fdot)


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
    return _last_step(f, jax.lax.stop_gradient(x), theta)


def newton_residual_norm(f, x, theta) -> Array:
    """``|f(x, theta)|``, the convergence check used for the validity mask."""
    return jnp.sqrt(jnp.sum(jnp.square(jax.lax.stop_gradient(f(x, theta)))))
