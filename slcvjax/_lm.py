"""Joint Levenberg-Marquardt over the whole rig with a Schur complement over the poses.

Unknowns: the *global* block (camera 9, mirror 5, lasers 4 each) and one 6-DOF *pose
block* per board pose of a catadioptric view and per direct chessboard view.  Every
observation touches the global block and at most one pose block:

=========== ===== ============================================== ==========
observation rows  local parameters                                pose block
=========== ===== ============================================== ==========
dot         2     camera, mirror, board pose (20)                board pose
spot        2     camera, mirror, its laser, board pose (24)     board pose
rim pixel   1     camera, mirror (14)                             none
chess corner 2    camera, direct-view pose (15)                  direct view
=========== ===== ============================================== ==========

so each observation's Jacobian is computed over its few local parameters (forward mode,
with the implicit derivative of the reflection point) and scattered into the normal
equations ``H = J^T W J``, ``g = J^T W r``.  With ``H = [[A, B], [B^T, D]]`` and ``D``
block-diagonal (6x6 per pose) the damped step solves the reduced system

    (A - B D^-1 B^T) dg = -g_g + B D^-1 g_p,      dp = D^-1 (-g_p - B^T dg),

whose cost grows linearly with the number of views.  The rim residual is the signed
first-order (Sampson) distance of a rim pixel to the projected rim curve, in pixels:
``F(uv) / |dF/duv|`` with ``F = |X(uv) - C| - r``, ``X`` the pixel's ray on the rim's
plane and ``C`` the rim's centre.  Within one solve the normalisation ``|dF/duv|`` is held
at its value at the start, so that the cost the steps are judged by is the function
whose Jacobian they use (the global rows are gathered into a dense matrix, so that
``A`` and ``g_g`` are matrix products).

Robust loss (dots and spots): Huber or Cauchy on each observation's 2D residual norm
with scale ``c`` px, by iteratively reweighted least squares inside LM.  The loop is one
``lax.while_loop`` (jit- and vmap-able) and returns a result code, never raises.
"""

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ._camera import Camera, in_image, pixel_to_ray, project
from ._lasers import Lasers, line_plane_intersection
from ._mirror import ConeMirror, project_through_mirror
from ._pose import Pose
from ._problem import Packed
from ._rig import Rig
from ._safe import safe_div, safe_norm

N_CAM, N_MIR, N_LAS = 9, 5, 4
N_CM = N_CAM + N_MIR
LOSSES = ("huber", "cauchy", "linear")
RIM_MARGIN = 0.05  # the cone extended 5 % past its rim for residuals (see solve_mirror_point)
APEX_MARGIN = 0.05  # and 5 % of its height past the apex
INVALID_PENALTY = 0.5 * 30.0**2  # the cost of a 30 px residual, per invalid observation

# result codes
CONVERGED, MAX_STEPS, STALLED = 0, 1, 2
RESULT_NAMES = {CONVERGED: "converged", MAX_STEPS: "max_steps", STALLED: "stalled"}


class Params(eqx.Module):
    """All unknowns: the rig, the board poses (P,) and the direct-view poses (C,)."""

    rig: Rig
    poses: Pose
    chess: Pose

    @property
    def n_global(self) -> int:
        return self.rig.tangent_dim

    @property
    def n_blocks(self) -> int:
        return self.poses.t.shape[0] + self.chess.t.shape[0]

    def retract(self, dg: Float[Array, " G"], dp: Float[Array, "NB 6"]) -> "Params":
        p = self.poses.t.shape[0]
        rp = jax.vmap(lambda R, t, d: Pose(R, t).retract(d))
        return Params(
            self.rig.retract(dg),
            rp(self.poses.R, self.poses.t, dp[:p]),
            rp(self.chess.R, self.chess.t, dp[p:]),
        )


# ------------------------------------------------------------------ per-observation residuals


def _cm(cam: Camera, mir: ConeMirror, d):
    return cam.retract(d[:N_CAM]), mir.retract(d[N_CAM:N_CM])


def _dot(d, cam, mir, R, t, xb, px):
    c, m = _cm(cam, mir, d)
    res = project_through_mirror(
        c, m, Pose(R, t).retract(d[N_CM:]).apply(xb), rim_margin=RIM_MARGIN, apex_margin=APEX_MARGIN
    )
    return res.uv - px, res.valid


