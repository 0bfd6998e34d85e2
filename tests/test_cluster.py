"""Studies on a Ray cluster (slcvjax.experiments.cluster): the local numbers bit for bit, a killed
worker's chunk run again, an interrupted study resumed, another study's folder refused.

The cluster is a local Ray instance this module starts (two CPUs); the studies are small (one
noise level, three trials in chunks of two, test_sweep's scene: its compilations are shared)."""

import json
import os
import sys
import warnings

import pytest

from slcvjax.cli import main
from slcvjax.experiments import cluster as cl
from slcvjax.experiments.sweep import run_sweep

SWEEP = dict(noise=(0.5,), trials=3, seed=3, n_lasers=4, n_views=5)
SWEEP_ARGS = ["--noise", "0.5", "--trials", "3", "--seed", "3", "--lasers", "4", "--views", "5", "--chunk", "2"]


def _numbers(doc: dict) -> dict:
    """What a sweep's document computes (its timings, devices and cluster aside)."""
    detail = [{k: d[k] for k in ("noise", "trial", "seed", "converged")} for d in doc["trials_detail"]]
    return {"methods": doc["methods"], "converged": doc["converged"], "detail": detail}


@pytest.fixture(scope="module")
def local():
    """The sweep in this process, no folder: the reference."""
    return _numbers(run_sweep("paper", **SWEEP, chunk=2))


@pytest.fixture(scope="module")
def ray_cluster(tmp_path_factory):
    """A local Ray instance of two CPUs; its workers inherit the crash hook's folder."""
    ray = pytest.importorskip("ray", reason="Ray is not installed (pip install 'slcvjax[cluster]')")
    crash_dir = tmp_path_factory.mktemp("crash")
    os.environ[cl.CRASH_ENV] = str(crash_dir)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level="ERROR")
    yield crash_dir
    ray.shutdown()
    os.environ.pop(cl.CRASH_ENV, None)


def _chunk_files(folder) -> list[str]:
    return sorted(p.name for p in (folder / cl.CHUNKS).iterdir())


def test_the_cluster_gives_the_local_numbers_bit_for_bit_and_keeps_each_chunk(local, ray_cluster, tmp_path):
    ran = []
    doc = run_sweep("paper", **SWEEP, chunk=2, cluster="auto", out_dir=tmp_path, on_chunk=lambda k, n: ran.append(k))
    assert _numbers(doc) == local  # floats compared with ==: the same bits
    assert sorted(ran) == [0, 1] and _chunk_files(tmp_path) == ["chunk-000000.json", "chunk-000001.json"]
    manifest = json.loads((tmp_path / cl.MANIFEST).read_text())
    assert manifest["study"] == "sweep" and manifest["chunk_size"] == 2 and manifest["n_items"] == 3
    # a second run of the same settings finds every chunk and calibrates nothing
    again = run_sweep("paper", **SWEEP, cluster="auto", out_dir=tmp_path, on_chunk=lambda k, n: ran.append(k))
    assert _numbers(again) == local and sorted(ran) == [0, 1]


def test_a_worker_killed_under_a_chunk_has_the_chunk_run_again(local, ray_cluster, tmp_path):
    armed = ray_cluster / "crash-chunk-1"
    armed.touch()  # chunk 1's first attempt kills its worker process
    ran = []
    doc = run_sweep("paper", **SWEEP, chunk=2, cluster="auto", out_dir=tmp_path, on_chunk=lambda k, n: ran.append(k))
    assert not armed.exists()  # the worker died under it
    assert sorted(ran) == [0, 1]  # each chunk written once
    assert _numbers(doc) == local  # nothing lost, nothing counted twice


def test_an_interrupted_study_resumes_to_the_uninterrupted_output(local, ray_cluster, tmp_path):
    def stop(k, done):
        raise KeyboardInterrupt  # Ctrl-C once the first chunk is written

    with pytest.raises(KeyboardInterrupt):
        run_sweep("paper", **SWEEP, chunk=2, cluster="auto", out_dir=tmp_path, on_chunk=stop)
    assert len(_chunk_files(tmp_path)) == 1
    # resumed in this process (the same folder serves both paths): only the other chunk runs
    ran = []
    doc = run_sweep("paper", **SWEEP, resume="require", out_dir=tmp_path, on_chunk=lambda k, n: ran.append((k, n)))
    assert len(ran) == 1 and ran[0][1] == 3
    assert _numbers(doc) == local


