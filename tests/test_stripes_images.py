"""Line and ring lasers in images: rendered stripes, their detected centre lines against the
simulator's exact curves, their labels and boards, and the setup's laser kinds."""

import json
import os
from pathlib import Path

import numpy as np
import pytest

from slcvjax.calibration.staged import assign_spot_boards
from slcvjax.images.detect import (
    DOT_SUPPORT,
    ImageDetection,
    MirrorDisc,
    Setup,
    detect_folder,
    find_mirror,
    label_stripes,
    read_setup,
    setup_to_json,
    wall_level,
)
from slcvjax.images.render import Renderer, RenderOptions, render_scene, scene_sheets
from slcvjax.images.stripes import StripeSamples, find_stripes
from slcvjax.observations.formats import FormatError, StripeObs
from slcvjax.observations.simulate import (
    box_scene,
    paper_rig,
    paper_views,
    sheet_rig,
    simulate,
    visible_spots,
    visible_stripes,
)


def polyline_distance(p: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """(M,) distance of each point (M, 2) to a polyline (K, 2)."""
    a, b = poly[:-1], poly[1:]
    ab = b - a
    t = np.clip(np.einsum("mkj,kj->mk", p[:, None] - a[None], ab) / (ab * ab).sum(-1), 0.0, 1.0)
    return np.linalg.norm(p[:, None] - (a[None] + t[..., None] * ab[None]), axis=2).min(axis=1)


def scene(kinds, n_views=2, n_chess=2, step_deg=0.5, seed=11):
    rig, fans = sheet_rig(paper_rig(), kinds, seed=seed)
    sc = box_scene(rig, paper_views(n_views), n_chess_views=n_chess)
    sc.fans, sc.stripe_step_deg = fans, step_deg
    return sc


def exact_distances(sc, view: int, pixels: np.ndarray) -> np.ndarray:
    """Each pixel's distance to the nearest exact stripe curve of the view (dense polylines, every
    0.05 deg of each fan: chords sag by under 1e-4 px)."""
    polys = [uv for *_, uv in visible_stripes(sc, view)]
    return np.min([polyline_distance(pixels, p) for p in polys], axis=0)


@pytest.mark.parametrize("kinds", [("cone", "point", "point", "point", "point"), ("plane", "plane", "plane")])
def test_noise_free_stripe_centres_lie_on_the_exact_curve(kinds):
    """Rendered without sensor noise, the detected centre-line samples lie within 0.02 px RMS of
    the exact curve (the goal), none off by more than 0.06 px, about one per pixel along it."""
    sc = scene(kinds, n_views=2, step_deg=0.05)
    rig = sc.rig
    r = Renderer(rig.camera, rig.mirror, RenderOptions(noise=0.0))
    walls = [b for b in sc.boards if b != sc.chess_board]
    sheets, fans = scene_sheets(sc)
    for v in range(2):
        spots = [(w, x) for _, w, x, _ in visible_spots(sc, v)]
        img = r.catadioptric({b: sc.box_poses[v][b] for b in walls}, sc.boards, spots, v, sheets, fans)
        disc = find_mirror(img[:, :, 1].astype(float))
        green = img[:, :, 1].astype(float)
        wall = wall_level(green, disc)
        dotted = (wall - green > DOT_SUPPORT * (wall - disc.outside_level)) & disc.mask
        st = find_stripes(img, disc.mask, dotted)
        d = exact_distances(sc, v, st.pixels)
        length = sum(np.sum(np.linalg.norm(np.diff(uv, axis=0), axis=1)) for *_, uv in visible_stripes(sc, v))
        assert np.sqrt(np.mean(d**2)) < 0.02, (kinds, v, np.sqrt(np.mean(d**2)))
        assert d.max() < 0.06, (kinds, v, d.max())
        assert 0.5 * length < len(d) < 1.5 * length, (len(d), length)


def test_rendered_ring_detected_labelled_and_on_boards(tmp_path):
    """A rendered box scene of a ring laser and point lasers: every detected stripe sample is
    the ring's, within 0.1 px of the exact curve (sensor noise of 1 grey level), its board is
    the wall whose plane its exact point lies on (or null near a corner), the spots are still
    found apart from the stripe, and the report lists what was left out."""
    sc = scene(("cone", "point", "point", "point", "point"), n_views=2, n_chess=2)
    render_scene(sc, tmp_path, RenderOptions(noise=1.0, seed=3))
    setup = read_setup(tmp_path / "setup.json")
    assert setup.laser_kinds == ["cone", "point", "point", "point", "point"]
    assert setup.laser_azimuth_deg[0] is None
    obs, report = detect_folder(tmp_path)
    assert obs.laser_kinds == ("cone", "point", "point", "point", "point")
    dense = scene(("cone", "point", "point", "point", "point"), n_views=2, n_chess=2, step_deg=0.05)
    exact, _ = simulate(sc)
    for v, view in enumerate(obs.views):
        assert {s.laser for s in view.stripes} == {0}
        px = np.concatenate([s.pixels for s in view.stripes])
        d = exact_distances(dense, v, px)
        assert len(px) > 500 and np.sqrt(np.mean(d**2)) < 0.05 and d.max() < 0.2, (len(px), d.max())
        # each stripe's board: the wall whose exact curve it follows
        curves = {w: uv for _, w, _, uv in visible_stripes(dense, v)}
        for s in view.stripes:
            if s.board is None:
                continue
            own = polyline_distance(s.pixels, curves[s.board])
            assert np.all(own < 0.3), (v, s.board, own.max())
        # the point lasers' spots, all visible ones found, at their exact pixels
        found = {s.laser: s.pixel for s in view.spots}
        assert set(found) == {s.laser for s in exact.views[v].spots}
        for s in exact.views[v].spots:
            assert np.linalg.norm(found[s.laser] - s.pixel) < 0.5
        assert report.counts[view.name]["stripe samples"] == len(px)
    assert "stripe samples left out" in report.summary()


def test_stripes_without_a_board_split_onto_the_first_plane_their_rays_meet():
    """The calibration's board assignment for stripes that name none, at the true poses: each
    exact sample goes back to the wall the simulator put it on."""
    sc = scene(("cone", "point", "point", "point", "point"), n_views=2)
    exact, truth = simulate(sc)
    import dataclasses

    opened = dataclasses.replace(
        exact,
        views=[
            dataclasses.replace(v, stripes=[StripeObs(0, None, np.concatenate([s.pixels for s in v.stripes]))])
            for v in exact.views
        ],
    )
    got, _ = assign_spot_boards(opened, truth.rig.camera, truth.rig.mirror, truth.board_poses)
    for ve, vg in zip(exact.views, got.views, strict=True):
        want = {s.board: len(s.pixels) for s in ve.stripes}
        have = {s.board: len(s.pixels) for s in vg.stripes}
        assert have == want
        for s in vg.stripes:
            ref = next(x for x in ve.stripes if x.board == s.board)
            assert np.allclose(np.sort(s.pixels, axis=0), np.sort(ref.pixels, axis=0))


def _det(px: np.ndarray) -> ImageDetection:
    disc = MirrorDisc(np.zeros(2), (100.0, 100.0), 0.0, np.ones((1, 1), bool), 200.0, 30.0)
    st = StripeSamples(px, np.tile([1.0, 0.0], (len(px), 1)), np.ones(len(px)), np.ones(len(px)),
                       np.zeros(len(px), int), {})  # fmt: skip
    return ImageDetection("v", disc, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 2)), stripes=st)


