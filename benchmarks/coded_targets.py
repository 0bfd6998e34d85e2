"""ChArUco corners detected through the mirror against their exact projections.

Run: ``python benchmarks/coded_targets.py [--views 6] [--noise 0,1] [--seed 3] [--out FILE]``.

A rig unlike the paper preset's: an 800 x 600 camera (fx 640 px, milder distortion), a cone of
radius 25 mm and height 12 mm 47 mm in front of the lens, six point lasers.  Its box is
:func:`slcvjax.images.targetbox.box_setup`'s for that rig (``slcvjax setup init``'s placement:
four walls 140 mm from the axis, each board centred where the mirror sees its wall), each wall a
ChArUco board of 6 x 3 squares of 24 mm with 18 mm DICT_4X4_250 markers (ids continuing from wall
to wall).  The sensor takes ``--views`` poses drawn in the paper preset's motion range (seeded).
Each view is rendered (:mod:`slcvjax.images.render`, default options: 3 x 3 samples per pixel,
edges refined, blur 0.6 px) noise-free and with Gaussian sensor noise of 1 grey level (sigma
1/255 of full scale), and detected by ``slcvjax detect``'s path (:func:`slcvjax.detect_folder`,
whose coded walls go to :mod:`slcvjax.images.coded`).

A corner is *visible* (:func:`slcvjax.images.coded_box.visible_corners`) where it and the centres
of its four squares project through the mirror into the image and are seen there (the pixel's
reflected ray, traced back, reaches this board first: not the sensor's body, not another wall).
Visibility says nothing of resolution: near the apex the mirror squeezes a square's width to a
few pixels, and the white margin between a marker and its square's edge (3 mm here) to under a
pixel.  So the found fraction is also given by that margin's width in the image (``margin_px``:
the smaller of its two widths along the board's axes at the corner, from the exact projection's
derivative).

Figures: found / visible; corners labelled as another point (over 1 px from the exact pixel of
the point their label names); the per-axis RMS, 95th percentile and largest error of the found
corners (mislabels excluded, and counted), also per margin width; found corners that are not
visible; seconds per image for the detection.
"""

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from slcvjax import RenderOptions, detect_folder, render_scene
from slcvjax.geometry.camera import Camera
from slcvjax.geometry.mirror import ConeMirror
from slcvjax.geometry.rig import Rig, project_board_points
from slcvjax.images.coded_box import coded_box_scene, visible_corners
from slcvjax.observations.simulate import PAPER_ROTATION_DEG, PAPER_TRANSLATION_MM, paper_rig

MISLABEL_PX = 1.0
BOARD = {"squares": (6, 3), "square_mm": 24.0, "marker_mm": 18.0}
MARGIN_BINS = (0.0, 1.0, 2.0, np.inf)


def bench_rig() -> Rig:
    cam = Camera.create(640.0, 641.0, 403.5, 296.0, [-0.12, 0.03, 0.0006, -0.0004, 0.0], 800, 600)
    mirror = ConeMirror.create([0.4, -0.3, 47.0], [0.012, -0.01, 1.0], 25.0, 12.0)
    return Rig(cam, mirror, paper_rig(6).lasers)