def _spot(d, cam, mir, lp, ld, R, t, px):
    c, m = _cm(cam, mir, d)
    las = Lasers(lp[None], ld[None]).retract(d[N_CM : N_CM + N_LAS][None])
    x, ok = line_plane_intersection(
        las.points[0], las.directions[0], Pose(R, t).retract(d[N_CM + N_LAS :]), forward_only=False
    )
    res = project_through_mirror(c, m, x, rim_margin=RIM_MARGIN, apex_margin=APEX_MARGIN)
    return res.uv - px, ok & res.valid


def rim_value(cam: Camera, mir: ConeMirror, uv: Float[Array, "2"]) -> tuple[Float[Array, ""], Bool[Array, ""]]:
    """``F(uv) = |X(uv) - C| - r`` (mm): the pixel's ray on the rim's plane against the rim circle."""
    d, ok = pixel_to_ray(cam, uv)
    centre = mir.apex + mir.height * mir.axis
    lam = safe_div(jnp.dot(centre, mir.axis), jnp.dot(d, mir.axis))
    return safe_norm(lam * d - centre) - mir.radius, ok & (lam > 0.0)


def rim_scale(cam: Camera, mir: ConeMirror, uv: Float[Array, "2"]) -> Float[Array, ""]:
    """``|dF/duv|`` (mm per px): ``F / |dF/duv|`` is a pixel's first-order (Sampson) distance
    from the projected rim circle, in px."""
    return safe_norm(jax.jacfwd(lambda u: rim_value(cam, mir, u)[0])(uv))


def _rim(d, cam, mir, uv, norm):
    c, m = _cm(cam, mir, d)
    val, ok = rim_value(c, m, uv)
    return safe_div(val, norm)[None], ok & (norm > 0.0)


def rim_norms(rig: Rig, pk: Packed) -> Float[Array, " R"]:
    """Each rim pixel's ``|dF/duv|`` (:func:`rim_scale`) on ``rig``: the rim rows' normalisation."""
    return jax.vmap(lambda uv: rim_scale(rig.camera, rig.mirror, uv))(pk.rim_pixels)


def _chess(d, cam, R, t, xb, px):
    c = cam.retract(d[:N_CAM])
    uv, ok = project(c, Pose(R, t).retract(d[N_CAM:]).apply(xb))
    return uv - px, ok & in_image(c, jax.lax.stop_gradient(uv))


# ------------------------------------------------------------------ linearisation


class Rows(NamedTuple):
    """Scalar residual rows with their local Jacobians scattered by index."""

    r: Float[Array, " n"]  # residual
    jg: Float[Array, "n 18"]  # Jacobian w.r.t. camera, mirror and (at most) one laser
    gidx: Int[Array, "n 18"]  # global column of each (G = unused)
    jp: Float[Array, "n 6"]  # Jacobian w.r.t. the pose block
    pidx: Int[Array, " n"]  # pose block (NB = none)
    obs: Int[Array, " n"]  # observation id (for robust weights)
    kind: Int[Array, " n"]  # 0 dot, 1 spot, 2 rim, 3 chess
    valid: Bool[Array, " n"]


KIND_NAMES = ("dot", "spot", "rim", "chess")


