"""Real catadioptric cameras calibrated non-centrally from chessboards seen through the mirror.

Run: ``python benchmarks/real_omni.py [--data ../shared/data] [--out FILE]``.

Sets (third-party images' corners, read where the data folder has them; none is copied into
the project): OCamCalib's VMRImage and MiniOmni samples with the corners of its published fits
(method 1: pixel-level corners, method 2: sub-pixel), and Mei's paracatadioptric sample with
the corners ``slcvjax omni`` detects in its images (OpenCV's chessboard detector and corner
refiner, as OpenCV omnidir's reference run; the corner file that comes with the set disagrees
with the images in three views, see ``mei_corner_file_check`` in the JSON).  Each set is
calibrated as a user without a datasheet would: the central start (:mod:`slcvjax.calibration.central`: a
hyperboloid, vertex radius 20 mm as the scale's gauge), then the joint non-central fit of camera
(five distortion terms), mirror pose and board poses under the plain least-squares
loss (``loss="linear"``, every corner kept, as the published fits); the camera's projection
``auto``: a telecentric and a pinhole camera both fitted, the pinhole kept where an F-test of its
depth says the corners need it (``slcvjax.calibration.model_selection.perspective_test``).  Mei's set is also fitted as
what its name says, a paraboloid before a telecentric lens, and with ``mirror_shape.kind =
"auto"`` (the kind of the least 5-fold held-out error).

Reports per set and method:
- train RMS (``sqrt(mean |e|^2)`` over every corner) beside OCamCalib's published ``rms_px``,
  reproduced here from its model and extrinsics (``slcvjax.observations.published.ocam_project``);
- held-out RMS by leave-one-image-out cross-validation: the rig fitted (central start
  included; the projection the fit on every image chose) without the image, then camera and
  mirror held and only the image's board pose fitted; beside OCamCalib's model on the same
  images (which saw them all);
- how non-central the calibrated camera is: the reflected rays of the corners' pixels against
  the single point nearest to them all (the caustic's size: RMS and largest distance, mm of the
  gauge), and the camera's distance from that point;
- seconds per calibration.
For Mei's set the reference is OpenCV omnidir's train RMS 0.356 px (8 of 10 views, its own
corners; SOURCE.md).  A set none of the above was built on: the corners of OpenCV omnidir's
tutorial (``omni_calib_data.xml``: 15 views of a 6x9 grid of spacing 0.2 in a unit it does not
give), fitted with that unit taken as 100 mm (20 mm squares) and, to show what the unit does to
a fit whose scale's gauge is the mirror, as 10 and 1000 mm; beside the RMS 0.815 px that the
data's helper got from ``cv2.omnidir.calibrate`` (OpenCV 5.0.0, flags 0; not published).
Writes JSON naming the machine, each set with the commit it was measured at (``measured``);
``--sets mei`` (or ``ocam``, ``omnidir``) and ``--names VMRImage`` run
those groups and sets and keep the other entries of an existing ``--out`` file.
"""

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax
import numpy as np
from bench_forward import machine
from tqdm import tqdm

from slcvjax import (
    Observations,
    back_project,
    calibrate,
    held_out_rms,
    mei_observations,
    ocam_observations,
    ocam_residuals,
    omni_observations,
    omnidir_observations,
    report,
)

HERE = Path(__file__).resolve().parent
OCAM_SETS = {"VMRImage": "ocamcalib_vmrimage_catadioptric", "MiniOmni": "ocamcalib_miniomni_catadioptric"}
MEI_FOLDER, MEI_SIZE, MEI_OPENCV_RMS = "mei_paracatadioptric", (1280, 1024), 0.3564
MEI_OPENCV_VIEWS = (0, 1, 3, 4, 6, 7, 8, 9)  # the views OpenCV omnidir kept (SOURCE.md)
MEI_BOARD, MEI_SQUARE = (6, 8), 42.0  # inner corners, mm (SOURCE.md)
OMNIDIR_FILE = "opencv_contrib_omnidir_corners/omni_calib_data.xml"
OMNIDIR_HELPER_RMS = 0.8147  # cv2.omnidir.calibrate on that file, by the data's helper (SOURCE.md)
DEFAULT = ({"kind": "hyperboloid"}, "auto")  # the shape unknown: searched; the projection chosen (F-test)


def _rms_of(errs: list[np.ndarray]) -> float:
    e = np.concatenate(errs)
    return float(np.sqrt(np.mean(np.sum(e * e, axis=1))))


def fit(obs: Observations, model=DEFAULT):
    """The joint least-squares fit of ``obs`` from the central starts, ``model`` the mirror's
    shape and the camera's projection; (result, observations, seconds)."""
    t0 = time.perf_counter()
    obs = dataclasses.replace(obs, mirror_shape=dict(model[0]), camera_projection=model[1])
    res = calibrate(obs, loss="linear")
    return res, obs, time.perf_counter() - t0


