"""What several commands print and write: the calibration report, the pipe report, number formats."""

import logging
from pathlib import Path

import numpy as np

from ..calibration.result import Repair
from ..observations.formats import FormatError, write_observations

log = logging.getLogger(__name__)


def summary(obs, truth) -> str:
    rig = truth.rig
    n_dots = sum(int(s.sum()) for v in obs.views for _, s in v.boards.values())
    n_dots_all = sum(s.size for v in obs.views for _, s in v.boards.values())
    n_spots = sum(len(v.spots) for v in obs.views)
    n_rim = sum(len(v.rim) for v in obs.views)
    n_corners = sum(int(c.seen.sum()) for c in obs.calibration_views)
    cam = rig.camera
    tilt = np.degrees(np.arccos(np.clip(float(rig.mirror.axis[2]), -1, 1)))
    lines = [
        f"camera   {cam.width}x{cam.height}  fx {float(cam.fx):.3f}  fy {float(cam.fy):.3f}  "
        f"cx {float(cam.cx):.3f}  cy {float(cam.cy):.3f}  dist {np.round(np.asarray(cam.dist), 4).tolist()}",
        f"mirror   cone r {float(rig.mirror.radius):g} mm  h {float(rig.mirror.height):g} mm  "
        f"apex {np.round(np.asarray(rig.mirror.apex), 3).tolist()} mm  axis tilt {tilt:.2f} deg",
        f"lasers   {rig.lasers.n}",
        f"views    {len(obs.views)} catadioptric: {n_dots}/{n_dots_all} dots visible, "
        f"{n_spots}/{len(obs.views) * rig.lasers.n} spots, {n_rim} rim pixels",
        f"direct   {len(obs.calibration_views)} chessboard views, {n_corners} corners",
    ]
    return "\n".join(lines)


def fmt(x, nd=3):
    return "-" if x is None else f"{x:.{nd}f}"


def print_report(cal, name: str = "") -> None:
    """A short human-readable report of a calibration document's residuals and uncertainty."""
    res, unc = cal.extra["residuals"], cal.extra["uncertainty"]
    passes = cal.extra["stages"]["joint"]["passes"]
    log.info(f"== {name}" if name else "==")
    log.info(
        f"rms {res['rms_px']:.3f} px   sigma {res['sigma_px']:.3f} px   dof {res['dof']}   "
        f"joint: " + ", ".join(f"{p['name'].split(':')[0]} {p['steps']} steps {p['result']}" for p in passes)
    )
    log.info("per kind   " + "  ".join(f"{k} {fmt(v)}" for k, v in res["by_kind_rms_px"].items()))
    log.info("per view   " + "  ".join(f"{k} {fmt(v)}" for k, v in res["per_view_rms_px"].items()))
    log.info("per board  " + "  ".join(f"{k} {fmt(v)}" for k, v in res["per_board_rms_px"].items()))
    if res["per_laser_rms_px"]:
        log.info("per laser  " + "  ".join(f"{k}: {fmt(v)}" for k, v in res["per_laser_rms_px"].items()))
    out = res["outliers"]

    def _outlier(o):
        laser = f" laser {o['laser']}" if "laser" in o else ""
        return f"{o['kind']} {o['view']} {o['board']}{laser} {o['residual_px']:.1f} px"

    listed = "; ".join(_outlier(o) for o in out[:10]) + (" ..." if len(out) > 10 else "")
    log.info(f"outliers   {len(out)}" + (f": {listed}" if out else ""))
    fixed = [Repair.from_json(o, f"residuals.repairs[{i}]") for i, o in enumerate(res.get("repairs", []))]

    def _repair(o: Repair):
        what = " ".join(str(x) for x in (o.kind, o.view, o.board) if x) + (f" #{o.index}" if o.index >= 0 else "")
        if o.action == "relabelled" and o.new_index is not None:  # a dot given another grid position
            return f"{what} -> #{o.new_index}"
        if o.action == "relabelled":
            return f"{what} laser {o.laser} -> {o.new_laser}"
        return f"{what} left out ({fmt(o.residual_px, 1)} px)"

    if fixed:
        listed = "; ".join(_repair(o) for o in fixed[:10]) + (" ..." if len(fixed) > 10 else "")
        log.info(f"repaired   {len(fixed)}: {listed}")
    if res.get("rim_outliers"):
        log.info(f"rim        {res['rim_outliers']} rim pixel(s) more than 5 sigma (the rim's own) off the rim")
    if res["invalid"]:
        log.info(f"invalid    {res['invalid']} observation(s) fall outside the model (off the mirror or the sensor)")
    for st in cal.extra["stages"]["staged"]["reports"]:
        if st["stage"] == "mirror_kind":
            log.info("mirror kind " + "; ".join(st["notes"]))
    if cal.rig.camera.telecentric:
        log.info(f"camera     telecentric (fx, fy in px per {cal.rig.camera.unit:g} mm; its depth is the gauge, held)")
    if unc.get("status"):
        log.info(f"WARNING    {unc['status']}")
    cs = unc["camera_std"]
    log.info(f"camera std fx {fmt(cs['fx'])} fy {fmt(cs['fy'])} cx {fmt(cs['cx'])} cy {fmt(cs['cy'])} px")
    ms = unc["mirror_std"]
    apex, tilt = (", ".join(fmt(v, 4) for v in ms[k]) for k in ("apex_mm", "axis_tilt_deg"))
    log.info(f"mirror std apex [{apex}] mm  axis [{tilt}] deg")
    if "conic_constant" in ms:  # the shape estimated
        log.info(
            f"mirror     {cal.rig.mirror.kind}, conic constant {float(cal.rig.mirror.conic):.4f} "
            f"(std {fmt(ms['conic_constant'], 4)}), vertex radius {1.0 / float(cal.rig.mirror.curvature):g} mm held"
        )
    box = unc.get("rigid_box")
    if box:
        worst = max(
            (max(v for v in d["translation_std_mm"] if v is not None) for d in box["boards"].values()), default=0.0
        )
        log.info(
            f"rigid box  gauge {box['gauge']}, {len(box['boards'])} boards over {box['views']} views, box poses "
            f"std <= {worst:.3g} mm, {len(box['left_out'])} board pose(s) left out (do not fit the box)"
        )
    for i, las in enumerate(unc["lasers"]):
        if las["working_range_mm"] is None:
            log.info(f"laser {i:2d}   {las.get('status', 'undetermined')}")
            continue
        log.info(
            f"laser {i:2d}   std {fmt(las['position_std_mm'])} mm at {las['working_range_mm']:.0f} mm, "
            f"direction {fmt(las['direction_std_deg'])} deg" + (f"  ({las['status']})" if "status" in las else "")
        )


