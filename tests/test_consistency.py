"""The final consistency check (slcvjax.calibration.consistency): leverages against their closed
forms, silence on clean data, and an alarm with scaled std where one laser's spots are
noisier than its kind."""

import copy

import numpy as np
import pytest

import slcvjax as sj
from slcvjax.calibration.consistency import per_observation_rows
from slcvjax.calibration.covariance import kind_noise
from slcvjax.calibration.report import report
from slcvjax.observations.simulate import make_scene


def _scene(n_lasers: int, n_views: int):
    return make_scene("paper", n_lasers=n_lasers, n_views=n_views)


@pytest.fixture(scope="module")
def clean():
    obs, truth = sj.simulate(_scene(5, 8), noise=0.4, seed=11)
    return obs, truth, sj.calibrate(obs)


def test_leverages_sum_to_the_estimated_parameters_and_to_each_kinds_share(clean):
    """sum_i h_i = tr(H^-1 J^T J) = the number of estimated parameters, and each kind's rows
    share what :func:`kind_noise` gives by its own route (tr(H^-1 N_k), one normal per kind)."""
    obs, _, res = clean
    sq, dof, (_, row_kind, _, row_free, _, _) = per_observation_rows(res)
    h = 1.0 - row_free
    n_params = int(res.cov.glob.shape[0] - np.sum(np.diag(np.asarray(res.cov.glob)) == 0.0)) + 6 * int(
        np.sum(np.trace(np.asarray(res.cov.blocks), axis1=1, axis2=2) > 0.0)
    )
    assert h.sum() == pytest.approx(n_params, rel=1e-6)
    noise = kind_noise(res.params, res.packed, res.masks, res.loss, res.scale)
    for k in range(len(noise.leverage)):
        if noise.rows[k]:
            assert h[row_kind == k].sum() == pytest.approx(float(noise.leverage[k]), rel=1e-6, abs=1e-6)
    assert np.all((h > -1e-9) & (h < 1.0 + 1e-9))


def _dense_leverages(params, pk, masks, normal, loss, scale):
    """The leverages over every row of the padded problem at once (``rows_at``): the reference
    for the chunked loop of :func:`row_leverages`."""
    import jax
    import jax.numpy as jnp

    from slcvjax.calibration.linearise import n_observations, rows_at
    from slcvjax.calibration.losses import robust_weights
    from slcvjax.calibration.schur import schur_inverse

    rows = rows_at(params, pk, with_jac=True)
    w, _ = robust_weights(rows, n_observations(pk), loss, scale)
    s_inv, d_inv, dinv_bt = schur_inverse(normal)
    g = s_inv.shape[0]
    jg = rows.jg * jnp.concatenate([masks.glob, jnp.zeros(1)])[rows.gidx]
    jp = rows.jp * jnp.concatenate([masks.blocks, jnp.zeros(1)])[rows.pidx][:, None]
    dense = jax.vmap(lambda j, i: jnp.zeros(g + 1).at[i].add(j))(jg, rows.gidx)[:, :g]
    u = dense - jnp.einsum("nkg,nk->ng", jnp.concatenate([dinv_bt, jnp.zeros((1, 6, g))])[rows.pidx], jp)
    d_ext = jnp.concatenate([d_inv, jnp.zeros((1, 6, 6))])[rows.pidx]
    h = w * (jnp.einsum("ng,gh,nh->n", u, s_inv, u) + jnp.einsum("nk,nkl,nl->n", jp, d_ext, jp))
    return rows.r, rows.obs, rows.present & rows.valid, h


