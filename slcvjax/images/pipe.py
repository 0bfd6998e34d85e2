"""The paper's pipe experiment: the sensor inside a pipe, spots measured, diameter fitted.

The sensor sits at ``n_poses`` positions inside a straight pipe of the given
diameter (150 mm in the paper).  The pipe's axis is parallel to the camera's z
axis by default (as the paper assumes when it fits the circle in the camera's
xy plane) and passes at a random offset from the camera centre; a tilt can be
given.  Each laser's beam meets the pipe wall once (the emitter is inside); the
spot is projected through the mirror, and only spots that are really visible
are written.
"""

import dataclasses
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from ..geometry.mirror import ConeMirror, project_through_mirror, shape_json
from ..geometry.rig import SHAPE_COLUMN, Rig
from ..measurement.measure import Circle, ViewPoints, fit_circle_3d, measure_spots
from ..observations.formats import Observations, SpotObs, ViewObs
from ..observations.problem import bucket, pad_rows, padded_lasers


@dataclass
class PipeScene:
    """A straight pipe seen by the rig at several poses (all in the camera frame).

    ``centers[i]`` is a point of the pipe's axis in pose ``i`` and ``axes[i]`` its
    unit direction.
    """

    rig: Rig
    diameter: float
    centers: np.ndarray
    axes: np.ndarray


def pipe_scene(
    rig: Rig, diameter: float = 150.0, n_poses: int = 16, max_offset: float = 10.0, tilt_deg: float = 0.0, seed: int = 0
) -> PipeScene:
    """``n_poses`` poses of the rig inside a pipe: axis offsets uniform in a disc of ``max_offset`` mm.

    With ``tilt_deg > 0`` each pose's pipe axis is tilted from the camera's z axis
    by that angle towards a random azimuth.
    """
    if not np.isfinite(diameter) or diameter <= 0:
        raise ValueError(f"pipe diameter must be positive, got {diameter}")
    if n_poses < 1:
        raise ValueError(f"n_poses must be at least 1, got {n_poses}")
    rng = np.random.default_rng(seed)
    r = max_offset * np.sqrt(rng.uniform(0, 1, n_poses))
    phi = rng.uniform(0, 2 * np.pi, n_poses)
    centers = np.stack([r * np.cos(phi), r * np.sin(phi), np.zeros(n_poses)], axis=1)
    az = rng.uniform(0, 2 * np.pi, n_poses)
    t = np.radians(tilt_deg)
    axes = np.stack([np.sin(t) * np.cos(az), np.sin(t) * np.sin(az), np.full(n_poses, np.cos(t))], axis=1)
    return PipeScene(rig, float(diameter), centers, axes)


def beam_pipe_point(p, d, center, axis, radius):
    """Where the beam ``p + lam d`` (lam > 0) meets the cylinder; ``(x, ok)``."""
    w = p - center
    wp = w - jnp.dot(w, axis) * axis
    dp = d - jnp.dot(d, axis) * axis
    a = jnp.dot(dp, dp)
    b = 2.0 * jnp.dot(wp, dp)
    c = jnp.dot(wp, wp) - radius**2
    disc = b * b - 4.0 * a * c
    ok = (a > 1e-12) & (disc >= 0.0) & (c < 0.0)  # the emitter is inside the pipe
    lam = (-b + jnp.sqrt(jnp.where(ok, disc, 0.0))) / (2.0 * jnp.where(ok, a, 1.0))
    return p + lam * d, ok


@jax.jit
def _pipe_spots(rig: Rig, centers, axes, radius):
    def one_pose(c, a):
        def one_laser(p, d):
            x, ok = beam_pipe_point(p, d, c, a, radius)
            res = project_through_mirror(rig.camera, rig.mirror, x)
            return x, res.uv, ok & res.valid

        return jax.vmap(one_laser)(rig.lasers.points, rig.lasers.directions)

    return jax.vmap(one_pose)(centers, axes)


def _pipe_observations(rig: Rig, views: list[ViewObs], extra: dict) -> Observations:
    """Observations of spots alone (no boards, no direct views) for ``rig``'s camera, mirror and lasers."""
    cam = rig.camera
    return Observations(
        image_size=(cam.width, cam.height),
        mirror_radius=float(rig.mirror.radius),
        mirror_height=float(rig.mirror.height),
        n_lasers=rig.lasers.n,
        boards={},
        calibration_views=[],
        views=views,
        extra=extra,
        mirror_shape=None if isinstance(rig.mirror, ConeMirror) else shape_json(rig.mirror),
    )


