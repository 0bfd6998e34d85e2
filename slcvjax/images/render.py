"""The renderer: ray-traced images of a simulated scene, through the mirror and directly.

Every pixel is split into ``supersample x supersample`` cells, each traced at its
centre.  A catadioptric sample is undistorted, its ray meets the cone
(:func:`back_project`, closed form), and the reflected ray is followed to the first wall of
the box: the wall is white paper with black dots (the board points), a laser spot adds red
light with a Gaussian profile around the point where its beam meets the wall, and a ray that
comes back to the sensor's own body (a dark cylinder from the camera to just below the apex)
is dark: the camera's reflection at the image centre.  A sample that misses the mirror sees
the dim background, which draws the rim's edge.  A direct sample meets the chessboard's
plane: black and white squares with a white margin.  A cell that an edge crosses is traced
again at ``ceil(refine / supersample)`` squared samples, so that it holds its area's mean
radiance.  The optical blur acts on the cells (the lens blurs the light before a pixel
gathers it), then each pixel is the mean of its cells, and exposure, Gaussian sensor noise
and 8-bit quantisation are applied.  So a dot's image narrower than a pixel keeps its
sub-pixel place, and the centroids measured in noise-free images can be checked against
the exact projections to a hundredth of a pixel (``benchmarks/detection_accuracy.py``).

Radiances are linear in [0, 1]; the laser is pure red (650 nm light does not reach
the green and blue channels), so the detector finds dots in green and spots in
red against green.  Images are BGR ``uint8`` arrays, OpenCV's layout.
"""

from dataclasses import dataclass

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from ..geometry.camera import Camera, pixel_to_ray, undistort
from ..geometry.lasers import line_plane_intersection
from ..geometry.mirror import ConeMirror, back_project, body_clearance
from ..geometry.pose import Pose
from ..geometry.rig import project_board_points, project_rim
from ..geometry.sheets import sheet_gradient, sheet_value
from ..support.safe import safe_div, safe_norm, safe_normalize
from .pipe import beam_pipe_point
from .render_coded import drawing_albedo, pack_drawings

WALL = 0.72
DOT = 0.06
BACKGROUND = 0.12
BODY = 0.03
MIRROR_REFLECTANCE = 0.92
CHESS_BLACK = 0.05
CHESS_WHITE = 0.85
CHESS_SURROUND = 0.35


@dataclass(frozen=True)
class RenderOptions:
    """How images are rendered.

    Attributes:
        supersample: samples per pixel along each axis (anti-aliasing).
        refine: samples per pixel along each axis where an edge crosses it (at most
            ``supersample``: no refinement).
        noise: std of the Gaussian sensor noise in grey levels (0-255).
        blur: std of the Gaussian optical blur in pixels (0: none).
        exposure: gain on the radiance before quantisation (1: white paper at ~184 of 255).
        dot_radius_mm: radius of the printed dots on the walls.
        spot_sigma_mm: std of the laser spot's Gaussian profile on the wall.
        spot_power: peak red radiance of a spot on white paper (it saturates above 1).
        stripe_sigma_mm: std of a line or ring laser's stripe across it, on the surface (mm).
        stripe_power: peak red radiance of a stripe on white paper (below
            ``1 - MIRROR_REFLECTANCE * WALL`` / ``MIRROR_REFLECTANCE`` ~ 0.37 it does not saturate).
        body_radius_mm: radius of the sensor's body around the mirror axis (its dark reflection).
        body_gap_mm: the body ends this far before the apex, along the axis.
        seed: seed of the sensor noise.
    """

    supersample: int = 3
    refine: int = 12
    noise: float = 1.0
    blur: float = 0.6
    exposure: float = 1.0
    dot_radius_mm: float = 1.6
    spot_sigma_mm: float = 0.8
    spot_power: float = 0.9
    stripe_sigma_mm: float = 0.5
    stripe_power: float = 0.3
    body_radius_mm: float = 12.0
    body_gap_mm: float = 8.0
    seed: int = 0

    def __post_init__(self):
        checks = {
            "supersample": self.supersample >= 1,
            "refine": self.refine >= 0,
            "noise": self.noise >= 0,
            "blur": self.blur >= 0,
            "exposure": self.exposure > 0,
            "dot_radius_mm": self.dot_radius_mm > 0,
            "spot_sigma_mm": self.spot_sigma_mm > 0,
            "spot_power": self.spot_power >= 0,
            "stripe_sigma_mm": self.stripe_sigma_mm > 0,
            "stripe_power": self.stripe_power >= 0,
            "body_radius_mm": self.body_radius_mm >= 0,
        }
        for name, ok in checks.items():
            if not ok or not np.isfinite(getattr(self, name)):
                raise ValueError(f"render option {name} has an invalid value {getattr(self, name)!r}")


def _sample_grid(width: int, height: int, ss: int) -> jnp.ndarray:
    """Sub-pixel sample positions (OpenCV pixel centres at integers) of an image, (h, w, ss*ss, 2)."""
    off = (np.arange(ss) + 0.5) / ss - 0.5
    v = np.arange(height)[:, None, None] + np.repeat(off, ss)[None, None, :]
    u = np.arange(width)[None, :, None] + np.tile(off, ss)[None, None, :]
    u, v = np.broadcast_arrays(u, v)
    return jnp.asarray(np.stack([u, v], axis=-1), dtype=float)


