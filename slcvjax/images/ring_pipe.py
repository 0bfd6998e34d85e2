"""The pipe experiment with line and ring lasers: exact stripe observations of a pipe's wall.

Each sheet of light (a ring laser's cone, a line laser's plane) is sampled at emission angles
``phi`` (equal steps of ``step_deg`` about its axis, as
:func:`slcvjax.observations.simulate.sheet_rays`): the ray ``p + lam d`` from the apex with
``d = cos(theta) a + sin(theta) (cos(phi) e1 + sin(phi) e2)`` meets the pipe's wall where the
quadratic of :func:`wall_point` says (closed form; the emitter is inside the pipe, so there is
one root ahead).  The point is projected through the mirror
(:func:`slcvjax.geometry.mirror.project_through_mirror`) and written where it is seen, with
Gaussian pixel noise on both coordinates (as :func:`slcvjax.observations.simulate.simulate` does
for stripes).  The pipe is a cylinder, or an elliptic cylinder (an oval pipe): its cross-section
across its axis has the diameters ``major`` and ``minor``, the major one along the plane's ``e1``
(:func:`slcvjax.measurement.measure.plane_basis` of the pipe's axis) turned by ``orientation``.

The measurement reads observations only (:func:`ring_pipe_experiment`'s ``observed``): stripes
detected in rendered images of the same scene take the place of the exact ones.
"""

import jax
import jax.numpy as jnp
import numpy as np

from ..geometry.mirror import ConeMirror, project_through_mirror, shape_json
from ..geometry.rig import Rig
from ..measurement.measure import plane_basis
from ..measurement.ring import fit_rings
from ..measurement.stripes import measure_stripe_observations
from ..observations.formats import Observations, SpotObs, StripeObs, ViewObs
from ..support.safe import orthonormal_basis, safe_div, safe_sqrt
from .pipe import PipeScene, measure_observations, with_observed

RING_KINDS = ("cone", "point", "point", "point", "point")  # the ring experiment's rig: a ring laser, 4 point lasers


def wall_point(p, d, center, axis, major_dir, semi_major, semi_minor):
    """Where the ray ``p + lam d`` (lam > 0, camera frame, mm) meets an elliptic cylinder: axis
    through ``center`` along the unit ``axis``, semi-axes ``semi_major`` along the unit
    ``major_dir`` (across the axis) and ``semi_minor`` along ``axis x major_dir``.  A round pipe
    has equal semi-axes.  Returns ``(x (3,), ok)``; ``ok`` is False where ``p`` is not inside the
    pipe or the ray runs along the axis."""
    minor_dir = jnp.cross(axis, major_dir)
    w = p - center
    wu, wv = jnp.dot(w, major_dir) / semi_major, jnp.dot(w, minor_dir) / semi_minor
    du, dv = jnp.dot(d, major_dir) / semi_major, jnp.dot(d, minor_dir) / semi_minor
    a = du * du + dv * dv
    b = 2.0 * (wu * du + wv * dv)
    c = wu * wu + wv * wv - 1.0
    disc = b * b - 4.0 * a * c
    ok = (a > 1e-12) & (c < 0.0)  # inside: c < 0, so disc > 0 and one root is ahead
    lam = safe_div(-b + safe_sqrt(disc), 2.0 * a, eps=1e-12)
    return p + lam * d, ok & (lam > 0.0)


@jax.jit
def _sheet_wall_hits(rig: Rig, phis, centers, axes, majors, semi_major, semi_minor):
    """Per pose, sheet and emission angle: the wall point, its pixel through the mirror, seen."""
    sh = rig.sheets

    def one_pose(c, ax, mj):
        def one_sheet(p, a, th):
            e1, e2 = orthonormal_basis(a)

            def one_ray(phi):
                d = jnp.cos(th) * a + jnp.sin(th) * (jnp.cos(phi) * e1 + jnp.sin(phi) * e2)
                x, ok = wall_point(p, d, c, ax, mj, semi_major, semi_minor)
                res = project_through_mirror(rig.camera, rig.mirror, x)
                return x, res.uv, ok & res.valid

            return jax.vmap(one_ray)(phis)

        return jax.vmap(one_sheet)(sh.apex, sh.axis, sh.half_angle)

    return jax.vmap(one_pose)(centers, axes, majors)


