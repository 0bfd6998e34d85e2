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

from ..observations.problem import KIND_NAMES, Kind, Layout, kind_weights
from ..support.persist import PersistentJit
from .evaluate import solution_linearisation
from .linearise import chunk_bounds, flat_rows, kind_spans, observation_groups
from .losses import ObservationTable, loss_index, robust_observations
from .result import CalibrationResult
from .schur import schur_inverse


def row_leverages(params, pk, masks, normal, loss, scale):
    """Per scalar residual row of the padded problem ``pk`` at ``params``: its value ``r``, its
    observation id, kind, whether it counts (a real, valid row), and its leverage ``h`` (the
    diagonal of ``W J H^-1 J^T``, ``H = J^T W J`` the normal matrix ``normal`` of the solution,
    ``W`` the robust loss's weights (``loss`` an index of :data:`slcvjax.calibration.losses.LOSSES`,
    ``scale`` px), frozen columns and blocks left out by ``masks``); the leverages add up to the
    number of estimated parameters.  The rows are those of :func:`slcvjax.calibration.linearise.rows_at`,
    in its order; a padded row is zero and does not count.

    With ``H`` in Schur form (``S`` the global block's Schur complement, ``D`` the pose blocks,
    ``B`` their coupling), a row's ``(j_g, j_p)`` on pose block ``b`` has
    ``h = u^T S^-1 u + j_p^T D_b^-1 j_p`` with ``u = j_g - (D_b^-1 B_b^T)^T j_p``.

    The rows are visited chunk by chunk over each group's real observations, as the solve's
    :func:`slcvjax.calibration.linearise.accumulate` visits them (a traced trip count), so a shape
    bucket's padding costs nothing: the whole padded problem at once took 0.17-0.27 s of a
    9-15-view scene's 0.25-0.4 s report (``docs/performance.md``)."""
    import jax
    import jax.numpy as jnp

    s_inv, d_inv, dinv_bt = schur_inverse(normal)
    g = s_inv.shape[0]
    glob_mask = jnp.concatenate([masks.glob, jnp.zeros(1)])
    block_mask = jnp.concatenate([masks.blocks, jnp.zeros(1)])
    coupling_all = jnp.concatenate([dinv_bt, jnp.zeros((1, 6, g))])
    d_all = jnp.concatenate([d_inv, jnp.zeros((1, 6, 6))])
    kw = kind_weights(None)
    parts, offset = [], 0
    for grp in observation_groups(params, pk, True, None):
        n = grp.args[0].shape[0]
        if n == 0:
            continue
        k = min(grp.chunk, n)
        m = grp.fn(*(a[:k] for a in grp.args)).r.shape[1]  # its rows per observation (the trace alone: unused)
        spans = kind_spans(grp.regions, n)
        n_chunks = [(real - s + k - 1) // k for s, _, real in spans]

        def body(i, carry, grp=grp, n=n, k=k, m=m, spans=spans, n_chunks=n_chunks):
            r_out, h_out, kind_out, use_out = carry
            start, meant, real_end = chunk_bounds(spans, n, k, i, n_chunks)
            idx = start + jnp.arange(k)
            present = (idx >= meant) & (idx < real_end)
            c = grp.fn(
                *(jax.lax.dynamic_slice_in_dim(a, start, k) for a in grp.args), spot_chunk=meant >= grp.regions[-1][0]
            )
            rows = flat_rows(c, present, 0)
            t = ObservationTable(jnp.sum(rows.r.reshape(k, m) ** 2, axis=1), c.kind, c.ok & present, present, c.pidx)
            w = robust_observations(t, loss, scale, kw)[0][rows.obs]
            jg = rows.jg * glob_mask[rows.gidx]
            jp = rows.jp * block_mask[rows.pidx][:, None]
            dense = jax.vmap(lambda j, i: jnp.zeros(g + 1).at[i].add(j))(jg, rows.gidx)[:, :g]
            u = dense - jnp.einsum("nkg,nk->ng", coupling_all[rows.pidx], jp)
            h = w * (jnp.einsum("ng,gh,nh->n", u, s_inv, u) + jnp.einsum("nk,nkl,nl->n", jp, d_all[rows.pidx], jp))

            def put(out, new):
                new = new.reshape(k, m)
                old = jax.lax.dynamic_slice_in_dim(out, start, k)
                return jax.lax.dynamic_update_slice_in_dim(out, jnp.where(present[:, None], new, old), start, 0)

            use = rows.present & rows.valid
            return put(r_out, rows.r), put(h_out, h), put(kind_out, rows.kind), put(use_out, use)

        zeros = jnp.zeros((n, m))
        carry = (zeros, zeros, jnp.zeros((n, m), dtype=int), jnp.zeros((n, m), dtype=bool))
        r, h, kind, use = jax.lax.fori_loop(0, sum(n_chunks), body, carry)
        obs = jnp.broadcast_to(offset + jnp.arange(n)[:, None], (n, m))
        parts.append(tuple(a.reshape(-1) for a in (r, obs, kind, use, h)))
        offset += n
    return tuple(jnp.concatenate(p) for p in zip(*parts, strict=True))


_leverage_jit = PersistentJit(row_leverages, "row_leverages")


def per_observation_rows(result: CalibrationResult) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per observation of ``result.packed`` (dots, spots, rim pixels, corners, stripe samples, in
    that order): the sum of its rows' squared residuals (px^2), of their ``1 - h`` (the degrees of
    freedom they leave), and per row, its kind, residual and ``1 - h``, for valid rows only."""
    params, pk, masks = result.params, result.packed, result.masks
    layout, p, padded, m, lin = solution_linearisation(params, pk, masks, result.loss, result.scale)
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
    flags.  Returns ``{"level", "tests", "failed": [...], "shape": {kind: {...}}, "laser_scale":
    {laser: factor}}``: each failed test's group and p-value, its variance ratio to the rest of its
    kind (``ratio``), the two degrees of freedom (``dof``) and the std factor; each kind's shape
    (rows, skew, excess kurtosis, normality p-value); the failed lasers' std factors (by their
    index in the file)."""
    from scipy.special import fdtrc  # here: scipy.stats took 0.3-0.9 s of ``import slcvjax``

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
            spread[name] = (f, nu_g, nu_rest, float(fdtrc(nu_g, nu_rest, f)), ratio)  # P(F >= f)
    # the kinds' shape, per row: the rows of the kept observations
    kept_obs = np.zeros(n_pad, bool)
    kept_obs[_padded_ids(layout, n_pad)[keep]] = True
    shape = {}
    for k in kinds_present(kind):
        sel = kept_obs[row_obs] & (row_kind == k) & (row_free > 1e-6)
        if sel.sum() >= 20:
            z = row_r[sel] / (np.sqrt(_kind_sigma(result, k) ** 2 * row_free[sel]))
            d = z - z.mean()
            m2 = np.mean(d**2)
            shape[KIND_NAMES[k]] = {
                "rows": int(sel.sum()),
                "skew": float(np.mean(d**3) / m2**1.5),
                "excess_kurtosis": float(np.mean(d**4) / m2**2 - 3.0),
                "p_value": normality_p(z),
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


def normality_p(z: np.ndarray) -> float:
    """D'Agostino and Pearson's omnibus test that ``z`` (at least 20 values) is normal: the p-value
    of ``K^2 = Z_skew^2 + Z_kurt^2``, chi-squared with 2 degrees of freedom under the null
    (so ``p = exp(-K^2 / 2)``).  ``Z_skew``: D'Agostino's (1970) transform of the sample skewness
    ``sqrt(b1)``; ``Z_kurt``: Anscombe and Glynn's (1983) of the sample kurtosis ``b2`` (both as
    D'Agostino, Belanger and D'Agostino, The American Statistician 44 (1990) 316, give them).
    The same test as ``scipy.stats.normaltest`` (agreeing to round-off, tested) without importing
    ``scipy.stats``."""
    x = np.asarray(z, dtype=float)
    n = float(x.size)
    d = x - x.mean()
    m2, m3, m4 = (np.mean(d**2), np.mean(d**3), np.mean(d**4))
    # skewness
    y = m3 / m2**1.5 * np.sqrt((n + 1) * (n + 3) / (6 * (n - 2)))
    beta2 = 3 * (n**2 + 27 * n - 70) * (n + 1) * (n + 3) / ((n - 2) * (n + 5) * (n + 7) * (n + 9))
    w2 = -1 + np.sqrt(2 * (beta2 - 1))
    delta = 1 / np.sqrt(0.5 * np.log(w2))
    alpha = np.sqrt(2 / (w2 - 1))
    ya = (y if y != 0 else 1.0) / alpha  # a skewness of exactly 0 taken as y = 1, as scipy does
    z_skew = delta * np.log(ya + np.sqrt(ya**2 + 1))
    # kurtosis
    b2 = m4 / m2**2
    mean_b2 = 3 * (n - 1) / (n + 1)
    var_b2 = 24 * n * (n - 2) * (n - 3) / ((n + 1) ** 2 * (n + 3) * (n + 5))
    xk = (b2 - mean_b2) / np.sqrt(var_b2)
    skew_b2 = 6 * (n**2 - 5 * n + 2) / ((n + 7) * (n + 9)) * np.sqrt(6 * (n + 3) * (n + 5) / (n * (n - 2) * (n - 3)))
    a = 6 + 8 / skew_b2 * (2 / skew_b2 + np.sqrt(1 + 4 / skew_b2**2))
    t = 1 + xk * np.sqrt(2 / (a - 4))
    cube = np.sign(t) * np.cbrt((1 - 2 / a) / abs(t)) if t != 0 else np.nan  # undefined, as in scipy
    z_kurt = (1 - 2 / (9 * a) - cube) / np.sqrt(2 / (9 * a))
    return float(np.exp(-0.5 * (z_skew**2 + z_kurt**2)))


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