def wall_hit(origin, direction, walls_R, walls_t):
    """Nearest wall ahead of a ray: (wall index, hit?, board-frame xy, camera-frame point)."""

    def one(R, t):
        x, ok = line_plane_intersection(origin, direction, Pose(R, t))
        return x, jnp.where(ok, jnp.dot(x - origin, direction), jnp.inf)

    xs, lam = jax.vmap(one)(walls_R, walls_t)
    w = jnp.argmin(lam)
    hit = jnp.isfinite(lam[w])
    x = xs[w]
    local = walls_R[w].T @ (x - walls_t[w])
    return w, hit, local[:2], x


def _body_hit(origin, direction, mirror: ConeMirror, radius, gap):
    """Does the ray meet the top face of the sensor's body (a disc across the axis, ``gap`` before the apex)?"""
    return body_clearance(origin, direction, mirror, radius, gap) < 0.0


def cata_ray(cam, mirror, uv, body_radius, body_gap):
    """The reflected ray of one sample, and whether it is seen (meets the mirror, misses the body)."""
    ray = back_project(cam, mirror, uv)
    body = _body_hit(ray.point, ray.direction, mirror, body_radius, body_gap)
    return ray.point, ray.direction, ray.valid, ray.valid & ~body


def _stripe_light(x, normal, apex, axis, half_angle, fan, on, sopts):
    """The red radiance (on white paper) that line and ring lasers' light adds at a surface point.

    Args:
        x: (3,) the surface point, camera frame, mm.
        normal: (3,) the surface's unit normal there.
        apex, axis, half_angle: (K, 3), (K, 3), (K,) the sheets (:class:`slcvjax.geometry.sheets.Sheets`).
        fan: (K, 2) rad: each sheet's fan as the camera-frame azimuth of its emission direction
            ``x - apex``, from ``fan[k, 0]`` over ``fan[k, 1]`` (more than 2 pi: all round).
        on: (K,) bool, the sheets drawn (the rest is padding).
        sopts: (2,) the stripe's std across it on the surface (mm) and its peak power.

    Each stripe is a Gaussian across the curve where its sheet meets the surface, of std
    ``sopts[0]`` in the surface's distance to that curve: to first order ``|G(x)| / |grad_t G|``
    with ``G`` the sheet's value (:func:`slcvjax.geometry.sheets.sheet_value`) and ``grad_t G`` its
    gradient projected on the surface's tangent plane.  Returns the sum over the sheets, ().
    """

    def one(p, a, th, f, k):
        g = sheet_value(x, p, a, th)
        grad = sheet_gradient(x, p, a, th)
        tangential = safe_norm(grad - jnp.dot(grad, normal) * normal)
        d = safe_div(jnp.abs(g), tangential, eps=1e-12)
        q = x - p
        az = jnp.arctan2(q[1], q[0])
        in_fan = jnp.mod(az - f[0], 2 * jnp.pi) <= f[1]
        light = jnp.exp(-0.5 * jnp.minimum(d / sopts[0], 1e3) ** 2)
        return jnp.where(k & in_fan & (tangential > 1e-9), light, 0.0)

    return sopts[1] * jnp.sum(jax.vmap(one)(apex, axis, half_angle, fan, on))


def _cata_shade(
    origin, direction, valid, seen, walls_R, walls_t, dots, spots, spot_wall, spot_on, opts, sheets=None, drawing=None
):
    w, hit, xy, x = wall_hit(origin, direction, walls_R, walls_t)
    if drawing is None:  # the walls' dots
        d2 = jnp.min(jnp.sum((dots[w] - xy) ** 2, axis=1))
        albedo = jnp.where(d2 < opts[0] ** 2, DOT, WALL)
    else:  # the walls' printed targets (:mod:`slcvjax.images.render_coded`)
        albedo = drawing_albedo(w, xy, drawing)
    s2 = jnp.min(jnp.where(spot_on & (spot_wall == w), jnp.sum((spots - x) ** 2, axis=1), jnp.inf))
    laser = jnp.exp(-0.5 * jnp.minimum(s2, 1e6) / opts[1] ** 2)  # spots lie far apart: the nearest one
    seen = seen & hit
    grey = MIRROR_REFLECTANCE * albedo
    red = grey + MIRROR_REFLECTANCE * albedo / WALL * opts[2] * laser
    if sheets is not None:  # only with line or ring lasers: a rig of point lasers renders as before
        red = red + MIRROR_REFLECTANCE * albedo / WALL * _stripe_light(x, walls_R[w][:, 2], *sheets)
    mirror_px = jnp.where(valid, BODY, BACKGROUND)
    g = jnp.where(seen, grey, mirror_px)
    r = jnp.where(seen, red, mirror_px)
    return jnp.stack([g, g, r])  # BGR


