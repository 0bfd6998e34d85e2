"""The covariance of a solution, and the noise of each kind of observation.

One path: the problem is linearised at the solution (the compiled solve with no step) and
``H = J^T W J`` inverted by its Schur complement (:func:`covariance_of_linearisation`,
``sigma^2 H^-1``).  Where each kind of observation (dot, spot, rim, chess corner) has its own noise
sigma (:func:`kind_noise`: its squared residuals over its rows less the parameters they fix), the
covariance is the sandwich ``H^-1 (sum_k sigma_k^2 N_k) H^-1`` (:func:`covariance_and_noise`).
Frozen parameters, and those no weighted row reaches, get zero (co)variance.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ..observations.problem import KIND_NAMES, Kind, Layout, Packed, kinds_of
from ..support.persist import PersistentJit
from .base import CalibrationError
from .evaluate import linearisation_at, per_observation, solution_linearisation, solve_compiled
from .laser_fit import RAYLEIGH_MEDIAN
from .linearise import Linearisation
from .params import Masks, Params, make_masks, pad_masks
from .schur import Normal, leverage_shares, raw_normal, schur_inverse


class Covariance(NamedTuple):
    """Covariance at a solution: global block, per-pose marginals, and the noise estimate."""

    glob: Float[Array, "G G"]
    blocks: Float[Array, "NB 6 6"]
    sigma: Float[Array, ""]
    dof: Int[Array, ""]


def pooled_noise(lin: Linearisation, masks: Masks) -> tuple[Array, Array]:
    """The pooled noise variance ``sum(w r^2) / (n - k)`` over the valid scalar residuals (``n``)
    and the estimated parameters the weighted rows reach (``k``), and ``n - k``."""
    k = jnp.sum(masks.glob * lin.seen_glob) + 6 * jnp.sum(masks.blocks * lin.seen_blocks)
    dof = (lin.n_valid - k).astype(jnp.int64)
    return lin.weighted_sq / jnp.maximum(dof, 1).astype(float), dof


def covariance_of_linearisation(lin: Linearisation, masks: Masks, sigma: float | Array | None = None) -> Covariance:
    """``sigma^2 (J^T W J)^-1`` by the Schur complement; ``sigma`` from the residuals when None.

    The residual estimate is ``sum(w r^2) / (n - k)`` over the valid scalar residuals
    (``n``) and the estimated parameters (``k``).  Frozen parameters get zero variance.
    """
    pooled, dof = pooled_noise(lin, masks)
    s2 = pooled if sigma is None else jnp.asarray(sigma, dtype=float) ** 2
    Sinv, Dinv, Dinv_Bt = schur_inverse(lin.normal)
    cov_p = s2 * (Dinv + jnp.einsum("kig,gh,kjh->kij", Dinv_Bt, Sinv, Dinv_Bt))
    return _estimated_only(lin, masks, Covariance(s2 * Sinv, cov_p, jnp.sqrt(s2), dof))


def _estimated_only(lin: Linearisation, masks: Masks, cov: Covariance) -> Covariance:
    """``cov`` with zero (co)variance for the frozen parameters and those no weighted row reaches."""
    mg = masks.glob * lin.seen_glob
    return cov._replace(
        glob=cov.glob * mg[:, None] * mg[None, :], blocks=cov.blocks * (masks.blocks * lin.seen_blocks)[:, None, None]
    )


def sandwich_covariance(lin: Linearisation, meat: Normal, masks: Masks) -> Covariance:
    """``H^-1 M H^-1`` by the Schur complement: the covariance of the solution of the normal
    equations ``H`` (``lin``'s) when its rows' noise gives ``J^T W Cov(r) W J = M`` (``meat``, a
    plain sum in Schur form, :func:`raw_normal`), as where each kind of observation has its own
    noise sigma and ``M = sum_k sigma_k^2 N_k``.  With ``M = sigma^2 H`` it is
    :func:`covariance_of_linearisation`'s.  ``sigma`` and ``dof`` are the pooled ones.

    With ``E_k = D_k^-1 B_k^T`` the global block is ``S^-1 (A_M - sum_k (C_k E_k + E_k^T C_k^T)
    + sum_k E_k^T D_Mk E_k) S^-1`` (``C_k`` block ``k``'s coupling in ``M``) and pose block ``k``'s
    ``E_k G E_k^T - E_k S^-1 F_k D_k^-1 - (..)^T + D_k^-1 D_Mk D_k^-1`` with
    ``F_k = C_k - E_k^T D_Mk``."""
    Sinv, Dinv, E = schur_inverse(lin.normal)
    C = meat.B  # (NB, G, 6)
    CE = jnp.einsum("kgi,kih->gh", C, E)
    inner = meat.A - CE - CE.T + jnp.einsum("kig,kij,kjh->gh", E, meat.D, E)
    cov_g = Sinv @ inner @ Sinv
    F = C - jnp.einsum("kig,kij->kgj", E, meat.D)  # (NB, G, 6)
    cross = jnp.einsum("kig,gh,khj,kjl->kil", E, Sinv, F, Dinv)
    cov_p = (
        jnp.einsum("kig,gh,kjh->kij", E, cov_g, E)
        - cross
        - jnp.swapaxes(cross, 1, 2)
        + jnp.einsum("kij,kjl,klm->kim", Dinv, meat.D, Dinv)
    )
    s2, dof = pooled_noise(lin, masks)
    return _estimated_only(lin, masks, Covariance(cov_g, cov_p, jnp.sqrt(s2), dof))


covariance_compiled = jax.jit(covariance_of_linearisation)


HALF_NORMAL_MEDIAN = 0.6744897501960817  # median of |r| / sigma for 1D Gaussian r


def covariance_of(params: Params, pk: Packed, masks: Masks, loss: str, scale, sigma: float | None = None) -> Covariance:
    """:func:`slcvjax.calibration.covariance.covariance_of_linearisation` at ``params`` of the problem ``pk``,
    through its shape buckets (the compiled solve with no step linearises): with one ``sigma``
    given, ``sigma^2 H^-1`` (every kind weighted 1); with one per kind (dot, spot, rim, chess
    corner), ``(sum_k N_k / sigma_k^2)^-1`` (each kind weighted by its noise: the Cramer-Rao
    bound where the kinds' noise differ); otherwise :func:`covariance_and_noise`'s."""
    if sigma is None:
        return covariance_and_noise(params, pk, masks, loss, scale)[0]
    sig = np.asarray(sigma, dtype=float)
    if sig.ndim == 1:
        n_k = len(kinds_of(pk))
        if sig.shape != (n_k,) or not np.all(np.isfinite(sig) & (sig > 0)):
            raise ValueError(
                f"per-kind sigmas: expected {n_k} positive numbers ({', '.join(KIND_NAMES[:n_k])}), got {sig}"
            )
        layout, lin = linearisation_at(params, pk, masks, loss, scale, kind_weight=tuple(1.0 / sig**2))
        sig = np.asarray(1.0)
    else:
        layout, lin = linearisation_at(params, pk, masks, loss, scale)
    cov = covariance_compiled(lin, pad_masks(layout, masks), jnp.asarray(sig, dtype=float))
    return unpad_covariance(layout, cov)


def unpad_covariance(layout: Layout, cov: Covariance) -> Covariance:
    """A covariance of the padded problem restricted to the real lasers and pose blocks."""
    return cov._replace(glob=layout.unpad_glob(cov.glob, (0, 1)), blocks=layout.unpad_blocks(cov.blocks))


def covariance_and_noise(params: Params, pk: Packed, masks: Masks, loss: str, scale) -> "tuple[Covariance, KindNoise]":
    """The covariance of the solution ``params`` where each kind of observation has its own noise
    (:func:`kind_noise`): ``H^-1 (sum_k sigma_k^2 N_k) H^-1`` (``N_k`` the kind's ``J^T W J``;
    :func:`slcvjax.calibration.covariance.sandwich_covariance`), the solve having weighted every kind 1.
    Rendered images give the kinds different noise (spots' centroids noisier than dots', the
    rim's fitted edge far less noisy), which one pooled sigma would misstate.  A kind with too
    few free rows for its own sigma takes the pooled one.  With one noise for every kind it is
    ``sigma^2 H^-1``."""
    return sandwich_of(*kind_linearisations(params, pk, masks, loss, scale), masks)


def sandwich_of(layout: Layout, full, parts, masks: Masks) -> "tuple[Covariance, KindNoise]":
    """:func:`covariance_and_noise` of :func:`kind_linearisations`' linearisations."""
    noise = _noise_of(full, parts)
    padded = pad_masks(layout, masks)
    pooled2 = float(_pooled_noise_jit(full, padded)[0])
    meat = None
    for p, sig, n in zip(parts, noise.sigma, noise.rows, strict=True):
        if n == 0:
            continue
        raw = [np.asarray(a) for a in _raw_normal_jit(p.normal, p.seen_glob, p.seen_blocks)]
        s2 = sig**2 if np.isfinite(sig) else pooled2
        meat = [s2 * a for a in raw] if meat is None else [m + s2 * a for m, a in zip(meat, raw, strict=True)]
    if meat is None:
        raise CalibrationError(
            "the fit ended where it predicts none of the observations (each falls off the mirror or the "
            "sensor): the model does not fit these data (another mirror kind or camera projection may)"
        )
    cov = _sandwich_jit(full, type(full.normal)(*meat), padded)
    return unpad_covariance(layout, cov), noise


def kind_sigmas(params: Params, pk: Packed, min_count: int = 10) -> np.ndarray:
    """Per kind (dot, spot, rim, chess corner, and stripe sample where there are stripes) the
    noise sigma (px) from its median residual.

    Rim and stripe residuals are 1D (a distance to a curve), the others 2D.  NaN for a kind
    with fewer than ``min_count`` valid observations.
    """
    return sigmas_of(*per_observation(params, pk), min_count)[: len(kinds_of(pk))]


def sigmas_of(norm, kind, ok, min_count: int = 10) -> np.ndarray:
    """:func:`kind_sigmas` of a per-observation table (``per_observation``'s)."""
    out = np.full(len(Kind), np.nan)
    for k in Kind:
        sel = ok & (kind == k)
        if sel.sum() >= min_count:
            out[k] = np.median(norm[sel]) / (HALF_NORMAL_MEDIAN if k.rows == 1 else RAYLEIGH_MEDIAN)
    return out


_leverage_shares_jit = PersistentJit(leverage_shares, "leverage_shares")


_sandwich_jit = PersistentJit(sandwich_covariance, "sandwich_covariance")


_raw_normal_jit = PersistentJit(raw_normal, "raw_normal")


_pooled_noise_jit = PersistentJit(pooled_noise, "pooled_noise")


MIN_FREE_ROWS = 20  # a kind whose rows leave fewer free than this takes the pooled sigma


class KindNoise(NamedTuple):
    """Per kind (dot, spot, rim, chess corner): its valid scalar rows, the parameters its rows
    fix (the sum of their leverages), and its noise sigma (px) over the rows left free (NaN where
    fewer than :data:`MIN_FREE_ROWS` are)."""

    rows: np.ndarray
    leverage: np.ndarray
    sigma: np.ndarray


def kind_linearisations(params: Params, pk: Packed, masks: Masks, loss: str, scale):
    """The padded layout, the linearisation at ``params`` with every kind weighted 1 (as the
    solve weighs them), and one per kind with that kind alone (the compiled solve with no
    step: nothing new compiles)."""
    layout, p, padded, m, full = solution_linearisation(params, pk, masks, loss, scale)
    # one kind's rows alone: the others' counted as padding, which the sums skip
    kinds = kinds_of(pk)
    parts = [
        solve_compiled(p, padded.kinds_only(np.eye(len(kinds))[k]), m, loss, scale, 0).linearisation for k in kinds
    ]
    return layout, full, parts


def _noise_of(full, parts) -> KindNoise:
    t = full.table
    real = np.asarray(t.valid) & np.asarray(t.present)
    kinds = np.asarray(t.kind)
    present = tuple(Kind)[: len(parts)]
    rows = np.array([float(k.rows) * np.sum(real & (kinds == k)) for k in present])
    # every kind's share in one call (H^-1 once); a kind without rows fixes nothing
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *((p.normal, p.seen_glob, p.seen_blocks) for p in parts))
    lev = np.where(rows > 0, np.asarray(_leverage_shares_jit(full.normal, *stacked)), 0.0)
    free = rows - lev
    # the plain squared residuals: under the robust loss a kind noisier than its scale would have
    # its large residuals down-weighted and its sigma understated (gross outliers are left out
    # by then)
    sq = np.asarray(t.sq)
    wsq = np.array([float(np.sum(sq[real & (kinds == k)])) for k in present])
    sigma = np.where(free >= MIN_FREE_ROWS, np.sqrt(wsq / np.maximum(free, 1.0)), np.nan)
    return KindNoise(rows, lev, sigma)


def kind_noise(params: Params, pk: Packed, masks: Masks | None = None, loss: str = "huber", scale=1.0) -> KindNoise:
    """Each kind's noise sigma at the solution ``params``, from its squared residuals over its
    rows less the parameters they fix (:class:`KindNoise`,
    :func:`slcvjax.calibration.schur.leverage_share`).

    Board poses are fixed by their dots and, where a board shows few dots, by its spots; the
    lasers by the spots: on the paper preset the spots' rows fix about half of what they hold
    (144 of 296), so their residuals understate their noise by about 1.4x.  Over all kinds the
    leverages add up to the number of estimated parameters."""
    masks = make_masks(params) if masks is None else masks
    _, full, parts = kind_linearisations(params, pk, masks, loss, scale)
    return _noise_of(full, parts)


def robust_sigma(params: Params, pk: Packed) -> float:
    """Noise sigma (px) from the median 2D residual norm of the dots, spots and corners."""
    return robust_sigma_of(*per_observation(params, pk))


def robust_sigma_of(norm, kind, ok) -> float:
    """:func:`robust_sigma` of a per-observation table (``per_observation``'s)."""
    sel = ok & (kind != Kind.RIM) & (kind != Kind.STRIPE)
    if not sel.any():
        return 1.0
    return float(np.median(norm[sel]) / RAYLEIGH_MEDIAN)
