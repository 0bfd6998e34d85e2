"""Choosing what the data do not say: the mirror's kind (``mirror_shape.kind = "auto"``, by
held-out views) and the camera's projection (``camera_projection = "auto"``, by an F-test), and
calibrating a rig seen only through its mirror from each central start."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..geometry.conic import AsphereMirror, conic_kind
from ..geometry.rig import Rig
from ..observations.formats import Observations, shape_missing
from ..observations.problem import pack
from .base import CalibrationError, StageReport
from .central import central_start
from .evaluate import per_observation
from .executors import solve_loop
from .options import DEFAULT_OPTIONS, CalibrationOptions
from .report import report
from .result import CalibrationResult
from .schedule import calibrate_lockstep

AUTO_KINDS = ("hyperboloid", "paraboloid", "sphere")  # a hyperboloid's conic constant may cross to an ellipsoid's


def held_out_rms(rig: Rig, held: Observations) -> tuple[float, int, int]:
    """``(RMS px, observations used, left invalid)`` of views a calibrated rig did not see: its
    camera and mirror held, the views' poses (and lasers) fitted by plain least squares."""
    from ..geometry.mirror import shape_json

    held = dataclasses.replace(held, mirror_shape=shape_json(rig.mirror), camera_projection=rig.camera.projection)
    # calibrate()'s path for a given camera and mirror (no rigid box): the schedule from them
    options = DEFAULT_OPTIONS.replace(freeze=("camera", "mirror"), robust={"loss": "linear"})
    ev = calibrate_lockstep([held], rig.camera, options, solve_loop, mirror=rig.mirror)[0]
    r = report(ev, held)["residuals"]
    n = sum(int(s.sum()) for v in held.views for _, s in v.boards.values()) + sum(len(v.spots) for v in held.views)
    return float(r["rms_px"]), n - int(r["invalid"]), int(r["invalid"])


def auto_kind(obs: Observations, options: CalibrationOptions) -> "CalibrationResult":
    """``mirror_shape.kind = "auto"``: each of :data:`AUTO_KINDS` fitted on every view, then
    scored by ``options.auto_folds``-fold cross-validation over the views (every fifth view held out
    in turn, each fold's fit started from the fit on every view); the kind of the least held-out
    RMS (fewest held-out observations off the model first) is kept; the stage ``mirror_kind``
    reports each kind's figure, and says so where kinds lie within two standard errors of the
    best (the views do not determine the kind: a camera's distortion and the mirror's place
    absorb much of a shape's difference)."""
    from tqdm.auto import tqdm

    n = len(obs.views)
    if n < 2:
        raise CalibrationError("mirror_shape.kind: auto picks the kind by held-out views: it needs at least 2 views")
    k = min(options.auto_folds, n)
    folds = [list(range(i, n, k)) for i in range(k)]
    dims = {key: obs.mirror_shape[key] for key in ("vertex_radius",) if key in obs.mirror_shape}
    scores: dict[str, tuple[int, float]] = {}
    counted: dict[str, int] = {}
    fits: dict[str, CalibrationResult] = {}
    with tqdm(total=len(AUTO_KINDS) * (k + 1), desc="mirror kind (held-out views)", leave=False, disable=None) as bar:
        for kind in AUTO_KINDS:
            o_kind = dataclasses.replace(obs, mirror_shape={"kind": kind} | dims)
            kind_freeze, estimate = shape_unknowns(o_kind.mirror_shape, options.freeze)
            sq, used, bad = 0.0, 0, 0
            try:
                # every view from each central start; each fold's fit starts from it (one start:
                # the fold's own minimum, the held-out views' residuals left out of its cost)
                fits[kind] = full = through_the_mirror(o_kind, options)
                bar.update(1)
                for fold in folds:
                    train = dataclasses.replace(o_kind, views=[v for i, v in enumerate(obs.views) if i not in fold])
                    held = dataclasses.replace(o_kind, views=[obs.views[i] for i in fold])
                    fit = calibrate_lockstep(
                        [train],
                        full.rig.camera,
                        options.replace(freeze=kind_freeze),
                        solve_loop,
                        mirror=full.rig.mirror,
                        estimate=estimate,
                    )[0]
                    rms, n_used, n_bad = held_out_rms(fit.rig, held)
                    sq, used, bad = sq + rms * rms * n_used, used + n_used, bad + n_bad
                    bar.update(1)
            except CalibrationError:
                sq, used, bad = np.inf, 1, n
            scores[kind] = (bad, float(np.sqrt(sq / max(used, 1))))
            counted[kind] = used
    best = min(AUTO_KINDS, key=lambda kd: scores[kd])
    if not np.isfinite(scores[best][1]):
        raise CalibrationError("mirror_shape.kind: no kind of mirror fits these views")
    res = fits[best]
    notes = [
        f"{kd}: held-out RMS {scores[kd][1]:.4f} px"
        + (f", {scores[kd][0]} held-out observation(s) off the model" if scores[kd][0] else "")
        for kd in AUTO_KINDS
    ]
    notes.append(f"chosen: {best} (fitted as a {res.rig.mirror.kind}), {k}-fold over {n} views")
    # two standard errors of the held-out RMS (each observation two residuals): kinds within it
    # are not told apart by these views
    margin = 2.0 * scores[best][1] / np.sqrt(2.0 * counted[best])
    tied = [kd for kd in AUTO_KINDS if scores[kd][0] == scores[best][0] and scores[kd][1] <= scores[best][1] + margin]
    if len(tied) > 1:
        notes.append(
            f"not determined: the held-out views do not tell {', '.join(tied)} apart "
            f"(within two standard errors, {margin:.3f} px)"
        )
    return _reported_first(res, StageReport("mirror_kind", scores[best][1], "px (held out)", notes))


