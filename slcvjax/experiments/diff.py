"""Two calibrations of one sensor compared over the image, beside the difference their covariances
predict (mrcal's projection-diff, for a non-central rig).

The quantity: per pixel of a grid over calibration A's mirror image, the point where the pixel's
reflected ray is ``range_mm`` from the camera's centre, by A and by B
(:func:`slcvjax.experiments.export.points_at_ranges`); their distance ``|X_A - X_B|`` (mm) is the
map. Both are in the camera frame, which the camera itself fixes, so no alignment is fitted.

The prediction: each calibration's covariance gives the point's 3x3 covariance ``C`` (the report's
projection uncertainty, :func:`slcvjax.experiments.report.projection_std`: the camera's and the
mirror's covariance through the back-projection, ``jax.jacfwd``); for two independent calibrations
``E|X_A - X_B|^2 = trace(C_A) + trace(C_B)``, so the predicted difference is
``sqrt(std_A^2 + std_B^2)`` with ``std = sqrt(trace C)``. The ratio of the two maps is about 1
where the calibrations differ only by their noise; mrcal's rule of thumb: up to about 2 is normal,
more says one of them (or the model) is off.
"""

import logging
from pathlib import Path

import numpy as np

from ..calibration.stored import load_result
from ..observations.formats import FormatError, read_calibration
from .export import points_at_ranges, working_range
from .report import projection_std, rim_grid

log = logging.getLogger(__name__)


def _covariance(path) -> tuple[np.ndarray | None, str]:
    """The calibration's covariance (the rig's tangent, :meth:`Rig.retract`'s order), recomputed
    from the problem it carries; None (and why) where it carries none."""
    try:
        return np.asarray(load_result(path).cov.glob, float), ""
    except FormatError as e:
        return None, str(e)


def diff_maps(a_path, b_path, range_mm: float | None = None, n_grid: int = 48) -> dict:
    """Compare calibrations ``a_path`` and ``b_path`` (``slcv-calibration/1`` files with a mirror).

    Returns a dict: ``u``, ``v`` (the grid's columns and rows, px); ``diff_mm`` (len(v), len(u)),
    ``|X_A - X_B|`` (NaN where either ray misses the mirror or the range); ``predicted_mm``
    (``sqrt(std_A^2 + std_B^2)``, None where a file carries no problem to recompute its covariance,
    ``why_no_prediction`` then says why); ``ratio`` (``diff / predicted``); ``range_mm`` and
    ``range_why``; ``summary`` (medians and the 95th percentiles of the maps, and the share of
    pixels whose ratio is above 2).

    Raises:
        FormatError: a file is not a calibration, has no mirror, or the two calibrations' image
            sizes differ.
    """
    a, b = read_calibration(a_path), read_calibration(b_path)
    for cal, path in ((a, a_path), (b, b_path)):
        if cal.rig.mirror is None:
            raise FormatError(f"{path}: mirror: a camera-only calibration; diff compares rays through the mirror")
    sa, sb = (a.rig.camera.width, a.rig.camera.height), (b.rig.camera.width, b.rig.camera.height)
    if sa != sb:
        raise FormatError(f"{b_path}: camera: its image is {sb[0]}x{sb[1]}, {a_path}'s {sa[0]}x{sa[1]}")
    if range_mm is None:
        range_mm, why = working_range(a)
    elif not range_mm > 0:
        raise FormatError(f"--range: must be a positive number of mm, got {range_mm}")
    else:
        why = "as asked"
    us, vs = rim_grid(a.rig, n_grid)
    pix = np.stack(np.meshgrid(us, vs), axis=-1).reshape(-1, 2)
    xa, oka = points_at_ranges(a.rig, pix, [range_mm])
    xb, okb = points_at_ranges(b.rig, pix, [range_mm])
    ok = oka[:, 0] & okb[:, 0]
    diff = np.where(ok, np.linalg.norm(xa[:, 0] - xb[:, 0], axis=1), np.nan).reshape(len(vs), len(us))
    out: dict = {"u": us, "v": vs, "diff_mm": diff, "range_mm": float(range_mm), "range_why": why}
    cov_a, why_a = _covariance(a_path)
    cov_b, why_b = _covariance(b_path)
    if cov_a is None or cov_b is None:
        out.update(predicted_mm=None, ratio=None, why_no_prediction=why_a or why_b)
    else:
        std_a = projection_std(a.rig, cov_a, range_mm, grid=(us, vs))["std_mm"]
        std_b = projection_std(b.rig, cov_b, range_mm, grid=(us, vs))["std_mm"]
        pred = np.sqrt(std_a**2 + std_b**2)
        out.update(predicted_mm=pred, ratio=diff / pred)
    out["summary"] = _summary(out)
    return out


def _stats(x) -> dict:
    f = np.asarray(x)[np.isfinite(x)]
    if not f.size:
        return {"median": None, "p95": None, "max": None}
    return {"median": float(np.median(f)), "p95": float(np.percentile(f, 95)), "max": float(f.max())}


def _summary(out: dict) -> dict:
    s = {"pixels": int(np.isfinite(out["diff_mm"]).sum()), "diff_mm": _stats(out["diff_mm"])}
    if out.get("predicted_mm") is not None:
        s["predicted_mm"] = _stats(out["predicted_mm"])
        r = out["ratio"][np.isfinite(out["ratio"])]
        s["ratio"] = _stats(r)
        s["share_above_2"] = float(np.mean(r > 2.0)) if r.size else None
    return s


def plot_diff(out: dict, a_name: str, b_name: str, path) -> Path:
    """The maps as one PNG: the difference, the predicted difference and their ratio (mm, mm, 1)."""
    from ..observations.formats import abandon_target, atomic_target, commit_target
    from ..plots import pyplot

    plt = pyplot()
    panels = [("|X_A - X_B| (mm)", out["diff_mm"], "viridis")]
    if out.get("predicted_mm") is not None:
        panels += [("predicted sqrt(std_A² + std_B²) (mm)", out["predicted_mm"], "viridis")]
        panels += [("ratio (about 1 normal, > 2 suspect)", out["ratio"], "coolwarm")]
    fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 4.2), squeeze=False)
    ext = [out["u"][0], out["u"][-1], out["v"][-1], out["v"][0]]
    for ax, (title, m, cmap) in zip(axes[0], panels, strict=True):
        kw = {"vmin": 0.0, "vmax": 4.0} if cmap == "coolwarm" else {}
        im = ax.imshow(m, extent=ext, cmap=cmap, **kw)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("u (px)")
        ax.set_ylabel("v (px)")
        fig.colorbar(im, ax=ax, shrink=0.8)
    fig.suptitle(f"{a_name} vs {b_name}: reflected rays at {out['range_mm']:.0f} mm", fontsize=10)
    fig.tight_layout()
    path, tmp = atomic_target(path, ".png")
    try:
        fig.savefig(tmp, dpi=90)
    except BaseException:
        abandon_target(tmp)
        raise
    finally:
        plt.close(fig)
    commit_target(path, tmp)
    return path
