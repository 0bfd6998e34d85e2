"""The pinhole camera with Brown distortion, in OpenCV's conventions, and its telecentric twin.

Pixels are OpenCV's (integer coordinates at pixel centres), the camera frame
is OpenCV's (x right, y down, z forward) and the distortion coefficients are in
OpenCV's order ``(k1, k2, p1, p2, k3)``.  :func:`project` agrees with
``cv2.projectPoints`` and :func:`undistort` with ``cv2.undistortPoints`` (with a termination criterion)
run to convergence.

A telecentric (orthographic) camera, as paracatadioptric cameras often have, sees along +z:
a point ``(X, Y, Z)`` has the normalised point ``(X, Y) / L`` whatever its depth, ``L`` the
camera's fixed ``unit`` (mm), and the same distortion and ``K`` make its pixel; its rays are
parallel, each from ``(L x, L y, 0)`` along +z (:func:`pixel_to_line`).  The depth of the camera's
origin is then a gauge: nothing it sees changes with it.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from ..support.safe import safe_div, safe_normalize
from .newton import newton_implicit, newton_residual_norm


class Camera(eqx.Module):
    """Intrinsics of a pinhole camera with Brown distortion.

    Attributes:
        fx, fy, cx, cy: focal lengths and principal point in pixels (0-d arrays).
        dist: (5,) distortion ``(k1, k2, p1, p2, k3)``.
        width, height: image size in pixels (static).
        telecentric: an orthographic camera (static; see the module docstring).
        unit: a telecentric camera's normalising length ``L`` (mm, static): its ``fx`` is in
            pixels per ``L`` mm.
    """

    fx: Float[Array, ""]
    fy: Float[Array, ""]
    cx: Float[Array, ""]
    cy: Float[Array, ""]
    dist: Float[Array, "5"]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)
    telecentric: bool = eqx.field(static=True, default=False)
    unit: float = eqx.field(static=True, default=1.0)

    def __check_init__(self):
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"Camera: image size must be positive, got {self.width}x{self.height}")
        if not self.unit > 0:
            raise ValueError(f"Camera: a telecentric camera's unit must be positive, got {self.unit}")

    @staticmethod
    def create(fx, fy, cx, cy, dist, width: int, height: int, telecentric: bool = False, unit: float = 1.0) -> "Camera":
        f = lambda x: jnp.asarray(x, dtype=float)  # noqa: E731
        return Camera(
            f(fx), f(fy), f(cx), f(cy), f(dist).reshape(5), int(width), int(height), bool(telecentric), float(unit)
        )

    @property
    def projection(self) -> str:
        """``perspective`` or ``telecentric``."""
        return "telecentric" if self.telecentric else "perspective"

    @property
    def K(self) -> Float[Array, "3 3"]:
        """OpenCV's 3x3 camera matrix."""
        z = jnp.zeros_like(self.fx)
        o = jnp.ones_like(self.fx)
        return jnp.array([[self.fx, z, self.cx], [z, self.fy, self.cy], [z, z, o]])

    def params(self) -> Float[Array, "9"]:
        """``(fx, fy, cx, cy, k1, k2, p1, p2, k3)``."""
        return jnp.concatenate([jnp.stack([self.fx, self.fy, self.cx, self.cy]), self.dist])

    def with_params(self, p: Float[Array, "9"]) -> "Camera":
        """A camera with the 9 parameters of :meth:`params` replaced."""
        return Camera(p[0], p[1], p[2], p[3], p[4:9], self.width, self.height, self.telecentric, self.unit)

    def retract(self, delta: Float[Array, "9"]) -> "Camera":
        return self.with_params(self.params() + delta)


