"""Differentiable calibration: derivatives of the joint solution by the implicit function theorem.

The joint Levenberg-Marquardt (:mod:`slcvjax.calibration.lm`) stops at a stationary point of its robust
cost ``F(theta, y)``, where ``theta`` are the unknowns (the rig and every pose) and ``y``
the data: the observed pixels and the board geometry (the dots' and corners' positions
on their boards).  In the local coordinates ``delta`` of :meth:`Params.retract` the
solution satisfies ``grad_delta F = 0``, so a change ``dy`` of the data moves it by

    d delta = -H^-1 (d/dy grad_delta F) dy,      H = the Hessian of F in delta,

without differentiating through the iterations.  ``H`` is the full Hessian (the
Gauss-Newton part ``J^T W J`` plus the residuals' curvature, which matters at a noisy
solution), built observation by observation: each touches at most ``N_L`` (25) local parameters,
so its Hessian and its mixed derivative in its own data are small dense blocks,
scattered into the same Schur form as the normal equations and solved by eliminating
the pose blocks.  The reflection point's Newton solve gives exact second derivatives
here (:mod:`slcvjax.geometry.newton`).  One term is left out: the rim residual's
normalisation ``|dF/duv|``, which the LM holds constant within a solve, is held
constant here too (its variation enters multiplied by the rim residuals).

Frozen parameters stay fixed (their derivative is zero).  The API:

* :func:`solution_tangent` maps a change of the data to the change of the solution;
* :func:`differentiable_solution` returns the solution as a JAX value whose
  derivatives (``jax.jvp``, ``jax.jacfwd``, ``jax.grad``) with respect to the packed
  observations follow the theorem, so any function of the calibrated rig can be
  differentiated with respect to the pixels or the board geometry;
* :func:`sensitivity` applies it to a :class:`CalibrationResult`: the derivative of
  every global parameter (camera, mirror, lasers) with respect to every observed pixel.
"""

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..observations.problem import Kind, Layout, Packed, kind_weights, map_rows
from ..support.persist import PersistentJit
from .losses import LOSSES, robust_cost
from .params import N_CAM, N_CM, N_LAS, Masks, Params, element_columns, pad_problem, unpad_params
from .residuals import camera_mirror, chess_residual, dot_residual, rim_scale, rim_value, spot_residual
from .schur import Normal, finish_normal, schur_solve

N_G = N_CM + N_LAS  # the global part of an observation's local parameters (padded)
DATA_FIELDS = ("dot_pixels", "spot_pixels", "rim_pixels", "chess_pixels", "dot_points", "chess_points")


def _rho(r, k, robust: bool, loss: str, c):
    """The LM's per-observation cost of residual ``r`` with kind weight ``k``
    (see ``slcvjax.calibration.losses.robust_observations``)."""
    sq = k * jnp.sum(r**2)
    return robust_cost(sq, loss, c)[0] if robust else 0.5 * sq


class _Blocks(NamedTuple):
    """Per observation: its cost's local gradient, Hessian and mixed data derivative, with indices."""

    g: Float[Array, "n L"]  # d F_i / d local, local = [global N_G (19) | pose 6]
    h: Float[Array, "n L L"]  # d2 F_i / d local^2
    m: Float[Array, "n L 5"]  # d2 F_i / d local d y_i, y_i = [pixel 2 | board point 3]
    gidx: Array  # (n, N_G) global column of each global local parameter (G = none)
    pidx: Array  # (n,) pose block (NB = none)


N_L = N_G + 6  # an observation's local parameters


def _second_order(grad_fn):
    """``v -> (d grad / dv, grad)`` for a local-gradient function of ``v = [local N_L | data 5]``."""

    def blocks(y, *args):
        v = jnp.concatenate([jnp.zeros(N_L), y])
        jac, grad = jax.jacfwd(lambda v: (grad_fn(v, *args),) * 2, has_aux=True)(v)
        return grad, jac[:, :N_L], jac[:, N_L:]

    return blocks