def simulate_pipe(scene: PipeScene, noise: float = 0.0, seed: int = 0) -> tuple[Observations, np.ndarray]:
    """Spot observations of a pipe scene with Gaussian pixel noise, and the true points.

    Returns the observations (one view per pose, spots without a board; the
    pipe's truth in ``extra["simulation"]["pipe"]``) and the true spot points
    (n_poses, n_lasers, 3), NaN where a spot is not visible.
    """
    if not np.isfinite(noise) or noise < 0:
        raise ValueError(f"noise must be a non-negative number of pixels, got {noise}")
    rng = np.random.default_rng(seed)
    rig = scene.rig
    # poses and lasers padded to their buckets: one compilation for every count of them
    n_poses, n_lasers = len(scene.centers), rig.lasers.n
    cap = bucket(n_poses)
    x, uv, ok = (
        np.asarray(a)[:n_poses, :n_lasers]
        for a in _pipe_spots(
            rig.with_lasers(padded_lasers(rig.lasers)),
            jnp.asarray(pad_rows(scene.centers, cap)),
            jnp.asarray(pad_rows(scene.axes, cap)),
            scene.diameter / 2,
        )
    )
    views = []
    for i in range(len(scene.centers)):
        spots = []
        for laser in np.flatnonzero(ok[i]):
            px = uv[i, laser] + (rng.normal(0.0, noise, 2) if noise > 0 else 0.0)
            spots.append(SpotObs(int(laser), None, np.asarray(px, float)))
        views.append(ViewObs(f"pipe{i:02d}", {}, spots, np.zeros((0, 2))))
    obs = _pipe_observations(
        rig,
        views,
        {
            "simulation": {
                "pipe": {
                    "diameter": scene.diameter,
                    "centers": scene.centers.tolist(),
                    "axes": scene.axes.tolist(),
                },
                "noise_px": float(noise),
                "seed": int(seed),
            }
        },
    )
    return obs, np.where(ok[..., None], x, np.nan)


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def spots_from_images(
    folder,
    rig: Rig,
    pixel_sigma: float,
    rig_cov: np.ndarray | None = None,
    spot_sigma_mm: float | None = None,
    axis=(0.0, 0.0, 1.0),
    undetermined: tuple[int, ...] = (),
) -> tuple[Observations, dict[str, list[str]]]:
    """The laser spots of every image in ``folder`` (sorted by name), labelled by the calibrated
    rig's laser lines: each spot takes the one laser whose line its reflected ray passes near
    (:func:`slcvjax.measurement.measure.label_by_lines`).  A spot near no line or several, and two spots taking one
    laser, are left out and reported.  With ``spot_sigma_mm`` (the laser spot's Gaussian std on
    the surface) each centroid is corrected for the mirror's distortion of the spot's image, the
    surface taken across the radial direction from ``axis`` (a pipe's wall;
    :func:`slcvjax.measurement.measure.corrected_spot_pixels`).  No spot is given an ``undetermined``
    laser (the calibration's ``undetermined_lasers``).  Returns spot observations (one view per
    image, no boards) and the problems per image name.
    """
    from pathlib import Path

    from ..measurement.measure import label_by_lines
    from ..observations.formats import FormatError
    from .detect import find_mirror, find_spots, read_image

    folder = Path(folder)
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES) if folder.is_dir() else []
    if not files:
        raise FormatError(f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)})")
    cam = rig.camera
    views, problems = [], {}
    for f in files:
        img = read_image(f, (cam.width, cam.height), source="the calibration's camera")
        probs = problems.setdefault(f.name, [])
        disc = find_mirror(img[:, :, 1].astype(float))
        px = find_spots(img, disc) if disc is not None else np.zeros((0, 2))
        if disc is None:
            probs.append("no mirror disc found")
        labels = label_by_lines(rig, px, pixel_sigma, rig_cov, undetermined) if len(px) else np.zeros(0, int)
        spots = []
        for p, lab in zip(px, labels, strict=True):
            at = f"spot at ({p[0]:.1f}, {p[1]:.1f})"
            if lab < 0:
                held = f" (laser {', '.join(map(str, undetermined))} undetermined: no spot is given it)"
                probs.append(f"{at} lies near no laser's line, or near several; left out{held if undetermined else ''}")
            elif np.sum(labels == lab) > 1:
                probs.append(f"{at}: laser {lab} has {int(np.sum(labels == lab))} spots; left out")
            else:
                spots.append(SpotObs(int(lab), None, np.asarray(p, float)))
        missing = sorted(set(range(rig.lasers.n)) - {s.laser for s in spots} - set(undetermined))
        if missing:
            probs.append(f"no spot for laser {', '.join(map(str, missing))}")
        views.append(ViewObs(f.stem, {}, spots, np.zeros((0, 2))))
    extra: dict = {"detected_from": str(folder)}
    if spot_sigma_mm is not None:
        from ..measurement.measure import corrected_spot_pixels

        every = [s for v in views for s in v.spots]
        lasers = np.array([s.laser for s in every], int)
        pixels = np.array([s.pixel for s in every]).reshape(-1, 2)
        fixed = corrected_spot_pixels(rig, lasers, pixels, spot_sigma_mm, axis)
        for s, px in zip(every, fixed, strict=True):
            s.pixel = px
        extra["spot_centroids"] = {"corrected_for_the_mirror": True, "spot_sigma_mm": float(spot_sigma_mm)}
    obs = _pipe_observations(rig, views, extra)
    return obs, problems


