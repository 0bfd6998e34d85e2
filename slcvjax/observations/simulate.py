"""The simulator: the paper's reference rig in a calibration box, and its observations.

The ``paper`` preset follows Chen, Zhou & Xue (Measurement 148, 2019), Tables 1-4,
whose printed values lost their signs (magnitudes only):

- Table 1: a 640x480 camera, fx 551.757, fy 551.95, cx 322.826, cy 205.202 px; the
  distortion magnitudes are taken with barrel signs.
- Table 2: a cone of radius 20 mm and height 10 mm, 48 mm in front of the lens; its
  small tilt (1.4 deg) and offset (0.7 mm) are the preset's own.
- Tables 3-4: ten lasers whose beams radiate outwards nearly across the camera axis
  (Table 4's unit directions have ``|n_z| <= 0.055``, beams within 3.2 deg of the plane
  across the axis).  Which way each tilts was lost with the signs; the preset draws each
  beam's elevation in [-3.15, 0] deg (towards the camera's side, which keeps the spots in
  the mirror's view on the farther box walls), its azimuth within 2 deg of radial.  The
  table's emitter positions cannot be used as printed: the preset puts the emitters on a
  30 mm ring 5 mm in front of the lens (below the mirror, so that every spot is seen
  through it), with millimetre mounting errors.

The mirror sees the world between about 37 and 18 deg below the plane across its axis,
so a nearly horizontal beam's spot is seen at a healthy angle to its viewing ray
(25-37 deg inside a 150 mm pipe, 18-30 deg on the box walls).  The calibration box is
280 mm wide (the paper does not give its size; a wider box would put its walls' spots
above the mirror's view): its walls carry 3x3 dot grids (50 mm across by 20 mm down,
centred 30 mm behind the lens) where the mirror looks; sixteen views move the sensor
inside the box; twelve direct views of a 9x6, 25 mm chessboard serve the intrinsics;
every view has rim edge pixels.  Only points that are really visible are written.
"""

from collections.abc import Sequence
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from ..geometry.camera import Camera
from ..geometry.lasers import Lasers, line_plane_intersection
from ..geometry.mirror import ConeMirror, shape_json
from ..geometry.pose import Pose, so3_exp
from ..geometry.rig import Rig, project_board_points, project_direct, project_rim
from ..geometry.sheets import Sheets
from .formats import Calibration, CalibrationViewObs, Observations, SpotObs, StripeObs, ViewObs
from .problem import padded_lasers

PRESETS = ("paper",)
PITCH_X = 50.0
PITCH_Y = 20.0
GRID_Z_MM = -30.0  # the wall grids' centre along the camera axis, box frame
LASER_RING_MM = 30.0
LASER_RING_Z_MM = 5.0
LASER_MAX_NZ = 0.055  # Table 4: the largest |n_z| of a beam's unit direction


@dataclass
class Scene:
    """A simulated calibration: the true rig, the boards and every true pose.

    ``box_poses[i][board]`` is ``T_cam_board`` of catadioptric view ``i``;
    ``chess_poses[j]`` is ``T_cam_board`` of direct chessboard view ``j``.
    """

    rig: Rig
    boards: dict[str, np.ndarray]
    box_poses: list[dict[str, Pose]]
    chess_board: str
    chess_poses: list[Pose]
    rim_points_per_view: int
    info: dict
    # the line and ring lasers' stripes: an emission-angle step (deg) along each sheet's fan, and
    # per sheet (its element index) the fan's limits as camera-frame azimuths (deg, from, to;
    # absent: all round)
    stripe_step_deg: float = 0.5
    fans: dict = field(default_factory=dict)
    # each coded wall's type and fields (a ChArUco or AprilGrid spec, as
    # :func:`slcvjax.observations.targets.read_board` gives it); a board not listed is a grid of dots
    board_types: dict = field(default_factory=dict)


