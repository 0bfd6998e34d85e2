"""Repairs of the observations: wrong labels given back, gross outliers left out, and every change
recorded.

Spots that lie on another laser's line are relabelled (from the consensus fit of the lines);
dots and spots beyond ``outlier_sigmas`` sigmas of their kind (and ``min_outlier_px``) are
found under the redescending Cauchy loss and left out; what fits again once they are out comes
back (a dot on another grid position, a spot on exactly one other laser's line).  Each change is a
:class:`slcvjax.calibration.result.Repair` in the trial's ``repairs``.
"""

import dataclasses

import numpy as np

from ..observations.formats import Observations
from ..observations.problem import KIND_NAMES, Kind, Packed
from .covariance import kind_sigmas, sigmas_of
from .evaluate import per_observation, probe_at
from .result import AT_THE_FINAL_GEOMETRY, Repair
from .trial import Trial


def _dot_source(tr: "Trial", i: int, pk: Packed) -> dict:
    """Dot row ``i`` of ``pk`` as a :class:`Repair` names it (its ``kind``, ``view``, ``index``
    and ``board``)."""
    if not pk.dot_src:
        return dict(kind="dot", view=None, index=-1, board="")
    v, b, j = pk.dot_src[i]
    return dict(kind="dot", view=tr.obs.views[v].name, index=j, board=b)


def _spot_source(tr: "Trial", i: int, pk: Packed | None = None) -> dict:
    """Spot row ``i`` of ``pk`` (the trial's problem by default) as a :class:`Repair` names it."""
    pk = tr.pk if pk is None else pk
    if not pk.spot_src:
        return dict(kind="spot", view=None, index=-1, board=None)
    v, j = pk.spot_src[i]
    return dict(kind="spot", view=tr.obs.views[v].name, index=j, board=tr.obs.views[v].spots[j].board)


def relabel_spots(tr: "Trial", fit) -> "Trial":
    """The trial with its spots given the labels of :func:`slcvjax.calibration.laser_fit.fit_lasers`
    (another laser, or left out), each change recorded in its ``repairs``."""
    own = np.asarray(tr.pk.spot_laser)[: fit.labels.shape[0]]
    changed = np.flatnonzero(fit.labels != own)
    if not changed.size:
        return tr
    records = []
    for i in changed:
        new = int(fit.labels[i])
        r_own = fit.residual[i, own[i]]
        if new >= 0:
            reason = f"lies on laser {new}'s line, not on its own (threshold {fit.threshold:.3g} px)"
        elif fit.undetermined[own[i]]:
            reason = f"laser {own[i]} is undetermined: its spots cannot fix a line"
        else:
            reason = f"lies on no laser's line, or on more than one (threshold {fit.threshold:.3g} px)"
        records.append(
            Repair(
                **_spot_source(tr, i),
                action="relabelled" if new >= 0 else "left out",
                reason=reason,
                residual_px=float(r_own) if np.isfinite(r_own) else None,
                laser=int(own[i]),
                new_laser=new if new >= 0 else None,
                new_residual_px=float(fit.residual[i, new]) if new >= 0 else None,
                stage="lines",
            )
        )
    n_d, keep = int(tr.pk.counts[Kind.DOT]), fit.labels >= 0
    every = tr.pk.select(np.ones(n_d, bool), np.ones(keep.size, bool), np.where(keep, fit.labels, own))
    aside = (every, np.concatenate([np.zeros(n_d, bool), ~keep]))
    tr = dataclasses.replace(tr.with_repairs(*records), set_aside=aside)
    return tr.using(every.select(np.ones(n_d, bool), keep))


