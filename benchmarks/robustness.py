"""Robustness of the calibration to wrong labels and gross outliers: laser error against the bound, and the flags.

Run: ``python benchmarks/robustness.py [--seeds 3] [--shares 0,0.05,0.1,0.2] [--gross 0.05,0.1]
[--rows 0.25] [--regrid 0.25] [--grid 0.25] [--mix 0.1] [--noise 0.3] [--out FILE]``.

Scenes: the paper preset (10 lasers, 16 views) and an 8-laser rig at 12 views.  For each seed a
scene is simulated at ``--noise`` px and corrupted in one of these ways:

* ``labels``: a share of its laser spots is given the label of the laser next to it in azimuth
  (what a detector does when two beams' spots lie close); the pixels stay true;
* ``gross``: a share of its dots and of its spots is moved 5-50 px in a random direction (a
  blob taken for a dot, a reflection taken for a spot);
* ``rows``: in a share of its views, one row of one board's dots is labelled as the row next
  to it (each of those dots carries the pixel of its neighbour one row up, which keeps its own);
* ``regrid``: in a share of its views, one dot next to a grid position not seen there is
  labelled as that position (a grid one step off at its edge, for one dot);
* ``grid`` / ``grid_rigid`` (``--grid``): in a share of its views, the whole best-seen board
  labelled one row off, calibrated with free board poses and with the rigid box;
* ``mix`` (``--mix``): a share of dots and spots moved, the same share of spots relabelled, and
  a row off in 2.5 times that share of the views, together.

The corrupted observations are calibrated (``calibrate``) and compared with:

* the truth, per laser, over the bound of the clean scene (``cramer_rao``): position and
  direction error at the working point over the bound's standard deviation, RMS over the
  lasers and the worst laser;
* the calibration's own claim: the worst laser's error over its reported standard deviation
  (a confident wrong answer is a large ratio; an undetermined laser is counted apart), before
  and after the final consistency check scales the std of the lasers it flags
  and withdraws the std of the lasers that kept fewer than half their spots
  (``worst_laser_over_checked_std``, over the lasers that keep a std), how many runs the check
  raised an alarm in, and how many lasers it withdrew;
* the observations it flags, against the corrupted ones: those it relabelled or left out
  (``CalibrationResult.repairs``) and the report's outliers (residual above 5 sigma), each
  named by view, kind and index: precision and recall.

Goals (issue 17): 5 % wrong labels -> error <= 1.2x the bound, 10 % -> <= 1.5x, 20 % -> <= 2x or a
refusal naming the lasers; flag precision and recall >= 0.95.  Writes JSON with the machine.
"""

import argparse
import copy
import json
import time
from pathlib import Path

import numpy as np
from bench_forward import machine

from slcvjax import (
    CalibrationError,
    calibrate,
    cramer_rao,
    laser_errors,
    laser_std,
    laser_working_points,
    make_scene,
    report,
    require_determined,
    simulate,
)

RIGS = {"paper_10x16": (10, 16), "lasers8_views12": (8, 12)}


def relabel(obs, share: float, n_lasers: int, rng) -> tuple[object, set]:
    """``obs`` with ``share`` of its spots labelled as the laser next in azimuth (the preset's
    lasers go round the ring in index order), and the keys (:func:`key`) of those spots."""
    spots = [(v, j) for v, view in enumerate(obs.views) for j in range(len(view.spots))]
    k = int(round(share * len(spots)))
    picked = rng.choice(len(spots), size=k, replace=False) if k else []
    wrong = set()
    for i in picked:
        v, j = spots[i]
        s = obs.views[v].spots[j]
        s.laser = (s.laser + 1) % n_lasers
        wrong.add(("spot", obs.views[v].name, None, j))
    return obs, wrong


def gross(obs, share: float, rng) -> tuple[object, set]:
    """``obs`` with ``share`` of its seen dots and of its spots moved 5-50 px in a random direction."""
    wrong = set()
    dots = [
        (v, b, j)
        for v, view in enumerate(obs.views)
        for b, (_, seen) in view.boards.items()
        for j in np.flatnonzero(seen)
    ]
    spots = [(v, j) for v, view in enumerate(obs.views) for j in range(len(view.spots))]

    def shift():
        a = rng.uniform(0, 2 * np.pi)
        return rng.uniform(5, 50) * np.array([np.cos(a), np.sin(a)])

    for i in rng.choice(len(dots), size=int(round(share * len(dots))), replace=False):
        v, b, j = dots[i]
        obs.views[v].boards[b][0][j] += shift()
        wrong.add(("dot", obs.views[v].name, b, int(j)))
    for i in rng.choice(len(spots), size=int(round(share * len(spots))), replace=False):
        v, j = spots[i]
        obs.views[v].spots[j].pixel = obs.views[v].spots[j].pixel + shift()
        wrong.add(("spot", obs.views[v].name, None, j))
    return obs, wrong