def _rows(params: Params, pk: Packed, with_jac: bool = True, rim_norm: Array | None = None) -> Rows:
    """Every residual row with its local Jacobian.

    ``rim_norm``: the rim rows' normalisations (:func:`rim_norms`), held as constants; by
    default those of ``params`` itself, so that the rim rows are the pixels' first-order
    distances from the rim (the Jacobian still holds them constant).  The LM passes the
    normalisation at its start, so that its cost and its Jacobian describe one function.
    """
    rig = params.rig
    cam, mir, las = rig.camera, rig.mirror, rig.lasers
    g = rig.tangent_dim
    nb = params.n_blocks
    n_p = params.poses.t.shape[0]

    def lin(fun, n_local, *args):
        z = jnp.zeros(n_local)
        if with_jac:
            jac, (r, ok) = jax.jacfwd(lambda d: (fun(d, *args)[0], fun(d, *args)), has_aux=True)(z)
        else:
            r, ok = fun(z, *args)
            jac = jnp.zeros(r.shape + (n_local,))
        return r, jac, ok

    cm_idx = jnp.arange(N_CM)
    out = []
    # dots
    R, t = params.poses.R[pk.dot_pose], params.poses.t[pk.dot_pose]
    r, j, ok = jax.vmap(lambda *a: lin(_dot, N_CM + 6, cam, mir, *a))(R, t, pk.dot_points, pk.dot_pixels)
    n = r.shape[0]
    jg = jnp.concatenate([j[:, :, :N_CM], jnp.zeros((n, 2, N_LAS))], axis=2)
    gi = jnp.broadcast_to(jnp.concatenate([cm_idx, jnp.full(N_LAS, g)]), (n, 2, N_CM + N_LAS))
    out.append((r, jg, gi, j[:, :, N_CM:], jnp.broadcast_to(pk.dot_pose[:, None], (n, 2)), ok, 0, 2))
    # spots
    R, t = params.poses.R[pk.spot_pose], params.poses.t[pk.spot_pose]
    lp, ld = las.points[pk.spot_laser], las.directions[pk.spot_laser]
    r, j, ok = jax.vmap(lambda *a: lin(_spot, N_CM + N_LAS + 6, cam, mir, *a))(lp, ld, R, t, pk.spot_pixels)
    n = r.shape[0]
    lidx = N_CM + N_LAS * pk.spot_laser[:, None] + jnp.arange(N_LAS)[None, :]
    gi = jnp.concatenate([jnp.broadcast_to(cm_idx, (n, N_CM)), lidx], axis=1)
    out.append(
        (
            r,
            j[:, :, : N_CM + N_LAS],
            jnp.broadcast_to(gi[:, None, :], (n, 2, N_CM + N_LAS)),
            j[:, :, N_CM + N_LAS :],
            jnp.broadcast_to(pk.spot_pose[:, None], (n, 2)),
            ok,
            1,
            2,
        )
    )
    # rim
    norm = jax.lax.stop_gradient(rim_norms(rig, pk) if rim_norm is None else rim_norm)
    r, j, ok = jax.vmap(lambda uv, s: lin(_rim, N_CM, cam, mir, uv, s))(pk.rim_pixels, norm)
    n = r.shape[0]
    jg = jnp.concatenate([j, jnp.zeros((n, 1, N_LAS))], axis=2)
    gi = jnp.broadcast_to(jnp.concatenate([cm_idx, jnp.full(N_LAS, g)]), (n, 1, N_CM + N_LAS))
    out.append((r, jg, gi, jnp.zeros((n, 1, 6)), jnp.full((n, 1), nb), ok, 2, 1))
    # chess corners
    R, t = params.chess.R[pk.chess_pose], params.chess.t[pk.chess_pose]
    r, j, ok = jax.vmap(lambda *a: lin(_chess, N_CAM + 6, cam, *a))(R, t, pk.chess_points, pk.chess_pixels)
    n = r.shape[0]
    jg = jnp.concatenate([j[:, :, :N_CAM], jnp.zeros((n, 2, N_MIR + N_LAS))], axis=2)
    gi = jnp.broadcast_to(jnp.concatenate([jnp.arange(N_CAM), jnp.full(N_MIR + N_LAS, g)]), (n, 2, N_CM + N_LAS))
    out.append((r, jg, gi, j[:, :, N_CAM:], jnp.broadcast_to(n_p + pk.chess_pose[:, None], (n, 2)), ok, 3, 2))

    rows = []
    offset = 0
    for r, jg, gi, jp, pi, ok, kind, m in out:
        n = r.shape[0]
        obs_id = jnp.broadcast_to(offset + jnp.arange(n)[:, None], (n, m))
        offset += n
        okm = jnp.broadcast_to(ok[:, None], (n, m))
        rows.append(
            Rows(
                jnp.where(okm, r, 0.0).reshape(-1),
                jnp.where(okm[..., None], jg, 0.0).reshape(-1, N_CM + N_LAS),
                gi.reshape(-1, N_CM + N_LAS),
                jnp.where(okm[..., None], jp, 0.0).reshape(-1, 6),
                pi.reshape(-1),
                obs_id.reshape(-1),
                jnp.full(n * m, kind),
                okm.reshape(-1),
            )
        )
    return Rows(*(jnp.concatenate(parts) for parts in zip(*rows, strict=True)))