def _outliers(tr: "Trial", pk: Packed) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Which dots and spots of ``pk`` lie beyond ``policy.outlier_sigmas`` sigmas of their kind (and
    beyond ``policy.min_outlier_px``) at the trial's solution (each kind's sigma from the median
    residual of the observations the trial keeps, corrected for the degrees of freedom), or
    whose prediction is not valid (off the mirror or the sensor), with every observation's
    residual norm and kind, the thresholds (px) per kind and the validity."""
    norm, kind, ok = per_observation(tr.params, pk)
    # the sigmas of what the trial keeps: this table where ``pk`` is that problem
    sig = sigmas_of(norm, kind, ok) if pk is tr.pk else kind_sigmas(tr.params, tr.pk)
    n_d, n_s = int(pk.counts[Kind.DOT]), int(pk.counts[Kind.SPOT])
    bad = np.zeros(n_d + n_s, bool)
    # the residuals are smaller than the noise by the parameters they fix: the dots the board
    # poses (6 each), the spots the lasers (4 each); the median's sigma is scaled back up
    kept_d, kept_s = int(tr.pk.counts[Kind.DOT]), int(tr.pk.counts[Kind.SPOT])
    sig[Kind.DOT] *= np.sqrt(2 * kept_d / max(2 * kept_d - 6 * tr.pk.n_poses, 1))
    sig[Kind.SPOT] *= np.sqrt(2 * kept_s / max(2 * kept_s - 4 * tr.obs.n_lasers, 1))
    limit = np.maximum(tr.policy.outlier_sigmas * sig, tr.policy.min_outlier_px)
    for k in (Kind.DOT, Kind.SPOT):
        if np.isfinite(sig[k]):
            bad |= (ok & (kind == k) & (norm > limit[k]))[: n_d + n_s]
    bad |= ~ok[: n_d + n_s]  # predicted off the mirror or the sensor: out of the model's reach
    return bad, norm, kind, limit, ok


def leave_out(tr: "Trial", starts, rerun, rounds: int = 3, find: bool = True) -> "Trial":
    """The trial with its gross outliers left out: the dots and spots beyond ``policy.outlier_sigmas``
    sigmas (:func:`_outliers`).  Where there are any, the final pass runs first with the
    redescending Cauchy loss (``rerun(tr, "cauchy", scale)``, first at ``policy.cauchy_widen`` times the
    loss scale, then at it), under which a gross outlier no longer drags
    its board's pose, so that the outliers found then are the wrong observations, not the good
    ones of a dragged board (and every board tries its other starts under that loss,
    ``starts(tr)``: a board whose own dots are a third wrong is found again from its neighbours);
    those are left out and the final pass runs again with the
    calibration's loss (``rerun(tr, None, scale)``; each returns the trial after it); observations
    left out that fit the new solution come back, until the set left out stays the same (at most
    ``rounds`` times).  A board left with fewer than ``policy.min_board_dots`` dots is left out
    whole (its pose is not determined).
    Spots set aside earlier by their lines (``tr.set_aside``) are predictions at this geometry,
    not fitted residuals: those predicted near their line (:func:`predicted_fit`) come back
    and are judged with the rest (a board pose wrong when the lines were fitted made them look
    wrong), before the outliers are looked for and again once they are out (:func:`_bring_back`).  What stays
    left out is recorded in ``tr.repairs``.  ``find=False`` (the linear loss: a plain least-squares
    fit) looks for no outlier; only the spots set aside by their lines are judged again."""
    scale = tr.scale
    none_aside = np.zeros(int(tr.pk.counts[Kind.DOT]) + int(tr.pk.counts[Kind.SPOT]), bool)
    full, aside = tr.set_aside if tr.set_aside is not None else (tr.pk, none_aside)
    out = aside & ~predicted_fit(tr, full, aside)
    if not np.array_equal(out, aside):
        tr = rerun(use_all_but(tr, full, out), None, scale)
    whole = np.zeros_like(out)
    if find and not np.array_equal(_outliers(tr, full)[0], out):  # more than what stays set aside
        tr, out, whole = _robust_rounds(tr, full, out, starts, rerun, scale, rounds)
    tr = _readmit(tr, full, aside, out)
    if not out.any():
        return tr
    # the residuals that left them out, for the records
    _, norm, kind, limit, valid = _outliers(tr, full)
    tr, full, out = _bring_back(tr, full, aside, out, whole, rerun, scale)
    n_d = int(full.counts[Kind.DOT])
    records = []
    for i in np.flatnonzero(out & ~aside):  # those set aside and still out have their record
        if i < n_d:
            src, laser = _dot_source(tr, i, full), None
        else:
            src, laser = _spot_source(tr, i - n_d, full), int(np.asarray(full.spot_laser)[i - n_d])
        k = int(kind[i])
        if whole[i]:
            why = "its board's pose in this view is not determined: "
            why += f"fewer than {tr.policy.min_board_dots} of its dots agree"
        elif not valid[i]:
            why = "its prediction falls off the mirror or the sensor (out of the model's reach)"
        else:
            why = f"residual {norm[i]:.3g} px beyond {limit[k]:.3g} px ({tr.policy.outlier_sigmas:g} sigma of the "
            why += f"{KIND_NAMES[k]}s, at least {tr.policy.min_outlier_px:g} px)"
        records.append(
            Repair(
                **src,
                action="left out",
                reason=why,
                residual_px=float(norm[i]) if valid[i] and not whole[i] else None,
                laser=laser,
                whole_board=bool(whole[i]),
            )
        )
    return tr.with_repairs(*records)


def use_all_but(tr: "Trial", full: Packed, out: np.ndarray) -> "Trial":
    """The trial solving ``full`` without the rows where ``out`` holds (dots, then spots)."""
    n_d = int(full.counts[Kind.DOT])
    return tr.using(full.select(~out[:n_d], ~out[n_d:]))


def predicted_fit(tr: "Trial", full: Packed, rows: np.ndarray) -> np.ndarray:
    """Where ``rows`` holds: the observation of ``full`` is predicted, at the trial's solution,
    within ``policy.consensus_px`` (elsewhere False).  A left-out spot's residual is a prediction,
    which the spot's own weight would shrink: a laser with few spots predicts a good one several
    noise sigmas off, so it is judged as the lines' consensus judges a spot, then refitted."""
    if not rows.any():
        return np.zeros_like(rows)
    n = rows.size
    norm, _, valid = per_observation(tr.params, full)
    return rows & valid[:n] & (norm[:n] <= tr.policy.consensus_px)