def _best_boards(obs, share: float, rng):
    """In ``share`` of the views (drawn by ``rng``), the best-seen board: (view, name, its pixels
    and seen mask, which the caller edits in place, and the board's points)."""
    n = int(round(share * len(obs.views)))
    for v in rng.choice(len(obs.views), size=n, replace=False):
        view = obs.views[v]
        b = max(view.boards, key=lambda name: int(view.boards[name][1].sum()))
        px, seen = view.boards[b]
        yield view, b, px, seen, obs.boards[b]


def shift_rows(obs, share: float, rng) -> tuple[object, set]:
    """``obs`` with, in ``share`` of its views, one row of its best-seen board labelled one row
    off: each dot of the row whose neighbour one row up is seen takes that neighbour's pixel."""
    wrong = set()
    for view, b, px, seen, pts in _best_boards(obs, share, rng):
        ys = np.unique(np.round(pts[:, 1], 6))
        cols = np.round(pts[:, 0], 6)
        pairs_by_row = []
        for r in range(len(ys) - 1):
            here = np.flatnonzero(seen & (np.round(pts[:, 1], 6) == ys[r]))
            up = {cols[k]: k for k in np.flatnonzero(seen & (np.round(pts[:, 1], 6) == ys[r + 1]))}
            pairs = [(j, up[cols[j]]) for j in here if cols[j] in up]
            if len(pairs) >= 3:
                pairs_by_row.append(pairs)
        if not pairs_by_row:
            continue
        for j, k in pairs_by_row[rng.integers(len(pairs_by_row))]:
            px[j] = px[k]
            wrong.add(("dot", view.name, b, int(j)))
    return obs, wrong


def shift_grid(obs, share: float, rng) -> tuple[object, set]:
    """``obs`` with, in ``share`` of its views, the whole of its best-seen board labelled one row
    off: every dot whose neighbour one row up is seen takes that neighbour's pixel, and the dots
    of the top row seen become unseen (a grid placed one row off as a whole)."""
    wrong = set()
    for view, b, px, seen, pts in _best_boards(obs, share, rng):
        ys = np.round(pts[:, 1], 6)
        rows = np.unique(ys)
        cols = np.round(pts[:, 0], 6)
        old_px, old_seen = px.copy(), seen.copy()
        at = {(ys[k], cols[k]): k for k in range(len(pts))}
        for j in range(len(pts)):
            r = int(np.searchsorted(rows, ys[j]))
            k = at.get((rows[r + 1], cols[j])) if r + 1 < len(rows) else None
            if k is not None and old_seen[k]:
                px[j], seen[j] = old_px[k], True
                wrong.add(("dot", view.name, b, int(j)))
            else:
                seen[j] = False
    return obs, wrong


def mixture(obs, share: float, n_lasers: int, rng) -> tuple[object, set]:
    """``share`` of the dots and spots moved (:func:`gross`), ``share`` of the spots labelled as the
    next laser (:func:`relabel`), and one row off in ``2.5 share`` of the views (:func:`shift_rows`)."""
    obs, a = gross(obs, share, rng)
    obs, b = relabel(obs, share, n_lasers, rng)
    obs, c = shift_rows(obs, 2.5 * share, rng)
    return obs, a | b | c


def regrid(obs, share: float, rng) -> tuple[object, set]:
    """``obs`` with, in ``share`` of the views where any board has one, one seen dot that lies
    next to a grid position not seen there labelled as that position (a grid placed one step
    off at its edge, for one dot)."""
    wrong = set()
    choices = {}
    for v, view in enumerate(obs.views):
        for b, (_, seen) in view.boards.items():
            pts = obs.boards[b]
            spacing = np.min(np.linalg.norm(pts[1:] - pts[0], axis=1))
            pairs = [
                (b, j, k)
                for j in np.flatnonzero(seen)
                for k in np.flatnonzero(~seen)
                if seen.sum() >= 6 and np.linalg.norm(pts[j] - pts[k]) < 1.5 * spacing
            ]
            choices.setdefault(v, []).extend(pairs)
    views = [v for v, c in choices.items() if c]
    for v in rng.choice(views, size=min(len(views), int(round(share * len(obs.views)))), replace=False):
        view = obs.views[v]
        b, j, k = choices[v][rng.integers(len(choices[v]))]
        px, seen = view.boards[b]
        px[k], seen[k], seen[j] = px[j], True, False
        wrong.add(("dot", view.name, b, int(k)))
    return obs, wrong