def _pipe_shade(origin, direction, valid, seen, centre, axis, radius, spots, spot_on, opts, sheets=None):
    """A sample inside a pipe: its inner wall is plain paper-white, lit by the laser spots (and
    the stripes of ``sheets``, :func:`_stripe_light`'s arguments, where given)."""
    x, hit = beam_pipe_point(origin, direction, centre, axis, radius)
    s2 = jnp.min(jnp.where(spot_on, jnp.sum((spots - x) ** 2, axis=1), jnp.inf))
    laser = jnp.exp(-0.5 * jnp.minimum(s2, 1e6) / opts[1] ** 2)
    seen = seen & hit
    grey = MIRROR_REFLECTANCE * WALL
    red = grey + MIRROR_REFLECTANCE * opts[2] * laser
    if sheets is not None:  # only with line or ring lasers: a rig of point lasers renders as before
        radial = (x - centre) - jnp.dot(x - centre, axis) * axis
        red = red + MIRROR_REFLECTANCE * _stripe_light(x, safe_normalize(radial), *sheets)
    mirror_px = jnp.where(valid, BODY, BACKGROUND)
    g = jnp.where(seen, grey, mirror_px)
    r = jnp.where(seen, red, mirror_px)
    return jnp.stack([g, g, r])  # BGR


def chess_sample(d, ok, R, t, cols, rows, square):
    x, ahead = line_plane_intersection(jnp.zeros(3), d, Pose(R, t))
    xy = (R.T @ (x - t))[:2]
    i = jnp.floor(xy[0] / square)
    j = jnp.floor(xy[1] / square)
    inside = (xy[0] >= -square) & (xy[0] < cols * square) & (xy[1] >= -square) & (xy[1] < rows * square)
    margin = (xy[0] >= -2 * square) & (xy[0] < (cols + 1) * square) & (xy[1] >= -2 * square)
    margin = margin & (xy[1] < (rows + 1) * square)
    black = jnp.mod(i + j, 2) == 0
    val = jnp.where(inside, jnp.where(black, CHESS_BLACK, CHESS_WHITE), jnp.where(margin, CHESS_WHITE, CHESS_SURROUND))
    val = jnp.where(ok & ahead, val, CHESS_SURROUND)
    return jnp.stack([val, val, val])


@jax.jit
def _cata_rays(cam, mirror, samples, body):
    f = jax.vmap(lambda uv: cata_ray(cam, mirror, uv, body[0], body[1]))
    return jax.lax.map(f, samples)


@jax.jit
def _cata_band(rays, walls_R, walls_t, dots, spots, spot_wall, spot_on, opts, sheets=None, drawing=None):
    f = lambda o, d, v, s: _cata_shade(
        o, d, v, s, walls_R, walls_t, dots, spots, spot_wall, spot_on, opts, sheets, drawing
    )  # noqa: E731
    return jax.lax.map(lambda r: jax.vmap(f)(*r), rays)


@jax.jit
def _pipe_band(rays, centre, axis, radius, spots, spot_on, opts, sheets=None):
    f = lambda o, d, v, s: _pipe_shade(o, d, v, s, centre, axis, radius, spots, spot_on, opts, sheets)  # noqa: E731
    return jax.lax.map(lambda r: jax.vmap(f)(*r), rays)


@jax.jit
def _camera_rays(cam, samples):
    return jax.lax.map(jax.vmap(lambda uv: pixel_to_ray(cam, uv)), samples)


@jax.jit
def _chess_band(rays, R, t, grid):
    f = lambda d, ok: chess_sample(d, ok, R, t, grid[0], grid[1], grid[2])  # noqa: E731
    return jax.lax.map(lambda r: jax.vmap(f)(*r), rays)


@jax.jit
def _fine_rays(cam, mirror, body, centres, offsets):
    """The reflected ray of each sample of each cell: (m, k) of :func:`cata_ray`'s four fields."""
    f = jax.vmap(jax.vmap(lambda uv: cata_ray(cam, mirror, uv, body[0], body[1])))
    return f(centres[:, None, :] + offsets[None])


@jax.jit
def _cata_shade_rays(rays, walls_R, walls_t, dots, spots, spot_wall, spot_on, opts, sheets=None, drawing=None):
    """Each cell's mean radiance in the box from its samples' reflected rays (:func:`_fine_rays`)."""
    f = lambda o, d, v, s: _cata_shade(
        o, d, v, s, walls_R, walls_t, dots, spots, spot_wall, spot_on, opts, sheets, drawing
    )  # noqa: E731
    return jax.vmap(jax.vmap(f))(*rays).mean(axis=1)


@jax.jit
def _pipe_shade_rays(rays, centre, axis, radius, spots, spot_on, opts, sheets=None):
    """Each cell's mean radiance inside a pipe from its samples' reflected rays (:func:`_fine_rays`)."""
    f = lambda o, d, v, s: _pipe_shade(o, d, v, s, centre, axis, radius, spots, spot_on, opts, sheets)  # noqa: E731
    return jax.vmap(jax.vmap(f))(*rays).mean(axis=1)


