"""A ring laser's profile of a pipe: one circle, or one ellipse, per view from all its samples.

The points of a ring laser's stripe lie on the pipe wall.  Projected along the pipe's axis onto
the plane across it (coordinates of :func:`slcvjax.measurement.measure.plane_basis`) they lie on
the pipe's cross-section, whatever the tilt between the cone of light and the pipe: a circle for a
round pipe, an ellipse for an oval one.

Circle: :func:`slcvjax.measurement.measure.fit_circle`'s estimator (algebraic start, then
geometric least squares with each point weighted by the inverse of its radial variance).

Ellipse: ``(q - c)^T A (q - c) = 1`` with ``A = S / R0^2`` (``R0`` the circle's radius, ``S``
symmetric, 3 unknowns, the identity for the circle): smooth in its five unknowns even for a round
pipe, where an ellipse's orientation is undefined.  It minimises the weighted squared Sampson
distances ``r_i = f_i / |grad f_i|`` (``f = (q - c)^T A (q - c) - 1``): the first-order
geometric distance to the ellipse, exact for a point on it and, for a pipe's small ovality, within
a second-order term of the true distance.  From ``A``'s eigenvalues ``m -+ g`` the semi-axes are
``a = (m - g)^-1/2 >= b = (m + g)^-1/2``; ``orientation`` is the major axis's angle from ``e1``
(rad, in (-pi/2, pi/2]); ``ovality = (D_max - D_min) / D_mean = 2 (a - b) / (a + b)``.

Uncertainty: the fit's derivative with respect to every point (the implicit-function theorem at
the minimum) applied to the points' covariance in the factored form
:class:`slcvjax.measurement.stripes.StripeViewPoints` keeps: each point's own pixel block, plus the
calibration's covariance through the points' Jacobian, which every point shares (it does not
average out over the samples, and it dominates the diameter's std).  Ovality is not negative, so
its first-order std (along the fitted ellipse's own ovality direction) says how far it may move,
but where the ovality is under about two std the estimate is biased upwards (the length of a
noisy 2-vector): a round pipe measures a small positive ovality.
"""

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from ..observations.problem import bucket, pad_rows
from ..support.safe import safe_div, safe_norm, safe_sqrt
from .measure import Circle, circle_sensitivities, fit_circle_theta, plane_basis
from .stripes import StripeViewPoints


@dataclass
class PlanePoints:
    """Points projected on the plane across a pipe's axis, with their covariance in factored form.

    Attributes:
        q: (n, 2) the points' coordinates in the plane (mm, :func:`plane_basis`).
        pixel_cov: (n, 2, 2) each point's covariance from its own pixel noise (mm^2).
        jq: (n, 2, G) the coordinates' Jacobian with respect to the rig's tangent, or None.
        rig_cov: (G, G) the calibration's covariance, or None.
    """

    q: np.ndarray
    pixel_cov: np.ndarray
    jq: np.ndarray | None = None
    rig_cov: np.ndarray | None = None

    @property
    def blocks(self) -> np.ndarray:
        """(n, 2, 2) each point's own covariance, calibration included (mm^2)."""
        out = self.pixel_cov.copy()
        if self.jq is not None and self.rig_cov is not None:
            out += np.einsum("nag,gh,nbh->nab", self.jq, self.rig_cov, self.jq)
        return out

    def propagate(self, sens: np.ndarray) -> np.ndarray:
        """(p, p): the covariance of ``p`` quantities whose derivative with respect to each point
        is ``sens`` (p, n, 2)."""
        out = np.einsum("pni,nij,qnj->pq", sens, self.pixel_cov, sens)
        if self.jq is not None and self.rig_cov is not None:
            m = np.einsum("pni,nig->pg", sens, self.jq)
            out = out + m @ self.rig_cov @ m.T
        return out


UNRELIABLE_STD_FACTOR = 5.0  # a point whose std is over this many times its ring's median is left out