@jax.jit
def _beam_wall_hits(rig: Rig, centers, axes, majors, semi_major, semi_minor):
    """Per pose and point laser: where its beam meets the wall, its pixel through the mirror, seen."""

    def one_pose(c, a, mj):
        def one_laser(p, d):
            x, ok = wall_point(p, d, c, a, mj, semi_major, semi_minor)
            res = project_through_mirror(rig.camera, rig.mirror, x)
            return x, res.uv, ok & res.valid

        return jax.vmap(one_laser)(rig.lasers.points, rig.lasers.directions)

    return jax.vmap(one_pose)(centers, axes, majors)


def major_directions(axes: np.ndarray, orientation_deg: float = 0.0) -> np.ndarray:
    """(P, 3) the major-axis direction of each pose's pipe: ``e1`` of :func:`plane_basis` of its
    axis turned by ``orientation_deg`` towards ``e2``."""
    out = []
    t = np.radians(orientation_deg)
    for a in np.asarray(axes, float).reshape(-1, 3):
        e1, e2 = plane_basis(a)
        out.append(np.cos(t) * e1 + np.sin(t) * e2)
    return np.asarray(out).reshape(-1, 3)


def simulate_ring_pipe(
    scene: PipeScene,
    noise: float = 0.0,
    seed: int = 0,
    step_deg: float = 0.5,
    minor: float | None = None,
    orientation_deg: float = 0.0,
    fans: dict | None = None,
) -> tuple[Observations, list[list[np.ndarray]], list[np.ndarray]]:
    """Exact stripe (and spot) observations of a pipe scene, with Gaussian pixel noise.

    Args:
        scene: the pipe and the poses (:func:`slcvjax.images.pipe.pipe_scene`), with the true rig;
            ``scene.diameter`` is the pipe's diameter, its largest one for an oval pipe.
        noise: pixel noise (px per coordinate) of every stripe sample and spot.
        seed: the noise's seed.
        step_deg: the emission-angle step along each sheet (deg).
        minor: an oval pipe's smallest diameter (mm; None: round).
        orientation_deg: an oval pipe's major axis from the plane's ``e1`` (deg).
        fans: per line laser (element index) its fan's camera-frame azimuth limits (deg, from,
            to; :attr:`slcvjax.observations.simulate.Scene.fans`); absent: all round.

    Returns the observations (one view per pose; stripes and spots carry no board; the truth in
    ``extra["simulation"]["pipe"]``), per view and stripe the true points (M, 3) of its samples
    in order, and per view the true spot points (S, 3) in the order of its spots.
    """
    if not np.isfinite(noise) or noise < 0:
        raise ValueError(f"noise must be a non-negative number of pixels, got {noise}")
    if not step_deg > 0:
        raise ValueError(f"step_deg must be positive, got {step_deg}")
    major = scene.diameter
    minor = major if minor is None else float(minor)
    if not 0 < minor <= major:
        raise ValueError(f"the minor diameter must lie in (0, {major:g}] mm, got {minor:g}")
    rig = scene.rig
    rng = np.random.default_rng(seed)
    majors = major_directions(scene.axes, orientation_deg)
    n_poses = len(scene.centers)
    sheet_el = rig.sheet_elements
    stripes_xyz: list[list[np.ndarray]] = [[] for _ in range(n_poses)]
    stripes: list[list[StripeObs]] = [[] for _ in range(n_poses)]
    if rig.has_sheets:
        phis = np.arange(0.0, 2 * np.pi, np.radians(step_deg))
        x, uv, ok = (
            np.asarray(a)
            for a in _sheet_wall_hits(
                rig,
                jnp.asarray(phis),
                jnp.asarray(scene.centers),
                jnp.asarray(scene.axes),
                jnp.asarray(majors),
                major / 2,
                minor / 2,
            )  # fmt: skip
        )
        for i in range(n_poses):
            for j, e in enumerate(sheet_el):
                keep = ok[i, j].copy()
                if fans and int(e) in fans:
                    lo, hi = (np.radians(v) for v in fans[int(e)])
                    az = np.arctan2(x[i, j, :, 1], x[i, j, :, 0])
                    keep &= np.mod(az - lo, 2 * np.pi) <= np.mod(hi - lo, 2 * np.pi)
                if keep.sum() < 2:
                    continue
                px = uv[i, j, keep] + (rng.normal(0.0, noise, (int(keep.sum()), 2)) if noise > 0 else 0.0)
                stripes[i].append(StripeObs(int(e), None, np.asarray(px, float)))
                stripes_xyz[i].append(x[i, j, keep])
    spots: list[list[SpotObs]] = [[] for _ in range(n_poses)]
    spots_xyz: list[np.ndarray] = [np.zeros((0, 3)) for _ in range(n_poses)]
    if rig.lasers is not None and rig.lasers.n:
        bx, buv, bok = (
            np.asarray(a)
            for a in _beam_wall_hits(
                rig, jnp.asarray(scene.centers), jnp.asarray(scene.axes), jnp.asarray(majors), major / 2, minor / 2
            )
        )
        point_el = rig.point_elements
        for i in range(n_poses):
            for k in np.flatnonzero(bok[i]):
                px = buv[i, k] + (rng.normal(0.0, noise, 2) if noise > 0 else 0.0)
                spots[i].append(SpotObs(int(point_el[k]), None, np.asarray(px, float)))
            spots_xyz[i] = bx[i, bok[i]]
    views = [ViewObs(f"pipe{i:02d}", {}, spots[i], np.zeros((0, 2)), stripes[i]) for i in range(n_poses)]
    cam = rig.camera
    obs = Observations(
        image_size=(cam.width, cam.height),
        mirror_radius=float(rig.mirror.radius),
        mirror_height=float(rig.mirror.height),
        n_lasers=rig.n_elements,
        boards={},
        calibration_views=[],
        views=views,
        extra={
            "simulation": {
                "pipe": {
                    "diameter": major,
                    "minor_diameter": minor,
                    "orientation_deg": float(orientation_deg),
                    "centers": scene.centers.tolist(),
                    "axes": scene.axes.tolist(),
                },
                "noise_px": float(noise),
                "stripe_step_deg": float(step_deg),
                "seed": int(seed),
            }
        },
        mirror_shape=None if isinstance(rig.mirror, ConeMirror) else shape_json(rig.mirror),
        laser_kinds=rig.kinds,
    )
    return obs, stripes_xyz, spots_xyz