def n_observations(pk: Packed) -> int:
    return pk.dot_pose.shape[0] + pk.spot_pose.shape[0] + pk.rim_pixels.shape[0] + pk.chess_pose.shape[0]


# ------------------------------------------------------------------ robust loss


def block_costs(params: Params, pk: Packed, loss: str, scale) -> Float[Array, " NB"]:
    """The robust cost of the observations of each pose block (dots and spots of a board)."""
    return block_costs_of_rows(_rows(params, pk, with_jac=False), n_observations(pk), params.n_blocks, loss, scale)


def block_costs_of_rows(rows: Rows, n_obs: int, n_blocks: int, loss: str, scale) -> Float[Array, " NB"]:
    """:func:`block_costs` from residual rows already evaluated."""
    rho = _obs_costs(rows, n_obs, loss, jnp.asarray(scale, dtype=float))
    block = jax.ops.segment_max(rows.pidx, rows.obs, num_segments=n_obs)
    return jax.ops.segment_sum(rho, block, num_segments=n_blocks + 1)[:n_blocks]


def _obs_costs(rows: Rows, n_obs: int, loss: str, scale):
    return _robust(rows, n_obs, loss, scale, jnp.ones(4))[1]


def robust_weights(rows: Rows, n_obs: int, loss: str, scale, kind_weight=None) -> tuple[Array, Array]:
    """Per-row IRLS weights and the total robust cost (dots and spots robust, the rest plain).

    ``kind_weight`` (4,) weighs each kind (dot, spot, rim, chess); 0 drops it.  A weight
    ``(sigma / sigma_kind)^2`` whitens a kind to the noise ``sigma`` before the robust loss,
    so that ``scale`` (in units of ``sigma``) suits every kind.
    """
    kw = jnp.ones(4) if kind_weight is None else jnp.asarray(kind_weight, dtype=float)
    w, rho, _ = _robust(rows, n_obs, loss, scale, kw)
    return w[rows.obs], jnp.sum(rho)


def robust_cost(sq, loss: str, c):
    """``(rho, w)`` of whitened squared residual norms ``sq``: the robust cost and its IRLS
    weight ``2 rho'(sq)``; smooth enough to be differentiated twice (``sq = 0`` included)."""
    norm = jnp.sqrt(jnp.maximum(sq, 1e-300))
    if loss == "huber":
        inside = norm <= c
        return jnp.where(inside, 0.5 * sq, c * norm - 0.5 * c * c), jnp.where(inside, 1.0, c / norm)
    if loss == "cauchy":
        return 0.5 * c * c * jnp.log1p(sq / (c * c)), 1.0 / (1.0 + sq / (c * c))
    return 0.5 * sq, jnp.ones_like(sq)


def _robust(rows: Rows, n_obs: int, loss: str, scale, kw):
    """Per-observation IRLS weights, costs (invalid ones at a fixed penalty) and kinds."""
    kind_obs = jax.ops.segment_max(rows.kind, rows.obs, num_segments=n_obs)
    k = kw[kind_obs]
    sq = k * jax.ops.segment_sum(rows.r**2, rows.obs, num_segments=n_obs)  # whitened
    # dots and spots; the rim and the chessboard corners stay plain (a robust rim made the
    # lasers from rendered images worse in benchmarks/images_vs_file.py)
    robust = kind_obs <= 1
    rho, w = robust_cost(sq, loss, scale)
    w = jnp.where(robust, w, 1.0) * k
    rho = jnp.where(robust, rho, 0.5 * sq)
    # an invalid prediction (off the mirror, off the sensor) costs a fixed penalty, so that a
    # step cannot lower the cost by pushing observations out of the model's reach
    valid = jax.ops.segment_min(rows.valid.astype(jnp.int32), rows.obs, num_segments=n_obs) > 0
    rho = jnp.where(valid, rho, INVALID_PENALTY * k)
    return w, rho, kind_obs


# ------------------------------------------------------------------ normal equations


class Normal(NamedTuple):
    A: Float[Array, "G G"]
    bg: Float[Array, " G"]
    B: Float[Array, "NB G 6"]
    D: Float[Array, "NB 6 6"]
    bp: Float[Array, "NB 6"]


