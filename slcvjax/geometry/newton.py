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

import contextlib
import functools
import threading
from collections.abc import Callable

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PyTree

from ..support.safe import solve2x2

# per thread: a calibration tracing in one thread (``calibrate_many(workers=2)``) must not see
# another thread's design or implicit derivative switch the roots to their exact form
_SECOND_ORDER = threading.local()


def _second_order() -> bool:
    return getattr(_SECOND_ORDER, "on", False)


@contextlib.contextmanager
def exact_second_order():
    """Within this context (while tracing), derivatives of a root are exact to every order.

    The one frozen-Jacobian step gives exact first derivatives only: its second
    derivative misses the root's own curvature.  Inside the context the converged root
    carries a custom JVP, ``dx = -J(x, theta)^-1 df/dtheta dtheta``, written with ``x``
    itself (so differentiating the rule again differentiates the root again): the
    second derivatives that the implicit derivative of a calibration's solution needs
    (:mod:`slcvjax.calibration.implicit`) and the bound's gradient in experiment design.  It acts at trace
    time, in the calling thread only: functions already compiled outside it keep their
    first-order form, and other threads trace as before.
    """
    old = _second_order()
    _SECOND_ORDER.on = True
    try:
        yield
    finally:
        _SECOND_ORDER.on = old


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
    if _second_order():
        return _exact_root(f, x, theta)
    jac = jax.lax.stop_gradient(jax.jacfwd(f)(x, theta_sg))
    return x - solve2x2(jac, f(x, theta))


def newton_residual_norm(f, x, theta) -> Array:
    """``|f(x, theta)|``, the convergence check used for the validity mask."""
    return jnp.sqrt(jnp.sum(jnp.square(jax.lax.stop_gradient(f(x, theta)))))
