"""A calibration's report: one self-contained HTML page recomputed from its calibration file.

:func:`write_report` reads a file written by ``slcvjax calibrate`` (one that carries its problem,
:func:`slcvjax.calibration.stored.load_result`) and writes one HTML file, its figures inlined as
base64 PNG, with no external resource:

- a status line: converged or not, the lasers the data could not fix, ``uncertainty.status``;
- the rig in 3D (camera, mirror, laser lines, one view's targets);
- per view, each observation's residual vector on the image (over the image itself where the
  image folder is given), drawn at a stated gain;
- per kind of observation (dot, spot, rim, chess corner), the histogram of the residual
  components with the Gaussian of the kind's sigma, and a normal QQ plot;
- the parameters with their standard deviations (the file's ``uncertainty``), and beside them
  the Cramér–Rao bound at the estimate with the per-kind sigmas;
- the repairs and the outliers;
- the projection uncertainty over the image: per pixel of the mirror's image, the std of the
  point where its reflected ray reaches a range, propagated from the camera's and the mirror's
  covariance;
- the staged start, the joint passes and the options.

Every number in it is the file's or is computed from the file's problem; where the report has to
choose (the range of the uncertainty map, the sigma of a kind the calibration could not estimate)
it says what it chose.
"""

import base64
import html
import io
import json
import logging
import os
import statistics
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ..calibration.bound import cramer_rao
from ..calibration.linearise import residual_rows
from ..calibration.params import Params, pad_params
from ..calibration.result import CalibrationResult, Repair
from ..calibration.stored import load_result
from ..geometry.camera import Camera
from ..geometry.mirror import Mirror, back_project
from ..geometry.rig import CAMERA_DOF, CAMERA_NAMES, MIRROR_DOF, Rig, project_rim
from ..observations.formats import read_calibration
from ..observations.problem import KIND_NAMES, Kind, Layout, Packed
from ..plots import plot_rig, pyplot
from ..support.persist import PersistentJit
from .export import apex_pixel, observed_radii

log = logging.getLogger(__name__)

KIND_TITLES = {
    "dot": "board dots",
    "spot": "laser spots",
    "rim": "rim pixels",
    "chess": "chessboard corners",
    "stripe": "stripe samples",
}
_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


# --------------------------------------------------------------------------- numbers


def _residual_rows(params: Params, pk: Packed):
    """The residual rows of a padded problem without Jacobians: value, observation, kind, use."""
    rows = residual_rows(params, pk)
    return rows.r, rows.obs, rows.kind, rows.present & rows.valid


# compiled once per shape bucket, and kept on disk (the eager rows take seconds)
_rows_jit = PersistentJit(_residual_rows, "report_rows")


def residual_vectors(result: CalibrationResult) -> dict:
    """Each fitted observation's residual (model pixel less observed pixel, px) at the solution.

    Returns a dict of arrays over the observations of ``result.packed`` (dots, spots, rim
    pixels, chessboard corners, in that order): ``kind`` (N,) :class:`Kind`; ``valid`` (N,) the
    model predicts it; ``pixel`` (N, 2) the observed pixel (NaN for a rim pixel, whose residual
    is its distance to the rim's image); ``vector`` (N, 2) the residual (a rim pixel's in its
    first column); ``view`` (N,) the catadioptric view (a chessboard corner's direct view) it
    belongs to; ``board`` (N,) its board's name ('' for a rim pixel or corner); and the residual
    components with their kinds, one per scalar row (the two coordinates of a point, a rim
    pixel's distance), valid rows only: ``rows_r``, ``rows_kind``.  The rows are those of the
    calibration's cost (:func:`slcvjax.calibration.linearise.residual_rows`, evaluated on the
    problem padded to its shape bucket).
    """
    pk = result.packed
    layout = Layout.of(pk, n_lasers=result.rig.lasers.n, sheet_dim=result.rig.sheet_dim)
    r, obs, kind_r, use = (np.asarray(a) for a in _rows_jit(pad_params(layout, result.params), layout.pad_packed(pk)))
    n_pad = int(sum(layout.cap[:4])) + (layout.stripes[1] if layout.stripes is not None else 0)
    vector = np.full((n_pad, 2), np.nan)
    valid = np.zeros(n_pad, bool)
    order = np.argsort(obs[use], kind="stable")
    ids, rr = obs[use][order], r[use][order]
    first = np.ones(ids.size, bool)
    first[1:] = ids[1:] != ids[:-1]
    vector[ids[first], 0] = rr[first]
    vector[ids[~first], 1] = rr[~first]
    valid[ids] = True
    vector = np.stack([layout.unpad_observations(vector[:, j]) for j in range(2)], axis=1)
    valid = layout.unpad_observations(valid)
    counts = [int(c) for c in np.asarray(pk.counts)]
    n = sum(counts)
    kind = np.repeat(np.arange(len(counts)), counts)
    n_d, n_s, n_r = counts[: Kind.CHESS]
    parts = [
        np.asarray(pk.dot_pixels),
        np.asarray(pk.spot_pixels),
        np.full((n_r, 2), np.nan),
        np.asarray(pk.chess_pixels),
    ]
    if pk.has_stripes:
        parts.append(np.asarray(pk.stripe_pixels))
    pixel = np.concatenate(parts)
    view = np.full(n, -1)
    board = np.full(n, "", dtype=object)
    for i, k in enumerate(np.asarray(pk.dot_pose)):
        view[i], board[i] = pk.pose_keys[k]
    for j, k in enumerate(np.asarray(pk.spot_pose)):
        view[n_d + j], board[n_d + j] = pk.pose_keys[k]
    for j, k in enumerate(np.asarray(pk.chess_pose)):
        view[n_d + n_s + n_r + j] = pk.chess_keys[k]
    if pk.has_stripes:
        first = sum(counts[:4])
        for j, k in enumerate(np.asarray(pk.stripe_pose)):
            view[first + j], board[first + j] = pk.pose_keys[k]
    one = (kind == Kind.RIM) | (kind == Kind.STRIPE)  # a distance from a curve: one component
    comp = np.concatenate([vector[valid & ~one].ravel(), vector[valid & one, 0]])
    comp_kind = np.concatenate([np.repeat(kind[valid & ~one], 2), kind[valid & one]])
    return {
        "kind": kind,
        "valid": valid,
        "pixel": pixel,
        "vector": vector,
        "view": view,
        "board": board,
        "rows_r": comp,
        "rows_kind": comp_kind,
    }


