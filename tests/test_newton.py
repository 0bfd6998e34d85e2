"""Newton with the implicit derivative against a root known in closed form: the value, first
derivatives, exact second derivatives in every mode, the unrolled baseline, and the
residual check that flags a system without a root."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slcvjax.geometry.newton import newton_implicit, newton_residual_norm


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


@pytest.mark.slow
def test_second_derivatives_are_exact_in_every_mode():
    ref = jax.hessian(closed_form)(THETA)
    for hess in (jax.hessian, lambda f: jax.jacfwd(jax.jacfwd(f)), lambda f: jax.jacrev(jax.jacrev(f))):
        np.testing.assert_allclose(hess(root)(THETA), ref, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(jax.jit(hess(root))(THETA), ref, rtol=1e-9, atol=1e-12)
    # a batch of roots under vmap: each its own
    thetas = jnp.stack([THETA, jnp.array([9.0, -0.3])])
    np.testing.assert_allclose(
        jax.vmap(jax.hessian(root))(thetas), jax.vmap(jax.hessian(closed_form))(thetas), rtol=1e-9, atol=1e-12
    )


def test_the_first_derivative_costs_one_jacobian_of_the_residual():
    """Under a first derivative the last step evaluates ``f``'s Jacobian once (as the plain
    frozen step does): the traced program holds the loop's Jacobian and one more."""
    calls = []

    def counted(x, theta):
        calls.append(1)
        return f(x, theta)

    jax.make_jaxpr(jax.jacfwd(lambda t: newton_implicit(counted, X0, t, 12)))(THETA)
    # f traced twice for the loop's body (its value and its Jacobian) and twice for the last
    # step's rule (its Jacobian in x and its jvp in theta): what the plain frozen step traced
    assert len(calls) <= 4, len(calls)


def test_a_system_without_a_root_is_flagged():
    theta = jnp.array([-1.0, 0.7])  # x0^2 + x1^2 = -1: no real root
    x = root(theta)
    assert np.all(np.isfinite(np.asarray(x)))
    assert float(newton_residual_norm(f, x, theta)) > 1e-3
