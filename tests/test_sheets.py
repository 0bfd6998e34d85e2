"""Sheets of light (line and ring lasers) against closed forms."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slcvjax.geometry.pose import Pose, so3_exp
from slcvjax.geometry.sheets import Sheets, ray_meets_sheet, sheet_on_board, sheet_value


def board_pose(normal_tilt_deg: float, z: float) -> Pose:
    """A board whose plane is ``z`` mm along the camera's z, tilted about x."""
    R = np.asarray(so3_exp(jnp.array([np.deg2rad(normal_tilt_deg), 0.0, 0.0])))
    return Pose(jnp.asarray(R), jnp.array([0.0, 0.0, z]))


@pytest.mark.parametrize("theta_deg", [20.0, 45.0, 70.0])
def test_cone_meets_a_plane_across_its_axis_in_a_circle(theta_deg):
    h = 80.0
    s = Sheets.create(["cone"], [[0.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]], [np.deg2rad(theta_deg)])
    x, ok = sheet_on_board(s, 0, board_pose(0.0, h), jnp.linspace(0, 2 * np.pi, 50))
    assert np.all(ok)
    r = np.linalg.norm(np.asarray(x)[:, :2], axis=1)
    np.testing.assert_allclose(r, h * np.tan(np.deg2rad(theta_deg)), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(x)[:, 2], h, atol=1e-12)


@pytest.mark.parametrize(("theta_deg", "tilt_deg"), [(30.0, 20.0), (40.0, 35.0), (25.0, 10.0)])
def test_cone_meets_a_tilted_plane_in_an_ellipse_of_dandelins_eccentricity(theta_deg, tilt_deg):
    """A cone of half-angle theta cut by a plane at the angle beta to its axis is a conic of
    eccentricity cos(beta) / cos(theta) (Dandelin spheres)."""
    th, beta = np.deg2rad(theta_deg), np.deg2rad(90.0 - tilt_deg)
    apex, axis = np.array([3.0, -2.0, 1.0]), np.array([0.0, 0.0, 1.0])
    s = Sheets.create(["cone"], [apex], [axis], [th])
    pose = board_pose(tilt_deg, 100.0)
    x, ok = sheet_on_board(s, 0, pose, jnp.linspace(0, 2 * np.pi, 400, endpoint=False))
    x = np.asarray(x)[np.asarray(ok)]
    assert len(x) == 400  # an ellipse: every ray of the cone meets the plane
    # on both surfaces
    g = jax.vmap(lambda p: sheet_value(p, jnp.asarray(apex), jnp.asarray(axis), th))(jnp.asarray(x))
    np.testing.assert_allclose(np.asarray(g), 0.0, atol=1e-9)
    R, t = np.asarray(pose.R), np.asarray(pose.t)
    local = (x - t) @ R  # board frame
    np.testing.assert_allclose(local[:, 2], 0.0, atol=1e-9)
    # the ellipse's axes from its second moments over the boundary are not its axes; fit the conic
    u, v = local[:, 0], local[:, 1]
    A = np.stack([u * u, u * v, v * v, u, v, np.ones_like(u)], axis=1)
    coef = np.linalg.svd(A)[2][-1]
    a, b, c = coef[0], coef[1] / 2, coef[2]
    lam = np.linalg.eigvalsh(np.array([[a, b], [b, c]]))
    lam = lam if lam[0] * lam[1] > 0 else -lam
    lam = np.sort(np.abs(lam))  # 1/semi-axis^2 up to one common factor
    ecc = np.sqrt(1.0 - lam[0] / lam[1])
    np.testing.assert_allclose(ecc, np.cos(beta) / np.cos(th), rtol=1e-7)


def test_plane_meets_a_board_in_a_line_through_both_planes():
    s = Sheets.create(["plane"], [[5.0, 0.0, 0.0]], [[1.0, 0.2, 0.1]])
    pose = board_pose(25.0, 120.0)
    x, ok = sheet_on_board(s, 0, pose, jnp.linspace(-1.0, 1.0, 30))
    x = np.asarray(x)[np.asarray(ok)]
    n = np.array([1.0, 0.2, 0.1]) / np.linalg.norm([1.0, 0.2, 0.1])
    np.testing.assert_allclose((x - [5.0, 0.0, 0.0]) @ n, 0.0, atol=1e-9)
    np.testing.assert_allclose((x - np.asarray(pose.t)) @ np.asarray(pose.R)[:, 2], 0.0, atol=1e-9)
    # collinear: rank one about their mean
    sv = np.linalg.svd(x - x.mean(axis=0), compute_uv=False)
    assert sv[1] < 1e-9 * sv[0]