def reliable(svp: StripeViewPoints, laser: int | None = None) -> np.ndarray:
    """(n,) which points of a view (of ``laser``, by its element index, when given) a ring fit
    uses: not grazing, and with a largest pixel-noise std under ``UNRELIABLE_STD_FACTOR`` times the
    median of theirs.  The points beyond are seen near the mirror's apex, where the cone's normal
    turns fast: there the first-order std stops describing the error (on the reference rig in a
    150 mm pipe at 0.3 px, samples within 3 px of the apex's image erred by up to 72 of their std,
    and biased the diameters by up to 0.18 mm)."""
    use = ~svp.grazing if laser is None else (~svp.grazing & (svp.lasers == laser))
    if not np.any(use):
        return use
    big = np.sqrt(np.linalg.eigvalsh(svp.pixel_cov)[:, -1])
    return use & (big <= UNRELIABLE_STD_FACTOR * np.median(big[use]))


def ring_plane_points(svp: StripeViewPoints, laser: int | None = None, axis=(0.0, 0.0, 1.0)) -> PlanePoints:
    """The points of a view (those of ``laser``, by its element index, when given) that a ring fit
    uses (:func:`reliable`) on the plane across ``axis`` (camera frame)."""
    use = reliable(svp, laser)
    basis = plane_basis(axis)
    q = svp.xyz[use] @ basis.T
    pix = np.einsum("ia,nab,jb->nij", basis, svp.pixel_cov[use], basis)
    jq = None if svp.j_rig is None else np.einsum("ia,nag->nig", basis, svp.j_rig[use])
    return PlanePoints(q, pix, jq, svp.rig_cov)


def tangential_bias(q: np.ndarray, pixel_cov: np.ndarray, w: np.ndarray, center, radius: float) -> float:
    """The second-order bias of a fitted radius (mm) from the points' noise along the circle.

    A point moved by ``t`` along the circle lands at the radius ``sqrt(R^2 + t^2) ~ R + t^2/(2R)``:
    the weighted radial fit takes ``sum(w_i tau_i^2) / (2 R sum(w_i))`` too much, with
    ``tau_i^2`` each point's own (pixel) variance along the circle.  A stripe's samples are
    noisy along the stripe as much as across it, and a ring's stripe runs along the circle: at
    0.3 px on the reference rig this is about 0.007 mm of radius.  The calibration's share is
    left out: it moves the points together (the same shift for every view), not about the circle."""
    u = q - np.asarray(center)
    u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-300)
    t = np.column_stack([-u[:, 1], u[:, 0]])
    tau2 = np.einsum("ni,nij,nj->n", t, pixel_cov, t)
    return float(np.sum(w * tau2) / (2.0 * radius * np.sum(w)))


def fit_circle_factored(pp: PlanePoints, iters: int = 50, debias: bool = True) -> Circle:
    """:func:`slcvjax.measurement.measure.fit_circle` of :class:`PlanePoints` (the same estimate,
    each point weighted by its own radial variance), its std from the factored covariance; with
    ``debias`` the radius less its :func:`tangential_bias` (the residuals are to the fitted
    circle)."""
    theta, w = fit_circle_theta(pp.q, pp.blocks, iters)
    res = np.linalg.norm(pp.q - theta[:2], axis=1) - theta[2]
    if debias:
        theta = theta.copy()
        theta[2] -= tangential_bias(pp.q, pp.pixel_cov, w, theta[:2], theta[2])
    ct = pp.propagate(circle_sensitivities(theta, pp.q, w))
    if not np.all(np.isfinite(ct)):
        raise ValueError("the circle's covariance is not finite (a point's uncertainty is unbounded)")
    return Circle(
        theta[:2],
        float(2.0 * theta[2]),
        float(2.0 * np.sqrt(max(ct[2, 2], 0.0))),
        res,
        float(np.sqrt(np.mean(res**2))),
        np.sqrt(np.maximum(np.diag(ct)[:2], 0.0)),
    )


# ----------------------------------------------------------------------------- ellipse


