"""The tutorial runs: every ``bash`` block of ``docs/your-own-rig.md``, in order, in an empty folder.

Convention (stated on the page): the tutorial's paths are relative (``my-rig/...``) and the
commands run with an empty ``tmp_path`` as the working folder, so they run as written; a line
ending in ``\\`` continues on the next; a word with ``*`` is expanded as a shell would (sorted;
quoted words are not); every command is a ``slcvjax`` command, run in-process through
``slcvjax_cli.main``.  ``text`` blocks (the photos, alternatives) are not run.

The page's simulate command renders a ChArUco box for a rig unlike the preset (its camera size,
mirror size and laser count checked here); its ``setup.json`` must be the one ``setup images``
writes from ``setup init``'s.  At the end the calibrated lasers are compared with the truth,
against the Cramér–Rao bound of the observations ``detect`` wrote, at each kind's noise as the
calibration estimated it (as ``slcvjax demo`` compares).
"""

import glob
import json
import re
import shlex
from pathlib import Path

import numpy as np
import pytest

import slcvjax as sj
from slcvjax.calibration.bound import laser_errors
from slcvjax.observations.problem import KIND_NAMES
from slcvjax_cli import main

PAGE = Path(__file__).resolve().parents[1] / "docs" / "your-own-rig.md"
BOUND_RATIO = 1.3  # the lasers' RMS error over the bound's RMS std, position and direction


def tutorial_commands(text: str) -> list[str]:
    """The page's ``bash`` blocks as command lines, in order (continuations joined, comments dropped)."""
    out = []
    for block in re.findall(r"^```bash\n(.*?)^```", text, flags=re.S | re.M):
        for line in re.sub(r"\\\n\s*", " ", block).splitlines():
            line = line.strip()
            if line and not line.startswith("#"):
                out.append(line)
    return out


def words(line: str) -> list[str]:
    """A command line's words as a shell gives them: quotes removed, an unquoted ``*`` expanded here."""
    out = []
    for raw in shlex.split(line, posix=False):
        word = shlex.split(raw)[0]
        if "*" in word and raw[:1] not in "'\"":
            out.extend(sorted(glob.glob(word)) or [word])
        else:
            out.append(word)
    return out


def test_the_page_parses_into_slcvjax_commands():
    cmds = [words(line) for line in tutorial_commands(PAGE.read_text())]
    assert cmds and all(c[0] == "slcvjax" for c in cmds), cmds
    names = [c[1] for c in cmds]
    for name in ("setup", "target", "simulate", "detect", "calibrate", "export", "measure"):
        assert name in names
    assert words("slcvjax setup images a b --views 'view*.png'")[-1] == "view*.png"  # quoted: not expanded


@pytest.mark.slow
def test_the_tutorial_runs_and_calibrates_within_the_bound(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    simulated_setup = None
    for line in tutorial_commands(PAGE.read_text()):
        argv = words(line)  # here, when the files a glob names exist
        rc = main(argv[1:])
        assert rc == 0, f"{' '.join(argv)} exited {rc}"
        if argv[1] == "simulate" and "--target" in argv:
            simulated_setup = json.loads(Path("my-rig/images/setup.json").read_text())
        if argv[1:3] == ["setup", "images"]:
            # what the simulator wrote beside its images is what setup init + setup images write
            assert simulated_setup is not None
            assert json.loads(Path("my-rig/images/setup.json").read_text()) == simulated_setup
    for f in ("targets/wall0.pdf", "targets/build_sheet.md", "calibration_report.html", "pipe.json"):
        assert Path("my-rig", f).is_file(), f

    truth = sj.read_calibration("my-rig/truth.json")
    ref = sj.paper_rig()
    rig = truth.rig
    assert rig.camera.width != ref.camera.width and float(rig.mirror.radius) != float(ref.mirror.radius)
    assert rig.lasers.n != ref.lasers.n

    res = sj.load_result("my-rig/calibration.json")
    detected = sj.read_observations("my-rig/detected.json")
    assert len(res.observations.views) == len(detected.views)
    pooled = float(res.cov.sigma)
    kinds = [k for k in KIND_NAMES if k in res.kind_sigma]
    sigma = [s if s is not None and np.isfinite(s) else pooled for s in (res.kind_sigma[k] for k in kinds)]
    bound = sj.cramer_rao(truth, res.observations, sigma, packed=res.packed, rigid=True)
    assert not res.undetermined_lasers
    pos, ang = laser_errors(res.rig, truth.rig, bound["x_ref"])
    ratio_pos = float(np.sqrt(np.mean(pos**2))) / bound["position_rms_mm"]
    ratio_ang = float(np.sqrt(np.mean(ang**2))) / bound["direction_rms_rad"]
    print(f"tutorial: lasers' RMS error over the bound: position {ratio_pos:.2f}, direction {ratio_ang:.2f}")
    assert ratio_pos < BOUND_RATIO and ratio_ang < BOUND_RATIO, (ratio_pos, ratio_ang)

    pipe = json.loads(Path("my-rig/pipe_observations.json").read_text())["simulation"]["pipe"]
    circles = [v["circle"] for v in json.loads(Path("my-rig/pipe.json").read_text())["views"] if v.get("circle")]
    assert circles, "no circle fitted in the pipe"
    for c in circles:  # within 4 of its std, or 1 mm
        assert abs(c["diameter"] - pipe["diameter"]) < max(4 * c["diameter_std"], 1.0), (c, pipe)


def test_the_resized_rig_is_the_reference_rig_at_its_sizes():
    from slcvjax.images.own_box import sized_rig

    ref, same = sj.paper_rig(6), sized_rig(n_lasers=6)
    assert same is not None and float(same.camera.fx) == pytest.approx(float(ref.camera.fx), rel=1e-12)
    big = sized_rig((1280, 960), 40.0, 20.0, 96.0, 6, laser_tilt_deg=10.0)
    assert big.camera.width == 1280 and float(big.camera.fx) == pytest.approx(2 * float(ref.camera.fx))
    tilt = np.degrees(
        np.arcsin(np.asarray(big.lasers.directions)[:, 2]) - np.arcsin(np.asarray(ref.lasers.directions)[:, 2])
    )
    np.testing.assert_allclose(tilt, -10.0, atol=1e-9)


def test_setup_images_lists_the_photos_and_names_a_folder_without_them(tmp_path, capsys):
    setup = tmp_path / "setup.json"
    assert main(["setup", "init", "--mirror", "cone:20x10", "--lasers", "3", "--out", str(setup)]) == 0
    photos = tmp_path / "photos"
    (photos / "box").mkdir(parents=True)
    for name in ("box/b.jpg", "box/a.jpg", "d1.jpg", "notes.txt"):
        (photos / name).write_bytes(b"")
    assert main(["setup", "images", str(setup), str(photos), "--views", "box/*.jpg", "--direct", "d*.jpg"]) == 0
    doc = json.loads((photos / "setup.json").read_text())
    assert [v["image"] for v in doc["views"]] == ["box/a.jpg", "box/b.jpg"]
    assert doc["chessboard_views"] == [{"image": "d1.jpg", "board": "chess"}]
    assert doc["boards"] == json.loads(setup.read_text())["boards"]
    capsys.readouterr()
    assert main(["setup", "images", str(setup), str(photos), "--views", "*.png"]) == 2
    assert "no image matches --views '*.png'" in capsys.readouterr().err