def measure_observations(
    rig: Rig,
    obs: Observations,
    pixel_sigma: float,
    rig_cov: np.ndarray | None = None,
    undetermined: tuple[int, ...] = (),
) -> list[ViewPoints]:
    """Triangulate every spot of every view of an observations file (see :func:`measure_spots`;
    ``undetermined``: the calibration's undetermined lasers, whose spots give no point).

    A spot's laser is its element index in the files (``lasers[i]``); in a rig that mixes kinds
    it is measured with its point laser (:attr:`Rig.local_index`) and reported by its element
    index again (``lasers``, ``fits_laser`` and ``missing``)."""
    if obs.n_lasers != rig.n_elements:
        raise ValueError(f"the observations have {obs.n_lasers} lasers, the calibration {rig.n_elements}")
    local, elements = rig.local_index, rig.point_elements
    lasers, pixels, view_of = [], [], []
    for v, view in enumerate(obs.views):
        for s in view.spots:
            lasers.append(int(local[s.laser]))
            pixels.append(s.pixel)
            view_of.append(v)
    held = tuple(int(local[e]) for e in undetermined if rig.element_kinds[e] == "point")
    views = measure_spots(
        rig, np.asarray(lasers, int), np.reshape(pixels, (-1, 2)), np.asarray(view_of, int), len(obs.views),
        pixel_sigma, rig_cov, held,
    )  # fmt: skip
    if rig.kinds:  # back to element indices
        for vp in views:
            vp.lasers = elements[vp.lasers]
            vp.fits_laser = np.where(vp.fits_laser >= 0, elements[np.maximum(vp.fits_laser, 0)], -1)
            vp.missing = [(k, int(elements[las]), why) for k, las, why in vp.missing]
    return views


def view_circle(vp: ViewPoints, axis=(0.0, 0.0, 1.0), name: str = "") -> Circle:
    """The circle through a view's points, leaving out those nearly parallel to their rays
    and those off their laser's line (never used: a wrong label or a stray spot).

    When fewer than 3 points remain, the nearly parallel ones are used too (each weighted
    by its radial variance) and ``nearly_parallel_used`` says how many entered the fit.
    Raises ``ValueError`` naming the view when it has fewer than 3 points on their lines.
    """
    use = np.flatnonzero(~vp.parallel & ~vp.off_line)
    if use.size < 3:
        use = np.flatnonzero(~vp.off_line)
    if use.size < 3:
        raise ValueError(f"view {name}: {use.size} points on their lasers' lines, a circle needs at least 3")
    sel = (3 * use[:, None] + np.arange(3)).ravel()
    circle = fit_circle_3d(vp.xyz[use], vp.cov[np.ix_(sel, sel)], axis=axis)
    circle.nearly_parallel_used = int(np.sum(vp.parallel[use]))
    return circle


def with_observed(simulated: Observations, observed: Observations) -> Observations:
    """``observed`` (one view per pose of a pipe scene, in its order: e.g. detected in its rendered
    images) carrying the scene's truth of ``simulated`` (for the plots and the points file)."""
    if len(observed.views) != len(simulated.views):
        raise ValueError(f"{len(observed.views)} observed views for a pipe scene of {len(simulated.views)} poses")
    return dataclasses.replace(observed, extra={**observed.extra, "simulation": simulated.extra["simulation"]})


