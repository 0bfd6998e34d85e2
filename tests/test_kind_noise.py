"""Each kind's own noise: leverages, the sandwich covariance, and the per-kind sigmas."""

import jax
import numpy as np
import pytest

from slcvjax.calibration.calibrate import calibrate
from slcvjax.calibration.covariance import covariance_of, kind_noise, kind_sigmas, sandwich_covariance
from slcvjax.calibration.linearise import Linearisation
from slcvjax.calibration.params import Masks
from slcvjax.calibration.schur import Normal, leverage_share, leverage_shares
from slcvjax.observations.simulate import make_scene, simulate

jax.config.update("jax_enable_x64", True)

G, NB = 5, 3


def _schur_problem(rng, n_rows=40):
    """Dense rows of a small Schur-form problem: each row touches the globals and one pose block."""
    jg = rng.normal(size=(n_rows, G))
    jp = rng.normal(size=(n_rows, 6))
    block = rng.integers(0, NB, n_rows)
    block[: 3 * 7] = np.repeat(np.arange(NB), 7)  # every block well determined
    dense = np.zeros((n_rows, G + 6 * NB))
    dense[:, :G] = jg
    for i, b in enumerate(block):
        dense[i, G + 6 * b : G + 6 * b + 6] = jp[i]
    return jg, jp, block, dense


def _normal(jg, jp, block, sel) -> Normal:
    """The plain sums ``J^T J`` of the rows ``sel`` in Schur form."""
    A = jg[sel].T @ jg[sel]
    B = np.zeros((NB, G, 6))
    D = np.zeros((NB, 6, 6))
    for i in np.flatnonzero(sel):
        B[block[i]] += np.outer(jg[i], jp[i])
        D[block[i]] += np.outer(jp[i], jp[i])
    return Normal(A, np.zeros(G), B, D, np.zeros((NB, 6)))


def test_leverage_share_is_the_trace_of_the_hat_matrix():
    rng = np.random.default_rng(0)
    jg, jp, block, dense = _schur_problem(rng)
    every = np.ones(len(jg), bool)
    full = _normal(jg, jp, block, every)
    hat = dense @ np.linalg.solve(dense.T @ dense, dense.T)
    part = rng.uniform(size=len(jg)) < 0.4
    share = leverage_share(full, _normal(jg, jp, block, part), np.ones(G), np.ones(NB))
    assert float(share) == pytest.approx(np.trace(hat[np.ix_(part, part)]), rel=1e-10)
    # over a partition of the rows the shares add up to the number of parameters
    rest = leverage_share(full, _normal(jg, jp, block, ~part), np.ones(G), np.ones(NB))
    assert float(share + rest) == pytest.approx(G + 6 * NB, rel=1e-10)


def test_leverage_shares_of_stacked_parts_are_each_parts_trace():
    rng = np.random.default_rng(2)
    jg, jp, block, dense = _schur_problem(rng)
    full = _normal(jg, jp, block, np.ones(len(jg), bool))
    hat = dense @ np.linalg.solve(dense.T @ dense, dense.T)
    which = rng.integers(0, 3, len(jg))
    parts = [_normal(jg, jp, block, which == k) for k in range(3)]
    stacked = jax.tree_util.tree_map(lambda *a: np.stack(a), *parts)
    shares = leverage_shares(full, stacked, np.ones((3, G)), np.ones((3, NB)))
    for k in range(3):
        sel = which == k
        assert float(shares[k]) == pytest.approx(np.trace(hat[np.ix_(sel, sel)]), rel=1e-10)


def test_sandwich_covariance_is_the_dense_one():
    rng = np.random.default_rng(1)
    jg, jp, block, dense = _schur_problem(rng)
    kinds = rng.integers(0, 2, len(jg))
    sig = np.array([0.3, 1.7])
    full = _normal(jg, jp, block, np.ones(len(jg), bool))
    parts = [_normal(jg, jp, block, kinds == k) for k in range(2)]
    meat = jax.tree_util.tree_map(lambda a, b: sig[0] ** 2 * a + sig[1] ** 2 * b, *parts)
    lin = Linearisation(full, None, np.ones(G), np.ones(NB), float(len(jg)), 1.0)
    cov = sandwich_covariance(lin, meat, Masks(np.ones(G), np.ones(NB)))
    Hinv = np.linalg.inv(dense.T @ dense)
    expected = Hinv @ (dense.T @ np.diag(sig[kinds] ** 2) @ dense) @ Hinv
    np.testing.assert_allclose(cov.glob, expected[:G, :G], rtol=1e-9, atol=1e-12)
    for b in range(NB):
        s = slice(G + 6 * b, G + 6 * b + 6)
        np.testing.assert_allclose(cov.blocks[b], expected[s, s], rtol=1e-9, atol=1e-12)
    # one noise for every row: sigma^2 H^-1
    same = sandwich_covariance(lin, jax.tree_util.tree_map(lambda a: 4.0 * a, full), Masks(np.ones(G), np.ones(NB)))
    np.testing.assert_allclose(same.glob, 4.0 * Hinv[:G, :G], rtol=1e-9)