def _observation_blocks(params: Params, pk: Packed, loss: str, scale, kind_weight) -> _Blocks:
    """Every observation's cost derivatives at ``params`` (local coordinates zero)."""
    if pk.has_stripes:
        raise NotImplementedError(
            "the implicit derivative does not hold line and ring lasers' stripe samples yet: a calibration "
            "with stripes has no differentiable solution or pixel sensitivity"
        )
    rig = params.rig
    cam, mir, las = rig.camera, rig.mirror, rig.lasers
    g, nb = rig.tangent_dim, params.n_blocks
    n_p = params.poses.t.shape[0]
    kw = jnp.asarray(kind_weight, dtype=float)
    c = jnp.asarray(scale, dtype=float)

    def residual_grad(fun, kind: Kind, n_glob, has_pose, has_point):
        """The local gradient of one observation's robust cost, as a function of [local | data]."""

        def cost(z, y, *args):
            d = jnp.concatenate([z[:n_glob], z[N_G:]]) if has_pose else z[:n_glob]
            px, xb = y[:2], y[2:]
            r, ok = fun(d, *args, xb, px) if has_point else fun(d, *args, px)
            return jnp.where(ok, _rho(r, kw[kind], kind.robust, loss, c), 0.0)

        return lambda v, *args: jax.grad(cost)(v[:N_L], v[N_L:], *args)

    def rim_grad(v):
        # the LM's rim residual F / |dF/duv| holds |dF/duv| constant within a solve, at its
        # value where the solve started (at a solution: the solution itself, to within the
        # last pass's movement); the gradient below holds it at the current estimate, and its
        # derivative then follows |dF/duv| exactly
        z, px = v[:N_L], v[N_L : N_L + 2]
        c0, m0 = camera_mirror(cam, mir, z)
        s = rim_scale(c0, m0, px)

        def cost(z2):
            c2, m2 = camera_mirror(cam, mir, z2)
            val, ok = rim_value(c2, m2, px)
            return jnp.where(ok & (s > 0.0), 0.5 * kw[Kind.RIM] * (val / s) ** 2, 0.0)

        return jax.grad(cost)(z)

    cm = jnp.arange(N_CM)
    none = jnp.full(N_LAS, g)

    def blocks(fn, count, rows, *consts):
        """``_second_order(fn)`` of each row ``[data 5 | indices]`` up to ``count``, the rest zeros:
        a padded problem's padding costs next to nothing (the loop stops at the last chunk that
        holds a real row) and adds nothing."""
        out = map_rows(lambda *a: jax.vmap(lambda r: fn(r, *a[:-1]))(a[-1]))(*consts, rows, count)
        real = jnp.arange(rows.shape[0]) < count
        return tuple(jnp.where(real.reshape((-1,) + (1,) * (x.ndim - 1)), x, 0.0) for x in out)

    def idx(a):
        return a.astype(float)[:, None]

    def index(r, at):
        return r[at].astype(int)

    def posed(f):
        """The blocks of a row ``[data 5 | pose]`` of a kind seen from a pose."""
        return lambda r, R, t: _second_order(f)(r[:5], R[index(r, 5)], t[index(r, 5)])

    out = []
    # dots: [camera, mirror | pose], data [pixel | board point]
    f = residual_grad(lambda d, R, t, xb, px: dot_residual(d, cam, mir, R, t, xb, px), Kind.DOT, N_CM, True, True)
    rows = jnp.concatenate([pk.dot_pixels, pk.dot_points, idx(pk.dot_pose)], axis=1)
    gr, h, m = blocks(posed(f), pk.counts[Kind.DOT], rows, params.poses.R, params.poses.t)
    n = rows.shape[0]
    out.append((gr, h, m, jnp.broadcast_to(jnp.concatenate([cm, none]), (n, N_G)), pk.dot_pose))
    # spots: [camera, mirror, laser | pose], data [pixel | (none)]
    f = residual_grad(
        lambda d, lp, ld, R, t, px: spot_residual(d, cam, mir, lp, ld, R, t, px), Kind.SPOT, N_G, True, False
    )
    n = pk.spot_pixels.shape[0]
    rows = jnp.concatenate([pk.spot_pixels, jnp.zeros((n, 3)), idx(pk.spot_laser), idx(pk.spot_pose)], axis=1)

    def spot(r, lp, ld, R, t):
        i, p = index(r, 5), index(r, 6)
        return _second_order(f)(r[:5], lp[i], ld[i], R[p], t[p])

    gr, h, m = blocks(spot, pk.counts[Kind.SPOT], rows, las.points, las.directions, params.poses.R, params.poses.t)
    lidx = element_columns(params.rig, pk.spot_laser, N_LAS, g)
    gi = jnp.concatenate([jnp.broadcast_to(cm, (n, N_CM)), lidx], axis=1)
    out.append((gr, h, m, gi, pk.spot_pose))
    # rim pixels: [camera, mirror], data [pixel]
    n = pk.rim_pixels.shape[0]
    rows = jnp.concatenate([pk.rim_pixels, jnp.zeros((n, 3))], axis=1)
    gr, h, m = blocks(lambda r: _second_order(rim_grad)(r), pk.counts[Kind.RIM], rows)
    out.append((gr, h, m, jnp.broadcast_to(jnp.concatenate([cm, none]), (n, N_G)), jnp.full(n, nb)))
    # chessboard corners: [camera | direct-view pose], data [pixel | board point]
    f = residual_grad(lambda d, R, t, xb, px: chess_residual(d, cam, R, t, xb, px), Kind.CHESS, N_CAM, True, True)
    rows = jnp.concatenate([pk.chess_pixels, pk.chess_points, idx(pk.chess_pose)], axis=1)
    gr, h, m = blocks(posed(f), pk.counts[Kind.CHESS], rows, params.chess.R, params.chess.t)
    n = rows.shape[0]
    gi = jnp.broadcast_to(jnp.concatenate([jnp.arange(N_CAM), jnp.full(N_G - N_CAM, g)]), (n, N_G))
    out.append((gr, h, m, gi, n_p + pk.chess_pose))
    return _Blocks(*(jnp.concatenate(parts) for parts in zip(*out, strict=True)))