def _outlier_mask(result: CalibrationResult, outliers: list[dict]) -> np.ndarray:
    """Which observations of ``result.packed`` the file's ``residuals.outliers`` lists."""
    pk, obs = result.packed, result.observations
    n = int(np.sum(np.asarray(pk.counts)))
    out = np.zeros(n, bool)
    n_d = int(pk.counts[Kind.DOT])
    names = [v.name for v in obs.views] if obs is not None else []
    dots = {(names[v], b, int(j)): i for i, (v, b, j) in enumerate(pk.dot_src) if v >= 0}
    spots = {(names[v], int(j)): n_d + i for i, (v, j) in enumerate(pk.spot_src) if v >= 0}
    for o in outliers:
        i = dots.get((o["view"], o["board"], o["index"])) if o["kind"] == "dot" else spots.get((o["view"], o["index"]))
        if i is not None:
            out[i] = True
    return out


def _point_jacobians(camera: Camera, mirror: Mirror, grid, range_mm):
    """Per pixel of ``grid`` (n, 2): the Jacobian (3 x 15) of the point at ``range_mm`` along its
    reflected ray with respect to the camera's and the mirror's tangent, and its validity."""
    c = CAMERA_DOF

    def point(delta, uv):
        ray = back_project(camera.retract(delta[:c]), mirror.retract(delta[c:]), uv)
        m, d = ray.point, ray.direction
        md = jnp.dot(m, d)
        disc = md * md - jnp.dot(m, m) + range_mm**2
        s = -md + jnp.sqrt(jnp.maximum(disc, 0.0))
        return m + s * d, ray.valid & (disc > 0.0) & (s > 0.0)

    def one(uv):
        zero = jnp.zeros(CAMERA_DOF + MIRROR_DOF)
        return jax.jacfwd(lambda d: point(d, uv)[0])(zero), point(zero, uv)[1]

    return jax.vmap(one)(grid)


# one program per camera and mirror kind (the grid has a fixed size), kept on disk
_jacobians_jit = PersistentJit(_point_jacobians, "report_projection")


