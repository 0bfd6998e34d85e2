"""Sensor design for measurement: the lasers' geometry that minimises the predicted pipe-diameter error.

The design variables are the lasers' mounting: each beam's elevation (its angle above the
plane across the camera's z axis), the ring's radius and the ring's height (every emitter
moved by the same amount; each keeps its azimuth, its aim and its own small offsets). Each is
``start + range * tanh(u)``, so every iterate stays within the mounting range.

The **prediction** for a pipe of diameter ``D`` (the sensor on the pipe's axis, the axis along
the camera's z): each laser's spot ``x_i`` where its beam meets the wall, seen at pixel
``uv_i``; the point measured from it (:func:`slcvjax.measurement.measure.triangulate_spot`) has the Jacobians
``J_px`` (pixel) and ``J_rig`` (the rig's tangent), so the points' joint covariance is
``sigma^2 J_px J_px^T`` (per point) ``+ J_rig C J_rig^T`` (shared), with ``C`` the bound of the
calibration the plan would give (:func:`slcvjax.experiments.design.calibration_covariance`: the same box, views
and noise). The diameter's variance follows through the weighted circle fit's implicit
derivative at the true circle (:func:`slcvjax.measurement.measure.fit_circle`'s weights and sensitivity), as the
measurement itself reports it.

**Constraints.** Every laser's spot must be seen in every pipe of the range: its mirror point
at least ``margin_mm`` inside the mirror's rim, its reflected ray at least ``margin_mm`` clear
of the sensor's body (the disc that the renderer's ``body_radius_mm``/``body_gap_mm`` describe),
its pixel ``margin_px`` inside the image; no emitter may be seen through the mirror; and every
laser keeps at least ``min_wall_spots`` spots on the calibration walls (or all it had, if it
had fewer). These are discrete, so a gradient cannot reach them from a start that violates
them: the design first takes the best mounting that satisfies them among common offsets (every
beam's elevation, the ring's radius and height) on a grid over the range, then minimises the
mean over the diameters of ``var(D) / D^2`` (the relative diameter variance) by Adam-scaled
gradient steps (:func:`optax.scale_by_adam`), each shortened until the value, re-evaluated at
the new mounting, goes down with every constraint held. Which spots the calibration sees is
decided at the current mounting and held while differentiating, as in :mod:`slcvjax.experiments.design`; the
points' Jacobians and the calibration's are differentiated through the reflection point's
exact second derivatives.
"""

import time
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np
import optax

from ..geometry.camera import project
from ..geometry.lasers import Lasers
from ..geometry.mirror import BODY_CLEAR_FAR, body_clearance, project_through_mirror, solve_mirror_point
from ..geometry.rig import Rig
from ..images.pipe import beam_pipe_point
from ..measurement.measure import circle_sensitivity, triangulate_spot
from ..support.persist import PersistentJit
from ..support.safe import safe_normalize
from .descent import Accepted, adam_descent
from .design import MIN_SPOTS, Plan, calibration_covariance, design_problem, pad_views

BODY_RADIUS_MM = 12.0  # the renderer's default sensor body (RenderOptions)
BODY_GAP_MM = 8.0