class _Hessian(NamedTuple):
    A: Float[Array, "G G"]
    B: Float[Array, "NB G 6"]
    D: Float[Array, "NB 6 6"]


def _assemble(bl: _Blocks, g: int, nb: int, masks: Masks) -> _Hessian:
    """The Schur-form Hessian over the estimated parameters: the observations' second-order blocks
    scattered into sums, then finished as the solve's normal equations are
    (:func:`slcvjax.calibration.schur.finish_normal`: frozen parameters, and those no row reaches,
    get a unit diagonal)."""
    gm = jnp.concatenate([masks.glob, jnp.zeros(1)])[bl.gidx]  # (n, N_G)
    pm = jnp.concatenate([masks.blocks, jnp.zeros(1)])[bl.pidx]  # (n,)
    h = bl.h * jnp.concatenate([gm, jnp.broadcast_to(pm[:, None], (pm.shape[0], 6))], axis=1)[:, :, None]
    h = h * jnp.concatenate([gm, jnp.broadcast_to(pm[:, None], (pm.shape[0], 6))], axis=1)[:, None, :]
    A = jnp.zeros((g + 1, g + 1)).at[bl.gidx[:, :, None], bl.gidx[:, None, :]].add(h[:, :N_G, :N_G])
    B = jnp.zeros((nb + 1, g + 1, 6)).at[bl.pidx[:, None], bl.gidx].add(h[:, :N_G, N_G:])
    D = jnp.zeros((nb + 1, 6, 6)).at[bl.pidx].add(h[:, N_G:, N_G:])
    ne, _, _ = finish_normal(Normal(A, jnp.zeros(g + 1), B, D, jnp.zeros((nb + 1, 6))), masks.glob, masks.blocks)
    return _Hessian(ne.A, ne.B, ne.D)


def _schur_solve(hs: _Hessian, rg, rp):
    """Solve ``H x = r`` for ``r = (rg (G, k), rp (NB, 6, k))`` (:func:`slcvjax.calibration.schur.schur_solve`)."""
    return schur_solve(hs.A, hs.B, hs.D, rg, rp)


def _data_tangent(pk: Packed, dpk, layout: Layout) -> Float[Array, "n 5"]:
    """The data tangents of ``pk``'s observations in the per-observation layout of
    :func:`_observation_blocks` for the problem padded by ``layout`` (zero on padded rows)."""

    def get(name):
        like = getattr(pk, name)
        v = getattr(dpk, name, None) if dpk is not None else None
        if v is None or getattr(v, "dtype", None) == jax.dtypes.float0:
            return jnp.zeros(np.shape(like))
        return jnp.asarray(v, dtype=float)

    def kind(k, pixels, points=None):
        n, cap = layout.n[k], layout.cap[k]
        rows = jnp.concatenate(
            [get(pixels), jnp.zeros((np.shape(getattr(pk, pixels))[0], 3)) if points is None else get(points)], axis=1
        )
        return jnp.pad(rows[:n], ((0, cap - n), (0, 0)))

    return jnp.concatenate(
        [
            kind(0, "dot_pixels", "dot_points"),
            kind(1, "spot_pixels"),
            kind(2, "rim_pixels"),
            kind(3, "chess_pixels", "chess_points"),
        ]
    )


