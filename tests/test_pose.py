import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import slcvjax as sj

from ._helpers import central_diff


@given(st.integers(0, 2**31 - 1), st.sampled_from([1e-12, 1e-6, 1e-3, 0.5, 3.0]))
def test_so3_exp_matches_rodrigues_and_log_inverts(seed, scale):
    rng = np.random.default_rng(seed)
    w = rng.normal(size=3)
    w = w / np.linalg.norm(w) * scale
    r = np.asarray(sj.so3_exp(jnp.asarray(w)))
    ref, _ = cv2.Rodrigues(w)
    np.testing.assert_allclose(r, ref, atol=1e-12)
    np.testing.assert_allclose(np.asarray(sj.so3_log(jnp.asarray(r))), w, atol=1e-9 * max(1.0, scale))


@pytest.mark.slow
def test_so3_exp_jacobian_at_zero_is_hat():
    jac = jax.jit(jax.jacfwd(sj.so3_exp))  # one compilation, not one per operation
    j = np.asarray(jac(jnp.zeros(3)))
    for i in range(3):
        e = np.zeros(3)
        e[i] = 1.0
        np.testing.assert_allclose(j[:, :, i], np.asarray(sj.geometry.pose.hat(jnp.asarray(e))), atol=1e-15)
    w = jnp.array([0.3, -0.2, 0.1])
    np.testing.assert_allclose(jac(w), central_diff(sj.so3_exp, np.asarray(w)), atol=1e-8)


def test_pose_compose_inverse_apply(rng):
    a = sj.Pose.from_rvec(rng.normal(size=3), rng.normal(size=3) * 10)
    b = sj.Pose.from_rvec(rng.normal(size=3), rng.normal(size=3) * 10)
    p = jnp.asarray(rng.normal(size=(5, 3)))
    np.testing.assert_allclose((a @ b).apply(p), a.apply(b.apply(p)), atol=1e-12)
    np.testing.assert_allclose(a.inverse().apply(a.apply(p)), p, atol=1e-12)
    assert float(jnp.abs((a @ a.inverse()).t).max()) < 1e-12


def test_retract_zero_is_identity_and_small_step_is_first_order(rng):
    a = sj.Pose.from_rvec(rng.normal(size=3), rng.normal(size=3))
    z = a.retract(jnp.zeros(6))
    np.testing.assert_allclose(z.R, a.R, atol=1e-15)
    d = jnp.array([1e-4, -2e-4, 3e-4, 0.1, 0.2, 0.3])
    b = a.retract(d)
    np.testing.assert_allclose(np.asarray(sj.so3_log(b.R @ a.R.T)), np.asarray(d[:3]), atol=1e-12)
    np.testing.assert_allclose(b.t - a.t, d[3:], atol=1e-15)
    assert float(jnp.abs(b.R.T @ b.R - jnp.eye(3)).max()) < 1e-14


def test_rvec_roundtrip(rng):
    rv = rng.normal(size=3)
    rv = rv / np.linalg.norm(rv) * 2.0
    assert np.allclose(sj.Pose.from_rvec(rv, np.zeros(3)).rvec(), rv, atol=1e-10)
    assert sj.Pose.identity().rvec().tolist() == pytest.approx([0.0, 0.0, 0.0])