@dataclass
class MeasurePlan:
    """A sensor to design for measuring pipes.

    ``plan``: the calibration it is calibrated with (box, views, noise; :class:`slcvjax.experiments.design.Plan`).
    ``diameters``: the pipes it must measure (mm). The mounting range: each beam's elevation
    within ``elevation_range_deg`` of its start, the ring's radius and height within
    ``ring_radius_range_mm`` and ``ring_z_range_mm``.
    """

    plan: Plan
    diameters: np.ndarray = field(default_factory=lambda: np.linspace(100.0, 300.0, 5))
    elevation_range_deg: float = 20.0
    ring_radius_range_mm: float = 10.0
    ring_z_range_mm: float = 25.0
    margin_mm: float = 1.0
    margin_px: float = 3.0
    min_wall_spots: int = 6
    body_radius_mm: float = BODY_RADIUS_MM
    body_gap_mm: float = BODY_GAP_MM

    def __post_init__(self):
        self.diameters = np.asarray(self.diameters, dtype=float).reshape(-1)
        if self.diameters.size < 1 or not np.all(np.isfinite(self.diameters)) or np.any(self.diameters <= 0):
            raise ValueError(f"diameters must be positive numbers of mm, got {self.diameters.tolist()}")
        ranges = {
            "elevation_range_deg": self.elevation_range_deg,
            "ring_radius_range_mm": self.ring_radius_range_mm,
            "ring_z_range_mm": self.ring_z_range_mm,
            "margin_mm": self.margin_mm,
            "margin_px": self.margin_px,
        }
        for name, v in ranges.items():
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a non-negative number, got {v}")
        if self.min_wall_spots < MIN_SPOTS:
            raise ValueError(f"min_wall_spots must be at least {MIN_SPOTS}, got {self.min_wall_spots}")
        r = np.hypot(*np.asarray(self.plan.rig.lasers.points)[:, :2].T)
        if np.max(r) + self.ring_radius_range_mm >= 0.5 * np.min(self.diameters):
            raise ValueError(
                f"the ring (radius up to {np.max(r) + self.ring_radius_range_mm:.1f} mm) must stay inside the "
                f"smallest pipe ({np.min(self.diameters):g} mm)"
            )


# ----------------------------------------------------------------------------- the mounting as variables


def mounting_of(lasers: Lasers) -> dict[str, np.ndarray]:
    """The lasers' mounting: emitter azimuth, ring radius and height, aim azimuth and elevation (rad, mm)."""
    p, d = np.asarray(lasers.points), np.asarray(lasers.directions)
    return {
        "azimuth": np.arctan2(p[:, 1], p[:, 0]),
        "radius": np.hypot(p[:, 0], p[:, 1]),
        "z": p[:, 2],
        "aim": np.arctan2(d[:, 1], d[:, 0]),
        "elevation": np.arcsin(np.clip(d[:, 2], -1.0, 1.0)),
    }


def _lasers_at(u, start, ranges) -> Lasers:
    """The lasers at the design variables ``u`` (N elevations, then ring radius and height)."""
    n = start["azimuth"].shape[0]
    elev = start["elevation"] + ranges[0] * jnp.tanh(u[:n])
    radius = start["radius"] + ranges[1] * jnp.tanh(u[n])
    z = start["z"] + ranges[2] * jnp.tanh(u[n + 1])
    az, aim = start["azimuth"], start["aim"]
    points = jnp.stack([radius * jnp.cos(az), radius * jnp.sin(az), z], axis=1)
    directions = jnp.stack([jnp.cos(elev) * jnp.cos(aim), jnp.cos(elev) * jnp.sin(aim), jnp.sin(elev)], axis=1)
    return Lasers(points, directions)


# ----------------------------------------------------------------------------- one pipe


def _spot_margins(rig: Rig, x, body, proj):
    """Of a scene point ``x`` and its projection ``proj``: whether it is seen, its margins (mm to
    the rim, mm clear of the body, px inside the image; continuous also where it is not seen:
    the mirror's surface continued past its rim) and the mirror point that sees it."""
    cam, mir = rig.camera, rig.mirror
    m, _ = solve_mirror_point(mir, x, rim_margin=1.0, telecentric=cam.telecentric)
    rim = mir.height - jnp.dot(m - mir.apex, mir.axis)
    clear = body_clearance(m, safe_normalize(x - m), mir, body[0], body[1])
    uv, _ = project(cam, m)
    img = jnp.min(jnp.stack([uv[0] + 0.5, cam.width - 0.5 - uv[0], uv[1] + 0.5, cam.height - 0.5 - uv[1]]))
    return proj.valid & (clear > 0.0), rim, clear, img, m