@jax.jit
def _chess_fine(cam, centres, offsets, R, t, grid):
    """Each cell's mean radiance of a direct chessboard view from its samples' rays.  The
    undistortion is linearised at the cell's centre (one Newton solve and its 2x2 derivative per
    cell instead of one solve per sample): over a cell (its samples within 1/6 px of its centre
    along each axis at 3 samples per pixel) the second-order term is below 1e-4 px at the
    preset's distortion (k1 = -0.28), in the image's corners too."""

    def cell(c):
        xy, ok = undistort(cam, c)
        jac = jax.jacfwd(lambda uv: undistort(cam, uv)[0])(c)

        def f(off):
            p = xy + jac @ off
            d = jnp.stack([p[0], p[1], jnp.ones_like(p[0])])
            return chess_sample(d / jnp.linalg.norm(d), ok, R, t, grid[0], grid[1], grid[2])

        return jax.vmap(f)(offsets).mean(axis=0)

    return jax.vmap(cell)(centres)


CHUNK = 32768
EDGE_SPREAD = 0.01  # a cell whose radiance differs from a neighbour's by more than this lies at an edge
REFINE_CELLS = 2048  # cells per call of the refinement (one compiled shape)


def _chunked_samples(width: int, height: int, ss: int) -> tuple[jnp.ndarray, int]:
    """Every sample of an image, padded and split into chunks: (n_chunks, CHUNK, 2), and the true count."""
    samples = _sample_grid(width, height, ss).reshape(-1, 2)
    n = samples.shape[0]
    pad = (-n) % CHUNK
    samples = jnp.concatenate([samples, jnp.zeros((pad, 2))]) if pad else samples
    return samples.reshape(-1, CHUNK, 2), n