def normal_equations(rows: Rows, w, g: int, nb: int, gmask, pmask) -> Normal:
    """``J^T W J`` and ``J^T W r`` in Schur form; frozen parameters get a unit diagonal."""
    jg = rows.jg * jnp.concatenate([gmask, jnp.zeros(1)])[rows.gidx]
    jp = rows.jp * jnp.concatenate([pmask, jnp.zeros(1)])[rows.pidx][:, None]
    wr = w * rows.r
    # the global columns as one dense (rows, G) matrix: its products are matrix products,
    # three times faster on a CPU than scattering each row's 18 x 18 outer product
    n = rows.r.shape[0]
    J = jnp.zeros((n, g + 1)).at[jnp.arange(n)[:, None], rows.gidx].add(jg)[:, :g]
    A = (J * w[:, None]).T @ J
    bg = J.T @ wr
    D = jnp.zeros((nb + 1, 6, 6)).at[rows.pidx].add(w[:, None, None] * jp[:, :, None] * jp[:, None, :])[:nb]
    B = (
        jnp.zeros((nb + 1, g + 1, 6))
        .at[rows.pidx[:, None], rows.gidx]
        .add(w[:, None, None] * jg[:, :, None] * jp[:, None, :])[:nb, :g]
    )
    bp = jnp.zeros((nb + 1, 6)).at[rows.pidx].add(wr[:, None] * jp)[:nb]
    # frozen parameters, and pose blocks left without any valid observation, get a unit diagonal
    empty = jnp.trace(D, axis1=1, axis2=2) <= 0.0
    A = A + jnp.diag(jnp.where(jnp.diag(A) > 0.0, 1.0 - gmask, 1.0))
    D = D + jnp.where(empty | (pmask <= 0.0), 1.0, 0.0)[:, None, None] * jnp.eye(6)
    return Normal(A, bg, B, D, bp)


def schur_step(ne: Normal, lam) -> tuple[Array, Array]:
    """The damped Gauss-Newton step by the Schur complement over the pose blocks."""
    A = ne.A + lam * jnp.diag(jnp.maximum(jnp.diag(ne.A), 1e-9))
    dd = jnp.maximum(jnp.diagonal(ne.D, axis1=1, axis2=2), 1e-9)
    D = ne.D + lam * jax.vmap(jnp.diag)(dd)
    Dinv_Bt = jnp.linalg.solve(D, jnp.swapaxes(ne.B, 1, 2))  # (NB, 6, G)
    Dinv_bp = jnp.linalg.solve(D, ne.bp[..., None])[..., 0]  # (NB, 6)
    S = A - jnp.einsum("kgi,kih->gh", ne.B, Dinv_Bt)
    rhs = -ne.bg + jnp.einsum("kgi,ki->g", ne.B, Dinv_bp)
    dg = jnp.linalg.solve(S, rhs)
    dp = -Dinv_bp - jnp.einsum("kig,g->ki", Dinv_Bt, dg)
    return dg, dp


def dense_step(ne: Normal, lam) -> tuple[Array, Array]:
    """The same step from the full dense system (for tests and small problems)."""
    g, nb = ne.A.shape[0], ne.D.shape[0]
    H = jnp.zeros((g + 6 * nb, g + 6 * nb))
    H = H.at[:g, :g].set(ne.A)
    Bf = jnp.swapaxes(ne.B, 0, 1).reshape(g, 6 * nb)
    H = H.at[:g, g:].set(Bf).at[g:, :g].set(Bf.T)
    H = H.at[g:, g:].set(jax.scipy.linalg.block_diag(*ne.D) if nb else jnp.zeros((0, 0)))
    H = H + lam * jnp.diag(jnp.maximum(jnp.diag(H), 1e-9))
    x = jnp.linalg.solve(H, -jnp.concatenate([ne.bg, ne.bp.reshape(-1)]))
    return x[:g], x[g:].reshape(nb, 6)


# ------------------------------------------------------------------ the solver


class Masks(eqx.Module):
    """1 = estimated, 0 = frozen; ``glob`` over the global block, ``blocks`` over the pose blocks."""

    glob: Float[Array, " G"]
    blocks: Float[Array, " NB"]