def pipe_prediction(rig: Rig, cov, sigma, radius, body):
    """The pipe of ``radius`` around the camera's z axis: the diameter's predicted variance (mm^2;
    inf with fewer than 3 spots seen), and per laser whether its spot is seen, its margins and
    the angle between its beam and the ray that sees it (rad)."""
    las = rig.lasers
    g = rig.tangent_dim
    ez, c0 = jnp.array([0.0, 0.0, 1.0]), jnp.zeros(3)

    def spot(i):
        x, hit = beam_pipe_point(las.points[i], las.directions[i], c0, ez, radius)
        proj = project_through_mirror(rig.camera, rig.mirror, x)
        seen, rim, body_m, img, m = _spot_margins(rig, x, body, proj)

        def point(delta, px):
            return triangulate_spot(rig.retract(delta), i, px).xyz

        j_rig, j_px = jax.jacfwd(point, argnums=(0, 1))(jnp.zeros(g), proj.uv)
        ray = safe_normalize(x - m)  # where the spot is seen, its mirror point
        angle = jnp.arccos(jnp.clip(jnp.abs(jnp.dot(ray, las.directions[i])), 0.0, 1.0))
        return x, hit & seen, rim, body_m, img, j_rig, j_px, angle

    x, seen, rim, body_m, img, j_rig, j_px, angle = jax.vmap(spot)(jnp.arange(las.n))
    n = las.n
    ok = seen[:, None, None]
    j_rig = jnp.where(ok, j_rig, 0.0)[:, :2, :].reshape(2 * n, g)
    j_px = jnp.where(ok, j_px, 0.0)[:, :2, :]
    own = sigma**2 * jnp.einsum("nij,nkj->nik", j_px, j_px)  # (n, 2, 2) pixel noise per point
    cov_q = j_rig @ cov @ j_rig.T
    cov_q = cov_q + jax.scipy.linalg.block_diag(*[own[i] for i in range(n)])
    q = jnp.where(seen[:, None], x[:, :2], jnp.array([radius, 0.0]))
    u = safe_normalize(q, axis=-1)
    blocks = jnp.stack([cov_q[2 * i : 2 * i + 2, 2 * i : 2 * i + 2] for i in range(n)])
    var_r = jnp.einsum("ni,nij,nj->n", u, blocks, u)
    var_r = jnp.where(seen, var_r, jnp.inf)
    w = jnp.where(seen, jnp.min(var_r) / var_r, 0.0)  # as fit_circle weighs the points
    sens = circle_sensitivity(jnp.array([0.0, 0.0, radius]), q, w).reshape(3, 2 * n)
    var_d = 4.0 * sens[2] @ cov_q @ sens[2]
    var_d = jnp.where(jnp.sum(seen) >= 3, var_d, jnp.inf)
    return var_d, seen, rim, body_m, img, angle


def _emitters_seen(rig: Rig, body):
    def seen(p):
        return _spot_margins(rig, p, body, project_through_mirror(rig.camera, rig.mirror, p))[0]

    return jax.vmap(seen)(rig.lasers.points)


def _evaluate(u, start, ranges, rig0, views, T_bw, chess, pk, sigma, present, radii, body):
    """At the design variables ``u``: per diameter the predicted variance and the spots' margins,
    the wall spots per laser, whether each emitter is seen."""
    rig = rig0.with_lasers(_lasers_at(u, start, ranges))
    cov, _, w_spot, _ = calibration_covariance(views, rig, T_bw, chess, pk, sigma, present)
    var_d, seen, rim, body_m, img, angle = jax.vmap(lambda r: pipe_prediction(rig, cov, sigma, r, body))(radii)
    wall = jax.ops.segment_sum(w_spot.astype(int), pk.spot_laser, num_segments=rig.lasers.n)
    # a laser with too few wall spots is not calibrated: its bound (and every diameter) is undetermined
    var_d = jnp.where((jnp.min(wall) >= MIN_SPOTS) & (var_d > 0.0), var_d, jnp.inf)
    return var_d, seen, rim, body_m, img, angle, wall, _emitters_seen(rig, body)


