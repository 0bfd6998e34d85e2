"""An independent ray tracer of held-out rigs, for testing the detector on images it was not tuned to.

Written apart from :mod:`slcvjax.images.render` (it does not call it or share its shading):
plain NumPy, with OpenCV for the lens distortion only.  Every pixel is split into
``supersample x supersample`` samples; each is undistorted to a camera ray
(OpenCV's ``undistortPoints`` polished by Newton), meets the cone as a quadric (the smallest positive root with
``0 <= q.a <= h``), is reflected about the quadric's gradient and followed to the first plane of
a closed box around the sensor (four walls, a floor and a ceiling; the walls' corners may be
left open, a gap through which the outside's darkness is seen).  Shading: light walls (albedo
``wall``, optionally shaded along their height), dark discs where a wall point lies within the
dots' radius of a grid point, red Gaussian laser spots where each beam first meets the box
(peak ``spot_peak`` times white, saturating allowed), a dark surround outside the mirror.  The
samples are averaged, optionally blurred, exposed to 8 bits with Gaussian noise in grey levels.
Direct views trace the camera's rays to a chessboard plane.

The truth (where each dot's and spot's centre lands, the rim) comes from the library's public
geometry (:func:`slcvjax.project_board_points`, :func:`slcvjax.project_through_mirror`,
:func:`slcvjax.geometry.rig.distance_to_rim`), checked against this tracer's own rays.
The ``setup.json`` is written in the format ``slcvjax simulate --render`` writes: nominal
azimuths and grid directions from view 0's exact projections, lasers numbered by increasing
image azimuth from the one nearest 0 deg, the walls a rigid group.
"""

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np


@dataclass(frozen=True)
class HeldOutRig:
    """A held-out rig and its scene. Lengths in mm, angles in degrees, levels in [0, 1] of white."""

    width: int = 800
    height: int = 600
    focal_px: float = 600.0
    dist: tuple = (-0.22, 0.06, 0.0008, -0.0006, -0.006)
    cone_radius: float = 22.0
    cone_height: float = 13.0
    rim_z: float = 60.0  # the rim's distance in front of the lens
    mirror_tilt_deg: float = 1.0
    mirror_offset_mm: tuple = (0.4, -0.3)
    n_lasers: int = 8
    laser_ring_mm: float = 30.0
    laser_z_mm: float = 30.0
    laser_elev_deg: float = 2.0  # each beam's elevation drawn in [-this, +this]
    cols: int = 4
    rows: int = 3
    pitch_mm: float = 18.0
    dot_radius_mm: float = 1.25
    grid_z_mm: float = 27.0  # the grids' centre along the box's axis (box frame = sensor frame of view 0)
    wall: float = 0.78
    dot: float = 0.07
    shading: float = 0.0  # wall albedo varies by +-shading (relative) along the wall's height
    surround: float = 0.05  # outside the mirror, and outside the box through open corners
    mirror_reflectance: float = 0.92
    spot_sigma_mm: float = 0.8
    spot_peak: float = 3.0  # red radiance at a spot's centre on white (above 1: saturated)
    box_half_mm: float = 85.0
    floor_mm: float = -120.0
    ceiling_mm: float = 160.0
    open_corner_mm: float = 0.0  # each wall stops this far before the corner
    motion_mm: tuple = (35.0, 35.0, 5.0)
    rotation_deg: tuple = (3.0, 3.0, 15.0)
    n_views: int = 6
    n_chess: int = 3
    chess_inner: tuple = (9, 6)
    chess_square_mm: float = 20.0
    noise: float = 1.0  # grey levels
    blur_px: float = 0.5
    supersample: int = 3
    scale: float = 1.0  # image size and focal length scaled (a reduced-resolution copy of the rig)
    seed: int = 0
    extra: dict = field(default_factory=dict)


# ------------------------------------------------------------------ geometry (NumPy)


def _rot(rvec) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(rvec, float).reshape(3, 1))[0]


@dataclass
class _Geometry:
    K: np.ndarray
    dist: np.ndarray
    size: tuple[int, int]
    apex: np.ndarray
    axis: np.ndarray
    radius: float
    height: float
    laser_p: np.ndarray  # (L, 3) camera frame
    laser_d: np.ndarray
    T_box_cam: list[tuple[np.ndarray, np.ndarray]]  # per view (R, t)
    walls: dict[str, tuple[np.ndarray, np.ndarray]]  # T_box_wall (R, t)
    points: np.ndarray  # (M, 3) board points of a wall grid
    chess: np.ndarray
    T_cam_chess: list[tuple[np.ndarray, np.ndarray]]
    cache: tuple | None = None


