"""The joint LM's losses against their closed forms, and its result codes: converged at the
truth, max_steps when stopped early, an unknown loss refused."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slcvjax.calibration.evaluate import solve_compiled
from slcvjax.calibration.lm import CONVERGED, MAX_STEPS
from slcvjax.calibration.losses import loss_index, robust_cost
from slcvjax.calibration.params import Params, make_masks, pad_params, pad_problem
from slcvjax.observations.problem import pack, stack_poses
from slcvjax.observations.simulate import box_scene, paper_rig, paper_views, simulate


@pytest.mark.parametrize("c", [0.5, 2.0])
@pytest.mark.slow
def test_losses_match_their_closed_forms(c):
    r = np.linspace(0.0, 6.0 * c, 61)
    sq = jnp.asarray(r**2)
    huber = np.where(r <= c, 0.5 * r**2, c * r - 0.5 * c * c)
    cauchy = 0.5 * c * c * np.log1p(r**2 / (c * c))
    for name, ref in (("huber", huber), ("cauchy", cauchy), ("linear", 0.5 * r**2)):
        rho, w = robust_cost(sq, name, c)
        np.testing.assert_allclose(rho, ref, rtol=1e-12, atol=1e-15)
        # the IRLS weight is 2 d rho / d sq (away from sq = 0, where the derivative is one-sided)
        drho = jax.vmap(jax.grad(lambda s, name=name: robust_cost(s, name, c)[0]))(sq[1:])
        np.testing.assert_allclose(w[1:], 2.0 * drho, rtol=1e-9)
        # a traced loss index selects the same
        rho_t, w_t = robust_cost(sq, jnp.asarray(loss_index(name)), c)
        np.testing.assert_allclose(rho_t, rho, rtol=1e-15)
        np.testing.assert_allclose(w_t, w, rtol=1e-15)
    assert np.all(cauchy <= huber + 1e-15) and np.all(huber <= 0.5 * r**2 + 1e-15)
    with pytest.raises(ValueError, match="unknown loss 'l2'"):
        robust_cost(sq, "l2", c)


def _box_problem(noise: float = 0.0, seed: int = 0):
    """A small box scene's problem at the truth: its parameters, padded arrays and masks, layout."""
    obs, truth = simulate(box_scene(paper_rig(3), paper_views(4), n_chess_views=4), noise=noise, seed=seed)
    pk = pack(obs)
    poses = stack_poses([truth.board_poses[v][b] for v, b in pk.pose_keys])
    chess = stack_poses([truth.calibration_view_poses[c] for c in pk.chess_keys])
    params = Params(truth.rig, poses, chess)
    layout, _, arr, masks = pad_problem(params, pk, make_masks(params))  # as the calibration pads it
    return params, arr, masks, layout


def _off_intrinsics(params):
    """``params`` with fx, fy, cx, cy off by a few px."""
    delta = np.zeros(params.rig.tangent_dim)
    delta[:4] = [4.0, -3.0, 2.0, 2.0]
    return Params(params.rig.retract(jnp.asarray(delta)), params.poses, params.chess)


@pytest.fixture(scope="module")
def problem():
    return _box_problem()


@pytest.mark.slow
def test_converged_at_the_truth(problem):
    params, arr, masks, layout = problem
    res = solve_compiled(pad_params(layout, params), arr, masks, "linear", 1.0, 50)
    assert int(res.result) == CONVERGED
    assert float(res.cost) < 1e-16 and int(res.steps) <= 3


def test_max_steps_when_stopped_early(problem):
    params, arr, masks, layout = problem
    start = _off_intrinsics(params)
    res = solve_compiled(pad_params(layout, start), arr, masks, "huber", 1.0, 1)
    assert int(res.result) == MAX_STEPS and int(res.steps) == 1
    assert float(res.cost) < float(res.initial_cost)
    full = solve_compiled(pad_params(layout, start), arr, masks, "huber", 1.0, 100)
    assert int(full.result) == CONVERGED and float(full.cost) < 1e-12 * float(full.initial_cost)


def test_a_solve_stops_within_its_tolerance_of_the_minimum():
    # noisy observations: the solve ends where its model predicts a decrease under rtol, which must
    # leave at most that much of the cost to a solve run on until its steps change nothing
    params, arr, masks, layout = _box_problem(noise=0.5, seed=3)
    start = pad_params(layout, _off_intrinsics(params))
    rtol = 1e-10
    res = solve_compiled(start, arr, masks, "huber", 1.5, 100, rtol)
    assert int(res.result) == CONVERGED and int(res.steps) >= 1
    # from the same start (each solve holds the rim rows' normalisation at its start's), on until
    # a step changes nothing
    further = solve_compiled(start, arr, masks, "huber", 1.5, 100, 0.0)
    assert int(further.steps) > int(res.steps)
    assert float(further.cost) <= float(res.cost)
    assert float(res.cost) - float(further.cost) <= rtol * float(res.cost)
