"""Scenes of a rig no test or benchmark tunes to: what a new user's data looks like to the code.

An 800x600 camera (another focal length, principal point and distortion than the preset's),
a cone mirror of another size, offset and tilt, eight point lasers on another ring with their
own mounting errors, in a box of another width; each scene moves the sensor to poses of its
own seed, so its numbers of dots, spots, rim pixels and poses are its own.  Used by
``bench_compile.py`` (the command-line rows) and ``bench_throughput.py``.
"""

import numpy as np

from slcvjax.geometry.camera import Camera
from slcvjax.geometry.lasers import Lasers
from slcvjax.geometry.mirror import ConeMirror
from slcvjax.geometry.rig import Rig
from slcvjax.observations.simulate import PAPER_ROTATION_DEG, PAPER_TRANSLATION_MM, box_scene

HALF_WIDTH_MM = 150.0


def user_rig(n_lasers: int = 8) -> Rig:
    """The other rig: 800x600 camera, a 22 mm x 11 mm cone 52 mm out, ``n_lasers`` point lasers."""
    camera = Camera.create(690.4, 689.1, 405.3, 287.6, [-0.24, 0.07, -0.0009, 0.0011, -0.006], 800, 600)
    mirror = ConeMirror.create([-0.5, 0.7, 52.0], [-0.018, 0.022, 1.0], 22.0, 11.0)
    rng = np.random.default_rng(4242)
    pts, dirs = [], []
    for i in range(n_lasers):
        az = 2 * np.pi * (i + 0.3) / n_lasers + np.radians(rng.uniform(-4, 4))
        ring, z = 33.0 + rng.uniform(-1, 1), 6.0 + rng.uniform(-1, 1)
        aim = az + np.radians(rng.uniform(-3, 3))
        elev = -np.arcsin(rng.uniform(0.005, 0.05))
        pts.append([ring * np.cos(az), ring * np.sin(az), z])
        dirs.append([np.cos(elev) * np.cos(aim), np.cos(elev) * np.sin(aim), np.sin(elev)])
    return Rig(camera, mirror, Lasers.create(np.array(pts), np.array(dirs)))


def user_scene(n_views: int, seed: int, n_lasers: int = 8):
    """The other rig at ``n_views`` sensor poses drawn from ``seed`` (view 0 the box frame)."""
    rng = np.random.default_rng(seed)
    views = np.zeros((n_views, 6))
    views[1:, :3] = np.radians(rng.uniform(-1, 1, (n_views - 1, 3)) * np.asarray(PAPER_ROTATION_DEG))
    views[1:, 3:] = rng.uniform(-1, 1, (n_views - 1, 3)) * np.asarray(PAPER_TRANSLATION_MM)
    return box_scene(user_rig(n_lasers), views, HALF_WIDTH_MM, n_chess_views=10)


def write_scenes(folder, views, seed0: int = 500, noise: float = 0.3) -> list:
    """Simulate one scene per entry of ``views`` (its view count), seeds from ``seed0``; write each as an
    observation file in ``folder``; return the paths."""
    from pathlib import Path

    from slcvjax import simulate, write_observations

    out = []
    for i, n_v in enumerate(views):
        obs, _ = simulate(user_scene(n_v, seed0 + i), noise=noise, seed=seed0 + i)
        path = Path(folder) / f"user{i:02d}_{n_v}views.json"
        write_observations(path, obs)
        out.append(path)
    return out
