"""The pass schedule of :func:`slcvjax.calibrate` after the staged start, and its driver.

A. camera, mirror, board and direct-view poses from dots, rim and corners (lasers frozen, spots
   weighted 0): the staged mirror tilt is weakly observable from the rim alone and the boards fix
   it (A2 again where a board's flip changed);
B. the lasers refitted on the refined geometry by consensus (spots that lie on another laser's
   line are given that laser, see :func:`slcvjax.calibration.laser_fit.fit_lasers`), then everything
   jointly with a Huber loss at 3 sigma (sigma estimated robustly from the residuals); every board
   then tries its other starts (flipped twin, carried pose), and the spots the consensus set aside
   that this solution puts on their own line come back;
C. the same with sigma re-estimated at B's solution (the final pass); where a dot or spot lies
   beyond 5 sigma, the gross outliers are found under the Cauchy loss, left out, and C runs again
   (C3, :func:`slcvjax.calibration.repairs.leave_out`); where a board still fits badly, its other
   starts again and C again (C2).

:data:`SCHEDULE` is the table of these steps; :func:`calibrate_lockstep` runs it over one or
several calibrations at once (an executor of :mod:`slcvjax.calibration.executors` runs each pass's
solves).
"""

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..observations.problem import (
    KIND_NAMES,
    Kind,
    stack_poses,
    unstack_poses,
)
from .base import CalibrationError
from .board_starts import keep_better, misfit_boards, other_starts_of, turned
from .covariance import covariance_and_noise, robust_sigma
from .executors import solve_vmap
from .laser_fit import aimed_lasers, fit_lasers
from .options import CalibrationOptions
from .params import Params, make_masks, unpad_params
from .passes import (
    PASS_A,
    PASS_A2,
    PASS_B,
    PASS_B2,
    PASS_C,
    PASS_C2,
    PASS_C3,
    RTOL_START,
    TWIN_SOLVE,
    PassSpec,
    record_pass,
    solve_job,
)
from .repairs import leave_out, predicted_fit, relabel_spots, take_spot_records, use_all_but
from .result import CalibrationResult
from .sheet_fit import fit_sheets
from .staged import board_poses
from .trial import Trial, start_trial


