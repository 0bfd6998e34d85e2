"""Shared helpers for the tests: random rigs and central finite differences."""

import jax
import jax.numpy as jnp
import numpy as np

import slcvjax as sj


def _monotonic(dist, r_max: float) -> bool:
    """Whether the radial distortion map is invertible (increasing) up to radius r_max."""
    k1, k2, _, _, k3 = dist
    r = np.linspace(0, r_max, 200)
    return bool(np.all(1 + 3 * k1 * r**2 + 5 * k2 * r**4 + 7 * k3 * r**6 > 0.05))


def random_camera(rng: np.random.Generator, width: int = 640, height: int = 480) -> sj.Camera:
    """A realistic random camera: barrel distortion that stays invertible over the whole image."""
    while True:
        cam = _random_camera(rng, width, height)
        corner = max(width, height) / float(cam.fx)
        if _monotonic(np.asarray(cam.dist), 1.3 * corner):
            return cam


def _random_camera(rng, width, height):
    fx = rng.uniform(450, 700)
    return sj.Camera.create(
        fx,
        fx * rng.uniform(0.98, 1.02),
        width / 2 + rng.uniform(-20, 20),
        height / 2 + rng.uniform(-40, 20),
        [
            rng.uniform(-0.3, -0.1),
            rng.uniform(0.0, 0.1),
            rng.uniform(-2e-3, 2e-3),
            rng.uniform(-2e-3, 2e-3),
            rng.uniform(-0.02, 0.0),
        ],
        width,
        height,
    )


def random_mirror(rng: np.random.Generator) -> sj.ConeMirror:
    r = rng.uniform(12, 30)
    h = r / rng.uniform(1.4, 2.6)
    dist = r * rng.uniform(2.2, 3.0)
    tilt = rng.normal(0, 0.03, 2)
    return sj.ConeMirror.create([rng.uniform(-1, 1), rng.uniform(-1, 1), dist], [tilt[0], tilt[1], 1.0], r, h)


def central_diff(f, x: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """Jacobian of f at x by central differences, shape f(x).shape + x.shape."""
    x = np.asarray(x, float)
    f0 = np.asarray(f(jnp.asarray(x)))
    out = np.zeros(f0.shape + x.shape)
    for idx in np.ndindex(x.shape):
        e = np.zeros_like(x)
        e[idx] = eps
        out[(...,) + idx] = (np.asarray(f(jnp.asarray(x + e))) - np.asarray(f(jnp.asarray(x - e)))) / (2 * eps)
    return out


# one pixel's back-projection and one point's projection through the mirror, over a batch, jitted
# (the camera and mirror as arguments: one compilation serves every mirror of a kind)
back_project_many = jax.jit(jax.vmap(sj.back_project, in_axes=(None, None, 0)))
project_many = jax.jit(jax.vmap(sj.project_through_mirror, in_axes=(None, None, 0)))


def on_true_lines(truth: sj.Rig, points: np.ndarray) -> np.ndarray:
    """Each point moved to its laser's true line (the foot of its perpendicular): the true
    working points near a calibration's own, which lie on the estimated lines, so that
    ``laser_errors`` measured at those would give a position error of zero."""
    p, d = np.asarray(truth.lasers.points), np.asarray(truth.lasers.directions)
    return p + np.sum((np.asarray(points) - p) * d, axis=1, keepdims=True) * d
