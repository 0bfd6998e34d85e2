"""The rigid target box model: its normal equations against the free model's by the chain rule,
its board pose covariances, the bound, and a row-shifted grid found as a misfit."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slcvjax.calibration.base import CalibrationError
from slcvjax.calibration.bound import cramer_rao, laser_errors
from slcvjax.calibration.calibrate import calibrate
from slcvjax.calibration.covariance import covariance_compiled
from slcvjax.calibration.evaluate import linearisation_at
from slcvjax.calibration.params import Params, make_masks, pad_masks
from slcvjax.calibration.rigid import board_pose_covariances, board_poses_of, box_model, rigid_masks, rigid_params
from slcvjax.cli import main
from slcvjax.geometry.pose import Pose, so3_log
from slcvjax.observations.formats import read_observations
from slcvjax.observations.problem import pack, stack_poses, unstack_poses
from slcvjax.observations.simulate import box_scene, paper_rig, paper_views, simulate


@pytest.fixture(scope="module")
def small():
    """A small box scene (5 views, 4 lasers), its truth and both models' parameters at the truth."""
    obs, truth = simulate(box_scene(paper_rig(4), paper_views(5), n_chess_views=6), noise=0.3, seed=1)
    pk = pack(obs)
    poses = [truth.board_poses[v][b] for v, b in pk.pose_keys]
    chess = stack_poses([truth.calibration_view_poses[c] for c in pk.chess_keys])
    free = Params(truth.rig, stack_poses(poses), chess)
    model = box_model(pk, obs.extra["rigid_boards"])
    rigid = rigid_params(model, pk.pose_keys, poses, truth.rig, chess)
    return obs, truth, pk, free, model, rigid


def _dense(lin, layout, n_global: int) -> tuple[np.ndarray, np.ndarray]:
    """``(H, b)`` of a linearisation over its real unknowns: global, board pose blocks, direct views."""
    ne = lin.normal
    blocks = list(range(layout.n[4])) + [layout.cap[4] + i for i in range(layout.n[5])]
    # the padded lasers' columns (held, with no spot) cut from the global block
    A = layout.unpad_glob(ne.A, axes=(0, 1))[:n_global, :n_global]
    B = np.concatenate([layout.unpad_glob(np.asarray(ne.B)[k])[:n_global] for k in blocks], axis=1)
    D = jax.scipy.linalg.block_diag(*[np.asarray(ne.D)[k] for k in blocks])
    H = np.block([[A, B], [B.T, np.asarray(D)]])
    b = np.concatenate([layout.unpad_glob(ne.bg)[:n_global]] + [np.asarray(ne.bp)[k] for k in blocks])
    return H, b


def _chain(model, rigid: Params, pk) -> np.ndarray:
    """d(free unknowns) / d(rigid unknowns) at the rigid parameters, by forward differentiation of
    each board pose ``T_cam_box retract(d_v) @ T_box_board retract(d_b)`` in the free tangent."""
    g = rigid.rig.tangent_dim
    k_box = len(model.boards)
    n_v, n_c = model.n_blocks, rigid.chess.t.shape[0]
    n_r = g + 6 * k_box + 6 * n_v + 6 * n_c
    P0 = unstack_poses(board_poses_of(model, rigid))
    V = unstack_poses(rigid.poses)
    Bx = unstack_poses(rigid.box)

    def free_of(theta):
        parts = [theta[:g]]
        for k in range(pk.n_poses):
            blk, bx = int(model.pair_block[k]), int(model.pair_box[k])
            dv = theta[g + 6 * k_box + 6 * blk : g + 6 * k_box + 6 * blk + 6]
            T = Pose(jnp.asarray(V[blk].R), jnp.asarray(V[blk].t)).retract(dv)
            if bx < len(model.boards):
                db = theta[g + 6 * bx : g + 6 * bx + 6]
                T = T @ Pose(jnp.asarray(Bx[bx].R), jnp.asarray(Bx[bx].t)).retract(db)
            parts += [so3_log(T.R @ jnp.asarray(P0[k].R).T), T.t - jnp.asarray(P0[k].t)]
        parts.append(theta[g + 6 * k_box + 6 * n_v :])
        return jnp.concatenate(parts)

    return np.asarray(jax.jacfwd(free_of)(jnp.zeros(n_r)))


