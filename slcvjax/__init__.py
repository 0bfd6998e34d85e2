"""slcvjax: calibrate and measure with a structured-light catadioptric vision sensor.

Every job is one name here: simulate or load observations, render and detect images,
calibrate (staged, joint, rigid box, catadioptric cameras from chessboards), the bound and
the implicit derivative, measure laser points and pipes, sweep the noise, design the
calibration or the lasers, and plot.  The modules behind them are arranged in layers, each
importing only the layers before it: ``support`` (numerical safety, the caches) ->
``geometry`` (poses, camera, mirrors, lasers, the rig) -> ``observations`` (the data model,
its file formats, the packed problem, the simulator) -> ``calibration`` -> ``measurement``
-> ``images`` (render, detect) -> ``plots`` -> ``experiments`` (sweep, design, catadioptric
cameras from images) -> ``cli`` (one module per command).  The names below are the stable
API; the layers' modules may move.  The image, measurement, experiment and plot names are
imported when first used, so ``import slcvjax`` loads no more than the calibration needs.

Precision policy: calibration is done in float64.  Importing ``slcvjax`` turns on
``jax_enable_x64`` for the process (JAX has one such flag per process; the library's
arrays are float64 and its tests run with ``jax_numpy_dtype_promotion="strict"``), so import
``slcvjax`` before making JAX arrays that should be float64.  Units are millimetres and radians.

Importing ``slcvjax`` also turns on JAX's persistent compilation cache
(:mod:`slcvjax.support.cache`: ``SLCVJAX_CACHE_DIR`` chooses the folder, ``off`` disables it);
``compilation_cache_dir()`` says which folder is in use.
"""

import importlib

import jax

jax.config.update("jax_enable_x64", True)

from .support import cache as _cache  # noqa: E402
from .support.cache import compilation_cache_dir  # noqa: E402

_cache.enable()

from .calibration.base import CalibrationError  # noqa: E402
from .calibration.bound import cramer_rao, laser_errors, laser_std, laser_working_points  # noqa: E402
from .calibration.calibrate import calibrate, calibrate_many  # noqa: E402
from .calibration.implicit import (  # noqa: E402
    Sensitivity,
    differentiable_solution,
    sensitivity,
    solution_tangent,
    stationary_point,
)
from .calibration.model_selection import held_out_rms  # noqa: E402
from .calibration.report import report, reprojections, to_calibration  # noqa: E402
from .calibration.result import CalibrationResult, require_determined  # noqa: E402
from .calibration.staged import Staged, staged  # noqa: E402
from .calibration.stored import load_result  # noqa: E402
from .geometry.camera import (  # noqa: E402
    Camera,
    distort,
    in_image,
    pixel_to_ray,
    project,
    project_normalized,
    project_points,
    undistort,
)
from .geometry.conic import AsphereMirror, ConicMirror  # noqa: E402
from .geometry.lasers import Lasers, line_plane_intersection  # noqa: E402
from .geometry.mirror import (  # noqa: E402
    ConeMirror,
    Mirror,
    MirrorProjection,
    MirrorRay,
    RayHit,
    back_project,
    intersect,
    mirror_of_shape,
    project_through_mirror,
    reflect,
    solve_mirror_point,
    surface_normal,
)
from .geometry.pose import Pose, so3_exp, so3_log  # noqa: E402
from .geometry.rig import (  # noqa: E402
    Rig,
    distance_to_rim,
    laser_spot_cam,
    project_board_points,
    project_direct,
    project_rim,
    project_spots,
)
from .observations.formats import (  # noqa: E402
    Calibration,
    CalibrationViewObs,
    FormatError,
    Observations,
    SpotObs,
    ViewObs,
    read_calibration,
    read_observations,
    write_calibration,
    write_observations,
)
from .observations.simulate import PRESETS, Scene, box_scene, make_scene, paper_rig, paper_scene, paper_views, simulate  # noqa: E402

__version__ = "0.1.0"