def test_chunked_leverages_equal_every_row_at_once(clean):
    """:func:`row_leverages` visits the real rows chunk by chunk; over every padded row at once
    the same rows, ids, flags and leverages come out (to round-off: the loop's program rounds
    otherwise)."""
    import jax

    from slcvjax.calibration.consistency import row_leverages
    from slcvjax.calibration.evaluate import solve_compiled
    from slcvjax.calibration.losses import loss_index
    from slcvjax.calibration.params import pad_problem

    _, _, res = clean
    _, p, pk, m = pad_problem(res.params, res.packed, res.masks)
    normal = solve_compiled(p, pk, m, res.loss, res.scale, 0).linearisation.normal
    args = (p, pk, m, normal, loss_index(res.loss), float(res.scale))
    r, obs, _, use, h = (np.asarray(a) for a in jax.jit(row_leverages)(*args))
    r0, obs0, use0, h0 = (np.asarray(a) for a in jax.jit(_dense_leverages)(*args))
    assert use.sum() > 100 and np.array_equal(use, use0) and np.array_equal(obs[use], obs0[use0])
    np.testing.assert_allclose(r[use], r0[use0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(h[use], h0[use0], rtol=0, atol=1e-12)
    assert np.all(r[~use] == 0.0) and np.all(h[~use] == 0.0)


def test_clean_data_pass_the_check(clean):
    obs, _, res = clean
    unc = report(res, obs)["uncertainty"]
    assert unc["consistency"]["tests"] > 20 and unc["consistency"]["failed"] == []
    assert "status" not in unc and all("std_scale" not in x for x in unc["lasers"])


def test_a_laser_noisier_than_its_kind_is_flagged_and_its_std_scaled():
    """Laser 2's spots carry 3x the others' noise (a dim, blurred spot): the covariance, with one
    sigma for all spots, would understate its std about 3x.  The check names laser 2, the status
    says so, its std is scaled by the root of its spread against the spots' sigma, and the other
    lasers keep theirs.  Plain least squares: the robust passes would leave the noisiest of its
    spots out as misfits and keep the rest."""
    obs, truth = sj.simulate(_scene(5, 12), noise=0.4, seed=12)
    bad = copy.deepcopy(obs)
    rng = np.random.default_rng(3)
    for view in bad.views:
        for s in view.spots:
            if s.laser == 2:
                s.pixel = np.asarray(s.pixel) + rng.normal(0.0, np.sqrt(1.2**2 - 0.4**2), 2)
    res = sj.calibrate(bad, loss="linear")
    unc = report(res, bad)["uncertainty"]
    failed = {f["group"]: f for f in unc["consistency"]["failed"]}
    assert list(failed) == ["laser 2"], unc["consistency"]
    assert "inconsistent" in unc["status"] and "laser 2" in unc["status"]
    item = unc["lasers"][2]
    factor = failed["laser 2"]["std_factor"]
    assert item["std_scale"] == pytest.approx(factor) and factor > 1.5
    assert "inconsistent" in item["status"]
    assert all("std_scale" not in unc["lasers"][i] for i in (0, 1, 3, 4))
    # the factor is the laser's spread against the spots' sigma the covariance assumed
    sq, dof, _ = per_observation_rows(res)
    from slcvjax.calibration.report import obs_table

    norm, kind, ok, view, board, laser, index = obs_table(res)
    sel = ok & (kind == 1) & (laser == 2)
    assert factor == pytest.approx(np.sqrt(sq[sel].sum() / dof[sel].sum()) / res.kind_sigma["spot"], rel=1e-9)
    plain = report(sj.calibrate(obs, loss="linear"), obs)["uncertainty"]
    assert plain["consistency"]["failed"] == []


def _gross_seed2():
    """The preset with 10 % of its dots and spots moved 5-50 px (benchmarks/robustness.py's
    ``gross`` corruption, seed 2), calibrated: (truth, result, uncertainty, errors)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent.parent / "benchmarks"))
    from robustness import gross

    clean, truth = sj.simulate(_scene(10, 16), noise=0.3, seed=2)
    obs, _ = gross(copy.deepcopy(clean), 0.1, np.random.default_rng(1002))
    res = sj.calibrate(obs)
    unc = report(res, obs)["uncertainty"]
    # the errors at the true working points (the clean scene's, as the robustness benchmark takes them)
    pos, ang = sj.laser_errors(res.rig, truth.rig, sj.cramer_rao(truth, clean, 0.3)["x_ref"])
    return truth, res, unc, (pos, np.degrees(ang))


@pytest.fixture(scope="module")
def gross_seed2():
    return _gross_seed2()


@pytest.mark.slow
def test_a_laser_that_lost_most_of_its_spots_has_its_std_withdrawn(gross_seed2):
    """There the repairs leave 5 of laser 1's spots out and give 2 to laser 6: its line, on the
    3 left of the 8 once its own, ends some 50x the bound, where its covariance claimed a std 44x
    smaller than its error.  The report withdraws that std (None) and says why."""
    from slcvjax.calibration.bound import laser_std, laser_working_points

    _, res, unc, (pos, ang) = gross_seed2
    withdrawn = [i for i, x in enumerate(unc["lasers"]) if x["position_std_mm"] is None]
    assert withdrawn == [1], withdrawn
    item = unc["lasers"][1]
    assert item["direction_std_deg"] is None and item["status"].startswith("suspect: only 3 of the 8 spots"), item
    assert "kept fewer than 50% of their spots" in unc["status"]
    # what the covariance alone would have claimed: a std far below the error
    sd_p, _ = laser_std(res.rig, np.asarray(res.cov.glob), laser_working_points(res.rig, res.params.poses, res.packed))
    assert pos[1] > 10 * sd_p[1], (pos[1], sd_p[1])


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason="laser 6, given two of laser 1's spots by the repairs, ends 1.22 deg off at a std of 0.20 deg (6x): "
    "its residuals pass the final check (issue 61, item 1: a robust consensus)",
)
def test_no_laser_ends_beyond_3_of_its_reported_std(gross_seed2):
    _, _, unc, (pos, ang) = gross_seed2
    for i, item in enumerate(unc["lasers"]):
        if item["position_std_mm"] is not None:
            assert pos[i] <= 3 * item["position_std_mm"] and ang[i] <= 3 * item["direction_std_deg"], (i, item)


def test_normality_p_is_dagostino_pearsons_test():
    """:func:`normality_p` (written out to spare ``import slcvjax`` scipy.stats) against
    ``scipy.stats.normaltest`` on normal, heavy-tailed, skewed and constant-skew samples."""
    from scipy import stats

    from slcvjax.calibration.consistency import normality_p

    rng = np.random.default_rng(0)
    samples = [rng.normal(size=20), rng.normal(size=3000) * 4.0, rng.standard_t(3, 500), rng.exponential(1.0, 200)]
    samples += [np.r_[-np.ones(15), np.ones(15)], rng.uniform(-1, 1, 1000)]
    for z in samples:
        assert normality_p(z) == pytest.approx(stats.normaltest(z).pvalue, rel=1e-10, abs=1e-300)