def _robust_rounds(tr: "Trial", full: Packed, out, starts, rerun, scale: float, rounds: int):
    """The outliers of ``full`` found under the Cauchy loss, left out, and the final pass run
    again on the rest until the set stays the same (see :func:`leave_out`); ``out``: the rows
    left out so far.  Returns the trial, the rows left out and those of boards left out whole."""
    n_d = int(full.counts[Kind.DOT])
    # graduated: at a wide scale first, where the good observations of a dragged board still
    # pull (at the final scale they may already count as outliers: a local minimum)
    tr = rerun(tr, "cauchy", tr.policy.cauchy_widen * scale)
    tr = rerun(tr, "cauchy", scale)
    tr = starts(tr)
    tr = rerun(tr, "cauchy", scale)
    ran = False  # the final pass run again with the calibration's loss on what is kept
    whole = np.zeros_like(out)
    for _ in range(rounds):
        bad = _outliers(tr, full)[0]
        # a board with too few dots left: every dot and spot of it out
        pose_d, pose_s = np.asarray(full.dot_pose)[:n_d], np.asarray(full.spot_pose)[: len(out) - n_d]
        kept = np.bincount(pose_d[~bad[:n_d]], minlength=full.n_poses)
        min_dots = tr.policy.min_board_dots
        weak = (kept < min_dots) & (np.bincount(pose_d, minlength=full.n_poses) >= min_dots)
        whole = np.concatenate([weak[pose_d], weak[pose_s]])
        bad |= whole
        if ran and np.array_equal(bad, out):
            break
        out = bad
        tr = rerun(use_all_but(tr, full, out), None, scale)
        ran = True
    return tr, out, whole


