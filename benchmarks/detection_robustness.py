"""The detector on images it was not tuned to: an independent tracer's held-out rigs and widely varied renders.

Run: ``python benchmarks/detection_robustness.py [--views 8] [--scenes a,b] [--baseline REV] [--out FILE]``.

Two rendering paths.  ``tests/_tracer.py`` is a NumPy ray tracer written apart from the project's
renderer (:mod:`slcvjax.images.render`): the held-out rig (800x600, a 22 x 13 mm cone, 8 lasers,
4x3 dot grids at 18 mm pitch with 2.5 mm dots on the light walls of a 170 mm closed box,
saturated spots, the sensor moved +-35 mm, 1 grey level of noise) and variations of it (larger
dots at a finer pitch, a dim scene with unsaturated spots, the box's corners open, small dots
under uneven light).  ``slcvjax simulate --render``'s renderer draws the paper preset's box with
render options far from its defaults.  Every folder is detected (:func:`slcvjax.detect_folder`)
by the current detector and by a named baseline (``slcvjax/images/detect.py`` at ``--baseline``,
default the branch's fork point from ``main``), in the same run.

Measured against the truth (the exact projections of the library's geometry): per view, the
rim found (at least a quarter of its sectors, RMS distance to the true rim under 0.5 px); the
fraction of the visible dots (the dot's whole disc in the mirror's view) placed on the grid;
dots placed on a wrong grid position (nearer another dot's true pixel than their own's, or over
3 px from it: must be 0); spots found with the right laser, and mislabelled (over 2 px from
their laser's true spot); lasers never found.  Writes JSON naming the machine and versions.
"""

import argparse
import json
import platform
import subprocess
import sys
import tempfile
import time
import types
from dataclasses import replace
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

from _tracer import HeldOutRig, goals, measure, render_folder  # noqa: E402

from slcvjax import RenderOptions, detect_folder, render_scene  # noqa: E402
from slcvjax.geometry.mirror import back_project, body_clearance  # noqa: E402
from slcvjax.geometry.rig import project_board_points  # noqa: E402
from slcvjax.observations.simulate import (  # noqa: E402
    PAPER_ROTATION_DEG,
    PAPER_TRANSLATION_MM,
    box_scene,
    paper_rig,
    simulate,
)

HELD_OUT = {
    "heldout": HeldOutRig(),
    "big_dots_fine_pitch": HeldOutRig(dot_radius_mm=2.0, pitch_mm=14.0, seed=1),
    "dim_unsaturated": HeldOutRig(wall=0.33, dot=0.04, surround=0.03, spot_peak=0.45, seed=2),
    "open_corners": HeldOutRig(open_corner_mm=14.0, seed=3),
    "small_dots_uneven": HeldOutRig(dot_radius_mm=0.9, shading=0.25, blur_px=0.8, seed=4),
}
RENDERED = {
    "render_default": RenderOptions(noise=1.0),
    "render_small_dim": RenderOptions(noise=1.0, dot_radius_mm=1.0, spot_power=0.35, exposure=0.55, blur=1.0, seed=1),
    "render_big_bright": RenderOptions(noise=1.0, dot_radius_mm=2.4, spot_power=3.0, exposure=1.3, blur=0.4, seed=2),
}


def machine() -> dict:
    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": __import__("os").cpu_count(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "numpy": np.__version__,
        "opencv": cv2.__version__,
        "commit": _git("rev-parse", "HEAD"),
        "dirty": bool(_git("status", "--porcelain", "--", "slcvjax")),
    }


def _git(*args) -> str:
    return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True).stdout.strip()


def baseline_detector(rev: str):
    """``slcvjax/images/detect.py`` as of ``rev``, loaded as a module of the current package."""
    src = _git("show", f"{rev}:slcvjax/images/detect.py")
    if not src:
        raise SystemExit(f"no slcvjax/images/detect.py at {rev!r}")
    mod = types.ModuleType("slcvjax.images._detect_baseline")
    mod.__package__ = "slcvjax.images"
    mod.__file__ = f"<{rev}:slcvjax/images/detect.py>"
    sys.modules[mod.__name__] = mod
    exec(compile(src, mod.__file__, "exec"), mod.__dict__)
    return mod.detect_folder


# ------------------------------------------------------------------ truth of the renderer's scenes


