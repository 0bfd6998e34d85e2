"""The renderer's shortcuts: the mirror's own edges (its rim, the body's reflection), traced once
per rig, give the image that tracing every edge cell anew in each view gives; shading only the
samples that see past the mirror gives the image that shading every sample gives; a direct view's
edge cells, their undistortion linearised at each cell's centre, give the image of every sample's
own ray."""

import jax
import numpy as np
import pytest

import slcvjax.images.render as render
from slcvjax.geometry.camera import Camera, pixel_to_ray
from slcvjax.images.render import Renderer, RenderOptions
from slcvjax.observations.simulate import make_scene, visible_spots


@pytest.mark.slow
def test_the_mirrors_edges_traced_once_give_the_image_traced_in_the_view():
    scene = make_scene("paper", n_lasers=6, n_views=4)
    rig = scene.rig
    walls = [b for b in scene.boards if b != scene.chess_board]
    renderer = Renderer(rig.camera, rig.mirror, RenderOptions(noise=0.0))
    ys, _, _ = renderer._mirror_edges
    assert len(ys) > 5000  # the rim's and the body's edge cells of a 640x480 image at 3x3 cells
    view = ({b: scene.box_poses[2][b] for b in walls}, scene.boards, [(w, x) for _, w, x, _ in visible_spots(scene, 2)])
    pipe = (np.array([0.0, 0.0, 60.0]), np.array([0.0, 0.0, 1.0]), 75.0, np.zeros((0, 3)))
    cached = renderer.catadioptric(*view), renderer.pipe(*pipe)
    assert 0.2 < len(renderer._seen) / renderer._unseen.shape[0] < 0.5  # the samples shaded
    packed = renderer._seen, renderer._seen_rays
    renderer._seen, renderer._seen_rays = np.arange(renderer._unseen.shape[0]), renderer._rays  # every sample
    for a, b in zip(cached, (renderer.catadioptric(*view), renderer.pipe(*pipe)), strict=True):
        np.testing.assert_array_equal(a, b)
    renderer._seen, renderer._seen_rays = packed
    renderer._mirror_edges = None  # every edge cell traced in the view
    traced = renderer.catadioptric(*view), renderer.pipe(*pipe)
    for a, b in zip(cached, traced, strict=True):
        diff = np.abs(a.astype(int) - b.astype(int))
        assert diff.max() <= 1 and np.count_nonzero(diff) <= 10, (diff.max(), np.count_nonzero(diff))


@jax.jit
def _every_sample_ray(cam, centres, offsets, R, t, grid):
    """The edge cells' means with each sample's own ray (a Newton undistortion per sample)."""

    def f(uv):
        return render.chess_sample(*pixel_to_ray(cam, uv), R, t, grid[0], grid[1], grid[2])

    return jax.vmap(jax.vmap(f))(centres[:, None, :] + offsets[None]).mean(axis=1)


def test_a_direct_view_with_the_undistortion_linearised_per_cell_is_the_exact_one(monkeypatch):
    # a camera of stronger distortion and wider view than the preset's, so the board reaches far out
    cam = Camera.create(300.0, 305.0, 322.0, 236.0, [-0.36, 0.14, 0.002, -0.0015, -0.02], 640, 480)
    scene = make_scene("paper", n_views=2)
    cols, rows = render.grid_shape(scene.boards[scene.chess_board])
    square = float(scene.boards[scene.chess_board][1, 0] - scene.boards[scene.chess_board][0, 0])
    renderer = Renderer(cam, None, RenderOptions(noise=0.0))
    poses = scene.chess_poses[:2]
    linearised = [renderer.chessboard(pose, cols, rows, square) for pose in poses]
    monkeypatch.setattr(render, "_chess_fine", _every_sample_ray)
    for a, pose in zip(linearised, poses, strict=True):
        b = renderer.chessboard(pose, cols, rows, square)
        assert np.count_nonzero((a < 60) != (b < 60)) == 0  # the same squares, where they are
        diff = np.abs(a.astype(int) - b.astype(int))
        assert diff.max() <= 1 and np.count_nonzero(diff) <= 100, (diff.max(), np.count_nonzero(diff))
