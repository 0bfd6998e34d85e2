import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slcvjax.observations.problem import (
    Layout,
    bucket,
    dot_residuals,
    map_padded,
    map_rows,
    pack,
    spot_residuals,
    stack_poses,
)
from slcvjax.observations.simulate import make_scene, simulate


@pytest.fixture(scope="module")
def packed_truth():
    obs, truth = simulate(make_scene("paper", n_lasers=6, n_views=4), noise=0.0, seed=0)
    packed = pack(obs)
    poses = stack_poses([truth.board_poses[v][b] for v, b in packed.pose_keys])
    return obs, truth, packed, poses


@pytest.mark.slow
def test_pack_counts_every_observation(packed_truth):
    obs, _, packed, poses = packed_truth
    n_dots = sum(int(s.sum()) for v in obs.views for _, s in v.boards.values())
    assert packed.dot_points.shape == (n_dots, 3) and packed.dot_pose.shape == (n_dots,)
    assert packed.spot_pixels.shape == (sum(len(v.spots) for v in obs.views), 2)
    assert poses.R.shape == (len(packed.pose_keys), 3, 3)
    assert set(np.asarray(packed.spot_laser).tolist()) == set(range(6))


@pytest.mark.slow
def test_residuals_vanish_at_the_truth_and_grow_away_from_it(packed_truth):
    _, truth, packed, poses = packed_truth
    f = jax.jit(dot_residuals)
    g = jax.jit(spot_residuals)
    rd, okd = f(truth.rig, poses, packed)
    rs, oks = g(truth.rig, poses, packed)
    assert bool(np.all(okd)) and bool(np.all(oks))
    assert float(jnp.abs(rd).max()) < 1e-9 and float(jnp.abs(rs).max()) < 1e-9
    moved = truth.rig.retract(
        jnp.zeros(truth.rig.tangent_dim).at[truth.rig.layout.elements[0].start].set(0.5)
    )  # laser 0: 0.5 mm
    rs2, _ = g(moved, poses, packed)
    hit = np.asarray(packed.spot_laser) == 0
    assert float(jnp.abs(rs2[hit]).min()) > 0.01
    np.testing.assert_allclose(np.asarray(rs2[~hit]), 0.0, atol=1e-9)


def test_bucket_ladder():
    assert [bucket(n) for n in (0, 1, 8, 9, 100, 128, 129)] == [0, 8, 8, 16, 128, 128, 256]
    assert [bucket(n, 4096, 4) for n in (0, 1, 4096, 4097, 16384, 16385)] == [0, 4096, 4096, 16384, 16384, 65536]
    with pytest.raises(ValueError):
        bucket(-1)


@pytest.mark.slow
def test_datasets_of_different_sizes_share_one_layout():
    """Two scenes with different numbers of views, lasers and so of every observation: one set
    of padded sizes (the joint problem's coarse ladder), and a fine one on request."""
    sizes = []
    for n_lasers, n_views, seed in ((3, 3, 0), (8, 9, 1)):
        obs, _ = simulate(make_scene("paper", n_lasers=n_lasers, n_views=n_views), noise=0.5, seed=seed)
        sizes.append(Layout.of(pack(obs), n_lasers=obs.n_lasers))
    assert sizes[0].n != sizes[1].n and sizes[0].lasers[0] != sizes[1].lasers[0]
    assert sizes[0].cap == sizes[1].cap and sizes[0].lasers[1] == sizes[1].lasers[1]
    fine = Layout.of(pack(obs), fine=True)
    assert fine.cap == tuple(bucket(n) for n in fine.n) and fine.cap != sizes[1].cap


@pytest.mark.parametrize("n", [0, 13, 300])
def test_map_padded_equals_the_unpadded_map(n):
    """Padded to its bucket, looped over chunks of 256 (the last moved back to fit): the
    real rows as the plain map gives them."""
    vf = jax.vmap(lambda a, x: (a * jnp.sin(x), jnp.sum(x)), in_axes=(None, 0))
    rows = np.random.default_rng(0).normal(size=(n, 2))
    out = map_padded(jax.jit(map_rows(vf)), 2.0, rows=rows)
    ref = vf(2.0, jnp.asarray(rows))
    assert out[0].shape == (n, 2) and out[1].shape == (n,)
    np.testing.assert_array_equal(np.asarray(out[0]), np.asarray(ref[0]))
    np.testing.assert_array_equal(np.asarray(out[1]), np.asarray(ref[1]))


def _rel(a, b):
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


