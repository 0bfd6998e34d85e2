"""Several calibrations at once: in lockstep (``calibrate_many(batch="vmap")``) with the trial axis
sharded over devices, and two at a time in threads (``batch="loop", workers=2``).

The test processes see two CPU devices (``JAX_NUM_CPU_DEVICES=2``, set in ``tests/conftest.py``):
three trials are calibrated in lockstep (padded to four, two per device) and one after another
with :func:`calibrate`, and the two must agree to round-off.
"""

import jax
import numpy as np
import pytest

import slcvjax.calibration.executors as C
from slcvjax.calibration.calibrate import calibrate, calibrate_many
from slcvjax.calibration.executors import resolve_batch
from slcvjax.observations.simulate import make_scene, simulate

SCENE = dict(n_lasers=4, n_views=5)  # test_calibrate's sizes: the loop's compilation is shared
SEEDS = (0, 1, 2)


def test_batch_choice():
    # lockstep trials under vmap pay on a CPU (one core runs them in turn) and win on an accelerator
    assert resolve_batch("auto") == ("loop" if jax.default_backend() == "cpu" else "vmap")
    assert resolve_batch("vmap") == "vmap"
    with pytest.raises(ValueError, match="batch"):
        calibrate_many([], batch="pmap")
    with pytest.raises(ValueError, match="workers"):
        calibrate_many([], batch="loop", workers=0)


@pytest.mark.slow
def test_sharded_lockstep_calibrations_equal_one_after_another(monkeypatch):
    assert len(jax.devices()) == 2, "the suite runs with two CPU devices (JAX_NUM_CPU_DEVICES=2, tests/conftest.py)"
    shards, solve = [], C.solve_batched

    def recording(*args, **kwargs):
        out = solve(*args, **kwargs)
        shards.append(len(out.cost.sharding.device_set))
        return out

    monkeypatch.setattr(C, "solve_batched", recording)
    scene = make_scene("paper", **SCENE)
    observations = [simulate(scene, noise=0.5, seed=s)[0] for s in SEEDS]
    lockstep = calibrate_many(observations, batch="vmap")
    # every pass ran as one vmap-ped solve spread over both devices
    assert len(shards) >= 4 and set(shards) == {2}
    threaded = calibrate_many(observations, batch="loop", workers=2)
    for i, obs in enumerate(observations):
        ref = calibrate(obs)
        for res in (lockstep[i], threaded[i]):  # in lockstep, and two at a time in threads
            assert [(p.name, p.steps) for p in res.passes] == [(p.name, p.steps) for p in ref.passes]
            np.testing.assert_allclose(np.asarray(res.rig.lasers.points), np.asarray(ref.rig.lasers.points), atol=1e-7)
        np.testing.assert_allclose(
            np.asarray(lockstep[i].rig.lasers.directions), np.asarray(ref.rig.lasers.directions), atol=1e-10
        )


def test_calibrate_many_rejects_an_unknown_keyword():
    obs, _ = simulate(make_scene("paper", n_lasers=3, n_views=3), noise=0.3, seed=0)
    with pytest.raises(TypeError, match="lozz"):
        calibrate_many([obs], lozz="cauchy")
