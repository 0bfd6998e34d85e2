"""Noise-sensitivity sweeps: Monte Carlo calibrations at several pixel noises beside the Cramér–Rao bound.

A sweep simulates one scene (a preset) at each noise level ``trials`` times with
different seeds, calibrates every trial (staged, then joint), and compares each laser
with the truth component by component, as in Figs. 6–7 of Chen, Zhou & Xue (2019):

* ``x0, y0, z0``: the point of the estimated line nearest the laser's true working
  point (the mean of its spots), minus that working point (mm);
* ``nx, ny, nz``: the estimated unit direction (sign-aligned) minus the true one.

The bound is the same scene's ``sigma^2 (J^T J)^-1`` at the truth, propagated to the
same components; it scales with the noise, so it is computed once.  Every trial has
the same observation shapes, so the whole sweep shares one compilation.  The trials
are calibrated by :func:`calibrate_many`: on a CPU in a loop, two at a time in threads
(a ``vmap`` batch waits for its slowest trial: ``benchmarks/bench_sweep.py`` measured
the loop 1.8x faster), on an accelerator all of them in lockstep, each LM pass one
``vmap``-ped solve with the trial axis sharded over the devices.  The trials go in chunks
(:func:`sweep_chunk`) through :func:`slcvjax.experiments.cluster.run_chunks`: here, or one Ray
task per chunk on a cluster, each finished chunk kept in the output folder for a resume.
"""

import csv
import io
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ..calibration.bound import cramer_rao, laser_errors
from ..calibration.calibrate import calibrate_many
from ..calibration.executors import resolve_batch
from ..calibration.result import require_determined
from ..geometry.rig import Rig
from ..observations.formats import write_json_atomic, write_text_atomic
from ..observations.simulate import make_scene, simulate
from ..support.safe import std_of_variance
from .cluster import prepare_folder, run_chunks

SWEEP_FORMAT = "slcv-sweep/1"
COMPONENTS = ("x0", "y0", "z0", "nx", "ny", "nz")


def laser_component_errors(est: Rig, truth: Rig, x_ref: np.ndarray) -> np.ndarray:
    """Per laser the errors of ``x0, y0, z0`` (mm) and ``nx, ny, nz``: shape (N, 6)."""
    p, d = np.asarray(est.lasers.points), np.asarray(est.lasers.directions)
    dt = np.asarray(truth.lasers.directions)
    d = d * np.where(np.sum(d * dt, axis=1, keepdims=True) < 0, -1.0, 1.0)
    foot = p + np.sum((x_ref - p) * d, axis=1, keepdims=True) * d
    return np.concatenate([foot - x_ref, d - dt], axis=1)


def laser_component_std(rig: Rig, cov_glob: np.ndarray, x_ref: np.ndarray) -> np.ndarray:
    """Per laser the standard deviations of ``x0 .. nz`` from the global covariance: (N, 6)."""
    out = np.zeros((rig.lasers.n, 6))

    def comps(delta4, i):
        return jnp.concatenate(rig.lasers.at_working_point(i, x_ref[i], delta4))

    for i in range(rig.lasers.n):
        sl = rig.layout.elements[i]
        j = np.asarray(jax.jacfwd(comps)(jnp.zeros(sl.stop - sl.start), i))
        out[i] = std_of_variance(np.diag(j @ np.asarray(cov_glob)[sl, sl] @ j.T))
    return out


def _summaries(comp: np.ndarray, pos: np.ndarray, ang: np.ndarray) -> dict:
    """``comp`` (levels, trials, N, 6), ``pos``/``ang`` (levels, trials, N) -> the JSON block of a method."""
    return {
        "position_rms_mm": np.sqrt(np.mean(pos**2, axis=(1, 2))).tolist(),
        "direction_rms_deg": np.degrees(np.sqrt(np.mean(ang**2, axis=(1, 2)))).tolist(),
        "per_laser": {
            c: np.sqrt(np.mean(comp[..., k] ** 2, axis=1)).T.tolist()  # [laser][level]
            for k, c in enumerate(COMPONENTS)
        },
    }