# name -> the module that defines it, imported on first use (:func:`__getattr__`)
_LAZY = {
    "CameraCalibration": "calibration.chessboard",
    "calibrate_camera_images": "calibration.chessboard",
    "detect_corners": "calibration.chessboard",
    "mei_observations": "observations.published",
    "ocam_observations": "observations.published",
    "ocam_project": "observations.published",
    "ocam_residuals": "observations.published",
    "omnidir_observations": "observations.published",
    "Circle": "measurement.measure",
    "SpotPoints": "measurement.measure",
    "ViewPoints": "measurement.measure",
    "fit_circle": "measurement.measure",
    "fit_circle_3d": "measurement.measure",
    "label_by_lines": "measurement.measure",
    "measure_spots": "measurement.measure",
    "triangulate_spot": "measurement.measure",
    "RenderOptions": "images.render",
    "Renderer": "images.render",
    "render_pipe": "images.render",
    "render_scene": "images.render",
    "DetectionReport": "images.detect",
    "Setup": "images.detect",
    "detect_folder": "images.detect",
    "read_setup": "images.detect",
    "calibrate_detected": "images.centroids",
    "PipeScene": "images.pipe",
    "measurement_inputs": "images.pipe",
    "pipe_experiment": "images.pipe",
    "pipe_scene": "images.pipe",
    "simulate_pipe": "images.pipe",
    "spots_from_images": "images.pipe",
    "plot_detections": "plots",
    "plot_pipe": "plots",
    "plot_rig": "plots",
    "StudyError": "experiments.cluster",
    "run_chunks": "experiments.cluster",
    "plot_sweep": "experiments.sweep",
    "run_sweep": "experiments.sweep",
    "sweep_csv": "experiments.sweep",
    "write_sweep": "experiments.sweep",
    "Plan": "experiments.design",
    "confirm": "experiments.design",
    "design_document": "experiments.design",
    "optimise": "experiments.design",
    "plot_design": "experiments.design",
    "predict": "experiments.design",
    "MeasurePlan": "experiments.laser_design",
    "confirm_lasers": "experiments.laser_design",
    "laser_design_document": "experiments.laser_design",
    "optimise_lasers": "experiments.laser_design",
    "plot_laser_design": "experiments.laser_design",
    "omni_observations": "experiments.omni",
    "plot_residuals": "experiments.omni",
    "report_html": "experiments.report",
    "write_report": "experiments.report",
}


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'slcvjax' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY))


__all__ = [
    "AsphereMirror",
    "Calibration",
    "CalibrationError",
    "CalibrationResult",
    "CalibrationViewObs",
    "Camera",
    "CameraCalibration",
    "Circle",
    "ConeMirror",
    "ConicMirror",
    "DetectionReport",
    "FormatError",
    "Lasers",
    "MeasurePlan",
    "Mirror",
    "MirrorProjection",
    "MirrorRay",
    "Observations",
    "PRESETS",
    "PipeScene",
    "Plan",
    "Pose",
    "RayHit",
    "RenderOptions",
    "Renderer",
    "Rig",
    "Scene",
    "Sensitivity",
    "Setup",
    "SpotObs",
    "SpotPoints",
    "Staged",
    "StudyError",
    "ViewObs",
    "ViewPoints",
    "back_project",
    "box_scene",
    "calibrate",
    "calibrate_camera_images",
    "calibrate_detected",
    "calibrate_many",
    "compilation_cache_dir",
    "confirm",
    "confirm_lasers",
    "cramer_rao",
    "design_document",
    "detect_corners",
    "detect_folder",
    "differentiable_solution",
    "distance_to_rim",
    "distort",
    "fit_circle",
    "fit_circle_3d",
    "held_out_rms",
    "in_image",
    "intersect",
    "label_by_lines",
    "laser_design_document",
    "laser_errors",
    "require_determined",
    "laser_spot_cam",
    "laser_std",
    "laser_working_points",
    "line_plane_intersection",
    "load_result",
    "make_scene",
    "measure_spots",
    "measurement_inputs",
    "mei_observations",
    "mirror_of_shape",
    "ocam_observations",
    "ocam_project",
    "ocam_residuals",
    "omni_observations",
    "omnidir_observations",
    "optimise",
    "optimise_lasers",
    "paper_rig",
    "paper_scene",
    "paper_views",
    "pipe_experiment",
    "pipe_scene",
    "pixel_to_ray",
    "plot_design",
    "plot_detections",
    "plot_laser_design",
    "plot_pipe",
    "plot_residuals",
    "plot_rig",
    "plot_sweep",
    "predict",
    "project",
    "project_board_points",
    "project_direct",
    "project_normalized",
    "project_points",
    "project_rim",
    "project_spots",
    "project_through_mirror",
    "read_calibration",
    "read_observations",
    "read_setup",
    "reflect",
    "render_pipe",
    "render_scene",
    "report",
    "report_html",
    "reprojections",
    "run_chunks",
    "run_sweep",
    "sensitivity",
    "simulate",
    "simulate_pipe",
    "so3_exp",
    "so3_log",
    "solution_tangent",
    "solve_mirror_point",
    "spots_from_images",
    "staged",
    "stationary_point",
    "surface_normal",
    "sweep_csv",
    "to_calibration",
    "triangulate_spot",
    "undistort",
    "write_calibration",
    "write_observations",
    "write_report",
    "write_sweep",
]