def grid_points(cols: int, rows: int, pitch: float, centred: bool = False, pitch_y: float | None = None) -> np.ndarray:
    """Board points of a ``cols x rows`` grid (x fastest), z = 0, in mm (``pitch_y`` defaults to ``pitch``)."""
    x, y = np.meshgrid(np.arange(cols) * pitch, np.arange(rows) * (pitch if pitch_y is None else pitch_y))
    pts = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    if centred:
        pts[:, :2] -= pts[:, :2].mean(axis=0)
    return pts


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def paper_camera() -> Camera:
    """The paper's camera (Table 1); distortion magnitudes with barrel signs."""
    return Camera.create(551.757, 551.95, 322.826, 205.202, [-0.28, 0.09, 0.0012, -0.0008, -0.01], 640, 480)


def paper_rig(n_lasers: int = 10) -> Rig:
    """The reference rig with ``n_lasers`` lasers evenly spread on a ring, beams nearly across the axis."""
    if n_lasers < 1:
        raise ValueError(f"n_lasers must be at least 1, got {n_lasers}")
    mirror = ConeMirror.create([0.6, -0.4, 48.0], [0.02, -0.015, 1.0], 20.0, 10.0)
    rng = np.random.default_rng(20190914)  # fixed: the preset's small mounting errors
    pts, dirs = [], []
    for i in range(n_lasers):
        az = 2 * np.pi * i / n_lasers + np.radians(rng.uniform(-3, 3))
        ring, z = LASER_RING_MM + rng.uniform(-1, 1), LASER_RING_Z_MM + rng.uniform(-1.5, 1.5)
        aim_az = az + np.radians(rng.uniform(-2, 2))
        elev = -np.arcsin(rng.uniform(0.0, LASER_MAX_NZ))
        pts.append([ring * np.cos(az), ring * np.sin(az), z])
        dirs.append([np.cos(elev) * np.cos(aim_az), np.cos(elev) * np.sin(aim_az), np.sin(elev)])
    return Rig(paper_camera(), mirror, Lasers.create(np.array(pts), np.array(dirs)))


