"""``slcvjax export``: each format read back by OpenCV (or by a reader written here from the tool's
documented layout), its projection compared with the project's own camera and, for a mirror, with
the non-central forward model through the mirror (``project_through_mirror``, Newton on the law of
reflection: not the back-projection the fit sampled)."""

import ast
import re
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import slcvjax as sj
import slcvjax_cli
from slcvjax.experiments import export as ex
from slcvjax_cli import main


def _camera(k3: float = -0.01) -> sj.Camera:
    return sj.Camera.create(551.757, 551.95, 322.826, 205.202, [-0.28, 0.09, 0.0012, -0.0008, k3], 640, 480)


def _points(rng, n=400) -> np.ndarray:
    """Points in front of the camera over its whole image (mm, camera frame)."""
    uv = rng.uniform([0, 0], [639, 479], size=(n, 2))
    xy = (uv - [322.8, 205.2]) / 552.0 * 0.8  # inside the distortion's monotonic range
    z = rng.uniform(200.0, 3000.0, size=n)
    return np.column_stack([xy * z[:, None], z])


def _read_fs(path) -> cv2.FileStorage:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_FORMAT_YAML)
    assert fs.isOpened(), path
    return fs


def _seq(node) -> np.ndarray:
    return np.array([node.at(i).real() for i in range(node.size())])


def mei(intr, points_model) -> np.ndarray:
    """Mei's unified model from its published formula (Mei & Rives 2007; cv2.omnidir's
    projectPoints): unit sphere, shift by xi, radial-tangential distortion, K (skew 0)."""
    fx, fy, cx, cy, xi, k1, k2, p1, p2 = intr
    s = points_model / np.linalg.norm(points_model, axis=1, keepdims=True)
    x, y = s[:, 0] / (s[:, 2] + xi), s[:, 1] / (s[:, 2] + xi)
    r2 = x * x + y * y
    rad = 1 + k1 * r2 + k2 * r2 * r2
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.column_stack([fx * xd + cx, fy * yd + cy])


def read_ocamcalib(path) -> dict:
    """calib_results.txt as OCamCalib's C reader (get_ocam_model) reads it: per section a comment
    line, then the values; polynomials as their length then the coefficients."""
    lines = [ln.strip() for ln in path.read_text().splitlines()]
    data = [ln for ln in lines if ln and not ln.startswith("#")]
    pol = [float(v) for v in data[0].split()]
    invpol = [float(v) for v in data[1].split()]
    assert int(pol[0]) == len(pol) - 1 and int(invpol[0]) == len(invpol) - 1
    xc, yc = (float(v) for v in data[2].split())
    c, d, e = (float(v) for v in data[3].split())
    height, width = (int(v) for v in data[4].split())
    return {"pol": pol[1:], "invpol": invpol[1:], "xc": xc, "yc": yc, "c": c, "d": d, "e": e,
            "height": height, "width": width, "comments": [ln for ln in lines if ln.startswith("#")]}  # fmt: skip


def world2cam(m: dict, points_model) -> np.ndarray:
    """OCamCalib's world2cam (ocam_functions.c), returning OpenCV's (u, v) = (column, row)."""
    norm = np.hypot(points_model[:, 0], points_model[:, 1])
    theta = np.arctan(points_model[:, 2] / norm)
    rho = sum(a * theta**i for i, a in enumerate(m["invpol"]))
    x, y = points_model[:, 0] / norm * rho, points_model[:, 1] / norm * rho
    row = x * m["c"] + y * m["d"] + m["xc"]
    col = x * m["e"] + y + m["yc"]
    return np.column_stack([col, row])


def _cal(rig) -> sj.Calibration:
    return sj.Calibration(rig)


