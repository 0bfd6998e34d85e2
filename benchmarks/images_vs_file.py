"""Calibration from rendered images against calibration from observation files at matched noise.

Run: ``python benchmarks/images_vs_file.py [--seeds 6] [--image-noise 1.0] [--out FILE]``.

For each seed the paper preset is rendered with sensor noise (``--image-noise`` grey levels,
the seed's own noise), detected and calibrated from the centroids as detected ("images", as
``slcvjax calibrate --raw-centroids`` does: the targets the detector left out placed by the
box's other walls, :func:`slcvjax.images.centroids.calibrate_detected`).  The detection's errors are
measured against the simulator's exact projections: sigma of the dots and spots, of the rim
pixels (their distance to the true rim curve) and of the chessboard corners.  The same
detection calibrated again from its centroids corrected for the mirror's distortion of each
dot's and spot's image at that calibration (``corrected``) and two calibrations from files at
that noise go beside it:

* ``file``: the exact observation file (every visible dot, 360 rim points per view) with
  Gaussian noise of the detection's sigma per kind (dots, spots, rim, corners);
* ``subset``: the detected observations themselves, each pixel replaced by its exact
  projection plus Gaussian noise of the same sigma (same points and labels as the images;
  only the detection's error is exchanged for white noise).

Reports the lasers' RMS position and direction errors against the truth for each, over the
seeds, and their ratios.  ``images / subset`` near 1 means the detector's errors cost no
more than white noise of their size; ``images / file`` adds what the detector leaves out.
"""

import argparse
import json
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import jax.numpy as jnp
import numpy as np
from bench_forward import machine
from tqdm import tqdm

from slcvjax import (
    RenderOptions,
    SpotObs,
    ViewObs,
    calibrate,
    calibrate_detected,
    cramer_rao,
    detect_folder,
    distance_to_rim,
    laser_errors,
    make_scene,
    project_rim,
    render_scene,
    simulate,
)