def _bring_back(
    tr: "Trial", full: Packed, aside, out, whole, rerun, scale: float
) -> tuple["Trial", Packed, np.ndarray]:
    """Observations left out that fit once the outliers are gone come back: a dot that lies on
    another grid position of its board (one not seen in that view) with that position, a spot
    that lies on exactly one other laser's line (within ``policy.consensus_px``, as the consensus
    looks for it: a left-out spot's residual is a prediction) with that laser, and a spot set
    aside by its lines that its own line now predicts (:func:`predicted_fit`).  The spots are
    kept only if they fit once refitted.  Records the changes; returns the trial, the problem
    (with the new labels) and the rows still left out."""
    n_d, n_s = int(full.counts[Kind.DOT]), int(full.counts[Kind.SPOT])
    _, norm, _, limit, valid = _outliers(tr, full)
    cand = out & ~whole
    own = predicted_fit(tr, full, cand & aside)
    moved = _regrid(tr, full, cand, limit[0])
    lasers = {i: k for i, k in _relaser(tr, full, cand, tr.policy.consensus_px).items() if not own[i]}
    if not (moved or lasers or own.any()):
        return tr, full, out
    old_full, old_labels = full, np.asarray(full.spot_laser)[:n_s]
    labels = old_labels.copy()
    for i, k in lasers.items():
        labels[i - n_d] = k
    full = _with_dot_labels(full, tr.obs, moved).select(np.ones(n_d, bool), np.ones(n_s, bool), labels)
    out = out & ~own
    out[list(moved) + list(lasers)] = False
    tr = rerun(use_all_but(tr, full, out), None, scale)
    still_bad = _outliers(tr, full)[0]
    misfit = [i for i in lasers if still_bad[i]]
    if misfit or (own & still_bad).any():  # still beyond the noise: out again, with its own label
        for i in misfit:
            labels[i - n_d] = old_labels[i - n_d]
            del lasers[i]
        full = full.select(np.ones(n_d, bool), np.ones(n_s, bool), labels)
        out[misfit] = True
        out |= own & still_bad
        tr = rerun(use_all_but(tr, full, out), None, scale)
    tr, _ = take_spot_records(tr, full, np.flatnonzero(own & ~out))
    norm_new = per_observation(tr.params, full)[0]
    for i, k in moved.items():
        tr = tr.with_repairs(
            Repair(
                **_dot_source(tr, i, old_full),
                action="relabelled",
                reason=f"lies on grid position {k} of its board (not seen otherwise), not on its own",
                residual_px=float(norm[i]) if valid[i] else None,
                new_index=k,
                new_residual_px=float(norm_new[i]),
            )
        )
    for i, k in lasers.items():
        # its residual under its own label: now, else where the lines set it aside
        tr, taken = take_spot_records(tr, full, [i])
        before = [r.residual_px for r in taken]
        tr = tr.with_repairs(
            Repair(
                **_spot_source(tr, i - n_d, full),
                action="relabelled",
                reason=f"lies on laser {k}'s line {AT_THE_FINAL_GEOMETRY}, not on its own",
                residual_px=float(norm[i]) if valid[i] else (before[0] if before else None),
                laser=int(old_labels[i - n_d]),
                new_laser=k,
                new_residual_px=float(norm_new[i]),
            )
        )
    return tr, full, out


def take_spot_records(tr: "Trial", full: Packed, rows) -> tuple["Trial", list[Repair]]:
    """The trial without the records of the spots in ``rows`` of ``full`` (counted after the
    dots) in its ``repairs``, and those records."""
    n_d = int(full.counts[Kind.DOT])
    keys = {(src["view"], src["index"]) for src in (_spot_source(tr, i - n_d, full) for i in rows)}
    mine = [r.kind == "spot" and (r.view, r.index) in keys for r in tr.repairs]
    taken = [r for r, m in zip(tr.repairs, mine, strict=True) if m]
    kept = tuple(r for r, m in zip(tr.repairs, mine, strict=True) if not m)
    return dataclasses.replace(tr, repairs=kept), taken


def _readmit(tr: "Trial", full: Packed, aside: np.ndarray, out: np.ndarray) -> "Trial":
    """The trial without the records of the spots set aside by their lines that are no longer left out."""
    return take_spot_records(tr, full, np.flatnonzero(aside & ~out))[0]


