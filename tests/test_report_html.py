"""The calibration report (``slcvjax report``): one self-contained HTML file whose numbers are the
calibration file's, with every section, that a browser shows without an error."""

import json
import re
import shutil
import subprocess
from html.parser import HTMLParser

import cv2
import numpy as np
import pytest

import slcvjax as sj
from slcvjax.calibration.evaluate import per_observation
from slcvjax.experiments.report import projection_std, residual_vectors
from slcvjax_cli import main

SECTIONS = (
    "status-line",
    "rig",
    "residual-vectors",
    "histograms",
    "parameters",
    "repairs",
    "projection-uncertainty",
    "passes",
)


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """A small simulated calibration written as a file, its result, and an image folder."""
    tmp = tmp_path_factory.mktemp("report")
    obs, _ = sj.simulate(sj.make_scene("paper", n_lasers=3, n_views=5), noise=0.3, seed=1)
    res = sj.calibrate(obs)
    path = tmp / "cal.json"
    sj.write_calibration(path, sj.to_calibration(res))
    images = tmp / "images"
    images.mkdir()
    w, h = obs.image_size
    for name in [v.name for v in obs.views[:2]]:  # two of the views' images: the others drawn on a canvas
        cv2.imwrite(str(images / f"{name}.png"), np.full((h, w, 3), 200, np.uint8))
    return {"path": path, "res": res, "obs": obs, "images": images, "tmp": tmp}


@pytest.fixture(scope="module")
def written(calibrated):
    """The report written by the command, over the image folder."""
    out = calibrated["tmp"] / "report.html"
    assert main(["report", str(calibrated["path"]), "--images", str(calibrated["images"]), "--out", str(out)]) == 0
    return out


class _Tables(HTMLParser):
    """The report's tables as lists of rows of cell texts, keyed by the table's class (else its order)."""

    def __init__(self):
        super().__init__()
        self.tables, self._rows, self._cell, self._key = {}, None, None, None

    def handle_starttag(self, tag, attrs):
        if tag == "table":
            self._key = dict(attrs).get("class") or str(len(self.tables))
            self._rows = []
        elif tag == "tr" and self._rows is not None:
            self._rows.append([])
        elif tag in ("td", "th") and self._rows is not None:
            self._cell = ""

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._cell is not None:
            self._rows[-1].append(self._cell.strip())
            self._cell = None
        elif tag == "table":
            self.tables[self._key] = self._rows
            self._rows = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell += data


def _tables(text: str) -> dict:
    p = _Tables()
    p.feed(text)
    return p.tables


def _num(cell: str) -> float:
    return float("nan") if cell == "–" else float(cell)


def test_the_report_is_one_self_contained_file(written):
    text = written.read_text()
    assert text.startswith("<!DOCTYPE html>")
    srcs = re.findall(r'\bsrc\s*=\s*["\']([^"\']*)', text)
    hrefs = re.findall(r'\bhref\s*=\s*["\']([^"\']*)', text)
    assert srcs and all(s.startswith("data:image/png;base64,") for s in srcs)
    assert all(h.startswith("#") for h in hrefs), [h for h in hrefs if not h.startswith("#")]
    assert "<link" not in text and "<script" not in text and "url(" not in text
    assert [p.name for p in written.parent.glob("*.html")] == ["report.html"]  # one file, nothing beside it


def test_the_report_has_every_section_and_an_honest_status(written, calibrated):
    text = written.read_text()
    for sid in SECTIONS:
        assert f'id="{sid}"' in text, sid
    assert "Converged: the last pass reached a minimum." in text
    # every view (5 catadioptric, 12 direct) has its residual figure, at a stated gain
    assert len(re.findall(r"<figure><img", text)) == 1 + 5 + 12 + 1 + 1
    assert re.search(r"<b>\d+ times its length</b>", text)
    assert "(2 of 17 found)" in text  # two images given: drawn over them
    assert "at the estimate, not at the" in text


def test_its_numbers_are_the_calibration_files(written, calibrated):
    doc = json.loads(calibrated["path"].read_text())
    unc, res = doc["uncertainty"], doc["residuals"]
    tables = _tables(written.read_text())
    lasers = tables["lasers"][1:]
    assert len(lasers) == len(unc["lasers"]) == 3
    for row, las in zip(lasers, unc["lasers"], strict=True):
        got = [_num(row[k]) for k in (3, 4, 5)]
        want = [las["working_range_mm"], las["position_std_mm"], las["direction_std_deg"]]
        np.testing.assert_allclose(got, want, rtol=1e-3)
    cam = {r[0]: r for r in tables["camera"][1:]}
    for name, std in unc["camera_std"].items():
        np.testing.assert_allclose(_num(cam[name][2]), std, rtol=1e-3)
    mirror = {r[0]: r for r in tables["mirror"][1:]}
    np.testing.assert_allclose(
        [_num(mirror[f"apex {a} (mm)"][2]) for a in "xyz"], unc["mirror_std"]["apex_mm"], rtol=1e-3
    )
    tilt = [_num(mirror[f"axis tilt e{j} (deg)"][2]) for j in (1, 2)]
    np.testing.assert_allclose(tilt, unc["mirror_std"]["axis_tilt_deg"], rtol=1e-3)
    # the bound at the estimate, with each kind's sigma (the pooled one where a kind has none)
    r = calibrated["res"]
    sigmas = [res["by_kind_sigma_px"][k] or res["sigma_px"] for k in ("dot", "spot", "rim", "chess")]
    crb = sj.cramer_rao(sj.to_calibration(r), r.observations, sigmas, packed=r.packed)
    np.testing.assert_allclose([_num(row[6]) for row in lasers], crb["position_std_mm"], rtol=1e-3)
    np.testing.assert_allclose([_num(row[7]) for row in lasers], np.degrees(crb["direction_std_rad"]), rtol=1e-3)
    text = written.read_text()
    assert f"RMS reprojection error {res['rms_px']:.4g} px" in text
    views = {row[0]: _num(row[1]) for t in tables.values() if t[0] == ["view", "RMS (px)"] for row in t[1:]}
    assert views.keys() == res["per_view_rms_px"].keys()
    np.testing.assert_allclose(list(views.values()), list(res["per_view_rms_px"].values()), rtol=1e-3)


