"""A simulated box of coded targets: ChArUco or AprilGrid walls around the sensor, and their truth.

:func:`coded_box_scene` places the walls as :func:`slcvjax.images.targetbox.box_setup` places them
for a user's own rig (``slcvjax setup init``): ``n_walls`` boards facing the mirror's axis, each
centred where the mirror sees its wall, marker ids continuing from wall to wall.  The sensor
moves in the box as in :func:`slcvjax.observations.simulate.box_scene` (``T_box_cam`` per view).
The scene's ``board_types`` carries each wall's spec, so :func:`slcvjax.images.render.render_scene`
draws its print (:mod:`slcvjax.images.render_coded`) and its ``setup.json`` names its type.

:func:`visible_corners` is the truth a coded detector is measured against: each board point's
exact pixel (:func:`slcvjax.geometry.rig.project_board_points`) and whether it is *visible*
(defined there, in words a benchmark can quote).
"""

import jax
import jax.numpy as jnp
import numpy as np

from ..geometry.pose import Pose, so3_exp
from ..geometry.rig import Rig, project_board_points
from ..observations.simulate import Scene, draw_chess_poses, grid_points
from ..observations.targets import aprilgrid_tag_corners
from .render import RenderOptions, cata_ray, wall_hit
from .targetbox import box_setup

CHESS = (9, 6, 25.0)  # the direct views' chessboard: inner corners and square (simulate's)


def coded_box_scene(
    rig: Rig,
    views: np.ndarray,
    target: str = "charuco-box",
    n_chess_views: int = 0,
    mirror_distance_mm: float | None = None,
    chessboard: tuple[int, int, float] = CHESS,
    **box,
) -> Scene:
    """The sensor at ``views`` (V, 6: rotation vector rad, translation mm of ``T_box_cam``) in a box
    of coded walls (``target``: ``charuco-box`` or ``aprilgrid-box``).

    ``mirror_distance_mm`` (default: the rig's apex distance along the camera's axis) and ``box``
    (``width_mm``, ``n_walls``, ``squares``, ``square_mm``, ``marker_mm``, ``spacing``,
    ``board_z_mm``) go to :func:`~slcvjax.images.targetbox.box_setup`.  The box frame is the
    camera's at the sensor's nominal place.  ``n_chess_views`` direct views of the chessboard
    ``chessboard`` (inner corners cols, rows and square mm; default simulate's 9 x 6, 25 mm), named
    ``chess`` as ``box_setup`` names it.  Returns the :class:`Scene`; its
    ``board_types`` holds each wall's spec, its ``info["box"]`` the setup's box.
    """
    if target not in ("charuco-box", "aprilgrid-box"):
        raise ValueError(f"coded_box_scene: target must be charuco-box or aprilgrid-box, got {target!r}")
    views = np.asarray(views, float)
    if views.ndim != 2 or views.shape[1] != 6 or len(views) < 1:
        raise ValueError(f"views must be an (n, 6) array with n >= 1, got shape {views.shape}")
    cam, mirror = rig.camera, rig.mirror
    dist = float(mirror.apex[2]) if mirror_distance_mm is None else float(mirror_distance_mm)
    setup, _ = box_setup(
        float(mirror.radius),
        float(mirror.height),
        rig.n_elements,
        target=target,
        mirror_distance_mm=dist,
        image_size=(cam.width, cam.height),
        chessboard=None,
        **box,
    )
    T_box = setup.extra["box"]["T_box_board"]
    walls = list(setup.boards)
    T_box_board = {b: Pose(jnp.asarray(T_box[b]["R"]), jnp.asarray(T_box[b]["t"])) for b in walls}
    box_poses = []
    for v in views:
        T_cam_box = Pose(so3_exp(jnp.asarray(v[:3])), jnp.asarray(v[3:])).inverse()
        box_poses.append({b: T_cam_box @ T_box_board[b] for b in walls})
    boards = {b: np.asarray(setup.boards[b].points, float) for b in walls}
    chess = grid_points(*chessboard[:2], chessboard[2])
    boards["chess"] = chess
    chess_poses = draw_chess_poses(cam, chess, n_chess_views, np.random.default_rng(11)) if n_chess_views else []
    info = {
        "preset": target,
        "box": setup.extra["box"],
        "chessboard": dict(zip(("cols", "rows", "square_mm"), chessboard, strict=True)),
    }
    types = {b: dict(setup.boards[b].target) for b in walls}
    return Scene(rig, boards, box_poses, "chess", chess_poses, 90, info, board_types=types)