def pipe_experiment(
    rig: Rig,
    scene: PipeScene,
    noise: float,
    seed: int = 0,
    pixel_sigma: float | None = None,
    rig_cov: np.ndarray | None = None,
    axis=(0.0, 0.0, 1.0),
    observed: Observations | None = None,
    undetermined: tuple[int, ...] = (),
) -> dict:
    """Simulate the pipe scene with its true rig, measure with ``rig`` (e.g. a calibration).

    ``observed``: the spots to measure instead of simulated ones (one view per pose, in the
    scene's order: those detected in its rendered images, :func:`spots_from_images`); the
    truth is still the scene's.  ``undetermined``: the calibration's undetermined lasers, whose
    spots give no point.

    The circles are fitted across ``axis`` (the camera's z axis, as in the paper),
    from the points that are not nearly parallel to their rays.  Returns per pose
    the true and measured points, the fitted circle and the point errors, with
    summary figures: the mean diameter, the per-point fit errors (mean, max) and
    the point errors against the truth beside their reported standard deviations
    (over the points used).
    """
    obs, truth = simulate_pipe(scene, noise=noise, seed=seed)
    if observed is not None:
        obs = with_observed(obs, observed)
    sigma = noise if pixel_sigma is None else pixel_sigma
    views = measure_observations(rig, obs, sigma, rig_cov, undetermined)
    poses = []
    for i, vp in enumerate(views):
        try:
            circle = view_circle(vp, axis, name=obs.views[i].name)
        except ValueError:  # too few points, or a fit that cannot be trusted: no circle for this pose
            circle = None
        true_xyz = truth[i, vp.lasers]
        poses.append({"points": vp, "truth": true_xyz, "error": vp.xyz - true_xyz, "circle": circle})
    used = [~p["points"].parallel & ~p["points"].off_line for p in poses]
    errs = np.concatenate([p["error"][u] for p, u in zip(poses, used, strict=True)]) if poses else np.zeros((0, 3))
    stds = np.concatenate([p["points"].std[u] for p, u in zip(poses, used, strict=True)]) if poses else np.zeros((0, 3))
    errs_all = np.concatenate([p["error"] for p in poses]) if poses else np.zeros((0, 3))
    stds_all = np.concatenate([p["points"].std for p in poses]) if poses else np.zeros((0, 3))
    circles = [p["circle"] for p in poses if p["circle"] is not None]
    fit_err = np.abs(np.concatenate([c.residuals for c in circles])) if circles else np.zeros(0)
    diam = np.array([c.diameter for c in circles])
    d_std = np.array([c.diameter_std for c in circles], dtype=float)
    within = np.abs(diam - scene.diameter) <= 2.0 * d_std  # NaN std: not within

    def stat(f, x):
        return float(f(x)) if np.size(x) else None

    return {
        "observations": obs,
        "poses": poses,
        "diameters": diam,
        "diameter_stds": d_std,
        "summary": {
            "true_diameter_mm": scene.diameter,
            "poses": len(poses),
            "points": int(sum(len(p["points"].lasers) for p in poses)),
            "nearly_parallel": int(sum(np.sum(p["points"].parallel) for p in poses)),
            "off_line": int(sum(np.sum(p["points"].off_line) for p in poses)),
            "median_ray_line_angle_deg": stat(
                np.median, np.degrees(np.concatenate([p["points"].angle for p in poses])) if poses else []
            ),
            "circles": len(circles),
            "mean_diameter_mm": stat(np.mean, diam),
            "median_abs_diameter_error_mm": stat(np.median, np.abs(diam - scene.diameter)),
            "rms_diameter_std_mm": stat(lambda x: np.sqrt(np.mean(x**2)), d_std),
            "fit_error_mean_mm": stat(np.mean, fit_err),
            "fit_error_max_mm": stat(np.max, fit_err),
            "point_error_rms_mm": stat(lambda e: np.sqrt(np.mean(np.sum(e**2, axis=1))), errs),
            "point_std_rms_mm": stat(lambda e: np.sqrt(np.mean(np.sum(e**2, axis=1))), stds),
            "point_error_over_std_all": (
                float(np.sqrt(np.sum(errs_all**2) / np.sum(stds_all**2))) if np.sum(stds_all**2) > 0 else None
            ),
            "diameters_within_two_std": int(np.sum(within)),
        },
    }


