import subprocess
import sys

import numpy as np
import pytest

from slcvjax import cli
from slcvjax.calibration.bound import laser_errors
from slcvjax.observations.formats import read_calibration, read_observations

from ._helpers import on_true_lines


@pytest.mark.slow
def test_demo_runs_end_to_end_from_images(tmp_path, capsys):
    out_dir = tmp_path / "demo"
    assert cli.main(["demo", "--views", "5", "--lasers", "4", "--out", str(out_dir)]) == 0
    out = capsys.readouterr().out
    assert "camera" in out and "mirror" in out and "bound" in out
    assert "mean diameter" in out
    for name in [
        "observations.json",
        "truth.json",
        "images/setup.json",
        "images/view04.png",
        "detected.json",
        "detection_report.txt",
        "calibration.json",
        "rig_3d.png",
        "detections.png",
        "pipe_points.json",
        "pipe_circles.png",
    ]:
        assert (out_dir / name).exists(), name
    # the calibration from the rendered images against the simulator's truth
    cal, truth = read_calibration(out_dir / "calibration.json"), read_calibration(out_dir / "truth.json")
    x_ref = on_true_lines(truth.rig, [las["working_point"] for las in cal.extra["uncertainty"]["lasers"]])
    pos, ang = laser_errors(cal.rig, truth.rig, x_ref)
    assert pos.max() < 1.0 and np.degrees(ang.max()) < 1.0, (pos, np.degrees(ang))
    assert read_observations(out_dir / "detected.json").views[0].spots


def test_demo_refuses_both_pose_models(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        cli.main(["demo", "--rigid", "--free-poses", "--out", str(tmp_path / "d")])
    assert exit_.value.code == 2
    assert "--free-poses" in capsys.readouterr().err
    assert not (tmp_path / "d").exists()


@pytest.mark.slow
def test_console_script_reports_usage_errors():
    r = subprocess.run([sys.executable, "-m", "slcvjax.cli", "nonsense"], capture_output=True, text=True)
    assert r.returncode == 2
    assert "invalid choice" in r.stderr


@pytest.mark.slow
def test_calibrate_from_a_calibration_evaluates_it_on_held_out_views(tmp_path, capsys):
    """Fit on some views, then ``--from CAL --freeze camera,mirror`` on other views: camera and
    mirror are held as given, and the held-out residuals expose a wrong mirror."""
    import dataclasses
    import json

    from slcvjax.observations.formats import Calibration, write_calibration, write_observations
    from slcvjax.observations.simulate import box_scene, paper_rig, paper_views, simulate

    rig = paper_rig(5)
    views = paper_views(14)
    train, _ = simulate(box_scene(rig, views[:9], n_chess_views=8), noise=0.3, seed=2)
    held, _ = simulate(box_scene(rig, views[9:], n_chess_views=8), noise=0.3, seed=3)
    write_observations(tmp_path / "train.json", train)
    write_observations(tmp_path / "held.json", held)
    assert cli.main(["calibrate", str(tmp_path / "train.json"), "--out", str(tmp_path / "cal.json")]) == 0
    cal = read_calibration(tmp_path / "cal.json")

    def evaluate(cal_path, out):
        args = ["calibrate", str(tmp_path / "held.json"), "--from", str(cal_path), "--freeze", "camera,mirror"]
        assert cli.main(args + ["--loss", "linear", "--out", str(out)]) == 0
        return json.loads(out.read_text())

    doc = evaluate(tmp_path / "cal.json", tmp_path / "eval.json")
    ev = read_calibration(tmp_path / "eval.json")
    np.testing.assert_array_equal(np.asarray(ev.rig.camera.K), np.asarray(cal.rig.camera.K))
    np.testing.assert_array_equal(np.asarray(ev.rig.mirror.apex), np.asarray(cal.rig.mirror.apex))
    good = doc["residuals"]["rms_px"]
    assert doc["residuals"]["invalid"] == 0 and good < 0.6  # 0.3 px noise: a 2D norm's RMS is 0.42
    # the same held-out views against a mirror 0.6 mm off: the residuals say so
    moved = dataclasses.replace(cal.rig.mirror, apex=cal.rig.mirror.apex + np.array([0.6, 0.0, 0.0]))
    write_calibration(tmp_path / "bad.json", Calibration(dataclasses.replace(cal.rig, mirror=moved), cal.board_poses))
    bad = evaluate(tmp_path / "bad.json", tmp_path / "eval_bad.json")["residuals"]["rms_px"]
    assert bad > 2 * good
    both = ["--from", str(tmp_path / "cal.json"), "--camera", str(tmp_path / "cal.json")]
    assert cli.main(["calibrate", str(tmp_path / "held.json"), *both, "--out", str(tmp_path / "x.json")]) != 0
    assert "--camera and --from" in capsys.readouterr().err


def _run_python(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)


def test_help_and_version_answer_without_importing_jax():
    """``slcvjax --help``, ``slcvjax CMD --help`` and ``--version`` parse without the library: no JAX
    (nor ``slcvjax`` itself, which imports JAX) in ``sys.modules`` when they exit."""
    commands = sorted(cli.build_parser()._subparsers._group_actions[0].choices)
    code = (
        "import sys, slcvjax_cli\n"
        f"for argv in [['--help'], ['--version']] + [[c, '--help'] for c in {commands!r}]:\n"
        "    try:\n"
        "        slcvjax_cli.main(argv)\n"
        "    except SystemExit as e:\n"
        "        assert e.code == 0, (argv, e.code)\n"
        "heavy = sorted(m for m in sys.modules if m.split('.')[0] in ('jax', 'jaxlib', 'slcvjax', 'numpy'))\n"
        "print('IMPORTED', heavy)\n"
    )
    r = _run_python(code)
    assert r.returncode == 0, r.stderr
    assert "IMPORTED []" in r.stdout, r.stdout[-2000:]
    assert {"simulate", "detect", "calibrate", "camera", "omni", "measure", "target", "setup", "demo"} <= set(commands)


def test_the_console_script_is_the_light_entry_point():
    from importlib.metadata import entry_points

    (script,) = [e for e in entry_points(group="console_scripts") if e.name == "slcvjax"]
    assert script.value == "slcvjax_cli:main"


def test_version(capsys):
    import slcvjax

    with pytest.raises(SystemExit) as exit_:
        cli.main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.strip() == f"slcvjax {slcvjax.__version__}"


def test_the_parsers_copies_of_library_values_agree():
    import slcvjax_cli
    from slcvjax.observations.simulate import PAPER_HALF_WIDTH, PRESETS

    assert slcvjax_cli.PRESETS == PRESETS
    assert slcvjax_cli.PAPER_HALF_WIDTH == PAPER_HALF_WIDTH


def test_quiet_and_verbose(tmp_path, capsys):
    """The reports go through ``logging``: ``-q`` keeps only warnings and errors, ``-v`` adds debug lines,
    and the default comes back after the command (for a caller in the same process)."""
    small = ["--views", "3", "--lasers", "2"]
    assert cli.main(["-q", "simulate", *small, "--out", str(tmp_path / "q")]) == 0
    assert capsys.readouterr().out == ""
    assert (tmp_path / "q" / "observations.json").exists()
    assert cli.main(["simulate", *small, "-v", "--out", str(tmp_path / "v")]) == 0
    out = capsys.readouterr().out
    assert "wrote" in out and "JAX" in out and "compilation cache" in out
    assert cli.main(["simulate", *small, "--out", str(tmp_path / "d")]) == 0
    out = capsys.readouterr().out
    assert "wrote" in out and "compilation cache" not in out