def rim_grid(rig: Rig, n_grid: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """The columns and rows (px) of an ``n_grid`` x ``n_grid`` grid over the bounding box of the
    mirror rim's image, within the sensor."""
    uv_rim, ok = project_rim(rig, jnp.linspace(0.0, 2 * np.pi, 360, endpoint=False))
    rim = np.asarray(uv_rim)[np.asarray(ok)]
    w, h = int(rig.camera.width), int(rig.camera.height)
    if len(rim):
        lo = np.maximum(rim.min(axis=0), 0.0)
        hi = np.minimum(rim.max(axis=0), [w - 1.0, h - 1.0])
    else:
        lo, hi = np.zeros(2), np.array([w - 1.0, h - 1.0])
    return np.linspace(lo[0], hi[0], n_grid), np.linspace(lo[1], hi[1], n_grid)


def projection_std(rig: Rig, cov_glob, range_mm: float, n_grid: int = 64, grid=None) -> dict:
    """The projection uncertainty over the mirror's image: per pixel of an ``n_grid`` x
    ``n_grid`` grid over the image of the mirror's rim, the std (mm) of the point where the
    pixel's reflected ray reaches ``range_mm`` from the camera's centre, propagated from the
    covariance of the camera and the mirror.

    The point is ``X = M + s d`` (``M`` the mirror point, ``d`` the reflected unit direction of
    :func:`slcvjax.geometry.mirror.back_project`) with ``|X| = range_mm``; its Jacobian ``J``
    (3 x 15) with respect to the rig's camera and mirror tangent (``Rig.retract``'s first
    ``CAMERA_DOF + MIRROR_DOF`` columns) comes from ``jax.jacfwd``, and its std is
    ``sqrt(trace(J C J^T))`` with ``C`` the camera and mirror block of ``cov_glob``: the root of
    the sum of the three coordinates' variances, the pixel itself taken as exact.

    ``grid``: ``(us, vs)``, the grid's columns and rows (px) where given (another calibration's,
    to compare two), else ``n_grid`` of each over the rim's image.

    Returns ``{"u", "v"}`` (the grid's pixel centres, px), ``"std_mm"`` (len(v), len(u), NaN
    where the pixel sees no valid reflected ray or its ray does not reach the range) and
    ``"range_mm"``.
    """
    g = CAMERA_DOF + MIRROR_DOF
    cov = np.asarray(cov_glob, dtype=float)[:g, :g]
    us, vs = rim_grid(rig, n_grid) if grid is None else (np.asarray(grid[0], float), np.asarray(grid[1], float))
    grid = jnp.asarray(np.stack(np.meshgrid(us, vs), axis=-1).reshape(-1, 2))
    jac, valid = _jacobians_jit(rig.camera, rig.mirror, grid, jnp.asarray(float(range_mm)))
    jac, valid = np.asarray(jac), np.asarray(valid)
    var = np.einsum("nij,jk,nik->n", jac, cov, jac)
    std = np.where(valid & np.all(np.isfinite(jac), axis=(1, 2)), np.sqrt(np.maximum(var, 0.0)), np.nan)
    return {"u": us, "v": vs, "std_mm": std.reshape(len(vs), len(us)), "range_mm": float(range_mm)}


def _sigmas(residuals: dict) -> tuple[list[float], list[str]]:
    """Each kind's sigma for the bound (the file's ``by_kind_sigma_px``) and, per kind, where it
    comes from: a kind the calibration gave no sigma takes the pooled ``sigma_px``."""
    pooled = float(residuals["sigma_px"])
    out, said = [], []
    for k in (k for k in KIND_NAMES if k in residuals["by_kind_sigma_px"]):
        s = residuals["by_kind_sigma_px"].get(k)
        out.append(pooled if s is None else float(s))
        said.append("pooled sigma (the kind has too few free rows for its own)" if s is None else "its own")
    return out, said


# --------------------------------------------------------------------------- figures


def _png(fig, dpi: int = 100) -> str:
    """A matplotlib figure as an inline ``<img>`` (base64 PNG); closes the figure."""
    plt = pyplot()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return _img(buf.getvalue())


def _img(png: bytes, alt: str = "figure") -> str:
    data = base64.b64encode(png).decode("ascii")
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


def _rig_figure(result: CalibrationResult, cal, obs) -> tuple[str, str]:
    """The rig in 3D with the targets of the view that sees the most boards; returns the image and
    its caption."""
    import tempfile

    view = max(range(len(cal.board_poses)), key=lambda v: len(cal.board_poses[v]), default=None)
    walls = [] if view is None else [(b, T, obs.boards[b]) for b, T in cal.board_poses[view].items()]
    with tempfile.TemporaryDirectory() as tmp:
        path = plot_rig(
            result.rig,
            Path(tmp) / "rig.png",
            walls=walls,
            title="Camera, mirror and laser lines"
            + ("" if view is None else f" with view {obs.views[view].name}'s targets"),
            omit=result.undetermined_lasers,
        )
        img = _img(path.read_bytes(), "the rig in 3D")
    held = result.undetermined_elements
    cap = "Camera frame (x red, y green, z blue), the mirror and each laser's line drawn to the target it meets."
    if held:
        cap += f" Not drawn: laser {', '.join(map(str, held))} (undetermined)."
    return img, cap


def _load_images(folder: Path | None, names: list[str]) -> dict[str, np.ndarray]:
    """The images of ``names`` (view names: image file stems) in ``folder``, as OpenCV reads them
    (BGR); the file names come from the folder's ``setup.json`` where it has one."""
    if folder is None:
        return {}
    import cv2

    folder = Path(folder)
    files: dict[str, Path] = {}
    setup = folder / "setup.json"
    if setup.is_file():
        from ..images.detect import read_setup

        s = read_setup(setup)
        for f in list(s.views) + [im for im, _ in s.chessboard_views]:
            files[Path(f).stem] = folder / f
    for p in sorted(folder.iterdir()) if folder.is_dir() else []:
        if p.suffix.lower() in _IMAGE_SUFFIXES:
            files.setdefault(p.stem, p)
            files.setdefault(p.name, p)
    out = {}
    for n in names:
        # a view is named by its image's file name (omni, detect) or its stem
        f = files.get(n) or files.get(Path(n).stem)
        if f is not None and f.is_file():
            img = cv2.imread(str(f), cv2.IMREAD_COLOR)
            if img is not None:
                out[n] = img
    return out


def _gain(norms: np.ndarray) -> float:
    """A round gain that draws the median residual about 15 px long."""
    med = float(np.median(norms)) if norms.size else 0.0
    return min((g for g in (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000) if g * med >= 15.0), default=1000.0)


def _scale_bar(gain: float, length_px: float) -> float:
    """The round residual (px: 1, 2 or 5 times a power of ten) drawn closest to ``length_px`` long at ``gain``."""
    target = length_px / gain
    e = np.floor(np.log10(target))
    choices = [m * 10.0**k for k in (e - 1, e, e + 1) for m in (1, 2, 5)]
    return float(min(choices, key=lambda c: abs(np.log(c / target))))


def _view_figure(name, size, image, rim_model, pts, vec, kinds, outlier, rim_pixels, gain, title) -> str:
    """One view: the image (or a grey canvas), the observed points, their residuals at ``gain``
    and a scale arrow of 1 px of residual; a catadioptric view (``rim_model`` given) is cropped to
    the image of the mirror's rim where that encloses the view's points (a rim the images do not
    show, such as the placeholder radius of a calibration whose rim is unknown, leaves the whole
    image)."""
    plt = pyplot()
    w, h = size
    x0, y0, x1, y1 = 0.0, 0.0, float(w), float(h)
    seen = pts[np.all(np.isfinite(pts), axis=1)]
    rim_ok = rim_model is not None and len(rim_model) > 2 and np.all(np.isfinite(rim_model))
    if rim_ok:  # the rim's image encloses what the view saw through the mirror
        from matplotlib.path import Path as Polygon

        rim_ok = bool(np.all(Polygon(rim_model).contains_points(seen))) and bool(
            np.all((rim_model > -0.5 * w) & (rim_model < 1.5 * np.array([w, h])))
        )
    if rim_ok:
        pad = 0.04 * float(np.ptp(rim_model[:, 0]))
        x0, y0 = np.maximum(rim_model.min(axis=0) - pad, 0.0)
        x1, y1 = np.minimum(rim_model.max(axis=0) + pad, [w, h])
    fig, ax = plt.subplots(figsize=(5.0, 5.0 * (y1 - y0) / (x1 - x0)))
    if image is not None:
        ax.imshow(image[..., ::-1], interpolation="nearest")
    else:
        ax.imshow(np.full((h, w), 0.93), cmap="gray", vmin=0, vmax=1, interpolation="nearest")
    if rim_model is not None and len(rim_model):
        ax.plot(*np.vstack([rim_model, rim_model[:1]]).T, "-", lw=0.6, color="magenta")
    if rim_pixels is not None and len(rim_pixels):
        ax.plot(*rim_pixels.T, ".", ms=1.0, color="tab:cyan")
    style = {Kind.DOT: ("o", "tab:green", 3), Kind.SPOT: ("P", "gold", 5), Kind.CHESS: ("s", "tab:blue", 2.5)}
    for k, (marker, color, ms) in style.items():
        sel = kinds == k
        if np.any(sel):
            ax.plot(*pts[sel].T, marker, ms=ms, mfc="none", mec=color, mew=0.8, ls="none")
    ok = np.all(np.isfinite(vec), axis=1)
    d = vec * gain
    ax.quiver(
        pts[ok, 0], pts[ok, 1], d[ok, 0], d[ok, 1], angles="xy", scale_units="xy", scale=1, color="red", width=0.003
    )
    if np.any(outlier):
        ax.plot(*pts[outlier].T, "o", ms=9, mfc="none", mec="darkorange", mew=1.2, ls="none")
    # the scale: an arrow of 1 px of residual
    # the scale: an arrow of a round residual drawn about a tenth of the panel's width
    bar = _scale_bar(gain, 0.1 * (x1 - x0))
    ax0, ay0 = x0 + 0.03 * (x1 - x0), y1 - 0.04 * (y1 - y0)
    box = {"facecolor": "white", "alpha": 0.8, "edgecolor": "none", "pad": 1.5}
    ax.annotate(
        "", xy=(ax0 + bar * gain, ay0), xytext=(ax0, ay0), arrowprops={"arrowstyle": "->", "color": "red", "lw": 1.4}
    )
    ax.text(ax0, ay0 - 0.025 * (y1 - y0), f"{bar:g} px residual (x{gain:g})", color="red", fontsize=7, bbox=box)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y1, y0)
    ax.set_title(title, fontsize=8)
    ax.axis("off")
    return _png(fig, dpi=110)