class _Lockstep:
    """The trials of :func:`calibrate_lockstep` and how a pass's solves run over them: the driver
    that :data:`SCHEDULE`'s steps call (``solver`` runs a pass's solves, all trials' at once).
    Each trial is an immutable :class:`Trial`; ``trials[i]`` is the current state of the i-th
    calibration, replaced by each step that changes it."""

    def __init__(self, trials: list[Trial], solver, options: CalibrationOptions, bar=None):
        self.trials, self.solver, self.options, self.policy = trials, solver, options, options.robust
        self.freeze = set(options.freeze)
        self.loss, self.loss_scale, self.max_steps, self.bar = (
            options.robust.loss,
            options.robust.loss_scale,
            options.max_steps,
            bar,
        )
        self.every = list(range(len(trials)))

    def solve(self, spec: PassSpec, chosen: list[int], scale: float | None = None) -> None:
        """The pass ``spec`` of the ``chosen`` trials from where they are (``scale``: its loss
        scale instead of the one ``spec`` gives)."""
        trials = self.trials
        for i in chosen:
            if scale is not None:
                trials[i] = dataclasses.replace(trials[i], scale=scale)
            elif spec.scale_floor is not None:
                trials[i] = self.rescale(trials[i], spec.scale_floor)
        jobs = [solve_job(trials[i], trials[i].params, spec) for i in chosen]
        own = spec.steps if spec.steps is not None and spec.steps < self.max_steps else None  # the pass's own limit
        solved = self.solver(jobs, spec.loss or self.loss, own or self.max_steps, size=len(trials))
        for i, res in zip(chosen, solved, strict=True):
            tr = record_pass(trials[i], spec.name, res, own)
            trials[i] = dataclasses.replace(tr, params=unpad_params(tr.layout, res.params))
        if self.bar is not None:
            self.bar.set_postfix_str(spec.name.split(":")[0])

    def rescale(self, tr: Trial, floor: float) -> Trial:
        """The trial with its loss scale where it stands: the user's, else ``policy.scale_sigmas`` x
        the robust noise sigma, at least ``floor`` px."""
        return dataclasses.replace(
            tr, scale=self.loss_scale or self.policy.scale_sigmas * max(robust_sigma(tr.params, tr.pk), floor)
        )

    def other_starts(self, chosen: list[int], turned_only: bool, pass_loss: str | None = None) -> list[int]:
        """Each board pose of the ``chosen`` trials swapped for its flipped twin, or for its pose
        carried over from another view (:func:`carried_poses`), where that fits better, both refined
        with the rig held (``turned_only``: only swaps that turn the board; ``pass_loss``: a loss
        for this instead of the calibration's).  Returns the trials where any board turned."""
        trials, this_loss = self.trials, pass_loss or self.loss
        chosen = [i for i in chosen if trials[i].pk.n_poses]
        starts = [other_starts_of(trials[i].params, trials[i].pk, trials[i].masks) for i in chosen]
        # one solve per kind of start over the chosen trials: the batch shapes of a pass
        solved = [
            self.solver(
                [solve_job(trials[i], c, TWIN_SOLVE, hold) for i, (c, hold) in zip(chosen, kind, strict=True)],
                this_loss,
                self.max_steps,
                size=len(trials),
            )
            for kind in zip(*starts, strict=True)
        ]
        turned = []
        for n_i, i in enumerate(chosen):
            tr = trials[i]
            params, n_moved = tr.params, 0
            for res in (kind[n_i] for kind in solved):
                other = unpad_params(tr.layout, res.params)
                params, n = keep_better(params, other, tr.pk, this_loss, tr.scale, turned_only)
                n_moved += n
            trials[i] = tr = dataclasses.replace(tr, params=params)
            if n_moved:
                trials[i] = tr.noted(f"{n_moved} board pose(s) turned after it")
                turned.append(i)
        return turned

    def aimed_starts(self, chosen: list[int]) -> None:
        """B again from every laser aimed from the camera's centre through its spots
        (:func:`slcvjax.calibration.laser_fit.aimed_lasers`) where that turns a laser by more than
        :attr:`RobustPolicy.aimed_turn_deg`; kept where it ends at a lower cost.  A laser whose spots lie
        along a few mm of its line at 140 mm (measured: the preset at 0.9 px, seeds 12 and 14)
        went from B into a line nearly along its boards, 82 degrees off, while a start near
        the truth ended at a lower cost."""
        trials, picked, starts = self.trials, [], []
        for i in chosen:
            tr = trials[i]
            p = tr.params
            if p.rig.lasers.n == 0:
                continue
            aimed = aimed_lasers(p.rig.camera, p.rig.mirror, tr.pk, unstack_poses(p.poses), p.rig.lasers)
            cos = np.abs(np.sum(np.asarray(aimed.directions) * np.asarray(p.rig.lasers.directions), axis=1))
            if np.any(cos < np.cos(np.radians(self.policy.aimed_turn_deg))):
                picked.append(i)
                starts.append(Params(p.rig.with_lasers(aimed), p.poses, p.chess))
        if not picked:
            return
        jobs = [solve_job(trials[i], st, PASS_B2) for i, st in zip(picked, starts, strict=True)]
        now = [solve_job(trials[i], trials[i].params, PASS_B2) for i in picked]
        solved = self.solver(jobs, self.loss, self.max_steps, size=len(trials))
        # B's own final cost held the rim rows' normalisation of B's start: the cost at B's
        # solution is taken again with the one the aimed solve started from (the same rig)
        current = self.solver(now, self.loss, 0, size=len(trials))
        for i, res, cur in zip(picked, solved, current, strict=True):
            kept = float(res.cost) < float(cur.cost)
            tr = record_pass(
                trials[i], PASS_B2.name, res, None, "kept: a lower cost than B's" if kept else "B's cost is lower"
            )
            trials[i] = dataclasses.replace(tr, params=unpad_params(tr.layout, res.params)) if kept else tr

    def result(self, tr: Trial) -> CalibrationResult:
        """A trial's result at the end of the schedule: its solution, covariance and passes."""
        cov, noise = covariance_and_noise(tr.params, tr.pk, tr.masks, self.loss, tr.scale)
        return CalibrationResult(
            tr.params,
            tr.st,
            tr.pk,
            tr.masks,
            cov,
            self.loss,
            float(tr.scale),
            tr.passes,
            {"staged_s": tr.t_staged, "total_s": time.perf_counter() - tr.t0},
            dict(zip(KIND_NAMES, noise.sigma.tolist(), strict=False)),
            tr.repairs,
            undetermined_lasers=tr.undetermined,
            observations=tr.obs,
            options=self.options,
            undetermined_sheets=tr.undetermined_sheets,
        )