def make_masks(params: Params, freeze: frozenset | set | tuple = ()) -> Masks:
    """Freeze masks from block names: camera, mirror, lasers, poses, chess_poses."""
    known = {"camera", "mirror", "lasers", "poses", "chess_poses"}
    bad = set(freeze) - known
    if bad:
        raise ValueError(
            f"unknown parameter block(s) to freeze: {', '.join(sorted(bad))} (known: {', '.join(sorted(known))})"
        )
    n_l = params.rig.lasers.n
    glob = jnp.concatenate(
        [
            jnp.full(N_CAM, 0.0 if "camera" in freeze else 1.0, dtype=float),
            jnp.full(N_MIR, 0.0 if "mirror" in freeze else 1.0, dtype=float),
            jnp.full(N_LAS * n_l, 0.0 if "lasers" in freeze else 1.0, dtype=float),
        ]
    )
    p, c = params.poses.t.shape[0], params.chess.t.shape[0]
    blocks = jnp.concatenate(
        [
            jnp.full(p, 0.0 if "poses" in freeze else 1.0, dtype=float),
            jnp.full(c, 0.0 if "chess_poses" in freeze else 1.0, dtype=float),
        ]
    )
    return Masks(glob, blocks)  # strongly typed, so every pass shares one compilation


class LMResult(NamedTuple):
    params: Params
    cost: Float[Array, ""]
    initial_cost: Float[Array, ""]
    steps: Int[Array, ""]
    result: Int[Array, ""]


def _cost(params, pk, loss, scale, kind_weight, rim_norm=None):
    rows = _rows(params, pk, with_jac=False, rim_norm=rim_norm)
    _, c = robust_weights(rows, n_observations(pk), loss, scale, kind_weight)
    return c


def solve(
    params: Params,
    pk: Packed,
    masks: Masks,
    loss: str = "huber",
    scale: float | Array = 1.0,
    max_steps: int = 100,
    rtol: float = 1e-10,
    kind_weight: Array | None = None,
) -> LMResult:
    """Levenberg-Marquardt from ``params``; returns the solution and a result code.

    Stops when an accepted step lowers the cost by less than ``rtol`` (relative) or
    moves no parameter noticeably, when the damping saturates (stalled), or after
    ``max_steps`` linearisations.  ``kind_weight`` (4,) weighs dots, spots, rim and
    chess corners (0 drops a kind; freeze what it alone determines).
    """
    if loss not in LOSSES:
        raise ValueError(f"unknown loss {loss!r} (known: {', '.join(LOSSES)})")
    g, nb, n_obs = params.n_global, params.n_blocks, n_observations(pk)
    scale = jnp.asarray(scale, dtype=float)
    kw = jnp.ones(4) if kind_weight is None else jnp.asarray(kind_weight, dtype=float)

    # the rim rows' normalisation is held at its value at the start: with it varying, the
    # cost would not be the function whose Jacobian the steps use, and near the minimum
    # every step was rejected (measured: 20-30 wasted linearisations per pass)
    rim_norm = rim_norms(params.rig, pk)

    def linearise(p):
        rows = _rows(p, pk, rim_norm=rim_norm)
        w, c = robust_weights(rows, n_obs, loss, scale, kw)
        return normal_equations(rows, w, g, nb, masks.glob, masks.blocks), c

    # the Jacobian is taken at the top of an iteration when the last step was accepted (or
    # at the start), so the residual function with derivatives is traced only once
    def body(s):
        p, ne, cost, c0, lam, it, done, code, stale = s
        ne, cost = jax.lax.cond(stale, linearise, lambda q: (ne, cost), p)
        c0 = jnp.where(it == 0, cost, c0)
        dg, dp = schur_step(ne, lam)
        cand = p.retract(dg, dp)
        c_new = _cost(cand, pk, loss, scale, kw, rim_norm)
        ok = jnp.isfinite(c_new) & (c_new < cost)
        small = (cost - c_new) <= rtol * cost
        tiny = jnp.maximum(jnp.max(jnp.abs(dg)), jnp.max(jnp.abs(dp), initial=0.0)) < 1e-12
        p = jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), cand, p)
        cost_out = jnp.where(ok, c_new, cost)
        lam = jnp.where(ok, jnp.maximum(lam / 3.0, 1e-12), lam * 4.0)
        it = it + 1
        # at the minimum every step is rejected with a cost equal up to round-off
        flat = jnp.abs(cost - c_new) <= 1e-12 * cost
        converged = (ok & (small | tiny)) | (~ok & (tiny | flat))
        stalled = lam > 1e10
        out_of_steps = it >= max_steps
        code = jnp.where(converged, CONVERGED, jnp.where(stalled, STALLED, MAX_STEPS))
        done = converged | stalled | out_of_steps
        return p, ne, cost_out, c0, lam, it, done, code, ok

    ne0 = Normal(jnp.zeros((g, g)), jnp.zeros(g), jnp.zeros((nb, g, 6)), jnp.zeros((nb, 6, 6)), jnp.zeros((nb, 6)))
    inf = jnp.asarray(jnp.inf)
    state = (
        params,
        ne0,
        inf,
        inf,
        jnp.asarray(1e-3),
        jnp.asarray(0),
        jnp.asarray(False),
        jnp.asarray(MAX_STEPS),
        jnp.asarray(True),
    )
    p, _, cost, c0, _, it, _, code, _ = jax.lax.while_loop(lambda s: ~s[6], body, state)
    return LMResult(p, cost, c0, it, code)