def _nearest(points: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each point its nearest reference point and the distance."""
    d = np.linalg.norm(points[:, None, :] - ref[None, :, :], axis=2)
    j = np.argmin(d, axis=1)
    return ref[j], d[np.arange(len(points)), j]


def preset_truth():
    """The paper preset's scene, its exact observations and truth, and its true rim curve (pixels)."""
    scene = make_scene("paper")
    exact, truth = simulate(scene)
    curve, ok = project_rim(truth.rig, jnp.linspace(0, 2 * np.pi, 7200, endpoint=False))
    return scene, exact, truth, np.asarray(curve)[np.asarray(ok)]


def corner_errors(obs, exact) -> np.ndarray:
    """(n, 2) detected chessboard corners minus their exact pixels (the board's 180 degree twin
    taken where the detector numbered the corners from the other end)."""
    out = []
    for cd, ct in zip(obs.calibration_views, exact.calibration_views, strict=True):
        if cd.seen.any():
            e1, e2 = cd.pixels - ct.pixels, cd.pixels[::-1] - ct.pixels
            out.append(e1 if np.abs(e1).mean() < np.abs(e2).mean() else e2)
    return np.concatenate(out).reshape(-1, 2)


def detection_errors(obs, exact, truth):
    """Per kind the detection's sigma (per axis): dots, spots, rim (distance to the true curve), corners."""
    dots, spots, corners = [], [], []
    for vd, vt in zip(obs.views, exact.views, strict=True):
        ref = np.concatenate([px[s] for px, s in vt.boards.values()])
        for px, seen in vd.boards.values():
            if seen.any():
                q, _ = _nearest(px[seen], ref)
                dots.append(px[seen] - q)
        exact_spots = {s.laser: s.pixel for s in vt.spots}
        spots.extend([(s.pixel - exact_spots[s.laser])[None] for s in vd.spots if s.laser in exact_spots])
    corners = [corner_errors(obs, exact)]
    dots, spots, corners = (np.concatenate(x) for x in (dots, spots, corners))
    rim = distance_to_rim(truth.rig, np.concatenate([v.rim for v in obs.views]))

    def rms(e):  # mislabelled points (a row shift) are not noise
        return float(np.sqrt(np.mean(e[np.linalg.norm(e, axis=1) < 1.0] ** 2)))

    sig = {
        "dots_px": rms(dots),
        "spots_px": rms(spots),
        # the distance to the curve; a few rim pixels are pulled off by a nearby dot: median-based
        "rim_px": float(np.median(rim) / 0.6744897501960817),
        "rim_rms_px": float(np.sqrt(np.mean(rim**2))),
        "corners_px": float(np.sqrt(np.mean(corners**2))),
    }
    return sig


def subset_with_white_noise(obs, exact, rim_curve, sig, rng):
    """The detected observations with each pixel replaced by its exact projection plus white noise."""
    views = []
    for vd, vt in zip(obs.views, exact.views, strict=True):
        ref = np.concatenate([px[s] for px, s in vt.boards.values()])
        boards = {}
        for b, (px, seen) in vd.boards.items():
            new = px.copy()
            if seen.any():
                q, _ = _nearest(px[seen], ref)
                new[seen] = q + rng.normal(0, sig["dots_px"], q.shape)
            boards[b] = (new, seen)
        exact_spots = {s.laser: s.pixel for s in vt.spots}
        spots = [
            SpotObs(s.laser, s.board, exact_spots[s.laser] + rng.normal(0, sig["spots_px"], 2))
            for s in vd.spots
            if s.laser in exact_spots
        ]
        q, _ = _nearest(vd.rim, rim_curve)
        normal = q - np.mean(rim_curve, axis=0)
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        rim = q + normal * rng.normal(0, sig["rim_px"], (len(q), 1))
        views.append(ViewObs(vd.name, boards, spots, rim))
    cal = [
        replace(ct, pixels=ct.pixels + rng.normal(0, sig["corners_px"], ct.pixels.shape))
        for ct in exact.calibration_views
    ]
    return replace(obs, views=views, calibration_views=cal)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=6)
    ap.add_argument("--image-noise", type=float, default=1.0)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    scene, exact, truth, rim_curve = preset_truth()
    errs = {k: ([], []) for k in ("images", "corrected", "subset", "file")}
    rows = []
    t_render = []
    for seed in tqdm(range(args.seeds), desc="seeds"):
        rng = np.random.default_rng(1000 + seed)
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            render_scene(scene, Path(tmp) / "images", RenderOptions(noise=args.image_noise, seed=seed))
            t_render.append(time.perf_counter() - t0)
            detected, _ = detect_folder(Path(tmp) / "images")
        # as the CLI calibrates: the targets the detector left out placed by the box's other walls
        first, obs, _ = calibrate_detected(detected, correct_centroids=False)
        sig = detection_errors(obs, exact, truth)
        cases = {
            "images": obs,
            "corrected": obs,  # the same, calibrated again from centroids corrected at that calibration
            "subset": subset_with_white_noise(obs, exact, rim_curve, sig, rng),
            "file": subset_with_white_noise(exact, exact, rim_curve, sig, rng),  # every exact pixel, noised
        }
        x_ref = cramer_rao(truth, exact, 1.0)["x_ref"]
        row = {"seed": seed, "detection_sigma": sig}
        for name, o in cases.items():
            if name == "images":
                res = first
            elif name == "corrected":
                res = calibrate_detected(detected, correct_centroids=True)[0]
            else:
                res = calibrate(o)
            p, a = laser_errors(res.rig, truth.rig, x_ref)
            errs[name][0].append(p)
            errs[name][1].append(a)
            row[name] = {
                "position_rms_mm": float(np.sqrt(np.mean(p**2))),
                "direction_rms_deg": float(np.degrees(np.sqrt(np.mean(a**2)))),
                "passes": [q.result for q in res.passes],
            }
        rows.append(row)
        tqdm.write(json.dumps(row))

    def rms(x):
        return float(np.sqrt(np.mean(np.square(np.concatenate(x)))))

    summary = {
        k: {"position_rms_mm": rms(v[0]), "direction_rms_deg": float(np.degrees(rms(v[1])))} for k, v in errs.items()
    }
    ratios = {
        f"{a}/{b}": {
            "position": summary[a]["position_rms_mm"] / summary[b]["position_rms_mm"],
            "direction": summary[a]["direction_rms_deg"] / summary[b]["direction_rms_deg"],
        }
        for a in ("images", "corrected")
        for b in ("subset", "file")
    }
    out = {
        "machine": machine(),
        "image_noise_grey": args.image_noise,
        "seeds": args.seeds,
        "render_s_per_seed": float(np.mean(t_render)),
        "summary": summary,
        "ratios": ratios,
        "per_seed": rows,
    }
    print(json.dumps({k: out[k] for k in ("summary", "ratios")}, indent=1))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