# ----------------------------------------------------------------------------- calibration input and output


def measurement_inputs(path, cal, kind: str = "spot") -> tuple[float | None, np.ndarray | None]:
    """From a read calibration: the default pixel sigma and the rig covariance (or None).

    The pixel sigma is the calibration's noise sigma of its spots
    (``residuals.by_kind_sigma_px.spot``: what the spots' residuals say over the rows the fit
    leaves free; ``kind="stripe"``: of its stripe samples, ``by_kind_sigma_px.stripe``), else its
    pooled one (``residuals.sigma_px``; ``rms_px / sqrt(2)`` when only the 2D RMS is there).
    The covariance is ``uncertainty.covariance.matrix`` when present; a malformed
    one raises :class:`FormatError` naming the file and the field.
    """
    from ..observations.formats import FormatError, ReadContext

    if cal.rig.mirror is None or cal.rig.n_elements == 0:
        raise FormatError(f"{path}: mirror, lasers: a camera-only calibration cannot measure laser spots")
    ctx = ReadContext(str(path))
    res = ctx.get(cal.extra, "residuals", "", dict, optional=True) or {}
    by_kind = ctx.get(res, "by_kind_sigma_px", "residuals", dict, optional=True) or {}
    sigma = None
    for where, val in (
        (f"residuals.by_kind_sigma_px.{kind}", by_kind.get(kind)),
        ("residuals.sigma_px", res.get("sigma_px")),
        ("residuals.rms_px", res.get("rms_px")),
    ):
        if val is not None:  # each one given is checked, the first one is used
            x = ctx.number(val, where)
            if x < 0:
                ctx.fail(where, f"expected a non-negative number, got {x:g}")
            if sigma is None:
                sigma = x / np.sqrt(2.0) if where.endswith("rms_px") else x  # the 2D RMS: per axis
    unc = ctx.get(cal.extra, "uncertainty", "", dict, optional=True) or {}
    covariance = ctx.get(unc, "covariance", "uncertainty", dict, optional=True) or {}
    mat = ctx.get(covariance, "matrix", "uncertainty.covariance", list, optional=True)
    cov = None
    if mat is not None:
        g = cal.rig.tangent_dim
        n = len(mat)
        if n not in (g, g - 1):
            raise FormatError(
                f"{path}: uncertainty.covariance.matrix: {n} rows, expected {g} "
                f"(camera 9 + mirror 6 + each laser's columns: 4 per point laser, 3 per plane, 6 per cone; "
                f"or {g - 1} without the mirror's shape column)"
            )
        cov = ctx.matrix(mat, n, n, "uncertainty.covariance.matrix")
        scale = float(np.max(np.abs(cov), initial=0.0))
        bad = np.flatnonzero(np.diag(cov) < -1e-9 * scale)
        if bad.size:  # a negative variance: a NaN standard deviation in every point measured
            i = int(bad[0])
            ctx.fail(f"uncertainty.covariance.matrix[{i}][{i}]", f"a variance must not be negative, got {cov[i, i]:g}")
        asym = np.abs(cov - cov.T) > 1e-6 * scale
        if asym.any():
            i, j = (int(k) for k in np.argwhere(asym)[0])
            ctx.fail(f"uncertainty.covariance.matrix[{i}][{j}]", f"not symmetric ({cov[i, j]:g} against {cov[j, i]:g})")
        if n == g - 1:  # without the mirror's shape column: the shape given
            cov = np.insert(np.insert(cov, SHAPE_COLUMN, 0.0, axis=0), SHAPE_COLUMN, 0.0, axis=1)
    return sigma, cov


def stripe_points_json(svp) -> list[dict]:
    """The ``points`` entries of a view's stripe samples
    (:class:`slcvjax.measurement.stripes.StripeViewPoints`): ``stripe`` and ``sample`` in place
    of a spot's ``spot``, the ray's angle to the sheet and the ``grazing`` flag."""
    std = svp.std
    return [
        {
            "laser": int(svp.lasers[i]),
            "stripe": int(svp.stripe_index[i]),
            "sample": int(svp.sample_index[i]),
            "xyz": svp.xyz[i].tolist(),
            "std": [None if not np.isfinite(v) else float(v) for v in std[i]],
            "angle_deg": float(np.degrees(svp.angle[i])),
            "angle_std_deg": float(np.degrees(svp.angle_std[i])),
            "grazing": bool(svp.grazing[i]),
        }
        for i in range(len(svp.lasers))
    ]