def _geometry(rig: HeldOutRig) -> _Geometry:
    rng = np.random.default_rng(1000 + rig.seed)
    s = rig.scale
    w, h = round(rig.width * s), round(rig.height * s)
    f = rig.focal_px * s
    K = np.array([[f, 0, (w - 1) / 2 + 3.1 * s], [0, f * 1.001, (h - 1) / 2 - 2.4 * s], [0, 0, 1.0]])
    tilt = math.radians(rig.mirror_tilt_deg)
    axis = np.array([math.sin(tilt) * 0.6, -math.sin(tilt) * 0.8, math.cos(tilt)])
    rim_c = np.array([*rig.mirror_offset_mm, rig.rim_z])
    apex = rim_c - rig.cone_height * axis
    # lasers on a ring round the axis, beams radiating outwards nearly across it
    az = np.radians(10.0 + 360.0 / rig.n_lasers * np.arange(rig.n_lasers) + rng.uniform(-4, 4, rig.n_lasers))
    p = np.stack([rig.laser_ring_mm * np.cos(az), rig.laser_ring_mm * np.sin(az), np.full_like(az, rig.laser_z_mm)], 1)
    aim = az + np.radians(rng.uniform(-2, 2, rig.n_lasers))
    el = np.radians(rng.uniform(-rig.laser_elev_deg, rig.laser_elev_deg, rig.n_lasers))
    d = np.stack([np.cos(el) * np.cos(aim), np.cos(el) * np.sin(aim), np.sin(el)], 1)
    # numbered by increasing azimuth from the one nearest 0 deg (the detector's convention)
    a = np.degrees(np.arctan2(d[:, 1], d[:, 0])) % 360
    order = np.argsort(a)
    start = int(np.argmin(np.abs((a[order] + 180) % 360 - 180)))
    order = np.roll(order, -start)
    p, d = p[order], d[order]
    # the box's walls: board x along the wall, y along -z of the box, z into the box; origin at dot 0
    H = rig.box_half_mm
    walls = {}
    for j in range(4):
        th = j * math.pi / 2
        inward = -np.array([math.cos(th), math.sin(th), 0.0])
        along = np.array([-math.sin(th), math.cos(th), 0.0])
        down = np.array([0.0, 0.0, -1.0])
        R = np.stack([along, down, np.cross(along, down)], 1)
        if R[:, 2] @ inward < 0:
            R[:, 0] *= -1
            R[:, 2] *= -1
        centre = -H * inward + np.array([0.0, 0.0, rig.grid_z_mm])
        origin = centre - R[:, 0] * rig.pitch_mm * (rig.cols - 1) / 2 - R[:, 1] * rig.pitch_mm * (rig.rows - 1) / 2
        walls[f"wall{j}"] = (R, origin)
    gx, gy = np.meshgrid(np.arange(rig.cols) * rig.pitch_mm, np.arange(rig.rows) * rig.pitch_mm)
    points = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1)
    poses = [(np.eye(3), np.zeros(3))]
    mot, rot = np.asarray(rig.motion_mm), np.radians(rig.rotation_deg)
    for _ in range(rig.n_views - 1):
        poses.append((_rot(rng.uniform(-rot, rot)), rng.uniform(-mot, mot)))
    cols, rows = rig.chess_inner
    cx, cy = np.meshgrid(np.arange(cols) * rig.chess_square_mm, np.arange(rows) * rig.chess_square_mm)
    chess = np.stack([cx.ravel(), cy.ravel(), np.zeros(cx.size)], 1)
    chess_poses = []
    while len(chess_poses) < rig.n_chess:
        R = _rot(np.radians(rng.uniform([-30, -30, -15], [30, 30, 15])))
        t = np.array([rng.uniform(-40, 40), rng.uniform(-30, 30), rng.uniform(380, 520)]) - R @ chess.mean(0)
        uv = cv2.projectPoints(chess @ R.T + t, np.zeros(3), np.zeros(3), K, np.asarray(rig.dist))[0].reshape(-1, 2)
        if np.all((uv > 20) & (uv < np.array([w, h]) - 20)):
            chess_poses.append((R, t))
    return _Geometry(K, np.asarray(rig.dist, float), (w, h), apex, axis, rig.cone_radius, rig.cone_height, p, d,
                     poses, walls, points, chess, chess_poses)  # fmt: skip


