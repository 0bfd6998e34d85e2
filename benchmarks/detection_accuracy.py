"""Detection from rendered images against the simulator's exact projections, per kind.

Run: ``python benchmarks/detection_accuracy.py [--noise 0,1] [--seed 0] [--out FILE]``.

The paper preset is rendered at each sensor noise level (grey levels) and detected.  Every
detected dot and spot is compared with the exact projection of the point its label names (the
board point, or the laser's spot): the per-axis RMS error, the largest error, and the points
labelled as another (over 1 px from their label's projection).  Dots and spots are compared
as detected (``raw``), corrected for the mirror's distortion of their image at the true rig
and poses (``corrected_truth``), and corrected at the calibration made from these images
(``corrected_calibration``, :func:`slcvjax.images.centroids.calibrate_detected` with
``correct_centroids=True``, as ``slcvjax calibrate`` does for detected images).  Rim pixels
are measured by their distance to the true rim curve (:func:`slcvjax.distance_to_rim`),
chessboard corners against their exact projections.  Completeness: detected over visible dots
and spots.
"""

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_forward import machine
from images_vs_file import corner_errors, preset_truth

from slcvjax import RenderOptions, calibrate_detected, detect_folder, distance_to_rim, render_scene
from slcvjax.images.centroids import corrected_observations, detection_sizes

MISLABEL_PX = 1.0


def point_errors(obs, exact) -> dict:
    """Dots and spots of ``obs`` against the exact pixels of their labels."""
    out = {}
    for kind in ("dots", "spots"):
        errs, wrong, n_true = [], 0, 0
        for vd, vt in zip(obs.views, exact.views, strict=True):
            if kind == "dots":
                n_true += sum(int(s.sum()) for _, s in vt.boards.values())
                found = []
                for b, (px, seen) in vd.boards.items():
                    tp, ts = vt.boards[b]
                    found += [px[i] - tp[i] if ts[i] else np.full(2, np.inf) for i in np.flatnonzero(seen)]
            else:
                n_true += len(vt.spots)
                ex = {s.laser: s.pixel for s in vt.spots}
                found = [np.asarray(s.pixel) - ex[s.laser] if s.laser in ex else np.full(2, np.inf) for s in vd.spots]
            for e in found:
                if np.linalg.norm(e) < MISLABEL_PX:
                    errs.append(e)
                else:
                    wrong += 1
        e = np.asarray(errs).reshape(-1, 2)
        out[kind] = {
            "rms_px": float(np.sqrt(np.mean(e**2))),
            "max_px": float(np.max(np.linalg.norm(e, axis=1))),
            "found": len(e) + wrong,
            "visible": n_true,
            "mislabelled": wrong,
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--noise", default="0,1", help="sensor noise levels, grey levels")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    scene, exact, truth, _ = preset_truth()
    levels = []
    for noise in (float(x) for x in args.noise.split(",")):
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            render_scene(scene, Path(tmp) / "images", RenderOptions(noise=noise, seed=args.seed))
            t_render = time.perf_counter() - t0
            detected, _ = detect_folder(Path(tmp) / "images")
        radii, sigma = detection_sizes(detected)
        at_truth, _ = corrected_observations(truth.rig, truth.board_poses, detected, radii, sigma)
        _, at_cal, notes = calibrate_detected(detected, correct_centroids=True)
        d = distance_to_rim(truth.rig, np.concatenate([v.rim for v in detected.views]))
        corners = corner_errors(detected, exact)
        row = {
            "image_noise_grey": noise,
            "render_s": t_render,
            "raw": point_errors(detected, exact),
            "corrected_truth": point_errors(at_truth, exact),
            "corrected_calibration": point_errors(at_cal, exact),
            "rim": {"rms_distance_px": float(np.sqrt(np.mean(d**2))), "median_distance_px": float(np.median(d))},
            "corners": {"rms_px": float(np.sqrt(np.mean(corners**2))), "n": len(corners)},
            "notes": notes,
        }
        levels.append(row)
        print(json.dumps(row, indent=1))
    out = {"machine": machine(), "seed": args.seed, "render_options": vars(RenderOptions()), "levels": levels}
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
