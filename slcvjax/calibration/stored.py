"""A calibration file that carries its problem: every figure of a calibration can be recomputed
from the file alone.

:func:`slcvjax.calibration.report.to_calibration` writes, beside the rig and the report, a
``problem`` section (``slcv-problem/1``):

- ``observations``: the observations as the calibration was given them (``slcv-observations/1``);
- ``packed``: the rows the final pass fitted, after the repairs (relabelled spots and dots, the
  outliers left out, the boards the staged start gave to spots seen without one), each array with
  its shape and dtype, and the rows' sources (view, board, index);
- ``solution``: every leaf of the solver's unknowns (:class:`slcvjax.calibration.params.Params`) at
  full precision, and the masks of what was estimated;
- ``options``: the :class:`slcvjax.calibration.options.CalibrationOptions` it ran with;
- ``loss``, ``scale``: the robust loss and its scale (px) of the final pass;
- ``kind_sigma``: the noise sigma of each kind of observation (px; None where a kind had too few
  free rows);
- ``covariance``: the covariance of the solution (the rig's global block and each pose block),
  which a file of the rigid box model is read back with (its box model is not rebuilt);
- ``slcvjax_version``: the package that wrote it.

:func:`load_result` rebuilds the :class:`slcvjax.calibration.result.CalibrationResult` at the
solution without solving again: the report, the uncertainty, the per-kind noise, the
sensitivity to the pixels and the bound at the solution then run as on the live result.  Arrays
are written with Python's shortest round-trip float text, so the values read back are the same
float64 numbers; a non-finite value is written as the string ``"nan"``, ``"inf"`` or ``"-inf"``.
"""

import os
from importlib import metadata
from typing import Any

import jax
import numpy as np

from ..geometry.pose import Pose
from ..observations.formats import (
    CALIBRATION_FORMAT,
    FormatError,
    Observations,
    calibration_from_json,
    load_json,
    observations_from_json,
    observations_to_json,
)
from ..observations.problem import KIND_NAMES, Packed
from .base import StageReport
from .covariance import Covariance, covariance_and_noise
from .lm import Outcome
from .options import CalibrationOptions
from .params import Masks, Params
from .result import CalibrationResult, JointPass, Repair
from .staged import Staged

PROBLEM_FORMAT = "slcv-problem/1"
_ARRAYS = (
    "dot_pose",
    "dot_points",
    "dot_pixels",
    "spot_pose",
    "spot_laser",
    "spot_pixels",
    "rim_pixels",
    "chess_pose",
    "chess_points",
    "chess_pixels",
    "counts",
)
_STRIPE_ARRAYS = ("stripe_pose", "stripe_sheet", "stripe_pixels")  # where the rig has line or ring lasers
_NONFINITE = {"nan": np.nan, "inf": np.inf, "-inf": -np.inf}


def array_json(a) -> dict:
    """An array as JSON: ``{"shape", "dtype", "values"}`` (values flattened in C order, a
    non-finite float as ``"nan"``, ``"inf"`` or ``"-inf"``)."""
    a = np.asarray(a)
    if a.dtype.kind == "f":
        values = [
            float(v) if np.isfinite(v) else ("nan" if np.isnan(v) else ("inf" if v > 0 else "-inf")) for v in a.ravel()
        ]
    elif a.dtype.kind in "iub":
        values = [int(v) for v in a.ravel()]
    else:
        raise TypeError(f"cannot store an array of dtype {a.dtype}")
    return {"shape": list(a.shape), "dtype": str(a.dtype), "values": values}


def _array(val: Any, where: str, source: str) -> np.ndarray:
    """The array of :func:`array_json`'s ``val`` (``FormatError`` naming ``where`` if malformed)."""
    if not isinstance(val, dict) or not {"shape", "dtype", "values"} <= set(val):
        raise FormatError(f"{source}: {where}: expected an object with shape, dtype and values")
    try:
        dtype = np.dtype(val["dtype"])
        shape = tuple(int(n) for n in val["shape"])
        values = [_NONFINITE[v] if isinstance(v, str) else v for v in val["values"]]
        a = np.asarray(values, dtype=dtype)
        return a.reshape(shape)
    except (TypeError, ValueError, KeyError) as e:
        raise FormatError(f"{source}: {where}: not an array of its shape and dtype ({e})") from None


def _keys(val, where: str, source: str) -> tuple:
    if not isinstance(val, list):
        raise FormatError(f"{source}: {where}: expected a list")
    return tuple(tuple(k) if isinstance(k, list) else k for k in val)