def _scatter(bl: _Blocks, v, g: int, nb: int, masks: Masks):
    """Per-observation local vectors ``v`` (n, N_L, ...) summed into the global and pose parts."""
    extra = v.shape[2:]
    rg = jnp.zeros((g + 1,) + extra).at[bl.gidx].add(v[:, :N_G])[:g]
    rp = jnp.zeros((nb + 1, 6) + extra).at[bl.pidx].add(v[:, N_G:])[:nb]
    rg = rg * masks.glob.reshape((g,) + (1,) * len(extra))
    rp = rp * masks.blocks.reshape((nb, 1) + (1,) * len(extra))
    return rg, rp


class _Linearised(NamedTuple):
    blocks: _Blocks
    hessian: _Hessian
    step_g: Float[Array, " G"]  # the Newton step towards the exact stationary point
    step_p: Float[Array, "NB 6"]


def _linearise(params: Params, pk: Packed, masks: Masks, loss: str, scale, kind_weight) -> _Linearised:
    g, nb = params.n_global, params.n_blocks
    bl = _observation_blocks(params, pk, loss, scale, kind_weight)
    hs = _assemble(bl, g, nb, masks)
    rg, rp = _scatter(bl, -bl.g, g, nb, masks)
    xg, xp = _schur_solve(hs, rg[:, None], rp[..., None])
    return _Linearised(bl, hs, xg[:, 0], xp[..., 0])


def _linearise_with(loss: str):
    return lambda params, pk, masks, scale, kind_weight: _linearise(params, pk, masks, loss, scale, kind_weight)


# per loss, :func:`_linearise` compiled and its traced program kept on disk (a new process traced
# it for 5 s before it could load the compilation)
LINEARISE = {loss: PersistentJit(_linearise_with(loss), f"implicit_linearise_{loss}") for loss in LOSSES}


def linearised(params: Params, pk: Packed, masks: Masks, loss: str, scale, kind_weight) -> _Linearised:
    """:func:`_linearise` compiled (its arguments committed to the device: a solution straight from
    the LM holds host arrays, a Newton step's result device arrays, one program for both)."""
    return LINEARISE[loss](params, pk, masks, jnp.asarray(scale, dtype=float), kind_weights(kind_weight))


def _tangent(lin: _Linearised, masks: Masks, dy: Float[Array, "n 5"]):
    g, nb = lin.step_g.shape[0], lin.step_p.shape[0]
    v = -jnp.einsum("nij,nj->ni", lin.blocks.m, dy)
    rg, rp = _scatter(lin.blocks, v, g, nb, masks)
    xg, xp = _schur_solve(lin.hessian, rg[:, None], rp[..., None])
    return xg[:, 0], xp[..., 0]


_tangent_jit = jax.jit(_tangent)


def solution_tangent(
    params: Params, pk: Packed, masks: Masks, loss: str, scale, kind_weight, dpk
) -> tuple[Float[Array, " G"], Float[Array, "NB 6"]]:
    """The change ``(dg, dp)`` of the solution (local coordinates) for a change ``dpk`` of the data.

    ``params`` must be a stationary point of the LM's cost for ``pk`` with the same
    ``masks``, ``loss``, ``scale`` and ``kind_weight`` (an LM solution; for derivatives
    exact to the last digits polish it first with :func:`stationary_point`).  ``dpk``
    holds tangents of the fields in :data:`DATA_FIELDS` (a :class:`Packed` of tangents,
    or any object with some of these attributes; missing ones count as zero).  The problem is
    padded to its shape buckets (:func:`slcvjax.calibration.params.pad_problem`): every dataset of
    a bucket shares the compiled linearisation.
    """
    layout, padded, ppk, pmasks = pad_problem(params, pk, masks)
    lin = linearised(padded, ppk, pmasks, loss, scale, kind_weight)
    dg, dp = _tangent_jit(lin, pmasks, _data_tangent(pk, dpk, layout))
    return dg[layout.glob_index(dg.shape[0])], dp[layout.block_index()]


