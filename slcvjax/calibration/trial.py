"""One calibration's state between the passes: its observations, problem, solution and records."""

import time

import cv2
import jax.numpy as jnp
import numpy as np

from ..geometry.camera import Camera
from ..geometry.pose import Pose
from ..observations.formats import Observations
from ..observations.problem import Kind, Layout, Packed, pack, stack_poses
from .base import CalibrationError
from .options import CalibrationOptions
from .params import Params, make_masks
from .result import JointPass
from .staged import staged


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


class Trial:
    """One calibration's state between the passes of :func:`calibrate_lockstep`."""

    def __init__(self, obs, camera, options: CalibrationOptions, t0, fine: bool = False, mirror=None, estimate=()):
        self.obs, self.t0 = obs, t0
        self.options = options
        self.policy = options.robust
        freeze = set(options.freeze)
        st = staged(obs, camera=camera, pk=pack(obs), mirror=mirror, policy=self.policy)
        self.st, self.pk = st, st.packed  # spots without a board have one now
        self.t_staged = time.perf_counter() - t0
        self.t_last: float | None = None  # when its last pass ended (the progress lines' timings)
        if camera is not None and not st.chess_poses:
            st.chess_poses = {}
        chess = chess_start(obs, self.pk, st.camera, st.chess_poses)
        if not chess:
            chess_stack = Pose(jnp.zeros((0, 3, 3)), jnp.zeros((0, 3)))
            if camera is None:
                raise CalibrationError("calibration_views: no direct views and no camera given")
        else:
            chess_stack = stack_poses(chess)
        self.params = Params(st.rig, stack_poses(st.poses), chess_stack)
        self.freeze, self.estimate = set(freeze), estimate
        # lasers held because their spots cannot fix a line (found again where B refits the lasers)
        self.undetermined: tuple[int, ...] = st.undetermined
        self.masks = make_masks(self.params, set(freeze), estimate, held_lasers=st.undetermined)
        self.mask_a = make_masks(self.params, set(freeze) | {"lasers"}, estimate)
        self.fine = fine
        if st.undetermined and "lasers" in freeze:  # no refit: their spots go now
            n_d, n_s = int(self.pk.counts[Kind.DOT]), int(self.pk.counts[Kind.SPOT])
            held = np.isin(np.asarray(self.pk.spot_laser)[:n_s], st.undetermined)
            self.pk = self.pk.select(np.ones(n_d, bool), ~held)
        self.use(self.pk)
        self.passes: list[JointPass] = []
        self.repairs: list[dict] = []
        self.scale = 1.0
        # the problem before spots were set aside by their lines (:func:`relabel_spots`), and
        # which of its rows were: the outlier check looks at them again on the final geometry
        self.set_aside: tuple[Packed, np.ndarray] | None = None

    def use(self, pk: Packed) -> None:
        """Solve the problem ``pk`` from now on (the same poses; fewer or relabelled observations)."""
        self.pk = pk
        self.layout = Layout.of(pk, fine=self.fine, n_lasers=self.params.rig.lasers.n)
        self.arr = self.layout.pad_packed(pk)