def problem_json(result: CalibrationResult) -> dict:
    """The ``problem`` section of a calibration file (see the module docstring)."""
    pk, obs = result.packed, result.observations
    leaves = jax.tree_util.tree_leaves(result.params)
    packed = {name: array_json(getattr(pk, name)) for name in _ARRAYS}
    packed |= {
        "pose_keys": [list(k) for k in pk.pose_keys],
        "chess_keys": list(pk.chess_keys),
        "dot_src": [list(k) for k in pk.dot_src],
        "spot_src": [list(k) for k in pk.spot_src],
        "pair_block": None if pk.pair_block is None else array_json(pk.pair_block),
        "pair_box": None if pk.pair_box is None else array_json(pk.pair_box),
    }
    if pk.has_stripes:
        packed |= {name: array_json(getattr(pk, name)) for name in _STRIPE_ARRAYS}
        packed["stripe_src"] = [list(k) for k in pk.stripe_src]
    try:
        version = metadata.version("slcvjax")
    except metadata.PackageNotFoundError:
        version = None
    cov = result.cov
    return {
        "format": PROBLEM_FORMAT,
        "slcvjax_version": version,
        "observations": None if obs is None else observations_to_json(obs),
        "packed": packed,
        "solution": {
            "n_poses": int(result.params.poses.t.shape[0]),
            "n_chess": int(result.params.chess.t.shape[0]),
            "n_box": result.params.n_box,
            "leaves": [array_json(x) for x in leaves],
        },
        "masks": {"glob": array_json(result.masks.glob), "blocks": array_json(result.masks.blocks)},
        "options": result.options.to_json(),
        "loss": result.loss,
        "scale": float(result.scale),
        "kind_sigma": {
            k: (float(v) if v is not None and np.isfinite(v) else None) for k, v in result.kind_sigma.items()
        },
        "covariance": {
            "glob": array_json(cov.glob),
            "blocks": array_json(cov.blocks),
            "sigma": float(cov.sigma),
            "dof": int(cov.dof),
        },
    }


def _get(obj: Any, key: str, where: str, source: str):
    if not isinstance(obj, dict) or key not in obj:
        raise FormatError(f"{source}: {where}.{key}: missing")
    return obj[key]


def _staged(stages: dict, source: str) -> Staged:
    """The staged result as the file's ``stages.staged`` gives it (its rig and its reports)."""
    st = _get(stages, "staged", "stages", source)
    rig_doc = {"format": CALIBRATION_FORMAT} | {k: st[k] for k in ("camera", "mirror", "lasers") if k in st}
    cal = calibration_from_json(rig_doc, f"{source}: stages.staged")
    reports = [
        StageReport(r["stage"], np.nan if r["rms"] is None else r["rms"], r["unit"], list(r["notes"]))
        for r in _get(st, "reports", "stages.staged", source)
    ]
    rig = cal.rig
    points, sheets = _split_undetermined(rig, cal.undetermined_lasers)
    return Staged(rig.camera, rig.mirror, rig.lasers, [], {}, reports, None, points, rig.sheets, rig.kinds, sheets)


def _split_undetermined(rig, elements) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """A file's undetermined lasers (their indices in the file) as the point lasers' and the
    sheets' own indices."""
    if not rig.kinds:
        return tuple(elements), ()
    local, kinds = rig.local_index, rig.element_kinds
    points = tuple(int(local[e]) for e in elements if kinds[e] == "point")
    return points, tuple(int(local[e]) for e in elements if kinds[e] != "point")


def _repairs(doc, source: str) -> tuple[Repair, ...]:
    """The file's ``residuals.repairs`` as records (an error names the file, the field and the index)."""
    if not isinstance(doc, list):
        raise FormatError(f"{source}: residuals.repairs: expected a list, got {type(doc).__name__}")
    return tuple(Repair.from_json(r, f"{source}: residuals.repairs[{i}]") for i, r in enumerate(doc))


def _box(doc: dict) -> dict:
    """``CalibrationResult.box`` from the file's ``uncertainty.rigid_box``."""

    def nan(x):
        return np.asarray([np.nan if v is None else v for v in x], dtype=float)

    boards = {
        b: {
            "pose": Pose(np.asarray(d["R"], float), np.asarray(d["t"], float)),
            "rotation_deg": nan(d["rotation_std_deg"]),
            "translation_mm": nan(d["translation_std_mm"]),
        }
        for b, d in doc["boards"].items()
    }
    return {"gauge": doc["gauge"], "boards": boards} | {
        k: doc[k] for k in ("views", "free_board_poses", "left_out", "spots_restored", "notes")
    }