def _render_truth(scene, opts: RenderOptions) -> dict:
    """The project's renderer's scene as the tracer's truth: dots visible whole (centre and 12
    edge points project into the image and their rays miss the sensor's body), visible spots."""
    exact, _ = simulate(scene)
    rig = scene.rig
    w, h = rig.camera.width, rig.camera.height
    edge = np.array([[np.cos(a), np.sin(a), 0.0] for a in np.linspace(0, 2 * np.pi, 12, endpoint=False)])
    bp = jax.jit(jax.vmap(lambda uv: back_project(rig.camera, rig.mirror, uv)))
    views = []
    for i, vt in enumerate(exact.views):
        dots = {}
        for b, (uv, _) in vt.boards.items():
            pts = np.asarray(scene.boards[b])
            ring = (pts[:, None, :] + opts.dot_radius_mm * edge[None]).reshape(-1, 3)
            allp = np.concatenate([pts, ring])
            puv, pok = (np.array(a) for a in project_board_points(rig, scene.box_poses[i][b], jnp.asarray(allp)))
            pok &= np.all((puv > 1) & (puv < np.array([w, h]) - 2), 1)
            ray = bp(jnp.asarray(np.where(pok[:, None], puv, [w / 2, h / 2])))
            clear = np.asarray(
                jax.vmap(lambda o, d: body_clearance(o, d, rig.mirror, opts.body_radius_mm, opts.body_gap_mm))(
                    ray.point, ray.direction
                )
            )
            pok &= np.asarray(ray.valid) & (clear > 0)
            m = len(pts)
            dots[b] = (np.asarray(uv), pok[:m] & pok[m:].reshape(m, -1).all(1))
        spots = [{"laser": s.laser, "pixel": np.asarray(s.pixel), "board": s.board} for s in vt.spots]
        views.append({"dots": dots, "spots": spots})
    return {"views": views, "rig": rig}


def render_paper(folder: Path, opts: RenderOptions, n_views: int, seed: int) -> dict:
    rng = np.random.default_rng(100 + seed)
    rot, tra = np.asarray(PAPER_ROTATION_DEG), np.asarray(PAPER_TRANSLATION_MM)
    views = np.concatenate([np.radians(rng.uniform(-rot, rot, (n_views, 3))), rng.uniform(-tra, tra, (n_views, 3))], 1)
    scene = box_scene(paper_rig(), views, n_chess_views=2)
    render_scene(scene, folder, opts)
    return _render_truth(scene, opts)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--scenes", default=",".join([*HELD_OUT, *RENDERED]))
    ap.add_argument("--baseline", default=None, help="git revision of the baseline detector (default: fork from main)")
    ap.add_argument("--no-baseline", action="store_true")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "detection_robustness.json"))
    args = ap.parse_args()
    rev = args.baseline or _git("merge-base", "HEAD", "main") or "HEAD"
    detectors = {"current": detect_folder}
    if not args.no_baseline:
        detectors["baseline"] = baseline_detector(rev)
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.scenes.split(","):
            folder = Path(tmp) / name
            t0 = time.perf_counter()
            if name in HELD_OUT:
                rig = replace(HELD_OUT[name], n_views=args.views, n_chess=2)
                truth = render_folder(rig, folder)
                kind = "tracer"
            else:
                truth = render_paper(folder, RENDERED[name], args.views, seed=list(RENDERED).index(name))
                kind = "render"
            t_render = time.perf_counter() - t0
            results[name] = {"path": kind, "render_s": round(t_render, 1)}
            for label, det in detectors.items():
                t0 = time.perf_counter()
                obs, report = det(folder)
                m = measure(obs, report, truth)
                m["detect_s"] = round(time.perf_counter() - t0, 1)
                m["goals"] = goals(m)
                results[name][label] = m
                print(
                    f"{name:22s} {label:8s} rim {m['rim_found_views']}/{m['views']}  dots "
                    f"{m['dots_placed']}/{m['dots_visible']} ({100 * m['dots_placed_fraction']:.0f} %) "
                    f"wrong {m['dots_wrong_position']}  spots {m['spots_found_right']}/{m['spots_visible']} "
                    f"mislabelled {m['spots_mislabelled']}  lasers lost {m['lasers_never_found']}  "
                    f"chess {m['chessboard_views_found']}/2  ({m['detect_s']} s)",
                    flush=True,
                )
    doc = {
        "benchmark": "detection_robustness",
        "command": " ".join(["python", *sys.argv]),
        "machine": machine(),
        "baseline_revision": None if args.no_baseline else rev,
        "scenes": {
            **{
                k: {"path": "tracer", **{f: v for f, v in vars(r).items() if f != "extra"}} for k, r in HELD_OUT.items()
            },
            **{k: {"path": "render", **vars(o)} for k, o in RENDERED.items()},
        },
        "results": results,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=1, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
