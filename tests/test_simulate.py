import json

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import slcvjax as sj
from slcvjax import cli
from slcvjax.observations.simulate import make_scene, simulate

from ._helpers import back_project_many, project_many
from ._reference import RefRig


@pytest.fixture(scope="module")
def exact():
    scene = make_scene("paper")
    obs, truth = simulate(scene, noise=0.0, seed=0)
    return scene, obs, truth


def _ray_distance(m, d, x):
    v = x - m
    return np.linalg.norm(v - np.sum(v * d, axis=-1, keepdims=True) * d, axis=-1)


@pytest.mark.slow
def test_preset_matches_the_paper(exact):
    scene, obs, truth = exact
    cam = truth.rig.camera
    assert (cam.width, cam.height) == (640, 480)
    assert float(cam.fx) == pytest.approx(551.757) and float(cam.fy) == pytest.approx(551.95)
    assert float(truth.rig.mirror.radius) == 20.0 and float(truth.rig.mirror.height) == 10.0
    tilt = np.degrees(np.arccos(float(truth.rig.mirror.axis[2])))
    assert 1.0 <= tilt <= 2.0
    assert np.linalg.norm(np.asarray(truth.rig.mirror.apex[:2])) < 1.0
    assert truth.rig.lasers.n == 10 and len(obs.views) == 16 and len(obs.calibration_views) == 12
    # the whole rim fits the image
    ruv, rok = sj.project_rim(truth.rig, jnp.linspace(0, 2 * np.pi, 360))
    assert bool(np.all(rok))


def test_noise_free_dots_lie_on_their_back_projected_rays(exact):
    scene, obs, truth = exact
    rig = truth.rig
    n_seen = 0
    for view, poses in zip(obs.views, truth.board_poses, strict=True):
        for b, (px, seen) in view.boards.items():
            x = np.asarray(poses[b].apply(jnp.asarray(obs.boards[b])))
            # every dot of the board at once (one shape, one compilation), the seen ones checked
            ray = back_project_many(rig.camera, rig.mirror, jnp.asarray(np.where(seen[:, None], px, 0.0)))
            assert bool(np.all(np.asarray(ray.valid)[seen]))
            dist = _ray_distance(np.asarray(ray.point)[seen], np.asarray(ray.direction)[seen], x[seen])
            assert dist.max() < 1e-6
            n_seen += int(seen.sum())
            # what is not written is really not visible
            res = project_many(rig.camera, rig.mirror, jnp.asarray(x))
            assert not np.any(np.asarray(res.valid)[~seen])
    assert n_seen >= 0.9 * 16 * 36


def test_noise_free_spots_are_laser_wall_intersections_seen_through_the_mirror(exact):
    scene, obs, truth = exact
    rig = truth.rig
    ref = RefRig.from_package(rig.camera, rig.mirror)
    n = 0
    for view, poses in zip(obs.views, truth.board_poses, strict=True):
        for spot in view.spots:
            p = np.asarray(rig.lasers.points[spot.laser])
            d = np.asarray(rig.lasers.directions[spot.laser])
            pose = poses[spot.board]
            nrm, t = np.asarray(pose.R[:, 2]), np.asarray(pose.t)
            lam = nrm @ (t - p) / (nrm @ d)
            x = p + lam * d
            # the named wall is the first one the beam meets
            for other in poses.values():
                n2, t2 = np.asarray(other.R[:, 2]), np.asarray(other.t)
                lam2 = n2 @ (t2 - p) / (n2 @ d) if abs(n2 @ d) > 1e-9 else np.inf
                assert not (0 < lam2 < lam - 1e-9)
            m, dr = ref.back_project(spot.pixel)
            assert _ray_distance(m, dr, x) < 1e-6
            n += 1
    assert n >= 0.9 * 16 * 10  # 148 of 160 on the preset: some spots in the box's corners are out of view


def test_direct_views_agree_with_opencv(exact):
    scene, obs, truth = exact
    cam = truth.rig.camera
    for cv, pose in zip(obs.calibration_views, truth.calibration_view_poses, strict=True):
        ref, _ = cv2.projectPoints(
            obs.boards[cv.board], np.asarray(pose.rvec()), np.asarray(pose.t), np.asarray(cam.K), np.asarray(cam.dist)
        )
        np.testing.assert_allclose(cv.pixels, ref.reshape(-1, 2), atol=1e-9)
        assert cv.seen.all()


def test_rim_pixels_lie_on_the_rim_circle(exact):
    scene, obs, truth = exact
    mir = truth.rig.mirror
    a, c = np.asarray(mir.axis), np.asarray(mir.apex + mir.height * mir.axis)
    rays = jax.jit(jax.vmap(sj.pixel_to_ray, in_axes=(None, 0)))
    for view in obs.views[:3]:
        assert len(view.rim) >= 60
        d, ok = rays(truth.rig.camera, jnp.asarray(view.rim))
        d = np.asarray(d)
        x = ((c @ a) / (d @ a))[:, None] * d
        assert bool(np.all(ok))
        assert np.abs(np.linalg.norm(x - c, axis=1) - float(mir.radius)).max() < 1e-8


