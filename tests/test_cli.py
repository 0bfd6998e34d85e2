import subprocess
import sys

from slcvjax import cli


def test_demo_runs_and_writes_its_folder(tmp_path, capsys):
    assert cli.main(["demo", "--views", "5", "--lasers", "4", "--out", str(tmp_path / "demo")]) == 0
    out = capsys.readouterr().out
    assert "camera" in out and "mirror" in out and "bound" in out
    assert "mean diameter" in out
    for name in ["observations.json", "truth.json", "calibration.json", "pipe_points.json", "pipe_circles.png"]:
        assert (tmp_path / "demo" / name).exists()


def test_console_script_reports_usage_errors():
    r = subprocess.run([sys.executable, "-m", "slcvjax.cli", "nonsense"], capture_output=True, text=True)
    assert r.returncode == 2
    assert "invalid choice" in r.stderr
