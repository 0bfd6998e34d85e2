"""Differentiable calibration: implicit derivatives of the solution against finite differences."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slcvjax.calibration import implicit as _implicit
from slcvjax.calibration.calibrate import calibrate
from slcvjax.calibration.params import pad_problem
from slcvjax.geometry.camera import undistort
from slcvjax.geometry.mirror import solve_mirror_point
from slcvjax.observations.simulate import make_scene, simulate

# the scene and noise of test_calibrate's joint test: its compiled LM is reused
SCENE = dict(n_lasers=4, n_views=5)


def _flat(params):
    return jnp.concatenate([jnp.ravel(x) for x in jax.tree_util.tree_leaves(params)])


@pytest.fixture(scope="module")
def solved():
    obs, _ = simulate(make_scene("paper", **SCENE), noise=0.5, seed=3)
    res = calibrate(obs)
    arr = res.packed.arrays()
    p0, steps = _implicit.stationary_point(res.params, arr, res.masks, res.loss, res.scale)
    return res, arr, p0, steps


def _fd_hessian(fun, x, eps):
    """Central differences of the (exact, first-order) Jacobian of ``fun``."""
    jac = jax.jit(jax.jacfwd(fun))
    cols = [(jac(x.at[i].add(eps)) - jac(x.at[i].add(-eps))) / (2 * eps) for i in range(x.shape[0])]
    return jnp.stack(cols, -1)


@pytest.mark.slow
def test_second_derivatives_of_the_reflection_point_are_exact():
    mir = make_scene("paper").rig.mirror
    p = jnp.array([150.0, 40.0, 56.0])

    def point(q):
        return solve_mirror_point(mir, q)[0]

    fd = _fd_hessian(point, p, 1e-3)
    exact = jax.jit(jax.jacfwd(jax.jacrev(point)))(p)
    scale = float(jnp.max(jnp.abs(fd)))
    assert scale > 1e-4
    np.testing.assert_allclose(np.asarray(exact), np.asarray(fd), atol=1e-6 * scale)


def test_second_derivatives_of_undistortion_are_exact():
    cam = make_scene("paper").rig.camera
    uv = jnp.array([40.0, 30.0])

    def xy(dist):
        return undistort(dataclasses.replace(cam, dist=dist), uv)[0]

    exact = jax.jit(jax.jacfwd(jax.jacrev(xy)))(cam.dist)

    fd = _fd_hessian(xy, cam.dist, 1e-6)
    np.testing.assert_allclose(np.asarray(exact), np.asarray(fd), atol=1e-6 * float(jnp.max(jnp.abs(fd))))


@pytest.mark.slow
def test_newton_polish_reaches_a_stationary_point(solved):
    res, arr, p0, steps = solved
    assert 1 <= steps <= 6
    # padded to its shape buckets as the library pads it: the polish's compiled linearisation
    _, p_pad, arr_pad, masks_pad = pad_problem(p0, arr, res.masks)
    lin = _implicit.linearised(p_pad, arr_pad, masks_pad, res.loss, res.scale, None)
    assert float(jnp.max(jnp.abs(lin.step_g))) < 1e-9


@pytest.mark.slow
def test_newton_from_the_lm_solution_compiles_its_linearisation_once(solved):
    # the LM's solution holds host arrays, Newton's steps give device arrays: one program for both
    res, arr, _, _ = solved
    _implicit.LINEARISE[res.loss].clear()
    _, steps = _implicit.stationary_point(res.params, arr, res.masks, res.loss, res.scale)
    assert steps >= 1
    assert _implicit.LINEARISE[res.loss].signatures() == 1


@pytest.mark.slow
def test_the_sensitivity_of_other_sizes_compiles_no_linearisation(solved):
    # another dataset's numbers of lasers, views, dots and spots fall in the same shape buckets
    res, *_ = solved
    first = _implicit.sensitivity(res)
    n = _implicit.LINEARISE[res.loss].signatures()
    obs, _ = simulate(make_scene("paper", n_lasers=3, n_views=6), noise=0.5, seed=4)
    other = calibrate(obs)
    assert other.packed.counts[0] != res.packed.counts[0] and other.rig.lasers.n != res.rig.lasers.n
    sens = _implicit.sensitivity(other)
    # and the solution's tangent (differentiable_solution's), of either size
    arr = other.packed.arrays()
    dg, dp = _implicit.solution_tangent(other.params, arr, other.masks, other.loss, other.scale, None, arr)
    assert dg.shape == (other.rig.tangent_dim,) and dp.shape == (other.params.n_blocks, 6)
    assert _implicit.LINEARISE[res.loss].signatures() == n
    assert sens.glob.shape == (other.rig.tangent_dim, 2 * int(np.sum(other.packed.counts)))
    assert first.glob.shape == (res.rig.tangent_dim, 2 * int(np.sum(res.packed.counts)))
    assert np.all(np.isfinite(sens.glob))


@pytest.mark.slow
def test_solution_derivative_matches_finite_differences(solved):
    res, arr, p0, _ = solved
    rng = np.random.default_rng(0)
    dpk = {
        k: jnp.asarray(rng.normal(size=getattr(arr, k).shape)) * (0.1 if "points" in k else 1.0)
        for k in _implicit.DATA_FIELDS
    }
    dg, dp = _implicit.solution_tangent(p0, arr, res.masks, res.loss, res.scale, None, dpk=_Obj(dpk))
    _, analytic = jax.jvp(lambda a, b: _flat(p0.retract(a, b)), (jnp.zeros_like(dg), jnp.zeros_like(dp)), (dg, dp))
    # truth: re-solve (to the exact stationary point) on perturbed data
    eps, outs = 1e-4, []
    for e in (eps, -eps):
        pk = dataclasses.replace(arr, **{k: getattr(arr, k) + e * v for k, v in dpk.items()})
        q, _ = _implicit.stationary_point(p0, pk, res.masks, res.loss, res.scale)
        outs.append(_flat(q))
    fd = (outs[0] - outs[1]) / (2 * eps)
    scale = float(jnp.max(jnp.abs(fd)))
    assert scale > 1.0
    np.testing.assert_allclose(np.asarray(analytic), np.asarray(fd), atol=1e-6 * scale)


@pytest.mark.slow
def test_differentiable_solution_under_jvp_and_the_pixel_sensitivity(solved):
    res, arr, p0, _ = solved
    rng = np.random.default_rng(1)
    d_spot = jnp.asarray(rng.normal(size=arr.spot_pixels.shape))

    def lasers(spot_pixels):
        pk = dataclasses.replace(arr, spot_pixels=spot_pixels)
        sol = _implicit.differentiable_solution(p0, pk, res.masks, res.loss, res.scale)
        return jnp.concatenate([sol.rig.lasers.points.ravel(), sol.rig.lasers.directions.ravel()])

    value, tangent = jax.jvp(lasers, (arr.spot_pixels,), (d_spot,))
    np.testing.assert_array_equal(np.asarray(value[:3]), np.asarray(p0.rig.lasers.points[0]))
    dg, dp = _implicit.solution_tangent(p0, arr, res.masks, res.loss, res.scale, None, _Obj({"spot_pixels": d_spot}))
    n_l = p0.rig.lasers.n
    _, expect = jax.jvp(lambda a, b: lasers_of(p0.retract(a, b)), (jnp.zeros_like(dg), jnp.zeros_like(dp)), (dg, dp))
    np.testing.assert_allclose(np.asarray(tangent), np.asarray(expect), rtol=1e-10, atol=1e-12)
    # the per-pixel sensitivity: its spot columns applied to the same change give the same tangent
    sens = _implicit.sensitivity(res)
    cols = sens.kind == 1
    np.testing.assert_allclose(sens.glob[:, cols] @ np.asarray(d_spot).ravel(), np.asarray(dg), atol=1e-9)
    assert sens.laser_point.shape == (n_l, 3, sens.glob.shape[1])
    # a spot moves its own laser most (the others only through the camera, mirror and pose)
    j = int(np.flatnonzero(cols)[0])
    own = int(np.asarray(arr.spot_laser)[sens.index[j]])
    others = [i for i in range(n_l) if i != own]
    assert np.abs(sens.laser_point[own, :, j]).max() > 10 * np.abs(sens.laser_point[others, :, j]).max()


def lasers_of(params):
    return jnp.concatenate([params.rig.lasers.points.ravel(), params.rig.lasers.directions.ravel()])


class _Obj:
    """Attributes from a dict (a partial set of data tangents)."""

    def __init__(self, d):
        self.__dict__.update(d)