def _hyperboloid_rig(k3=0.0) -> sj.Rig:
    """A central rig: a hyperboloid whose outer focus is the camera's centre, on its axis."""
    vertex_radius, kappa = 20.0, -2.0
    distance = vertex_radius / (np.sqrt(-kappa) - 1.0)  # vertex to the outer focus
    mirror = sj.mirror_of_shape(
        {"kind": "hyperboloid", "vertex_radius": vertex_radius, "conic_constant": kappa, "radius": 30.0},
        [0.0, 0.0, distance],
        [0.0, 0.0, 1.0],
    )
    cam = sj.Camera.create(400.0, 400.0, 320.0, 240.0, [-0.1, 0.02, 0.0, 0.0, k3], 640, 480)
    return sj.Rig(cam, mirror, sj.Lasers.create(np.zeros((0, 3)), np.zeros((0, 3))))


def _through_mirror(rig, rng, range_mm, n=1500):
    """Pixels and points seen through the mirror: random pixels over the image, their reflected
    rays at 0.5, 1, 2 x range_mm, kept where the forward model (Newton) gives the pixel back."""
    uv = rng.uniform([0, 0], [rig.camera.width - 1.0, rig.camera.height - 1.0], size=(n, 2))
    scale = rng.choice(np.asarray(ex.RANGE_FACTORS), size=n) * range_mm

    def point(q, r):
        ray = sj.back_project(rig.camera, rig.mirror, q)
        m, d = ray.point, ray.direction
        md = jnp.dot(m, d)
        s = -md + jnp.sqrt(jnp.maximum(md * md - jnp.dot(m, m) + r * r, 0.0))
        return m + s * d, ray.valid

    pts, ok = jax.vmap(point)(jnp.asarray(uv), jnp.asarray(scale))
    proj = jax.vmap(lambda p: sj.project_through_mirror(rig.camera, rig.mirror, p))(pts)
    back = np.asarray(proj.uv)
    keep = np.asarray(ok) & np.asarray(proj.valid) & (np.linalg.norm(back - uv, axis=1) < 1e-6)
    assert keep.sum() > n // 4
    return back[keep], np.asarray(pts)[keep]


# --------------------------------------------------------------------------- the lens's formats


def test_the_parser_repeats_the_formats():
    assert slcvjax_cli.EXPORT_FORMATS == ex.FORMATS


def test_opencv_ros_and_mrcal_give_the_camera_exactly(tmp_path, rng):
    cam = _camera()
    cal = _cal(sj.Rig.camera_only(cam))
    pts = _points(rng)
    truth = np.asarray(sj.project_points(cam, pts)[0])
    for fmt in ("opencv", "ros"):
        ex.export(cal, fmt, tmp_path / f"{fmt}.yaml")
        fs = _read_fs(tmp_path / f"{fmt}.yaml")
        if fmt == "opencv":
            k, dist = fs.getNode("camera_matrix").mat(), fs.getNode("distortion_coefficients").mat()
        else:
            assert fs.getNode("distortion_model").string() == "plumb_bob"
            k = _seq(fs.getNode("camera_matrix").getNode("data")).reshape(3, 3)
            dist = _seq(fs.getNode("distortion_coefficients").getNode("data"))
            p = _seq(fs.getNode("projection_matrix").getNode("data")).reshape(3, 4)
            np.testing.assert_array_equal(p[:, :3], k)
        assert fs.getNode("image_width").real() == 640 and fs.getNode("image_height").real() == 480
        uv = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), k, dist)[0].reshape(-1, 2)
        np.testing.assert_allclose(uv, truth, atol=1e-9)
    ex.export(cal, "mrcal", tmp_path / "cam.cameramodel")
    model = ast.literal_eval((tmp_path / "cam.cameramodel").read_text())
    assert model["lensmodel"] == "LENSMODEL_OPENCV5" and model["imagersize"] == [640, 480]
    assert model["extrinsics"] == [0.0] * 6
    i = np.asarray(model["intrinsics"])
    k = np.array([[i[0], 0, i[2]], [0, i[1], i[3]], [0, 0, 1]])
    uv = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), k, i[4:])[0].reshape(-1, 2)
    np.testing.assert_allclose(uv, truth, atol=1e-9)