@dataclass
class Ellipse:
    """A fitted ellipse in the plane across a pipe's axis (:func:`plane_basis` coordinates), mm.

    Attributes:
        center: (2,) its centre.
        major, minor: its largest and smallest diameters ``2a >= 2b``.
        orientation: the major axis's angle from ``e1`` towards ``e2`` (rad, in (-pi/2, pi/2]).
        ovality: ``(major - minor) / mean_diameter`` (a fraction).
        mean_diameter: ``(major + minor) / 2``.
        std: each of those quantities' first-order std (keys ``center`` (2,), ``major``,
            ``minor``, ``orientation``, ``ovality``, ``mean_diameter``), or None.
        residuals: (n,) each point's Sampson distance to the ellipse (mm, signed: outside > 0).
        rms: their RMS (mm).
    """

    center: np.ndarray
    major: float
    minor: float
    orientation: float
    ovality: float
    mean_diameter: float
    std: dict | None
    residuals: np.ndarray
    rms: float


def _sampson(theta, q, r0):
    """Sampson distances (n,) of points ``q`` (n, 2) to the ellipse ``theta`` (see the module)."""
    c = theta[:2]
    a = jnp.array([[theta[2], theta[3]], [theta[3], theta[4]]]) / r0**2
    d = q - c
    ad = d @ a
    f = jnp.sum(ad * d, axis=1) - 1.0
    return safe_div(f, 2.0 * safe_norm(ad, axis=-1))


def _ellipse_cost(theta, q, w, r0):
    return 0.5 * jnp.sum(w * _sampson(theta, q, r0) ** 2)


@jax.jit
def _ellipse_step(theta, q, w, r0):
    """The weighted residuals (n,) and their Jacobian (n, 5) at ``theta``."""
    sw = jnp.sqrt(w)
    r = _sampson(theta, q, r0)
    j = jax.jacfwd(_sampson)(theta, q, r0)
    return sw * r, sw[:, None] * j


@jax.jit
def _ellipse_sensitivity(theta, q, w, r0):
    """d theta / d q (5, n, 2) at a minimum, by the implicit-function theorem."""
    h = jax.hessian(_ellipse_cost)(theta, q, w, r0)
    b = jax.jacfwd(jax.grad(_ellipse_cost), argnums=1)(theta, q, w, r0)
    return -jnp.linalg.solve(h, b.reshape(5, -1)).reshape(b.shape)


def _ellipse_quantities(theta, r0):
    """``[cx, cy, major, minor, orientation, ovality, mean_diameter]`` of ``theta``."""
    a11, a12, a22 = theta[2] / r0**2, theta[3] / r0**2, theta[4] / r0**2
    m, u, v = 0.5 * (a11 + a22), 0.5 * (a11 - a22), a12
    g = safe_sqrt(u * u + v * v)
    semi_a, semi_b = 1.0 / jnp.sqrt(m - g), 1.0 / jnp.sqrt(m + g)
    # the major axis is the eigenvector of the smaller eigenvalue m - g: 90 deg from the larger's
    phi = 0.5 * jnp.arctan2(v, u) + 0.5 * jnp.pi
    phi = jnp.where(phi > 0.5 * jnp.pi, phi - jnp.pi, phi)
    ovality = 2.0 * (semi_a - semi_b) / (semi_a + semi_b)
    return jnp.stack([theta[0], theta[1], 2 * semi_a, 2 * semi_b, phi, ovality, semi_a + semi_b])


_ellipse_quantities_jac = jax.jit(jax.jacfwd(_ellipse_quantities))
_ellipse_quantities_jit = jax.jit(_ellipse_quantities)