class Covariance(NamedTuple):
    """Covariance at a solution: global block, per-pose marginals, and the noise estimate."""

    glob: Float[Array, "G G"]
    blocks: Float[Array, "NB 6 6"]
    sigma: Float[Array, ""]
    dof: Int[Array, ""]


def schur_inverse(ne: Normal) -> tuple[Array, Array, Array]:
    """``(S^-1, D^-1, D^-1 B^T)``: the global block of ``H^-1`` (``S`` the Schur complement over
    the poses) and the pose blocks' pieces that give theirs."""
    Dinv = jnp.linalg.inv(ne.D)
    Dinv_Bt = jnp.einsum("kij,kgj->kig", Dinv, ne.B)
    S = ne.A - jnp.einsum("kgi,kih->gh", ne.B, Dinv_Bt)
    return jnp.linalg.inv(S), Dinv, Dinv_Bt


def covariance(
    params: Params,
    pk: Packed,
    masks: Masks,
    loss: str,
    scale,
    sigma: float | None = None,
    kind_weight: Array | None = None,
) -> Covariance:
    """``sigma^2 (J^T W J)^-1`` by the Schur complement; ``sigma`` from the residuals when None.

    The residual estimate is ``sum(w r^2) / (n - k)`` over the valid scalar residuals
    (``n``) and the estimated parameters (``k``).  Frozen parameters get zero variance.
    ``kind_weight`` (4,) as in :func:`solve`: with weights ``(sigma / sigma_kind)^2``
    the covariance holds for kinds of different noise.
    """
    g, nb = params.n_global, params.n_blocks
    rows = _rows(params, pk)
    w, _ = robust_weights(rows, n_observations(pk), loss, jnp.asarray(scale, dtype=float), kind_weight)
    ne = normal_equations(rows, w, g, nb, masks.glob, masks.blocks)
    seen_blocks = (
        jax.ops.segment_sum(
            (rows.valid & (jnp.sum(jnp.abs(rows.jp), axis=1) > 0)).astype(float), rows.pidx, num_segments=nb + 1
        )[:nb]
        > 0
    )
    seen_glob = (jnp.zeros(g + 1).at[rows.gidx].add(jnp.abs(rows.jg))[:g] > 0).astype(float)
    seen_blocks = seen_blocks.astype(float)
    k = jnp.sum(masks.glob * seen_glob) + 6 * jnp.sum(masks.blocks * seen_blocks)
    n = jnp.sum(rows.valid.astype(float))
    dof = (n - k).astype(jnp.int64)
    s2 = (
        jnp.sum(w * rows.r**2) / jnp.maximum(dof, 1).astype(float)
        if sigma is None
        else jnp.asarray(sigma, dtype=float) ** 2
    )
    Sinv, Dinv, Dinv_Bt = schur_inverse(ne)
    mg = masks.glob * seen_glob
    cov_g = s2 * Sinv * mg[:, None] * mg[None, :]
    cov_p = s2 * (Dinv + jnp.einsum("kig,gh,kjh->kij", Dinv_Bt, Sinv, Dinv_Bt))
    cov_p = cov_p * (masks.blocks * seen_blocks)[:, None, None]
    return Covariance(cov_g, cov_p, jnp.sqrt(s2), dof)


def residual_rows(params: Params, pk: Packed) -> Rows:
    """The residual rows at ``params`` without Jacobians (for reports)."""
    return _rows(params, pk, with_jac=False)