@pytest.mark.slow
def test_rigid_normal_equations_are_the_free_ones_by_the_chain_rule(small):
    obs, truth, pk, free, model, rigid = small
    lay_f, lin_f = linearisation_at(free, pk, make_masks(free), "linear", 1.0)
    masks_r = rigid_masks(model, make_masks(free), pk.n_poses)
    pk_r = model.packed(pk)
    lay_r, lin_r = linearisation_at(rigid, pk_r, masks_r, "linear", 1.0)
    g = truth.rig.tangent_dim
    H_f, b_f = _dense(lin_f, lay_f, g)
    H_r, b_r = _dense(lin_r, lay_r, g + 6 * len(model.boards))
    M = _chain(model, rigid, pk)
    scale = np.abs(H_r).max()
    np.testing.assert_allclose(H_r, M.T @ H_f @ M, atol=1e-9 * scale)
    np.testing.assert_allclose(b_r, M.T @ b_f, atol=1e-9 * np.abs(b_r).max())
    # every board pose's covariance in the rigid model: the chain rule through the dense inverse
    sigma = 0.3
    cov = covariance_compiled(lin_r, pad_masks(lay_r, masks_r), jnp.asarray(sigma))
    cov = cov._replace(blocks=lay_r.unpad_blocks(cov.blocks))
    full = sigma**2 * np.linalg.inv(H_r)
    pose_cov = board_pose_covariances(model, rigid, lin_r, masks_r, cov, lay_r)
    n_pair = 6 * pk.n_poses
    C_pairs = (M @ full @ M.T)[g : g + n_pair, g : g + n_pair]
    for k in range(pk.n_poses):
        ref = C_pairs[6 * k : 6 * k + 6, 6 * k : 6 * k + 6]
        np.testing.assert_allclose(pose_cov[k], ref, rtol=1e-6, atol=1e-9 * np.abs(ref).max())


@pytest.mark.slow
def test_rigid_bound_is_tighter_for_every_laser(small):
    obs, truth, *_ = small
    free = cramer_rao(truth, obs, 0.5)
    rigid = cramer_rao(truth, obs, 0.5, rigid=True)
    # the rigid model is the free one constrained: no parameter can lose information
    assert np.all(rigid["position_std_mm"] <= free["position_std_mm"] * (1 + 1e-9))
    assert np.all(rigid["direction_std_rad"] <= free["direction_std_rad"] * (1 + 1e-9))
    assert rigid["direction_rms_rad"] < 0.97 * free["direction_rms_rad"]
    d_glob = np.diag(rigid["cov"].glob) - np.diag(free["cov"].glob)
    assert np.all(d_glob <= 1e-12 * np.diag(free["cov"].glob).max())


@pytest.mark.slow
def test_rigid_calibration_recovers_the_box(small):
    obs, truth, *_ = small
    res = calibrate(obs, rigid=True)
    assert res.passes[-1].name.startswith("R: rigid box") and res.passes[-1].converged
    box = res.box
    gauge = box["gauge"]
    for b, d in box["boards"].items():
        if b == gauge:
            continue
        # the truth's T_box_board: the gauge's pose inverted times the board's, in any view
        ref = truth.board_poses[0][gauge].inverse() @ truth.board_poses[0][b]
        err = np.asarray(d["pose"].t) - np.asarray(ref.t)
        assert np.all(np.abs(err) < 5 * np.asarray(d["translation_mm"])), (b, err, d["translation_mm"])
        rot = np.degrees(np.asarray(so3_log(jnp.asarray(d["pose"].R) @ jnp.asarray(ref.R).T)))
        assert np.all(np.abs(rot) < 5 * np.asarray(d["rotation_deg"])), (b, rot, d["rotation_deg"])
    # the lasers within a few bound stds of the truth
    bound = cramer_rao(truth, obs, 0.3, rigid=True)
    pos, ang = laser_errors(res.rig, truth.rig, bound["x_ref"])
    assert np.sqrt(np.mean(pos**2)) < 3 * bound["position_rms_mm"]
    assert np.sqrt(np.mean(ang**2)) < 3 * bound["direction_rms_rad"]


def test_rigid_needs_a_declared_group(small):
    obs = small[0]
    bare = obs.__class__(**{**obs.__dict__, "extra": {}})
    with pytest.raises(CalibrationError, match="no rigid_boards"):
        calibrate(bare, rigid=True)
    with pytest.raises(CalibrationError, match=r"rigid_boards\[1\]: unknown board 'wallX'"):
        calibrate(obs, rigid=["wall0", "wallX"])