def _reported_first(res: "CalibrationResult", rep: StageReport) -> "CalibrationResult":
    """``res`` with ``rep`` first among its staged start's reports (a choice made before it)."""
    return dataclasses.replace(res, staged=dataclasses.replace(res.staged, reports=[rep, *res.staged.reports]))


def shape_unknowns(shape: dict, freeze) -> tuple[set, set]:
    """``(freeze, estimate)`` for a mirror of ``shape`` seen through only: a sphere's or a
    paraboloid's conic constant is its kind's, a hyperboloid's (or an ellipsoid's) left out is
    estimated; a sphere's axis is held (its vertex slides over it with the axis: only its centre
    is seen)."""
    estimate = {"shape"} if "conic_constant" in shape_missing(shape) else set()
    freeze = set(freeze) | ({"mirror_tilt"} if shape["kind"] == "sphere" else set())
    return freeze, estimate


def perspective_test(tele: "CalibrationResult", persp: "CalibrationResult") -> tuple[float, int, int]:
    """``(p-value, extra unknowns, dof)`` of the F-test of a telecentric fit against the
    perspective one of the same views: a telecentric camera is a pinhole's limit at an infinite
    distance, so the pinhole's extra unknowns (its depth, held before a telecentric lens: the
    gauge of parallel rays) nest it.  ``F = ((S_t - S_p) / q) / (S_p / dof_p)``, ``S`` the
    weighted squared residuals (``sigma^2 dof``), ``q = dof_t - dof_p``; a small p-value says the
    views need the perspective.  ``(0, q, dof_p)`` where ``q < 1`` and the pinhole fits better."""
    s_t = float(tele.cov.sigma) ** 2 * int(tele.cov.dof)
    s_p = float(persp.cov.sigma) ** 2 * int(persp.cov.dof)
    q, dof = int(tele.cov.dof) - int(persp.cov.dof), int(persp.cov.dof)
    if q < 1 or dof < 1 or s_p <= 0.0:
        return (0.0 if s_p < s_t else 1.0), q, dof
    f = max((s_t - s_p) / q / (s_p / dof), 0.0)
    # P(F(q, dof) > f) = I_x(dof/2, q/2), x = dof / (dof + q f): the regularised incomplete beta
    pval = float(jax.scipy.special.betainc(dof / 2.0, q / 2.0, dof / (dof + q * f)))
    return pval, q, dof