def _unpadded(layout: Layout, lin: _Linearised, g: int) -> _Linearised:
    """A padded problem's linearisation restricted to its real observations, its ``g`` real global
    parameters and its real pose blocks, the indices renumbered (a column or block that is none:
    the real sizes)."""
    bl, hs = lin.blocks, lin.hessian
    nb_pad = lin.step_p.shape[0]
    (n_p, n_c), cap_p = layout.n[4:], layout.cap[4]
    gidx = np.asarray(bl.gidx)
    gidx = np.where(gidx >= g, g, gidx)  # padded lasers' columns are never an observation's
    pidx = np.asarray(bl.pidx)
    pidx = np.where(pidx >= nb_pad, n_p + n_c, np.where(pidx >= cap_p, pidx - cap_p + n_p, pidx))
    blocks = _Blocks(
        *(layout.unpad_observations(x) for x in (bl.g, bl.h, bl.m)),
        layout.unpad_observations(gidx),
        layout.unpad_observations(pidx),
    )
    hessian = _Hessian(
        layout.unpad_glob(hs.A, axes=(0, 1)),
        layout.unpad_blocks(layout.unpad_glob(hs.B, axes=(1,))),
        layout.unpad_blocks(hs.D),
    )
    return _Linearised(blocks, hessian, layout.unpad_glob(lin.step_g), layout.unpad_blocks(lin.step_p))


def stationary_point(
    params: Params, pk: Packed, masks: Masks, loss: str, scale, kind_weight=None, max_steps: int = 6, tol: float = 1e-10
) -> tuple[Params, int]:
    """Newton steps with the exact Hessian from an LM solution to its exact stationary point.

    The LM stops on a relative cost decrease, which can leave a weakly determined
    direction (a near-gauge of the poses) a little short of the minimum: a tiny cost
    difference but a visible one in the parameters.  From there Newton converges
    quadratically (typically 2-3 steps to ``tol`` in local coordinates).  Returns the
    point and the number of steps taken; raises ``ValueError`` when a step does not
    shrink (``params`` was not near a minimum).

    Hand-written rather than optimistix's ``Newton``: each step is one Schur solve of the
    problem's own second-order linearisation, where ``optimistix.root_find`` on the gradient
    forms its dense Jacobian.  To the same point and cost, ours took 292 ms against 348 ms with
    223 unknowns and 551 ms against 1357 ms with 511 (the preset), compiling in 9 s against
    37 s (``benchmarks/bench_solvers.py``, ``benchmarks/results/solvers.json``).
    """
    layout, params, _, steps = _newton(params, pk, masks, loss, scale, kind_weight, max_steps, tol)
    return unpad_params(layout, params), steps


def _newton(params: Params, pk: Packed, masks: Masks, loss: str, scale, kind_weight, max_steps: int, tol: float):
    """:func:`stationary_point` on the padded problem: its layout, the padded point, the
    linearisation there (the sensitivity's) and the number of steps."""
    layout, params, pk, masks = pad_problem(params, pk, masks)
    last = np.inf
    for k in range(max_steps + 1):
        lin = linearised(params, pk, masks, loss, scale, kind_weight)
        if k == max_steps:
            break
        size = float(jnp.maximum(jnp.max(jnp.abs(lin.step_g)), jnp.max(jnp.abs(lin.step_p), initial=0.0)))
        if not np.isfinite(size) or (k >= 2 and size > 0.5 * last):
            raise ValueError(f"Newton from the given solution does not converge (step {size:.3g} after {last:.3g})")
        if size <= tol:
            return layout, params, lin, k
        params, last = params.retract(lin.step_g, lin.step_p), size
    return layout, params, lin, max_steps


@functools.partial(jax.custom_jvp, nondiff_argnums=(3,))
def _pinned(params: Params, pk: Packed, masks: Masks, loss: str, scale, kind_weight) -> Params:
    return params


@_pinned.defjvp
def _pinned_jvp(loss, primals, tangents):
    params, pk, masks, scale, kind_weight = primals
    dpk = tangents[1]
    params = jax.lax.stop_gradient(params)
    dg, dp = solution_tangent(params, jax.lax.stop_gradient(pk), masks, loss, scale, kind_weight, dpk)
    zg, zp = jnp.zeros(params.n_global), jnp.zeros((params.n_blocks, 6))
    _, dparams = jax.jvp(lambda a, b: params.retract(a, b), (zg, zp), (dg, dp))
    return params, dparams


def differentiable_solution(
    params: Params, pk: Packed, masks: Masks, loss: str = "huber", scale=1.0, kind_weight=None
) -> Params:
    """``params`` (the LM's solution for ``pk``) with derivatives in ``pk`` by the implicit function theorem.

    The value is ``params`` unchanged; differentiating any function of it with respect to
    the float fields of ``pk`` (pixels, board points) gives the derivative of the
    calibrated solution, as if the LM were run again on the changed data (forward mode:
    ``jax.jvp``, ``jax.jacfwd``).  Derivatives with respect to ``params`` itself are not
    defined (it is held constant).
    """
    if loss not in LOSSES:
        raise ValueError(f"unknown loss {loss!r} (known: {', '.join(LOSSES)})")
    return _pinned(params, pk, masks, loss, jnp.asarray(scale, dtype=float), kind_weights(kind_weight))