def sweep_chunk(payload: dict, items: list[dict]) -> list[dict]:
    """Simulate and calibrate a chunk of a sweep's trials (the task of :func:`run_chunks`).

    Args:
        payload: ``scene`` (the preset's :class:`Scene`), ``truth`` (its true :class:`Rig`),
            ``x_ref`` (N, 3) the lasers' working points (mm), ``batch`` (``loop`` or ``vmap``) and
            ``workers`` (:func:`calibrate_many`'s).
        items: one per trial, ``{"noise": px, "seed": int, ...}``.

    Returns:
        One record per trial: ``comp_joint``/``comp_staged`` (N, 6) component errors
        (:func:`laser_component_errors`), ``pos_*`` (N,) mm and ``ang_*`` (N,) rad
        (:func:`laser_errors`), ``converged`` and ``seconds`` (in lockstep: the chunk's mean).

    Raises:
        CalibrationError: a trial whose lasers cannot be determined.
    """
    scene, truth, x_ref = payload["scene"], payload["truth"], np.asarray(payload["x_ref"])
    observations = [simulate(scene, noise=it["noise"], seed=it["seed"])[0] for it in items]
    t1 = time.perf_counter()
    # on a CPU two calibrations at once overlap one's host steps with the other's solves
    results = calibrate_many(observations, batch=payload["batch"], workers=payload["workers"])
    per_trial = (time.perf_counter() - t1) / len(results)
    out = []
    for res in results:
        require_determined(res)
        rec = {
            "converged": bool(res.passes[-1].converged),
            # in lockstep (vmap) the trials share their time: the chunk's mean
            "seconds": res.timings["total_s"] if payload["batch"] == "loop" else per_trial,
        }
        for m, rig in (("joint", res.rig), ("staged", res.staged.rig)):
            rec[f"comp_{m}"] = laser_component_errors(rig, truth, x_ref).tolist()
            pos, ang = laser_errors(rig, truth, x_ref)
            rec[f"pos_{m}"], rec[f"ang_{m}"] = np.asarray(pos).tolist(), np.asarray(ang).tolist()
        out.append(rec)
    return out


def default_chunk(batch: str) -> int:
    """Trials per chunk by default: 8 in a loop (a few seconds each on a CPU core), 256 in lockstep
    (``vmap``: an accelerator's batch)."""
    return 8 if batch == "loop" else 256


def run_sweep(
    preset: str = "paper",
    noise: tuple[float, ...] = (0.0, 0.3, 0.6, 0.9),
    trials: int = 8,
    seed: int = 0,
    n_lasers: int = 10,
    n_views: int = 16,
    progress: bool = False,
    batch: str = "auto",
    *,
    out_dir=None,
    resume: str = "auto",
    chunk: int | None = None,
    cluster=None,
    cache_dir=None,
    on_chunk=None,
) -> dict:
    """Run a sweep; returns the ``slcv-sweep/1`` document (plus per-trial details under ``trials_detail``).

    Trial ``t`` of level ``l`` simulates with seed ``seed + 1000 l + t``.  ``batch``:
    how the trials are calibrated (:func:`calibrate_many`: ``auto``, ``loop`` or ``vmap``).

    The trials run in chunks of ``chunk`` (default :func:`default_chunk`) through
    :func:`slcvjax.experiments.cluster.run_chunks`: here, or on the Ray cluster ``cluster``
    (``auto``, ``local:N``, ``ray://HOST:PORT``; ``cache_dir``: the workers' shared compilation
    cache), with the same numbers either way.  With ``out_dir`` every finished chunk is kept there
    (``study.json``, ``chunks/``) and a run of the same settings resumes it (``resume``: ``auto``,
    ``require`` or ``restart``; another sweep's folder raises
    :class:`~slcvjax.experiments.cluster.StudyError`).  ``on_chunk(index, done)``: called after
    each chunk.
    """
    noise = tuple(float(s) for s in noise)
    if not noise or any(not np.isfinite(s) or s < 0 for s in noise):
        raise ValueError(f"noise: expected non-negative pixel sigmas, got {list(noise)}")
    if trials < 1:
        raise ValueError(f"trials: expected at least 1, got {trials}")
    batch = resolve_batch(batch)
    items = [
        {"level": li, "noise": s, "trial": t, "seed": seed + 1000 * li + t}
        for li, s in enumerate(noise)
        for t in range(trials)
    ]
    settings = {"preset": preset, "noise": list(noise), "trials": trials, "seed": seed, "lasers": n_lasers}
    settings |= {"views": n_views, "batch": batch}
    if out_dir is not None:  # another sweep's folder is refused before any work
        _, chunk = prepare_folder(out_dir, "sweep", settings, len(items), chunk, resume, default_chunk(batch))
        resume = "auto"
    t0 = time.perf_counter()  # the bound's compilation included
    scene = make_scene(preset, n_lasers=n_lasers, n_views=n_views)
    exact, truth = simulate(scene)
    unit = cramer_rao(truth, exact, 1.0)  # the bound at 1 px; it scales with the noise
    x_ref = np.asarray(unit["x_ref"])
    unit_comp = laser_component_std(truth.rig, np.asarray(unit["cov"].glob), x_ref)
    n = truth.rig.lasers.n
    payload = {
        "scene": scene,
        "truth": truth.rig,
        "x_ref": x_ref,
        "batch": batch,
        "workers": min(2, os.cpu_count() or 1),
    }
    records = run_chunks(
        sweep_chunk, payload, items, study="sweep", settings=settings, chunk_size=chunk,
        default_chunk_size=default_chunk(batch), folder=out_dir, resume=resume, cluster=cluster,
        cache_dir=cache_dir, progress=progress, on_chunk=on_chunk,
    )  # fmt: skip
    shape = (len(noise), trials, n)
    comp = {m: np.zeros(shape + (6,)) for m in ("staged", "joint")}
    pos = {m: np.zeros(shape) for m in ("staged", "joint")}
    ang = {m: np.zeros(shape) for m in ("staged", "joint")}
    detail = []
    for it, rec in zip(items, records, strict=True):
        li, t = it["level"], it["trial"]
        for m in ("staged", "joint"):
            comp[m][li, t] = rec[f"comp_{m}"]
            pos[m][li, t], ang[m][li, t] = rec[f"pos_{m}"], rec[f"ang_{m}"]
        detail.append(
            {
                "noise": it["noise"],
                "trial": t,
                "seed": it["seed"],
                "seconds": rec["seconds"],
                "converged": rec["converged"],
            }
        )
    sig = np.asarray(noise)
    bound_comp = sig[:, None, None] * unit_comp[None]  # (levels, N, 6)
    bound = {
        "position_rms_mm": (sig * unit["position_rms_mm"]).tolist(),
        "direction_rms_deg": (sig * np.degrees(unit["direction_rms_rad"])).tolist(),
        "per_laser": {c: bound_comp[..., k].T.tolist() for k, c in enumerate(COMPONENTS)},
    }
    return {
        "format": SWEEP_FORMAT,
        "noise": list(noise),
        "trials": trials,
        "methods": {
            "staged": _summaries(comp["staged"], pos["staged"], ang["staged"]),
            "joint": _summaries(comp["joint"], pos["joint"], ang["joint"]),
            "bound": bound,
        },
        "scene": {"preset": preset, "lasers": n, "views": n_views, "seed": seed},
        "batch": batch,
        "devices": [str(d) for d in jax.devices()],
        "cluster": None if cluster is None else str(cluster),
        "converged": int(sum(d["converged"] for d in detail)),
        "seconds": time.perf_counter() - t0,
        "trials_detail": detail,
    }