def _first_pass(d: _Lockstep) -> None:
    """A: the geometry without the lasers, only far enough to decide the boards' flips again
    (to the start's tolerance where the poses are held: no flip is decided again)."""
    d.solve(PASS_A if "poses" not in d.freeze else dataclasses.replace(PASS_A, rtol=RTOL_START), d.every)


def _reflip(d: _Lockstep) -> None:
    """The boards' flips decided again on the refined geometry, then A2 where any board turned
    (otherwise pass A's poses already fit the dots on this geometry).  Where a board's dots no
    longer back-project onto the mirror at A's solution, the trial keeps A's poses (noted)."""
    again = []
    for i, tr in enumerate(d.trials):
        p = tr.params
        try:
            poses = stack_poses(board_poses(p.rig.camera, p.rig.mirror, tr.pk, start=p.poses)[0])
        except CalibrationError as e:
            d.trials[i] = tr.noted(f"the boards' flips not decided again: {e}")
            continue
        if np.any(turned(poses, p.poses)):
            d.trials[i] = dataclasses.replace(tr, params=Params(p.rig, poses, p.chess))
            again.append(i)
    if again:
        d.solve(PASS_A2, again)


def _refit_lasers(d: _Lockstep) -> None:
    """The lasers refitted on the refined geometry (:func:`slcvjax.calibration.laser_fit.fit_lasers`):
    spots relabelled or left out where they fit another laser's line or none, and a laser whose
    spots cannot fix a line held (undetermined)."""
    for i, tr in enumerate(d.trials):
        p = tr.params
        poses = unstack_poses(p.poses)
        fit = fit_lasers(p.rig.camera, p.rig.mirror, tr.pk, poses, tr.obs.n_points, policy=d.policy)
        rig = p.rig.with_lasers(fit.lasers)
        held_sheets = tr.undetermined_sheets
        if rig.has_sheets:
            sf = fit_sheets(rig.camera, rig.mirror, tr.pk, poses, rig.sheets.kinds, start=rig.sheets)
            rig, held_sheets = rig.with_sheets(sf.sheets), sf.held
        params = Params(rig, p.poses, p.chess)
        masks = make_masks(params, tr.freeze, tr.estimate, held_lasers=fit.held, held_sheets=held_sheets)
        tr = dataclasses.replace(tr, params=params, undetermined=fit.held, masks=masks, undetermined_sheets=held_sheets)
        if held_sheets and tr.pk.has_stripes:  # a sheet its stripes cannot fix: held, its samples go
            n_t = int(tr.pk.counts[Kind.STRIPE])
            tr = tr.using(tr.pk.select_stripes(~np.isin(np.asarray(tr.pk.stripe_sheet)[:n_t], held_sheets)))
        d.trials[i] = relabel_spots(tr, fit)


def _rescale(d: _Lockstep) -> None:
    """The loss scale re-estimated at B's solution: the user's, else 3 x the robust noise sigma."""
    for i, tr in enumerate(d.trials):
        d.trials[i] = d.rescale(tr, PASS_B.scale_floor)


def _readmit_set_aside(d: _Lockstep) -> None:
    """The spots set aside by their lines (:func:`relabel_spots`) that the joint solution so far
    predicts near their own line (:func:`predicted_fit`) come back before C, which then fits
    them (rather than C again once they are judged on C's solution: :func:`leave_out` judges
    those still aside there)."""
    for i, tr in enumerate(d.trials):
        if tr.set_aside is None:
            continue
        full, aside = tr.set_aside
        back = predicted_fit(tr, full, aside)
        if not back.any():
            continue
        tr = take_spot_records(tr, full, np.flatnonzero(back))[0]
        d.trials[i] = use_all_but(dataclasses.replace(tr, set_aside=(full, aside & ~back)), full, aside & ~back)


def _leave_outliers(d: _Lockstep) -> None:
    """Observations far beyond the noise (gross outliers: a wrong dot, a reflection taken for a
    spot) left out and C run again (C3), so that none is spread over good ones (:func:`leave_out`)."""
    for i in d.every:

        def rerun(tr, pass_loss, scale, i=i):
            spec = PASS_C3
            if pass_loss:
                name = f"C3: joint (Cauchy loss at {scale:.3g} px, to find the outliers)"
                spec = dataclasses.replace(PASS_C3, name=name, loss=pass_loss)
            d.trials[i] = tr
            d.solve(spec, [i], scale)
            return d.trials[i]

        def starts(tr, i=i):
            d.trials[i] = tr
            d.other_starts([i], turned_only=False, pass_loss="cauchy")
            return d.trials[i]

        d.trials[i] = leave_out(d.trials[i], starts, rerun, find=d.loss != "linear")