def test_distance_to_rim_is_the_offset_across_the_rims_image(exact):
    """Rim points off the sampled angles, moved across the curve by known amounts: their
    distance is that amount (to the curve's bending over such offsets, < 1e-4 px)."""
    _, _, truth = exact
    angles = jnp.asarray(np.random.default_rng(3).uniform(0, 2 * np.pi, 50))
    uv, ok = (np.asarray(x) for x in sj.project_rim(truth.rig, angles))
    ahead, _ = sj.project_rim(truth.rig, angles + 1e-6)
    tangent = (np.asarray(ahead) - uv) / np.linalg.norm(np.asarray(ahead) - uv, axis=1, keepdims=True)
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    shift = np.linspace(-0.05, 0.05, 50)
    d = sj.distance_to_rim(truth.rig, uv[ok] + shift[ok, None] * normal[ok])
    np.testing.assert_allclose(d, np.abs(shift[ok]), atol=1e-4)


def test_lasers_are_visible_inside_a_150_mm_pipe(exact):
    scene, obs, truth = exact
    rig = truth.rig
    p, d = np.asarray(rig.lasers.points), np.asarray(rig.lasers.directions)
    # beam meets the cylinder x^2 + y^2 = 75^2 around the camera's z axis
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = 2 * (p[:, 0] * d[:, 0] + p[:, 1] * d[:, 1])
    c = p[:, 0] ** 2 + p[:, 1] ** 2 - 75.0**2
    lam = (-b + np.sqrt(b * b - 4 * a * c)) / (2 * a)
    res = project_many(rig.camera, rig.mirror, jnp.asarray(p + lam[:, None] * d))
    assert bool(np.all(res.valid))


def test_noise_is_gaussian_with_the_requested_sigma(exact):
    scene, obs0, _ = exact
    obs, _ = simulate(scene, noise=0.5, seed=3)
    diffs = []
    for v0, v in zip(obs0.views, obs.views, strict=True):
        for b, (px0, seen) in v0.boards.items():
            diffs.append((v.boards[b][0] - px0)[seen])
        diffs.append(np.array([s.pixel for s in v.spots]) - np.array([s.pixel for s in v0.spots]))
    for c0, c in zip(obs0.calibration_views, obs.calibration_views, strict=True):
        diffs.append(c.pixels - c0.pixels)
    e = np.concatenate(diffs).ravel()
    assert abs(e.mean()) < 0.03
    assert e.std() == pytest.approx(0.5, rel=0.05)


def test_cli_simulate_writes_readable_files(tmp_path, capsys):
    rc = cli.main(
        [
            "simulate",
            "--preset",
            "paper",
            "--noise",
            "0.2",
            "--seed",
            "4",
            "--lasers",
            "5",
            "--views",
            "3",
            "--out",
            str(tmp_path),
        ]
    )
    assert rc == 0
    obs = sj.observations.formats.read_observations(tmp_path / "observations.json")
    cal = sj.observations.formats.read_calibration(tmp_path / "truth.json")
    assert obs.n_lasers == 5 and len(obs.views) == 3 and cal.rig.lasers.n == 5
    assert len(cal.board_poses) == 3 and len(cal.calibration_view_poses) == 12
    assert json.loads((tmp_path / "truth.json").read_text())["simulation"]["noise_px"] == 0.2
    assert "wrote" in capsys.readouterr().out


@pytest.mark.parametrize(
    "args, expected",
    [
        (["--preset", "box"], "unknown preset"),
        (["--noise", "-1"], "noise"),
        (["--views", "0"], "n_views"),
        (["--lasers", "0"], "n_lasers"),
    ],
)
def test_cli_simulate_bad_arguments(tmp_path, capsys, args, expected):
    rc = cli.main(["simulate", *args, "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err
    assert rc == 2
    assert expected in err and err.count("\n") == 1
    assert not (tmp_path / "x").exists()


def test_noise_per_kind():
    """One sigma per kind (dots, spots, rim, corners): each kind's pixels lie that far from the
    exact ones; four equal sigmas draw what one does."""
    scene = make_scene("paper", n_lasers=4, n_views=5)
    exact, _ = simulate(scene)
    sig = [0.02, 0.3, 0.0, 0.05]
    obs, truth = simulate(scene, noise=sig, seed=3)
    dots = np.concatenate(
        [
            px[s] - vx.boards[b][0][s]
            for v, vx in zip(obs.views, exact.views, strict=True)
            for b, (px, s) in v.boards.items()
        ]
    )
    spots = np.array([s.pixel - t.pixel for v, vx in zip(obs.views, exact.views, strict=True)
                      for s, t in zip(v.spots, vx.spots, strict=True)])  # fmt: skip
    corners = np.concatenate(
        [
            c.pixels[c.seen] - e.pixels[c.seen]
            for c, e in zip(obs.calibration_views, exact.calibration_views, strict=True)
        ]
    )
    for e, s in ((dots, sig[0]), (spots, sig[1]), (corners, sig[3])):
        assert np.std(e) == pytest.approx(s, rel=0.2)
    # the rim's angles are drawn at random, so its pixels are compared with the rim's curve
    assert np.max(sj.distance_to_rim(truth.rig, np.concatenate([v.rim for v in obs.views]))) < 1e-4  # its chords
    assert truth.extra["simulation"]["noise_px"] == sig
    one, _ = simulate(scene, noise=0.1, seed=3)
    four, _ = simulate(scene, noise=[0.1] * 4, seed=3)
    np.testing.assert_array_equal(one.views[2].spots[0].pixel, four.views[2].spots[0].pixel)
    np.testing.assert_array_equal(one.views[1].rim, four.views[1].rim)
    with pytest.raises(ValueError, match="four"):
        simulate(scene, noise=[0.1, 0.2])