def _kalibr(path) -> dict:
    fs = _read_fs(path)
    cam = fs.getNode("cam0")
    return {
        "model": cam.getNode("camera_model").string(),
        "intrinsics": _seq(cam.getNode("intrinsics")),
        "distortion_model": cam.getNode("distortion_model").string(),
        "dist": _seq(cam.getNode("distortion_coeffs")),
        "resolution": _seq(cam.getNode("resolution")),
    }


def _reported(text: str) -> tuple[float, float]:
    m = re.search(r"RMS ([0-9.]+) px, worst ([0-9.]+) px", text)
    return float(m.group(1)), float(m.group(2))


def test_kalibr_pinhole_is_exact_without_k3_and_a_reported_fit_with_it(tmp_path, rng):
    pts = _points(rng)
    for k3 in (0.0, -0.01):
        cam = _camera(k3)
        path = tmp_path / f"camchain{k3}.yaml"
        rep = ex.export(_cal(sj.Rig.camera_only(cam)), "kalibr", path)
        k = _kalibr(path)
        assert k["model"] == "pinhole" and k["distortion_model"] == "radtan"
        np.testing.assert_array_equal(k["resolution"], [640, 480])
        fx, fy, cx, cy = k["intrinsics"]
        uv = mei([fx, fy, cx, cy, 0.0, *k["dist"]], pts)  # xi = 0: a pinhole with radtan
        err = np.linalg.norm(uv - np.asarray(sj.project_points(cam, pts)[0]), axis=1)
        if k3 == 0.0:
            assert rep.fit is None
            assert err.max() < 1e-9
        else:  # k3 has no place in radtan: refitted over the image, and the reported figures are the truth's
            rms, worst = _reported(path.read_text())
            assert rms == pytest.approx(rep.fit.rms_px, abs=1e-3) and 0.0 < rms < 0.5
            assert np.sqrt(np.mean(err**2)) == pytest.approx(rms, rel=0.3, abs=0.005)
            assert err.max() < 1.5 * worst + 0.01