def print_placed(notes: list[str]) -> None:
    """One line for the targets the detector left out and the box placed (or could not), and one
    for the centroids' correction (:func:`slcvjax.images.centroids.calibrate_detected`'s notes)."""
    from ..images.centroids import CENTROIDS_NOTE

    targets = [n for n in notes if not n.startswith(CENTROIDS_NOTE)]
    if targets:
        placed = sum("placed by the box" in n for n in targets)
        log.info(
            f"{placed} of {len(targets)} targets the detector could not place were placed by the box's other walls"
        )
    for n in notes:
        if n.startswith(CENTROIDS_NOTE):
            log.info(n)


def export_opencv(path, camera) -> None:
    """Write a camera as OpenCV FileStorage YAML (camera_matrix, distortion_coefficients), as
    ``slcvjax export --format opencv`` does (:func:`slcvjax.experiments.export.write_opencv`)."""
    from ..experiments.export import write_opencv

    write_opencv(path, camera, ["written by slcvjax"])


def board_flags(args) -> tuple[tuple[int, int], float]:
    """``--board`` and ``--square`` as ``((cols, rows), square_mm)``, checked the same way in every
    command that takes them (``camera``, ``omni``)."""
    pattern = board_arg(args.board)
    if not (args.square > 0 and np.isfinite(args.square)):
        raise FormatError(f"--square: must be a positive number of mm, got {args.square}")
    return pattern, float(args.square)


def board_arg(text: str) -> tuple[int, int]:
    try:
        cols, rows = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise FormatError(f"--board: expected COLSxROWS inner corners such as 9x6, got {text!r}") from None
    if cols < 2 or rows < 2:
        raise FormatError(f"--board: a chessboard has at least 2x2 inner corners, got {text!r}")
    return cols, rows


def print_points(names, views, circles) -> None:
    for k, (name, vp) in enumerate(zip(names, views, strict=True)):
        flagged = int(np.sum(vp.parallel))
        line = f"{name:>10s}  {len(vp.lasers):3d} points"
        if flagged:
            line += f" ({flagged} nearly parallel)"
        for i in np.flatnonzero(vp.off_line):
            other = f", on laser {vp.fits_laser[i]}'s" if vp.fits_laser[i] >= 0 else ""
            line += f"; spot {vp.spot_index[i]} off laser {vp.lasers[i]}'s line{other} (left out)"
        if vp.missing:
            line += f", {len(vp.missing)} spot(s) without a point"
        c = circles[k] if circles else None
        if c is not None:
            line += f"  diameter {c.diameter:.3f} +- {fmt(c.diameter_std)} mm  fit rms {c.rms:.3f} mm"
            if c.nearly_parallel_used:
                line += f"  (fewer than 3 reliable points: {c.nearly_parallel_used} nearly parallel ones used)"
        log.info(line)


