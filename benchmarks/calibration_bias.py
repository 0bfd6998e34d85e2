"""Does the calibration's reported std hold over many calibrations?  Camera, mirror and the pipe's diameter.

Run: ``python benchmarks/calibration_bias.py [--seeds 40] [--noise 0.5,0.1] [--rigid] [--out FILE]
[--cluster auto|local:N|ray://HOST:PORT] [--chunks DIR]``: the calibrations in chunks
(``slcvjax.run_chunks``), here or on a Ray cluster, with the same numbers; ``--chunks`` keeps each
finished chunk there and resumes from it.

The paper preset's box is simulated at each ``--noise`` level for every seed (seeds 3000, 3001,
...) and calibrated (free board poses, or the rigid box model with ``--rigid``).  Two checks
against the simulator's truth:

- camera and mirror: the tangent error ``d`` (the increment that takes the estimate to the truth,
  by Gauss-Newton through the retraction) over the reported std, per parameter (mean: the bias in
  stds; RMS: the spread and bias together), and the Mahalanobis distance squared ``d^T C^-1 d``
  over the parameters the calibration estimates (its mean is their number where the first-order
  covariance holds and the estimate is unbiased);
- the pipe: the preset measures a 150 mm pipe at 16 poses from noise-free spots with the
  calibration's covariance, so each calibration's diameter error over its reported std is the
  calibration's alone (RMS, mean, the largest).

Writes JSON naming the machine.
"""

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from bench_forward import machine
from jax.flatten_util import ravel_pytree

from slcvjax import (
    calibrate,
    measurement_inputs,
    paper_scene,
    pipe_experiment,
    pipe_scene,
    run_chunks,
    simulate,
    to_calibration,
)
from slcvjax.geometry.rig import CAMERA_DOF, CAMERA_NAMES, MIRROR_DOF

MIRROR_NAMES = ("apex_x", "apex_y", "apex_z", "tilt_x", "tilt_y", "shape")
N_CM = CAMERA_DOF + MIRROR_DOF


def camera_mirror_error(est, truth) -> np.ndarray:
    """The camera and mirror tangent increment that takes ``est`` to ``truth`` (Gauss-Newton, 4 steps)."""
    target, _ = ravel_pytree((truth.camera, truth.mirror))
    rest = jnp.zeros(est.tangent_dim - N_CM)

    def gap(d):
        r = est.retract(jnp.concatenate([d, rest]))
        return ravel_pytree((r.camera, r.mirror))[0] - target

    d = jnp.zeros(N_CM)
    for _ in range(4):
        d = d - jnp.linalg.lstsq(jax.jacfwd(gap)(d), gap(d))[0]
    return np.asarray(d)


def _named(names, values) -> dict:
    """``{name: value}``, null where the value is not finite (a parameter not estimated)."""
    return {n: None if not np.isfinite(v) else float(v) for n, v in zip(names, values, strict=True)}


def bias_chunk(payload: dict, items: list[dict]) -> list[dict]:
    """Calibrate a chunk of trials (``{"noise": px, "seed": int}``): per trial the camera and
    mirror error over its std ``z`` (NaN where not estimated), its Mahalanobis distance squared
    ``m2``, and the pipe's diameter error ``e`` and reported std ``s`` (mm)."""
    scene, pipe, rigid = payload["scene"], payload["pipe"], payload["rigid"]
    out = []
    for it in items:
        obs, _ = simulate(scene, noise=it["noise"], seed=it["seed"])
        res = calibrate(obs, rigid=rigid)
        _, cov = measurement_inputs("<calibration>", to_calibration(res, obs))
        d = camera_mirror_error(res.rig, scene.rig)
        c = cov[:N_CM, :N_CM]
        free = np.diag(c) > 0  # the parameters estimated (a datasheet's shape is not)
        z = np.where(free, d / np.sqrt(np.where(free, np.diag(c), 1.0)), np.nan)
        m2 = float(d[free] @ np.linalg.solve(c[np.ix_(free, free)], d[free]))
        got = pipe_experiment(res.rig, pipe, 0.0, seed=0, pixel_sigma=0.0, rig_cov=cov)
        e, s = float(np.mean(got["diameters"] - 150.0)), float(np.mean(got["diameter_stds"]))
        out.append({"z": z.tolist(), "m2": m2, "free": int(free.sum()), "e": e, "s": s})
    return out