@pytest.mark.parametrize("theta_deg", [30.0, 60.0, 110.0])
def test_a_ray_from_inside_meets_the_cone_where_it_was_aimed(theta_deg):
    th = np.deg2rad(theta_deg)
    apex, axis = np.array([1.0, 2.0, -3.0]), np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
    s = Sheets.create(["cone"], [apex], [axis], [th])
    e1 = np.cross(axis, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    rng = np.random.default_rng(3)
    for _ in range(20):
        phi, dist = rng.uniform(0, 2 * np.pi), rng.uniform(20, 200)
        target = apex + dist * (np.cos(th) * axis + np.sin(th) * (np.cos(phi) * e1 + np.sin(phi) * e2))
        origin = apex + np.sign(np.cos(th)) * rng.uniform(1, 10) * axis  # inside the nappe
        d = (target - origin) / np.linalg.norm(target - origin)
        lam, x, ok = ray_meets_sheet(jnp.asarray(origin), jnp.asarray(d), s.apex[0], s.axis[0], s.half_angle[0], True)
        assert bool(ok)
        np.testing.assert_allclose(float(lam), np.linalg.norm(target - origin), rtol=1e-10)
        np.testing.assert_allclose(np.asarray(x), target, atol=1e-8)


def test_a_ray_meets_a_plane_in_closed_form_and_misses_when_parallel():
    p, n = np.array([0.0, 0.0, 50.0]), np.array([0.0, 0.0, 1.0])
    s = Sheets.create(["plane"], [p], [n])
    o, d = np.array([1.0, 2.0, 0.0]), np.array([0.1, 0.0, 1.0]) / np.linalg.norm([0.1, 0.0, 1.0])
    lam, x, ok = ray_meets_sheet(jnp.asarray(o), jnp.asarray(d), s.apex[0], s.axis[0], s.half_angle[0], False)
    assert bool(ok)
    np.testing.assert_allclose(float(lam), 50.0 / d[2], rtol=1e-12)
    _, _, ok = ray_meets_sheet(jnp.asarray(o), jnp.array([1.0, 0.0, 0.0]), s.apex[0], s.axis[0], s.half_angle[0], False)
    assert not bool(ok)
    # behind the origin: not forward
    _, _, ok = ray_meets_sheet(jnp.asarray(o), -jnp.asarray(d), s.apex[0], s.axis[0], s.half_angle[0], False, True)
    assert not bool(ok)


def test_retract_moves_each_kind_by_its_own_columns():
    s = Sheets.create(
        ["plane", "cone", "plane"],
        [[0.0, 0.0, 10.0], [1.0, 1.0, 1.0], [0.0, 5.0, 0.0]],
        [[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]],
        [0.0, 0.5, 0.0],
    )
    assert s.dofs == (3, 6, 3)
    same = s.retract(jnp.zeros(12))
    for a, b in zip(jax.tree_util.tree_leaves(s), jax.tree_util.tree_leaves(same), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-15)
    delta = jnp.asarray([2.0, 0.0, 0.0] + [0.0, 0.0, 3.0, 0.0, 0.0, 0.1] + [0.0, 0.0, 0.0])
    moved = s.retract(delta)
    np.testing.assert_allclose(np.asarray(moved.apex[0]), [0.0, 0.0, 12.0])  # along the normal
    np.testing.assert_allclose(np.asarray(moved.apex[1]), [1.0, 1.0, 4.0])  # along the axis
    np.testing.assert_allclose(float(moved.half_angle[1]), 0.6)
    np.testing.assert_allclose(np.asarray(moved.half_angle)[[0, 2]], np.pi / 2)  # planes stay planes


def test_working_point_of_a_plane_is_the_foot_of_the_perpendicular():
    s = Sheets.create(["plane"], [[0.0, 0.0, 10.0]], [[0.0, 0.6, 0.8]])
    x = np.array([3.0, 4.0, 50.0])
    foot, normal, *_ = s.at_working_point(0, x)
    n = np.array([0.0, 0.6, 0.8])
    np.testing.assert_allclose(np.asarray(foot), x - ((x - [0, 0, 10]) @ n) * n, atol=1e-12)
    np.testing.assert_allclose(np.abs(np.asarray(normal)), n, atol=1e-12)


def test_bad_kinds_are_refused():
    with pytest.raises(ValueError, match="unknown kind 'line'"):
        Sheets.create(["line"], [[0.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]])


def test_the_rig_plot_draws_each_sheet_on_its_own_surface(tmp_path):
    """plot_rig's lines for a line laser (a disc in its plane) and a ring laser (its cone's
    generatrices and end circle) lie on their sheets: G = 0 at every vertex."""
    from slcvjax.observations.simulate import paper_rig, sheet_rig
    from slcvjax.plots import plot_rig, sheet_lines

    rig, _ = sheet_rig(paper_rig(), ("cone", "point", "plane"))
    for j in range(rig.sheets.apex.shape[0]):
        pts = np.concatenate(sheet_lines(rig.sheets, j, 150.0))
        sh = rig.sheets
        g = np.array([float(sheet_value(jnp.asarray(x), sh.apex[j], sh.axis[j], sh.half_angle[j])) for x in pts])
        assert np.abs(g).max() < 1e-9, g
    assert plot_rig(rig, tmp_path / "rig.png").stat().st_size > 10_000
