"""One calibration's state between the passes: its observations, problem, solution and records."""

import dataclasses
import time
from dataclasses import dataclass

import cv2
import jax.numpy as jnp
import numpy as np

from ..geometry.camera import Camera
from ..geometry.pose import Pose
from ..observations.formats import Observations
from ..observations.problem import Kind, Layout, Packed, pack, stack_poses
from .base import CalibrationError
from .options import CalibrationOptions, RobustPolicy
from .params import Masks, Params, make_masks
from .result import JointPass, Repair
from .staged import Staged, staged


def chess_start(obs: Observations, pk: Packed, cam: Camera, known: dict[int, Pose]) -> list[Pose]:
    out = []
    for ci in pk.chess_keys:
        if ci in known:
            out.append(known[ci])
            continue
        cv = obs.calibration_views[ci]
        ok, rvec, tvec = cv2.solvePnP(
            obs.boards[cv.board][cv.seen], cv.pixels[cv.seen], np.asarray(cam.K), np.asarray(cam.dist)
        )
        if not ok:
            raise CalibrationError(f"calibration_views[{ci}]: the chessboard's pose could not be found")
        out.append(Pose.from_rvec(rvec.ravel(), tvec.ravel()))
    return out


@dataclass(frozen=True)
class Trial:
    """One calibration's state between the passes of :func:`calibrate_lockstep`.  Immutable: a
    step returns a new state (:meth:`using`, :meth:`with_pass`, :meth:`noted`,
    :func:`dataclasses.replace`); :func:`start_trial` makes the first."""

    obs: Observations
    t0: float  # when it started (``time.perf_counter``)
    options: CalibrationOptions
    st: Staged  # the staged start
    t_staged: float  # the staged start's seconds
    params: Params  # the solution so far
    freeze: frozenset[str]
    estimate: tuple | set | frozenset
    # lasers held because their spots cannot fix a line (found again where B refits the lasers)
    undetermined: tuple[int, ...]
    masks: Masks  # what the passes free
    mask_a: Masks  # what passes A and A2 free (the lasers held)
    fine: bool  # fine shape buckets (the vmap executor)
    pk: Packed  # the problem it solves now
    layout: Layout  # ``pk``'s shape buckets
    arr: Packed  # ``pk`` padded to them
    passes: tuple[JointPass, ...] = ()
    repairs: tuple[Repair, ...] = ()
    scale: float = 1.0  # the loss scale (px)
    # the problem before spots were set aside by their lines (:func:`relabel_spots`), and
    # which of its rows were: the outlier check looks at them again on the final geometry
    set_aside: tuple[Packed, np.ndarray] | None = None
    # line and ring lasers held because their stripes cannot fix them (their index among the sheets)
    undetermined_sheets: tuple[int, ...] = ()
    t_last: float | None = None  # when its last pass ended (the progress lines' timings)

    @property
    def policy(self) -> RobustPolicy:
        return self.options.robust

    def using(self, pk: Packed) -> "Trial":
        """The trial solving the problem ``pk`` from now on (the same poses; fewer or relabelled
        observations)."""
        rig = self.params.rig
        layout = Layout.of(pk, fine=self.fine, n_lasers=rig.lasers.n, sheet_dim=rig.sheet_dim)
        return dataclasses.replace(self, pk=pk, layout=layout, arr=layout.pad_packed(pk))

    def with_pass(self, joint: JointPass) -> "Trial":
        """The trial with the pass ``joint`` run last."""
        return dataclasses.replace(self, passes=(*self.passes, joint))

    def noted(self, note: str) -> "Trial":
        """The trial with ``note`` added to its last pass's notes (what followed it)."""
        last = self.passes[-1]
        return dataclasses.replace(
            self, passes=(*self.passes[:-1], dataclasses.replace(last, notes=(*last.notes, note)))
        )

    def with_repairs(self, *repairs: Repair) -> "Trial":
        """The trial with ``repairs`` recorded after its own."""
        return dataclasses.replace(self, repairs=(*self.repairs, *repairs))


def start_trial(obs, camera, options: CalibrationOptions, t0, fine: bool = False, mirror=None, estimate=()) -> Trial:
    """A trial at its staged start: the staged stages' rig and poses (:func:`staged`), the
    direct views' poses, the masks of ``options.freeze`` (``estimate``: the shape's unknowns
    it estimates), the problem padded to its shape buckets (``fine``: the vmap executor's)."""
    policy = options.robust
    freeze = frozenset(options.freeze)
    st = staged(obs, camera=camera, pk=pack(obs), mirror=mirror, policy=policy)
    pk = st.packed  # spots without a board have one now
    t_staged = time.perf_counter() - t0
    if camera is not None and not st.chess_poses:
        st = dataclasses.replace(st, chess_poses={})
    chess = chess_start(obs, pk, st.camera, st.chess_poses)
    if not chess:
        chess_stack = Pose(jnp.zeros((0, 3, 3)), jnp.zeros((0, 3)))
        if camera is None:
            raise CalibrationError("calibration_views: no direct views and no camera given")
    else:
        chess_stack = stack_poses(chess)
    params = Params(st.rig, stack_poses(st.poses), chess_stack)
    masks = make_masks(params, set(freeze), estimate, held_lasers=st.undetermined, held_sheets=st.undetermined_sheets)
    mask_a = make_masks(params, set(freeze) | {"lasers"}, estimate)
    if st.undetermined and "lasers" in freeze:  # no refit: their spots go now
        n_d, n_s = int(pk.counts[Kind.DOT]), int(pk.counts[Kind.SPOT])
        held = np.isin(np.asarray(pk.spot_laser)[:n_s], st.undetermined)
        pk = pk.select(np.ones(n_d, bool), ~held)
    if st.undetermined_sheets:  # their stripes cannot fix them: they are held and their samples go
        n_t = int(pk.counts[Kind.STRIPE])
        pk = pk.select_stripes(~np.isin(np.asarray(pk.stripe_sheet)[:n_t], st.undetermined_sheets))
    layout = Layout.of(pk, fine=fine, n_lasers=params.rig.lasers.n, sheet_dim=params.rig.sheet_dim)
    return Trial(
        obs,
        t0,
        options,
        st,
        t_staged,
        params,
        freeze,
        estimate,
        st.undetermined,
        masks,
        mask_a,
        fine,
        pk,
        layout,
        layout.pad_packed(pk),
        undetermined_sheets=st.undetermined_sheets,
    )
