"""What the stages share: the calibration's error, a stage's report, and back-projected rays with
the map from a ray's direction to pixels (the metric in which the stages measure a ray's misfit)."""

from dataclasses import dataclass, field

import jax
import jax.numpy as jnp

from ..geometry.mirror import back_project
from ..observations.problem import map_rows
from ..support.persist import PersistentJit


class CalibrationError(ValueError):
    """A calibration that cannot be done from these observations (the message says why)."""


@dataclass
class StageReport:
    """What one stage did: its name, an RMS figure (its own units) and notes."""

    name: str
    rms: float
    unit: str
    notes: list[str] = field(default_factory=list)


def rays_with_pixel_metric(camera, mirror, uv):
    """Back-projected rays and, per ray, the 2x3 map from a direction change to pixels."""

    def one(u):
        ray = back_project(camera, mirror, u)
        jac = jax.jacfwd(lambda x: back_project(camera, mirror, x).direction)(u)  # (3, 2)
        return ray, jnp.linalg.pinv(jac)

    return jax.vmap(one)(uv)


rays_with_pixel_metric = PersistentJit(map_rows(rays_with_pixel_metric), "rays_with_pixel_metric")
