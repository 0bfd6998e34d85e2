"""A simulated rig of one's own sizes in the box of coded targets ``slcvjax setup init`` lays out for it.

``slcvjax simulate --target charuco-box --render`` uses this so that a user without hardware, and the
tutorial's test, get images like their own rig's: :func:`sized_rig` is the reference rig (the paper's
camera, cone and lasers) resized to another image, mirror and laser count, and
:func:`render_own_box` renders it in the box of ``setup init``'s ``setup.json`` and writes that
same ``setup.json`` beside the images, with the images listed (what ``slcvjax setup images``
writes), so nothing in it comes from the simulation's truth.
"""

import numpy as np

from ..geometry.camera import Camera
from ..geometry.lasers import Lasers
from ..geometry.mirror import ConeMirror
from ..geometry.rig import Rig
from ..observations.simulate import paper_camera, paper_rig

# the reference rig's cone (radius, height, apex distance in front of the lens, mm)
PAPER_CONE = (20.0, 10.0, 48.0)


def sized_rig(
    image_size: tuple[int, int] = (640, 480),
    mirror_radius: float = PAPER_CONE[0],
    mirror_height: float = PAPER_CONE[1],
    mirror_distance: float = PAPER_CONE[2],
    n_lasers: int = 10,
    laser_tilt_deg: float = 0.0,
) -> Rig:
    """The reference rig resized: an image of ``image_size`` (width, height px), a cone of
    ``mirror_radius`` and ``mirror_height`` with its apex ``mirror_distance`` mm in front of the
    lens, and ``n_lasers`` point lasers.  With the defaults it is :func:`paper_rig` exactly.

    The focal length is chosen so that the rim's image fills the same fraction of the image's
    half height as the reference rig's (``f = 0.793 (H / 2) (distance + height) / radius``); the
    principal point keeps the reference's offset from the image centre in proportion, the
    distortion its coefficients (they act on normalised coordinates).  The mirror keeps the
    reference's small offset and tilt; the lasers are :func:`paper_rig`'s with their ring scaled by
    ``mirror_radius / 20`` (their emitters 1.5 radii from the axis, beams nearly across it), each
    beam then turned ``laser_tilt_deg`` towards the camera (about its own horizontal, so that its
    spots fall nearer the camera than the lens, e.g. below a box's printed targets).
    """
    w, h = (int(v) for v in image_size)
    r0, h0, d0 = PAPER_CONE
    if min(w, h) < 16 or mirror_radius <= 0 or mirror_height <= 0 or mirror_distance <= 0:
        raise ValueError(f"sized_rig: bad sizes {image_size}, {mirror_radius}, {mirror_height}, {mirror_distance}")
    ref = paper_camera()
    fill = float(ref.fx) * r0 / (d0 + h0) / (ref.height / 2)  # the rim's radius over the half height
    fx = fill * (h / 2) * (mirror_distance + mirror_height) / mirror_radius
    fy = fx * float(ref.fy) / float(ref.fx)
    cx = (w - 1) / 2 + (float(ref.cx) - (ref.width - 1) / 2) * h / ref.height
    cy = (h - 1) / 2 + (float(ref.cy) - (ref.height - 1) / 2) * h / ref.height
    paper = paper_rig(n_lasers)
    if (w, h, mirror_radius, mirror_height, mirror_distance, laser_tilt_deg) == (ref.width, ref.height, r0, h0, d0, 0):
        return paper
    cam = Camera.create(fx, fy, cx, cy, np.asarray(ref.dist), w, h)
    m = paper.mirror
    apex = np.asarray(m.apex) + np.array([0.0, 0.0, mirror_distance - d0])
    mirror = ConeMirror.create(apex, np.asarray(m.axis), mirror_radius, mirror_height)
    pts = np.asarray(paper.lasers.points) * np.array([mirror_radius / r0, mirror_radius / r0, 1.0])
    d = np.asarray(paper.lasers.directions)
    radial = np.linalg.norm(d[:, :2], axis=1)
    elev = np.arctan2(d[:, 2], radial) - np.radians(laser_tilt_deg)
    d = np.concatenate([d[:, :2] / radial[:, None] * np.cos(elev)[:, None], np.sin(elev)[:, None]], axis=1)
    return Rig(cam, mirror, Lasers.create(pts, d))


def render_own_box(scene, setup, out_dir, opts, progress: bool = False) -> list[str]:
    """Render ``scene`` (:func:`slcvjax.images.coded_box.coded_box_scene` of ``setup``'s box) into
    ``out_dir`` and write ``setup`` there with the images listed; returns the image names.

    The ``setup.json`` is ``setup`` (``slcvjax setup init``'s) with ``views`` and
    ``chessboard_views`` filled in, as ``slcvjax setup images`` fills them: the simulator's own
    knowledge (the walls' azimuths seen in view 0, the spots' size) is not in it.
    """
    from pathlib import Path

    from ..observations.formats import write_json_atomic
    from .detect import setup_to_json
    from .render import render_scene
    from .targetbox import with_images

    files = render_scene(scene, out_dir, opts, progress=progress)
    views = [f for f in files if f.startswith("view")]
    direct = [f for f in files if f.startswith("chess")]
    write_json_atomic(Path(out_dir) / "setup.json", setup_to_json(with_images(setup, views, direct)))
    return files