@pytest.mark.slow
def test_each_kind_sigma_is_its_noise():
    """Dots, spots, rim and corners with their own white noise (not the preset's laser count or
    views): each kind's sigma over its free rows is its noise; the spots' residuals alone (their
    median) understate it, as their rows fix the lasers and, where a board shows few dots, its
    pose.  The leverages add up to the parameters estimated."""
    scene = make_scene("paper", n_lasers=7, n_views=13)
    sig = np.array([0.02, 0.05, 0.008, 0.03])
    est, med, free = [], [], []
    seeds = (3, 4, 5, 6)
    for seed in seeds:
        res = calibrate(simulate(scene, noise=sig, seed=seed)[0])
        noise = kind_noise(res.params, res.packed, res.masks, res.loss, res.scale)
        np.testing.assert_allclose(noise.sigma, [res.kind_sigma[k] for k in ("dot", "spot", "rim", "chess")])
        # the estimated parameters: the rows less the degrees of freedom the covariance counts
        assert noise.leverage.sum() == pytest.approx(noise.rows.sum() - int(res.cov.dof), rel=1e-9)
        est.append(noise.sigma)
        med.append(kind_sigmas(res.params, res.packed))
        free.append(noise.rows - noise.leverage)
        # the lasers' covariance takes the spots' own noise, 2.5x the dots' and 6x the rim's:
        # above what one pooled sigma gives
        pooled = covariance_of(res.params, res.packed, res.masks, res.loss, res.scale, sigma=float(res.cov.sigma))
        g = res.rig.layout.elements[0].start
        assert np.trace(res.cov.glob[g:, g:]) > 1.5 * np.trace(pooled.glob[g:, g:])
    # a sigma over f free rows has a relative std of about 1 / sqrt(2 f): within 4 of those
    tol = 4.0 / np.sqrt(2.0 * np.mean(free, axis=0) * len(seeds))
    assert np.all(np.abs(np.mean(est, axis=0) / sig - 1.0) < tol), (np.mean(est, axis=0) / sig, tol)
    assert np.mean(med, axis=0)[1] / sig[1] < 0.8


@pytest.mark.slow
def test_per_kind_bound_is_the_weighted_estimators():
    """``cramer_rao`` with one sigma per kind: ``(sum_k N_k / sigma_k^2)^-1``. With every sigma
    equal it is ``sigma^2 H^-1``; it scales as the sigmas squared; and by Gauss-Markov it lies
    below the covariance of the estimator that weighs every kind 1 (``H^-1 (sum_k sigma_k^2 N_k)
    H^-1``) in the Loewner order."""
    from slcvjax.calibration.bound import cramer_rao
    from slcvjax.calibration.covariance import kind_linearisations, sandwich_covariance
    from slcvjax.calibration.params import Params, make_masks, pad_masks
    from slcvjax.calibration.schur import raw_normal
    from slcvjax.observations.problem import pack, stack_poses

    obs, truth = simulate(make_scene("paper", n_lasers=4, n_views=6))

    def glob(sigma):
        return np.asarray(cramer_rao(truth, obs, sigma)["cov"].glob)

    one = glob(0.03)
    np.testing.assert_allclose(glob([0.03] * 4), one, rtol=1e-8, atol=1e-14)
    sig = np.array([0.02, 0.05, 0.008, 0.03])
    bound = glob(sig)
    np.testing.assert_allclose(glob(2 * sig), 4 * bound, rtol=1e-8, atol=1e-14)
    # the equal-weight estimator's covariance at the truth, from the same linearisations
    pk = pack(obs)
    params = Params(truth.rig, stack_poses([truth.board_poses[v][b] for v, b in pk.pose_keys]),
                    stack_poses(truth.calibration_view_poses))  # fmt: skip
    masks = make_masks(params)
    layout, full, parts = kind_linearisations(params, pk, masks, "huber", 1e9)
    meat = None
    for p, s in zip(parts, sig, strict=True):
        raw = jax.tree_util.tree_map(lambda a, s=s: s**2 * a, raw_normal(p.normal, p.seen_glob, p.seen_blocks))
        meat = raw if meat is None else jax.tree_util.tree_map(np.add, meat, raw)
    equal = np.asarray(sandwich_covariance(full, meat, pad_masks(layout, masks)).glob)[: one.shape[0], : one.shape[0]]
    gap = np.linalg.eigvalsh(equal - bound)
    assert gap.min() > -1e-9 * np.abs(equal).max()
    assert np.trace(equal) > 1.01 * np.trace(bound)  # here weighting by the noise gains (3.7 %)
