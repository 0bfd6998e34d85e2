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
    from slcvjax.calibration.report import _obs_table

    norm, kind, ok, view, board, laser, index = _obs_table(res)
    sel = ok & (kind == 1) & (laser == 2)
    assert factor == pytest.approx(np.sqrt(sq[sel].sum() / dof[sel].sum()) / res.kind_sigma["spot"], rel=1e-9)
    plain = report(sj.calibrate(obs, loss="linear"), obs)["uncertainty"]
    assert plain["consistency"]["failed"] == []