def test_omnidir_of_a_lens_is_mei_with_xi_near_zero(tmp_path, rng):
    cam = _camera(0.0)
    path = tmp_path / "omni.yaml"
    rep = ex.export(_cal(sj.Rig.camera_only(cam)), "opencv-omnidir", path)
    fs = _read_fs(path)
    k, d, xi = (fs.getNode(n).mat() for n in ("camera_matrix", "distortion_coefficients", "xi"))
    assert d.shape == (1, 4) and xi.shape == (1, 1) and k[0, 1] == 0.0
    pts = _points(rng)
    uv = mei([k[0, 0], k[1, 1], k[0, 2], k[1, 2], xi[0, 0], *d.ravel()], pts)
    err = np.linalg.norm(uv - np.asarray(sj.project_points(cam, pts)[0]), axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.05 and rep.fit.rms_px < 0.05
    assert fs.getNode("central_approximation_rms_px").real() == pytest.approx(rep.fit.rms_px)


def test_a_telecentric_camera_is_refused_by_the_pinhole_formats(tmp_path):
    cam = sj.Camera.create(5.0, 5.0, 320.0, 240.0, np.zeros(5), 640, 480, telecentric=True, unit=1.0)
    for fmt in ("opencv", "ros", "mrcal", "kalibr"):
        with pytest.raises(sj.FormatError, match="camera.projection: telecentric"):
            ex.export(_cal(sj.Rig.camera_only(cam)), fmt, tmp_path / f"x.{fmt}")
        assert not (tmp_path / f"x.{fmt}").exists()


# --------------------------------------------------------------------------- through a mirror


@pytest.fixture(scope="module")
def central_rig():
    return _hyperboloid_rig()


def test_a_central_rig_is_fitted_exactly(tmp_path, central_rig):
    """A hyperboloid with the camera at its outer focus is central: Mei's model and OCamCalib's
    polynomial describe it, the viewpoint is the inner focus, the reported error is ~0 and an
    independent evaluation through the non-central forward model agrees."""
    cal = _cal(central_rig)
    rng = np.random.default_rng(3)
    px, pts = _through_mirror(central_rig, rng, 500.0)
    rep = ex.export(cal, "opencv-omnidir", tmp_path / "omni.yaml", range_mm=500.0)
    fs = _read_fs(tmp_path / "omni.yaml")
    k, d, xi = (fs.getNode(n).mat() for n in ("camera_matrix", "distortion_coefficients", "xi"))
    r, t = fs.getNode("R_cam_model").mat(), fs.getNode("t_cam_model_mm").mat().ravel()
    assert np.linalg.det(r) == pytest.approx(-1.0)  # the mirror's image: a left-handed frame
    focus = 2 * 20.0 * np.sqrt(2.0)  # the foci 2 a e apart, a = R / (e^2 - 1) = 20 mm, e = sqrt(2)
    np.testing.assert_allclose(t, [0.0, 0.0, focus], atol=1e-3)
    uv = mei([k[0, 0], k[1, 1], k[0, 2], k[1, 2], xi[0, 0], *d.ravel()], (pts - t) @ r)
    assert np.max(np.linalg.norm(uv - px, axis=1)) < 0.01
    assert rep.fit.rms_px < 0.01 and rep.fit.max_px < 0.05
    ex.export(cal, "ocamcalib", tmp_path / "calib_results.txt", range_mm=500.0)
    m = read_ocamcalib(tmp_path / "calib_results.txt")
    assert (m["width"], m["height"]) == (640, 480) and len(m["pol"]) == 5
    r_o, t_o = _frame_of(m["comments"])
    uv = world2cam(m, (pts - t_o) @ r_o)
    assert np.max(np.linalg.norm(uv - px, axis=1)) < 0.01


def _frame_of(comments: list[str]) -> tuple[np.ndarray, np.ndarray]:
    line = next(c for c in comments if "X_cam = R X_model + t" in c)
    r = re.search(r"R = \[([^\]]+)\]", line).group(1)
    t = re.search(r"t_mm = \[([^\]]+)\]", line).group(1)
    return np.array([float(v) for v in r.split(",")]).reshape(3, 3), np.array([float(v) for v in t.split(",")])


@pytest.mark.parametrize("fmt", ["opencv-omnidir", "ocamcalib"])
def test_the_cone_rigs_approximation_reports_what_an_independent_evaluation_gives(tmp_path, fmt):
    """The reference rig's cone is far from central (its viewpoints are a ring): the reported
    RMS is what random pixels over the mirror's image, checked through the forward model, give."""
    rig = sj.paper_rig(3)
    path = tmp_path / ("omni.yaml" if fmt == "opencv-omnidir" else "calib_results.txt")
    assert main(["export", _write_truth(tmp_path, rig), "--format", fmt, "--out", str(path), "--range", "130"]) == 0
    px, pts = _through_mirror(rig, np.random.default_rng(5), 130.0, n=3000)
    if fmt == "opencv-omnidir":
        fs = _read_fs(path)
        k, d, xi = (fs.getNode(n).mat() for n in ("camera_matrix", "distortion_coefficients", "xi"))
        r, t = fs.getNode("R_cam_model").mat(), fs.getNode("t_cam_model_mm").mat().ravel()
        uv = mei([k[0, 0], k[1, 1], k[0, 2], k[1, 2], xi[0, 0], *d.ravel()], (pts - t) @ r)
        rms = fs.getNode("central_approximation_rms_px").real()
    else:
        m = read_ocamcalib(path)
        r, t = _frame_of(m["comments"])
        uv = world2cam(m, (pts - t) @ r)
        rms, _ = _reported(" ".join(m["comments"]))
    err = np.linalg.norm(uv - px, axis=1)
    assert rms > 1.0  # not central: it shows
    assert np.sqrt(np.mean(err**2)) == pytest.approx(rms, rel=0.2)


def _write_truth(tmp_path, rig) -> str:
    path = tmp_path / "truth.json"
    sj.write_calibration(path, sj.Calibration(rig))
    return str(path)


def test_export_command_prints_the_approximation_and_refuses_bad_input(tmp_path, capsys, central_rig):
    cal = _write_truth(tmp_path, central_rig)
    out = tmp_path / "camchain.yaml"
    assert main(["export", cal, "--format", "kalibr", "--out", str(out), "--range", "500"]) == 0
    text = capsys.readouterr().out
    assert "central approximation (Mei unified model) over the mirror's field: RMS 0.000 px" in text
    assert _kalibr(out)["model"] == "omni" and len(_kalibr(out)["intrinsics"]) == 5
    assert main(["export", cal, "--format", "opencv", "--out", str(tmp_path / "lens.yaml")]) == 0
    assert "its lens alone" in capsys.readouterr().out
    assert main(["export", cal, "--format", "ros", "--out", str(tmp_path / "x.yaml"), "--range", "-1"]) == 2
    assert main(["export", cal, "--format", "kalibr", "--out", str(tmp_path / "x.yaml"), "--range", "-1"]) == 2
    assert "--range: must be a positive number" in capsys.readouterr().err
    assert main(["export", str(tmp_path / "missing.json"), "--format", "ros", "--out", str(out)]) == 2


# --------------------------------------------------------------------------- --camera from YAML

ROS_YAML = """image_width: 640
image_height: 480
camera_name: left
camera_matrix:
  rows: 3
  cols: 3
  data: [500.5, 0, 320.25, 0, 501.0, 240.75, 0, 0, 1]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [0.1, -0.2, 0.001, 0.002, 0.05]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
"""


def test_read_camera_takes_opencv_and_ros_yaml(tmp_path):
    from slcvjax.observations.camera_files import read_camera

    cam = _camera()
    for fmt in ("opencv", "ros"):
        ex.export(_cal(sj.Rig.camera_only(cam)), fmt, tmp_path / f"{fmt}.yaml")
        back = read_camera(tmp_path / f"{fmt}.yaml")
        np.testing.assert_array_equal(np.asarray(back.params()), np.asarray(cam.params()))
        assert (back.width, back.height) == (640, 480)
    (tmp_path / "ros.yaml").write_text(ROS_YAML)  # as a ROS user holds it
    back = read_camera(tmp_path / "ros.yaml")
    np.testing.assert_array_equal(
        np.asarray(back.params()), [500.5, 501.0, 320.25, 240.75, 0.1, -0.2, 0.001, 0.002, 0.05]
    )
    four = ROS_YAML.replace(
        "cols: 5\n  data: [0.1, -0.2, 0.001, 0.002, 0.05]", "cols: 4\n  data: [0.1, -0.2, 0.001, 0.002]"
    )
    (tmp_path / "four.yaml").write_text(four)
    assert float(read_camera(tmp_path / "four.yaml").dist[4]) == 0.0
    bad = {
        "shape.yaml": (
            ROS_YAML.replace("rows: 3\n  cols: 3\n  data: [500.5", "rows: 2\n  cols: 3\n  data: [500.5").replace(
                ", 0, 0, 1]\ndistortion_model", "]\ndistortion_model"
            ),
            "camera_matrix: expected 3x3",
        ),  # fmt: skip
        "model.yaml": (ROS_YAML.replace("plumb_bob", "equidistant"), "distortion_model: 'equidistant'"),
        "nowidth.yaml": (ROS_YAML.replace("image_width: 640\n", ""), "image_width: missing"),
        "nan.yaml": (ROS_YAML.replace("0.002, 0.05]", "0.002, .nan]"), "distortion_coefficients[4]: not a finite"),
    }
    for name, (text, needle) in bad.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(sj.FormatError, match=re.escape(f"{name}: {needle}")):
            read_camera(tmp_path / name)


def test_calibrate_names_a_bad_camera_yaml(tmp_path, capsys):
    obs, _ = sj.simulate(sj.make_scene("paper", n_lasers=2, n_views=2), noise=0.0, seed=0)
    sj.write_observations(tmp_path / "obs.json", obs)
    (tmp_path / "cam.yaml").write_text(ROS_YAML.replace("image_width: 640\n", ""))
    argv = ["calibrate", str(tmp_path / "obs.json"), "--camera", str(tmp_path / "cam.yaml")]
    assert main([*argv, "--out", str(tmp_path / "cal.json")]) == 2
    assert "cam.yaml: image_width: missing" in capsys.readouterr().err


MEI_IMAGES = Path(__file__).resolve().parents[2] / "shared" / "data" / "mei_paracatadioptric"


@pytest.mark.slow
def test_a_real_omni_calibration_exports_to_every_format_and_reports(tmp_path, capsys):
    """``slcvjax omni`` on Mei's paracatadioptric images (a real central camera), then every
    export format and the HTML report.  The central approximations are fitted where the boards
    were seen: their reported RMS is what random pixels of that annulus, checked through the
    calibrated forward model, give, and it is sub-pixel (the camera is central; OpenCV omnidir
    fits its corners to 0.356 px)."""
    images = sorted(MEI_IMAGES.glob("img_para_*.png"))
    if len(images) < 10:
        pytest.skip(f"{MEI_IMAGES} absent")
    cal_path = tmp_path / "mei.json"
    args = ["omni", *map(str, images), "--board", "6x8", "--square", "42", "--out", str(cal_path), "--no-plot"]
    assert main([*args, "--projection", "perspective"]) == 0
    cal = sj.read_calibration(cal_path)
    rig = cal.rig
    apex = np.asarray(rig.mirror.apex)
    centre = np.array(
        [rig.camera.fx * apex[0] / apex[2] + rig.camera.cx, rig.camera.fy * apex[1] / apex[2] + rig.camera.cy]
    )
    seen = np.concatenate(
        [np.asarray(px, float) for v in cal.extra["problem"]["observations"]["views"] for px in v["boards"].values()]
    )
    radii = np.linalg.norm(seen - centre, axis=1)
    capsys.readouterr()
    for fmt in ex.FORMATS:
        out = tmp_path / f"{fmt}.txt"
        assert main(["export", str(cal_path), "--format", fmt, "--out", str(out)]) == 0, fmt
        text = capsys.readouterr().out
        assert out.exists() and f"wrote {out}" in text
    # the approximations over the observed annulus, checked independently
    px, pts = _through_mirror(rig, np.random.default_rng(2), ex.working_range(cal)[0], n=6000)
    r = np.linalg.norm(px - centre, axis=1)
    keep = (r >= radii.min()) & (r <= radii.max())
    px, pts = px[keep], pts[keep]
    fs = _read_fs(tmp_path / "opencv-omnidir.txt")
    k, d, xi = (fs.getNode(n).mat() for n in ("camera_matrix", "distortion_coefficients", "xi"))
    r_m, t_m = fs.getNode("R_cam_model").mat(), fs.getNode("t_cam_model_mm").mat().ravel()
    uv_mei = mei([k[0, 0], k[1, 1], k[0, 2], k[1, 2], xi[0, 0], *d.ravel()], (pts - t_m) @ r_m)
    m = read_ocamcalib(tmp_path / "ocamcalib.txt")
    r_o, t_o = _frame_of(m["comments"])
    uv_ocam = world2cam(m, (pts - t_o) @ r_o)
    for uv, rms in (
        (uv_mei, fs.getNode("central_approximation_rms_px").real()),
        (uv_ocam, _reported(" ".join(m["comments"]))[0]),
    ):
        err = np.sqrt(np.mean(np.sum((uv - px) ** 2, axis=1)))
        assert err == pytest.approx(rms, rel=0.25) and rms < 1.0, (err, rms)
    report = tmp_path / "report.html"
    assert main(["report", str(cal_path), "--images", str(MEI_IMAGES), "--out", str(report)]) == 0
    text = report.read_text()
    assert "(10 of 10 found)" in text  # views named by their image's file name are drawn over it
    assert f"the annulus {radii.min() - 0.05 * np.ptp(radii):.0f}-" in text  # the map covers the data