def key(item: dict) -> tuple:
    """A flagged observation's identity: kind, view, board (dots only), index."""
    return (item["kind"], item["view"], item["board"] if item["kind"] == "dot" else None, item["index"])


def one(n_lasers: int, n_views: int, mode: str, share: float, seed: int, noise: float) -> dict:
    scene = make_scene("paper", n_lasers=n_lasers, n_views=n_views)
    clean, truth = simulate(scene, noise=noise, seed=seed)
    bound = cramer_rao(truth, clean, noise)
    rng = np.random.default_rng(1000 + seed)
    obs = copy.deepcopy(clean)
    if mode == "labels":
        obs, wrong = relabel(obs, share, n_lasers, rng)
    elif mode == "gross":
        obs, wrong = gross(obs, share, rng)
    elif mode == "regrid":
        obs, wrong = regrid(obs, share, rng)
    elif mode in ("grid", "grid_rigid"):
        obs, wrong = shift_grid(obs, share, rng)
    elif mode == "mix":
        obs, wrong = mixture(obs, share, n_lasers, rng)
    else:
        obs, wrong = shift_rows(obs, share, rng)
    base = {"mode": mode, "share": share, "seed": seed, "corrupted": len(wrong)}
    t0 = time.perf_counter()
    try:
        res = require_determined(calibrate(obs, rigid=mode == "grid_rigid"))
    except CalibrationError as e:
        return base | {"refused": str(e), "seconds": time.perf_counter() - t0}
    seconds = time.perf_counter() - t0
    pos, ang = laser_errors(res.rig, truth.rig, bound["x_ref"])
    p_ratio, a_ratio = pos / bound["position_std_mm"], ang / bound["direction_std_rad"]
    x_ref = laser_working_points(res.rig, res.params.poses, res.packed)
    sd_p, sd_a = laser_std(res.rig, np.asarray(res.cov.glob), x_ref)
    determined = np.isfinite(sd_p) & np.isfinite(sd_a)
    full = report(res, obs)
    rep, unc = full["residuals"], full["uncertainty"]
    # the final check's std factors (1 where it passed): the std the report gives
    factor = np.array([x.get("std_scale", 1.0) for x in unc["lasers"]])[: len(sd_p)]
    # ... and the lasers whose std it withdrew (most of their spots left out: a possible wrong consensus)
    withdrawn = np.array([x.get("position_std_mm") is None for x in unc["lasers"]])[: len(sd_p)]
    flagged = {key(o) for o in rep["outliers"]} | {
        (r.kind, r.view, r.board if r.kind == "dot" else None, r.index) for r in res.repairs if not r.whole_board
    }
    names = {view.name: view for view in obs.views}
    for r in res.repairs:  # a board left out whole flags each of its dots in that view
        if r.whole_board and r.view in names and r.board in names[r.view].boards:
            flagged |= {("dot", r.view, r.board, int(j)) for j in np.flatnonzero(names[r.view].boards[r.board][1])}
    hit = len(flagged & wrong)
    claim = np.maximum(pos / sd_p, ang / sd_a)[determined]
    claim_scaled = (np.maximum(pos / sd_p, ang / sd_a) / factor)[determined & ~withdrawn]
    return base | {
        "seconds": seconds,
        "final_pass": res.passes[-1].result,
        "position_over_bound_rms": float(np.sqrt(np.mean(p_ratio**2))),
        "direction_over_bound_rms": float(np.sqrt(np.mean(a_ratio**2))),
        "worst_laser_over_bound": float(max(p_ratio.max(), a_ratio.max())),
        "worst_laser_over_reported_std": float(claim.max()) if claim.size else None,
        "worst_laser_over_checked_std": float(claim_scaled.max()) if claim_scaled.size else None,
        "check_failed": [f["group"] for f in unc["consistency"]["failed"]],
        "withdrawn_lasers": np.flatnonzero(withdrawn & determined).tolist(),
        "undetermined_lasers": np.flatnonzero(~determined).tolist(),
        "flagged": len(flagged),
        "relabelled": sum(r.action == "relabelled" for r in res.repairs),
        "left_out": sum(r.action == "left out" for r in res.repairs),
        "boards_left_out": len({(r.view, r.board) for r in res.repairs if r.whole_board}),
        "flag_precision": hit / len(flagged) if flagged else None,
        "flag_recall": hit / len(wrong) if wrong else None,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--shares", default="0,0.05,0.1,0.2", help="shares of spots with a wrong label")
    ap.add_argument("--gross", default="0.05,0.1", help="shares of dots and spots moved 5-50 px")
    ap.add_argument("--rows", default="0.25", help="shares of views with a row of dots labelled one row off")
    ap.add_argument("--regrid", default="0.25", help="shares of views with a dot labelled as an unseen grid position")
    ap.add_argument("--grid", default="", help="shares of views with a whole board one row off (free poses and rigid)")
    ap.add_argument(
        "--mix", default="", help="shares of the mixture: moved, relabelled, and rows off in 2.5x the views"
    )
    ap.add_argument("--noise", type=float, default=0.3)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()

    def shares(text):
        return [float(s) for s in text.split(",") if s]

    cases = [("labels", s) for s in shares(args.shares)] + [("gross", s) for s in shares(args.gross)]
    cases += [("rows", s) for s in shares(args.rows)] + [("regrid", s) for s in shares(args.regrid)]
    cases += [(m, s) for s in shares(args.grid) for m in ("grid", "grid_rigid")]
    cases += [("mix", s) for s in shares(args.mix)]
    rows = []
    for rig, (n_lasers, n_views) in RIGS.items():
        for mode, share in cases:
            for seed in range(args.seeds):
                r = one(n_lasers, n_views, mode, share, seed, args.noise) | {"rig": rig}
                rows.append(r)
                if "refused" in r:
                    print(f"{rig:16s} {mode:6s} {share:4.0%} seed {seed}: refused: {r['refused']}", flush=True)
                    continue
                print(
                    f"{rig:16s} {mode:6s} {share:4.0%} seed {seed}: err/bound {r['position_over_bound_rms']:6.2f} "
                    f"{r['direction_over_bound_rms']:6.2f}, worst laser {r['worst_laser_over_bound']:6.1f}x bound, "
                    f"{r['worst_laser_over_reported_std']:6.1f}x its std; flagged {r['flagged']:3d}, "
                    f"{r['corrupted']:3d} corrupted (precision {r['flag_precision']}, recall {r['flag_recall']})",
                    flush=True,
                )
    summary = []
    for rig in RIGS:
        for mode, share in cases:
            rs = [r for r in rows if r["rig"] == rig and r["mode"] == mode and r["share"] == share]
            ok = [r for r in rs if "refused" not in r]

            def rms(k, ok=ok):
                return float(np.sqrt(np.mean([r[k] ** 2 for r in ok]))) if ok else None

            def mean(k, ok=ok):
                vals = [r[k] for r in ok if r[k] is not None]
                return float(np.mean(vals)) if vals else None

            claims = [r["worst_laser_over_reported_std"] for r in ok if r["worst_laser_over_reported_std"] is not None]
            summary.append(
                {
                    "rig": rig,
                    "mode": mode,
                    "share": share,
                    "runs": len(rs),
                    "refused": len(rs) - len(ok),
                    "position_over_bound": rms("position_over_bound_rms"),
                    "direction_over_bound": rms("direction_over_bound_rms"),
                    "worst_laser_over_bound": max((r["worst_laser_over_bound"] for r in ok), default=None),
                    "worst_laser_over_reported_std": max(claims, default=None),
                    "worst_laser_over_checked_std": max(
                        (
                            r["worst_laser_over_checked_std"]
                            for r in ok
                            if r["worst_laser_over_checked_std"] is not None
                        ),
                        default=None,
                    ),
                    "check_alarms": sum(bool(r["check_failed"]) for r in ok),
                    "withdrawn_lasers": sum(len(r["withdrawn_lasers"]) for r in ok),
                    "undetermined_lasers": sum(len(r["undetermined_lasers"]) for r in ok),
                    "flagged_mean": mean("flagged"),
                    "boards_left_out": sum(r["boards_left_out"] for r in ok),
                    "flag_precision": mean("flag_precision"),
                    "flag_recall": mean("flag_recall"),
                }
            )

    def f(x, nd=2):
        return "-" if x is None else f"{x:.{nd}f}"

    print(
        "rig              kind   share  pos/bound dir/bound  worst/bound  worst/std  checked  alarms  flagged "
        "precision recall refused"
    )
    for s in summary:
        print(
            f"{s['rig']:16s} {s['mode']:6s} {s['share']:5.0%} {f(s['position_over_bound']):>9s} "
            f"{f(s['direction_over_bound']):>9s} {f(s['worst_laser_over_bound'], 1):>11s} "
            f"{f(s['worst_laser_over_reported_std'], 1):>10s} {f(s['worst_laser_over_checked_std'], 1):>8s} "
            f"{s['check_alarms']:7d} {f(s['flagged_mean'], 1):>7s} "
            f"{f(s['flag_precision']):>9s} {f(s['flag_recall']):>6s} {s['boards_left_out']:10d} {s['refused']:7d}"
        )
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        doc = {"benchmark": "robustness", "machine": machine(), "noise_px": args.noise, "summary": summary}
        args.out.write_text(json.dumps(doc | {"runs": rows}, indent=1))
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