def _setup(kinds, az):
    return Setup((640, 480), 20.0, 10.0, len(kinds), {}, ["v.png"], [], az, laser_kinds=list(kinds))


def test_line_lasers_labelled_by_azimuth_and_a_ring_with_lines_left_out():
    """Samples at image azimuths 10, 130, 250 deg (and one at 70: between two lasers' azimuths
    0 and 120 within half their spacing of neither... 70 is 50 from 120, so it is labelled)."""
    ang = np.radians([10.0, 11.0, 130.0, 250.0, 251.0, 60.0])
    px = 80 * np.column_stack([np.cos(ang), np.sin(ang)])
    st, probs = label_stripes([_det(px)], _setup(["plane", "point", "plane", "plane"], [0.0, 45.0, 120.0, 240.0]),
                              [{}])  # fmt: skip
    got = {s.laser: len(s.pixels) for s in st[0]}
    assert got == {0: 2, 2: 1, 3: 2}
    assert any("match no line laser's azimuth" in p for p in probs[0])  # 60 deg: half-way
    st, probs = label_stripes([_det(px)], _setup(["cone", "plane"], [None, 0.0]), [{}])
    assert st[0] == [] and any("cannot be told" in p for p in probs[0])
    st, _ = label_stripes([_det(px)], _setup(["point", "cone"], [30.0, None]), [{}])
    assert [(s.laser, s.board, len(s.pixels)) for s in st[0]] == [(1, None, 6)]