@pytest.mark.slow
def test_a_row_shifted_grid_does_not_fit_the_box(tmp_path, capsys):
    """One wall of one view labelled a row off (every dot as the dot one row above): with free
    poses it vanishes into its pose; the rigid box finds it and leaves it out."""
    scene = box_scene(paper_rig(6), paper_views(12), n_chess_views=8)
    obs, truth = simulate(scene, noise=0.4, seed=11)
    path = tmp_path / "obs.json"
    from slcvjax.observations.formats import write_observations

    write_observations(path, obs)
    doc = json.loads(path.read_text())
    view, board = 4, "wall2"
    px = doc["views"][view]["boards"][board]
    cols = 3
    assert sum(p is not None for p in px[: len(px) - cols]) >= 4
    doc["views"][view]["boards"][board] = [None] * cols + px[: len(px) - cols]
    path.write_text(json.dumps(doc))
    shifted = read_observations(path)

    free = calibrate(shifted)
    assert not [r for r in free.repairs if r.board == board and r.view == obs.views[view].name]

    assert main(["calibrate", str(path), "--rigid", "--out", str(tmp_path / "cal.json")]) == 0
    assert "1 board pose(s) left out" in capsys.readouterr().out
    cal = json.loads((tmp_path / "cal.json").read_text())
    left = [r for r in cal["residuals"]["repairs"] if r["kind"] == "board"]
    assert [(r["view"], r["board"]) for r in left] == [(obs.views[view].name, board)]
    assert left[0]["residual_px"] > 10
    box = cal["uncertainty"]["rigid_box"]
    assert box["left_out"] == [{"view": obs.views[view].name, "board": board}]
    # the left-out board's pose is the box's: the truth's, not the shifted one
    t = np.asarray(cal["board_poses"][view][board]["t"])
    assert np.linalg.norm(t - np.asarray(truth.board_poses[view][board].t)) < 3.0


@pytest.mark.slow
def test_the_box_judges_again_the_spots_the_free_solve_relabelled(small):
    """Under free poses a board seen by a few dots is placed as much by its spots as by its dots,
    so a spot of its own laser can be taken for another's.  Pass R judges the relabelled and
    left-out spots again at the box's geometry: a spot whose own label fits comes back with it,
    a label that was wrong in the input stays corrected."""
    import dataclasses

    from slcvjax.calibration.evaluate import per_observation
    from slcvjax.calibration.result import Repair
    from slcvjax.calibration.rigid_pass import rigid_refine
    from slcvjax.observations.formats import SpotObs

    obs, *_ = small
    # a genuinely wrong label in the input: view 2's first spot given the next laser
    v_bad = 2
    spots = list(obs.views[v_bad].spots)
    true_laser = spots[0].laser
    spots[0] = SpotObs((true_laser + 1) % obs.n_lasers, spots[0].board, spots[0].pixel)
    views = list(obs.views)
    views[v_bad] = dataclasses.replace(views[v_bad], spots=spots)
    wrong = dataclasses.replace(obs, views=views)
    free = calibrate(wrong)
    row_bad = free.packed.spot_src.index((v_bad, 0))
    assert int(free.packed.spot_laser[row_bad]) == true_laser, "the free solve corrects the input's wrong label"

    # a correct spot of another view handed to the next laser, as a weakly placed board allows
    n_s = int(free.packed.counts[1])
    row = next(i for i, (v, _) in enumerate(free.packed.spot_src) if v != v_bad)
    v, j = free.packed.spot_src[row]
    labels = np.asarray(free.packed.spot_laser)[:n_s].copy()
    own = int(labels[row])
    assert own == obs.views[v].spots[j].laser
    labels[row] = (own + 1) % obs.n_lasers
    record = Repair("spot", obs.views[v].name, j, obs.views[v].spots[j].board, "relabelled", "handed by the test",
                    laser=own, new_laser=int(labels[row]))  # fmt: skip
    n_d = int(free.packed.counts[0])
    handed = dataclasses.replace(
        free, packed=free.packed.select(np.ones(n_d, bool), np.ones(n_s, bool), labels), repairs=(*free.repairs, record)
    )
    res = rigid_refine(handed, wrong, list(obs.extra["rigid_boards"]))
    restored = {(r["view"], r["index"]) for r in res.box["spots_restored"]}
    assert (obs.views[v].name, j) in restored, (res.box["spots_restored"], free.repairs)
    # each spot restored was changed by the free solve and had its true label in the input
    names = [w.name for w in obs.views]
    for name, k in restored:
        assert (name, k) == (obs.views[v].name, j) or any(
            r.kind == "spot" and (r.view, r.index) == (name, k) for r in free.repairs
        )
        assert (names.index(name), k) != (v_bad, 0)
    assert f"{len(restored)} spot(s) back with their own labels" in res.passes[-1].name and res.passes[-1].converged
    assert not [r for r in res.repairs if r.kind == "spot" and (r.view, r.index) == (obs.views[v].name, j)]
    used_labels = np.asarray(res.packed.spot_laser)[: int(res.packed.counts[1])].tolist()
    got = dict(zip(res.packed.spot_src, used_labels, strict=True))
    assert got[(v, j)] == own
    assert got[(v_bad, 0)] == true_laser  # the input's wrong label is not brought back
    # and every spot used fits the box at the noise
    norm, kind, ok = per_observation(res.params, res.packed)
    assert np.all(norm[(kind == 1) & ok] < 5 * 0.3 * 2.5)