def _relative_variance(u, start, ranges, rig0, views, T_bw, chess, pk, sigma, present, radii, body):
    var_d = _evaluate(u, start, ranges, rig0, views, T_bw, chess, pk, sigma, present, radii, body)[0]
    return jnp.mean(var_d / (2.0 * radii) ** 2)


_evaluate_jit = PersistentJit(_evaluate, "laser_design_evaluate")
_value_and_grad_jit = PersistentJit(jax.value_and_grad(_relative_variance), "laser_design_value_and_grad")


# ----------------------------------------------------------------------------- the design


@dataclass
class MeasurePrediction:
    """Per diameter: the predicted diameter std (mm; inf where fewer than 3 spots are seen), the
    spots seen, the smallest margins and the smallest beam-ray angle; per laser the wall spots."""

    diameters: np.ndarray
    diameter_std_mm: np.ndarray
    spots_seen: np.ndarray
    rim_margin_mm: np.ndarray
    body_margin_mm: np.ndarray
    image_margin_px: np.ndarray
    min_angle_deg: np.ndarray
    wall_spots: np.ndarray
    emitters_seen: int
    seen: np.ndarray  # (K, N)

    def feasible(self, mp: MeasurePlan, wall_needed: np.ndarray) -> bool:
        return bool(
            np.all(self.seen)
            and np.min(self.rim_margin_mm) >= mp.margin_mm
            and np.min(self.body_margin_mm) >= mp.margin_mm
            and np.min(self.image_margin_px) >= mp.margin_px
            and self.emitters_seen == 0
            and np.all(self.wall_spots >= wall_needed)
        )

    def to_json(self) -> dict:
        def num(x):
            return float(x) if np.isfinite(x) else None

        return {
            "diameters_mm": self.diameters.tolist(),
            "diameter_std_mm": [num(x) for x in self.diameter_std_mm],
            "spots_seen": self.spots_seen.tolist(),
            "min_rim_margin_mm": [num(x) for x in self.rim_margin_mm],
            "min_body_margin_mm": [num(x) for x in self.body_margin_mm],
            "min_image_margin_px": [num(x) for x in self.image_margin_px],
            "min_beam_ray_angle_deg": [num(x) for x in self.min_angle_deg],
            "wall_spots_per_laser": self.wall_spots.tolist(),
            "emitters_seen": self.emitters_seen,
        }


class Compiled:
    def __init__(self, mp: MeasurePlan):
        plan = mp.plan
        self.mp = mp
        self.pk, self.T_bw, self.chess, present = design_problem(plan)
        self.start = {k: jnp.asarray(v) for k, v in mounting_of(plan.rig.lasers).items()}
        self.ranges = jnp.asarray([np.radians(mp.elevation_range_deg), mp.ring_radius_range_mm, mp.ring_z_range_mm])
        self.n = plan.rig.lasers.n
        self.radii = jnp.asarray(mp.diameters / 2.0)
        self.body = jnp.asarray([mp.body_radius_mm, mp.body_gap_mm])
        self.common = (
            self.start, self.ranges, plan.rig, jnp.asarray(pad_views(plan.views, present.views.shape[0])), self.T_bw,
            self.chess, self.pk, jnp.asarray(float(plan.noise)), present,
        )  # fmt: skip

    def evaluate(self, u) -> MeasurePrediction:
        var_d, seen, rim, body_m, img, angle, wall, emitters = (
            np.asarray(a) for a in _evaluate_jit(u, *self.common, self.radii, self.body)
        )
        ang = np.where(seen, angle, np.inf)
        return MeasurePrediction(
            np.asarray(self.mp.diameters), np.sqrt(var_d), seen.sum(axis=1), rim.min(axis=1),
            np.minimum(body_m, BODY_CLEAR_FAR).min(axis=1), img.min(axis=1), np.degrees(ang.min(axis=1)), wall,
            int(emitters.sum()), seen,
        )  # fmt: skip

    def value_and_grad(self, u):
        return _value_and_grad_jit(u, *self.common, self.radii, self.body)

    def rig_at(self, u) -> Rig:
        r = self.mp.plan.rig
        return r.with_lasers(_lasers_at(jnp.asarray(u), self.start, self.ranges))