def fit_ellipse(pp: PlanePoints, iters: int = 60, debias: bool = True) -> Ellipse:
    """Fit an ellipse to :class:`PlanePoints` (see the module): the circle first, then damped
    Gauss-Newton on the weighted Sampson distances (the circle's weights: each point's inverse
    radial variance); with ``debias`` each diameter less twice the circle's
    :func:`tangential_bias` (a first approximation for a small ovality).  Raises ``ValueError`` for
    fewer than 5 points or a fit that is not an ellipse."""
    q = np.asarray(pp.q, float).reshape(-1, 2)
    n = q.shape[0]
    if n < 5:
        raise ValueError(f"an ellipse needs at least 5 points, got {n}")
    circ, w = fit_circle_theta(q, pp.blocks, 50)
    r0 = float(circ[2])
    size = bucket(n)
    qp, wp = jnp.asarray(pad_rows(q, size)), jnp.asarray(pad_rows(w, size, 0.0))
    theta = np.array([circ[0], circ[1], 1.0, 0.0, 1.0])
    rw, jw = (np.asarray(x) for x in _ellipse_step(jnp.asarray(theta), qp, wp, r0))
    cost = float(rw @ rw)
    for _ in range(iters):
        step, *_ = np.linalg.lstsq(jw, -rw, rcond=None)
        for _halve in range(30):
            trial = theta + step
            rt, jt = (np.asarray(x) for x in _ellipse_step(jnp.asarray(trial), qp, wp, r0))
            if np.all(np.isfinite(rt)) and float(rt @ rt) <= cost:
                break
            step = 0.5 * step
        else:
            break
        theta, rw, jw, cost = trial, rt, jt, float(rt @ rt)
        if np.max(np.abs(step)) < 1e-13 * max(1.0, r0):
            break
    vals = np.array(_ellipse_quantities_jit(jnp.asarray(theta), r0))
    if debias:  # the circle's tangential bias off each diameter (the ovality left as fitted)
        shift = 2.0 * tangential_bias(q, pp.pixel_cov, w, theta[:2], 0.5 * float(vals[6]))
        vals[[2, 3, 6]] -= shift
    s = theta[2:]
    if not (np.all(np.isfinite(vals)) and s[0] * s[2] - s[1] ** 2 > 0 and s[0] + s[2] > 0):
        raise ValueError("the ellipse fit did not give an ellipse (the points do not bound one)")
    res = np.asarray(_sampson(jnp.asarray(theta), jnp.asarray(q), r0))
    sens = np.asarray(_ellipse_sensitivity(jnp.asarray(theta), qp, wp, r0))[:, :n]
    jd = np.asarray(_ellipse_quantities_jac(jnp.asarray(theta), r0))
    cq = jd @ pp.propagate(sens) @ jd.T
    std = None
    if np.all(np.isfinite(cq)):
        sd = np.sqrt(np.maximum(np.diag(cq), 0.0))
        std = {
            "center": sd[:2],
            "major": float(sd[2]),
            "minor": float(sd[3]),
            "orientation": float(sd[4]),
            "ovality": float(sd[5]),
            "mean_diameter": float(sd[6]),
        }
    return Ellipse(
        vals[:2].copy(),
        float(vals[2]),
        float(vals[3]),
        float(vals[4]),
        float(vals[5]),
        float(vals[6]),
        std,
        res,
        float(np.sqrt(np.mean(res**2))),
    )


def fit_rings(svp: StripeViewPoints, kinds, axis=(0.0, 0.0, 1.0)) -> tuple[dict, list[str]]:
    """Each ring laser's circle and ellipse in one view: ``{laser: (Circle, Ellipse or None)}``
    (``kinds``: the rig's element kinds; a ring laser is a ``cone``), and notes on the rings left
    without (fewer than 5 usable samples) or without an ellipse (the fit gave none)."""
    out, notes = {}, []
    for e, kind in enumerate(kinds):
        if kind != "cone" or not np.any(svp.lasers == e):
            continue
        pp = ring_plane_points(svp, e, axis)
        if len(pp.q) < 5:
            notes.append(f"ring laser {e}: {len(pp.q)} usable samples, no circle (it needs 5)")
            continue
        circle = fit_circle_factored(pp)
        try:
            ellipse = fit_ellipse(pp)
        except ValueError as exc:
            ellipse = None
            notes.append(f"ring laser {e}: no ellipse ({exc})")
        out[e] = (circle, ellipse)
    return out, notes