@pytest.mark.slow
def test_padded_problem_solves_as_the_unpadded_one():
    """Padding in every array (dots, spots, rim, corners, board and direct-view poses, lasers) is
    masked out exactly: the same steps, cost, parameters, covariance and residual table."""
    from slcvjax.calibration.covariance import covariance_compiled
    from slcvjax.calibration.evaluate import solve_compiled
    from slcvjax.calibration.params import Params, make_masks, pad_masks, pad_params, unpad_params

    # the sizes of test_calibrate's scene, so that the padded solve (in its bucket) shares its compilation
    obs, truth = simulate(make_scene("paper", n_lasers=4, n_views=5), noise=0.5, seed=3)
    pk = pack(obs)
    poses = stack_poses([truth.board_poses[v][b] for v, b in pk.pose_keys])
    chess = stack_poses([truth.calibration_view_poses[c] for c in pk.chess_keys])
    p_true = Params(truth.rig, poses, chess)
    rng = np.random.default_rng(0)
    start = p_true.retract(
        jnp.asarray(rng.normal(0, 1e-3, p_true.n_global)), jnp.asarray(rng.normal(0, 1e-3, (p_true.n_blocks, 6)))
    )
    masks = make_masks(start, {"chess_poses"})
    padded = Layout.of(pk, n_lasers=obs.n_lasers)
    exact = padded._replace(cap=padded.n, lasers=(obs.n_lasers,) * 2)  # no padding at all
    assert all(c > n for c, n in zip(padded.cap, padded.n, strict=True)) and padded.lasers[1] > padded.lasers[0]
    out = []
    for lay in (exact, padded):
        p, a, m = pad_params(lay, start), lay.pad_packed(pk), pad_masks(lay, masks)
        res = solve_compiled(p, a, m, loss="huber", scale=1.5, max_steps=100, rtol=1e-10)
        cov = covariance_compiled(res.linearisation, m, None)
        out.append((lay, res, cov))
    (le, re, ce), (lp, rp, cp) = out
    assert int(re.steps) == int(rp.steps) and int(re.result) == int(rp.result)
    assert float(rp.cost) == pytest.approx(float(re.cost), rel=1e-9)
    pe, pp = unpad_params(le, re.params), unpad_params(lp, rp.params)
    for a, b in zip(jax.tree_util.tree_leaves(pp), jax.tree_util.tree_leaves(pe), strict=True):
        assert _rel(a, b) < 1e-9
    assert np.shape(cp.glob)[0] > np.shape(ce.glob)[0]
    assert _rel(lp.unpad_glob(cp.glob, (0, 1)), ce.glob) < 1e-9
    assert float(cp.sigma) == pytest.approx(float(ce.sigma), rel=1e-9)
    assert int(cp.dof) == int(ce.dof)
    assert _rel(lp.unpad_blocks(cp.blocks), le.unpad_blocks(ce.blocks)) < 1e-9
    tp, te = rp.linearisation.table, re.linearisation.table
    for a, b in zip(tp[:4], te[:4], strict=True):  # sq, kind, valid, present
        a, b = lp.unpad_observations(a), le.unpad_observations(b)
        assert a.shape == b.shape and _rel(a, b) < 1e-9

    def real_block(lay, block):  # a padded problem's pose block index as the real problem's
        b = lay.unpad_observations(block)
        chess = b >= lay.cap[4]
        none = b >= lay.cap[4] + lay.cap[5]
        return np.where(none, -1, np.where(chess, b - lay.cap[4] + lay.n[4], b))

    np.testing.assert_array_equal(real_block(lp, tp.block), real_block(le, te.block))
    # the padding itself: no weight, no cost, not valid
    t = rp.linearisation.table
    pad = ~np.asarray(t.present)
    assert pad.sum() == sum(c - n for c, n in zip(lp.cap[:4], lp.n[:4], strict=True))
    assert not np.any(np.asarray(t.valid)[pad]) and np.all(np.asarray(t.sq)[pad] == 0.0)


@pytest.mark.slow
def test_a_new_problem_size_compiles_nothing(compilations):
    """After one calibration, a dataset of other sizes in the same buckets (fewer views and
    lasers, other sensor poses: fewer dots, spots, rim pixels and board poses) compiles no
    program: every function it runs is compiled per bucket, none op by op on its own sizes."""
    from slcvjax.calibration.calibrate import calibrate

    first, _ = simulate(make_scene("paper", n_lasers=7, n_views=11), noise=0.3, seed=5)
    other, _ = simulate(make_scene("paper", n_lasers=5, n_views=9), noise=0.3, seed=6)
    calibrate(first)
    with compilations() as compiled:
        res = calibrate(other)
    assert res.passes[-1].converged
    assert compiled == []


def test_recent_results_are_found_by_identity_and_value_and_the_oldest_leave():
    from slcvjax.support.recent import Recent

    calls = []
    r = Recent(2)

    def f(tag):
        calls.append(tag)
        return tag

    a, b, c = np.zeros(3), np.zeros(3), np.zeros(3)  # equal values, distinct objects
    assert r.get((a,), 1, lambda: f("a1")) == "a1"
    assert r.get((a,), 1, lambda: f("again")) == "a1"  # the same object and value: kept
    assert r.get((b,), 1, lambda: f("b1")) == "b1"  # an equal but other object: computed
    assert r.get((a,), 2, lambda: f("a2")) == "a2"  # another value: computed; a1 leaves
    assert r.get((a,), 1, lambda: f("a1 again")) == "a1 again"
    assert r.get((c, a), None, lambda: f("ca")) == "ca"
    assert calls == ["a1", "b1", "a2", "a1 again", "ca"]
