"""The final check: do the residuals at the solution agree with the noise the uncertainty assumes?

A calibration's standard deviations hold where its residuals are what its noise model says: each
kind of observation (dot, spot, rim pixel, chessboard corner, stripe sample) Gaussian with its own
sigma ``sigma_k`` (:func:`slcvjax.calibration.covariance.kind_noise`).  A laser pulled by wrong
spots, a board placed one row off, or a model that does not fit leaves residuals that are larger,
or shaped otherwise, than that; its reported std is then too small.  After the last pass this
module tests, at a family-wise false-alarm level ``alpha`` (``CalibrationOptions.consistency_level``,
default 0.01) split over the tests by Bonferroni:

- **each group's spread**: per laser (its spots or stripe samples), per board in a view (its dots),
  per direct view (its corners) and per view's rim, ``T = sum r^2 / sigma_k^2`` over its scalar
  rows against its expectation ``nu = sum (1 - h)``, ``h`` each row's leverage (the diagonal of
  ``J H^-1 J^T`` at the solution: what the fit itself absorbs).  Under the model ``T`` is close to
  ``chi^2(nu)``; the group fails where ``P(chi^2(nu) >= T)`` is below its share of ``alpha``;
- **each kind's shape**: the kind's rows, each divided by ``sigma_k sqrt(1 - h)``, against the
  normal distribution by D'Agostino and Pearson's test of skew and kurtosis (``scipy.stats.normaltest``).

Rows already reported as outliers (beyond ``RobustPolicy.outlier_sigmas``) and the observations the
model cannot predict are left out: they are listed in the report.  A laser whose group fails has
its std scaled by ``sqrt(T / nu)`` (never down), and the report says so.  The rate at which clean
data raise an alarm is measured by ``benchmarks/consistency.py``.
"""

import numpy as np
from scipy import stats

from ..observations.problem import KIND_NAMES, Kind, Layout
from ..support.persist import PersistentJit
from .evaluate import solve_compiled
from .linearise import rows_at
from .params import pad_problem
from .result import CalibrationResult
from .schur import schur_inverse


def row_leverages(params, pk, masks, normal):
    """Per scalar residual row of the padded problem ``pk`` at ``params``: its value ``r``, its
    observation id, kind, whether it counts (a real, valid row), and its leverage ``h`` (the
    diagonal of ``J H^-1 J^T``, ``H`` the normal matrix ``normal`` of the solution, frozen
    columns and blocks left out by ``masks``).

    With ``H`` in Schur form (``S`` the global block's Schur complement, ``D`` the pose blocks,
    ``B`` their coupling), a row's ``(j_g, j_p)`` on pose block ``b`` has
    ``h = u^T S^-1 u + j_p^T D_b^-1 j_p`` with ``u = j_g - (D_b^-1 B_b^T)^T j_p``."""
    import jax
    import jax.numpy as jnp

    rows = rows_at(params, pk, with_jac=True)
    s_inv, d_inv, dinv_bt = schur_inverse(normal)
    g = s_inv.shape[0]
    jg = rows.jg * jnp.concatenate([masks.glob, jnp.zeros(1)])[rows.gidx]
    jp = rows.jp * jnp.concatenate([masks.blocks, jnp.zeros(1)])[rows.pidx][:, None]
    dense = jax.vmap(lambda j, i: jnp.zeros(g + 1).at[i].add(j))(jg, rows.gidx)[:, :g]
    coupling = jnp.concatenate([dinv_bt, jnp.zeros((1, 6, g))])[rows.pidx]
    u = dense - jnp.einsum("nkg,nk->ng", coupling, jp)
    d_ext = jnp.concatenate([d_inv, jnp.zeros((1, 6, 6))])[rows.pidx]
    h = jnp.einsum("ng,gh,nh->n", u, s_inv, u) + jnp.einsum("nk,nkl,nl->n", jp, d_ext, jp)
    return rows.r, rows.obs, rows.kind, rows.present & rows.valid, h


_leverage_jit = PersistentJit(row_leverages, "row_leverages")


