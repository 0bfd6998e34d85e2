"""slcvjax: calibrate and measure with a structured-light catadioptric vision sensor.

Precision policy: calibration is done in float64.  Importing ``slcvjax`` turns on
``jax_enable_x64``; arrays made by the library are float64 unless a benchmark
documents a float32 path as safe.  Units are millimetres and radians.

Importing ``slcvjax`` also turns on JAX's persistent compilation cache
(:mod:`slcvjax._cache`: ``SLCVJAX_CACHE_DIR`` chooses the folder, ``off`` disables it);
``compilation_cache_dir()`` says which folder is in use.
"""

import jax

jax.config.update("jax_enable_x64", True)

from . import _cache  # noqa: E402
from ._cache import compilation_cache_dir  # noqa: E402

_cache.enable()

from ._calibrate import (  # noqa: E402
    CalibrationResult,
    calibrate,
    calibrate_many,
    cramer_rao,
    laser_errors,
    to_calibration,
)
from ._camera import (  # noqa: E402
    Camera,
    distort,
    in_image,
    pixel_to_ray,
    project,
    project_normalized,
    project_points,
    undistort,
)
from ._implicit import (  # noqa: E402
    Sensitivity,
    differentiable_solution,
    sensitivity,
    solution_tangent,
    stationary_point,
)
from ._io import (  # noqa: E402
    Calibration,
    FormatError,
    Observations,
    read_calibration,
    read_observations,
    write_calibration,
    write_observations,
)
from ._lasers import Lasers, line_plane_intersection  # noqa: E402
from ._mirror import (  # noqa: E402
    ConeMirror,
    MirrorProjection,
    MirrorRay,
    RayHit,
    back_project,
    intersect,
    project_through_mirror,
    reflect,
    solve_mirror_point,
    surface_normal,
)
from ._pose import Pose, so3_exp, so3_log  # noqa: E402
from ._rig import (  # noqa: E402
    Rig,
    laser_spot_cam,
    project_board_points,
    project_direct,
    project_rim,
    project_spots,
)
from ._simulate import Scene, make_scene, simulate  # noqa: E402

__version__ = "0.1.0"

__all__ = [
    "Calibration",
    "CalibrationResult",
    "Camera",
    "ConeMirror",
    "FormatError",
    "Lasers",
    "MirrorProjection",
    "MirrorRay",
    "Observations",
    "Pose",
    "RayHit",
    "Rig",
    "Scene",
    "Sensitivity",
    "back_project",
    "calibrate",
    "calibrate_many",
    "compilation_cache_dir",
    "cramer_rao",
    "differentiable_solution",
    "distort",
    "in_image",
    "intersect",
    "laser_errors",
    "laser_spot_cam",
    "line_plane_intersection",
    "make_scene",
    "pixel_to_ray",
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
    "reflect",
    "sensitivity",
    "simulate",
    "so3_exp",
    "so3_log",
    "solution_tangent",
    "solve_mirror_point",
    "stationary_point",
    "surface_normal",
    "to_calibration",
    "undistort",
    "write_calibration",
    "write_observations",
]
