"""Measuring with line and ring lasers: stripe samples -> 3D points with uncertainty.

A stripe sample is a pixel on the centre line of a line or ring laser's stripe.  Its pixel is
back-projected through the mirror (closed form, :func:`slcvjax.geometry.mirror.back_project`)
to a reflected ray, and the 3D point is where that ray first meets the laser's sheet of light
ahead of the mirror (:func:`slcvjax.geometry.sheets.ray_meets_sheet`, forward only: a plane's
one root, a cone's nearest root on its own nappe).  Unlike a point laser's spot, the sample is
exactly on its sheet by construction, so no closest-approach gap is left over.

Uncertainty is first order, as for the spots (:mod:`slcvjax.measurement.measure`): the
Jacobians of the point with respect to the sample's pixel (3, 2) and to the rig's tangent
(3, G; only the camera's, the mirror's and that sheet's columns are non-zero) propagate the
pixel noise (``sigma`` px per coordinate, independent per sample) and the calibration's
covariance (G, G), which every sample of every view shares.  The joint covariance of a view's
points is therefore kept in factored form: a (3, 3) pixel block per sample plus
``J_rig C J_rig^T``.

Grazing rays: where the reflected ray runs nearly in the sheet, a small error of either moves
the intersection far along the ray, and the first-order std stops being trustworthy.  The
angle between the ray and the sheet's tangent plane at the point (``angle``) has its own
first-order std (from the pixel noise and the calibration's covariance); a point is flagged
``grazing`` when its angle is under ``GRAZING_FACTOR`` times that std, or under
``GRAZING_FLOOR_DEG`` whatever the noise.  A ray exactly in a plane, or tangent to a cone, gives
no point at all: it is listed in ``missing`` with its reason (never a NaN).
"""

from dataclasses import dataclass, field
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ..geometry.mirror import back_project
from ..geometry.rig import Rig
from ..geometry.sheets import ray_meets_sheet, sheet_gradient
from ..observations.problem import map_padded, map_rows
from ..support.persist import PersistentJit
from ..support.safe import safe_arccos, safe_normalize, std_of_variance

GRAZING_FACTOR = 5.0  # an angle between ray and sheet under this many of its own stds is "grazing"
GRAZING_FLOOR_DEG = 0.5  # ... and always under this angle (its std is 0 with exact pixels and rig)


class SamplePoint(NamedTuple):
    """One triangulated stripe sample (camera frame).

    Attributes:
        xyz: (3,) the point where the reflected ray meets the sheet (mm).
        angle: () the angle between the ray and the sheet's tangent plane at the point (rad, in
            [0, pi/2]; 0 is a ray in the sheet).
        reach: () the distance from the mirror point to the point along the ray (mm).
        valid: () False where the pixel's ray misses the mirror or meets the sheet nowhere ahead
            of the mirror (then ``xyz`` is the mirror point, finite and meaningless).
    """

    xyz: Float[Array, "3"]
    angle: Float[Array, ""]
    reach: Float[Array, ""]
    valid: Bool[Array, ""]


def triangulate_sample(rig: Rig, sheet: Int[Array, ""], uv: Float[Array, "2"]) -> SamplePoint:
    """The 3D point of one stripe sample: pixel ``uv`` (px) of sheet ``sheet`` (its index among
    ``rig.sheets``, not its element index), camera frame, mm.

    Values and gradients stay finite everywhere, a ray tangent to the sheet included.
    """
    sh = rig.sheets
    ray = back_project(rig.camera, rig.mirror, uv)
    p, a, th = sh.apex[sheet], sh.axis[sheet], sh.half_angle[sheet]
    cone = jnp.asarray(sh.is_cone)[sheet]
    lam, x, ok = ray_meets_sheet(ray.point, ray.direction, p, a, th, cone, forward_only=True)
    n = safe_normalize(sheet_gradient(x, p, a, th))
    s = jnp.abs(jnp.dot(safe_normalize(ray.direction), n))
    angle = 0.5 * jnp.pi - safe_arccos(s)
    return SamplePoint(x, angle, lam, ray.valid & ok)


def _sample_jacobians(rig: Rig, rows):
    """Rows ``[sheet, u, v]`` -> points, the Jacobians of ``(xyz, angle)`` with respect to the
    pixel (n, 4, 2) and the rig's tangent (n, 4, G)."""
    g = rig.tangent_dim

    def one(row):
        sheet, px = row[0].astype(jnp.int32), row[1:3]

        def f(delta, px):
            sp = triangulate_sample(rig.retract(delta), sheet, px)
            return jnp.concatenate([sp.xyz, sp.angle[None]])

        j_rig, j_px = jax.jacfwd(f, argnums=(0, 1))(jnp.zeros(g), px)
        return triangulate_sample(rig, sheet, px), j_px, j_rig

    return jax.vmap(one)(rows)


_sample_jacobians_jit = PersistentJit(map_rows(_sample_jacobians, chunk=128), "stripe_sample_jacobians")