@dataclass
class MeasureDesign:
    """The lasers before and after, their predictions and the objective at each accepted step."""

    plan: MeasurePlan
    rig_before: Rig
    rig_after: Rig
    predicted_before: MeasurePrediction
    predicted_after: MeasurePrediction
    history: list[float]
    feasible: bool
    timings: dict


def _grid_start(c: "Compiled", wall_needed, points: int):
    """The best feasible mounting among common offsets of every beam's elevation, the ring's radius
    and its height on a grid over the range (``points`` values each; the start included):
    ``(u, prediction)``, or the grid point that sees the most spots with ``feasible`` False."""
    mp = c.mp
    t = np.arctanh(np.linspace(-1.0, 1.0, points) * (1.0 - 1e-6))
    radius_steps = t if mp.ring_radius_range_mm > 0 else [0.0]
    z_steps = t if mp.ring_z_range_mm > 0 else [0.0]
    elev_steps = t if mp.elevation_range_deg > 0 else [0.0]
    best, best_value, most, most_seen = None, np.inf, None, -1
    candidates = [np.zeros(c.n + 2)]
    for a in elev_steps:
        for b in radius_steps:
            for z in z_steps:
                candidates.append(np.concatenate([np.full(c.n, a), [b, z]]))
    for u in candidates:
        p = c.evaluate(jnp.asarray(u))
        if p.feasible(mp, wall_needed):
            value = float(np.mean(p.diameter_std_mm**2 / p.diameters**2))
            if value < best_value:
                best, best_value = (u, p), value
        seen = int(p.seen.sum())
        if seen > most_seen:
            most, most_seen = (u, p), seen
    return (best, True) if best is not None else (most, False)


def optimise_lasers(
    mp: MeasurePlan, steps: int = 60, learning_rate: float = 0.1, grid: int = 9, progress: bool = False
) -> MeasureDesign:
    """The lasers' mounting within its range that minimises the predicted diameter error.

    First the best feasible mounting among common offsets on a grid (:func:`_grid_start`;
    the visibility constraints are discrete, so a gradient cannot find them from an infeasible
    start); from there each beam's elevation and the ring's radius and height by Adam-scaled
    gradient steps on the mean relative diameter variance, each halved (at most 10 times) until
    the value, re-evaluated at the new mounting, goes down with every constraint held. Stops after
    ``steps`` accepted steps or when no shortened step helps. Where no grid point is feasible
    the result says so (``feasible`` False) and carries the grid point that sees the most spots.
    """
    t0 = time.perf_counter()
    c = Compiled(mp)
    before = c.evaluate(jnp.zeros(c.n + 2))
    wall_needed = np.minimum(before.wall_spots, mp.min_wall_spots)
    t_compile = time.perf_counter() - t0
    (u, current), feasible = _grid_start(c, wall_needed, grid)
    u = jnp.asarray(u)
    t_grid = time.perf_counter() - t0 - t_compile
    history = [float(np.mean(current.diameter_std_mm**2 / current.diameters**2))]
    if feasible:
        f, grad = c.value_and_grad(u)

        def search(u, direction, lr, f0):
            for _ in range(10):
                u_new = u - lr * direction
                f_new, g_new = c.value_and_grad(u_new)
                if np.isfinite(float(f_new)) and float(f_new) < f0:
                    p_new = c.evaluate(u_new)
                    if p_new.feasible(mp, wall_needed):
                        return Accepted(u_new, f_new, g_new, lr, p_new)
                lr *= 0.5
            return None

        d = adam_descent(
            u,
            f,
            grad,
            search,
            steps,
            learning_rate,
            optax.scale_by_adam(),
            progress="laser design" if progress else None,
            postfix=lambda v: {"value": f"{v:.3g}"},
        )
        u, current = d.u, current if d.extra is None else d.extra
        history = [history[0], *d.history[1:]]
    timings = {"compile_s": t_compile, "grid_s": t_grid, "total_s": time.perf_counter() - t0}
    return MeasureDesign(mp, mp.plan.rig, c.rig_at(u), before, current, history, feasible, timings)