def sweep_csv(doc: dict) -> str:
    """One row per method, noise level and laser: the RMS errors of the six components."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["method", "noise_px", "laser"] + [f"{c}_rms" for c in COMPONENTS])
    for m, block in doc["methods"].items():
        per = block["per_laser"]
        for li, s in enumerate(doc["noise"]):
            for laser in range(len(per["x0"])):
                w.writerow([m, s, laser] + [f"{per[c][laser][li]:.6g}" for c in COMPONENTS])
    return buf.getvalue()


def plot_sweep(doc: dict, path) -> Path:
    """The paper's Figs. 6–7: RMS error of each component against noise, one curve per laser, bound dashed."""
    from ..plots import pyplot

    plt = pyplot()
    path = Path(path)
    fig, axs = plt.subplots(2, 3, figsize=(13, 7.5))
    noise = doc["noise"]
    joint, bound = doc["methods"]["joint"]["per_laser"], doc["methods"]["bound"]["per_laser"]
    n = len(joint["x0"])
    colors = plt.cm.tab10(np.arange(n) % 10)
    for ax, c in zip(axs.ravel(), COMPONENTS, strict=True):
        for i in range(n):
            ax.plot(noise, joint[c][i], "o-", ms=3, lw=1, color=colors[i], label=f"laser {i}")
            ax.plot(noise, bound[c][i], "--", lw=0.8, color=colors[i])
        ax.set_xlabel("pixel noise sigma (px)")
        ax.set_ylabel(f"RMS error of {c}" + (" (mm)" if c.endswith("0") else ""))
        ax.set_title(c)
        ax.grid(alpha=0.3)
    axs[0, 0].legend(fontsize=6, ncol=2)
    fig.suptitle(f"Joint calibration over {doc['trials']} trials per level (solid) and the Cramer-Rao bound (dashed)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def write_sweep(doc: dict, out_dir) -> list[Path]:
    """Write ``sweep.json``, ``sweep.csv`` and ``sweep.png`` into ``out_dir``; returns the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "sweep.json", doc)
    write_text_atomic(out / "sweep.csv", sweep_csv(doc))
    return [out / "sweep.json", out / "sweep.csv", plot_sweep(doc, out / "sweep.png")]