@dataclass
class StripeViewPoints:
    """The measured stripe points of one view, in the order of its stripes and their samples.

    Attributes:
        lasers: (n,) each point's laser (its element index: ``lasers[i]`` of the calibration file).
        stripe_index: (n,) each point's stripe among the view's stripes (input order).
        sample_index: (n,) each point's sample among its stripe's pixels.
        xyz: (n, 3) the points, camera frame (mm).
        pixel_cov: (n, 3, 3) each point's covariance from its own pixel noise (mm^2).
        j_rig: (n, 3, G) the points' Jacobian with respect to the rig's tangent (mm per unit of
            each column), or None without a calibration covariance.
        rig_cov: (G, G) the calibration's covariance (shared by every point), or None.
        angle: (n,) the angle between each reflected ray and its sheet (rad).
        angle_std: (n,) that angle's first-order std (rad).
        grazing: (n,) the ray is nearly in the sheet (see the module): the point's std is not
            trustworthy, and fits leave it out.
        missing: samples that gave no point: ``(stripe_index, sample_index, laser, reason)``.
    """

    lasers: np.ndarray
    stripe_index: np.ndarray
    sample_index: np.ndarray
    xyz: np.ndarray
    pixel_cov: np.ndarray
    j_rig: np.ndarray | None
    rig_cov: np.ndarray | None
    angle: np.ndarray
    angle_std: np.ndarray
    grazing: np.ndarray
    missing: list[tuple[int, int, int, str]] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.lasers)

    @property
    def cov_blocks(self) -> np.ndarray:
        """(n, 3, 3) each point's own covariance (pixel noise and calibration), mm^2."""
        out = self.pixel_cov.copy()
        if self.j_rig is not None and self.rig_cov is not None:
            out += np.einsum("nag,gh,nbh->nab", self.j_rig, self.rig_cov, self.j_rig)
        return out

    @property
    def std(self) -> np.ndarray:
        """(n, 3) each coordinate's std (mm); NaN where the covariance is not positive."""
        return std_of_variance(np.diagonal(self.cov_blocks, axis1=1, axis2=2))

    def joint_cov(self, idx=None) -> np.ndarray:
        """The (3k, 3k) joint covariance of the points ``idx`` (default all; mm^2): the pixel
        blocks on the diagonal plus the calibration's shared part.  Dense: for a few hundred
        points at most; fits use the factored form."""
        idx = np.arange(len(self)) if idx is None else np.asarray(idx)
        k = idx.size
        cov = np.zeros((3 * k, 3 * k))
        for m, i in enumerate(idx):
            cov[3 * m : 3 * m + 3, 3 * m : 3 * m + 3] = self.pixel_cov[i]
        if self.j_rig is not None and self.rig_cov is not None and k:
            jr = self.j_rig[idx].reshape(3 * k, -1)
            cov += jr @ self.rig_cov @ jr.T
        return cov

    def select(self, idx) -> "StripeViewPoints":
        """The points ``idx`` (an index array or boolean mask) with the same calibration part."""
        idx = np.arange(len(self))[idx]
        return StripeViewPoints(
            self.lasers[idx],
            self.stripe_index[idx],
            self.sample_index[idx],
            self.xyz[idx],
            self.pixel_cov[idx],
            None if self.j_rig is None else self.j_rig[idx],
            self.rig_cov,
            self.angle[idx],
            self.angle_std[idx],
            self.grazing[idx],
            list(self.missing),
        )