def _finish(cells: np.ndarray, opts: RenderOptions, seed: int) -> np.ndarray:
    """The image of a linear radiance image at ``opts.supersample`` cells per pixel along each axis
    (H ss, W ss, 3): optical blur (on the cells: the lens blurs the light before a pixel gathers
    it, so a feature narrower than a pixel keeps its sub-pixel place), each pixel the mean of its
    cells, exposure, sensor noise and quantisation (H, W, 3)."""
    ss = opts.supersample
    img = cells * opts.exposure * 255.0
    if opts.blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), opts.blur * ss)
    img = cv2.resize(img, (img.shape[1] // ss, img.shape[0] // ss), interpolation=cv2.INTER_AREA)  # block means
    if opts.noise > 0:
        img = img + np.random.default_rng(seed).normal(0.0, opts.noise, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


class Renderer:
    """Renders the images of one rig: the rays of every sample are traced once, then each view is shaded.

    The camera's rays and their reflections in the mirror do not depend on where
    the sensor is, so they are computed at construction (about a second for a
    640x480 camera at 3x3 samples); a view then costs its wall intersections and
    shading only.
    """

    def __init__(self, camera: Camera, mirror: ConeMirror | None, opts: RenderOptions = RenderOptions()):
        self.camera, self.mirror, self.opts = camera, mirror, opts
        ss = opts.supersample
        self._samples, self._n = _chunked_samples(camera.width, camera.height, ss)
        self._rays = None
        self._body = jnp.asarray([opts.body_radius_mm, opts.body_gap_mm], dtype=float)
        self._mirror_edges = None
        if mirror is not None:
            self._rays = _cata_rays(camera, mirror, self._samples, self._body)
            self._mirror_edges = self._trace_mirror_edges()
            self._seen, self._seen_rays, self._unseen = self._compact_seen()
        self._chess_rays = None

    def _compact_seen(self):
        """The samples whose reflected ray leaves the mirror into the scene (a third of a
        640x480 image through the preset's cone), their rays packed in chunks, and every sample's
        radiance where it sees the mirror only (the body's reflection, or the dim background
        around the rim; :func:`_cata_shade` gives these whatever the scene): a view shades the
        packed rays only."""
        _, _, valid, seen = self._rays
        seen = np.asarray(seen).reshape(-1)
        idx = np.flatnonzero(seen)
        rows = np.concatenate([idx, np.full((-len(idx)) % CHUNK, idx[0] if len(idx) else 0)])

        def pack(a):
            a = np.asarray(a)
            return jnp.asarray(a.reshape(-1, *a.shape[2:])[rows].reshape(-1, CHUNK, *a.shape[2:]))

        packed = tuple(pack(a) for a in self._rays)
        unseen = np.where(np.asarray(valid).reshape(-1), BODY, BACKGROUND)
        return idx, packed, np.repeat(unseen[:, None], 3, axis=1)

    def _unpack(self, shaded) -> np.ndarray:
        """Per-sample radiance in the chunks' layout of every sample from that of the packed
        seen samples (:meth:`_compact_seen`)."""
        out = self._unseen.copy()
        out[self._seen] = np.asarray(shaded).reshape(-1, 3)[: len(self._seen)]
        return out.reshape(-1, CHUNK, 3)

    def _to_cells(self, samples) -> np.ndarray:
        """Per-sample values (chunked, as the samples) as an image of cells (H ss, W ss, ...)."""
        h, w, ss = self.camera.height, self.camera.width, self.opts.supersample
        flat = np.asarray(samples).reshape(-1, *np.shape(samples)[2:])[: self._n]
        cells = flat.reshape(h, w, ss, ss, *flat.shape[1:])
        return cells.swapaxes(1, 2).reshape(h * ss, w * ss, *flat.shape[1:])

    def _offsets(self) -> jnp.ndarray | None:
        """The samples of a refined cell about its centre (k, 2), or None where nothing is refined."""
        ss = self.opts.supersample
        sub = -(-self.opts.refine // ss)
        return None if sub <= 1 else jnp.asarray(_sample_grid(1, 1, sub).reshape(-1, 2) / ss)

    def _trace_mirror_edges(self):
        """The cells at the mirror's own edges (its rim, the body's reflection), which do not move
        from view to view, with their samples' reflected rays traced once: ``(ys, xs, ray chunks)``."""
        offsets = self._offsets()
        if offsets is None:
            return None
        _, _, valid, seen = self._rays
        kind = self._to_cells(valid.astype(np.uint8) + seen.astype(np.uint8))
        square = np.ones((3, 3), np.uint8)
        edge = cv2.dilate(kind, square) != cv2.erode(kind, square)
        ys, xs = np.nonzero(cv2.dilate(edge.astype(np.uint8), square))
        centres = self._cell_centres(ys, xs)
        chunks = [_fine_rays(self.camera, self.mirror, self._body, c, offsets) for c in centres]
        return ys, xs, chunks

    def _cell_centres(self, ys, xs) -> list[jnp.ndarray]:
        """The centres (px) of cells ``(ys, xs)`` in chunks of ``REFINE_CELLS`` (the last padded)."""
        ss, n = self.opts.supersample, len(ys)
        centres = np.zeros((n + (-n) % REFINE_CELLS, 2))
        centres[:n, 0], centres[:n, 1] = (xs + 0.5) / ss - 0.5, (ys + 0.5) / ss - 0.5
        return [jnp.asarray(centres[i : i + REFINE_CELLS]) for i in range(0, n, REFINE_CELLS)]

    def _traced(self, shade):
        """``fine(centres, offsets)`` for :meth:`_cells`: the samples' reflected rays traced, then
        ``shade(rays) -> (m, 3)``."""
        return lambda centres, offsets: shade(_fine_rays(self.camera, self.mirror, self._body, centres, offsets))

    def _cells(self, out, fine, cached=None) -> np.ndarray:
        """The image at its samples' resolution (H ss, W ss, 3): each sample stands for the mean
        radiance over its cell, ``1/ss`` px square. A cell an edge crosses (it or a neighbour differs
        from a neighbour by more than ``EDGE_SPREAD``: an edge can pass between the samples) is
        averaged over ``ceil(refine / ss)`` squared samples by
        ``fine(centres (m, 2), offsets (k, 2)) -> (m, 3)``; the cells at the mirror's own edges by
        ``cached(ray chunk) -> (m, 3)`` from their rays traced once (where given)."""
        cells = self._to_cells(out)
        offsets = self._offsets()
        if offsets is None:
            return cells
        square = np.ones((3, 3), np.uint8)
        c32 = cells.astype(np.float32)
        d = cv2.dilate(c32, square) - cv2.erode(c32, square)
        spread = np.maximum(np.maximum(d[..., 0], d[..., 1]), d[..., 2])
        edge = cv2.dilate((spread > EDGE_SPREAD).astype(np.uint8), square).astype(bool)
        if cached is not None and self._mirror_edges is not None:
            ys, xs, chunks = self._mirror_edges
            edge[ys, xs] = False
            cells[ys, xs] = np.concatenate([np.asarray(cached(c)) for c in chunks])[: len(ys)]
        ys, xs = np.nonzero(edge)
        means = [np.asarray(fine(c, offsets)) for c in self._cell_centres(ys, xs)]
        if means:
            cells[ys, xs] = np.concatenate(means)[: len(ys)]
        return cells

    def catadioptric(
        self,
        walls: dict[str, Pose],
        boards: dict[str, np.ndarray],
        spots: list[tuple[str, np.ndarray]],
        seed: int = 0,
        sheets=None,
        fans: dict | None = None,
        drawings: dict | None = None,
    ) -> np.ndarray:
        """One catadioptric image (BGR uint8, ``height x width``).

        Args:
            walls: ``T_cam_board`` of every wall (each an infinite plane ``z = 0`` of its board frame).
            boards: each wall's dot centres in its board frame (M, 3), mm.
            spots: each visible laser spot's wall and 3D point (camera frame, mm).
            seed: seed of this image's sensor noise.
            sheets: line and ring lasers (:class:`slcvjax.geometry.sheets.Sheets`, camera frame)
                whose light draws stripes on the walls, or None (none: the image is the same as
                without the argument, bit for bit).
            fans: per sheet (its index among ``sheets``) the fan's camera-frame azimuth limits
                (deg, from, to) of its emission directions; a sheet not listed shines all round.
            drawings: each wall's print (:class:`slcvjax.images.printable.Drawing`, board frame;
                a wall not listed is plain paper) shaded in place of ``boards``' dots
                (:mod:`slcvjax.images.render_coded`), or None: the dots.
        """
        if self._rays is None:
            raise ValueError("this renderer has no mirror; it renders direct views only")
        names = list(walls)
        if not names:
            raise ValueError("a catadioptric image needs at least one wall")
        walls_R = jnp.stack([walls[b].R for b in names])
        walls_t = jnp.stack([walls[b].t for b in names])
        m = max(len(boards[b]) for b in names)
        dots = np.full((len(names), max(m, 1), 2), 1e9)
        for i, b in enumerate(names):
            dots[i, : len(boards[b])] = np.asarray(boards[b])[:, :2]
        n_spots = max(len(spots), 1)
        spot_xyz = np.full((n_spots, 3), 1e9)
        spot_wall = np.full(n_spots, -1)
        for i, (b, x) in enumerate(spots):
            spot_xyz[i], spot_wall[i] = x, names.index(b)
        o = self.opts
        opts = jnp.asarray([o.dot_radius_mm, o.spot_sigma_mm, o.spot_power], dtype=float)
        scene = (walls_R, walls_t, jnp.asarray(dots), jnp.asarray(spot_xyz), jnp.asarray(spot_wall),
                 jnp.asarray(spot_wall >= 0), opts)  # fmt: skip
        if sheets is not None and sheets.n:
            scene = (*scene, self._sheet_args(sheets, fans))
        kw = {} if drawings is None else {"drawing": pack_drawings([drawings.get(b) for b in names])}
        out = self._unpack(_cata_band(self._seen_rays, *scene, **kw))
        shade = lambda rays: _cata_shade_rays(rays, *scene, **kw)  # noqa: E731
        return _finish(self._cells(out, self._traced(shade), shade), o, seed)

    def _sheet_args(self, sheets, fans: dict | None) -> tuple:
        """:func:`_stripe_light`'s sheet arguments (after ``x, normal``) for ``sheets`` and their
        ``fans`` (by sheet index, deg), padded to a multiple of 4 sheets (one compilation for a
        few counts)."""
        n = sheets.n
        k = n + (-n) % 4
        apex, axis, th = np.zeros((k, 3)), np.tile([0.0, 0.0, 1.0], (k, 1)), np.full(k, np.pi / 2)
        apex[:n], axis[:n], th[:n] = np.asarray(sheets.apex), np.asarray(sheets.axis), np.asarray(sheets.half_angle)
        fan = np.tile([0.0, 4 * np.pi], (k, 1))
        for j, (lo, hi) in (fans or {}).items():
            fan[j] = np.radians(lo), np.radians((hi - lo) % 360.0)
        sopts = jnp.asarray([self.opts.stripe_sigma_mm, self.opts.stripe_power], dtype=float)
        return (jnp.asarray(apex), jnp.asarray(axis), jnp.asarray(th), jnp.asarray(fan), jnp.arange(k) < n, sopts)

    def pipe(
        self, centre, axis, radius: float, spots: np.ndarray, seed: int = 0, sheets=None, fans: dict | None = None
    ) -> np.ndarray:
        """One catadioptric image from inside a straight pipe (BGR uint8): the pipe's axis through
        ``centre`` along the unit ``axis`` (camera frame, mm), its inner ``radius`` (mm), and the
        laser spots' 3D points on its wall (S, 3).  ``sheets`` and ``fans``: line and ring lasers'
        light drawn as stripes on the wall, as in :meth:`catadioptric`."""
        if self._rays is None:
            raise ValueError("this renderer has no mirror; it renders direct views only")
        spots = np.asarray(spots, float).reshape(-1, 3)
        spot_xyz = np.full((max(len(spots), 1), 3), 1e9)
        spot_xyz[: len(spots)] = spots
        o = self.opts
        opts = jnp.asarray([o.dot_radius_mm, o.spot_sigma_mm, o.spot_power], dtype=float)
        scene = (jnp.asarray(centre, float), jnp.asarray(axis, float), jnp.asarray(float(radius)),
                 jnp.asarray(spot_xyz), jnp.arange(len(spot_xyz)) < len(spots), opts)  # fmt: skip
        if sheets is not None and sheets.n:
            scene = (*scene, self._sheet_args(sheets, fans))
        out = self._unpack(_pipe_band(self._seen_rays, *scene))
        shade = lambda rays: _pipe_shade_rays(rays, *scene)  # noqa: E731
        return _finish(self._cells(out, self._traced(shade), shade), o, seed)

    def chessboard(self, T_cam_board: Pose, cols: int, rows: int, square: float, seed: int = 0) -> np.ndarray:
        """One direct chessboard image (BGR uint8): ``cols x rows`` inner corners at ``(i, j) * square``, mm."""
        if self.camera.telecentric:
            raise ValueError("chessboard: direct views are rendered for a perspective camera only")
        if self._chess_rays is None:
            self._chess_rays = _camera_rays(self.camera, self._samples)
        grid = jnp.asarray([cols, rows, square], dtype=float)
        out = _chess_band(self._chess_rays, T_cam_board.R, T_cam_board.t, grid)
        fine = lambda px, off: _chess_fine(self.camera, px, off, T_cam_board.R, T_cam_board.t, grid)  # noqa: E731
        return _finish(self._cells(out, fine), self.opts, seed)


def grid_shape(points: np.ndarray) -> tuple[int, int]:
    """(cols, rows) of a regular grid of board points ordered x fastest."""
    cols = len(np.unique(np.round(points[:, 0], 6)))
    rows = len(np.unique(np.round(points[:, 1], 6)))
    if cols * rows != len(points):
        raise ValueError(f"board points ({len(points)}) are not a regular grid ({cols} x {rows})")
    return cols, rows


def scene_setup(scene, image_names: list[str], chess_names: list[str]):
    """The ``slcv-setup/1`` content of a simulated scene: what its user would know before detection.

    Each wall target's nominal azimuth and axis directions in the image come from
    the exact projections of view 0 (a user reads them off the first image, or from
    the box's drawing); the lasers are numbered by the detector's convention
    (by increasing azimuth from the one nearest 0 deg), which the presets follow.
    """
    from .detect import BoardLayout, Setup, azimuth_deg, circular_mean_deg

    rig = scene.rig
    ruv, rok = project_rim(rig, jnp.linspace(0, 2 * np.pi, 64, endpoint=False))
    centre = np.asarray(ruv)[np.asarray(rok)].mean(axis=0)
    boards = {}
    for name, pts in scene.boards.items():
        cols, rows = grid_shape(pts)
        layout = BoardLayout(np.asarray(pts, float), cols, rows, target=scene.board_types.get(name))
        if name != scene.chess_board and len(scene.box_poses):
            uv, ok = project_board_points(rig, scene.box_poses[0][name], jnp.asarray(pts))
            uv, ok = np.asarray(uv), np.asarray(ok)
            if ok.any():
                az = azimuth_deg(uv[ok], centre)
                layout.azimuth_deg = circular_mean_deg(az) % 360
            grid_uv = uv.reshape(rows, cols, 2)
            if cols > 1:
                d = (azimuth_deg(grid_uv[:, 1], centre) - azimuth_deg(grid_uv[:, 0], centre) + 180) % 360 - 180
                layout.x_dir = 1 if np.nanmedian(d) > 0 else -1
            if rows > 1:
                r = np.linalg.norm(grid_uv - centre, axis=-1)
                layout.y_dir = 1 if np.nanmedian(r[1] - r[0]) > 0 else -1
        boards[name] = layout
    setup = Setup(
        image_size=(rig.camera.width, rig.camera.height),
        mirror_radius=float(rig.mirror.radius),
        mirror_height=float(rig.mirror.height),
        n_lasers=rig.lasers.n,
        boards=boards,
        views=image_names,
        chessboard_views=[(c, scene.chess_board) for c in chess_names],
        extra={"simulation": dict(scene.info)},
    )
    if rig.has_sheets:
        setup.n_lasers = rig.n_elements
        setup.laser_kinds = list(rig.element_kinds)
        setup.laser_azimuth_deg = _laser_azimuths(scene, centre)
    return setup


def _laser_azimuths(scene, centre: np.ndarray) -> list[float | None]:
    """Each laser's image azimuth (deg) about ``centre`` as a user reads it off the first images
    where it shows: a point laser's spot, a line laser's stripe's middle (the circular mean of its
    exact pixels); None for a ring laser (and for a laser never seen)."""
    from ..observations.simulate import visible_spots, visible_stripes
    from .detect import azimuth_deg, circular_mean_deg

    rig = scene.rig
    out: list[float | None] = [None] * rig.n_elements
    point_of = rig.point_elements
    for v in range(len(scene.box_poses)):
        for laser, _, _, uv in visible_spots(scene, v):
            e = int(point_of[laser])
            if out[e] is None:
                out[e] = float(azimuth_deg(uv, centre)[0])
        per_line: dict[int, list] = {}
        for e, _, _, uv in visible_stripes(scene, v):
            if rig.element_kinds[e] == "plane" and out[e] is None:
                per_line.setdefault(e, []).append(uv)
        for e, uvs in per_line.items():
            out[e] = circular_mean_deg(azimuth_deg(np.concatenate(uvs), centre)) % 360.0
        if all(a is not None for a, k in zip(out, rig.element_kinds, strict=True) if k != "cone"):
            break
    return out


def scene_sheets(scene) -> tuple:
    """``(sheets, fans)`` for :meth:`Renderer.catadioptric` and :meth:`Renderer.pipe` of a scene's
    rig: its line and ring lasers, and their fans by sheet index (deg; the scene's ``fans`` are
    by element index), or ``(None, None)`` for a rig of point lasers."""
    rig = scene.rig
    if not rig.has_sheets:
        return None, None
    local = rig.local_index
    fans = {int(local[e]): tuple(f) for e, f in getattr(scene, "fans", {}).items()}
    return rig.sheets, fans


def _coded_drawings(scene) -> dict | None:
    """Each wall's print where the scene has coded walls (``scene.board_types``), dot walls drawn as
    discs of their points; None for a scene of dot walls (rendered from the dots, as before)."""
    types = getattr(scene, "board_types", {})
    if not types:
        return None
    from .printable import board_drawing

    walls = [b for b in scene.boards if b != scene.chess_board]
    return {b: board_drawing(types.get(b), scene.boards[b]) for b in walls}


def _cone_only(mirror) -> None:
    if not isinstance(mirror, ConeMirror):
        raise ValueError(f"rendering supports the cone mirror only, not a {type(mirror).__name__}")


def render_scene(scene, out_dir, opts: RenderOptions = RenderOptions(), progress: bool = False) -> list[str]:
    """Render every view of a simulated scene into ``out_dir`` with its ``setup.json``; returns the files.

    One PNG per catadioptric view (``view00.png``, ...) and per direct chessboard
    view (``chess00.png``, ...).  Image ``k`` of a kind gets noise seed ``opts.seed + k``
    (chessboard images ``+ 1000``).  The cone mirror only (its setup's ``mirror_shape``).
    """
    from pathlib import Path

    _cone_only(scene.rig.mirror)

    from ..observations.formats import write_json_atomic
    from ..observations.simulate import visible_spots
    from .detect import setup_to_json

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rig = scene.rig
    renderer = Renderer(rig.camera, rig.mirror, opts)
    walls = [b for b in scene.boards if b != scene.chess_board]
    cols, rows = grid_shape(scene.boards[scene.chess_board])
    square = float(scene.boards[scene.chess_board][1, 0] - scene.boards[scene.chess_board][0, 0])
    names, chess_names = [], []
    sheet_light = scene_sheets(scene)
    drawings = _coded_drawings(scene)
    jobs = [("view", i) for i in range(len(scene.box_poses))] + [("chess", j) for j in range(len(scene.chess_poses))]
    if progress:
        from tqdm import tqdm

        jobs = tqdm(jobs, desc="render", unit="image", leave=False)
    for kind, i in jobs:
        if kind == "view":
            spots = [(w, x) for _, w, x, _ in visible_spots(scene, i)]
            walls_i = {b: scene.box_poses[i][b] for b in walls}
            img = renderer.catadioptric(walls_i, scene.boards, spots, opts.seed + i, *sheet_light, drawings=drawings)
            name = f"view{i:02d}.png"
            names.append(name)
        else:
            img = renderer.chessboard(scene.chess_poses[i], cols, rows, square, opts.seed + 1000 + i)
            name = f"chess{i:02d}.png"
            chess_names.append(name)
        if not cv2.imwrite(str(out / name), img):
            raise OSError(f"{out / name}: could not write the image")
    setup = scene_setup(scene, names, chess_names)
    # what a user knows of the printed targets and the lasers
    for b in setup.boards.values():
        if b.azimuth_deg is not None and b.target is None:
            b.dot_radius_mm = opts.dot_radius_mm
    setup.spot_sigma_mm = opts.spot_sigma_mm
    if rig.has_sheets:
        setup.stripe_sigma_mm = opts.stripe_sigma_mm
    setup.rigid_boards = [k for k, b in setup.boards.items() if b.azimuth_deg is not None]  # the box's walls
    write_json_atomic(out / "setup.json", setup_to_json(setup))
    return names + chess_names


def render_pipe(scene, out_dir, opts: RenderOptions = RenderOptions(), progress: bool = False) -> list[str]:
    """Render every pose of a pipe scene (:class:`slcvjax.images.pipe.PipeScene`) into ``out_dir``: one PNG per
    pose (``pipe00.png``, ...), image ``k`` with noise seed ``opts.seed + k``; returns the names.

    The pipe's inner wall is the only surface; every beam lights its spot where it meets the
    wall, and every line or ring laser draws its stripe (a line laser's fan from the scene's
    ``fans``, by element index, where it has them; all round otherwise).  No setup is written:
    the spots are labelled by a calibration's laser lines when measured
    (``slcvjax measure CAL IMAGE_DIR``).
    """
    _cone_only(scene.rig.mirror)
    from pathlib import Path

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rig = scene.rig
    renderer = Renderer(rig.camera, rig.mirror, opts)
    hit = jax.jit(jax.vmap(beam_pipe_point, in_axes=(0, 0, None, None, None)))
    sheet_light = scene_sheets(scene)
    poses = range(len(scene.centers))
    if progress:
        from tqdm import tqdm

        poses = tqdm(poses, desc="render pipe", unit="image", leave=False)
    names = []
    for i in poses:
        x, ok = hit(rig.lasers.points, rig.lasers.directions, scene.centers[i], scene.axes[i], scene.diameter / 2)
        spots = np.asarray(x)[np.asarray(ok)]
        img = renderer.pipe(scene.centers[i], scene.axes[i], scene.diameter / 2, spots, opts.seed + i, *sheet_light)
        name = f"pipe{i:02d}.png"
        if not cv2.imwrite(str(out / name), img):
            raise OSError(f"{out / name}: could not write the image")
        names.append(name)
    return names