def views(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rot, tra = np.asarray(PAPER_ROTATION_DEG), np.asarray(PAPER_TRANSLATION_MM)
    out = np.zeros((n, 6))
    for i in range(n):
        out[i, :3] = np.radians(rng.uniform(-rot, rot))
        out[i, 3:] = rng.uniform(-tra, tra)
    return out


def margin_px(scene, view: int, board: str) -> np.ndarray:
    """Per corner, the image width (px) of the white margin between a marker and its square's edge,
    the smaller along the board's two axes (the exact projection's derivative, central differences)."""
    spec = scene.board_types[board]
    margin = (spec["square_mm"] - spec["marker_mm"]) / 2
    pts = scene.boards[board]
    pose = scene.box_poses[view][board]
    widths = []
    for axis in (0, 1):
        d = np.zeros(3)
        d[axis] = 0.25
        a, _ = project_board_points(scene.rig, pose, jnp.asarray(pts + d))
        b, _ = project_board_points(scene.rig, pose, jnp.asarray(pts - d))
        widths.append(np.linalg.norm(np.asarray(a) - np.asarray(b), axis=1) / 0.5 * margin)
    return np.minimum(*widths)


def measure(scene, obs, opts) -> dict:
    errs, bin_of, wrong, n_vis, n_found_vis, n_found_unvis = [], [], 0, 0, 0, 0
    bins = np.zeros((len(MARGIN_BINS) - 1, 2), int)  # visible, found
    for v, view in enumerate(obs.views):
        truth = visible_corners(scene, v, opts)
        for b, (uv, vis) in truth.items():
            px, seen = view.boards[b]
            e = px - uv
            bad = seen & (np.linalg.norm(e, axis=1) > MISLABEL_PX)
            wrong += int(bad.sum())
            good = seen & ~bad
            errs.append(e[good])
            n_vis += int(vis.sum())
            k = np.digitize(margin_px(scene, v, b), MARGIN_BINS) - 1
            bin_of.append(k[good])
            n_found_vis += int((good & vis).sum())
            n_found_unvis += int((good & ~vis).sum())
            for i in range(len(bins)):
                bins[i, 0] += int((vis & (k == i)).sum())
                bins[i, 1] += int((good & vis & (k == i)).sum())
    e = np.concatenate(errs)
    kb = np.concatenate(bin_of)
    n = np.linalg.norm(e, axis=1)
    by_margin = {
        f"{MARGIN_BINS[i]:g}-{MARGIN_BINS[i + 1]:g} px": {
            "visible": int(bins[i, 0]),
            "found": int(bins[i, 1]),
            "fraction": float(bins[i, 1] / bins[i, 0]) if bins[i, 0] else None,
            "rms_px": np.sqrt((e[kb == i] ** 2).mean(axis=0)).tolist() if np.any(kb == i) else None,
        }
        for i in range(len(bins))
    }
    return {
        "visible": n_vis,
        "found_visible": n_found_vis,
        "found_fraction": n_found_vis / max(n_vis, 1),
        "found_not_visible": n_found_unvis,
        "mislabelled": wrong,
        "rms_px": np.sqrt((e**2).mean(axis=0)).tolist() if len(e) else None,
        "p95_px": float(np.percentile(n, 95)) if len(n) else None,
        "max_px": float(n.max()) if len(n) else None,
        "found_by_margin_px": by_margin,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--noise", default="0,1", help="sensor noise levels, grey levels (comma-separated)")
    ap.add_argument("--seed", type=int, default=3, help="seed of the sensor's poses")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "coded_targets.json"))
    args = ap.parse_args()
    scene = coded_box_scene(bench_rig(), views(args.views, args.seed), **BOARD)
    levels = {}
    for noise in (float(x) for x in args.noise.split(",")):
        opts = RenderOptions(noise=noise, seed=args.seed)
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            render_scene(scene, tmp, opts)
            t_render = time.perf_counter() - t0
            t0 = time.perf_counter()
            obs, _ = detect_folder(tmp)
            t_detect = time.perf_counter() - t0
        res = measure(scene, obs, opts)
        res.update(render_s=t_render, detect_s_per_image=t_detect / len(obs.views))
        levels[f"{noise:g}"] = res
        rms = res["rms_px"] or [float("nan")] * 2
        print(
            f"noise {noise:g} grey levels: found {res['found_visible']} of {res['visible']} visible corners "
            f"({100 * res['found_fraction']:.1f} %), mislabelled {res['mislabelled']}, RMS u {rms[0]:.4f} "
            f"v {rms[1]:.4f} px, p95 {res['p95_px']:.3f}, max {res['max_px']:.3f} px; "
            f"detection {res['detect_s_per_image']:.2f} s/image"
        )
        for k, v in res["found_by_margin_px"].items():
            r = v["rms_px"]
            rms_txt = f", RMS u {r[0]:.4f} v {r[1]:.4f} px" if r else ""
            print(f"   margin {k}: found {v['found']} of {v['visible']}{rms_txt}")
    out = {
        "machine": {
            "platform": platform.platform(),
            "cpu": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(),
            "python": sys.version.split()[0],
            "numpy": np.__version__,
            "opencv": cv2.__version__,
            "jax": jax.__version__,
        },
        "rig": {"image": [800, 600], "fx_px": 640.0, "cone_radius_mm": 25.0, "cone_height_mm": 12.0, "lasers": 6},
        "board": {**BOARD, "dictionary": "DICT_4X4_250", "walls": 4, "box_width_mm": 280.0},
        "views": args.views,
        "seed": args.seed,
        "goals": {"found_fraction": ">= 0.85", "mislabelled": 0, "rms_px_noise_free": "<= 0.03 per axis"},
        "levels": levels,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