# ----------------------------------------------------------------------------- confirmation, output


def confirm_lasers(mp: MeasurePlan, rig: Rig, trials: int, seed: int = 0, progress: bool = False) -> dict:
    """Monte Carlo check of a mounting: ``trials`` times, simulate the plan's box calibration with
    ``rig`` at the plan's noise, calibrate it, and measure each of the plan's pipes (the sensor on
    the axis, fresh pixel noise) with that calibration and its covariance.

    Returns per diameter the RMS diameter error over the trials (mm; its relative sampling error
    is about ``1 / sqrt(2 trials)``), the mean error, the RMS reported std, how many trials gave a circle, and
    how many calibrations failed (with the first reason).
    """
    import dataclasses

    from ..calibration.report import to_calibration
    from ..images.pipe import PipeScene, measure_observations, measurement_inputs, simulate_pipe, view_circle
    from .design import simulated_calibrations

    plan = dataclasses.replace(mp.plan, rig=rig)
    k = mp.diameters.size
    errors, reported = [[] for _ in range(k)], [[] for _ in range(k)]
    failed = []
    for t, (obs, _, res, error) in enumerate(simulated_calibrations(plan, trials, seed, progress)):
        if res is None:
            failed.append(error)
            continue
        _, cov = measurement_inputs("<calibration>", to_calibration(res, obs))
        for j, d in enumerate(mp.diameters):
            pipe = PipeScene(rig, float(d), np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]))
            pobs, _ = simulate_pipe(pipe, noise=plan.noise, seed=10_000 * (j + 1) + seed + t)
            vp = measure_observations(res.rig, pobs, plan.noise, cov)[0]
            try:
                circle = view_circle(vp)
            except ValueError:
                continue
            errors[j].append(circle.diameter - d)
            reported[j].append(circle.diameter_std)
    out = {"trials": trials, "failed": len(failed)}
    if failed:
        out["first_failure"] = failed[0]

    def rms(x):
        return float(np.sqrt(np.mean(np.square(x)))) if len(x) else None

    out["diameters_mm"] = mp.diameters.tolist()
    out["circles"] = [len(e) for e in errors]
    out["diameter_error_rms_mm"] = [rms(e) for e in errors]
    out["diameter_error_mean_mm"] = [float(np.mean(e)) if e else None for e in errors]
    out["reported_std_rms_mm"] = [rms(r) for r in reported]
    return out


def _lasers_json(lasers: Lasers) -> dict:
    m = mounting_of(lasers)
    return {
        "points_mm": np.asarray(lasers.points).tolist(),
        "directions": np.asarray(lasers.directions).tolist(),
        "elevation_deg": np.degrees(m["elevation"]).tolist(),
        "ring_radius_mm": m["radius"].tolist(),
        "ring_z_mm": m["z"].tolist(),
    }