@jax.jit
def _pixel_columns(lin: _Linearised, masks: Masks):
    """The solution's derivative with respect to every observed pixel coordinate (2 per observation)."""
    bl = lin.blocks
    g, nb = lin.step_g.shape[0], lin.step_p.shape[0]
    n = bl.m.shape[0]
    # one column per observed pixel coordinate (2 i + a for axis a of observation i), each
    # touching only its own observation's local parameters
    v = -bl.m[:, :, :2]  # (n, N_L, 2)
    col = 2 * jnp.arange(n)[:, None] + jnp.arange(2)[None, :]  # (n, 2)
    rg = jnp.zeros((g + 1, 2 * n)).at[bl.gidx[:, :, None], col[:, None, :]].add(v[:, :N_G])[:g]
    rp = jnp.zeros((nb + 1, 6, 2 * n)).at[bl.pidx[:, None, None], jnp.arange(6)[None, :, None], col[:, None, :]]
    rp = rp.add(v[:, N_G:])[:nb]
    rg, rp = rg * masks.glob[:, None], rp * masks.blocks[:, None, None]
    return _schur_solve(lin.hessian, rg, rp)


class Sensitivity(NamedTuple):
    """Derivatives of a calibration's global parameters with respect to its observed pixels.

    ``glob[:, j]`` is the derivative of the rig's local coordinates (camera 9, mirror 6,
    lasers 4 each, as in :meth:`Rig.retract`) with respect to pixel coordinate ``j``;
    columns are ordered by observation (dots, spots, rim pixels, chessboard corners, as in
    :class:`Packed`), two per observation (u, v), ``kind`` and ``index`` naming each
    column's observation.  ``laser_point`` and ``laser_direction`` (N, 3, n) are the
    derivatives of each laser's point nearest its working point and of its unit direction.
    ``params`` is the exact stationary point they were taken at (``newton_steps`` Newton
    steps from the calibration's solution).
    """

    glob: np.ndarray
    kind: np.ndarray
    index: np.ndarray
    axis: np.ndarray
    laser_point: np.ndarray
    laser_direction: np.ndarray
    params: Params
    newton_steps: int


def sensitivity(result, x_ref: np.ndarray | None = None) -> Sensitivity:
    """The derivative of a :class:`CalibrationResult`'s rig with respect to every observed pixel.

    Taken at the exact stationary point of the final pass's cost (:func:`stationary_point`
    from the calibration's solution).  ``x_ref`` (N, 3): the working point of each laser
    (default: the mean of its spots' 3D points, :func:`laser_working_points`).  A rim
    pixel's two columns are its derivative along u and v (only the component across the
    rim acts).
    """
    from .bound import laser_working_points

    pk = result.packed
    arr = pk.arrays()
    kw = kind_weights()  # the final pass's kind weights
    layout, padded, lin, steps = _newton(result.params, arr, result.masks, result.loss, result.scale, kw, 6, 1e-10)
    params = unpad_params(layout, padded)
    lin = _unpadded(layout, lin, params.rig.tangent_dim)
    if x_ref is None:
        x_ref = laser_working_points(params.rig, params.poses, pk)
    xg, _ = _pixel_columns(lin, result.masks)
    xg = np.asarray(xg)
    counts = [pk.dot_pose.shape[0], pk.spot_pose.shape[0], pk.rim_pixels.shape[0], pk.chess_pose.shape[0]]
    kind = np.repeat(np.repeat(np.arange(len(counts)), counts), 2)
    index = np.repeat(np.concatenate([np.arange(c) for c in counts]), 2)
    axis = np.tile(np.arange(2), sum(counts))
    rig = params.rig
    n_l = rig.lasers.n
    lp, ld = np.zeros((n_l, 3, xg.shape[1])), np.zeros((n_l, 3, xg.shape[1]))
    for i in range(n_l):

        def comps(d4, i=i):
            return jnp.concatenate(rig.lasers.at_working_point(i, x_ref[i], d4))

        sl = rig.layout.elements[i]
        j = np.asarray(jax.jacfwd(comps)(jnp.zeros(sl.stop - sl.start)))  # (6, 4)
        lp[i], ld[i] = j[:3] @ xg[sl], j[3:] @ xg[sl]
    return Sensitivity(xg, kind, index, axis, lp, ld, params, steps)
