"""Several calibrations at once: in lockstep (``calibrate_many(batch="vmap")``) with the trial axis
sharded over devices, and two at a time in threads (``batch="loop", workers=2``).

The sharded run needs several devices: a subprocess gets two CPU devices from
``XLA_FLAGS=--xla_force_host_platform_device_count=2`` and calibrates three trials (padded
to four, two per device); this process calibrates the same trials one after another
with :func:`calibrate`, and the two must agree to round-off.
"""

import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest

from slcvjax.calibration.calibrate import calibrate, calibrate_many, resolve_batch
from slcvjax.observations.simulate import make_scene, simulate

SCENE = dict(n_lasers=4, n_views=5)  # test_calibrate's sizes: the loop's compilation is shared
SEEDS = (0, 1, 2)

SCRIPT = """
import json
import jax
import numpy as np
import slcvjax.calibration.calibrate as C
from slcvjax.observations.simulate import make_scene, simulate

shards = []
solve = C._solve_batched


def recording(*args, **kwargs):
    out = solve(*args, **kwargs)
    shards.append(len(out.cost.sharding.device_set))
    return out


C._solve_batched = recording
scene = make_scene("paper", **SCENE)
res = C.calibrate_many([simulate(scene, noise=0.5, seed=s)[0] for s in SEEDS], batch="vmap")
print(json.dumps({
    "devices": len(jax.devices()),
    "shards": shards,
    "points": [np.asarray(r.rig.lasers.points).tolist() for r in res],
    "directions": [np.asarray(r.rig.lasers.directions).tolist() for r in res],
    "passes": [[[p.name, p.steps] for p in r.passes] for r in res],
}))
"""


def test_batch_choice():
    # lockstep trials under vmap pay on a CPU (one core runs them in turn) and win on an accelerator
    assert resolve_batch("auto") == ("loop" if jax.default_backend() == "cpu" else "vmap")
    assert resolve_batch("vmap") == "vmap"
    with pytest.raises(ValueError, match="batch"):
        calibrate_many([], batch="pmap")
    with pytest.raises(ValueError, match="workers"):
        calibrate_many([], batch="loop", workers=0)


@pytest.mark.slow
def test_sharded_lockstep_calibrations_equal_one_after_another():
    flags = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"
    env = dict(os.environ, XLA_FLAGS=flags.strip(), JAX_PLATFORMS="cpu")
    code = f"SCENE = {SCENE!r}\nSEEDS = {SEEDS!r}\n" + SCRIPT
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["devices"] == 2
    # every pass ran as one vmap-ped solve spread over both devices
    assert len(out["shards"]) >= 4 and set(out["shards"]) == {2}
    scene = make_scene("paper", **SCENE)
    observations = [simulate(scene, noise=0.5, seed=s)[0] for s in SEEDS]
    threaded = calibrate_many(observations, batch="loop", workers=2)
    for i, obs in enumerate(observations):
        ref = calibrate(obs)
        # two at a time in threads: the same calibrations
        assert [p.steps for p in threaded[i].passes] == [p.steps for p in ref.passes]
        np.testing.assert_allclose(
            np.asarray(threaded[i].rig.lasers.points), np.asarray(ref.rig.lasers.points), atol=1e-7
        )
        assert out["passes"][i] == [[p.name, p.steps] for p in ref.passes]
        np.testing.assert_allclose(out["points"][i], np.asarray(ref.rig.lasers.points), atol=1e-7)
        np.testing.assert_allclose(out["directions"][i], np.asarray(ref.rig.lasers.directions), atol=1e-10)


def test_calibrate_many_rejects_an_unknown_keyword():
    obs, _ = simulate(make_scene("paper", n_lasers=3, n_views=3), noise=0.3, seed=0)
    with pytest.raises(TypeError, match="lozz"):
        calibrate_many([obs], lozz="cauchy")
