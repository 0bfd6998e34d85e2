"""The designs' shared optimiser: Adam-scaled steps, each accepted only where it lowers the value."""

import jax
import jax.numpy as jnp
import numpy as np
import optax

from slcvjax.experiments.descent import Accepted, adam_descent

TARGET = jnp.asarray([3.0, -1.0])


def _value_and_grad(u):
    return jax.value_and_grad(lambda x: jnp.sum((x - TARGET) ** 2))(u)


def _halving(u, direction, lr, f0):
    for _ in range(10):
        u_new = u - lr * direction
        f_new, g_new = _value_and_grad(u_new)
        if float(f_new) < f0:
            return Accepted(u_new, f_new, g_new, lr)
        lr *= 0.5
    return None


def test_it_descends_to_the_minimum_of_a_quadratic():
    u0 = jnp.zeros(2)
    f0, g0 = _value_and_grad(u0)
    # Adam's momentum overshoots the minimum, where no shortened step can go down: a fresh start
    # (restart) goes on from there
    d = adam_descent(u0, f0, g0, _halving, 200, 0.3, optax.scale_by_adam(), grow=1.2, restart=True)
    assert all(b < a for a, b in zip(d.history, d.history[1:], strict=False))  # every accepted step lowers it
    assert d.history[0] == float(f0) and d.history[-1] == float(d.value) < 1e-6
    np.testing.assert_allclose(np.asarray(d.u), np.asarray(TARGET), atol=1e-3)


def test_a_stuck_search_restarts_adam_once_then_stops():
    calls = []

    def refuse_twice_then_halve(u, direction, lr, f0):
        calls.append(lr)
        return None if len(calls) <= 2 else _halving(u, direction, lr, f0)

    u0 = jnp.zeros(2)
    f0, g0 = _value_and_grad(u0)
    # with a restart allowed, the first refusal restarts and the second ends it
    d = adam_descent(u0, f0, g0, refuse_twice_then_halve, 5, 0.3, optax.scale_by_adam(), restart=True)
    assert len(calls) == 2 and d.history == [float(f0)] and d.extra is None
    # without, the first refusal ends it
    calls.clear()
    d = adam_descent(u0, f0, g0, refuse_twice_then_halve, 5, 0.3, optax.scale_by_adam())
    assert len(calls) == 1 and d.history == [float(f0)]
