"""The Schur algebra of :mod:`slcvjax.calibration.schur` against dense NumPy linear algebra: the
normal equations scattered from rows equal ``J^T W J`` and ``J^T W r`` of the dense Jacobian,
and every solve through the Schur complement equals the dense solve."""

import jax.numpy as jnp
import numpy as np
import pytest

from slcvjax.calibration.schur import (
    Rows,
    damping_diagonal,
    normal_equations,
    predicted_decrease,
    schur_inverse,
    schur_solve,
    schur_step,
)

G, NB, W = 7, 3, 4  # global columns, pose blocks, global columns per row


def _rows(seed: int, n: int = 60) -> Rows:
    """``n`` random rows: each reaches ``W`` distinct global columns (some the unused spare ``G``)
    and one pose block (some none, ``NB``)."""
    rng = np.random.default_rng(seed)
    gidx = np.stack([rng.permutation(G + 1)[:W] for _ in range(n)])
    pidx = rng.integers(0, NB + 1, n)
    pidx[: 6 * NB] = np.repeat(np.arange(NB), 6)  # every block well reached
    return Rows(
        r=jnp.asarray(rng.normal(size=n)),
        jg=jnp.asarray(rng.normal(size=(n, W))),
        gidx=jnp.asarray(gidx),
        jp=jnp.asarray(rng.normal(size=(n, 6))),
        pidx=jnp.asarray(pidx),
        obs=jnp.arange(n),
        kind=jnp.zeros(n, int),
        valid=jnp.ones(n, bool),
        present=jnp.ones(n, bool),
    )


def _dense_jacobian(rows: Rows) -> np.ndarray:
    """The rows' Jacobian over ``G`` global then ``6 NB`` pose columns, built row by row."""
    n = rows.r.shape[0]
    J = np.zeros((n, G + 6 * NB))
    for i in range(n):
        for j in range(W):
            if int(rows.gidx[i, j]) < G:
                J[i, int(rows.gidx[i, j])] += float(rows.jg[i, j])
        k = int(rows.pidx[i])
        if k < NB:
            J[i, G + 6 * k : G + 6 * k + 6] = np.asarray(rows.jp[i])
    return J


def _dense_h(ne) -> np.ndarray:
    """``[[A, B], [B^T, D]]`` as one dense matrix."""
    H = np.zeros((G + 6 * NB, G + 6 * NB))
    H[:G, :G] = np.asarray(ne.A)
    for k in range(NB):
        s = slice(G + 6 * k, G + 6 * k + 6)
        H[:G, s] = np.asarray(ne.B[k])
        H[s, :G] = np.asarray(ne.B[k]).T
        H[s, s] = np.asarray(ne.D[k])
    return H


@pytest.fixture(scope="module")
def system():
    rows = _rows(0)
    w = jnp.asarray(np.random.default_rng(1).uniform(0.2, 2.0, rows.r.shape[0]))
    ne = normal_equations(rows, w, G, NB, jnp.ones(G), jnp.ones(NB))
    return rows, np.asarray(w), ne


def test_the_normal_equations_are_the_dense_ones(system):
    rows, w, ne = system
    J = _dense_jacobian(rows)
    np.testing.assert_allclose(_dense_h(ne), J.T @ (w[:, None] * J), rtol=1e-12, atol=1e-12)
    g = J.T @ (w * np.asarray(rows.r))
    np.testing.assert_allclose(np.asarray(ne.bg), g[:G], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(ne.bp).ravel(), g[G:], rtol=1e-12, atol=1e-12)


def test_a_frozen_column_and_block_get_a_unit_diagonal_and_nothing_else():
    rows = _rows(2)
    w = jnp.ones(rows.r.shape[0])
    gmask, pmask = np.ones(G), np.ones(NB)
    gmask[2], pmask[1] = 0.0, 0.0
    ne = normal_equations(rows, w, G, NB, jnp.asarray(gmask), jnp.asarray(pmask))
    J = _dense_jacobian(rows)
    J[:, 2] = 0.0
    J[:, G + 6 : G + 12] = 0.0
    H = J.T @ J
    H[2, 2] = 1.0
    H[G + 6 : G + 12, G + 6 : G + 12] = np.eye(6)
    np.testing.assert_allclose(_dense_h(ne), H, rtol=1e-12, atol=1e-12)
    assert float(ne.bg[2]) == 0.0 and not np.any(np.asarray(ne.bp[1]))


def test_schur_solve_is_the_dense_solve(system):
    _, _, ne = system
    rng = np.random.default_rng(3)
    rg, rp = rng.normal(size=(G, 2)), rng.normal(size=(NB, 6, 2))
    xg, xp = schur_solve(ne.A, ne.B, ne.D, jnp.asarray(rg), jnp.asarray(rp))
    x = np.linalg.solve(_dense_h(ne), np.concatenate([rg, rp.reshape(6 * NB, 2)]))
    np.testing.assert_allclose(np.asarray(xg), x[:G], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.asarray(xp).reshape(6 * NB, 2), x[G:], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("lam", [0.0, 1e-3, 10.0])
def test_the_damped_step_is_the_dense_damped_solve(system, lam):
    """Marquardt's step: ``(H + lam diag(H)) d = -g``, and the decrease its model predicts,
    ``-(g.d + d.H d / 2)`` with the undamped ``H``."""
    _, _, ne = system
    H = _dense_h(ne)
    g = np.concatenate([np.asarray(ne.bg), np.asarray(ne.bp).ravel()])
    d = np.linalg.solve(H + lam * np.diag(np.maximum(np.diag(H), 1e-9)), -g)
    dg, dp = schur_step(ne, lam)
    np.testing.assert_allclose(np.asarray(dg), d[:G], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.asarray(dp).ravel(), d[G:], rtol=1e-9, atol=1e-12)
    decrease = -(g @ d + 0.5 * d @ H @ d)
    np.testing.assert_allclose(float(predicted_decrease(ne, lam, dg, dp)), decrease, rtol=1e-9)
    da, dd = damping_diagonal(ne)
    np.testing.assert_array_equal(np.concatenate([np.asarray(da), np.asarray(dd).ravel()]), np.diag(H))


def test_schur_inverse_gives_the_blocks_of_the_dense_inverse(system):
    _, _, ne = system
    Hinv = np.linalg.inv(_dense_h(ne))
    Sinv, Dinv, Dinv_Bt = (np.asarray(x) for x in schur_inverse(ne))
    np.testing.assert_allclose(Sinv, Hinv[:G, :G], rtol=1e-9, atol=1e-12)
    for k in range(NB):
        s = slice(G + 6 * k, G + 6 * k + 6)
        # the pose block of H^-1: D_k^-1 + (D_k^-1 B_k^T) S^-1 (D_k^-1 B_k^T)^T; its coupling -S^-1 (D_k^-1 B_k^T)^T
        np.testing.assert_allclose(Dinv[k] + Dinv_Bt[k] @ Sinv @ Dinv_Bt[k].T, Hinv[s, s], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(-Sinv @ Dinv_Bt[k].T, Hinv[:G, s], rtol=1e-9, atol=1e-12)