def per_observation_rows(result: CalibrationResult) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per observation of ``result.packed`` (dots, spots, rim pixels, corners, stripe samples, in
    that order): the sum of its rows' squared residuals (px^2), of their ``1 - h`` (the degrees of
    freedom they leave), and per row, its kind, residual and ``1 - h``, for valid rows only."""
    params, pk, masks = result.params, result.packed, result.masks
    layout, p, padded, m = pad_problem(params, pk, masks)
    lin = solve_compiled(p, padded, m, result.loss, result.scale, 0).linearisation
    r, obs, kind, use, h = (np.asarray(a) for a in _leverage_jit(p, padded, m, lin.normal))
    free = np.clip(1.0 - h, 0.0, 1.0)
    n_pad = int(sum(layout.cap[:4])) + (layout.stripes[1] if layout.stripes is not None else 0)
    sq = np.bincount(obs[use], weights=r[use] ** 2, minlength=n_pad)
    dof = np.bincount(obs[use], weights=free[use], minlength=n_pad)
    return (
        layout.unpad_observations(sq[:n_pad]),
        layout.unpad_observations(dof[:n_pad]),
        (obs[use], kind[use], r[use], free[use], layout, n_pad),
    )


def _kind_sigma(result: CalibrationResult, k: Kind) -> float:
    s = result.kind_sigma.get(k.label)
    return float(s) if s is not None and np.isfinite(s) else float(result.cov.sigma)


def final_check(result: CalibrationResult, table, outlier: np.ndarray, level: float | None = None) -> dict:
    """The final check of ``result`` (the module's docstring): ``table`` is the report's
    per-observation table ``(norm, kind, ok, view, board, laser, index)`` and ``outlier`` its
    flags.  Returns ``{"level", "tests", "failed": [...], "laser_scale": {laser: factor}}``: each
    failed test's group, its ``T / nu`` ratio, ``nu``, p-value, and for a group's spread the std
    factor ``sqrt(T / nu)``."""
    level = result.options.consistency_level if level is None else level
    norm, kind, ok, view, board, laser, _ = table
    sq, dof, (row_obs, row_kind, row_r, row_free, layout, n_pad) = per_observation_rows(result)
    keep = ok & ~outlier
    sigma2 = np.array([_kind_sigma(result, k) ** 2 if k in kinds_present(kind) else 1.0 for k in Kind])
    z2 = np.where(keep, sq / sigma2[kind], 0.0)
    groups: dict[str, np.ndarray] = {}
    structured = (kind == Kind.SPOT) | (kind == Kind.STRIPE)
    for i in sorted({int(x) for x in laser[keep & structured]}):
        groups[f"laser {i}"] = keep & structured & (laser == i)
    dots = keep & (kind == Kind.DOT)
    for v, b in sorted({(int(v), str(b)) for v, b in zip(view[dots], board[dots], strict=True)}):
        groups[f"view {v} board {b}"] = dots & (view == v) & (board == b)
    for v in sorted({int(x) for x in view[keep & (kind == Kind.CHESS)]}):
        groups[f"direct view {v}"] = keep & (kind == Kind.CHESS) & (view == v)
    for v in sorted({int(x) for x in view[keep & (kind == Kind.RIM)]}):
        groups[f"view {v} rim"] = keep & (kind == Kind.RIM) & (view == v)
    spread = {}
    for name, sel in groups.items():
        nu = float(dof[sel].sum())
        if nu >= 1.0:
            t = float(z2[sel].sum())
            spread[name] = (t, nu, float(stats.chi2.sf(t, nu)))
    # the kinds' shape, per row: the rows of the kept observations
    kept_obs = np.zeros(n_pad, bool)
    kept_obs[_padded_ids(layout, n_pad)[keep]] = True
    shape = {}
    for k in kinds_present(kind):
        sel = kept_obs[row_obs] & (row_kind == k) & (row_free > 1e-6)
        if sel.sum() >= 20:
            z = row_r[sel] / (np.sqrt(_kind_sigma(result, k) ** 2 * row_free[sel]))
            shape[KIND_NAMES[k]] = float(stats.normaltest(z).pvalue)
    n_tests = len(spread) + len(shape)
    cut = level / max(n_tests, 1)
    failed, scale = [], {}
    for name, (t, nu, p) in spread.items():
        if p < cut:
            factor = float(np.sqrt(t / nu))
            failed.append(
                {"test": "spread", "group": name, "ratio": t / nu, "dof": nu, "p_value": p, "std_factor": factor}
            )
            if name.startswith("laser "):
                scale[int(name.split()[1])] = max(factor, 1.0)
    for name, p in shape.items():
        if p < cut:
            failed.append({"test": "normality", "group": f"kind {name}", "p_value": p})
    return {"level": level, "tests": n_tests, "failed": failed, "laser_scale": scale}


def kinds_present(kind: np.ndarray) -> list[Kind]:
    return [k for k in Kind if np.any(kind == k)]


def _padded_ids(layout: Layout, n_pad: int) -> np.ndarray:
    """For each real observation (in the unpadded order), its id in the padded problem."""
    return layout.unpad_observations(np.arange(n_pad))