def test_setup_laser_kinds_round_trip_and_errors(tmp_path):
    sc = scene(("cone", "point", "point", "point", "point"), n_views=1, n_chess=1)
    from slcvjax.images.render import scene_setup

    setup = scene_setup(sc, ["view00.png"], [])
    doc = setup_to_json(setup)
    assert doc["laser_kinds"] == ["cone", "point", "point", "point", "point"]
    assert doc["laser_azimuth_deg"][0] is None and all(isinstance(a, float) for a in doc["laser_azimuth_deg"][1:])
    path = tmp_path / "setup.json"
    path.write_text(json.dumps(doc))
    back = read_setup(path)
    assert back.laser_kinds == setup.laser_kinds and back.laser_azimuth_deg == setup.laser_azimuth_deg
    for field, value, msg in [
        ("laser_kinds", ["cone", "point"], "laser_kinds"),
        ("laser_kinds", ["ring", "point", "point", "point", "point"], "laser_kinds[0]"),
        ("laser_azimuth_deg", [None, None, 1.0, 2.0, 3.0], "laser_azimuth_deg[1]"),
        ("stripe_sigma_mm", -1.0, "stripe_sigma_mm"),
    ]:
        path.write_text(json.dumps({**doc, field: value}))
        with pytest.raises(FormatError, match=msg.replace("[", r"\[").replace("]", r"\]")):
            read_setup(path)


REAL = Path(os.environ.get("SLCVJAX_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
REAL = REAL / "omni_laser_zhang_uncalibrated"
# counted by hand from the images: where the red line lies (u0, v0, u1, v1, px), and the floor
# mat's printed grid with its blocks in these frames (u0, v0, u1, v1)
LINE_BOXES = {
    "real_00_0.jpg": [(840, 205, 935, 245)],
    "real_04_test1_original.jpg": [(790, 135, 880, 170)],
    "real_07_test4_original.jpg": [(785, 135, 875, 170)],
    "real_08_supplement1_original.jpg": [(725, 130, 1105, 225)],
    "real_11_supplement4_original.jpg": [(855, 190, 950, 225)],
}
NO_LINE_FOUND = ["real_05_test2_original.jpg", "real_06_test3_original.jpg"]  # missed (see the docstring)
MAT = (700, 20, 1250, 300)


@pytest.mark.skipif(not REAL.is_dir(), reason="../shared/data/omni_laser_zhang_uncalibrated is absent")
@pytest.mark.parametrize("name", sorted(LINE_BOXES) + NO_LINE_FOUND)
def test_real_frames_red_line_found_and_nothing_on_the_mat(name):
    """Real 1920x1080 frames with a red line laser (used from ../shared/data only): the detector
    runs, finds the line where it crosses the blocks (frames 00, 04, 07, 08, 11: a piece in each
    hand-counted box), and nothing else on the floor's printed grid or its coloured blocks.
    Frames 05 (the line faint on a black block, red 47 of 255) and 06 (on a white block, 32 grey
    levels above it) are missed at these thresholds; they are checked for no false stripe only."""
    import cv2

    from slcvjax.images.stripes import find_red_stripes

    img = cv2.imread(str(REAL / name))
    disc = find_mirror(img[:, :, 1].astype(float))
    st = find_red_stripes(img, disc.mask)
    u, v = st.pixels[:, 0], st.pixels[:, 1]
    on_mat = (u >= MAT[0]) & (u <= MAT[2]) & (v >= MAT[1]) & (v <= MAT[3])
    boxes = LINE_BOXES.get(name, [])
    in_box = np.zeros(len(u), bool)
    for u0, v0, u1, v1 in boxes:
        here = (u >= u0) & (u <= u1) & (v >= v0) & (v <= v1)
        assert here.sum() >= 25, (name, int(here.sum()))
        in_box |= here
    assert not np.any(on_mat & ~in_box), (name, st.pixels[on_mat & ~in_box][:5])