def measure_stripes(
    rig: Rig,
    lasers: np.ndarray,
    stripe_of: np.ndarray,
    sample_of: np.ndarray,
    pixels: np.ndarray,
    view_of: np.ndarray,
    n_views: int,
    pixel_sigma: float,
    rig_cov: np.ndarray | None = None,
    undetermined: tuple[int, ...] = (),
) -> list[StripeViewPoints]:
    """Triangulate every stripe sample of several views in one compiled call.

    Args:
        rig: the calibrated rig (with its sheets of light).
        lasers: (N,) each sample's laser, its element index (``lasers[i]`` of the files); it must
            be a line or ring laser of ``rig``.
        stripe_of: (N,) each sample's stripe index in its view.
        sample_of: (N,) each sample's index in its stripe.
        pixels: (N, 2) the samples' pixels (px).
        view_of: (N,) each sample's view.
        n_views: the number of views.
        pixel_sigma: the samples' pixel noise (px per coordinate; the calibration's stripe sigma).
        rig_cov: optional (G, G) covariance of the rig's tangent (the calibration file's
            ``uncertainty.covariance.matrix``, :attr:`slcvjax.geometry.rig.Rig.layout` order).
        undetermined: lasers the calibration could not fix: their samples give no point (each is
            listed in ``missing``).

    Returns one :class:`StripeViewPoints` per view.  Raises ``ValueError`` naming the sample for a
    laser that is not a line or ring laser of the rig, and for a bad sigma or covariance shape.
    """
    if not np.isfinite(pixel_sigma) or pixel_sigma < 0:
        raise ValueError(f"pixel sigma must be a non-negative number of pixels, got {pixel_sigma}")
    g = rig.tangent_dim
    if rig_cov is not None and np.shape(rig_cov) != (g, g):
        raise ValueError(f"rig covariance has shape {np.shape(rig_cov)}, expected {(g, g)}")
    lasers = np.asarray(lasers, dtype=np.int64).reshape(-1)
    pixels = np.asarray(pixels, dtype=float).reshape(-1, 2)
    n = len(pixels)
    stripe_of, sample_of, view_of = (np.asarray(a, dtype=np.int64).reshape(-1) for a in (stripe_of, sample_of, view_of))
    if any(a.shape != (n,) for a in (lasers, stripe_of, sample_of, view_of)):
        raise ValueError(f"{n} sample pixels need as many laser, stripe, sample and view indices")
    kinds = rig.element_kinds
    bad = [i for i, e in enumerate(lasers) if not (0 <= e < len(kinds)) or kinds[e] == "point"]
    if bad:
        i = bad[0]
        what = "is not one of the rig's lasers" if not 0 <= lasers[i] < len(kinds) else "is a point laser"
        raise ValueError(
            f"view {view_of[i]}, stripe {stripe_of[i]}, sample {sample_of[i]}: laser {lasers[i]} {what} "
            "(a stripe needs a line or ring laser)"
        )
    local = rig.local_index
    if n:
        rows = np.column_stack([local[lasers].astype(float), pixels])
        sp, j_px, j_rig = map_padded(_sample_jacobians_jit, rig, rows=rows)
        xyz, angle, valid = sp.xyz, sp.angle, np.asarray(sp.valid, bool)
    else:
        xyz, angle, valid = np.zeros((0, 3)), np.zeros(0), np.zeros(0, bool)
        j_px, j_rig = np.zeros((0, 4, 2)), np.zeros((0, 4, g))
    finite = np.all(np.isfinite(xyz), axis=1) & np.isfinite(angle)
    pixel_cov = pixel_sigma**2 * np.einsum("nai,nbi->nab", j_px[:, :3], j_px[:, :3])
    angle_var = pixel_sigma**2 * np.sum(j_px[:, 3] ** 2, axis=1)
    if rig_cov is not None and n:
        angle_var = angle_var + np.einsum("ng,gh,nh->n", j_rig[:, 3], rig_cov, j_rig[:, 3])
    angle_std = np.sqrt(np.maximum(angle_var, 0.0))
    grazing = (angle < GRAZING_FACTOR * angle_std) | (angle < np.radians(GRAZING_FLOOR_DEG))
    held = np.isin(lasers, np.asarray(undetermined, dtype=np.int64))
    usable = valid & finite & ~held
    out = []
    for v in range(n_views):
        idx = np.flatnonzero(view_of == v)
        good = idx[usable[idx]]
        missing = []
        for i in idx[~usable[idx]]:
            if held[i]:
                why = f"laser {lasers[i]} is undetermined in the calibration (the data did not fix its sheet)"
            elif not finite[i]:
                why = "its point is not finite"
            else:
                why = "its reflected ray misses the mirror, or meets the laser's sheet nowhere ahead of the mirror"
            missing.append((int(stripe_of[i]), int(sample_of[i]), int(lasers[i]), why))
        out.append(
            StripeViewPoints(
                lasers=lasers[good],
                stripe_index=stripe_of[good],
                sample_index=sample_of[good],
                xyz=np.asarray(xyz[good], float),
                pixel_cov=pixel_cov[good],
                j_rig=None if rig_cov is None else np.asarray(j_rig[good, :3], float),
                rig_cov=None if rig_cov is None else np.asarray(rig_cov, float),
                angle=np.asarray(angle[good], float),
                angle_std=angle_std[good],
                grazing=grazing[good],
                missing=missing,
            )
        )
    return out


def measure_stripe_observations(
    rig: Rig, obs, pixel_sigma: float, rig_cov: np.ndarray | None = None, undetermined: tuple[int, ...] = ()
) -> list[StripeViewPoints]:
    """:func:`measure_stripes` of every stripe sample of every view of ``obs``
    (:class:`slcvjax.observations.formats.Observations`; its lasers must be the rig's elements)."""
    if obs.n_lasers != rig.n_elements:
        raise ValueError(f"the observations have {obs.n_lasers} lasers, the calibration {rig.n_elements}")
    lasers, stripe_of, sample_of, pixels, view_of = [], [], [], [], []
    for v, view in enumerate(obs.views):
        for k, s in enumerate(view.stripes):
            m = len(s.pixels)
            lasers.append(np.full(m, s.laser))
            stripe_of.append(np.full(m, k))
            sample_of.append(np.arange(m))
            pixels.append(np.asarray(s.pixels, float).reshape(-1, 2))
            view_of.append(np.full(m, v))

    def cat(parts, shape=(0,)):
        return np.concatenate(parts) if parts else np.zeros(shape)

    return measure_stripes(
        rig, cat(lasers).astype(int), cat(stripe_of).astype(int), cat(sample_of).astype(int),
        cat(pixels, (0, 2)), cat(view_of).astype(int), len(obs.views), pixel_sigma, rig_cov, undetermined,
    )  # fmt: skip