def load_result(path: str | os.PathLike) -> CalibrationResult:
    """The calibration of a file written by ``slcvjax calibrate`` (or
    :func:`slcvjax.calibration.report.to_calibration`), rebuilt at its solution without solving.

    The solution, the problem (the observations and the rows fitted after the repairs), the
    masks, the loss and its scale are read back exactly; the covariance and each kind's noise are
    computed again from them (a calibration of the rigid box model takes its stored covariance:
    its box model is not rebuilt), so that :func:`slcvjax.report`, :func:`slcvjax.sensitivity`,
    :func:`slcvjax.calibration.covariance.kind_noise` and the bound at the solution give the live
    result's figures.

    Raises:
        FormatError: the file is not a calibration, or carries no ``problem`` (a file written
            by hand or by an older version; ``slcvjax calibrate`` again writes one).
    """
    ctx, doc = load_json(path)
    source = str(path)
    cal = calibration_from_json(doc, source)
    prob = doc.get("problem")
    if not isinstance(prob, dict):
        raise FormatError(
            f"{source}: problem: missing (the file does not carry its problem: calibrate again with this version)"
        )
    if prob.get("format") != PROBLEM_FORMAT:
        raise FormatError(f"{source}: problem.format: expected {PROBLEM_FORMAT!r}, got {prob.get('format')!r}")
    obs_doc = _get(prob, "observations", "problem", source)
    obs: Observations | None = (
        None if obs_doc is None else observations_from_json(obs_doc, f"{source}: problem.observations")
    )
    pd = _get(prob, "packed", "problem", source)
    arrays = {
        name: _array(_get(pd, name, "problem.packed", source), f"problem.packed.{name}", source) for name in _ARRAYS
    }
    pair = {
        k: None if pd.get(k) is None else _array(pd[k], f"problem.packed.{k}", source)
        for k in ("pair_block", "pair_box")
    }
    stripes = {}
    if pd.get("stripe_pose") is not None:
        stripes = {
            name: _array(_get(pd, name, "problem.packed", source), f"problem.packed.{name}", source)
            for name in _STRIPE_ARRAYS
        }
        stripes["stripe_src"] = _keys(pd.get("stripe_src", []), "problem.packed.stripe_src", source)
    packed = Packed(
        **stripes,
        **arrays,
        pose_keys=_keys(pd["pose_keys"], "problem.packed.pose_keys", source),
        chess_keys=_keys(pd["chess_keys"], "problem.packed.chess_keys", source),
        dot_src=_keys(pd["dot_src"], "problem.packed.dot_src", source),
        spot_src=_keys(pd["spot_src"], "problem.packed.spot_src", source),
        **pair,
    )
    sol = _get(prob, "solution", "problem", source)

    def poses(n):
        return Pose(np.zeros((n, 3, 3)), np.zeros((n, 3)))

    n_box = int(sol["n_box"])
    template = Params(cal.rig, poses(int(sol["n_poses"])), poses(int(sol["n_chess"])), poses(n_box) if n_box else None)
    slots, treedef = jax.tree_util.tree_flatten(template)
    stored = [_array(x, f"problem.solution.leaves[{i}]", source) for i, x in enumerate(sol["leaves"])]
    if len(stored) != len(slots) or any(np.shape(a) != np.shape(b) for a, b in zip(stored, slots, strict=True)):
        raise FormatError(f"{source}: problem.solution.leaves: they do not fit the file's rig and poses")
    params = jax.tree_util.tree_unflatten(treedef, stored)
    m = _get(prob, "masks", "problem", source)
    masks = Masks(_array(m["glob"], "problem.masks.glob", source), _array(m["blocks"], "problem.masks.blocks", source))
    loss, scale = str(prob["loss"]), float(prob["scale"])
    options = CalibrationOptions.from_json(_get(prob, "options", "problem", source), f"{source}: problem.options")
    stages = _get(doc, "stages", "", source)
    joint = _get(stages, "joint", "stages", source)
    passes = tuple(
        JointPass(
            p["name"],
            p["steps"],
            p["cost0"],
            p["cost"],
            p["scale"],
            Outcome[p["outcome"].upper()],
            p["limit"],
            tuple(p["notes"]),
        )
        for p in joint["passes"]
    )
    held_points, held_sheets = _split_undetermined(cal.rig, cal.undetermined_lasers)
    unc = _get(doc, "uncertainty", "", source)
    box = _box(unc["rigid_box"]) if unc.get("rigid_box") is not None else None
    if box is None:
        cov, noise = covariance_and_noise(params, packed, masks, loss, scale)
        kind_sigma = dict(zip(KIND_NAMES, noise.sigma.tolist(), strict=False))
    else:
        c = prob["covariance"]
        cov = Covariance(
            _array(c["glob"], "problem.covariance.glob", source),
            _array(c["blocks"], "problem.covariance.blocks", source),
            np.asarray(float(c["sigma"])),
            np.asarray(int(c["dof"])),
        )
        kind_sigma = {k: (np.nan if v is None else float(v)) for k, v in prob["kind_sigma"].items()}
    return CalibrationResult(
        params,
        _staged(stages, source),
        packed,
        masks,
        cov,
        loss,
        scale,
        passes,
        dict(joint.get("timings_s") or {}),
        kind_sigma,
        _repairs(_get(doc, "residuals", "", source).get("repairs", []), source),
        box,
        held_points,
        obs,
        options,
        held_sheets,
    )