def level(noise: float, records: list[dict]) -> dict:
    """The summary of one noise level's trials (:func:`bias_chunk`'s records)."""
    z_cm = np.asarray([r["z"] for r in records])
    m2 = [r["m2"] for r in records]
    d_err, d_std = [r["e"] for r in records], [r["s"] for r in records]
    dz = np.asarray(d_err) / np.asarray(d_std)
    n_free = records[-1]["free"]
    names = CAMERA_NAMES + MIRROR_NAMES
    with np.errstate(invalid="ignore"):
        mean_z, rms_z = np.nanmean(z_cm, axis=0), np.sqrt(np.nanmean(z_cm**2, axis=0))
    return {
        "noise_px": noise,
        "calibrations": len(records),
        "camera_mirror": {
            "mean_error_over_std": _named(names, mean_z),
            "rms_error_over_std": _named(names, rms_z),
            "mahalanobis2_mean": float(np.mean(m2)),
            "mahalanobis2_median": float(np.median(m2)),
            "parameters_estimated": n_free,
        },
        "diameter": {
            "error_over_std_rms": float(np.sqrt(np.mean(dz**2))),
            "error_over_std_mean": float(np.mean(dz)),
            "error_over_std_max_abs": float(np.max(np.abs(dz))),
            "beyond_two_std": int(np.sum(np.abs(dz) > 2)),
            "error_rms_mm": float(np.sqrt(np.mean(np.square(d_err)))),
            "reported_std_rms_mm": float(np.sqrt(np.mean(np.square(d_std)))),
        },
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=40)
    ap.add_argument("--noise", default="0.5,0.1")
    ap.add_argument("--rigid", action="store_true", help="calibrate with the rigid target box model")
    ap.add_argument("--out", default="benchmarks/results/calibration_bias.json")
    ap.add_argument("--cluster", help="run the calibrations on a Ray cluster: auto, local:N or ray://HOST:PORT")
    ap.add_argument("--chunks", help="keep each finished chunk of calibrations in this folder, and resume from it")
    ap.add_argument("--chunk", type=int, default=4, help="calibrations per chunk (default 4)")
    args = ap.parse_args()
    t0 = time.perf_counter()
    noises = [float(v) for v in args.noise.split(",") if v]
    scene = paper_scene()
    payload = {"scene": scene, "pipe": pipe_scene(scene.rig, 150.0, 16, seed=0), "rigid": args.rigid}
    items = [{"noise": noise, "seed": 3000 + k} for noise in noises for k in range(args.seeds)]
    settings = {"noise": noises, "seeds": args.seeds, "rigid": args.rigid}
    records = run_chunks(
        bias_chunk, payload, items, study="calibration-bias", settings=settings, chunk_size=args.chunk,
        folder=args.chunks, cluster=args.cluster, progress=True,
    )  # fmt: skip
    rows = []
    for i, noise in enumerate(noises):
        r = level(noise, records[i * args.seeds : (i + 1) * args.seeds])
        cm, dm = r["camera_mirror"], r["diameter"]
        big = sorted(cm["mean_error_over_std"].items(), key=lambda kv: -abs(kv[1] or 0.0))[:4]
        print(
            f"{noise:g} px: camera+mirror Mahalanobis^2 {cm['mahalanobis2_mean']:.2f} for "
            f"{cm['parameters_estimated']} parameters; largest biases "
            + ", ".join(f"{n} {v:+.2f} std" for n, v in big)
            + f"; diameter error/std RMS {dm['error_over_std_rms']:.3f}, mean {dm['error_over_std_mean']:+.3f}, "
            f"max {dm['error_over_std_max_abs']:.2f}",
            flush=True,
        )
        rows.append(r)
    out = {"machine": machine(), "seconds": time.perf_counter() - t0, "rigid_box": args.rigid, "levels": rows}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
