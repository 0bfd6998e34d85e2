import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slcvjax.support.safe import (
    orthonormal_basis,
    safe_arccos,
    safe_div,
    safe_norm,
    safe_normalize,
    safe_sqrt,
    solve2x2,
)


def _finite_grad(f, x):
    g = jax.grad(lambda x: jnp.sum(f(x)))(x)
    return bool(np.all(np.isfinite(np.asarray(g))))


def test_values_match_numpy():
    x = jnp.array([4.0, 0.25, 9.0])
    np.testing.assert_allclose(safe_sqrt(x), np.sqrt(x))
    v = jnp.array([3.0, 4.0, 12.0])
    assert float(safe_norm(v)) == pytest.approx(13.0)
    np.testing.assert_allclose(safe_normalize(v), np.array([3, 4, 12]) / 13.0)
    assert float(safe_div(1.0, 4.0)) == 0.25
    assert float(safe_arccos(jnp.asarray(0.5))) == pytest.approx(np.pi / 3)


@pytest.mark.parametrize(
    "f, x",
    [
        (safe_sqrt, jnp.array([0.0, -1.0, 1e-320])),
        (safe_norm, jnp.zeros(3)),
        (safe_normalize, jnp.zeros(3)),
        (lambda x: safe_div(1.0, x), jnp.array([0.0])),
        (safe_arccos, jnp.array([1.0, -1.0, 1.5])),
    ],
)
def test_singular_points_give_finite_values_and_gradients(f, x):
    assert np.all(np.isfinite(np.asarray(f(x))))
    assert _finite_grad(f, x)


def test_singular_outputs_are_documented_values():
    assert float(safe_sqrt(jnp.asarray(-2.0))) == 0.0
    np.testing.assert_array_equal(safe_normalize(jnp.zeros(3)), np.zeros(3))
    assert float(safe_div(3.0, 0.0)) == 0.0


@pytest.mark.parametrize("axis", [[0, 0, 1], [1, 0, 0], [0, 1, 0], [1, 1, 1], [0.3, -0.2, 0.9], [-1, 1e-9, 0]])
def test_orthonormal_basis_is_right_handed(axis):
    a = jnp.asarray(axis, dtype=float)
    a = a / jnp.linalg.norm(a)
    e1, e2 = orthonormal_basis(a)
    frame = np.stack([e1, e2, a], axis=1)
    np.testing.assert_allclose(frame.T @ frame, np.eye(3), atol=1e-14)
    assert np.linalg.det(frame) == pytest.approx(1.0)


def test_solve2x2_matches_numpy_and_is_safe_when_singular():
    a = jnp.array([[3.0, 1.0], [2.0, 5.0]])
    b = jnp.array([1.0, -2.0])
    np.testing.assert_allclose(solve2x2(a, b), np.linalg.solve(a, b), rtol=1e-14)
    np.testing.assert_array_equal(solve2x2(jnp.zeros((2, 2)), b), np.zeros(2))