def caustic(res, obs: Observations) -> dict:
    """The reflected rays of every corner's pixel against the point nearest to them all."""
    uv = np.concatenate([px[s] for v in obs.views for px, s in v.boards.values()])
    rays = jax.vmap(lambda p: back_project(res.rig.camera, res.rig.mirror, p))(uv)
    ok = np.asarray(rays.valid)
    p, d = np.asarray(rays.point)[ok], np.asarray(rays.direction)[ok]
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    c = np.linalg.solve(proj.sum(0), np.einsum("nij,nj->i", proj, p))
    dist = np.linalg.norm(np.einsum("nij,nj->ni", proj, c - p), axis=1)
    return {
        "rays": int(ok.sum()),
        "rms_mm": float(np.sqrt(np.mean(dist**2))),
        "max_mm": float(dist.max()),
        "camera_to_viewpoint_mm": float(np.linalg.norm(c)),
        "vertex_radius_mm": 1.0 / float(res.rig.mirror.curvature),
    }


def _group(key: str) -> str:
    if key.startswith("Mei"):
        return "mei"
    if key.startswith("omnidir"):
        return "omnidir"
    return "ocam"


def corner_file_check(path: Path, detected: Observations) -> dict:
    """Per image, the corner file's corners against the detected ones (nearest, px): median and largest."""
    if not path.exists():
        return {}
    ref = mei_observations(path, MEI_SIZE)
    out = {}
    for v_ref, v in zip(ref.views, detected.views, strict=True):
        (px_ref, _), (px, _) = next(iter(v_ref.boards.values())), v.boards["chess"]
        d = np.linalg.norm(px_ref[:, None] - px[None], axis=2).min(axis=1)
        out[v.name] = {"median_px": float(np.median(d)), "max_px": float(d.max())}
    return out