def _turn_misfits(d: _Lockstep, rounds: int = 3) -> None:
    """A pose carried after B from a board still wrong then may be wrong yet: where a board fits
    badly the other starts again, and C again (C2) where a board turned, until none turns (at
    most ``rounds`` times)."""
    again = [i for i in d.every if misfit_boards(d.trials[i], d.loss)]
    for _ in range(rounds):
        again = d.other_starts(again, turned_only=True)
        if not again:
            break
        d.solve(PASS_C2, again)


@dataclass(frozen=True)
class Step:
    """One step of :data:`SCHEDULE`: what it does, the function that does it over the trials, the
    parameter block whose freezing skips it (None: it always runs), and the joint passes it may
    run (:class:`slcvjax.calibration.passes.PassSpec`)."""

    does: str
    run: Callable[[_Lockstep], None]
    unless_frozen: str | None = None
    passes: tuple[PassSpec, ...] = ()


# :func:`calibrate`'s schedule after the staged start, in order.  C keeps every kind at weight 1:
# weighting each by its own noise (the rim's is larger in rendered images) made the lasers worse
# from images (benchmarks/images_vs_file.py), where the dots' errors are mostly systematic.
SCHEDULE: tuple[Step, ...] = (
    Step("A: camera, mirror and poses, the lasers held and the spots unweighted", _first_pass, None, (PASS_A,)),
    Step("the boards' flips decided again; A2 where any turned", _reflip, "poses", (PASS_A2,)),
    Step("the lasers refitted on that geometry, their spots relabelled", _refit_lasers, "lasers"),
    Step("B: everything", lambda d: d.solve(PASS_B, d.every), None, (PASS_B,)),
    Step(
        "B2: B from lasers aimed through their spots, kept where better",
        lambda d: d.aimed_starts(d.every),
        "lasers",
        (PASS_B2,),
    ),
    Step("the loss scale re-estimated", _rescale),
    Step(
        "every board's other starts, swapped in where better",
        lambda d: d.other_starts(d.every, False),
        "poses",
        (TWIN_SOLVE,),
    ),
    Step("the spots set aside by their lines that fit now readmitted", _readmit_set_aside),
    Step("C: the final pass", lambda d: d.solve(PASS_C, d.every), None, (PASS_C,)),
    Step("C3: the gross outliers left out, C again", _leave_outliers, None, (PASS_C3, TWIN_SOLVE)),
    Step(
        "C2: badly fitting boards' other starts, C again where one turned",
        _turn_misfits,
        "poses",
        (TWIN_SOLVE, PASS_C2),
    ),
)


def schedule_table() -> str:
    """:data:`SCHEDULE` as a Markdown table (the formulation page holds it; a test keeps them equal)."""
    rows = ["| step | what it does | skipped when frozen | its joint passes |", "| --- | --- | --- | --- |"]
    for i, step in enumerate(SCHEDULE, 1):
        passes = "<br>".join(f"**{p.name}**: {p.describe()}" for p in step.passes) or "(no solve of its own)"
        rows.append(f"| {i} | {step.does} | {step.unless_frozen or ''} | {passes} |")
    return "\n".join(rows) + "\n"


def calibrate_lockstep(obs_list, camera, options: CalibrationOptions, solver, bar=None, mirror=None, estimate=()):
    """:func:`calibrate`'s :data:`SCHEDULE` for every observation set in step, under ``options``
    (its rigid box aside: :mod:`slcvjax.calibration.rigid_pass`); ``solver`` runs a pass's
    solves (:mod:`slcvjax.calibration.executors`)."""
    trials = [
        start_trial(
            o, camera, options, time.perf_counter(), fine=solver is solve_vmap, mirror=mirror, estimate=estimate
        )
        for o in obs_list
    ]
    d = _Lockstep(trials, solver, options, bar)
    for step in SCHEDULE:
        if step.unless_frozen not in d.freeze:
            step.run(d)
    return [d.result(tr) for tr in trials]
