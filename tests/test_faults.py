"""Faults outside the data (issue 61, item 3): a damaged cache, two processes at once, an
output that cannot be written, bad images, a calibration killed part way."""

import json
import os
import signal
import subprocess
import sys
import time
import warnings
import zlib
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax._src import compilation_cache as jax_cc

from slcvjax.cli import main
from slcvjax.observations.formats import temp_name_pattern
from slcvjax.support import cache, persist

# --------------------------------------------------------------------------- a damaged cache


@pytest.fixture
def own_cache(tmp_path, monkeypatch):
    """This process's compilation cache moved to a fresh folder for the test, then put back."""
    folder = tmp_path / "cache"

    def switch():
        jax_cc.reset_cache()
        jax.clear_caches()
        cache.forget_damaged()
        return cache.enable()

    monkeypatch.setenv(cache.ENV, str(folder))
    assert switch() == folder
    yield folder
    monkeypatch.undo()
    switch()


def _fn(x):
    return {"y": jnp.sin(x) * 3.0 + jnp.cos(x) ** 2, "s": jnp.sum(jnp.tanh(x))}


def _run_both(x):
    """A jitted function (JAX's compiled entry) and a PersistentJit one (a traced entry and a compiled one)."""
    jax.clear_caches()  # nothing from memory: the programs come from the folder or are compiled
    a = jax.jit(lambda v: _fn(v)["y"] * 2.0)(x)
    b = persist.PersistentJit(_fn, "faults_probe")(x)
    return np.asarray(a), np.asarray(b["y"]), np.asarray(b["s"])