def test_a_folder_of_other_settings_is_refused_and_restart_discards_it(local, tmp_path, capsys):
    run_sweep("paper", **SWEEP, chunk=2, out_dir=tmp_path, on_chunk=lambda k, n: None)
    out = str(tmp_path)
    assert main(["sweep", *SWEEP_ARGS[:2], "--trials", "4", *SWEEP_ARGS[4:], "--out", out]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "other settings" in err and "trials 3 there, 4 now" in err
    assert "--restart" in err and "Traceback" not in err
    assert main(["sweep", *SWEEP_ARGS[:-2], "--chunk", "1", "--out", out]) == 2
    assert "chunks of 2 trials" in capsys.readouterr().err
    assert _chunk_files(tmp_path) == ["chunk-000000.json", "chunk-000001.json"]  # untouched
    with pytest.raises(cl.StudyError, match="holds no study"):
        run_sweep("paper", **SWEEP, resume="require", out_dir=tmp_path / "empty")
    # --restart: the old chunks go, the new study starts afresh (refused before any work otherwise)
    cl.prepare_folder(tmp_path, "sweep", {"other": 1}, 3, 1, "restart")
    assert not list((tmp_path / cl.CHUNKS).iterdir())


def test_cluster_without_ray_is_one_line_naming_the_extra(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    assert main(["sweep", *SWEEP_ARGS, "--cluster", "local:2", "--out", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "pip install 'slcvjax[cluster]'" in err
    assert main(["design", "--confirm", "2", "--cluster", "local:2", "--out", str(tmp_path / "d")]) == 2
    assert "pip install 'slcvjax[cluster]'" in capsys.readouterr().err
    assert main(["sweep", "--cluster", "elsewhere", "--out", str(tmp_path / "s")]) == 2
    assert "auto, local:N (N >= 1) or ray://HOST:PORT" in capsys.readouterr().err
    assert not (tmp_path / "s").exists() and not (tmp_path / "d").exists()


def test_parse_cluster_and_settings_hash():
    assert cl.parse_cluster("local:3") == cl.ClusterSpec("local", workers=3)
    assert cl.parse_cluster("ray://head:10001") == cl.ClusterSpec("address", address="ray://head:10001")
    for bad in ("local:0", "local:x", "ray://head", "head:10001"):
        with pytest.raises(cl.StudyError, match="--cluster"):
            cl.parse_cluster(bad)
    import numpy as np

    a = {"x": np.arange(3.0), "n": 2}
    assert cl.settings_hash(a) == cl.settings_hash({"n": 2, "x": np.arange(3.0)})
    assert cl.settings_hash(a) != cl.settings_hash({"x": np.nextafter(np.arange(3.0), 9.0), "n": 2})
    assert cl.chunk_bounds(5, 2) == [(0, 2), (2, 4), (4, 5)]


def test_a_design_confirmation_on_the_cluster_equals_the_local_one(ray_cluster, tmp_path):
    from slcvjax.experiments.design import Plan, confirm
    from slcvjax.observations.simulate import box_scene, paper_rig, paper_views

    # tests/test_laser_design.py's plan: its calibrations' compilations are shared
    rig, views = paper_rig(4), paper_views(6)
    plan = Plan.from_scene(box_scene(rig, views), views, noise=0.5)
    here = confirm(plan, 2, seed=4, chunk=1)
    there = confirm(plan, 2, seed=4, chunk=1, cluster="auto", out_dir=tmp_path)
    assert there == here and here["trials"] == 2
    assert len(_chunk_files(tmp_path)) == 2


def test_a_task_error_on_the_cluster_is_raised_as_the_task_raised_it(ray_cluster, tmp_path):
    import operator

    # operator.getitem({}, items): the task raises TypeError in the worker (a builtin: workers import it)
    with pytest.raises(TypeError, match="unhashable") as info:
        cl.run_chunks(
            operator.getitem, {}, [1, 2, 3], study="t", settings={}, chunk_size=2, folder=tmp_path, cluster="auto"
        )
    assert type(info.value) is TypeError  # not Ray's wrapper, whose text carries the worker's traceback
    assert not list((tmp_path / cl.CHUNKS).iterdir())