def run_set(name: str, obs: Observations, reference: dict, cv: bool, model=DEFAULT) -> dict:
    res, obs_s, secs = fit(obs, model)
    start = next(r for r in res.staged.reports if r.name == "central_start")
    rep = report(res, obs_s)["residuals"]
    m = res.rig.mirror
    out = {
        "images": len(obs.views),
        "corners": sum(int(s.sum()) for v in obs.views for _, s in v.boards.values()),
        "train_rms_px": float(rep["rms_px"]),
        "train_invalid": int(rep["invalid"]),
        # the last pass converged, each before it converged or ran to its scheduled limit
        "converged": res.converged and all(p.finished for p in res.passes),
        "passes": [[p.name, p.steps, p.result] for p in res.passes],
        "seconds": secs,
        "model": {
            "mirror_shape": model[0],
            "camera_projection": model[1],
            "fitted_kind": res.rig.mirror.kind,
            "fitted_projection": res.rig.camera.projection,
        },
        "start": {"rms_px": start.rms, "notes": start.notes},
        "stages": [{"name": r.name, "rms": r.rms, "unit": r.unit, "notes": r.notes} for r in res.staged.reports],
        "camera": [float(x) for x in np.asarray(res.rig.camera.params())],
        "mirror": {"apex": np.asarray(m.apex).tolist(), "axis": np.asarray(m.axis).tolist(), "conic": float(m.conic)},
        "caustic": caustic(res, obs_s),
        "reference": reference,
    }
    if cv:
        errs, per_image = [], {}
        for k in tqdm(range(len(obs.views)), desc=f"{name} leave-one-out", leave=False):
            train = dataclasses.replace(obs, views=obs.views[:k] + obs.views[k + 1 :])
            held = dataclasses.replace(obs, views=[obs.views[k]])
            r_k = fit(train, (model[0], res.rig.camera.projection))[0]
            rms_k, n_k, bad_k = held_out_rms(r_k.rig, held)
            per_image[obs.views[k].name] = {"rms_px": rms_k, "corners": n_k, "invalid": bad_k}
            errs.append((rms_k, n_k))
        total = sum(n for _, n in errs)
        out["held_out_rms_px"] = float(np.sqrt(sum(r * r * n for r, n in errs) / total))
        out["held_out_invalid"] = sum(v["invalid"] for v in per_image.values())
        out["held_out_per_image"] = per_image
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(HERE.parent.parent / "shared" / "data"))
    ap.add_argument("--methods", default="1,2", help="OCamCalib methods whose corners are fitted")
    ap.add_argument("--cv-methods", default="1,2", help="those also cross-validated")
    ap.add_argument(
        "--sets",
        default="ocam,mei,omnidir",
        help="groups: ocam (VMRImage, MiniOmni), mei, omnidir",
    )
    ap.add_argument("--names", default=",".join(OCAM_SETS), help="the OCamCalib sets of the ocam groups")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    data = Path(args.data)
    out = {"machine": machine(), "data": str(data), "sets": {}}
    rows = []
    groups = set(args.sets.split(","))
    names = [n for n in args.names.split(",") if n in OCAM_SETS]
    for name in names if "ocam" in groups else []:
        path = data / OCAM_SETS[name] / f"{name}_reference.json"
        if not path.exists():
            print(f"{name}: {path} absent, skipped")
            continue
        for method in args.methods.split(","):
            obs, rec = ocam_observations(path, method)
            own = ocam_residuals(path, method)
            ref = {
                "ocamcalib_rms_px_published": float(rec["rms_px"]),
                "ocamcalib_rms_px_reproduced": _rms_of(list(own.values())),
                "ocamcalib_per_image_rms_px": {k: _rms_of([v]) for k, v in own.items()},
            }
            key = f"{name} (OCamCalib method {method})"
            cv = method in args.cv_methods.split(",")
            out["sets"][key] = r = run_set(key, obs, ref, cv)
            rows.append((key, r, ref["ocamcalib_rms_px_reproduced"], ref["ocamcalib_rms_px_reproduced"]))
    folder = data / MEI_FOLDER
    images = sorted(folder.glob("img_para_*.png"))
    if "mei" in groups and images:
        obs, missing = omni_observations(images, MEI_BOARD, MEI_SQUARE, {"kind": "hyperboloid"})
        if missing or len(obs.views) != len(images):
            raise SystemExit(f"{folder}: no board found in {missing}")
        out["mei_corner_file_check"] = corner_file_check(folder / "img_para_corners_calibDataMEI.json", obs)
        ref = {"opencv_omnidir_rms_px": MEI_OPENCV_RMS, "note": "OpenCV omnidir, 8 of 10 views, its own corners"}
        kept = dataclasses.replace(obs, views=[obs.views[i] for i in MEI_OPENCV_VIEWS])
        para = ({"kind": "paraboloid"}, "telecentric")
        auto = ({"kind": "auto"}, "telecentric")
        runs = (
            ("Mei para (OpenCV's 8 views)", kept, True, DEFAULT),
            ("Mei para, telecentric paraboloid (8 views)", kept, True, para),
            ("Mei para, telecentric auto (8 views)", kept, False, auto),
            ("Mei para (all 10 views)", obs, False, DEFAULT),
            ("Mei para, telecentric paraboloid (all 10)", obs, False, para),
        )
        for key, o, cv, model in runs:
            out["sets"][key] = r = run_set(key, o, ref, cv, model)
            rows.append((key, r, MEI_OPENCV_RMS, None))
    path = data / OMNIDIR_FILE
    if "omnidir" in groups and path.exists():
        ref = {
            "opencv_omnidir_rms_px_helper_run": OMNIDIR_HELPER_RMS,
            "note": "cv2.omnidir.calibrate (OpenCV 5.0.0, flags 0) by the data's helper; not a published value",
        }
        for unit, cv in ((100.0, True), (10.0, False), (1000.0, False)):
            key = f"omnidir tutorial ({2 * unit / 10:g} mm squares)"
            out["sets"][key] = r = run_set(key, omnidir_observations(path, unit_mm=unit), ref, cv)
            rows.append((key, r, OMNIDIR_HELPER_RMS, None))
    import subprocess

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=HERE).stdout
    dirty = subprocess.run(["git", "status", "--porcelain", "slcvjax"], capture_output=True, text=True, cwd=HERE).stdout
    stamp = {"commit": commit.strip() + ("+changes" if dirty.strip() else ""), "date": time.strftime("%Y-%m-%d")}
    out["runs"] = {g: stamp for g in groups}
    for r in out["sets"].values():
        r["measured"] = stamp
    if args.out and Path(args.out).exists():  # the sets not run keep their entries (and their stamps)
        old = json.loads(Path(args.out).read_text())
        for k, r in old.get("sets", {}).items():
            r.setdefault("measured", old.get("runs", {}).get(_group(k)))
        out["runs"] = old.get("runs", {}) | out["runs"]
        out["sets"] = old.get("sets", {}) | out["sets"]
        if "mei" not in groups and "mei_corner_file_check" in old:
            out["mei_corner_file_check"] = old["mei_corner_file_check"]
    print(f"\n{'set':34s} {'train':>7s} {'ref':>7s} {'held-out':>9s} {'ref':>7s} {'caustic':>8s} {'s/fit':>6s}")
    for key, r, ref_train, ref_held in rows:
        held = f"{r['held_out_rms_px']:9.3f}" if "held_out_rms_px" in r else f"{'-':>9s}"
        rh = f"{ref_held:7.3f}" if ref_held is not None and "held_out_rms_px" in r else f"{'-':>7s}"
        print(
            f"{key:34s} {r['train_rms_px']:7.3f} {ref_train:7.3f} {held} {rh} "
            f"{r['caustic']['rms_mm']:6.2f}mm {r['seconds']:6.1f}"
        )
    if args.out:
        Path(args.out).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