def through_the_mirror(obs: Observations, options: CalibrationOptions) -> "CalibrationResult":
    """A rig seen only through its mirror (no direct views): the joint passes from each central
    start (:func:`slcvjax.calibration.central.central_start`), the lowest final cost kept.  Where the shape leaves
    out the conic constant, the start searches it and the joint passes estimate it (the vertex
    radius held: the scale's gauge).  ``camera_projection = "auto"`` fits a telecentric and a
    perspective camera and keeps the perspective one only where :func:`perspective_test` says the
    views need it (p-value below ``options.projection_test_level``; fewer observations off the model
    first): the pinhole's depth is otherwise a near-gauge that drifts towards the telecentric
    limit and costs held-out accuracy."""
    if obs.camera_projection == "auto":
        return auto_projection(obs, options)
    shape = obs.mirror_shape
    freeze, estimate = shape_unknowns(shape, options.freeze)
    kind = shape["kind"]
    if kind == "asphere":  # started as its conic, then given its polynomial terms
        kind = conic_kind(shape["conic_constant"])
    starts = central_start(
        pack(obs),
        obs.image_size,
        kind,
        shape.get("vertex_radius"),
        shape.get("conic_constant"),
        shape.get("radius"),
        telecentric=obs.camera_projection == "telecentric",
    )
    if shape["kind"] == "asphere":
        starts = [
            (
                cam,
                AsphereMirror(
                    m.apex, m.axis, m.curvature, m.conic, m.radius, jnp.asarray(shape["coefficients"], float)
                ),
                rep,
            )
            for cam, m, rep in starts
        ]
    best, held = None, options.replace(freeze=freeze)
    for cam, mir, rep in starts:
        res = calibrate_lockstep([obs], cam, held, solve_loop, mirror=mir, estimate=estimate)[0]
        res = _reported_first(res, rep)
        if best is None or res.passes[-1].cost < best.passes[-1].cost:
            best = res
    if "radius" not in shape:  # the rim bounds nothing: where the estimate closed the conic, inside its widest circle
        mir = best.rig.mirror
        k1, c = 1.0 + float(mir.conic), float(mir.curvature)
        if k1 > 0 and k1 * (c * float(mir.radius)) ** 2 >= 1.0:
            rim = jnp.asarray(0.999 / (c * np.sqrt(k1)))
            best = dataclasses.replace(best, params=eqx.tree_at(lambda p: p.rig.mirror.radius, best.params, rim))
    return best


def auto_projection(obs: Observations, options: CalibrationOptions) -> "CalibrationResult":
    """:func:`through_the_mirror` for ``camera_projection = "auto"``."""
    fits: dict[str, CalibrationResult] = {}
    failed: dict[str, str] = {}
    for proj in ("telecentric", "perspective"):
        try:
            fits[proj] = through_the_mirror(dataclasses.replace(obs, camera_projection=proj), options)
        except CalibrationError as e:
            failed[proj] = str(e)
    if not fits:
        raise CalibrationError(
            "camera_projection: auto: neither projection fits these views ("
            + "; ".join(f"{k}: {v}" for k, v in failed.items())
            + ")"
        )
    notes = [f"{k}: failed ({v})" for k, v in failed.items()]
    if len(fits) == 1:
        (best,) = fits
    else:
        tele, persp = fits["telecentric"], fits["perspective"]
        off = {k: int(np.sum(~per_observation(r.params, r.packed)[2])) for k, r in fits.items()}
        pval, q, dof = perspective_test(tele, persp)
        for k, r in fits.items():
            notes.append(
                f"{k}: sigma {float(r.cov.sigma):.4f} px, dof {int(r.cov.dof)}"
                + (f", {off[k]} observation(s) off the model" if off[k] else "")
            )
        if off["telecentric"] != off["perspective"]:
            best = min(fits, key=lambda k: off[k])
            notes.append(f"chosen: {best} (fewer observations off the model)")
        else:
            best = "perspective" if pval < options.projection_test_level else "telecentric"
            notes.append(
                f"chosen: {best} (F-test of the perspective's {q} extra unknown(s): p = {pval:.3g}, "
                f"kept below {options.projection_test_level:g})"
            )
    res = fits[best]
    return _reported_first(res, StageReport("camera_projection", float(res.cov.sigma), "px (sigma)", notes))
