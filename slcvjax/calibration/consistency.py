"""The final check: do the residuals at the solution agree with the noise the uncertainty assumes?

A calibration's standard deviations hold where its residuals are what its noise model says: each
kind of observation (dot, spot, rim pixel, chessboard corner, stripe sample) Gaussian with its own
sigma ``sigma_k`` (:func:`slcvjax.calibration.covariance.kind_noise`).  A laser pulled by wrong
spots, a board placed one row off, or a model that does not fit leaves residuals that are larger,
or shaped otherwise, than that; its reported std is then too small.  After the last pass this
module tests, at a family-wise false-alarm level ``alpha`` (``CalibrationOptions.consistency_level``,
default 0.01) split by Bonferroni evenly over the families of tests (the lasers, the boards, the
direct views, the rims), then evenly over each family's tests, so that a rig's few lasers are
not drowned by its many boards:

- **each group's spread against the rest of its kind**: per laser (its spots or stripe samples),
  per board in a view (its dots), per direct view (its corners) and per view's rim, the group's
  sum of squared residuals ``S_g`` over the degrees of freedom its rows leave,
  ``nu_g = sum (1 - h)`` (``h`` each row's leverage: the diagonal of ``W J H^-1 J^T`` at the
  solution, what the fit itself absorbs), over the same for the rest of the kind.  Under the
  model the two are independent ``sigma_k^2 chi^2 / nu`` and their ratio ``F(nu_g, nu_rest)``;
  the group fails where ``P(F >= f)`` is below its share of ``alpha``.  Comparing with the rest
  of the kind, not with ``sigma_k`` (estimated from every group, the bad one included), keeps one
  bad laser among few from hiding by inflating its kind's sigma.

Each kind's shape is reported beside them (``shape``: its rows, each divided by
``sigma_k sqrt(1 - h)``, their skew, excess kurtosis and the p-value of D'Agostino and Pearson's
test of normality), but not tested against ``alpha``: with thousands of rows any real detector's
errors (a centroid's pixel-locking, a corner's bias near the apex) depart measurably from a
Gaussian, while the covariance, a second-moment statement, holds whatever their shape; the
groups' spreads are what make a std wrong.

Rows already reported as outliers (beyond ``RobustPolicy.outlier_sigmas``) and the observations the
model cannot predict are left out: they are listed in the report.  A laser whose group fails has
its std scaled by ``sqrt(S_g / (nu_g sigma_k^2))`` (its spread against the noise the covariance
assumed; never down), and the report says so.  The rate at which clean data raise an alarm is
measured by ``benchmarks/consistency.py``.
"""

import numpy as np
from scipy import stats

from ..observations.problem import KIND_NAMES, Kind, Layout
from ..support.persist import PersistentJit
from .evaluate import solve_compiled
from .linearise import n_observations, rows_at
from .losses import loss_index, robust_weights
from .params import pad_problem
from .result import CalibrationResult
from .schur import schur_inverse


def row_leverages(params, pk, masks, normal, loss, scale):
    """Per scalar residual row of the padded problem ``pk`` at ``params``: its value ``r``, its
    observation id, kind, whether it counts (a real, valid row), and its leverage ``h`` (the
    diagonal of ``W J H^-1 J^T``, ``H = J^T W J`` the normal matrix ``normal`` of the solution,
    ``W`` the robust loss's weights (``loss`` an index of :data:`slcvjax.calibration.losses.LOSSES`,
    ``scale`` px), frozen columns and blocks left out by ``masks``); the leverages add up to the
    number of estimated parameters.

    With ``H`` in Schur form (``S`` the global block's Schur complement, ``D`` the pose blocks,
    ``B`` their coupling), a row's ``(j_g, j_p)`` on pose block ``b`` has
    ``h = u^T S^-1 u + j_p^T D_b^-1 j_p`` with ``u = j_g - (D_b^-1 B_b^T)^T j_p``."""
    import jax
    import jax.numpy as jnp

    rows = rows_at(params, pk, with_jac=True)
    w, _ = robust_weights(rows, n_observations(pk), loss, scale)
    s_inv, d_inv, dinv_bt = schur_inverse(normal)
    g = s_inv.shape[0]
    jg = rows.jg * jnp.concatenate([masks.glob, jnp.zeros(1)])[rows.gidx]
    jp = rows.jp * jnp.concatenate([masks.blocks, jnp.zeros(1)])[rows.pidx][:, None]
    dense = jax.vmap(lambda j, i: jnp.zeros(g + 1).at[i].add(j))(jg, rows.gidx)[:, :g]
    coupling = jnp.concatenate([dinv_bt, jnp.zeros((1, 6, g))])[rows.pidx]
    u = dense - jnp.einsum("nkg,nk->ng", coupling, jp)
    d_ext = jnp.concatenate([d_inv, jnp.zeros((1, 6, 6))])[rows.pidx]
    h = w * (jnp.einsum("ng,gh,nh->n", u, s_inv, u) + jnp.einsum("nk,nkl,nl->n", jp, d_ext, jp))
    return rows.r, rows.obs, rows.kind, rows.present & rows.valid, h


_leverage_jit = PersistentJit(row_leverages, "row_leverages")


