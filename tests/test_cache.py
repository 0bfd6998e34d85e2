"""The persistent compilation cache: on by default, off, a chosen folder, unwritable, shared."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

# a fresh process: import slcvjax, compile a small function, report the cache folder and
# how many compilations were read from the cache
PROBE = """
import json, jax, jax.numpy as jnp
hits = []
jax.monitoring.register_event_listener(lambda e, **k: hits.append(e) if e.endswith("cache_hits") else None)
import slcvjax
f = jax.jit(lambda x: jnp.sin(x) * {k} + jnp.cos(x))
f(jnp.arange(7.0)).block_until_ready()
d = slcvjax.compilation_cache_dir()
print(json.dumps({{"dir": None if d is None else str(d), "hits": len(hits)}}))
"""


def run_probe(env_extra: dict, k: int = 3) -> tuple[dict, str]:
    env = {key: v for key, v in os.environ.items() if not key.startswith(("SLCVJAX_", "JAX_COMPILATION"))}
    env.update(env_extra)
    out = subprocess.run(
        [sys.executable, "-c", PROBE.format(k=k)], env=env, capture_output=True, text=True, timeout=300, check=True
    )
    return json.loads(out.stdout.strip().splitlines()[-1]), out.stderr


def entries(folder: Path) -> list[Path]:
    return [p for p in folder.glob("*") if p.is_file() and not p.name.startswith(".")] if folder.exists() else []


@pytest.mark.slow
def test_on_by_default_in_the_user_cache_folder(tmp_path):
    res, _ = run_probe({"XDG_CACHE_HOME": str(tmp_path), "HOME": str(tmp_path)})
    assert res["dir"] == str(tmp_path / "slcvjax")
    assert entries(tmp_path / "slcvjax"), "nothing was written to the default cache folder"
    again, _ = run_probe({"XDG_CACHE_HOME": str(tmp_path), "HOME": str(tmp_path)})
    assert again["hits"] >= 1  # the second process loads the compilation


def test_off(tmp_path):
    res, _ = run_probe({"SLCVJAX_CACHE_DIR": "off", "XDG_CACHE_HOME": str(tmp_path), "HOME": str(tmp_path)})
    assert res["dir"] is None and res["hits"] == 0
    assert not entries(tmp_path / "slcvjax")


def test_chosen_folder(tmp_path):
    folder = tmp_path / "chosen" / "cache"
    res, _ = run_probe({"SLCVJAX_CACHE_DIR": str(folder), "XDG_CACHE_HOME": str(tmp_path / "xdg")})
    assert res["dir"] == str(folder) and entries(folder)
    assert not entries(tmp_path / "xdg" / "slcvjax")


def test_unwritable_folder_warns_once_and_runs_uncached(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    res, err = run_probe({"SLCVJAX_CACHE_DIR": str(blocker / "cache")})
    assert res["dir"] is None and res["hits"] == 0
    lines = [ln for ln in err.splitlines() if "compilation cache folder" in ln]
    assert len(lines) == 1 and str(blocker / "cache") in lines[0]


@pytest.mark.slow
def test_two_processes_share_a_folder_at_once(tmp_path):
    folder = tmp_path / "shared"
    env = {key: v for key, v in os.environ.items() if not key.startswith(("SLCVJAX_", "JAX_COMPILATION"))}
    env["SLCVJAX_CACHE_DIR"] = str(folder)
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", PROBE.format(k=5)],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for _ in range(2)
    ]
    outs = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), [o[1][-2000:] for o in outs]
    assert all(json.loads(o[0].strip().splitlines()[-1])["dir"] == str(folder) for o in outs)
    res, err = run_probe({"SLCVJAX_CACHE_DIR": str(folder)}, k=5)
    assert res["hits"] >= 1 and "rror" not in err


# a fresh process: a PersistentJit function of a pytree (an equinox module with a static
# field, arrays of two dtypes), called twice with the same signature and once with another
TRACED = """
import json, jax, jax.numpy as jnp, numpy as np
import slcvjax
from slcvjax.support import persist as _persist
from slcvjax.geometry.pose import Pose

def f(pose, x, n):
    return {"y": pose.apply(x) * n.astype(float), "s": jnp.sum(x)}

g = _persist.PersistentJit(f, "test_probe")
pose = Pose(jnp.eye(3), jnp.array([1.0, 2.0, 3.0]))
a = g(pose, np.ones(3), np.array(2))
b = g(pose, np.ones(3) * 2, np.array(3))
c = g(pose, np.ones((2, 3)), np.array(2))
print(json.dumps({"a": np.asarray(a["y"]).tolist(), "b": float(b["s"]), "c": np.asarray(c["y"]).shape,
                  "stats": _persist.STATS}))
"""


@pytest.mark.slow
def test_traced_programs_persist_across_processes(tmp_path):
    env = {key: v for key, v in os.environ.items() if not key.startswith(("SLCVJAX_", "JAX_COMPILATION"))}
    env["SLCVJAX_CACHE_DIR"] = str(tmp_path)

    def run():
        out = subprocess.run(
            [sys.executable, "-c", TRACED], env=env, capture_output=True, text=True, timeout=300, check=True
        )
        return json.loads(out.stdout.strip().splitlines()[-1])

    first, second = run(), run()
    assert first["stats"] == {"exported": 2, "loaded": 0}  # two signatures
    assert second["stats"] == {"exported": 0, "loaded": 2}
    assert first["a"] == second["a"] == [[4.0, 6.0, 8.0]][0] and first["b"] == second["b"] == 6.0
    assert second["c"] == [2, 3]
    assert len(list((tmp_path / "traces").glob("test_probe-*.jaxexport"))) == 2