def ring_json(laser: int, circle: Circle, ellipse) -> dict:
    """A ring laser's circle and ellipse in one view (``views[k].rings[j]`` of ``slcv-points/1``)."""
    out = {
        "laser": int(laser),
        "points_used": int(circle.residuals.size),
        "circle": {
            "center": circle.center.tolist(),
            "center_std": None if circle.center_std is None else circle.center_std.tolist(),
            "diameter": circle.diameter,
            "diameter_std": circle.diameter_std,
            "rms": circle.rms,
        },
    }
    if ellipse is not None:
        sd = ellipse.std
        out["ellipse"] = {
            "center": ellipse.center.tolist(),
            "major_diameter": ellipse.major,
            "minor_diameter": ellipse.minor,
            "orientation_deg": float(np.degrees(ellipse.orientation)),
            "ovality": ellipse.ovality,
            "mean_diameter": ellipse.mean_diameter,
            "rms": ellipse.rms,
            "std": None
            if sd is None
            else {
                "center": np.asarray(sd["center"]).tolist(),
                "major_diameter": sd["major"],
                "minor_diameter": sd["minor"],
                "orientation_deg": float(np.degrees(sd["orientation"])),
                "ovality": sd["ovality"],
                "mean_diameter": sd["mean_diameter"],
            },
        }
    return out


def points_document(
    names: list[str],
    views: list[ViewPoints] | None,
    circles: list[Circle | None] | None = None,
    axis=None,
    meta: dict | None = None,
    stripe_views: list | None = None,
    rings: list[dict] | None = None,
) -> dict:
    """The ``slcv-points/1`` document of measured views (with their circles when fitted).

    ``views``: the spots' points per view (None: no spots); ``stripe_views``: the stripe samples'
    points per view (:class:`slcvjax.measurement.stripes.StripeViewPoints`), after the spots' in
    each view's ``points``; ``rings``: per view ``{laser: (Circle, Ellipse or None)}`` of its ring
    lasers (``views[k].rings``)."""
    out_views = []
    for k, name in enumerate(names):
        vp = views[k] if views is not None else None
        if vp is None:
            view = {"name": name, "points": [], "missing": []}
        else:
            view = _spot_view_json(name, vp)
            c = None if circles is None else circles[k]
            if c is not None:
                view["circle"] = _circle_json(c)
        if stripe_views is not None:
            svp = stripe_views[k]
            view["points"] += stripe_points_json(svp)
            view["missing"] += [
                {"stripe": st, "sample": sa, "laser": las, "reason": why} for st, sa, las, why in svp.missing
            ]
        if rings is not None and rings[k]:
            view["rings"] = [ring_json(e, c, el) for e, (c, el) in sorted(rings[k].items())]
        out_views.append(view)
    doc: dict = {"format": "slcv-points/1", "units": "mm"}
    if axis is not None:
        doc["axis"] = np.asarray(axis, float).tolist()
    doc.update(meta or {})
    doc["views"] = out_views
    return doc


def _circle_json(c: Circle) -> dict:
    return {
        "center": c.center.tolist(),
        "center_std": None if c.center_std is None else c.center_std.tolist(),
        "diameter": c.diameter,
        "diameter_std": c.diameter_std,
        "rms": c.rms,
        "residuals": c.residuals.tolist(),
        "points_used": int(c.residuals.size),
        "nearly_parallel_used": c.nearly_parallel_used,
    }


def _spot_view_json(name: str, vp: ViewPoints) -> dict:
    """A view's spots as ``slcv-points/1``: its points and the spots that gave none."""
    std = vp.std
    pts = [
        {
            "laser": int(vp.lasers[i]),
            "spot": int(vp.spot_index[i]),
            "xyz": vp.xyz[i].tolist(),
            "std": std[i].tolist(),
            "angle_deg": float(np.degrees(vp.angle[i])),
            "gap_mm": float(vp.gap[i]),
            "nearly_parallel": bool(vp.parallel[i]),
            "off_line": bool(vp.off_line[i]),
        }
        | ({"fits_laser": int(vp.fits_laser[i])} if vp.off_line[i] and vp.fits_laser[i] >= 0 else {})
        for i in range(len(vp.lasers))
    ]
    return {
        "name": name,
        "points": pts,
        "missing": [{"spot": s, "laser": las, "reason": why} for s, las, why in vp.missing],
    }
