"""Faults outside the data (issue 61, item 3): a damaged cache, two processes at once, an
output that cannot be written, bad images, a calibration killed part way."""

import warnings
import zlib
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax._src import compilation_cache as jax_cc

from slcvjax.cli import main
from slcvjax.support import cache, persist

# --------------------------------------------------------------------------- a damaged cache


@pytest.fixture
def own_cache(tmp_path, monkeypatch):
    """This process's compilation cache moved to a fresh folder for the test, then put back."""
    folder = tmp_path / "cache"

    def switch():
        jax_cc.reset_cache()
        jax.clear_caches()
        cache._DAMAGED.clear()
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
            assert persist._unframe(data)
    cache._DAMAGED.clear()
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
    payload = persist._unframe(bytes(data))
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
    import slcvjax.observations.simulate as sim

    out = tmp_path / "run" / "out"
    make_scene = sim.make_scene

    def vanish_then_make_scene(*args, **kwargs):  # the command has checked its output by now
        assert out.is_dir()
        out.rmdir()
        if how != "removed":
            out.write_text("a file now\n")
        return make_scene(*args, **kwargs)

    monkeypatch.setattr(sim, "make_scene", vanish_then_make_scene)
    argv = ["simulate", "--preset", "paper", "--lasers", "3", "--views", "2", "--out", str(out)]
    assert main(argv) == 2
    line = _one_error_line(capsys.readouterr().err, "simulate", str(out / "observations.json"))
    assert "vanished" in line
    assert _listing(tmp_path) == ({"run"} if how == "removed" else {"run", "run/out"})
