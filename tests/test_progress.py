"""Progress on the long commands: the passes as they end with their seconds, and one line where a
first run compiles."""

import re

import slcvjax as sj
from slcvjax.support import cache
from slcvjax_cli import main


def test_the_compile_note_says_when_a_run_compiles(tmp_path, monkeypatch):
    monkeypatch.setattr(cache, "compilation_cache_dir", lambda: tmp_path)
    assert cache.compile_note().startswith("compiling, once; kept in the cache")
    (tmp_path / "traces").mkdir()
    (tmp_path / "traces" / "program").write_text("x")
    assert cache.compile_note() is None
    monkeypatch.setattr(cache, "compilation_cache_dir", lambda: None)
    assert "the compilation cache is off" in cache.compile_note()


def test_calibrate_reports_each_pass_with_its_seconds_and_q_silences_it(tmp_path, capsys):
    obs, _ = sj.simulate(sj.make_scene("paper", n_lasers=2, n_views=3), noise=0.2, seed=0)
    sj.write_observations(tmp_path / "obs.json", obs)
    assert main(["calibrate", str(tmp_path / "obs.json"), "--out", str(tmp_path / "cal.json")]) == 0
    out = capsys.readouterr().out
    passes = re.findall(r"^  pass (\S+): .*?(\d+) steps, cost .* -> .*, \w+, ([0-9.]+) s$", out, re.M)
    stored = sj.read_calibration(tmp_path / "cal.json").extra["stages"]["joint"]["passes"]
    assert [p[0] for p in passes] == [p["name"].split(":")[0] for p in stored]
    assert [int(p[1]) for p in passes] == [p["steps"] for p in stored]
    assert main(["calibrate", str(tmp_path / "obs.json"), "--out", str(tmp_path / "cal2.json"), "-q"]) == 0
    assert "pass" not in capsys.readouterr().out
    # outside a command the library says nothing of its passes
    sj.calibrate(obs)
    assert "pass" not in capsys.readouterr().out
