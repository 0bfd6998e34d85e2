"""Laser stripes in catadioptric images: the sub-pixel centre lines of line and ring lasers' light.

A line or ring laser draws a thin stripe on whatever it lights, with a Gaussian profile across
it.  Its centre line is found in two steps, per image:

1. **Ridge pixels** (Steger's method): the laser's light relative to the scene's,
   ``S = red / green - 1`` (white walls and dark dots alike: the ratio divides the albedo out),
   smoothed by a Gaussian of ``sigma`` px.  At each pixel the Hessian's eigenvector of its most
   negative eigenvalue is the stripe's normal ``n`` in the image, and the second-order Taylor
   expansion along ``n`` has its maximum at ``t = -(grad S . n) / (n^T H n)``; a pixel is a ridge
   pixel where that maximum falls inside it (``|t n_u|, |t n_v| <= 0.5``), the curvature across is
   strong enough, the curvature along is under half of it (a line, not a blob: a point laser's
   spot has two equal curvatures), and the light is above a threshold.  This gives about one
   sample per pixel along the stripe.  Ridge pixels are linked by 8-connectivity; short pieces
   are dropped.
2. **Centre** (a Gaussian fit across): ``S`` itself (not smoothed) is sampled along ``n`` every
   half pixel over ``+-3 sigma`` (bicubic), and a parabola fitted to ``log S`` (weighted by
   ``S^2``, the samples above 15 % of the peak) gives the centre's offset along ``n``; once more
   from there.  A profile read along the exact normal of a curved stripe is still symmetric (the
   distance to a circle along its normal is ``|t|``), so the centre is not pulled towards the
   centre of curvature as a smoothed ridge's is.

Samples are left out where the fit cannot be trusted: on or next to a dark dot (its image's
edge mixes darkness into the ratio), against the rim, and where the profile is much brighter
than the rest of its piece (a point laser's spot on the stripe).

Pixels: OpenCV's (integer coordinates at pixel centres), ``(u, v)``.
"""

from dataclasses import dataclass

import cv2
import numpy as np

STRIPE_SIGMA_PX = 1.5  # the smoothing for the ridge pixels, about a stripe's own width in the image
MIN_PIECE = 8  # ridge pieces of fewer pixels are dropped
SPOT_FACTOR = 1.6  # a profile this much brighter than its piece's median is a spot on the stripe
MIN_STRIPE_PX = 30.0  # a lit region shorter than this (its length as a uniform bar) is a spot, not a stripe
BEND_DEG = 8.0  # samples whose normals differ by more than this within 3 sigma: a corner, left out


@dataclass
class StripeSamples:
    """The centre-line samples of one image's stripes (unlabelled).

    Attributes:
        pixels: (M, 2) px, sub-pixel centres on the stripes' centre lines.
        normals: (M, 2) unit, the stripe's normal in the image at each sample.
        peak: (M,) the fitted peak of the laser's relative light ``red / green - 1``.
        width: (M,) px, the fitted std of the profile across the stripe.
        piece: (M,) int, which linked piece of ridge pixels each sample came from.
        dropped: what was left out and why (counts by reason).
    """

    pixels: np.ndarray
    normals: np.ndarray
    peak: np.ndarray
    width: np.ndarray
    piece: np.ndarray
    dropped: dict


def laser_light(bgr: np.ndarray) -> np.ndarray:
    """The laser's light relative to the scene's, ``red / max(green, 4) - 1`` (H, W), float."""
    green = bgr[:, :, 1].astype(float)
    return bgr[:, :, 2].astype(float) / np.maximum(green, 4.0) - 1.0