def _garble(path: Path, how: str) -> None:
    data = bytearray(path.read_bytes())
    if how == "truncated":
        data = data[: len(data) // 2]
    elif how == "empty":
        data = bytearray()
    else:  # one byte flipped two thirds in
        data[2 * len(data) // 3] ^= 0x10
    path.write_bytes(bytes(data))


def _compiled(folder: Path) -> list[Path]:
    return sorted(folder.glob("*-cache"))


def _traced(folder: Path) -> list[Path]:
    return sorted((folder / "traces").glob("*.jaxexport"))


@pytest.mark.parametrize("how", ["truncated", "garbled", "empty"])
def test_a_damaged_cache_entry_is_dropped_and_compiled_again_with_one_warning(own_cache, how):
    x = np.linspace(-2.0, 2.0, 11)
    first = _run_both(x)
    compiled, traced = _compiled(own_cache), _traced(own_cache)
    assert len(compiled) >= 2 and len(traced) == 1
    before = {p.name: p.read_bytes() for p in compiled + traced}
    for p in compiled + traced:
        _garble(p, how)

    with pytest.warns(RuntimeWarning, match="compilation cache entry .* is damaged") as caught:
        again = _run_both(x)
    ours = [w for w in caught if "is damaged" in str(w.message)]
    assert len(ours) == 1, [str(w.message) for w in caught]
    assert len(cache.dropped_damaged()) == len(compiled) + len(traced)
    for a, b in zip(first, again, strict=True):
        assert a.tobytes() == b.tobytes()  # the same program: the same bits

    # the damaged entries were replaced by good ones: a third process-like pass loads them quietly
    after = {p.name: p.read_bytes() for p in _compiled(own_cache) + _traced(own_cache)}
    assert set(after) == set(before)
    for name, data in after.items():
        if name.endswith("-cache"):
            zlib.decompress(data)  # JAX's entries are zlib streams: it decompresses whole
        else:
            assert persist.unframe(data)
    cache.forget_damaged()
    loaded = persist.STATS["loaded"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        third = _run_both(x)
    assert persist.STATS["loaded"] == loaded + 1 and not cache.dropped_damaged()
    for a, b in zip(first, third, strict=True):
        assert a.tobytes() == b.tobytes()


def test_a_traced_entry_with_a_changed_byte_is_not_run(own_cache):
    """A flipped byte inside the serialized program: before the digest it deserialized and
    failed only at the call (or ran with the change); now it is dropped and traced again."""
    x = np.arange(5.0)
    first = _run_both(x)
    (entry,) = _traced(own_cache)
    data = bytearray(entry.read_bytes())
    payload = persist.unframe(bytes(data))
    start = len(data) - len(payload)
    data[start + len(payload) // 3] ^= 0x01
    entry.write_bytes(bytes(data))
    exported = persist.STATS["exported"]
    with pytest.warns(RuntimeWarning, match=r"traces/faults_probe-.*is damaged.*checksum"):
        again = _run_both(x)
    assert persist.STATS["exported"] == exported + 1
    for a, b in zip(first, again, strict=True):
        assert a.tobytes() == b.tobytes()


# --------------------------------------------------------------------------- outputs that cannot be written


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    """A small simulated scene (3 lasers, 5 views): observations.json and truth.json."""
    out = tmp_path_factory.mktemp("scene")
    assert (
        main(["simulate", "--preset", "paper", "--lasers", "3", "--views", "5", "--noise", "0.3", "--out", str(out)])
        == 0
    )
    return out


def _listing(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


def _one_error_line(err: str, command: str, path: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith(f"slcvjax {command}: error: {path}"), lines[0]
    assert "Traceback" not in err
    return lines[0]


def _unwritable_cases(scene: Path, tmp: Path) -> list[tuple[list[str], str, str]]:
    """(argv, the path the line names, what it says) of each way an output cannot be written."""
    blocker = tmp / "a_file"  # a file where a folder should be: root may write anywhere else
    blocker.write_text("in the way\n")
    folder = tmp / "taken.json"
    folder.mkdir()
    obs, truth = str(scene / "observations.json"), str(scene / "truth.json")
    return [
        (["calibrate", obs, "--out", f"{blocker}/cal.json"], f"{blocker}/cal.json", "is a file, not a directory"),
        (["calibrate", obs, "--out", str(folder)], str(folder), "it is a directory"),
        (["calibrate", obs, "--out", str(scene)], f"{scene}/observations.json", "would overwrite the input"),
        (
            ["calibrate", obs, "--out", str(tmp / "c.json"), "--export-opencv", f"{blocker}/cam.yaml"],
            f"{blocker}/cam.yaml",
            "is a file, not a directory",
        ),
        (["simulate", "--out", f"{blocker}/sim"], f"{blocker}/sim/observations.json", "is a file"),
        (["detect", str(scene), "--out", str(folder)], str(folder), "it is a directory"),
        (["measure", truth, obs, "--pixel-sigma", "0.3", "--out", truth], truth, "would overwrite the input"),
        (["measure", truth, obs, "--pixel-sigma", "0.3", "--out", f"{blocker}/p.json"], f"{blocker}/p.json", "a file"),
    ]


def test_an_output_that_cannot_be_written_is_one_line_and_exit_2(scene_dir, tmp_path, capsys):
    cases = _unwritable_cases(scene_dir, tmp_path)
    inputs = {p.name: p.read_bytes() for p in scene_dir.iterdir()}
    before_tmp, before_scene = _listing(tmp_path), _listing(scene_dir)
    for argv, path, says in cases:
        capsys.readouterr()
        assert main(argv) == 2, argv
        line = _one_error_line(capsys.readouterr().err, argv[0], path)
        assert says in line, line
        # nothing written anywhere: no output, no temporary file, the inputs untouched
        assert _listing(tmp_path) == before_tmp and _listing(scene_dir) == before_scene, argv
        assert {p.name: p.read_bytes() for p in scene_dir.iterdir()} == inputs


@pytest.mark.parametrize("how", ["removed", "replaced by a file"])
def test_an_output_folder_that_vanishes_during_the_run_is_one_line_and_exit_2(tmp_path, capsys, monkeypatch, how):
    """The folder is there when the command starts and gone when it writes: it is not made
    again (an unmounted drive's folder would be made on the disk below it)."""
    import slcvjax.cli.simulate as command

    out = tmp_path / "run" / "out"
    write = command.write_observations

    def vanish_then_write(*args, **kwargs):  # the command has checked its output by now
        assert out.is_dir()
        out.rmdir()
        if how != "removed":
            out.write_text("a file now\n")
        return write(*args, **kwargs)

    monkeypatch.setattr(command, "write_observations", vanish_then_write)
    argv = ["simulate", "--preset", "paper", "--lasers", "3", "--views", "2", "--out", str(out)]
    assert main(argv) == 2
    line = _one_error_line(capsys.readouterr().err, "simulate", str(out / "observations.json"))
    assert "vanished" in line
    assert _listing(tmp_path) == ({"run"} if how == "removed" else {"run", "run/out"})


# --------------------------------------------------------------------------- killed part way

# a fresh process writes a calibration and is stopped by a signal in the middle of the write:
# after the temporary file is filled, before it is renamed onto the target; SIGINT and SIGTERM
# reach it as they reach a command (``slcvjax_cli.stop_on_signals``), SIGKILL as it is
KILLED_WRITE = """
import contextlib, os, signal, sys
from slcvjax.cli import stop_on_signals
from slcvjax.observations import formats
cal = formats.read_calibration(sys.argv[1])
sig = getattr(signal, sys.argv[3])
formats.os.fsync = lambda fd: os.kill(os.getpid(), sig)
with (contextlib.nullcontext() if sig == signal.SIGKILL else stop_on_signals("test")):
    formats.write_calibration(sys.argv[2], cal)
"""


def _env() -> dict:
    return dict(os.environ)  # the tests' compilation cache (conftest) included


def _temps(folder: Path, target: str) -> list[Path]:
    return sorted(folder.glob(temp_name_pattern(folder / target)))


def test_a_write_stopped_by_a_signal_in_the_middle_leaves_no_output(scene_dir, tmp_path):
    """A signal between filling the temporary file and renaming it: the target stays absent (or
    its old whole self).  SIGINT and SIGTERM delete the temporary and exit 128 + the signal;
    SIGKILL leaves it, named as one, beside the target."""
    runs = {}
    for sig, old in [("SIGKILL", None), ("SIGKILL", b"old\n"), ("SIGTERM", None), ("SIGINT", b"old\n")]:
        out = tmp_path / f"{sig}-{old is not None}"
        out.mkdir()
        if old is not None:
            (out / "cal.json").write_bytes(old)
        argv = [sys.executable, "-c", KILLED_WRITE, str(scene_dir / "truth.json"), str(out / "cal.json"), sig]
        proc = subprocess.Popen(argv, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        runs[out] = (sig, old, proc)  # all at once: each spends its time importing
    for out, (sig, old, proc) in runs.items():
        _, err = proc.communicate(timeout=120)
        target = out / "cal.json"
        assert (target.read_bytes() if target.exists() else None) == old, (sig, err[-2000:])
        temps = _temps(out, "cal.json")
        if sig == "SIGKILL":
            assert proc.returncode == -signal.SIGKILL, err[-2000:]
            (temp,) = temps
            assert temp.name.startswith(".cal.json.") and temp.name.endswith(".tmp")
            assert json.loads(temp.read_text())["format"] == "slcv-calibration/1"  # filled, not renamed
            temp.unlink()
        else:
            assert proc.returncode == 128 + getattr(signal, sig), err[-2000:]
            assert temps == [] and "no output was left half written" in err, err[-2000:]
        assert sorted(p.name for p in out.iterdir()) == ([] if old is None else ["cal.json"])


def test_a_write_interrupted_in_the_middle_leaves_nothing(scene_dir, tmp_path, monkeypatch):
    """An exception (KeyboardInterrupt: Ctrl-C in a library caller) between filling the temporary
    file and renaming it: the write deletes its temporary; the target is absent or its old self."""
    from slcvjax.observations import formats

    cal = formats.read_calibration(scene_dir / "truth.json")

    def interrupt(fd):
        raise KeyboardInterrupt

    monkeypatch.setattr(formats.os, "fsync", interrupt)
    target = tmp_path / "cal.json"
    with pytest.raises(KeyboardInterrupt):
        formats.write_calibration(target, cal)
    assert list(tmp_path.iterdir()) == []
    target.write_text("old\n")
    with pytest.raises(KeyboardInterrupt):
        formats.write_calibration(target, cal)
    assert [p.name for p in tmp_path.iterdir()] == ["cal.json"] and target.read_text() == "old\n"


@pytest.mark.slow
def test_a_calibration_killed_at_any_moment_leaves_no_half_written_output(scene_dir, tmp_path):
    """`slcvjax calibrate` killed (SIGKILL, SIGTERM) at a few moments: from the start, during the
    solve, as it reports, as it writes.  The output is absent or a whole calibration equal to an
    uninterrupted run's; only SIGKILL may leave a temporary file, named as one."""
    from slcvjax.observations.formats import read_calibration

    obs = str(scene_dir / "observations.json")
    cmd = [sys.executable, "-m", "slcvjax.cli", "calibrate", obs, "--out"]
    whole = tmp_path / "whole" / "cal.json"
    # once to compile (where the tests' cache lacks it), once to time a run as the killed ones go
    subprocess.run(cmd + [str(whole)], env=_env(), capture_output=True, timeout=600, check=True)
    t0 = time.perf_counter()
    subprocess.run(cmd + [str(whole)], env=_env(), capture_output=True, timeout=600, check=True)
    seconds = time.perf_counter() - t0
    reference = json.loads(whole.read_text())

    moments = [("SIGKILL", 0.15 * seconds), ("SIGTERM", 0.3 * seconds), ("SIGKILL", 0.6 * seconds)]
    moments += [("SIGKILL", 0.9 * seconds), ("SIGTERM", 0.8 * seconds)]
    moments += [("SIGKILL", "report"), ("SIGTERM", "report")]  # as it prints its report: just before the write
    outcomes = []
    for k, (sig, when) in enumerate(moments):
        out = tmp_path / f"run{k}"
        target = out / "cal.json"
        proc = subprocess.Popen(
            cmd + [str(target)], env=_env(), stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
        )
        if when == "report":
            for line in proc.stdout:
                if line.startswith("=="):  # the report's first line: the solve has finished
                    break
        else:
            time.sleep(when)
        proc.send_signal(getattr(signal, sig))
        proc.communicate(timeout=600)
        if target.exists():
            doc = json.loads(target.read_text())  # whole JSON
            read_calibration(target)  # a valid calibration
            assert doc["lasers"] == reference["lasers"] and doc["mirror"] == reference["mirror"]
        temps = _temps(out, "cal.json") if out.exists() else []
        if sig == "SIGTERM":
            assert temps == [], (k, temps)
        else:
            assert all(t.name.startswith(".cal.json.") and t.name.endswith(".tmp") for t in temps)
        left = {p.name for p in out.iterdir()} - {t.name for t in temps} if out.exists() else set()
        assert left <= {"cal.json"}, left
        outcomes.append((sig, when, proc.returncode, target.exists()))
    # the early ones stopped it before it wrote (else the test did not test them); SIGTERM stops it
    # (143) once main runs, or by the signal's default while Python still imports; one that came
    # after it had finished (0) is the only way an output follows a SIGTERM
    assert not outcomes[0][3] and not outcomes[1][3], outcomes
    for sig, _, rc, written in outcomes:
        if sig == "SIGTERM":
            assert rc in (143, -signal.SIGTERM, 0) and (rc == 0 or not written), outcomes
        else:
            assert rc in (-signal.SIGKILL, 0), outcomes


# --------------------------------------------------------------------------- two processes at once


@pytest.mark.slow
def test_two_calibrations_at_once_with_one_fresh_cache_agree(scene_dir, tmp_path):
    """Two `slcvjax calibrate` of one scene started together on one empty cache folder: both
    compile and write its entries at once; both succeed, agree to round-off and are near the
    truth; a third run then loads their entries without a warning and agrees too."""
    from slcvjax.observations.formats import read_calibration

    env = {k: v for k, v in os.environ.items() if not k.startswith(("SLCVJAX_", "JAX_COMPILATION"))}
    env["SLCVJAX_CACHE_DIR"] = str(tmp_path / "cache")
    cmd = [sys.executable, "-m", "slcvjax.cli", "calibrate", str(scene_dir / "observations.json"), "--out"]

    def start(k):
        return subprocess.Popen(cmd + [str(tmp_path / f"cal{k}.json")], env=env, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)  # fmt: skip

    procs = [start(0), start(1)]
    outs = [p.communicate(timeout=900) for p in procs]
    for p, (_, err) in zip(procs, outs, strict=True):
        assert p.returncode == 0, err[-3000:]
        assert "arning" not in err and "rror" not in err, err[-3000:]
    third = subprocess.run(cmd + [str(tmp_path / "cal2.json")], env=env, capture_output=True, text=True, timeout=900)
    assert third.returncode == 0 and "arning" not in third.stderr, third.stderr[-3000:]
    assert any((tmp_path / "cache").glob("*-cache")) and any((tmp_path / "cache" / "traces").glob("*.jaxexport"))

    cals = [read_calibration(tmp_path / f"cal{k}.json") for k in range(3)]
    truth = read_calibration(scene_dir / "truth.json")
    for cal in cals[1:]:
        for a, b in [
            (cal.rig.camera.K, cals[0].rig.camera.K),
            (cal.rig.camera.dist, cals[0].rig.camera.dist),
            (cal.rig.mirror.apex, cals[0].rig.mirror.apex),
            (cal.rig.mirror.axis, cals[0].rig.mirror.axis),
            (cal.rig.lasers.points, cals[0].rig.lasers.points),
            (cal.rig.lasers.directions, cals[0].rig.lasers.directions),
        ]:
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-9, atol=1e-9)
    # near the truth, by the calibration's own standard deviations (not a copy of a wrong answer)
    doc = json.loads((tmp_path / "cal0.json").read_text())
    std = doc["uncertainty"]
    apex_err = np.abs(np.asarray(cals[0].rig.mirror.apex) - np.asarray(truth.rig.mirror.apex))
    assert np.all(apex_err < 5 * np.asarray(std["mirror_std"]["apex_mm"]) + 1e-6), apex_err
    fx_err = abs(float(cals[0].rig.camera.fx) - float(truth.rig.camera.fx))
    assert fx_err < 5 * std["camera_std"]["fx"], fx_err
    assert 0.2 < doc["residuals"]["sigma_px"] < 0.4  # the simulated noise is 0.3 px


# --------------------------------------------------------------------------- bad images


@pytest.fixture(scope="module")
def image_folder(tmp_path_factory):
    """A small rendered scene: two catadioptric views, one direct chessboard view, setup.json."""
    import dataclasses

    from slcvjax.images.render import RenderOptions, render_scene
    from slcvjax.observations.simulate import make_scene

    scene = make_scene("paper", n_lasers=3, n_views=2)
    scene = dataclasses.replace(scene, chess_poses=scene.chess_poses[:1])
    folder = tmp_path_factory.mktemp("images") / "images"
    render_scene(scene, folder, RenderOptions(noise=0.0))
    return folder


def _bad_images(h: int, w: int, good: bytes) -> dict:
    """name: an image array (h, w, 3) or the file's bytes."""
    import cv2

    rng = np.random.default_rng(0)
    disc = np.zeros((h, w, 3), np.uint8)
    cv2.circle(disc, (w // 2, h // 2), 150, (255, 255, 255), -1)
    half = np.zeros((h, w, 3), np.uint8)
    half[:, w // 2 :] = 255
    return {
        "all black": np.zeros((h, w, 3), np.uint8),
        "all white": np.full((h, w, 3), 255, np.uint8),
        "wrong size": np.full((h // 2, w // 2, 3), 128, np.uint8),
        "transposed": np.full((w, h, 3), 128, np.uint8),
        "truncated": good[: len(good) // 3],
        "truncated header": good[:30],
        "empty file": b"",
        "not an image": b"a text file\n",
        "noise": rng.integers(0, 256, (h, w, 3)).astype(np.uint8),
        "nearly white": (255 - rng.integers(0, 30, (h, w, 3))).astype(np.uint8),
        "gradient": np.tile(np.linspace(0, 255, w).astype(np.uint8)[None, :, None], (h, 1, 3)),
        "a plain disc": disc,
        "half white": half,
        "stripes": np.tile(((np.arange(w) // 2) % 2 * 255).astype(np.uint8)[None, :, None], (h, 1, 3)),
    }


NAMED = {  # what the one line says of an image that cannot be detected in at all
    "all black": "blank image",
    "all white": "blank image",
    "wrong size": "size 320x240, setup.json says 640x480",
    "transposed": "size 480x640, setup.json says 640x480",
    "truncated": "not a readable image",
    "truncated header": "not a readable image",
    "empty file": "not a readable image",
    "not an image": "not a readable image",
}


@pytest.mark.parametrize("image", ["view00.png", "chess00.png"])
def test_a_bad_image_gives_a_named_error_or_a_not_found_entry(image_folder, tmp_path, capsys, image):
    """`slcvjax detect` on a folder with one bad image: a one-line error naming it (exit 2, no
    output), or the image's "not found" entries in the report and the file, and nothing found in
    it (no board, spot or corner made up from noise); never a traceback."""
    import shutil

    import cv2

    from slcvjax.observations.formats import read_observations

    good = (image_folder / image).read_bytes()
    stem = Path(image).stem
    for case, bad in _bad_images(480, 640, good).items():
        folder = tmp_path / case.replace(" ", "_")
        shutil.copytree(image_folder, folder)
        if isinstance(bad, bytes):
            (folder / image).write_bytes(bad)
        else:
            assert cv2.imwrite(str(folder / image), bad)
        out = tmp_path / f"{folder.name}.json"
        capsys.readouterr()
        rc = main(["detect", str(folder), "--out", str(out)])
        got = capsys.readouterr()
        assert "Traceback" not in got.err and "ERROR" not in got.err, (case, got.err)
        if case in NAMED:
            assert rc == 2, case
            line = _one_error_line(got.err, "detect", str(folder / image))
            assert NAMED[case] in line, (case, line)
            assert not out.exists()
            continue
        assert rc == 0, (case, got.err)
        obs = read_observations(out)
        problems = obs.extra["detection"]["problems"][stem]
        report = next(ln for ln in got.out.splitlines() if ln.startswith(f"{stem}:"))
        if image.startswith("view"):
            view = next(v for v in obs.views if v.name == stem)
            assert not any(seen.any() for _, seen in view.boards.values()) and not view.spots, case
            expected = ["no mirror found"] if "no mirror found" in problems else [f"wall{j}: " for j in range(4)]
            assert all(any(p.startswith(e) for p in problems) for e in expected), (case, problems)
            assert any(p.startswith("no spot for laser 0, 1, 2") for p in problems) or problems == ["no mirror found"]
        else:
            assert stem not in [v.name for v in obs.calibration_views], case
            assert problems == ["no 9x6 chessboard found"], (case, problems)
        assert all(p in report for p in problems), (case, report)