def distort(dist: Float[Array, "5"], xy: Float[Array, "2"]) -> Float[Array, "2"]:
    """Brown distortion of one normalised point ``(x, y) = (X/Z, Y/Z)``."""
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    x, y = xy[0], xy[1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return jnp.stack([xd, yd])


def project_normalized(cam: Camera, xy: Float[Array, "2"]) -> Float[Array, "2"]:
    """Pixel of one undistorted normalised point."""
    d = distort(cam.dist, xy)
    return jnp.stack([cam.fx * d[0] + cam.cx, cam.fy * d[1] + cam.cy])


def project(cam: Camera, p_cam: Float[Array, "3"]) -> tuple[Float[Array, "2"], Bool[Array, ""]]:
    """Pixel of one 3D point of the camera frame (mm), as ``cv2.projectPoints``.

    Returns ``(uv, valid)``; ``valid`` is False for a point not in front of the
    camera (``Z <= 1e-9``), where ``uv`` is finite but meaningless.  A telecentric camera sees
    every point (``(X, Y) / L``, any depth).
    """
    if cam.telecentric:
        return project_normalized(cam, p_cam[:2] / cam.unit), jnp.array(True)
    z = p_cam[2]
    valid = z > 1e-9
    xy = jnp.stack([safe_div(p_cam[0], z), safe_div(p_cam[1], z)])
    return project_normalized(cam, xy), valid


def in_image(cam: Camera, uv: Float[Array, "2"]) -> Bool[Array, ""]:
    """Whether a pixel lies on the sensor (``-0.5 <= u < width - 0.5``, likewise ``v``)."""
    lim_u, lim_v = float(cam.width) - 0.5, float(cam.height) - 0.5
    return (uv[0] >= -0.5) & (uv[0] < lim_u) & (uv[1] >= -0.5) & (uv[1] < lim_v)


def _undistort_residual(xy, theta):
    dist, target = theta
    return distort(dist, xy) - target


def undistort(cam: Camera, uv: Float[Array, "2"], iters: int = 12) -> tuple[Float[Array, "2"], Bool[Array, ""]]:
    """Undistorted normalised point of one pixel (the inverse of :func:`project_normalized`).

    Newton on the distortion model from the distorted point, with an implicit
    derivative.  ``valid`` is False where Newton did not converge (far outside
    the region where the distortion polynomial is invertible).
    """
    target = jnp.stack([(uv[0] - cam.cx) / cam.fx, (uv[1] - cam.cy) / cam.fy])
    theta = (cam.dist, target)
    xy = newton_implicit(_undistort_residual, target, theta, iters)
    valid = newton_residual_norm(_undistort_residual, xy, theta) < 1e-10
    return xy, valid


def pixel_to_ray(cam: Camera, uv: Float[Array, "2"]) -> tuple[Float[Array, "3"], Bool[Array, ""]]:
    """Unit direction (camera frame) of the ray through a pixel, and its validity (+z for every
    pixel of a telecentric camera: see :func:`pixel_to_line`)."""
    xy, valid = undistort(cam, uv)
    if cam.telecentric:
        return jnp.array([0.0, 0.0, 1.0]), valid
    return safe_normalize(jnp.stack([xy[0], xy[1], jnp.ones_like(xy[0])])), valid


def pixel_to_line(cam: Camera, uv: Float[Array, "2"]) -> tuple[Float[Array, "3"], Float[Array, "3"], Bool[Array, ""]]:
    """The line a pixel sees, camera frame: ``(origin, unit direction, valid)``; the origin is
    the camera's centre, or a telecentric camera's ``(L x, L y, 0)``."""
    d, valid = pixel_to_ray(cam, uv)
    if cam.telecentric:
        xy, _ = undistort(cam, uv)
        return jnp.stack([xy[0], xy[1], jnp.zeros_like(xy[0])]) * cam.unit, d, valid
    return jnp.zeros(3), d, valid


def view_direction(x: Float[Array, "3"], telecentric: bool) -> Float[Array, "3"]:
    """The unit direction from the camera to a point it sees at ``x`` (camera frame): +z for a
    telecentric camera."""
    return jnp.array([0.0, 0.0, 1.0]) if telecentric else safe_normalize(x)


def project_points(cam: Camera, points: ArrayLike) -> tuple[Array, Array]:
    """:func:`project` over an (..., 3) array of points."""
    pts = jnp.asarray(points, dtype=float)
    f = jax.vmap(lambda p: project(cam, p))
    uv, valid = f(pts.reshape(-1, 3))
    return uv.reshape(pts.shape[:-1] + (2,)), valid.reshape(pts.shape[:-1])