def test_the_residual_vectors_are_the_fits(calibrated):
    r = calibrated["res"]
    rv = residual_vectors(r)
    norm, kind, ok = per_observation(r.params, r.packed)
    assert np.array_equal(rv["valid"], ok) and np.array_equal(rv["kind"], kind)
    v = np.where(np.isnan(rv["vector"]), 0.0, rv["vector"])
    np.testing.assert_allclose(np.linalg.norm(v, axis=1)[ok], norm[ok], atol=1e-9)
    # a dot's vector is its model pixel less its observed pixel
    cal = sj.to_calibration(r)
    view, board, j = r.packed.dot_src[0]
    model = sj.reprojections(cal, calibrated["obs"], view)["dots"][board][j]
    np.testing.assert_allclose(rv["pixel"][0] + rv["vector"][0], model, atol=1e-6)


def test_the_projection_uncertainty_follows_the_covariance(calibrated):
    r = calibrated["res"]
    cov = np.asarray(r.cov.glob)
    a = projection_std(r.rig, cov, 150.0, n_grid=16)
    b = projection_std(r.rig, 4.0 * cov, 150.0, n_grid=16)
    s = a["std_mm"]
    assert s.shape == (16, 16) and np.isfinite(s).sum() > 100
    np.testing.assert_allclose(b["std_mm"], 2.0 * s, rtol=1e-9)  # NaN where they are NaN
    # the laser block does not enter: only the camera's and the mirror's covariance
    c = cov.copy()
    c[15:, 15:] *= 100.0
    np.testing.assert_allclose(projection_std(r.rig, c, 150.0, n_grid=16)["std_mm"], s, rtol=1e-12)
    # a corner of the grid (outside the rim's image) sees no mirror
    assert np.isnan(s[0, 0])


def test_a_calibration_that_did_not_converge_says_so(calibrated, tmp_path):
    doc = json.loads(calibrated["path"].read_text())
    doc["uncertainty"]["converged"] = False
    doc["uncertainty"]["status"] = "not a minimum: the last pass (C: joint (final)) stopped after 9 steps"
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(doc))
    out = sj.write_report(path, tmp_path / "r.html")
    text = out.read_text()
    assert 'class="status bad"' in text and "NOT converged: not a minimum" in text


@pytest.mark.slow
def test_calibrate_report_writes_the_report_beside_the_calibration(calibrated, tmp_path):
    obs_path = tmp_path / "obs.json"
    sj.write_observations(obs_path, calibrated["obs"])
    assert main(["-q", "calibrate", str(obs_path), "--out", str(tmp_path / "cal.json"), "--report"]) == 0
    text = (tmp_path / "cal_report.html").read_text()
    assert all(f'id="{sid}"' in text for sid in SECTIONS)


def _chromium() -> str | None:
    return next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome") if shutil.which(n)), None)


_PROBE = """<script>
window.__errors = [];
window.addEventListener("error", e => window.__errors.push(String(e.message || e.type)), true);
window.addEventListener("load", () => {
  const imgs = Array.from(document.images);
  const bad = imgs.filter(i => !(i.complete && i.naturalWidth > 0)).length;
  document.body.setAttribute("data-images", String(imgs.length));
  document.body.setAttribute("data-broken", String(bad));
  document.body.setAttribute("data-errors", String(window.__errors.length));
});
</script>"""


@pytest.mark.skipif(_chromium() is None, reason="no chromium (Debian: apt-get install chromium)")
def test_a_browser_shows_it_without_an_error(written, tmp_path):
    page = tmp_path / "probe.html"
    page.write_text(written.read_text().replace("<head>", "<head>" + _PROBE, 1))
    cmd = [_chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--enable-logging=stderr", "--v=0"]
    cmd += ["--virtual-time-budget=10000", "--dump-dom", page.as_uri()]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    dom = run.stdout
    m = re.search(r'<body[^>]*data-images="(\d+)"[^>]*data-broken="(\d+)"[^>]*data-errors="(\d+)"', dom)
    assert m, (run.returncode, run.stderr[-2000:])
    n_images, broken, errors = (int(g) for g in m.groups())
    assert n_images == 20 and broken == 0 and errors == 0
    console = [line for line in run.stderr.splitlines() if "CONSOLE" in line or "Uncaught" in line]
    assert not console, console