def ring_pipe_experiment(
    rig: Rig,
    scene: PipeScene,
    noise: float,
    seed: int = 0,
    pixel_sigma: float | None = None,
    rig_cov: np.ndarray | None = None,
    axis=(0.0, 0.0, 1.0),
    observed: Observations | None = None,
    undetermined: tuple[int, ...] = (),
    step_deg: float = 0.5,
    minor: float | None = None,
    orientation_deg: float = 0.0,
) -> dict:
    """Simulate the pipe scene with its true rig (:func:`simulate_ring_pipe`), measure it with
    ``rig`` (a calibration, with its covariance ``rig_cov``), and fit each ring laser's circle
    and ellipse per view across ``axis``.

    ``observed``: the stripes (and spots) to measure instead of the exact ones, one view per pose
    in the scene's order (e.g. detected in rendered images); the pipe's truth is still the
    scene's, and per-sample point errors are then not computed (no sample matches an emission
    angle).  ``pixel_sigma``: the noise the std are propagated from (default ``noise``).

    Returns per pose the stripe points (:class:`slcvjax.measurement.stripes.StripeViewPoints`),
    the spot points, per ring laser (element index) its circle and ellipse, the sample points'
    errors against the truth, and a summary: the diameters' errors against their reported std.
    """
    obs, truth, _ = simulate_ring_pipe(scene, noise, seed, step_deg, minor, orientation_deg)
    exact = observed is None
    if observed is not None:
        obs = with_observed(obs, observed)
    sigma = noise if pixel_sigma is None else pixel_sigma
    stripe_views = measure_stripe_observations(rig, obs, sigma, rig_cov, undetermined)
    spot_views = measure_observations(rig, obs, sigma, rig_cov, undetermined) if rig.lasers.n else None
    poses = []
    d_true = scene.diameter
    minor_true = d_true if minor is None else float(minor)
    for i, svp in enumerate(stripe_views):
        kinds = tuple(k if e not in undetermined else "undetermined" for e, k in enumerate(rig.element_kinds))
        fits = {e: {"circle": c, "ellipse": el} for e, (c, el) in fit_rings(svp, kinds, axis)[0].items()}
        err = None
        if exact:
            true = np.concatenate(truth[i]) if truth[i] else np.zeros((0, 3))
            offsets = np.cumsum([0] + [len(t) for t in truth[i]])
            err = svp.xyz - true[offsets[svp.stripe_index] + svp.sample_index]
        poses.append(
            {"stripes": svp, "spots": None if spot_views is None else spot_views[i], "rings": fits, "error": err}
        )
    circ = [(f["circle"], f["ellipse"]) for p in poses for f in p["rings"].values()]
    diam = np.array([c.diameter for c, _ in circ])
    d_std = np.array([c.diameter_std for c, _ in circ], dtype=float)
    errs = diam - d_true if minor is None else np.zeros(0)
    ell_mean = np.array([el.mean_diameter for _, el in circ if el is not None])
    ov = np.array([el.ovality for _, el in circ if el is not None])
    ov_true = 2 * (d_true - minor_true) / (d_true + minor_true)

    def stat(f, x):
        return float(f(x)) if np.size(x) else None

    used = [~p["stripes"].grazing for p in poses]
    pe = (
        np.concatenate([p["error"][u] for p, u in zip(poses, used, strict=True)])
        if exact and poses
        else np.zeros((0, 3))
    )
    ps = np.concatenate([p["stripes"].std[u] for p, u in zip(poses, used, strict=True)]) if poses else np.zeros((0, 3))
    summary = {
        "true_diameter_mm": d_true,
        "true_minor_diameter_mm": minor_true,
        "poses": len(poses),
        "stripe_points": int(sum(len(p["stripes"]) for p in poses)),
        "grazing": int(sum(int(np.sum(p["stripes"].grazing)) for p in poses)),
        "missing": int(sum(len(p["stripes"].missing) for p in poses)),
        "circles": len(circ),
        "mean_diameter_mm": stat(np.mean, diam),
        "max_abs_diameter_error_mm": stat(lambda e: np.max(np.abs(e)), errs),
        "rms_diameter_error_mm": stat(lambda e: np.sqrt(np.mean(e**2)), errs),
        "rms_diameter_std_mm": stat(lambda x: np.sqrt(np.mean(x**2)), d_std),
        "diameter_error_over_std_rms": (
            stat(lambda e: np.sqrt(np.mean((e / d_std) ** 2)), errs) if np.all(d_std > 0) else None
        ),
        "ellipse_mean_diameter_mm": stat(np.mean, ell_mean),
        "true_ovality": ov_true,
        "mean_ovality": stat(np.mean, ov),
        "point_error_rms_mm": stat(lambda e: np.sqrt(np.mean(np.sum(e**2, axis=1))), pe),
        "point_std_rms_mm": stat(lambda e: np.sqrt(np.mean(np.sum(e**2, axis=1))), ps),
    }
    return {
        "observations": obs,
        "poses": poses,
        "diameters": diam,
        "diameter_stds": d_std,
        "truth": truth,
        "summary": summary,
    }
