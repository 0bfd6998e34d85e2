"""The detector on images it was not tuned to: an independent tracer's held-out rigs (tests/_tracer.py).

The tracer shares no rendering code with :mod:`slcvjax.images.render`; the truth is the library's
exact projection of each dot and spot, checked against the tracer's own rays. Goals at 1 grey
level of noise: the rim found in every view, at least 65 % of the visible dots placed, none on a
wrong grid position, no spot with another laser's label, and whatever is not placed reported.
"""

from dataclasses import replace

import pytest

from slcvjax.images.detect import detect_folder

from ._tracer import HeldOutRig, goals, measure, render_folder

# the held-out rig (800x600, 22 x 13 mm cone, 8 lasers, 4x3 grids at 18 mm pitch, 2.5 mm dots, a 170 mm
# closed box, the sensor moved +-35 mm, saturated spots, 1 grey level of noise) at 0.8 of its resolution (640x480)
SMALL = HeldOutRig(scale=0.8, n_views=5, n_chess=1, seed=11)


def _check(rig: HeldOutRig, folder, dots_goal: bool = True) -> dict:
    truth = render_folder(rig, folder)
    obs, report = detect_folder(folder)
    m = measure(obs, report, truth)
    met = goals(m)
    if not dots_goal:
        met.pop("dots_65pct")
    assert met == {k: True for k in met}, {k: v for k, v in m.items() if k != "per_view"}
    assert m["lasers_never_found"] == []
    assert len(obs.calibration_views) == rig.n_chess  # the direct chessboard views
    for v in m["per_view"]:  # what is not placed is reported
        if v["dots_placed"] < v["dots_visible"] or v["spots_right"] < v["spots_visible"]:
            assert report.problems.get(v["name"]), v
    return m


def test_held_out_rig_at_reduced_resolution(tmp_path):
    m = _check(SMALL, tmp_path)
    assert m["dots_visible"] >= 150  # the scene shows its grids (measured 196)


def test_held_out_rig_with_open_corners_finds_the_rim(tmp_path):
    """Dark wedges through the box's open corners cut the mirror's view into pieces up to the rim."""
    _check(replace(SMALL, open_corner_mm=14.0, n_views=3, seed=12), tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize(
    "rig",
    [
        HeldOutRig(n_views=8, n_chess=2),
        HeldOutRig(n_views=6, n_chess=1, dot_radius_mm=2.0, pitch_mm=14.0, seed=1),
        HeldOutRig(n_views=6, n_chess=1, wall=0.33, dot=0.04, surround=0.03, spot_peak=0.45, seed=2),
        HeldOutRig(n_views=6, n_chess=1, dot_radius_mm=0.9, shading=0.25, blur_px=0.8, seed=4),
    ],
    ids=["heldout", "big_dots_fine_pitch", "dim_unsaturated", "small_dots_uneven"],
)
def test_held_out_rigs_at_full_resolution(tmp_path, rig):
    _check(rig, tmp_path)


@pytest.mark.slow
def test_held_out_rig_with_open_corners_at_full_resolution(tmp_path):
    """The rim in every view, no dot a row or column off, no spot mislabelled; the share of dots
    placed is short of the goal here: the sensor's poses leave many targets with two rows in view
    whose missing row could lie on either side (beyond the rim or past the apex), which one image
    cannot tell; they are left out and reported (``ambiguous rows``) for the calibration to place
    by the box (benchmarks/detection_robustness.py, 8 views: 54 % placed)."""
    m = _check(HeldOutRig(n_views=6, n_chess=1, open_corner_mm=14.0, seed=3), tmp_path, dots_goal=False)
    if m["dots_placed_fraction"] < 0.65:
        pytest.xfail(f"{100 * m['dots_placed_fraction']:.0f} % of the visible dots placed (goal 65 %)")