def per_observation_rows(result: CalibrationResult) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per observation of ``result.packed`` (dots, spots, rim pixels, corners, stripe samples, in
    that order): the sum of its rows' squared residuals (px^2), of their ``1 - h`` (the degrees of
    freedom they leave), and per row, its kind, residual and ``1 - h``, for valid rows only."""
    params, pk, masks = result.params, result.packed, result.masks
    layout, p, padded, m = pad_problem(params, pk, masks)
    lin = solve_compiled(p, padded, m, result.loss, result.scale, 0).linearisation
    loss = np.asarray(loss_index(result.loss))
    out = _leverage_jit(p, padded, m, lin.normal, loss, np.asarray(float(result.scale)))
    r, obs, kind, use, h = (np.asarray(a) for a in out)
    free = np.clip(1.0 - h, 0.0, 1.0)
    n_pad = int(sum(layout.cap[:4])) + (layout.stripes[1] if layout.stripes is not None else 0)
    sq = np.bincount(obs[use], weights=r[use] ** 2, minlength=n_pad)
    dof = np.bincount(obs[use], weights=free[use], minlength=n_pad)
    return (
        layout.unpad_observations(sq[:n_pad]),
        layout.unpad_observations(dof[:n_pad]),
        (obs[use], kind[use], r[use], free[use], layout, n_pad),
    )


MIN_REST_DOF = 5.0  # a group is compared with the rest of its kind only where the rest leaves this many


def _kind_sigma(result: CalibrationResult, k: Kind) -> float:
    s = result.kind_sigma.get(k.label)
    return float(s) if s is not None and np.isfinite(s) else float(result.cov.sigma)


def final_check(result: CalibrationResult, table, outlier: np.ndarray, level: float | None = None) -> dict:
    """The final check of ``result`` (the module's docstring): ``table`` is the report's
    per-observation table ``(norm, kind, ok, view, board, laser, index)`` and ``outlier`` its
    flags.  Returns ``{"level", "tests", "failed": [...], "laser_scale": {laser: factor}}``: each
    failed test's group and p-value, and for a group's spread its variance ratio to the rest of
    its kind (``ratio``), the two degrees of freedom (``dof``) and the std factor."""
    level = result.options.consistency_level if level is None else level
    norm, kind, ok, view, board, laser, _ = table
    sq, dof, (row_obs, row_kind, row_r, row_free, layout, n_pad) = per_observation_rows(result)
    keep = ok & ~outlier
    groups: dict[str, tuple[Kind, np.ndarray]] = {}
    for k in (Kind.SPOT, Kind.STRIPE):
        for i in sorted({int(x) for x in laser[keep & (kind == k)]}):
            groups[f"laser {i}"] = (k, keep & (kind == k) & (laser == i))
    dots = keep & (kind == Kind.DOT)
    for v, b in sorted({(int(v), str(b)) for v, b in zip(view[dots], board[dots], strict=True)}):
        groups[f"view {v} board {b}"] = (Kind.DOT, dots & (view == v) & (board == b))
    for k, what in ((Kind.CHESS, "direct view {}"), (Kind.RIM, "view {} rim")):
        for v in sorted({int(x) for x in view[keep & (kind == k)]}):
            groups[what.format(v)] = (k, keep & (kind == k) & (view == v))
    total = {k: (float(sq[keep & (kind == k)].sum()), float(dof[keep & (kind == k)].sum())) for k in Kind}
    spread = {}
    for name, (k, sel) in groups.items():
        s_g, nu_g = float(sq[sel].sum()), float(dof[sel].sum())
        s_rest, nu_rest = total[k][0] - s_g, total[k][1] - nu_g
        if nu_g >= 1.0 and nu_rest >= MIN_REST_DOF and s_rest > 0.0:
            f = (s_g / nu_g) / (s_rest / nu_rest)
            ratio = s_g / nu_g / _kind_sigma(result, k) ** 2  # against the noise the std assume
            spread[name] = (f, nu_g, nu_rest, float(stats.f.sf(f, nu_g, nu_rest)), ratio)
    # the kinds' shape, per row: the rows of the kept observations
    kept_obs = np.zeros(n_pad, bool)
    kept_obs[_padded_ids(layout, n_pad)[keep]] = True
    shape = {}
    for k in kinds_present(kind):
        sel = kept_obs[row_obs] & (row_kind == k) & (row_free > 1e-6)
        if sel.sum() >= 20:
            z = row_r[sel] / (np.sqrt(_kind_sigma(result, k) ** 2 * row_free[sel]))
            shape[KIND_NAMES[k]] = {
                "rows": int(sel.sum()),
                "skew": float(stats.skew(z)),
                "excess_kurtosis": float(stats.kurtosis(z)),
                "p_value": float(stats.normaltest(z).pvalue),
            }
    n_tests = len(spread)
    families = {_family(name) for name in spread}
    size = {fam: sum(_family(name) == fam for name in spread) for fam in families}

    def cut(fam: str) -> float:  # alpha split evenly over the families, then over each family's tests
        return level / len(families) / max(size[fam], 1)

    failed, scale = [], {}
    for name, (f, nu, nu_rest, p, ratio) in spread.items():
        if p < cut(_family(name)):
            factor = float(np.sqrt(max(ratio, 1.0)))
            failed.append(
                {
                    "test": "spread",
                    "group": name,
                    "ratio": f,
                    "dof": [nu, nu_rest],
                    "p_value": p,
                    "std_factor": factor,
                }
            )
            if name.startswith("laser "):
                scale[int(name.split()[1])] = factor
    return {"level": level, "tests": n_tests, "failed": failed, "shape": shape, "laser_scale": scale}


def _family(name: str) -> str:
    """The family of a group's test: lasers, boards, direct views or rims."""
    if name.startswith("laser "):
        return "lasers"
    if name.startswith("direct view "):
        return "direct views"
    return "rims" if name.endswith(" rim") else "boards"


def kinds_present(kind: np.ndarray) -> list[Kind]:
    return [k for k in Kind if np.any(kind == k)]


def _padded_ids(layout: Layout, n_pad: int) -> np.ndarray:
    """For each real observation (in the unpadded order), its id in the padded problem."""
    return layout.unpad_observations(np.arange(n_pad))
