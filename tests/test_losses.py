"""The robust losses of :mod:`slcvjax.calibration.losses` against their closed forms, and each
IRLS weight against the finite difference of its cost: ``w = 2 d rho / d sq``."""

import jax.numpy as jnp
import numpy as np
import pytest

from slcvjax.calibration.losses import INVALID_PX, ObservationTable, loss_index, robust_cost, robust_observations
from slcvjax.calibration.options import LOSSES

C = 1.5  # the loss scale (px)
# squared norms either side of the scale (c^2 = 2.25), from tiny to a gross outlier
SQ = np.array([1e-6, 0.01, 0.5, 2.0, 2.5, 9.0, 100.0, 1e4])


def _rho_closed(loss: str, sq: np.ndarray) -> np.ndarray:
    norm = np.sqrt(sq)
    if loss == "huber":
        return np.where(norm <= C, 0.5 * sq, C * norm - 0.5 * C * C)
    if loss == "cauchy":
        return 0.5 * C * C * np.log1p(sq / (C * C))
    return 0.5 * sq


@pytest.mark.parametrize("loss", LOSSES)
def test_the_cost_is_its_closed_form(loss):
    rho, _ = robust_cost(jnp.asarray(SQ), loss, C)
    np.testing.assert_allclose(np.asarray(rho), _rho_closed(loss, SQ), rtol=1e-13, atol=1e-300)


@pytest.mark.parametrize("loss", LOSSES)
def test_the_weight_is_twice_the_cost_derivative(loss):
    """Central differences of ``rho`` in ``sq`` (step relative to ``sq``; both sides on one
    branch: no ``sq`` lies within a step of Huber's kink at ``c^2``)."""
    h = 1e-6 * SQ
    up, _ = robust_cost(jnp.asarray(SQ + h), loss, C)
    down, _ = robust_cost(jnp.asarray(SQ - h), loss, C)
    fd = (np.asarray(up) - np.asarray(down)) / (2 * h)
    _, w = robust_cost(jnp.asarray(SQ), loss, C)
    np.testing.assert_allclose(np.asarray(w), 2.0 * fd, rtol=1e-6)


@pytest.mark.parametrize("loss", LOSSES)
def test_a_traced_loss_index_selects_the_same_loss(loss):
    a = robust_cost(jnp.asarray(SQ), loss, C)
    b = robust_cost(jnp.asarray(SQ), jnp.asarray(loss_index(loss)), C)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_an_unknown_loss_is_refused_by_name():
    with pytest.raises(ValueError, match="unknown loss 'l1'"):
        loss_index("l1")


def test_the_observations_weights_and_costs():
    """Dots and spots robust, the rim and the corners plain, each whitened by its kind's weight;
    an invalid observation costs what ``INVALID_PX`` costs, padding nothing."""
    sq = np.array([9.0, 9.0, 9.0, 9.0, 0.0, 4.0])
    table = ObservationTable(
        sq=jnp.asarray(sq),
        kind=jnp.asarray([0, 1, 2, 3, 0, 1]),  # dot, spot, rim, chess, dot, spot
        valid=jnp.asarray([True, True, True, True, False, False]),  # padding is not valid either
        present=jnp.asarray([True, True, True, True, True, False]),
        block=jnp.zeros(6, int),
    )
    kw = jnp.asarray([1.0, 0.5, 2.0, 1.0])
    w, rho = (np.asarray(x) for x in robust_observations(table, "cauchy", C, kw))
    k = np.asarray(kw)[[0, 1, 2, 3]]
    robust_w = 1.0 / (1.0 + k[:2] * sq[:2] / C**2)
    np.testing.assert_allclose(w[:4], np.concatenate([robust_w * k[:2], k[2:]]), rtol=1e-13)
    np.testing.assert_allclose(rho[:2], _rho_closed("cauchy", k[:2] * sq[:2]), rtol=1e-13)
    np.testing.assert_allclose(rho[2:4], 0.5 * k[2:] * sq[2:4], rtol=1e-13)
    np.testing.assert_allclose(rho[4], _rho_closed("cauchy", np.array([INVALID_PX**2]))[0], rtol=1e-13)
    assert w[5] == 0.0 and rho[5] == 0.0  # padding