def _probe(tr: "Trial", kind: Kind, **rows) -> tuple[np.ndarray, np.ndarray]:
    """:func:`probe_at` the trial's solution and problem."""
    return probe_at(tr.params, tr.pk, kind, **rows)


def _relaser(tr: "Trial", full: Packed, candidates: np.ndarray, limit: float) -> dict[int, int]:
    """For the spot rows of ``full`` where ``candidates`` holds: the one other laser whose spot on
    the row's board, at the trial's solution, lies within ``limit`` px of its pixel (row, counted
    after the dots, -> laser); rows with none or several are not listed."""
    n_d, n_s = int(full.counts[Kind.DOT]), int(full.counts[Kind.SPOT])
    rows = np.flatnonzero(candidates[n_d : n_d + n_s])
    if not rows.size or tr.obs.n_lasers < 2:
        return {}
    own = np.asarray(full.spot_laser)[:n_s]
    cand = [(j, k) for j in rows for k in range(tr.obs.n_lasers) if k != own[j]]
    norm, ok = _probe(
        tr,
        Kind.SPOT,
        spot_pose=np.asarray([full.spot_pose[j] for j, _ in cand], np.int64),
        spot_laser=np.asarray([k for _, k in cand], np.int64),
        spot_pixels=np.asarray([full.spot_pixels[j] for j, _ in cand], float),
    )
    near = ok & (norm <= limit)
    out = {}
    for j in rows:
        hits = [k for m, (jj, k) in enumerate(cand) if jj == j and near[m]]
        if len(hits) == 1:
            out[n_d + int(j)] = hits[0]
    return out


def _regrid(tr: "Trial", full: Packed, candidates: np.ndarray, limit: float) -> dict[int, int]:
    """For the dot rows of ``full`` where ``candidates`` holds: the one grid position of its
    board, not seen in its view, whose projection at the trial's solution lies within ``limit``
    px of its pixel (row -> position index); rows with none or several are not listed."""
    n_d = int(full.counts[Kind.DOT])
    rows = [i for i in np.flatnonzero(candidates[:n_d])]
    if not rows or not full.dot_src:
        return {}
    seen: dict[tuple[int, str], set[int]] = {}
    for i, (v, b, j) in enumerate(full.dot_src):
        if not candidates[i]:
            seen.setdefault((v, b), set()).add(j)
    cand_row, cand_k, pose, pts, pix = [], [], [], [], []
    for i in rows:
        v, b, j = full.dot_src[i]
        grid = tr.obs.boards[b]
        for k in range(grid.shape[0]):
            if k != j and k not in seen.get((v, b), ()):
                cand_row.append(i), cand_k.append(k), pose.append(full.dot_pose[i])
                pts.append(grid[k]), pix.append(full.dot_pixels[i])
    if not cand_row or len(cand_row) > 4 * n_d:
        return {}
    norm, ok = _probe(
        tr,
        Kind.DOT,
        dot_pose=np.asarray(pose, np.int64),
        dot_points=np.asarray(pts, float),
        dot_pixels=np.asarray(pix, float),
    )
    near = ok & (norm <= limit)
    out = {}
    for i in rows:
        hits = [cand_k[m] for m in np.flatnonzero(near) if cand_row[m] == i]
        if len(hits) == 1:
            out[i] = hits[0]
    # two dots given one position: neither
    taken = [(full.dot_src[i][0], full.dot_src[i][1], k) for i, k in out.items()]
    return {i: k for (i, k), t in zip(out.items(), taken, strict=True) if taken.count(t) == 1}


def _with_dot_labels(pk: Packed, obs: Observations, moved: dict[int, int]) -> Packed:
    """``pk`` with dot row ``i`` labelled as grid position ``moved[i]`` of its board."""
    pts, src = np.array(pk.dot_points, float), list(pk.dot_src)
    for i, k in moved.items():
        v, b, _ = src[i]
        pts[i], src[i] = obs.boards[b][k], (v, b, k)
    return dataclasses.replace(pk, dot_points=pts, dot_src=tuple(src))