def sheet_rig(
    rig: Rig, kinds: Sequence[str] = ("cone", "point", "point", "point", "point"), seed: int = 5
) -> tuple[Rig, dict]:
    """A rig of ``rig``'s camera and mirror with the lasers ``kinds`` in order: point lasers as
    :func:`paper_rig` spreads them, ring lasers (``cone``) near the axis 5 mm in front of the lens
    opening 92-97 deg from the axis (the light a few degrees towards the camera, where the mirror
    sees the walls), line lasers (``plane``) through an emitter on the 30 mm ring, each plane
    tilted 3-8 deg from across the axis about its fan's aim.  Returns the rig and the line
    lasers' fans (camera-frame azimuths, deg, for :attr:`Scene.fans`: 100 deg about each aim)."""
    kinds = tuple(kinds)
    bad = [k for k in kinds if k not in ("point", "plane", "cone")]
    if bad or not kinds:
        raise ValueError(f"kinds: expected point, plane or cone for each laser, got {kinds}")
    rng = np.random.default_rng(seed)
    n_p = sum(k == "point" for k in kinds)
    points = paper_rig(max(n_p, 1)).lasers if n_p else None
    n_l = sum(k != "point" for k in kinds)
    apex, axis, angle, fans = [], [], [], {}
    for j, (i, k) in enumerate((i, k) for i, k in enumerate(kinds) if k != "point"):
        az = 2 * np.pi * (j + 0.25) / n_l + np.radians(rng.uniform(-5, 5))
        if k == "cone":
            apex.append([rng.uniform(-1, 1), rng.uniform(-1, 1), LASER_RING_Z_MM + rng.uniform(-1, 1)])
            tilt = np.radians(rng.uniform(0.5, 1.5))
            axis.append([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
            angle.append(np.radians(rng.uniform(92.0, 97.0)))
        else:
            apex.append([LASER_RING_MM * np.cos(az), LASER_RING_MM * np.sin(az), LASER_RING_Z_MM])
            tilt = np.radians(rng.uniform(3.0, 8.0)) * rng.choice([-1.0, 1.0])
            tangent = np.array([-np.sin(az), np.cos(az), 0.0])
            radial = np.array([np.cos(az), np.sin(az), 0.0])
            normal = np.cos(tilt) * np.array([0.0, 0.0, 1.0]) + np.sin(tilt) * radial
            normal += 0.03 * rng.uniform(-1, 1) * tangent
            axis.append(normal)
            angle.append(np.pi / 2)
            fans[i] = (float(np.degrees(az)) - 50.0, float(np.degrees(az)) + 50.0)
    sheets = Sheets.create([k for k in kinds if k != "point"], apex, axis, angle) if n_l else None
    lasers = points if points is not None else Lasers.create(np.zeros((0, 3)), np.zeros((0, 3)))
    return Rig.of_elements(rig.camera, rig.mirror, lasers, sheets, kinds), fans


def _box_walls(
    half_width: float, grid_z: float, pitch: float, pitch_y: float
) -> tuple[dict[str, np.ndarray], list[Pose]]:
    """Four walls at +-half_width (box frame, z up the sensor's axis), a 3x3 grid on each.

    Returns the board points and ``T_box_wall`` of each wall.  A wall's board
    frame has its origin at the grid's first dot, x horizontal along the wall,
    y along -z of the box, and z pointing into the box.
    """
    boards, poses = {}, []
    for j in range(4):
        az = j * np.pi / 2
        inward = -np.array([np.cos(az), np.sin(az), 0.0])
        along = np.array([-np.sin(az), np.cos(az), 0.0])
        down = np.array([0.0, 0.0, -1.0])
        r = np.stack([along, down, np.cross(along, down)], axis=1)
        if np.dot(r[:, 2], inward) < 0:
            r[:, 0] *= -1.0
            r[:, 2] *= -1.0
        centre = -half_width * inward + np.array([0.0, 0.0, grid_z])
        origin = centre - pitch * r[:, 0] - pitch_y * r[:, 1]
        boards[f"wall{j}"] = grid_points(3, 3, pitch, pitch_y=pitch_y)
        poses.append(Pose(jnp.asarray(r), jnp.asarray(origin)))
    return boards, poses


def draw_chess_poses(camera: Camera, board: np.ndarray, n: int, rng: np.random.Generator) -> list[Pose]:
    """Random direct chessboard poses with every corner in the image."""
    poses: list[Pose] = []
    centre = board.mean(axis=0)
    while len(poses) < n:
        rvec = np.radians(rng.uniform([-35, -35, -20], [35, 35, 20]))
        r = np.asarray(so3_exp(jnp.asarray(rvec)))
        dist = rng.uniform(330, 520)
        target = np.array([rng.uniform(-60, 60), rng.uniform(-45, 45), dist])
        pose = Pose(jnp.asarray(r), jnp.asarray(target - r @ centre))
        _, ok = project_direct(camera, pose, jnp.asarray(board))
        if bool(np.all(np.asarray(ok))):
            poses.append(pose)
    return poses


# the paper preset's box and motion range: roll, pitch, yaw (deg) and x, y, z (mm) of T_box_cam
PAPER_HALF_WIDTH = 140.0
PAPER_ROTATION_DEG = (3.0, 3.0, 20.0)
PAPER_TRANSLATION_MM = (25.0, 25.0, 8.0)


def paper_views(n_views: int = 16) -> np.ndarray:
    """The preset's sensor poses in the box, ``(n_views, 6)``: rotation vector (rad) and translation (mm).

    View 0 is the box frame itself; the others are drawn uniformly within the motion
    range (``PAPER_ROTATION_DEG``, ``PAPER_TRANSLATION_MM``) from a fixed seed.
    """
    if n_views < 1:
        raise ValueError(f"n_views must be at least 1, got {n_views}")
    rng = np.random.default_rng(7)  # fixed: the preset's motions
    rot, tra = np.asarray(PAPER_ROTATION_DEG), np.asarray(PAPER_TRANSLATION_MM)
    views = np.zeros((n_views, 6))
    for i in range(1, n_views):
        views[i, :3] = np.radians(rng.uniform(-rot, rot))
        views[i, 3:] = rng.uniform(-tra, tra)
    return views


def box_walls(half_width: float = PAPER_HALF_WIDTH) -> tuple[dict[str, np.ndarray], list[Pose]]:
    """The preset's four walls (3x3 dot grids) around a box of ``half_width``: points and ``T_box_wall``."""
    return _box_walls(half_width, GRID_Z_MM, PITCH_X, PITCH_Y)


def box_scene(rig: Rig, views: np.ndarray, half_width: float = PAPER_HALF_WIDTH, n_chess_views: int = 12) -> Scene:
    """The sensor at the given poses in the box: ``views`` (V, 6) holds ``T_box_cam`` per view.

    Each row is a rotation vector (rad) and a translation (mm), as from
    :func:`paper_views` or an experiment design (:mod:`slcvjax.experiments.design`).
    """
    views = np.asarray(views, dtype=float)
    if views.ndim != 2 or views.shape[1] != 6 or views.shape[0] < 1:
        raise ValueError(f"views must be an (n, 6) array with n >= 1, got shape {views.shape}")
    if not np.all(np.isfinite(views)):
        raise ValueError("views: non-finite value")
    boards, T_box_walls = box_walls(half_width)
    box_poses = []
    for v in views:
        T_cam_box = Pose(so3_exp(jnp.asarray(v[:3])), jnp.asarray(v[3:])).inverse()
        box_poses.append({f"wall{j}": T_cam_box @ T_box_walls[j] for j in range(4)})
    chess = grid_points(9, 6, 25.0)
    chess_poses = draw_chess_poses(rig.camera, chess, n_chess_views, np.random.default_rng(11))
    boards = dict(boards)
    boards["chess"] = chess
    info = {
        "preset": "paper",
        "box_half_width_mm": float(half_width),
        "wall_grid": {"cols": 3, "rows": 3, "pitch_x_mm": PITCH_X, "pitch_y_mm": PITCH_Y, "centre_z_mm": GRID_Z_MM},
        "chessboard": {"cols": 9, "rows": 6, "square_mm": 25.0},
    }
    return Scene(rig, boards, box_poses, "chess", chess_poses, 90, info)


def paper_scene(n_lasers: int = 10, n_views: int = 16, n_chess_views: int = 12) -> Scene:
    """The paper's calibration: the sensor moved to ``n_views`` poses inside the box."""
    return box_scene(paper_rig(n_lasers), paper_views(n_views), PAPER_HALF_WIDTH, n_chess_views)


@jax.jit
def _spots_all(rig: Rig, poses_R, poses_t):
    """Per laser and wall: the beam parameter, the 3D spot, and its pixel through the mirror."""
    from ..geometry.mirror import project_through_mirror

    def one(p, d, r, t):
        n = r[:, 2]
        denom = jnp.dot(n, d)
        x, ok = line_plane_intersection(p, d, Pose(r, t))
        lam = jnp.dot(x - p, d)
        res = project_through_mirror(rig.camera, rig.mirror, x)
        return lam, ok & (jnp.abs(denom) > 1e-6), res.uv, res.valid

    per_wall = jax.vmap(one, in_axes=(None, None, 0, 0))
    return jax.vmap(per_wall, in_axes=(0, 0, None, None))(rig.lasers.points, rig.lasers.directions, poses_R, poses_t)


def visible_spots(scene: Scene, view: int) -> list[tuple[int, str, np.ndarray, np.ndarray]]:
    """The laser spots of one catadioptric view: (laser, wall, 3D point in the camera frame, exact pixel).

    A beam makes its spot on the first wall it meets; the spot is listed where it
    is visible through the mirror.
    """
    rig = scene.rig
    walls = [b for b in scene.boards if b != scene.chess_board]
    poses = scene.box_poses[view]
    rs = jnp.stack([poses[b].R for b in walls])
    ts = jnp.stack([poses[b].t for b in walls])
    # the lasers padded to their bucket: one compilation for every laser count of it
    n = rig.lasers.n
    lam, ok, uv, vis = (np.asarray(a)[:n] for a in _spots_all(rig.with_lasers(padded_lasers(rig.lasers)), rs, ts))
    pts, dirs = np.asarray(rig.lasers.points), np.asarray(rig.lasers.directions)
    out = []
    for laser in range(rig.lasers.n):
        lam_l = np.where(ok[laser], lam[laser], np.inf)
        w = int(np.argmin(lam_l))
        if np.isfinite(lam_l[w]) and vis[laser, w]:
            out.append((laser, walls[w], pts[laser] + lam_l[w] * dirs[laser], uv[laser, w]))
    return out


@jax.jit
def _sheet_hits(rig: Rig, dirs, origins, poses_R, poses_t):
    """Per emission ray and wall: where the ray meets the wall's plane, and its pixel through the mirror."""
    from ..geometry.mirror import project_through_mirror

    def one(p, d, r, t):
        n = r[:, 2]
        den = jnp.dot(n, d)
        lam = jnp.where(jnp.abs(den) > 1e-9, jnp.dot(n, t - p) / jnp.where(jnp.abs(den) > 1e-9, den, 1.0), -1.0)
        x = p + lam * d
        res = project_through_mirror(rig.camera, rig.mirror, x)
        return lam, x, res.uv, res.valid

    per_wall = jax.vmap(one, in_axes=(None, None, 0, 0))
    return jax.vmap(per_wall, in_axes=(0, 0, None, None))(origins, dirs, poses_R, poses_t)


def sheet_rays(scene: Scene, element: int) -> tuple[np.ndarray, np.ndarray]:
    """The emission rays of one line or ring laser (element index ``element``): origins and unit
    directions (K, 3), camera frame, one per :attr:`Scene.stripe_step_deg` of its fan."""
    rig = scene.rig
    j = int(rig.local_index[element])
    sh = rig.sheets
    p, a, th = (np.asarray(x, float) for x in (sh.apex[j], sh.axis[j], sh.half_angle[j]))
    step = np.radians(scene.stripe_step_deg)
    phi = np.arange(0.0, 2 * np.pi, step)
    from ..support.safe import orthonormal_basis

    e1, e2 = (np.asarray(e) for e in orthonormal_basis(jnp.asarray(a)))
    u = np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2
    d = np.cos(th) * a + np.sin(th) * u
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    if element in scene.fans:
        lo, hi = (np.radians(x) for x in scene.fans[element])
        az = np.arctan2(d[:, 1], d[:, 0])
        keep = np.mod(az - lo, 2 * np.pi) <= np.mod(hi - lo, 2 * np.pi)
        d = d[keep]
    return np.broadcast_to(p, d.shape).copy(), d


def visible_stripes(scene: Scene, view: int) -> list[tuple[int, str, np.ndarray, np.ndarray]]:
    """The stripes of one catadioptric view: per line or ring laser and wall, (laser element index,
    wall, 3D points (M, 3) camera frame, exact pixels (M, 2)) of its emission rays that meet that
    wall first and are seen through the mirror, in the order of the fan."""
    rig = scene.rig
    if not rig.has_sheets:
        return []
    walls = [b for b in scene.boards if b != scene.chess_board]
    poses = scene.box_poses[view]
    rs = jnp.stack([poses[b].R for b in walls])
    ts = jnp.stack([poses[b].t for b in walls])
    out = []
    for e in rig.sheet_elements:
        org, d = sheet_rays(scene, int(e))
        if not len(d):
            continue
        lam, x, uv, ok = (np.asarray(a) for a in _sheet_hits(rig, jnp.asarray(d), jnp.asarray(org), rs, ts))
        lam_l = np.where(lam > 0, lam, np.inf)
        w = np.argmin(lam_l, axis=1)
        rows = np.arange(len(d))
        hit = np.isfinite(lam_l[rows, w]) & ok[rows, w]
        for k, b in enumerate(walls):
            sel = hit & (w == k)
            if sel.sum() >= 2:
                out.append((int(e), b, x[rows, w][sel], uv[rows, w][sel]))
    return out


def simulate(scene: Scene, noise: "float | Sequence[float]" = 0.0, seed: int = 0) -> tuple[Observations, Calibration]:
    """Observations of a scene with Gaussian pixel noise ``noise`` (px per axis), and the truth.

    ``noise`` is one sigma for every pixel, or one per kind: dots, spots, rim pixels,
    chessboard corners (as a detector gives them: rendered images make spots' centroids the
    noisiest and the rim's fitted edge the least noisy).  With ``noise = 0`` every pixel is the
    exact projection of the truth.  Points that are not visible are written as null; a
    laser's spot is written on the wall its beam meets first, where it is visible through the
    mirror.
    """
    sig = np.broadcast_to(np.asarray(noise, dtype=float), (5,)) if np.ndim(noise) == 0 else np.asarray(noise, float)
    if sig.shape == (4,):  # the stripes' centre lines as noisy as the spots
        sig = np.append(sig, sig[1])
    if sig.shape != (5,) or not np.all(np.isfinite(sig) & (sig >= 0)):
        raise ValueError(
            "noise must be a non-negative number of pixels, or four (dots, spots, rim, corners) or five (and "
            f"stripes), got {noise}"
        )
    rng = np.random.default_rng(seed)
    rig = scene.rig
    cam = rig.camera
    walls = [b for b in scene.boards if b != scene.chess_board]
    noise_px = float(sig[0]) if np.ndim(noise) == 0 else np.asarray(noise, float).tolist()

    def noisy(px, kind: int):
        s = sig[kind]
        return np.asarray(px, float) + rng.normal(0.0, s, np.shape(px)) if s > 0 else np.asarray(px, float)

    cal_views = []
    for j, pose in enumerate(scene.chess_poses):
        uv, ok = project_direct(cam, pose, jnp.asarray(scene.boards[scene.chess_board]))
        cal_views.append(CalibrationViewObs(f"chess{j:02d}", scene.chess_board, noisy(uv, 3), np.asarray(ok)))

    views = []
    for i, poses in enumerate(scene.box_poses):
        per_board = {}
        for b in walls:
            uv, ok = project_board_points(rig, poses[b], jnp.asarray(scene.boards[b]))
            per_board[b] = (noisy(uv, 0), np.asarray(ok))
        point_of = rig.point_elements
        spots = [SpotObs(int(point_of[laser]), wall, noisy(uv, 1)) for laser, wall, _, uv in visible_spots(scene, i)]
        stripes = [StripeObs(e, wall, noisy(uv, 4)) for e, wall, _, uv in visible_stripes(scene, i)]
        angles = np.sort(rng.uniform(0, 2 * np.pi, scene.rim_points_per_view))
        ruv, rok = project_rim(rig, jnp.asarray(angles))
        rim = noisy(np.asarray(ruv)[np.asarray(rok)], 2)
        views.append(ViewObs(f"view{i:02d}", per_board, spots, rim, stripes))

    obs = Observations(
        image_size=(cam.width, cam.height),
        mirror_radius=float(rig.mirror.radius),
        mirror_height=float(rig.mirror.height),
        n_lasers=rig.n_elements,
        boards={k: np.asarray(v, float) for k, v in scene.boards.items()},
        calibration_views=cal_views,
        views=views,
        extra={
            "simulation": {**scene.info, "noise_px": noise_px, "seed": int(seed)},
            "rigid_boards": list(walls),  # the walls stand still in the box (calibrate(rigid=True))
        },
        mirror_shape=None if isinstance(rig.mirror, ConeMirror) else shape_json(rig.mirror),
        laser_kinds=rig.kinds,
        board_types={k: dict(v) for k, v in scene.board_types.items()},
    )
    truth = Calibration(
        rig=rig,
        board_poses=[{b: p[b] for b in walls} for p in scene.box_poses],
        calibration_view_poses=list(scene.chess_poses),
        extra={"simulation": {**scene.info, "noise_px": noise_px, "seed": int(seed)}},
    )
    return obs, truth


def make_scene(preset: str = "paper", n_lasers: int = 10, n_views: int = 16) -> Scene:
    """A named preset scene (only ``paper`` for now)."""
    if preset != "paper":
        raise ValueError(f"unknown preset {preset!r} (known: {', '.join(PRESETS)})")
    return paper_scene(n_lasers=n_lasers, n_views=n_views)