def _distort(k: np.ndarray, x: np.ndarray, y: np.ndarray):
    k1, k2, p1, p2, k3 = k
    r2 = x * x + y * y
    rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y


def _camera_rays(g: _Geometry, uv: np.ndarray) -> np.ndarray:
    """Unit camera rays (n, 3) of pixels (n, 2): Newton on the distortion model (Jacobian by central
    differences) from OpenCV's ``undistortPoints``, to 1e-12 of the normalised plane."""
    xy = cv2.undistortPoints(uv.reshape(-1, 1, 2).astype(np.float64), g.K, g.dist).reshape(-1, 2)
    tx, ty = (uv[:, 0] - g.K[0, 2]) / g.K[0, 0], (uv[:, 1] - g.K[1, 2]) / g.K[1, 1]
    x, y = xy[:, 0].copy(), xy[:, 1].copy()
    e = 1e-7
    for _ in range(6):
        fx, fy = _distort(g.dist, x, y)
        ax, ay = _distort(g.dist, x + e, y)
        bx, by = _distort(g.dist, x, y + e)
        j11, j21, j12, j22 = (ax - fx) / e, (ay - fy) / e, (bx - fx) / e, (by - fy) / e
        rx, ry = fx - tx, fy - ty
        det = j11 * j22 - j12 * j21
        x -= (j22 * rx - j12 * ry) / det
        y -= (-j21 * rx + j11 * ry) / det
        if max(np.abs(rx).max(), np.abs(ry).max()) < 1e-12:
            break
    d = np.column_stack([x, y, np.ones(len(x))])
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _cone_reflect(g: _Geometry, d: np.ndarray):
    """Rays from the camera centre (unit ``d``) on the cone: (hit point, reflected unit direction, valid)."""
    a, A = g.axis, g.apex
    k1 = 1.0 + (g.radius / g.height) ** 2
    da, Aa = d @ a, A @ a
    qa2 = 1.0 - k1 * da**2
    qb = -2.0 * (d @ A) + 2.0 * k1 * da * Aa
    qc = A @ A - k1 * Aa**2
    disc = qb**2 - 4 * qa2 * qc
    ok = disc >= 0
    sq = np.sqrt(np.where(ok, disc, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        roots = np.stack([(-qb - sq) / (2 * qa2), (-qb + sq) / (2 * qa2)], 1)
    best = np.full(len(d), np.inf)
    for r in (roots[:, 0], roots[:, 1]):
        along = r * da - Aa
        good = ok & np.isfinite(r) & (r > 0) & (along >= 0) & (along <= g.height)
        best = np.where(good & (r < best), r, best)
    valid = np.isfinite(best)
    t = np.where(valid, best, 0.0)
    X = t[:, None] * d
    q = X - A
    n = q - k1 * (q @ a)[:, None] * a
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    r = d - 2.0 * np.sum(d * n, 1, keepdims=True) * n
    valid &= np.sum(d * n, 1) < 0  # seen from outside the cone
    return X, r, valid


def _box_hit(rig: HeldOutRig, o: np.ndarray, d: np.ndarray):
    """First box plane met by rays (box frame): (plane index 0-5, point); walls 0-3 as ``wall{j}``,
    4 floor, 5 ceiling; plane -1 where an open corner lets the ray out."""
    H = rig.box_half_mm
    ts = []
    with np.errstate(divide="ignore", invalid="ignore"):
        for j in range(4):
            th = j * math.pi / 2
            nrm = np.array([math.cos(th), math.sin(th), 0.0])
            ts.append((H - o @ nrm) / (d @ nrm))
        ts.append((rig.floor_mm - o[:, 2]) / d[:, 2])
        ts.append((rig.ceiling_mm - o[:, 2]) / d[:, 2])
    t = np.stack(ts, 1)
    t = np.where(np.isfinite(t) & (t > 1e-9), t, np.inf)
    plane = np.argmin(t, 1)
    tmin = t[np.arange(len(t)), plane]
    X = o + np.where(np.isfinite(tmin), tmin, 0.0)[:, None] * d
    if rig.open_corner_mm > 0:
        side = np.where(plane % 2 == 0, X[:, 1], X[:, 0])  # the coordinate along a wall
        out = (plane < 4) & (np.abs(side) > H - rig.open_corner_mm)
        plane = np.where(out, -1, plane)
    return plane, X


def _spot_points(rig: HeldOutRig, g: _Geometry, view: int):
    """Each laser's spot in the box frame and the plane it lies on (first box plane its beam meets)."""
    R, t = g.T_box_cam[view]
    o = g.laser_p @ R.T + t
    d = g.laser_d @ R.T
    return _box_hit(rig, o, d)


def _shade_walls(rig: HeldOutRig, g: _Geometry, view: int, X: np.ndarray, plane: np.ndarray):
    """Grey and red radiance of box points."""
    grey = np.full(len(X), rig.surround)
    red = np.zeros(len(X))
    onbox = plane >= 0
    grey[onbox] = rig.wall
    if rig.shading:
        grey[onbox] *= 1.0 + rig.shading * np.clip((X[onbox, 2] - rig.grid_z_mm) / 60.0, -1, 1)
    for j, (R, t) in enumerate(g.walls.values()):
        m = plane == j
        if not m.any():
            continue
        b = (X[m] - t) @ R  # board frame
        gi = np.clip(np.round(b[:, 0] / rig.pitch_mm), 0, rig.cols - 1)
        gj = np.clip(np.round(b[:, 1] / rig.pitch_mm), 0, rig.rows - 1)
        r = np.hypot(b[:, 0] - gi * rig.pitch_mm, b[:, 1] - gj * rig.pitch_mm)
        gm = grey[m]
        gm[r < rig.dot_radius_mm] = rig.dot
        grey[m] = gm
    sp_plane, sp = _spot_points(rig, g, view)
    for k in range(len(sp)):
        if sp_plane[k] < 0:
            continue
        m = plane == sp_plane[k]
        d2 = np.sum((X[m] - sp[k]) ** 2, 1)
        red[m] += rig.spot_peak * np.exp(-0.5 * d2 / rig.spot_sigma_mm**2) * (grey[m] / rig.wall)
    return grey, red


def _samples(g: _Geometry, ss: int, rows: slice) -> np.ndarray:
    w = g.size[0]
    off = (np.arange(ss) + 0.5) / ss - 0.5
    ys = np.arange(rows.start, rows.stop)
    v = (ys[:, None] + off[None, :]).ravel()
    u = (np.arange(w)[:, None] + off[None, :]).ravel()
    uu, vv = np.meshgrid(u, v)
    return np.column_stack([uu.ravel(), vv.ravel()])


def _expose(rig: HeldOutRig, g: _Geometry, grey_s: np.ndarray, red_s: np.ndarray, seed: int) -> np.ndarray:
    """Supersampled radiances (H*ss, W*ss) to a BGR uint8 image."""
    ss = rig.supersample
    w, h = g.size
    grey = grey_s.reshape(h, ss, w, ss).mean(axis=(1, 3))
    red = red_s.reshape(h, ss, w, ss).mean(axis=(1, 3))
    if rig.blur_px > 0:
        grey = cv2.GaussianBlur(grey, (0, 0), rig.blur_px)
        red = cv2.GaussianBlur(red, (0, 0), rig.blur_px)
    rng = np.random.default_rng(seed)
    img = np.empty((h, w, 3))
    img[:, :, 0] = grey
    img[:, :, 1] = grey
    img[:, :, 2] = grey + red
    img = img * 255.0 + rng.normal(0.0, rig.noise, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def _mirror_samples(rig: HeldOutRig, g: _Geometry):
    """The supersampled pixels' rays off the mirror (the same in every view): hit points, reflected
    directions (valid samples only) and the valid mask, computed once per geometry."""
    if g.cache is None:
        ss = rig.supersample
        w, h = g.size
        d = _camera_rays(g, _samples(g, ss, slice(0, h)))
        X, r, valid = _cone_reflect(g, d)
        g.cache = (X[valid], r[valid], valid)
    return g.cache


def trace_view(rig: HeldOutRig, g: _Geometry, view: int) -> np.ndarray:
    """The catadioptric image of one view (BGR uint8)."""
    ss = rig.supersample
    w, h = g.size
    R, t = g.T_box_cam[view]
    X, r, valid = _mirror_samples(rig, g)
    grey = np.full(valid.size, rig.surround)
    red = np.zeros(valid.size)
    plane, Xb = _box_hit(rig, X @ R.T + t, r @ R.T)
    gv, rv = _shade_walls(rig, g, view, Xb, plane)
    grey[valid] = rig.mirror_reflectance * gv
    red[valid] = rig.mirror_reflectance * rv
    return _expose(rig, g, grey.reshape(h * ss, w * ss), red.reshape(h * ss, w * ss), rig.seed + view)


def trace_chess(rig: HeldOutRig, g: _Geometry, k: int, chunk: int = 60) -> np.ndarray:
    """A direct view of the chessboard (BGR uint8): black and white squares, a white margin, grey beyond."""
    ss = rig.supersample
    w, h = g.size
    R, t = g.T_cam_chess[k]
    cols, rows = rig.chess_inner
    sq = rig.chess_square_mm
    greys = []
    for y0 in range(0, h, chunk):
        uv = _samples(g, ss, slice(y0, min(y0 + chunk, h)))
        d = _camera_rays(g, uv)
        n = R[:, 2]
        s = (t @ n) / (d @ n)
        b = ((s[:, None] * d) - t) @ R
        i, j = np.floor(b[:, 0] / sq + 1), np.floor(b[:, 1] / sq + 1)  # squares -1 .. cols
        inside = (i >= 0) & (i <= cols) & (j >= 0) & (j <= rows)
        margin = (
            (b[:, 0] > -1.6 * sq)
            & (b[:, 0] < (cols + 0.6) * sq)
            & (b[:, 1] > -1.6 * sq)
            & (b[:, 1] < (rows + 0.6) * sq)
        )
        grey = np.where(margin, 0.85, 0.35)
        grey = np.where(inside & ((i + j) % 2 == 0), 0.06, grey)
        greys.append(grey.reshape(-1, w * ss))
    gs = np.concatenate(greys)
    return _expose(rig, g, gs, np.zeros_like(gs), rig.seed + 1000 + k)


# ------------------------------------------------------------------ truth (the library's geometry)


def _jax_rig(g: _Geometry):
    from slcvjax import Camera, ConeMirror, Lasers, Rig

    cam = Camera.create(g.K[0, 0], g.K[1, 1], g.K[0, 2], g.K[1, 2], g.dist, g.size[0], g.size[1])
    return Rig(cam, ConeMirror.create(g.apex, g.axis, g.radius, g.height), Lasers.create(g.laser_p, g.laser_d))


def _T_cam_wall(g: _Geometry, view: int, name: str):
    Rb, tb = g.T_box_cam[view]
    Rw, tw = g.walls[name]
    return Rb.T @ Rw, Rb.T @ (tw - tb)


def _traced_hit(rig: HeldOutRig, g: _Geometry, view: int, uv: np.ndarray):
    """This tracer's box point (box frame) and plane seen at sub-pixel ``uv`` (n, 2); plane -2 off the mirror."""
    R, t = g.T_box_cam[view]
    d = _camera_rays(g, uv)
    X, r, valid = _cone_reflect(g, d)
    plane = np.full(len(uv), -2)
    Xb = np.zeros((len(uv), 3))
    if valid.any():
        plane[valid], Xb[valid] = _box_hit(rig, X[valid] @ R.T + t, r[valid] @ R.T)
    return plane, Xb


def truth(rig: HeldOutRig, g: _Geometry) -> dict:
    """Per view: every dot's exact pixel and whether it is visible whole (its centre and 12 points of
    its edge project through the mirror into the image, and this tracer's rays at those pixels meet
    that wall, the centre's within 0.05 mm of the dot's centre), every visible spot's laser, pixel
    and board; and the library's rig (for the rim)."""
    import jax.numpy as jnp

    from slcvjax import Pose, project_board_points

    jr = _jax_rig(g)
    w, h = g.size
    m = len(g.points)
    edge = np.array([[math.cos(a), math.sin(a), 0.0] for a in np.linspace(0, 2 * math.pi, 12, endpoint=False)])
    ring = (g.points[:, None, :] + rig.dot_radius_mm * edge[None]).reshape(-1, 3)
    per_wall = m + len(ring)
    views = []
    for v in range(rig.n_views):
        Rb, tb = g.T_box_cam[v]
        pts = []
        for name in g.walls:
            R, t = _T_cam_wall(g, v, name)
            pts.append(np.concatenate([g.points, ring]) @ R.T + t)
        sp_plane, sp = _spot_points(rig, g, v)
        pts.append((sp - tb) @ Rb)  # the spots, camera frame
        uv_all, ok_all = (
            np.asarray(a) for a in project_board_points(jr, Pose.identity(), jnp.asarray(np.concatenate(pts)))
        )
        inimg = ok_all & np.all((uv_all > 2) & (uv_all < np.array([w, h]) - 3), 1)
        plane, Xb = _traced_hit(rig, g, v, np.where(inimg[:, None], uv_all, 0.0))
        dots = {}
        for j, name in enumerate(g.walls):
            sl = slice(j * per_wall, (j + 1) * per_wall)
            uv, ok, pl = uv_all[sl], inimg[sl], plane[sl]
            Rw, tw = g.walls[name]
            near = np.linalg.norm(Xb[sl][:m] - (g.points @ Rw.T + tw), axis=1) < 0.05
            seen = ok[:m] & (pl[:m] == j) & near & ((pl[m:] == j) & ok[m:]).reshape(m, -1).all(1)
            dots[name] = (uv[:m], seen)
        spots = []
        base = 4 * per_wall
        for k in range(len(sp)):
            i = base + k
            if sp_plane[k] >= 0 and inimg[i] and plane[i] == sp_plane[k] and np.linalg.norm(Xb[i] - sp[k]) < 0.05:
                board = f"wall{int(sp_plane[k])}" if sp_plane[k] < 4 else None
                spots.append({"laser": k, "pixel": uv_all[i], "board": board})
        views.append({"dots": dots, "spots": spots})
    return {"views": views, "rig": jr}


# ------------------------------------------------------------------ a folder as `simulate --render` writes it


def _setup(rig: HeldOutRig, g: _Geometry, names: list[str], chess_names: list[str]) -> dict:
    """``slcv-setup/1``: nominal azimuths and grid directions from view 0's exact projections."""
    import jax.numpy as jnp

    from slcvjax import Pose, project_board_points
    from slcvjax.geometry.rig import project_rim

    jr = _jax_rig(g)
    ruv, rok = (np.asarray(a) for a in project_rim(jr, jnp.linspace(0, 2 * np.pi, 64, endpoint=False)))
    centre = ruv[rok].mean(0)

    def az(p):
        d = np.asarray(p).reshape(-1, 2) - centre
        return np.degrees(np.arctan2(d[:, 1], d[:, 0])) % 360

    boards = {}
    for name in g.walls:
        R, t = _T_cam_wall(g, 0, name)
        uv, ok = (
            np.asarray(a) for a in project_board_points(jr, Pose(jnp.asarray(R), jnp.asarray(t)), jnp.asarray(g.points))
        )
        a = az(uv[ok])
        mean = math.degrees(np.angle(np.exp(1j * np.radians(a)).mean())) % 360
        grid = uv.reshape(rig.rows, rig.cols, 2)
        dx = (az(grid[:, 1]) - az(grid[:, 0]) + 180) % 360 - 180
        r = np.linalg.norm(grid - centre, axis=-1)
        boards[name] = {
            "points": g.points.tolist(), "cols": rig.cols, "rows": rig.rows, "azimuth_deg": float(mean),
            "x_dir": 1 if np.nanmedian(dx) > 0 else -1, "y_dir": 1 if np.nanmedian(r[1] - r[0]) > 0 else -1,
            "dot_radius_mm": rig.dot_radius_mm,
        }  # fmt: skip
    boards["chess"] = {"points": g.chess.tolist(), "cols": rig.chess_inner[0], "rows": rig.chess_inner[1]}
    return {
        "format": "slcv-setup/1",
        "image_size": list(g.size),
        "mirror_shape": {"kind": "cone", "radius": rig.cone_radius, "height": rig.cone_height},
        "n_lasers": rig.n_lasers,
        "laser_azimuth_deg": None,
        "boards": boards,
        "views": [{"image": n} for n in names],
        "chessboard_views": [{"image": n, "board": "chess"} for n in chess_names],
        "spot_sigma_mm": rig.spot_sigma_mm,
        "rigid_boards": list(g.walls),
        "simulation": {"tracer": "tests/_tracer.py", **{k: v for k, v in asdict(rig).items() if k != "extra"}},
    }


def render_folder(rig: HeldOutRig, folder: str | Path) -> dict:
    """Trace every view and chessboard view of ``rig`` into ``folder`` with its ``setup.json``; returns the truth."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    g = _geometry(rig)
    names, chess_names = [], []
    for v in range(rig.n_views):
        names.append(f"view{v:02d}.png")
        cv2.imwrite(str(folder / names[-1]), trace_view(rig, g, v))
    for k in range(rig.n_chess):
        chess_names.append(f"chess{k:02d}.png")
        cv2.imwrite(str(folder / chess_names[-1]), trace_chess(rig, g, k))
    (folder / "setup.json").write_text(json.dumps(_setup(rig, g, names, chess_names), indent=1))
    tr = truth(rig, g)
    tr["geometry"] = g
    return tr


# ------------------------------------------------------------------ measures


def measure(obs, report, truth: dict) -> dict:
    """The detection of a folder (:func:`slcvjax.detect_folder`'s observations and report) against
    its truth (:func:`truth`, or the same layout): per view, the rim found (at least 60 rim
    pixels, RMS distance to the true rim under 0.5 px); the visible dots placed on their grid;
    dots placed on a wrong grid position (nearer another dot's true pixel than their own's, or
    over 3 px from it); spots found with the right laser (within 2 px of its true spot), and
    mislabelled (any other); lasers never found."""
    from slcvjax import distance_to_rim

    rig = truth["rig"]
    per_view, lasers_found = [], set()
    tot = dict(visible=0, placed=0, placed_invisible=0, wrong=0, spots_visible=0, spots_right=0, spots_wrong=0)
    rim_ok = 0
    for vd, vt in zip(obs.views, truth["views"], strict=True):
        d = distance_to_rim(rig, vd.rim) if len(vd.rim) else np.zeros(0)
        rim = bool(len(vd.rim) >= 60 and np.sqrt(np.mean(d**2)) < 0.5)
        rim_ok += rim
        vis = placed = wrong = placed_inv = 0
        for b, (tuv, tseen) in vt["dots"].items():
            px, seen = vd.boards[b]
            vis += int(tseen.sum())
            placed += int((seen & tseen).sum())
            placed_inv += int((seen & ~tseen).sum())
            finite = np.all(np.isfinite(tuv), 1)
            for i in np.flatnonzero(seen):
                dist = np.where(finite, np.linalg.norm(tuv - px[i], axis=1), np.inf)
                if int(np.argmin(dist)) != i or dist[i] > 3.0:
                    wrong += 1
        truth_spots = {s["laser"]: s["pixel"] for s in vt["spots"]}
        right = bad = 0
        for s in vd.spots:
            if s.laser in truth_spots and np.linalg.norm(np.asarray(s.pixel) - truth_spots[s.laser]) < 2.0:
                right += 1
                lasers_found.add(s.laser)
            else:
                bad += 1
        tot["visible"] += vis
        tot["placed"] += placed
        tot["placed_invisible"] += placed_inv
        tot["wrong"] += wrong
        tot["spots_visible"] += len(truth_spots)
        tot["spots_right"] += right
        tot["spots_wrong"] += bad
        per_view.append(
            dict(name=vd.name, rim_pixels=len(vd.rim), rim_found=rim, dots_visible=vis, dots_placed=placed,
                 wrong=wrong, spots_visible=len(truth_spots), spots_right=right, spots_wrong=bad)
        )  # fmt: skip
    n_lasers = obs.n_lasers
    return {
        "views": len(obs.views),
        "rim_found_views": rim_ok,
        "dots_visible": tot["visible"],
        "dots_placed": tot["placed"],
        "dots_placed_fraction": tot["placed"] / max(tot["visible"], 1),
        "dots_placed_not_visible_whole": tot["placed_invisible"],
        "dots_wrong_position": tot["wrong"],
        "spots_visible": tot["spots_visible"],
        "spots_found_right": tot["spots_right"],
        "spots_mislabelled": tot["spots_wrong"],
        "lasers_never_found": sorted(set(range(n_lasers)) - lasers_found),
        "chessboard_views_found": len(obs.calibration_views),
        "report": report.summary(),
        "per_view": per_view,
    }


def goals(m: dict) -> dict:
    """The goals at 1 grey level of noise: the rim in every view, at least 65 % of the visible dots
    placed, none on a wrong grid position, no spot mislabelled."""
    return {
        "rim_every_view": m["rim_found_views"] == m["views"],
        "dots_65pct": m["dots_placed_fraction"] >= 0.65,
        "no_wrong_position": m["dots_wrong_position"] == 0,
        "no_mislabelled_spot": m["spots_mislabelled"] == 0,
    }
