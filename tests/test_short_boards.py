"""A board whose dots mostly miss the staged mirror is left out of the calibration, with a note,
instead of refusing the whole calibration."""

import copy

import numpy as np

import slcvjax as sj
from slcvjax.calibration.staged import without_boards


def test_a_board_with_three_dots_on_the_mirror_is_left_out_with_a_note():
    obs, truth = sj.simulate(sj.make_scene("paper", n_lasers=3, n_views=5), noise=0.3, seed=4)
    bad = copy.deepcopy(obs)
    name = sorted(bad.views[2].boards)[0]
    px, seen = bad.views[2].boards[name]
    keep = np.flatnonzero(seen)[:3]
    px = px.copy()
    px[np.setdiff1d(np.flatnonzero(seen), keep)] = [1.0, 1.0]  # the image's corner: off the mirror
    bad.views[2].boards[name] = (px, seen)
    res = sj.calibrate(bad)
    notes = next(r for r in res.staged.reports if r.name == "board_poses").notes
    assert any(f"views[2].boards.{name}" in n and "left out" in n for n in notes), notes
    assert (2, name) not in [tuple(k) for k in res.packed.pose_keys]
    b = sj.cramer_rao(truth, obs, 0.3)
    pos, ang = sj.laser_errors(res.rig, truth.rig, b["x_ref"])
    assert np.all(pos < 4 * b["position_std_mm"]) and np.all(ang < 4 * b["direction_std_rad"])


def test_without_boards_drops_the_dots_and_frees_the_spots_on_them():
    obs, _ = sj.simulate(sj.make_scene("paper", n_lasers=3, n_views=2), noise=0.0, seed=0)
    view = obs.views[1]
    name = next(s.board for s in view.spots if s.board is not None)
    out = without_boards(obs, {(1, name)})
    assert name not in out.views[1].boards and name in out.views[0].boards
    assert all(s.board != name for s in out.views[1].spots)
    assert sum(s.board is None for s in out.views[1].spots) == sum(s.board == name for s in view.spots)
    assert obs.views[1].boards.keys() == view.boards.keys()  # the input is left as it was