def _histograms(rows_r, rows_kind, sigmas: list[float], said: list[str]) -> str:
    """Per kind: the histogram of the residual components with the Gaussian of its sigma, and the
    normal QQ plot of the components over that sigma."""
    plt = pyplot()
    present = [k for k in Kind if np.any(rows_kind == k)]
    fig, axs = plt.subplots(2, max(len(present), 1), figsize=(3.3 * max(len(present), 1), 6.0), squeeze=False)
    nd = statistics.NormalDist()
    for c, k in enumerate(present):
        r = rows_r[rows_kind == k]
        s = sigmas[k]
        ax = axs[0, c]
        lim = max(4.5 * s, float(np.max(np.abs(r))) if r.size else s)
        bins = np.linspace(-lim, lim, int(np.clip(np.sqrt(r.size) * 1.5, 10, 60)))
        ax.hist(r, bins=bins, density=True, color="tab:blue", alpha=0.6)
        x = np.linspace(-lim, lim, 300)
        ax.plot(x, np.exp(-0.5 * (x / s) ** 2) / (s * np.sqrt(2 * np.pi)), "k-", lw=1.2)
        own = said[k] == "its own"
        ax.set_title(
            f"{KIND_TITLES[k.label]}: {r.size} components\nGaussian sigma {s:.3g} px{'' if own else ' (pooled)'}",
            fontsize=9,
        )
        ax.set_xlabel("residual component (px)")
        ax.set_ylabel("density")
        ax = axs[1, c]
        z = np.sort(r / s)
        q = np.array([nd.inv_cdf((i + 0.5) / z.size) for i in range(z.size)])
        ax.plot(q, z, ".", ms=2.5, color="tab:blue")
        m = max(float(np.max(np.abs(q))), 1.0)
        ax.plot([-m, m], [-m, m], "k-", lw=0.8)
        ax.set_xlabel("normal quantile")
        ax.set_ylabel(f"residual / {s:.3g} px")
        ax.set_title("normal QQ plot", fontsize=9)
    fig.tight_layout()
    return _png(fig)


def _projection_figure(proj: dict, rim_model, size) -> str:
    """The projection uncertainty map with its colour bar."""
    plt = pyplot()
    w, h = size
    fig, ax = plt.subplots(figsize=(6.4, 6.4 * h / w))
    u, v, s = proj["u"], proj["v"], proj["std_mm"]
    du = (u[1] - u[0]) / 2 if len(u) > 1 else 0.5
    dv = (v[1] - v[0]) / 2 if len(v) > 1 else 0.5
    finite = s[np.isfinite(s)]
    # the colours span the 2nd to 98th percentiles: near the mirror's axis, where the surface is
    # singular, a few pixels would otherwise take the whole scale (the bar's ends say so)
    lo, hi = np.percentile(finite, [2, 98]) if finite.size else (0.0, 1.0)
    im = ax.imshow(
        s,
        extent=(u[0] - du, u[-1] + du, v[-1] + dv, v[0] - dv),
        origin="upper",
        cmap="viridis",
        interpolation="nearest",
        vmin=lo,
        vmax=hi,
    )
    if rim_model is not None and len(rim_model):
        ax.plot(*np.vstack([rim_model, rim_model[:1]]).T, "-", lw=0.8, color="magenta")
    ax.set_xlim(u[0] - du, u[-1] + du)
    ax.set_ylim(v[-1] + dv, v[0] - dv)
    ax.set_aspect("equal")
    ax.set_xlabel("u (px)")
    ax.set_ylabel("v (px)")
    ax.set_title(f"std of the point at {proj['range_mm']:.1f} mm along each pixel's reflected ray", fontsize=9)
    below, above = bool(finite.size and finite.min() < lo), bool(finite.size and finite.max() > hi)
    extend = {(True, True): "both", (True, False): "min", (False, True): "max"}.get((below, above), "neither")
    cb = fig.colorbar(im, ax=ax, shrink=0.85, extend=extend)
    cb.set_label("std (mm)")
    return _png(fig)