def laser_design_document(res: MeasureDesign, confirmed: dict | None = None) -> dict:
    """The ``slcv-laser-design/1`` document: the mounting range, the lasers before and after, the
    predictions, and the Monte Carlo confirmation when one was run."""
    mp = res.plan
    return {
        "format": "slcv-laser-design/1",
        "units": "mm",
        "frame": "camera",
        "noise_px": mp.plan.noise,
        "box_width_mm": 2.0 * mp.plan.half_width,
        "views": int(mp.plan.views.shape[0]),
        "diameters_mm": mp.diameters.tolist(),
        "mounting_range": {
            "elevation_deg": mp.elevation_range_deg,
            "ring_radius_mm": mp.ring_radius_range_mm,
            "ring_z_mm": mp.ring_z_range_mm,
        },
        "constraints": {
            "margin_mm": mp.margin_mm,
            "margin_px": mp.margin_px,
            "min_wall_spots": mp.min_wall_spots,
            "body_radius_mm": mp.body_radius_mm,
            "body_gap_mm": mp.body_gap_mm,
        },
        "feasible": res.feasible,
        "lasers_before": _lasers_json(res.rig_before.lasers),
        "lasers_after": _lasers_json(res.rig_after.lasers),
        "predicted": {"before": res.predicted_before.to_json(), "after": res.predicted_after.to_json()},
        "objective_history": res.history,
        "confirmed": confirmed,
        "timings": res.timings,
    }


def plot_laser_design(res: MeasureDesign, path, confirmed: dict | None = None):
    """Predicted diameter std over the pipes before and after (Monte Carlo beside it when given),
    the beams in a section through the axis, and the smallest beam-ray angle per pipe."""
    from pathlib import Path

    from ..plots import pyplot

    plt = pyplot()
    path = Path(path)
    b, a = res.predicted_before, res.predicted_after
    d = res.plan.diameters
    fig, axs = plt.subplots(1, 3, figsize=(15, 4.5))
    ax = axs[0]
    for p, style, name in ((b, "o-", "before"), (a, "^-", "after")):
        std = np.where(np.isfinite(p.diameter_std_mm), p.diameter_std_mm, np.nan)
        ax.plot(d, std, style, label=f"{name}: predicted")
    if confirmed:
        for name, marker in (("before", "s"), ("after", "v")):
            c = confirmed.get(name)
            if c:
                e = np.array([np.nan if x is None else x for x in c["diameter_error_rms_mm"]])
                ax.plot(d, e, marker, mfc="none", ms=9, label=f"{name}: simulated rms error ({c['trials']} trials)")
    unseen = d[~np.isfinite(b.diameter_std_mm)]
    if unseen.size:
        ax.plot(unseen, np.zeros_like(unseen), "rx", ms=10, label="before: too few spots seen")
    ax.set_xlabel("pipe diameter (mm)")
    ax.set_ylabel("diameter std (mm)")
    ax.set_ylim(bottom=0)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    ax = axs[1]
    reach = 0.5 * float(np.max(d))
    for rig, color, name in ((res.rig_before, "C0", "before"), (res.rig_after, "C1", "after")):
        m = mounting_of(rig.lasers)
        for i in range(rig.lasers.n):
            r0, z0, e = m["radius"][i], m["z"][i], m["elevation"][i]
            ax.plot([r0, reach], [z0, z0 + (reach - r0) * np.tan(e)], color=color, lw=1, alpha=0.7,
                    label=name if i == 0 else None)  # fmt: skip
    mir = res.rig_before.mirror
    apex_z, h, rad = float(mir.apex[2]), float(mir.height), float(mir.radius)
    ax.plot([0, rad], [apex_z, apex_z + h], "k-", lw=2, label="mirror")
    for x in d / 2:
        ax.axvline(x, color="0.6", ls=":", lw=1)
    ax.set_xlabel("distance from the axis (mm); dotted: the pipe walls")
    ax.set_ylabel("z along the camera axis (mm)")
    ax.legend(fontsize=8)
    ax.set_title("the beams in a section through the axis")
    ax = axs[2]
    for p, style, name in ((b, "o-", "before"), (a, "^-", "after")):
        ang = np.where(np.isfinite(p.min_angle_deg), p.min_angle_deg, np.nan)
        ax.plot(d, ang, style, label=name)
    ax.set_xlabel("pipe diameter (mm)")
    ax.set_ylabel("smallest beam-ray angle (deg)")
    ax.set_ylim(bottom=0)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.suptitle(f"Laser design for measurement: {res.rig_before.lasers.n} lasers, noise {res.plan.plan.noise} px")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