def print_stripes(names, stripe_views, rings) -> None:
    """One line per view: its stripe points, grazing ones, and each ring laser's circle and ellipse."""
    for k, (name, svp) in enumerate(zip(names, stripe_views, strict=True)):
        line = f"{name:>10s}  {len(svp.lasers):4d} stripe points"
        if int(np.sum(svp.grazing)):
            line += f" ({int(np.sum(svp.grazing))} grazing, left out of fits)"
        if svp.missing:
            line += f", {len(svp.missing)} sample(s) without a point"
        for e, (c, el) in sorted((rings[k] if rings else {}).items()):
            line += f"  ring {e}: diameter {c.diameter:.3f} +- {fmt(c.diameter_std)} mm"
            if el is not None:
                ov_std = el.std["ovality"] if el.std else None
                line += f", ovality {100 * el.ovality:.3f} +- {fmt(None if ov_std is None else 100 * ov_std)} %"
        log.info(line)


def pipe_report(res, paper: bool = True) -> None:
    s = res["summary"]
    log.info(
        f"pipe {s['true_diameter_mm']:g} mm, {s['poses']} poses, {s['points']} points: "
        f"mean diameter {fmt(s['mean_diameter_mm'])} mm (median |error| "
        f"{fmt(s['median_abs_diameter_error_mm'])} mm, rms reported std {fmt(s['rms_diameter_std_mm'])} mm; "
        f"{s['diameters_within_two_std']} of {s['circles']} within two reported std of the truth)"
    )
    log.info(
        f"per-point fit error: mean {fmt(s['fit_error_mean_mm'])} mm, max {fmt(s['fit_error_max_mm'])} mm; "
        f"point error vs truth rms {fmt(s['point_error_rms_mm'])} mm (reported std rms "
        f"{fmt(s['point_std_rms_mm'])} mm, {s['nearly_parallel']} nearly parallel points left out"
        + (f", {s['off_line']} off their laser's line" if s.get("off_line") else "")
        + ")"
    )
    log.info(
        f"the reflected rays meet the laser lines at a median {fmt(s['median_ray_line_angle_deg'], 2)} deg: "
        "the smaller the angle, the less a pixel says about the depth along the beam"
    )
    if s["points"] and s["nearly_parallel"] > s["points"] // 2:
        log.info(
            f"warning: {s['nearly_parallel']} of {s['points']} points are nearly parallel to their rays given the "
            "pixel noise and the calibration's laser directions; these diameters are not reliable (see their std)"
        )
    if paper:
        log.info("paper (Chen et al. 2019, real sensor): diameter 150.042 mm, fit errors < 3 mm, mean 1.5 mm")


def write_pipe(out: Path, res: dict, points_name: str, noise: float) -> list[str]:
    """Write a pipe experiment's observations, points (``slcv-points/1``) and plots; their names."""
    from ..images.pipe import points_document
    from ..observations.formats import write_json_atomic
    from ..plots import plot_pipe

    obs = res["observations"]
    write_observations(out / "pipe_observations.json", obs)
    names = [v.name for v in obs.views]
    views, circles = [p["points"] for p in res["poses"]], [p["circle"] for p in res["poses"]]
    meta = {"pixel_sigma": noise, "simulation": obs.extra["simulation"], "summary": res["summary"]}
    write_json_atomic(out / points_name, points_document(names, views, circles, (0.0, 0.0, 1.0), meta))
    plots = plot_pipe(res, out)
    return ["pipe_observations.json", points_name] + [p.name for p in plots]


def fmt_finite(x, nd=1, width=5):
    return f"{x:{width}.{nd}f}" if np.isfinite(x) else f"{'-':>{width}s}"


class progress_lines:
    """While it lasts, the calibration's passes are reported as they end (the ``slcvjax.progress``
    logger at the command's level), after a line where the first run compiles."""

    def __enter__(self):
        from ..calibration.passes import progress
        from ..support.cache import compile_note

        self._logger, self._level = progress, progress.level
        progress.setLevel(logging.getLogger("slcvjax").getEffectiveLevel())
        note = compile_note()
        if note:
            log.info(note)
        return self

    def __exit__(self, *exc):
        self._logger.setLevel(self._level)
        return False


def study_options(args) -> dict:
    """A study command's ``--cluster``, ``--cluster-cache``, ``--chunk``, ``--resume`` and
    ``--restart`` as ``run_sweep``'s keywords (``cluster``, ``cache_dir``, ``chunk``, ``resume``).
    Checked before any work: a bad ``--cluster``, or one without Ray installed, raises
    :class:`slcvjax.experiments.cluster.StudyError` (one line, exit 2)."""
    from ..experiments.cluster import parse_cluster, require_ray

    cluster = None
    if args.cluster is not None:
        cluster = parse_cluster(args.cluster)
        require_ray()
    elif args.cluster_cache is not None:
        raise ValueError("--cluster-cache: only with --cluster")
    if args.chunk is not None and args.chunk < 1:
        raise ValueError(f"--chunk: expected at least 1 trial, got {args.chunk}")
    resume = "require" if args.resume else "restart" if args.restart else "auto"
    return {"cluster": cluster, "cache_dir": args.cluster_cache, "chunk": args.chunk, "resume": resume}
