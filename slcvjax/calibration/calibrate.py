"""The calibration's entry points: :func:`calibrate` one rig, :func:`calibrate_many` several.

:func:`calibrate` runs the staged pipeline (:mod:`slcvjax.calibration.staged`), then the joint
Levenberg-Marquardt in passes (:mod:`slcvjax.calibration.schedule`), then, for the rigid box model,
pass R (:mod:`slcvjax.calibration.rigid_pass`).  Everything changed in the input is listed in
:attr:`slcvjax.calibration.result.CalibrationResult.repairs`.  It returns the joint result with its
covariance, and the staged result beside it.
"""

from concurrent.futures import ThreadPoolExecutor

from ..geometry.camera import Camera
from ..observations.formats import Observations
from .base import CalibrationError
from .executors import resolve_batch, solve_loop, solve_vmap
from .model_selection import auto_kind, through_the_mirror
from .options import CalibrationOptions, merged_options
from .result import CalibrationResult
from .rigid import rigid_group
from .rigid_pass import rigid_refine
from .schedule import calibrate_lockstep


def calibrate(
    obs: Observations,
    camera: Camera | None = None,
    freeze: tuple[str, ...] | set[str] | None = None,
    loss: str | None = None,
    loss_scale: float | None = None,
    max_steps: int | None = None,
    rigid: "bool | list[str] | None" = None,
    mirror=None,
    options: CalibrationOptions | None = None,
) -> CalibrationResult:
    """Calibrate the whole rig from observations (see the module docstring).

    Args:
        obs: the observations.
        options: the settings (:class:`slcvjax.calibration.options.CalibrationOptions`; default:
            its defaults).  ``freeze``, ``loss``, ``loss_scale``, ``max_steps`` and ``rigid``,
            where given (not None), override the options' fields of those names.
        camera: a known camera to start from (freeze it with ``freeze={"camera"}``);
            without it the intrinsics come from the direct chessboard views.
        mirror: a known mirror (pose and shape) to start from instead of the rim's
            (freeze it with ``"mirror"``; with the camera frozen too this evaluates a
            calibration on held-out views: only the poses and the lasers are fitted).
        freeze: parameter blocks held fixed: camera, mirror, lasers, poses, chess_poses.
        loss: ``huber`` (default), ``cauchy`` or ``linear`` for the dots and spots; ``linear`` is
            the plain least-squares fit: no observation is left out as a gross outlier.
        loss_scale: the robust loss's scale in px; by default 3 sigma, sigma estimated
            robustly from the residuals.
        max_steps: the most LM linearisations per pass.
        rigid: the rigid target box model (:mod:`slcvjax.calibration.rigid`) for the group of boards the
            observations declare (``rigid_boards``; ``True``) or for these board names:
            one pose per board in the box and one sensor pose per view, refined from the
            free solution (pass R); a board pose that does not fit the box is left out and
            reported.
    """
    options = merged_options(options, freeze, loss, loss_scale, max_steps, rigid)
    group = rigid_group(obs, options.rigid)
    telecentric = obs.camera_projection == "telecentric"
    through = camera is None and mirror is None and not obs.calibration_views and obs.mirror_shape is not None
    if obs.camera_projection == "auto" and not (through and obs.mirror_shape["kind"] != "cone"):
        raise CalibrationError(
            "camera_projection: auto is chosen from views through a conic mirror alone "
            "(no calibration_views, no camera or mirror to start from, a mirror_shape other than the cone)"
        )
    if camera is not None and camera.telecentric != telecentric:
        raise CalibrationError(
            f"camera_projection: the observations say {obs.camera_projection}, the camera given is {camera.projection}"
        )
    if telecentric and camera is None and (obs.calibration_views or obs.mirror_shape is None):
        raise CalibrationError(
            "camera_projection: a telecentric camera is calibrated through a conic mirror only "
            "(no calibration_views, a mirror_shape of kind sphere, paraboloid, hyperboloid or ellipsoid)"
        )
    auto = obs.mirror_shape is not None and obs.mirror_shape["kind"] == "auto"
    if auto and (camera is not None or mirror is not None or obs.calibration_views):
        raise CalibrationError(
            "mirror_shape.kind: auto is chosen from views through the mirror alone "
            "(no calibration_views, no camera or mirror to start from)"
        )
    if auto:
        res = auto_kind(obs, options)
    elif through:
        res = through_the_mirror(obs, options)
    else:
        res = calibrate_lockstep([obs], camera, options, solve_loop, mirror=mirror)[0]
    return rigid_refine(res, obs, group) if group else res


def calibrate_many(
    observations: list[Observations],
    batch: str = "auto",
    progress: bool = False,
    workers: int = 1,
    *,
    camera: Camera | None = None,
    freeze: tuple[str, ...] | set[str] | None = None,
    loss: str | None = None,
    loss_scale: float | None = None,
    max_steps: int | None = None,
    rigid: "bool | list[str] | None" = None,
    mirror=None,
    options: CalibrationOptions | None = None,
) -> list[CalibrationResult]:
    """Calibrate several observation sets (Monte Carlo trials, say) with :func:`calibrate`'s method.

    ``batch``:

    * ``loop``: one calibration after another, each through the compiled solves (fastest
      on a CPU, where a batch would wait for its slowest trial);
    * ``vmap``: every trial in lockstep, each LM pass of all trials one ``vmap``-ped solve
      whose trial axis is sharded over all JAX devices (:func:`jax.devices`); the host
      steps between the passes run trial by trial.  Sets of the same sizes share one
      compilation; the results equal ``loop``'s to round-off;
    * ``auto``: ``vmap`` where the default device is an accelerator, ``loop`` on a CPU.

    ``workers`` (``loop``): calibrations run at once in threads, each one's host steps
    (the staged stages, OpenCV, NumPy) beside another's compiled programs, which run one at
    a time (see ``slcvjax.support.persist``); results equal to round-off.

    ``camera``, ``freeze``, ``loss``, ``loss_scale``, ``max_steps``, ``rigid``, ``mirror`` and
    ``options`` are :func:`calibrate`'s, the same for every set.  With
    ``progress`` a bar counts the calibrations (in ``vmap`` they finish together, and the
    bar names the pass under way).
    """
    options = merged_options(options, freeze, loss, loss_scale, max_steps, rigid)
    groups = [rigid_group(o, options.rigid) for o in observations]

    def in_box(res, o, group):
        return rigid_refine(res, o, group) if group else res

    batch = resolve_batch(batch)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(observations), desc="calibrations", unit="calibration")
    try:
        if batch == "loop":
            if workers < 1:
                raise ValueError(f"workers: expected at least 1, got {workers}")

            def one(o, group):
                return in_box(calibrate_lockstep([o], camera, options, solve_loop, mirror=mirror)[0], o, group)

            out = []
            with ThreadPoolExecutor(workers) as pool:
                for res in pool.map(one, observations, groups) if workers > 1 else map(one, observations, groups):
                    out.append(res)
                    if bar is not None:
                        bar.update(1)
            return out
        out = calibrate_lockstep(observations, camera, options, solve_vmap, bar=bar, mirror=mirror)
        out = [in_box(res, o, g) for res, o, g in zip(out, observations, groups, strict=True)]
        if bar is not None:
            bar.update(len(out))  # in lockstep they finish together
        return out
    finally:
        if bar is not None:
            bar.close()
