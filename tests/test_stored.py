"""A calibration file carries its problem: read back, it gives the live result's figures."""

import json

import jax
import numpy as np
import pytest

import slcvjax as sj
from slcvjax.calibration.covariance import kind_noise
from slcvjax.observations.formats import FormatError, calibration_to_json
from slcvjax.observations.simulate import make_scene

# not the preset: 4 lasers, 7 views; two spots given another laser's label (repairs to carry)
SCENE = dict(n_lasers=4, n_views=7)


def _close(a, b, where=""):
    """``a`` and ``b`` (JSON values) equal, numbers to 1e-9 (relative, or absolute near 0)."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), f"{where}: keys {set(a) ^ set(b)}"
        for k in a:
            _close(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), f"{where}: lengths"
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _close(x, y, f"{where}[{i}]")
    elif isinstance(a, float) and isinstance(b, float):
        assert abs(a - b) <= 1e-9 * max(1.0, abs(a)), f"{where}: {a} != {b}"
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"


def _json(x):
    return json.loads(json.dumps(x))


def _calibrated(tmp_path, rigid=False):
    obs, truth = sj.simulate(make_scene("paper", **SCENE), noise=0.3, seed=21)
    view = obs.views[2]
    view.spots[0].laser = (view.spots[0].laser + 1) % obs.n_lasers
    live = sj.calibrate(obs, rigid=rigid)
    path = tmp_path / "cal.json"
    sj.write_calibration(path, sj.to_calibration(live, obs))
    return obs, truth, live, sj.load_result(path)


@pytest.fixture(scope="module")
def free(tmp_path_factory):
    return _calibrated(tmp_path_factory.mktemp("free"))


def test_the_file_gives_back_the_solution_and_the_problem(free):
    obs, _, live, loaded = free
    for a, b in zip(jax.tree_util.tree_leaves(live.params), jax.tree_util.tree_leaves(loaded.params), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    for name in ("dot_pixels", "dot_points", "spot_laser", "spot_pixels", "rim_pixels", "chess_pixels", "counts"):
        np.testing.assert_array_equal(np.asarray(getattr(live.packed, name)), getattr(loaded.packed, name))
    assert loaded.packed.pose_keys == live.packed.pose_keys and loaded.packed.spot_src == live.packed.spot_src
    np.testing.assert_array_equal(np.asarray(live.masks.glob), loaded.masks.glob)
    assert loaded.repairs and loaded.repairs == live.repairs  # the relabelled spot, as records
    # written as they were
    assert json.dumps([r.to_json() for r in loaded.repairs]) == json.dumps([r.to_json() for r in live.repairs])
    assert [p.name for p in loaded.passes] == [p.name for p in live.passes]
    assert loaded.observations.n_lasers == obs.n_lasers and len(loaded.observations.views) == len(obs.views)


def test_report_and_uncertainty_recomputed_from_the_file(free):
    obs, _, live, loaded = free
    # the covariance and the kinds' noise computed again from the stored problem
    np.testing.assert_allclose(np.asarray(loaded.cov.glob), np.asarray(live.cov.glob), rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(np.asarray(loaded.cov.blocks), np.asarray(live.cov.blocks), rtol=1e-9, atol=1e-15)
    _close(_json(sj.report(loaded)), _json(sj.report(live, obs)))
    # the file's own sections, as written, are what the loaded result reports
    doc = calibration_to_json(sj.to_calibration(loaded))
    live_doc = _json(sj.report(live, obs))
    _close(_json(doc["uncertainty"]), live_doc["uncertainty"])
    _close(_json(doc["residuals"]), live_doc["residuals"])
    a, b = (
        kind_noise(live.params, live.packed, live.masks, live.loss, live.scale),
        kind_noise(loaded.params, loaded.packed, loaded.masks, loaded.loss, loaded.scale),
    )
    np.testing.assert_allclose(a.sigma, b.sigma, rtol=1e-9)


def test_the_bound_at_the_solution_from_the_file(free):
    obs, _, live, loaded = free
    sig = [live.kind_sigma[k] for k in ("dot", "spot", "rim", "chess")]
    a = sj.cramer_rao(sj.to_calibration(live, obs), obs, sig, packed=live.packed)
    b = sj.cramer_rao(sj.to_calibration(loaded), loaded.observations, sig, packed=loaded.packed)
    np.testing.assert_allclose(b["position_std_mm"], a["position_std_mm"], rtol=1e-9)
    np.testing.assert_allclose(b["direction_std_rad"], a["direction_std_rad"], rtol=1e-9)


@pytest.mark.slow
def test_sensitivity_from_the_file(free):
    _, _, live, loaded = free
    a, b = sj.sensitivity(live), sj.sensitivity(loaded)
    for x, y in zip(a, b, strict=True):
        if isinstance(x, np.ndarray) or hasattr(x, "shape"):
            np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=1e-9, atol=1e-12)


@pytest.fixture(scope="module")
def rigid(tmp_path_factory, request):
    """A rigid box calibration read back with the covariance path switched off: the file's
    covariance is read, the box model is not rebuilt (nor any covariance computed again)."""
    import slcvjax.calibration.stored as stored

    def refused(*args, **kwargs):
        raise AssertionError("load_result computed a covariance for a rigid box calibration")

    mp = pytest.MonkeyPatch()
    mp.setattr(stored, "covariance_and_noise", refused)
    request.addfinalizer(mp.undo)
    return _calibrated(tmp_path_factory.mktemp("rigid"), rigid=True)


@pytest.mark.slow
def test_a_rigid_box_calibration_reads_back(rigid):
    obs, _, live, loaded = rigid
    assert loaded.box is not None
    _close(_json(sj.report(loaded)), _json(sj.report(live, obs)))


@pytest.mark.slow
def test_a_rigid_box_calibrations_std_round_trips(rigid):
    """The stored covariance is the live one, bit for bit, and so are the std reported from it
    (camera, mirror, lasers at their working range, the boards in the box)."""
    obs, _, live, loaded = rigid
    for name in ("glob", "blocks", "sigma", "dof"):
        np.testing.assert_array_equal(np.asarray(getattr(loaded.cov, name)), np.asarray(getattr(live.cov, name)))
    assert list(loaded.kind_sigma) == list(live.kind_sigma)
    np.testing.assert_array_equal(list(loaded.kind_sigma.values()), list(live.kind_sigma.values()))  # NaN too
    a, b = _json(sj.report(live, obs))["uncertainty"], _json(sj.report(loaded))["uncertainty"]
    for key in ("camera_std", "mirror_std", "lasers", "rigid_box"):
        assert b[key] == a[key], key


def test_a_file_without_its_problem_is_refused_by_name(free, tmp_path):
    obs, _, live, _ = free
    doc = calibration_to_json(sj.to_calibration(live, obs))
    del doc["problem"]
    path = tmp_path / "old.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(FormatError, match=r"old\.json: problem: missing"):
        sj.load_result(path)
    doc = calibration_to_json(sj.to_calibration(live, obs))
    doc["problem"]["solution"]["leaves"] = doc["problem"]["solution"]["leaves"][:-1]
    path.write_text(json.dumps(doc))
    with pytest.raises(FormatError, match=r"problem\.solution\.leaves"):
        sj.load_result(path)