def _derivatives(img: np.ndarray, sigma: float):
    """Gaussian-smoothed image and its first and second derivatives (each H x W) at scale ``sigma`` px."""
    r = int(np.ceil(4 * sigma))
    x = np.arange(-r, r + 1, dtype=float)
    g = np.exp(-0.5 * (x / sigma) ** 2)
    g /= g.sum()
    g1 = -x / sigma**2 * g
    g2 = (x**2 / sigma**4 - 1 / sigma**2) * g
    # correlation with the kernel reversed is convolution: flip the odd derivative
    f = lambda kx, ky: cv2.sepFilter2D(img, cv2.CV_64F, kx[::-1], ky[::-1], borderType=cv2.BORDER_REPLICATE)  # noqa: E731
    return f(g, g), f(g1, g), f(g, g1), f(g2, g), f(g1, g1), f(g, g2)


def ridge_pixels(
    light: np.ndarray,
    mask: np.ndarray,
    sigma: float = STRIPE_SIGMA_PX,
    threshold: float = 0.08,
    curvature: float | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Steger's ridge pixels of ``light`` (H, W) inside ``mask`` (H, W bool).

    Returns ``(pixels (K, 2) sub-pixel ridge points, normals (K, 2) unit, piece (K,) int)``: the
    linked pieces of at least ``MIN_PIECE`` pixels, numbered from 0.  ``threshold``: the least
    smoothed light on the ridge (a profile of peak ``A`` and std ``w`` px is ``A w / sqrt(w^2 +
    sigma^2)`` there), and its curvature across at least ``threshold / (w^2 + sigma^2)`` at
    ``w = 2 sigma`` (or ``curvature`` where given: the least ``-d2/dn2`` of the smoothed light).
    """
    s, sx, sy, sxx, sxy, syy = _derivatives(light, sigma)
    # the Hessian's most negative eigenvalue and its unit eigenvector
    half_tr = 0.5 * (sxx + syy)
    root = np.sqrt(0.25 * (sxx - syy) ** 2 + sxy**2)
    lam1, lam2 = half_tr - root, half_tr + root
    nx, ny = sxy, lam1 - sxx
    alt = np.abs(sxx - lam1) > np.abs(syy - lam1)  # the better-conditioned of the two forms
    nx = np.where(alt, lam1 - syy, nx)
    ny = np.where(alt, sxy, ny)
    norm = np.hypot(nx, ny)
    ok = norm > 1e-12
    nx, ny = np.where(ok, nx / np.where(ok, norm, 1), 1.0), np.where(ok, ny / np.where(ok, norm, 1), 0.0)
    t = -(sx * nx + sy * ny) / np.where(lam1 < 0, lam1, -1.0)
    curv = threshold / (5.0 * sigma**2) if curvature is None else curvature
    cand = (
        mask
        & ok
        & (lam1 < -curv)
        & (np.abs(lam2) < 0.5 * np.abs(lam1))
        & (s > threshold)
        & (np.abs(t * nx) <= 0.5)
        & (np.abs(t * ny) <= 0.5)
    )
    n, labels, stats, _ = cv2.connectedComponentsWithStats(cand.astype(np.uint8), connectivity=8)
    keep = np.zeros(n, bool)
    keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= MIN_PIECE
    ys, xs = np.nonzero(keep[labels])
    piece = np.unique(labels[ys, xs], return_inverse=True)[1].reshape(-1)
    tt = t[ys, xs]
    px = np.column_stack([xs + tt * nx[ys, xs], ys + tt * ny[ys, xs]])
    return px, np.column_stack([nx[ys, xs], ny[ys, xs]]), piece


def _profile_fit(light: np.ndarray, px: np.ndarray, nrm: np.ndarray, half: float):
    """One Gaussian fit across each stripe sample: ``log S`` sampled along the normal every half
    pixel over ``+-half`` px (bicubic), a parabola fitted (weights ``S^2``, samples above 15 % of
    the peak).  Returns ``(offset along the normal (K,) px, peak (K,), std (K,) px, ok (K,))``."""
    t = np.arange(-half, half + 1e-9, 0.5)
    mx = (px[:, 0:1] + t[None] * nrm[:, 0:1]).astype(np.float32)
    my = (px[:, 1:2] + t[None] * nrm[:, 1:2]).astype(np.float32)
    prof = cv2.remap(light.astype(np.float32), mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    prof = prof.astype(float)
    top = prof.max(axis=1, keepdims=True)
    use = prof > 0.15 * np.maximum(top, 1e-9)
    w = np.where(use, prof, 0.0) ** 2
    y = np.log(np.maximum(prof, 1e-9))
    # weighted least squares of y = a + b t + c t^2, per row
    T = np.stack([np.ones_like(t), t, t * t], axis=1)  # (n, 3)
    A = np.einsum("kn,ni,nj->kij", w, T, T)
    rhs = np.einsum("kn,ni,kn->ki", w, T, y)
    det_ok = np.abs(np.linalg.det(A)) > 1e-12
    A[~det_ok] = np.eye(3)
    coef = np.linalg.solve(A, rhs[..., None])[..., 0]
    a, b, c = coef[:, 0], coef[:, 1], coef[:, 2]
    ok = det_ok & (c < 0) & (use.sum(axis=1) >= 4)
    c_safe = np.where(ok, c, -1.0)
    off = -b / (2 * c_safe)
    peak = np.exp(a - b * b / (4 * c_safe))
    std = np.sqrt(-0.5 / c_safe)
    ok &= np.abs(off) <= 1.0
    return np.where(ok, off, 0.0), np.where(ok, peak, 0.0), np.where(ok, std, 0.0), ok


def find_stripes(
    bgr: np.ndarray,
    disc_mask: np.ndarray,
    avoid: np.ndarray | None = None,
    sigma: float = STRIPE_SIGMA_PX,
    threshold: float = 0.08,
    edge: int = 3,
) -> StripeSamples:
    """The centre-line samples of the laser stripes in one image (see the module).

    Args:
        bgr: (H, W, 3) uint8, OpenCV's BGR.
        disc_mask: (H, W) bool, the mirror's view (samples within ``edge`` px of its outline are
            left out: the rim cuts their profile).
        avoid: (H, W) bool or None, pixels whose neighbourhood spoils a profile (a dot's image);
            samples within ``2 sigma`` px of one are left out.
        sigma: px, the ridge's smoothing (about the stripe's std in the image).
        threshold: the least relative laser light ``red / green - 1`` on a stripe, smoothed.
    """
    light = laser_light(bgr)
    light = np.where(disc_mask, light, 0.0)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * edge + 1, 2 * edge + 1))
    core = cv2.erode(disc_mask.astype(np.uint8), kernel).astype(bool)
    px, nrm, piece = ridge_pixels(light, core, sigma, threshold)
    dropped: dict = {}
    if len(px):  # a point laser's spot: its lit region is short
        lit = (cv2.GaussianBlur(light, (0, 0), sigma) > threshold).astype(np.uint8)
        _, region = cv2.connectedComponents(lit, connectivity=8)
        iu = np.clip(np.rint(px).astype(int), 0, [light.shape[1] - 1, light.shape[0] - 1])
        reg = region[iu[:, 1], iu[:, 0]]
        short = np.zeros(len(px), bool)
        for k in np.unique(reg):
            ys, xs = np.nonzero(region == k)
            pts = np.column_stack([xs, ys]).astype(float)
            extent = 2.0 * np.sqrt(np.linalg.eigvalsh(np.cov(pts.T)).max() * 3.0) if len(pts) > 2 else 0.0
            short[reg == k] = k == 0 or extent < MIN_STRIPE_PX
        if short.any():
            dropped["a short lit region (a spot)"] = int(short.sum())
        px, nrm, piece = px[~short], nrm[~short], piece[~short]
    if avoid is not None and len(px):
        r = int(np.ceil(2 * sigma))
        near = cv2.dilate(avoid.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2))
        iu = np.clip(np.rint(px).astype(int), 0, [light.shape[1] - 1, light.shape[0] - 1])
        bad = near[iu[:, 1], iu[:, 0]] > 0
        if bad.any():
            dropped["next to a dark dot"] = int(bad.sum())
        px, nrm, piece = px[~bad], nrm[~bad], piece[~bad]
    half = 3.0 * sigma
    off, peak, std, ok = _profile_fit(light, px, nrm, half)
    px = px + off[:, None] * nrm
    off2, peak, std, ok2 = _profile_fit(light, px, nrm, half)
    px = px + off2[:, None] * nrm
    ok &= ok2 & (np.abs(off2) <= 0.5)
    if (~ok).any():
        dropped["no Gaussian profile across"] = int((~ok).sum())
    px, nrm, piece, peak, std = px[ok], nrm[ok], piece[ok], peak[ok], std[ok]
    # a point laser's spot on the stripe: far brighter than its piece
    spot = np.zeros(len(px), bool)
    for k in np.unique(piece):
        sel = piece == k
        spot[sel] = peak[sel] > SPOT_FACTOR * np.median(peak[sel])
    if spot.any():
        r = 4.0 * sigma
        d = np.linalg.norm(px[:, None] - px[spot][None], axis=2).min(axis=1)
        spot = d < r
        dropped["under a brighter spot"] = int(spot.sum())
    # a bend sharper than the smoothing can follow (the corner of two walls)
    bend = np.zeros(len(px), bool)
    for k in np.unique(piece):
        idx = np.flatnonzero(piece == k)
        d = np.linalg.norm(px[idx, None] - px[None, idx], axis=2)
        cos = np.abs(nrm[idx] @ nrm[idx].T)
        bend[idx] = np.any((d < 3.0 * sigma) & (cos < np.cos(np.radians(BEND_DEG))), axis=1)
    if bend.any():
        dropped["at a sharp bend"] = int(bend.sum())
    keep = ~spot & ~bend
    return StripeSamples(px[keep], nrm[keep], peak[keep], std[keep], piece[keep], dropped)


def find_red_stripes(
    bgr: np.ndarray,
    mask: np.ndarray,
    sigma: float = 2.0,
    curvature: float = 0.01,
    redness: float = 40.0,
    min_span: float = 25.0,
) -> StripeSamples:
    """A red laser line's centre-line samples in a real camera's image, where the laser saturates
    the sensor (its core white, its edges red) and lights surfaces of any colour.

    The ridge of the red channel (``R / 255``; Steger's ridge pixels, :func:`ridge_pixels`, at
    ``sigma`` px, the least curvature across ``curvature``, any level above 0.1), kept where red
    dominates within 4 px (``R - max(G, B)`` above ``redness`` grey levels, blurred at 1 px: a
    saturated core has a red rim) and in pieces at least ``min_span`` px across (a red lamp or a
    spot is shorter).  The centres are Steger's (no Gaussian fit: a saturated profile has a flat
    top).  ``mask``: (H, W) bool, where to look.
    """
    r, g, b = (bgr[:, :, k].astype(float) for k in (2, 1, 0))
    px, nrm, piece = ridge_pixels(r / 255.0, mask, sigma, threshold=0.1, curvature=curvature)
    dropped: dict = {}
    if not len(px):
        return StripeSamples(px, nrm, np.zeros(0), np.zeros(0), piece, dropped)
    red = cv2.dilate(cv2.GaussianBlur(r - np.maximum(g, b), (0, 0), 1.0), np.ones((9, 9), np.uint8))
    iu = np.clip(np.rint(px).astype(int), 0, [r.shape[1] - 1, r.shape[0] - 1])
    keep = red[iu[:, 1], iu[:, 0]] > redness
    if (~keep).any():
        dropped["not red"] = int((~keep).sum())
    short = np.zeros(len(px), bool)
    for k in np.unique(piece[keep]):
        sel = keep & (piece == k)
        q = px[sel]
        short[sel] = np.linalg.norm(q.max(axis=0) - q.min(axis=0)) < min_span
    if short.any():
        dropped["in a short piece"] = int(short.sum())
    keep &= ~short
    peak = r[iu[:, 1], iu[:, 0]] / 255.0
    return StripeSamples(px[keep], nrm[keep], peak[keep], np.full(int(keep.sum()), sigma), piece[keep], dropped)