@jax.jit
def _first_wall(cam, mirror, uv, walls_R, walls_t, body):
    """Per pixel: the reflected ray's first wall and its board-frame point, and whether it is seen
    (meets the mirror, misses the sensor's body, meets a wall)."""

    def one(p):
        o, d, _, seen = cata_ray(cam, mirror, p, body[0], body[1])
        w, hit, xy, _ = wall_hit(o, d, walls_R, walls_t)
        return w, xy, seen & hit

    return jax.vmap(one)(uv)


def _seen_on(
    scene: Scene, view: int, board: str, pts: np.ndarray, opts: RenderOptions
) -> tuple[np.ndarray, np.ndarray]:
    """Exact pixels of board points ``pts`` (N, 3) and whether each is seen there: its projection
    is valid and the pixel's reflected ray, traced back, meets this board's wall first within
    1e-3 mm of the point (not hidden by the sensor's body nor by another wall)."""
    rig = scene.rig
    pose = scene.box_poses[view][board]
    uv, ok = (np.asarray(a) for a in project_board_points(rig, pose, jnp.asarray(pts)))
    walls = list(scene.box_poses[view])
    rs = jnp.stack([scene.box_poses[view][b].R for b in walls])
    ts = jnp.stack([scene.box_poses[view][b].t for b in walls])
    body = jnp.asarray([opts.body_radius_mm, opts.body_gap_mm], dtype=float)
    w, xy, seen = (np.asarray(a) for a in _first_wall(rig.camera, rig.mirror, jnp.asarray(uv), rs, ts, body))
    same = (w == walls.index(board)) & (np.linalg.norm(xy - pts[:, :2], axis=1) < 1e-3)
    return uv, ok & seen & same


def neighbourhood(spec: dict) -> np.ndarray:
    """The board points (K, N, 3) whose sight makes each of a coded board's N points *visible*.

    ChArUco: its corner and the centres of the four squares around it (offsets ``(+-s/2, +-s/2)``),
    so the corner's four squares, and the markers in two of them, lie inside the mirror's view.
    AprilGrid: the four corners and the centre of the point's tag (its tag must be whole to be
    decoded).
    """
    from ..observations.targets import board_points

    pts = board_points(spec)
    if spec["type"] == "charuco":
        h = spec["square_mm"] / 2
        offs = np.array([[0, 0, 0], [-h, -h, 0], [h, -h, 0], [-h, h, 0], [h, h, 0]], float)
        return pts[None] + offs[:, None]
    tags = aprilgrid_tag_corners(spec["tag_cols"], spec["tag_rows"])
    tag_of = np.zeros(len(pts), int)
    for t, c in enumerate(tags):
        tag_of[c] = t
    corners = pts[tags[tag_of]]  # (N, 4, 3)
    return np.concatenate([corners, corners.mean(axis=1, keepdims=True)], axis=1).transpose(1, 0, 2)


def visible_corners(scene: Scene, view: int, opts: RenderOptions | None = None) -> dict[str, tuple]:
    """Each coded wall's exact corner pixels in view ``view`` and which are visible.

    Returns ``{board: (uv (N, 2) exact pixels, visible (N,) bool)}``.  A point is *visible* where
    it and every point of its :func:`neighbourhood` (its four squares' centres for a ChArUco
    corner; its tag's corners and centre for an AprilGrid corner) project through the mirror
    into the image (:func:`~slcvjax.geometry.rig.project_board_points` valid) and are seen there:
    the pixel's reflected ray, traced back, meets this board first (not the sensor's body, not
    another wall).  ``opts``: the body's size, as rendered.
    """
    opts = RenderOptions() if opts is None else opts
    out = {}
    for b, spec in scene.board_types.items():
        hood = neighbourhood(spec)
        k, n = hood.shape[:2]
        uv, seen = _seen_on(scene, view, b, hood.reshape(-1, 3), opts)
        out[b] = (uv.reshape(k, n, 2)[0], seen.reshape(k, n).all(axis=0))
    return out
