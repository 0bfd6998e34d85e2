import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slcvjax._problem import dot_residuals, pack, spot_residuals, stack_poses
from slcvjax._simulate import make_scene, simulate


@pytest.fixture(scope="module")
def packed_truth():
    obs, truth = simulate(make_scene("paper", n_lasers=6, n_views=4), noise=0.0, seed=0)
    packed = pack(obs)
    poses = stack_poses([truth.board_poses[v][b] for v, b in packed.pose_keys])
    return obs, truth, packed, poses


def test_pack_counts_every_observation(packed_truth):
    obs, _, packed, poses = packed_truth
    n_dots = sum(int(s.sum()) for v in obs.views for _, s in v.boards.values())
    assert packed.dot_points.shape == (n_dots, 3) and packed.dot_pose.shape == (n_dots,)
    assert packed.spot_pixels.shape == (sum(len(v.spots) for v in obs.views), 2)
    assert poses.R.shape == (len(packed.pose_keys), 3, 3)
    assert set(np.asarray(packed.spot_laser).tolist()) == set(range(6))


def test_residuals_vanish_at_the_truth_and_grow_away_from_it(packed_truth):
    _, truth, packed, poses = packed_truth
    f = jax.jit(dot_residuals)
    g = jax.jit(spot_residuals)
    rd, okd = f(truth.rig, poses, packed)
    rs, oks = g(truth.rig, poses, packed)
    assert bool(np.all(okd)) and bool(np.all(oks))
    assert float(jnp.abs(rd).max()) < 1e-9 and float(jnp.abs(rs).max()) < 1e-9
    moved = truth.rig.retract(jnp.zeros(truth.rig.tangent_dim).at[9 + 5].set(0.5))  # laser 0 moved 0.5 mm
    rs2, _ = g(moved, poses, packed)
    hit = np.asarray(packed.spot_laser) == 0
    assert float(jnp.abs(rs2[hit]).min()) > 0.01
    np.testing.assert_allclose(np.asarray(rs2[~hit]), 0.0, atol=1e-9)
