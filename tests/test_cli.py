import subprocess
import sys

import numpy as np
import pytest

from slcvjax import cli
from slcvjax._calibrate import laser_errors
from slcvjax._io import read_calibration, read_observations


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
    x_ref = np.array([las["working_point"] for las in cal.extra["uncertainty"]["lasers"]])
    pos, ang = laser_errors(cal.rig, truth.rig, x_ref)
    assert pos.max() < 1.0 and np.degrees(ang.max()) < 1.0, (pos, np.degrees(ang))
    assert read_observations(out_dir / "detected.json").views[0].spots


def test_console_script_reports_usage_errors():
    r = subprocess.run([sys.executable, "-m", "slcvjax.cli", "nonsense"], capture_output=True, text=True)
    assert r.returncode == 2
    assert "invalid choice" in r.stderr
