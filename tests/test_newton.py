"""Newton with the implicit derivative against a root known in closed form: the value, first
derivatives, second derivatives under ``exact_second_order``, the unrolled baseline, and the
residual check that flags a system without a root."""

import jax
import jax.numpy as jnp
import numpy as np

from slcvjax.geometry.newton import exact_second_order, newton_implicit, newton_residual_norm


def f(x, theta):
    """``x0^2 + x1^2 = a`` and ``x0 = b x1``: the root ``x1 = sqrt(a / (1 + b^2))``, ``x0 = b x1``."""
    a, b = theta
    return jnp.stack([x[0] ** 2 + x[1] ** 2 - a, x[0] - b * x[1]])


def closed_form(theta):
    a, b = theta
    x1 = jnp.sqrt(a / (1.0 + b * b))
    return jnp.stack([b * x1, x1])


THETA = jnp.array([4.0, 0.7])
X0 = jnp.array([1.0, 1.0])


def root(theta, implicit=True):
    return newton_implicit(f, X0, theta, 12, implicit=implicit)


def test_root_and_its_first_derivative():
    np.testing.assert_allclose(root(THETA), closed_form(THETA), rtol=1e-13)
    J = jax.jacfwd(root)(THETA)
    np.testing.assert_allclose(J, jax.jacfwd(closed_form)(THETA), rtol=1e-10)
    np.testing.assert_allclose(jax.jacrev(root)(THETA), J, rtol=1e-12)
    # the unrolled baseline: the same value and derivative
    unrolled = jax.jacfwd(lambda t: root(t, implicit=False))(THETA)
    np.testing.assert_allclose(unrolled, J, rtol=1e-10)
    assert float(newton_residual_norm(f, root(THETA), THETA)) < 1e-12


def test_second_derivative_is_exact_only_under_exact_second_order():
    ref = jax.hessian(closed_form)(THETA)
    with exact_second_order():
        exact = jax.hessian(root)(THETA)
    np.testing.assert_allclose(exact, ref, rtol=1e-9, atol=1e-12)
    # the one frozen-Jacobian step is exact to first order only: it misses the root's curvature
    plain = jax.hessian(root)(THETA)
    assert np.max(np.abs(plain - ref)) > 1e-3 * np.max(np.abs(ref))


def test_a_system_without_a_root_is_flagged():
    theta = jnp.array([-1.0, 0.7])  # x0^2 + x1^2 = -1: no real root
    x = root(theta)
    assert np.all(np.isfinite(np.asarray(x)))
    assert float(newton_residual_norm(f, x, theta)) > 1e-3