# --------------------------------------------------------------------------- HTML


def _fmt(x, digits: int = 4) -> str:
    """A number as text (``-`` for None; ``nan`` stays visible)."""
    if x is None:
        return "–"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int | np.integer):
        return str(int(x))
    if isinstance(x, float | np.floating):
        return f"{float(x):.{digits}g}"
    if isinstance(x, list | tuple):
        return "(" + ", ".join(_fmt(v, digits) for v in x) + ")"
    return html.escape(str(x))


def _table(header: list[str], rows: list[list], cls: str = "") -> str:
    """An HTML table of already formatted cells (strings are escaped, numbers formatted)."""
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)

    def cell(c) -> str:
        numeric = isinstance(c, int | float | np.integer | np.floating) and not isinstance(c, bool)
        vector = isinstance(c, list | tuple)
        cls = ' class="num"' if numeric else (' class="vec"' if vector else "")
        return f"<td{cls}>{_fmt(c)}</td>"

    body = "".join("<tr>" + "".join(cell(c) for c in r) + "</tr>" for r in rows)
    return f'<table class="{cls}"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:1.5em auto;max-width:1200px;
color:#222;padding:0 1em;line-height:1.4}
h1{font-size:1.5em;margin-bottom:.2em} h2{border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.8em}
.status{padding:.7em 1em;border-radius:6px;font-weight:600;margin:.8em 0}
.ok{background:#e6f4ea;border:1px solid #7cb98a} .bad{background:#fdecea;border:1px solid #e08a80}
.warn{background:#fff6e0;border:1px solid #e0c070}
table{border-collapse:collapse;margin:.6em 0;font-size:.88em} th,td{border:1px solid #ddd;padding:3px 7px;
text-align:left;vertical-align:top} th{background:#f3f3f3} td.num{text-align:right;font-variant-numeric:tabular-nums}
td.vec{white-space:nowrap;font-variant-numeric:tabular-nums}
.grid{display:grid;grid-template-columns:repeat(auto-fill,minmax(360px,1fr));gap:10px}
.grid figure{margin:0} img{max-width:100%;height:auto} figcaption,.note{font-size:.85em;color:#555}
code{background:#f4f4f4;padding:0 3px} .row{display:flex;flex-wrap:wrap;gap:1.2em;align-items:flex-start}
"""


# the repairs' columns, in order; the other fields are shown where a repair has them
_REPAIR_COLUMNS = (
    "kind", "view", "board", "index", "laser", "action", "residual_px", "new_laser", "new_index",
    "new_residual_px", "reason", "whole_board",
)  # fmt: skip
_REPAIR_ALWAYS = ("kind", "view", "board", "index", "action", "residual_px", "reason")


def _repair_table(repairs: tuple[Repair, ...], empty: str) -> str:
    """The repairs as a table: a row per :class:`Repair`, a column per field that any of them has
    (``whole_board``: where it holds)."""
    if not repairs:
        return f"<p class='note'>{empty}</p>"

    def cell(r: Repair, name: str):
        value = getattr(r, name)
        return None if value is False else value

    cols = [c for c in _REPAIR_COLUMNS if c in _REPAIR_ALWAYS or any(cell(r, c) is not None for r in repairs)]
    return _table(list(cols), [[cell(r, c) for c in cols] for r in repairs])


def _section(sid: str, title: str, body: str) -> str:
    return f'<section id="{sid}"><h2>{html.escape(title)}</h2>\n{body}\n</section>\n'


def report_html(
    path: str | os.PathLike,
    images: str | os.PathLike | None = None,
    range_mm: float | None = None,
    n_grid: int = 64,
) -> str:
    """The report of the calibration file ``path`` as one self-contained HTML page (see the
    module docstring).

    Args:
        path: a ``slcv-calibration/1`` file that carries its problem (``slcvjax calibrate``).
        images: the image folder the observations were detected in (its ``setup.json`` names
            the files; else a view's image is the file whose stem is the view's name): the
            residuals are drawn over the images. None: over a grey canvas.
        range_mm: the range of the projection uncertainty map (default: the mean working range
            of the determined lasers, else the mean distance of the first view's board points).
        n_grid: the map's grid of pixels is ``n_grid`` x ``n_grid`` over the mirror's image.
    """
    path = Path(path)
    doc = json.loads(path.read_text())
    result = load_result(path)
    obs = result.observations
    if obs is None:
        raise ValueError(f"{path}: problem.observations: the file carries no observations to draw")
    cal = read_calibration(path)  # the rig and board poses as the file gives them
    res, unc = doc["residuals"], doc["uncertainty"]
    stages = doc["stages"]
    size = (int(result.rig.camera.width), int(result.rig.camera.height))
    sections = []

    # status ---------------------------------------------------------------------------------
    converged = bool(unc.get("converged"))
    held = list(result.undetermined_elements)
    lines = [
        "Converged: the last pass reached a minimum."
        if converged
        else "NOT converged: " + html.escape(unc.get("status", "the last pass did not converge"))
    ]
    if held:
        lines.append(
            f"Undetermined lasers: {', '.join(map(str, held))} (their spots cannot fix a line; held, not used)."
        )
    if converged and unc.get("status"):
        lines.append(html.escape(unc["status"]))
    for i, las in enumerate(unc["lasers"]):
        if las.get("status") and i not in held:
            lines.append(f"Laser {i}: {html.escape(las['status'])}")
    cls = "ok" if converged and not held and len(lines) == 1 else ("bad" if not converged else "warn")
    n_out, n_rep = len(res.get("outliers", [])), len(result.repairs)
    summary = (
        f"RMS reprojection error {_fmt(res['rms_px'])} px over the valid observations; noise sigma "
        f"{_fmt(res['sigma_px'])} px ({res['dof']} degrees of freedom); {len(obs.views)} catadioptric and "
        f"{len(result.packed.chess_keys)} direct views; {result.rig.n_elements} lasers; loss {res['loss']['kind']} at "
        f"{_fmt(res['loss']['scale_px'])} px; {n_rep} repairs, {n_out} outliers, {res['invalid']} observations "
        "the model cannot predict."
    )
    status = f'<div class="status {cls}" id="status-line">' + "<br>".join(lines) + "</div>"
    status += f'<p class="note">{summary}</p>'

    # the rig --------------------------------------------------------------------------------
    img, cap = _rig_figure(result, cal, obs)
    sections.append(_section("rig", "The rig", f"<figure>{img}<figcaption>{cap}</figcaption></figure>"))

    # residual vectors per view --------------------------------------------------------------
    rv = residual_vectors(result)
    outlier = _outlier_mask(result, res.get("outliers", []))
    names = [v.name for v in obs.views] + [c.name for c in obs.calibration_views]
    pictures = _load_images(Path(images) if images is not None else None, names)
    point = rv["valid"] & (rv["kind"] != Kind.RIM)
    gain = _gain(np.linalg.norm(rv["vector"][point], axis=1))
    uv_rim, ok_rim = project_rim(result.rig, jnp.linspace(0.0, 2 * np.pi, 360, endpoint=False))
    rim_model = np.asarray(uv_rim)[np.asarray(ok_rim)]
    figs = []
    cat = rv["kind"] != Kind.CHESS
    for v, vo in enumerate(obs.views):
        # a stripe sample's residual is a distance across its curve: counted in the RMS, not drawn
        sel = cat & (rv["view"] == v) & (rv["kind"] != Kind.RIM) & (rv["kind"] != Kind.STRIPE)
        rms = res["per_view_rms_px"].get(vo.name)
        title = f"{vo.name}: RMS {_fmt(rms)} px (dots and spots" + (", stripe samples)" if vo.stripes else ")")
        rim_px = vo.rim if len(vo.rim) else None
        img = _view_figure(
            vo.name, size, pictures.get(vo.name), rim_model, rv["pixel"][sel], rv["vector"][sel],
            rv["kind"][sel], outlier[sel], rim_px, gain, title,
        )  # fmt: skip
        figs.append(f"<figure>{img}</figure>")
    chess = rv["kind"] == Kind.CHESS
    for c in result.packed.chess_keys:
        name = obs.calibration_views[c].name
        sel = chess & (rv["view"] == c)
        rms = res["per_direct_view_rms_px"].get(name)
        img = _view_figure(
            name, size, pictures.get(name), None, rv["pixel"][sel], rv["vector"][sel], rv["kind"][sel],
            outlier[sel], None, gain, f"{name} (direct view): RMS {_fmt(rms)} px",
        )  # fmt: skip
        figs.append(f"<figure>{img}</figure>")
    over = (
        f"over the images of <code>{html.escape(str(images))}</code> ({len(pictures)} of {len(names)} found)"
        if images is not None
        else "on a grey canvas of the image's size (give <code>--images DIR</code> to draw over the images)"
    )
    body = (
        f'<p class="note">Each fitted observation\'s residual (model pixel less observed pixel) drawn as a red arrow '
        f"<b>{gain:g} times its length</b> (the arrow at the bottom left: a residual of the length it states), "
        f"{over}. Dots: green circles; spots: yellow crosses; chessboard corners: blue squares; the mirror rim's "
        "model image: magenta; its detected edge pixels: cyan; the listed outliers: orange rings. Left-out "
        "observations are not drawn (see the repairs).</p>"
        f'<div class="grid">{"".join(figs)}</div>'
    )
    sections.append(_section("residual-vectors", "Residuals on the image", body))

    # histograms -----------------------------------------------------------------------------
    sigmas, said = _sigmas(res)
    img = _histograms(rv["rows_r"], rv["rows_kind"], sigmas, said)
    kind_rows = [
        [KIND_TITLES[k], res["by_kind_rms_px"].get(k), res["by_kind_sigma_px"].get(k)]
        for k in KIND_NAMES
        if k in res["by_kind_sigma_px"]
    ]
    body = (
        f"<figure>{img}<figcaption>Top: each kind's residual components (u and v of a point, a rim pixel's "
        "distance to the rim's image), with the Gaussian of the kind's estimated sigma. Bottom: the components "
        "over that sigma against the normal quantiles: on the line where the noise is Gaussian of that "
        "sigma.</figcaption></figure>"
        + '<div class="row">'
        + _table(["kind", "RMS of the residual norms (px)", "sigma (px)"], kind_rows)
        + _table(["view", "RMS (px)"], [[k, v] for k, v in res["per_view_rms_px"].items()])
        + _table(["laser", "RMS of its spots (px)"], [[k, v] for k, v in res["per_laser_rms_px"].items()])
        + _table(["board", "RMS of its dots (px)"], [[k, v] for k, v in res["per_board_rms_px"].items()])
        + "</div>"
    )
    sections.append(_section("histograms", "Residual distributions", body))

    # parameters -----------------------------------------------------------------------------
    bound_note, crb = "", None
    try:
        rigid = result.options.rigid if result.box is not None else False
        crb = cramer_rao(cal, obs, sigmas, packed=result.packed, rigid=rigid)
    except Exception as e:  # the report still shows the rest; it says why the bound is missing
        log.warning(f"{path}: the Cramér–Rao bound could not be computed: {e}")
        bound_note = f"<p class='status bad'>The bound could not be computed: {html.escape(str(e))}</p>"
    crb_sd = np.sqrt(np.maximum(np.diag(np.asarray(crb["cov"].glob)), 0.0)) if crb is not None else None
    glob_mask = np.asarray(result.masks.glob)
    cam = doc["camera"]
    K, dist = cam["K"], cam["dist"]
    values = dict(zip(("fx", "fy", "cx", "cy"), (K[0][0], K[1][1], K[0][2], K[1][2]), strict=True))
    values |= dict(zip(("k1", "k2", "p1", "p2", "k3"), dist, strict=True))
    cam_rows = [
        [
            n,
            values[n],
            unc["camera_std"][n] if glob_mask[i] else "held fixed",
            crb_sd[i] if crb_sd is not None and glob_mask[i] else "–",
        ]
        for i, n in enumerate(CAMERA_NAMES)
    ]
    mir = doc["mirror"]
    ms = unc["mirror_std"]
    c0 = CAMERA_DOF
    mir_rows = [
        [f"apex {a} (mm)", mir["apex"][j], ms["apex_mm"][j], crb_sd[c0 + j] if crb_sd is not None else "–"]
        for j, a in enumerate("xyz")
    ]
    mir_rows += [[f"axis {a}", mir["axis"][j], "", ""] for j, a in enumerate("xyz")]
    mir_rows += [
        [
            f"axis tilt e{j + 1} (deg)",
            "",
            ms["axis_tilt_deg"][j],
            np.degrees(crb_sd[c0 + 3 + j]) if crb_sd is not None else "–",
        ]
        for j in range(2)
    ]
    if "conic_constant" in ms:
        mir_rows.append(
            ["conic constant", mir.get("conic"), ms["conic_constant"], crb_sd[c0 + 5] if crb_sd is not None else "–"]
        )
    shape = ", ".join(f"{k} {_fmt(v)}" for k, v in mir.items() if k not in ("apex", "axis") and not isinstance(v, list))
    las_rows = []
    kinds = [ld.get("kind") or "point" for ld in doc["lasers"]]
    for i, (ld, lu) in enumerate(zip(doc["lasers"], unc["lasers"], strict=True)):
        kind = kinds[i]
        j = sum(k == kind if kind == "point" else k != "point" for k in kinds[:i])  # its index in its collection
        if kind == "point":
            b_pos, b_dir = ("position_std_mm", "direction_std_rad")
            where, along = ld.get("point"), ld.get("direction")
        else:
            b_pos, b_dir = ("sheet_position_std_mm", "sheet_normal_std_rad")
            where = ld.get("point") if kind == "plane" else ld.get("apex")
            along = ld.get("normal") if kind == "plane" else ld.get("axis")
        bound_ok = crb is not None and i not in held and b_pos in crb
        las_rows.append(
            [
                f"{i} ({kind})",
                where,
                along,
                lu["working_range_mm"],
                lu["position_std_mm"],
                lu["direction_std_deg"],
                float(crb[b_pos][j]) if bound_ok else None,
                float(np.degrees(crb[b_dir][j])) if bound_ok else None,
                lu.get("status", ""),
            ]
        )
    sig_text = ", ".join(f"{k} {_fmt(s)} px ({w})" for k, s, w in zip(KIND_NAMES, sigmas, said, strict=False))
    body = (
        f"<p class='note'>Standard deviations from the calibration's covariance (the file's "
        f"<code>uncertainty</code>). <b>Bound</b>: the Cramér–Rao bound evaluated <b>at the estimate, not at the "
        f"truth</b> (the truth is unknown), with each kind's sigma: {sig_text}. It is what an efficient estimator "
        "would reach on this design if the estimate were the truth. Where the robust loss weights no observation "
        "down, it equals the calibration's own covariance (both are the inverse information at the estimate with "
        "these sigmas); a difference shows the rows the loss weighted down.</p>"
        + bound_note
        + "<h3>Camera</h3>"
        + _table(["parameter", "value", "std", "bound"], cam_rows, "camera")
        + f"<h3>Mirror</h3><p class='note'>{shape}</p>"
        + _table(["parameter", "value", "std", "bound"], mir_rows, "mirror")
        + "<h3>Lasers</h3><p class='note'>Each laser's position std is that of its line at its working point "
        "(the point of the line nearest its spots' mean), its direction std the angle's; the bound's at the "
        "same point.</p>"
        + _table(
            [
                "laser",
                "point (mm)",
                "direction",
                "working range (mm)",
                "position std (mm)",
                "direction std (deg)",
                "bound position (mm)",
                "bound direction (deg)",
                "status",
            ],
            las_rows,
            "lasers",
        )
    )
    if unc.get("rigid_box"):
        box = unc["rigid_box"]
        brows = [[b, d["rotation_std_deg"], d["translation_std_mm"]] for b, d in box["boards"].items()]
        body += "<h3>Rigid target box</h3>" + _table(["board", "rotation std (deg)", "translation std (mm)"], brows)
        body += f"<p class='note'>Gauge: {html.escape(str(box['gauge']))}.</p>"
    sections.append(_section("parameters", "Parameters and their uncertainty", body))

    # repairs and outliers -------------------------------------------------------------------
    def records(items: list[dict], empty: str) -> str:
        if not items:
            return f"<p class='note'>{empty}</p>"
        cols = [
            "kind", "view", "board", "index", "laser", "action", "residual_px", "new_laser", "new_index",
            "new_residual_px", "reason",
        ]  # fmt: skip
        cols = [c for c in cols if any(c in it for it in items)]
        cols += sorted({k for it in items for k in it} - set(cols))
        return _table(cols, [[it.get(c) for c in cols] for it in items])

    body = (
        "<h3>Repairs</h3><p class='note'>Observations relabelled or left out before the final pass.</p>"
        + _repair_table(result.repairs, "No observation was repaired or left out.")
        + "<h3>Outliers</h3><p class='note'>Dots and spots kept in the final pass whose residual lies beyond "
        f"{_fmt(result.options.robust.outlier_sigmas)} sigmas of their kind (orange rings on the images).</p>"
        + records(res.get("outliers", []), "No outlier.")
        + f"<p class='note'>Rim pixels beyond that: {res.get('rim_outliers', 0)}; observations the model cannot "
        f"predict: {res['invalid']}.</p>"
    )
    sections.append(_section("repairs", "Repairs and outliers", body))

    # projection uncertainty -----------------------------------------------------------------
    ranges = [las["working_range_mm"] for las in unc["lasers"] if las.get("working_range_mm") is not None]
    if range_mm is not None:
        chosen, why = float(range_mm), "as asked"
    elif ranges:
        chosen, why = float(np.mean(ranges)), f"the mean working range of the {len(ranges)} determined lasers"
    else:
        v0 = next(iter(cal.board_poses[0].items())) if cal.board_poses and cal.board_poses[0] else None
        if v0 is None:
            chosen, why = 100.0, "no laser and no board: a default of 100 mm"
        else:
            pts = np.asarray(v0[1].apply(np.asarray(obs.boards[v0[0]], dtype=float)))
            chosen = float(np.mean(np.linalg.norm(pts, axis=1)))
            why = f"the mean distance of board {v0[0]}'s points in view {obs.views[0].name} (no determined laser)"
    radii = observed_radii(cal)
    grid, where = None, "the mirror's image"
    if radii is not None:  # where the calibration had data: outside it the model is an extrapolation
        c = apex_pixel(result.rig)
        lo = np.maximum(c - radii[1], 0.0)
        hi = np.minimum(c + radii[1], [size[0] - 1.0, size[1] - 1.0])
        grid = (np.linspace(lo[0], hi[0], n_grid), np.linspace(lo[1], hi[1], n_grid))
        where = f"the annulus {radii[0]:.0f}-{radii[1]:.0f} px about the mirror's centre where the calibration had data"
    proj = projection_std(result.rig, result.cov.glob, chosen, n_grid, grid)
    if radii is not None:
        r = np.hypot(*(np.stack(np.meshgrid(proj["u"], proj["v"]), axis=-1) - c).transpose(2, 0, 1))
        proj["std_mm"] = np.where((r >= radii[0]) & (r <= radii[1]), proj["std_mm"], np.nan)
    s = proj["std_mm"]
    finite = s[np.isfinite(s)]
    stats = (
        f"median {_fmt(float(np.median(finite)))} mm, 95th percentile {_fmt(float(np.percentile(finite, 95)))} mm, "
        f"largest {_fmt(float(np.max(finite)))} mm over {finite.size} pixels"
        if finite.size
        else "no pixel of the grid sees a valid reflected ray"
    )
    img = _projection_figure(proj, rim_model, size)
    body = (
        f"<figure>{img}<figcaption>Per pixel of a {n_grid} x {n_grid} grid over {where}, the standard "
        f"deviation (root of the trace of its 3x3 covariance) of the point where the pixel's reflected ray is "
        f"{proj['range_mm']:.1f} mm from the camera's centre ({why}), propagated (<code>jax.jacfwd</code> "
        "through the back-projection) from the covariance of the camera and the mirror; the pixel itself is "
        f"taken as exact. Magenta: the rim's image. {stats}.</figcaption></figure>"
    )
    sections.append(_section("projection-uncertainty", "Projection uncertainty over the image", body))

    # passes and options ---------------------------------------------------------------------
    st = stages.get("staged", {})
    srows = [[r["stage"], r["rms"], r["unit"], "; ".join(r["notes"])] for r in st.get("reports", [])]
    prows = [
        [p["name"], p["steps"], p.get("limit"), p["outcome"], p["cost0"], p["cost"], p["scale"], "; ".join(p["notes"])]
        for p in stages["joint"]["passes"]
    ]
    trows = [[k, v] for k, v in (stages["joint"].get("timings_s") or {}).items()]
    opts = doc["problem"]["options"]
    orows = [[k, json.dumps(v)] for k, v in opts.items() if k != "robust"]
    orows += [[f"robust.{k}", json.dumps(v)] for k, v in (opts.get("robust") or {}).items()]
    body = (
        "<h3>Staged start</h3>"
        + _table(["stage", "RMS", "unit", "notes"], srows)
        + "<h3>Joint passes</h3>"
        + _table(
            ["pass", "steps", "step limit", "outcome", "cost before", "cost after", "loss scale (px)", "notes"], prows
        )
        + ("<h3>Timings</h3>" + _table(["part", "seconds"], trows) if trows else "")
        + "<h3>Options</h3>"
        + _table(["option", "value"], orows)
        + f"<p class='note'>Written by slcvjax {html.escape(str(doc['problem'].get('slcvjax_version')))}.</p>"
    )
    sections.append(_section("passes", "Passes and options", body))

    title = f"Calibration report: {html.escape(path.name)}"
    toc = "".join(
        f'<a href="#{sid}">{t}</a> · '
        for sid, t in [
            ("rig", "rig"), ("residual-vectors", "residuals on the image"), ("histograms", "distributions"),
            ("parameters", "parameters"), ("repairs", "repairs and outliers"),
            ("projection-uncertainty", "projection uncertainty"), ("passes", "passes and options"),
        ]
    )[:-3]  # fmt: skip
    return (
        "<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
        f"<title>{title}</title><style>{_CSS}</style></head><body>\n"
        f"<h1>{title}</h1>{status}<nav class='note'>{toc}</nav>\n" + "".join(sections) + "</body></html>\n"
    )


def write_report(
    path: str | os.PathLike,
    out: str | os.PathLike,
    images: str | os.PathLike | None = None,
    range_mm: float | None = None,
) -> Path:
    """Write the report of the calibration file ``path`` (:func:`report_html`) to ``out``; returns it."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(report_html(path, images, range_mm), encoding="utf-8")
    return out
