"""The ``slcvjax`` command line."""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from ._io import FormatError, write_calibration, write_observations, write_text_atomic
from ._simulate import PAPER_HALF_WIDTH, PRESETS


def _summary(obs, truth) -> str:
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


def _cmd_simulate(args) -> int:
    from ._simulate import make_scene, simulate

    if args.pipe is not None:
        return _simulate_pipe(args)
    t0 = time.perf_counter()
    scene = make_scene(args.preset, n_lasers=args.lasers, n_views=args.views)
    obs, truth = simulate(scene, noise=args.noise, seed=args.seed)
    out = Path(args.out)
    write_observations(out / "observations.json", obs)
    write_calibration(out / "truth.json", truth)
    print(_summary(obs, truth))
    print(f"wrote {out / 'observations.json'} and {out / 'truth.json'} ({time.perf_counter() - t0:.1f} s)")
    if args.render:
        from ._render import render_scene

        opts = _render_options(args)
        t1 = time.perf_counter()
        files = render_scene(scene, out / "images", opts, progress=sys.stderr.isatty())
        print(f"wrote {len(files)} images and {out / 'images' / 'setup.json'} ({time.perf_counter() - t1:.1f} s)")
    return 0


def _render_options(args):
    """The image options of ``simulate --render``."""
    from ._render import RenderOptions

    return RenderOptions(noise=args.image_noise, blur=args.blur, exposure=args.exposure, seed=args.seed)


def _simulate_pipe(args) -> int:
    """``simulate --pipe D``: the preset's rig inside a pipe, its spots (and images with --render)."""
    from ._pipe import pipe_scene, simulate_pipe
    from ._simulate import make_scene

    t0 = time.perf_counter()
    rig = make_scene(args.preset, n_lasers=args.lasers, n_views=1).rig
    scene = pipe_scene(rig, args.pipe, args.views, seed=args.seed)
    obs, _ = simulate_pipe(scene, noise=args.noise, seed=args.seed)
    out = Path(args.out)
    write_observations(out / "pipe_observations.json", obs)
    n = sum(len(v.spots) for v in obs.views)
    print(f"pipe {args.pipe:g} mm, {len(obs.views)} poses, {n} spots; the pipe's truth in its simulation.pipe")
    print(f"wrote {out / 'pipe_observations.json'} ({time.perf_counter() - t0:.1f} s)")
    if args.render:
        from ._render import render_pipe

        opts = _render_options(args)
        t1 = time.perf_counter()
        files = render_pipe(scene, out / "pipe_images", opts, progress=sys.stderr.isatty())
        print(f"wrote {len(files)} images in {out / 'pipe_images'} ({time.perf_counter() - t1:.1f} s)")
    return 0


def _read_inputs(inputs: list[Path], progress: bool = True):
    """Each input as observations: a ``slcv-observations/1`` file, or an image folder (detected here)."""
    from ._detect import detect_folder
    from ._io import read_observations

    out = []
    for p in inputs:
        if p.is_dir():
            obs, rep = detect_folder(p, progress=progress and sys.stderr.isatty())
            bad = {k: v for k, v in rep.problems.items() if v}
            print(f"{p}: detected {len(obs.views)} catadioptric and {len(obs.calibration_views)} chessboard images"
                  f" ({len(bad)} with something not found; `slcvjax detect` lists them)")  # fmt: skip
            out.append(obs)
        else:
            out.append(read_observations(p))
    return out


def _cmd_detect(args) -> int:
    from ._detect import detect_folder

    t0 = time.perf_counter()
    obs, rep = detect_folder(args.folder, progress=sys.stderr.isatty())
    for line in rep.lines():
        print(line)
    write_observations(args.out, obs)
    n_dots = sum(int(s.sum()) for v in obs.views for _, s in v.boards.values())
    n_spots = sum(len(v.spots) for v in obs.views)
    n_corners = sum(int(c.seen.sum()) for c in obs.calibration_views)
    print(
        f"{n_dots} dots, {n_spots} spots, {sum(len(v.rim) for v in obs.views)} rim pixels, {n_corners} corners; "
        f"wrote {args.out} ({time.perf_counter() - t0:.1f} s)"
    )
    return 0


def _cmd_demo(args) -> int:
    from ._calibrate import (
        cramer_rao,
        laser_errors,
        reprojections,
        robust_sigma,
        to_calibration,
    )
    from ._centroids import calibrate_detected
    from ._rig import Rig
    from ._simulate import make_scene, simulate

    t0 = time.perf_counter()
    out = Path(args.out)
    images = not args.no_images
    steps = 5 if images else 4
    step = iter(range(1, steps + 1))
    print("slcvjax demo: the simulated reference rig (paper preset)", flush=True)
    print(f"[{next(step)}/{steps}] simulate", flush=True)
    scene = make_scene("paper", n_lasers=args.lasers, n_views=args.views)
    exact, truth = simulate(scene, noise=0.0 if images else args.noise, seed=args.seed)
    write_observations(out / "observations.json", exact)
    write_calibration(out / "truth.json", truth)
    print(_summary(exact, truth))
    timings = {}
    if images:
        from ._detect import detect_folder, read_image
        from ._render import RenderOptions, render_scene

        print(f"[{next(step)}/{steps}] render the images, then detect", flush=True)
        t1 = time.perf_counter()
        opts = RenderOptions(noise=args.image_noise, seed=args.seed)
        render_scene(scene, out / "images", opts, progress=sys.stderr.isatty())
        timings["render"] = time.perf_counter() - t1
        t1 = time.perf_counter()
        obs, rep = detect_folder(out / "images", progress=sys.stderr.isatty())
        timings["detect"] = time.perf_counter() - t1
        print(rep.summary() + " (each image's list: detection_report.txt)")
        write_text_atomic(out / "detection_report.txt", "\n".join(rep.lines()) + "\n")
        write_observations(out / "detected.json", obs)
        n_dots = sum(int(s.sum()) for v in obs.views for _, s in v.boards.values())
        n_spots = sum(len(v.spots) for v in obs.views)
        print(f"detected {n_dots} dots and {n_spots} spots in {len(obs.views)} views, "
              f"{sum(int(c.seen.sum()) for c in obs.calibration_views)} chessboard corners")  # fmt: skip
    else:
        obs = exact
    print(f"[{next(step)}/{steps}] calibrate: staged, then joint (the first run compiles, about a minute)", flush=True)
    t1 = time.perf_counter()
    rigid = args.rigid
    if rigid:
        print("  the box's walls as one rigid box: one pose per wall, one sensor pose per view")
    res, obs, notes = calibrate_detected(obs, rigid=rigid)
    _print_placed(notes)
    timings["calibration"] = time.perf_counter() - t1
    cal = to_calibration(res, obs)
    write_calibration(out / "calibration.json", cal)
    print_report(cal, "calibration")
    print(f"[{next(step)}/{steps}] compare with the truth and the Cramer-Rao bound", flush=True)
    # the bound at the noise of the points and spots (the detector's, from the residuals, for images)
    sigma = robust_sigma(res.params, res.packed) if images else max(args.noise, 1e-3)
    # with the boards the calibration gave the spots detected without one (else they are left out)
    bound = cramer_rao(truth, obs, sigma, packed=res.packed, rigid=rigid)
    pos, ang = laser_errors(res.rig, truth.rig, bound["x_ref"])
    st = res.staged
    pos_s, ang_s = laser_errors(Rig(st.camera, st.mirror, st.lasers), truth.rig, bound["x_ref"])
    unc = cal.extra["uncertainty"]["lasers"]
    print(f"bound at sigma {sigma:.3f} px" + (" (the dots' and spots' residuals)" if images else ""))
    print("laser  error (mm, deg)    reported std (mm, deg)   bound std (mm, deg)   staged error (mm, deg)")
    for i in range(len(pos)):
        print(
            f"{i:5d}  {pos[i]:6.3f} {np.degrees(ang[i]):6.3f}     {_fmt(unc[i]['position_std_mm']):>6s} "
            f"{_fmt(unc[i]['direction_std_deg']):>6s}          {bound['position_std_mm'][i]:6.3f} "
            f"{np.degrees(bound['direction_std_rad'][i]):6.3f}       {pos_s[i]:7.3f} {np.degrees(ang_s[i]):6.3f}"
        )
    rms = lambda x: float(np.sqrt(np.mean(np.square(x))))  # noqa: E731
    print(
        f"RMS    {rms(pos):6.3f} {np.degrees(rms(ang)):6.3f}     bound {bound['position_rms_mm']:.3f} "
        f"{np.degrees(bound['direction_rms_rad']):.3f}     staged {rms(pos_s):.3f} {np.degrees(rms(ang_s)):.3f}"
    )
    from ._plots import plot_detections, plot_rig

    v0 = 0
    walls = [(b, cal.board_poses[v0][b], obs.boards[b]) for b in sorted(cal.board_poses[v0])]
    plots = [plot_rig(res.rig, out / "rig_3d.png", walls, truth=truth.rig).name]
    if images:
        img = read_image(out / "images" / f"{obs.views[v0].name}.png", tuple(obs.image_size))
        plots.append(plot_detections(img, obs.views[v0], reprojections(cal, obs, v0), out / "detections.png").name)
    from ._pipe import measurement_inputs, pipe_experiment, pipe_scene, spots_from_images

    t2 = time.perf_counter()
    sigma_cal, rig_cov = measurement_inputs("calibration.json", cal)
    pipe_sc = pipe_scene(truth.rig, seed=args.seed)
    if images:
        from ._render import render_pipe

        print(f"[{next(step)}/{steps}] measure: the sensor rendered in a 150 mm pipe at 16 poses, its spots "
              "detected and labelled by this calibration's laser lines", flush=True)  # fmt: skip
        render_pipe(pipe_sc, out / "pipe_images", opts, progress=sys.stderr.isatty())
        # the demo knows its laser's spot size (the renderer's): the centroids are corrected for it
        observed, problems = spots_from_images(
            out / "pipe_images", res.rig, sigma_cal, rig_cov, spot_sigma_mm=opts.spot_sigma_mm
        )
        for name, probs in ((k, v) for k, v in problems.items() if v):
            print(f"  {name}: " + "; ".join(probs))
        pipe = pipe_experiment(
            res.rig, pipe_sc, args.noise, args.seed, pixel_sigma=sigma_cal, rig_cov=rig_cov, observed=observed
        )
        pixel_note = sigma_cal
    else:
        print(f"[{next(step)}/{steps}] measure: the sensor in a 150 mm pipe at 16 poses, {args.noise:g} px, "
              "with this calibration", flush=True)  # fmt: skip
        pipe = pipe_experiment(res.rig, pipe_sc, args.noise, args.seed, rig_cov=rig_cov)
        pixel_note = args.noise
    pipe_files = _write_pipe(out, pipe, "pipe_points.json", pixel_note)
    _pipe_report(pipe)
    timings["pipe"] = time.perf_counter() - t2
    print(
        "timings: "
        + ", ".join(f"{k} {v:.1f} s" for k, v in timings.items())
        + f" (compilation included), total {time.perf_counter() - t0:.1f} s"
    )
    files = ["observations.json", "truth.json"]
    files += ["images/", "detected.json", "detection_report.txt"] if images else []
    files += ["calibration.json"] + plots + (["pipe_images/"] if images else []) + pipe_files
    print(f"wrote {out}/ ({', '.join(files)})")
    return 0


def _fmt(x, nd=3):
    return "-" if x is None else f"{x:.{nd}f}"


def print_report(cal, name: str = "") -> None:
    """A short human-readable report of a calibration document's residuals and uncertainty."""
    res, unc = cal.extra["residuals"], cal.extra["uncertainty"]
    passes = cal.extra["stages"]["joint"]["passes"]
    print(f"== {name}" if name else "==")
    print(
        f"rms {res['rms_px']:.3f} px   sigma {res['sigma_px']:.3f} px   dof {res['dof']}   "
        f"joint: " + ", ".join(f"{p['name'].split(':')[0]} {p['steps']} steps {p['result']}" for p in passes)
    )
    print("per kind   " + "  ".join(f"{k} {_fmt(v)}" for k, v in res["by_kind_rms_px"].items()))
    print("per view   " + "  ".join(f"{k} {_fmt(v)}" for k, v in res["per_view_rms_px"].items()))
    print("per board  " + "  ".join(f"{k} {_fmt(v)}" for k, v in res["per_board_rms_px"].items()))
    if res["per_laser_rms_px"]:
        print("per laser  " + "  ".join(f"{k}: {_fmt(v)}" for k, v in res["per_laser_rms_px"].items()))
    out = res["outliers"]

    def _outlier(o):
        laser = f" laser {o['laser']}" if "laser" in o else ""
        return f"{o['kind']} {o['view']} {o['board']}{laser} {o['residual_px']:.1f} px"

    listed = "; ".join(_outlier(o) for o in out[:10]) + (" ..." if len(out) > 10 else "")
    print(f"outliers   {len(out)}" + (f": {listed}" if out else ""))
    fixed = res.get("repairs", [])

    def _repair(o):
        what = " ".join(str(x) for x in (o["kind"], o["view"], o["board"]) if x) + (
            f" #{o['index']}" if o["index"] >= 0 else ""
        )
        if o["action"] == "relabelled":
            return f"{what} laser {o['laser']} -> {o['new_laser']}"
        return f"{what} left out ({_fmt(o['residual_px'], 1)} px)"

    if fixed:
        listed = "; ".join(_repair(o) for o in fixed[:10]) + (" ..." if len(fixed) > 10 else "")
        print(f"repaired   {len(fixed)}: {listed}")
    if res.get("rim_outliers"):
        print(f"rim        {res['rim_outliers']} rim pixel(s) more than 5 sigma (the rim's own) off the rim")
    if res["invalid"]:
        print(f"invalid    {res['invalid']} observation(s) fall outside the model (off the mirror or the sensor)")
    for st in cal.extra["stages"]["staged"]["reports"]:
        if st["stage"] == "mirror_kind":
            print("mirror kind " + "; ".join(st["notes"]))
    if cal.rig.camera.telecentric:
        print(f"camera     telecentric (fx, fy in px per {cal.rig.camera.unit:g} mm; its depth is the gauge, held)")
    if not unc.get("converged", True):
        print(f"WARNING    {unc['status']}")
    cs = unc["camera_std"]
    print(f"camera std fx {_fmt(cs['fx'])} fy {_fmt(cs['fy'])} cx {_fmt(cs['cx'])} cy {_fmt(cs['cy'])} px")
    ms = unc["mirror_std"]
    apex, tilt = (", ".join(_fmt(v, 4) for v in ms[k]) for k in ("apex_mm", "axis_tilt_deg"))
    print(f"mirror std apex [{apex}] mm  axis [{tilt}] deg")
    if "conic_constant" in ms:  # the shape estimated
        print(
            f"mirror     {cal.rig.mirror.kind}, conic constant {float(cal.rig.mirror.conic):.4f} "
            f"(std {_fmt(ms['conic_constant'], 4)}), vertex radius {1.0 / float(cal.rig.mirror.curvature):g} mm held"
        )
    box = unc.get("rigid_box")
    if box:
        worst = max(
            (max(v for v in d["translation_std_mm"] if v is not None) for d in box["boards"].values()), default=0.0
        )
        print(
            f"rigid box  gauge {box['gauge']}, {len(box['boards'])} boards over {box['views']} views, box poses "
            f"std <= {worst:.3g} mm, {len(box['left_out'])} board pose(s) left out (do not fit the box)"
        )
    for i, las in enumerate(unc["lasers"]):
        print(
            f"laser {i:2d}   std {_fmt(las['position_std_mm'])} mm at {las['working_range_mm']:.0f} mm, "
            f"direction {_fmt(las['direction_std_deg'])} deg" + (f"  ({las['status']})" if "status" in las else "")
        )


def _print_placed(notes: list[str]) -> None:
    """One line for the targets the detector left out and the box placed (or could not)."""
    if notes:
        placed = sum("placed by the box" in n for n in notes)
        print(f"{placed} of {len(notes)} targets the detector could not place were placed by the box's other walls")


def _cmd_calibrate(args) -> int:
    from ._calibrate import to_calibration
    from ._centroids import calibrate_detected
    from ._io import read_calibration
    from ._staged import CalibrationError

    inputs = [Path(p) for p in args.inputs]
    observations = _read_inputs(inputs)  # all read (and image folders detected) before any calibration
    if args.camera and args.start_from:
        raise FormatError("--camera and --from both give the camera: give one")
    camera = read_calibration(args.camera).rig.camera if args.camera else None
    mirror = None
    if args.start_from:
        start = read_calibration(args.start_from).rig
        if start.mirror is None:
            raise FormatError(f"{args.start_from}: mirror: a camera-only calibration has no mirror to start from")
        camera, mirror = start.camera, start.mirror
    freeze = tuple(f for f in (args.freeze or "").split(",") if f)
    results = []
    for path, obs in zip(inputs, observations, strict=True):
        t0 = time.perf_counter()
        try:
            res, obs, notes = calibrate_detected(
                obs,
                camera=camera,
                mirror=mirror,
                freeze=freeze,
                loss=args.loss,
                loss_scale=args.loss_scale,
                rigid=args.rigid,
            )
        except CalibrationError as e:
            raise FormatError(f"{path}: {e}") from None
        _print_placed(notes)
        cal = to_calibration(res, obs)
        results.append((path, cal))
        print_report(cal, f"{path} ({time.perf_counter() - t0:.1f} s)")
    out = Path(args.out)
    if len(inputs) == 1 and out.suffix == ".json":
        targets = [out]
    else:
        if out.suffix == ".json":
            raise FormatError(f"{out}: several inputs need an output directory, not a .json file")
        targets = [out / f"{p.stem}.json" for p in inputs]
        if len({t.name for t in targets}) < len(targets):
            raise FormatError("inputs: two inputs share a file name; their outputs would collide")
    for (_, cal), target in zip(results, targets, strict=True):
        write_calibration(target, cal)
        print(f"wrote {target}")
    if args.export_opencv:
        export_opencv(args.export_opencv, results[0][1].rig.camera)
        print(f"wrote {args.export_opencv}")
    return 0


def export_opencv(path, camera) -> None:
    """Write a camera as OpenCV FileStorage YAML (camera_matrix, distortion_coefficients)."""
    import cv2

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{path.suffix}")
    fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", int(camera.width))
    fs.write("image_height", int(camera.height))
    fs.write("camera_matrix", np.asarray(camera.K, float))
    fs.write("distortion_coefficients", np.asarray(camera.dist, float).reshape(1, 5))
    fs.release()
    tmp.replace(path)


def _cmd_camera(args) -> int:
    from ._chessboard import calibrate_camera_images
    from ._io import Calibration
    from ._lasers import Lasers
    from ._rig import Rig
    from ._staged import CalibrationError

    cols, rows = _board_arg(args.board)
    if args.square <= 0:
        raise FormatError(f"--square: must be positive, got {args.square}")
    try:
        res = calibrate_camera_images(args.images, (cols, rows), args.square)
    except CalibrationError as e:
        raise FormatError(str(e)) from None
    for name, r in res.per_view_rms_px.items():
        print(f"{name}: rms {r:.4f} px")
    if res.missing:
        print(f"no {cols}x{rows} board found in: {', '.join(res.missing)}")
    c = res.camera
    print(
        f"fx {float(c.fx):.4f}  fy {float(c.fy):.4f}  cx {float(c.cx):.4f}  cy {float(c.cy):.4f}  "
        f"dist {np.round(np.asarray(c.dist), 6).tolist()}"
    )
    print(f"rms {res.rms_px:.5f} px (OpenCV's calibrateCamera on the same corners: {res.opencv_rms_px:.5f} px)")
    doc = Calibration(
        Rig(c, None, Lasers(np.zeros((0, 3)), np.zeros((0, 3)))),  # type: ignore[arg-type]
        extra={
            "residuals": {
                "rms_px": res.rms_px,
                "per_view_rms_px": res.per_view_rms_px,
                "opencv_rms_px": res.opencv_rms_px,
                "images_without_board": res.missing,
            }
        },
    )
    write_calibration(args.out, doc)
    print(f"wrote {args.out}")
    if args.export_opencv:
        export_opencv(args.export_opencv, c)
        print(f"wrote {args.export_opencv}")
    return 0


def _board_arg(text: str) -> tuple[int, int]:
    try:
        cols, rows = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise FormatError(f"--board: expected COLSxROWS inner corners such as 9x6, got {text!r}") from None
    if cols < 2 or rows < 2:
        raise FormatError(f"--board: a chessboard has at least 2x2 inner corners, got {text!r}")
    return cols, rows


def _cmd_omni(args) -> int:
    from ._calibrate import calibrate, to_calibration
    from ._omni import omni_observations, plot_residuals
    from ._staged import CalibrationError

    pattern = _board_arg(args.board)
    if not args.square > 0:
        raise FormatError(f"--square: must be positive, got {args.square}")
    shape: dict = {"kind": args.mirror}
    for key, val in (("vertex_radius", args.vertex_radius), ("conic_constant", args.conic), ("radius", args.rim)):
        if val is not None:
            shape[key] = val
    obs, missing = omni_observations(
        args.images, pattern, args.square, shape, "telecentric" if args.telecentric else "perspective"
    )
    n = len(obs.views)
    print(f"{n} of {len(args.images)} images show the {pattern[0]}x{pattern[1]} board")
    if missing:
        print(f"no board found in: {', '.join(missing)}")
    if args.observations:
        write_observations(args.observations, obs)
        print(f"wrote {args.observations}")
    t0 = time.perf_counter()
    try:
        res = calibrate(obs, loss=args.loss)
    except CalibrationError as e:
        raise FormatError(str(e)) from None
    cal = to_calibration(res, obs)
    cal.extra["images_without_board"] = missing
    print_report(cal, f"{n} views through the mirror ({time.perf_counter() - t0:.1f} s)")
    write_calibration(args.out, cal)
    print(f"wrote {args.out}")
    if not args.no_plot:
        out = Path(args.plot) if args.plot else Path(args.out).with_name(Path(args.out).stem + "_residuals.png")
        print(f"wrote {plot_residuals(args.images, cal, obs, out)}")
    return 0


def _parse_axis(text: str | None):
    if text is None:
        return (0.0, 0.0, 1.0)
    try:
        axis = [float(v) for v in text.split(",")]
    except ValueError:
        raise ValueError(f"--axis: expected three numbers x,y,z, got {text!r}") from None
    if len(axis) != 3 or not np.all(np.isfinite(axis)) or np.linalg.norm(axis) < 1e-12:
        raise ValueError(f"--axis: expected a non-zero finite vector x,y,z, got {text!r}")
    return tuple(axis)


def _print_points(names, views, circles) -> None:
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
            line += f"  diameter {c.diameter:.3f} +- {_fmt(c.diameter_std)} mm  fit rms {c.rms:.3f} mm"
            if c.nearly_parallel_used:
                line += f"  (fewer than 3 reliable points: {c.nearly_parallel_used} nearly parallel ones used)"
        print(line)


def _cmd_measure(args) -> int:
    from ._io import read_calibration, read_observations, write_json_atomic
    from ._pipe import measure_observations, measurement_inputs, points_document, view_circle

    cal = read_calibration(args.calibration)
    sigma_cal, cov = measurement_inputs(args.calibration, cal)
    sigma = args.pixel_sigma if args.pixel_sigma is not None else sigma_cal
    if sigma is None:
        raise ValueError(f"{args.calibration}: residuals: no residual sigma to use; give --pixel-sigma")
    if Path(args.input).is_dir():
        from ._pipe import spots_from_images

        obs, problems = spots_from_images(args.input, cal.rig, sigma, cov, args.spot_mm, _parse_axis(args.axis))
        bad = {k: v for k, v in problems.items() if v}
        n = sum(len(v.spots) for v in obs.views)
        print(f"{args.input}: {n} spots in {len(obs.views)} images, labelled by the calibration's laser lines"
              + (f", centroids corrected for a {args.spot_mm:g} mm spot" if args.spot_mm else ""))  # fmt: skip
        for name, probs in bad.items():
            print(f"  {name}: " + "; ".join(probs))
    else:
        obs = read_observations(args.input)
    if obs.n_lasers != cal.rig.lasers.n:
        raise ValueError(
            f"{args.input}: n_lasers: {obs.n_lasers}, but the calibration {args.calibration} has "
            f"{cal.rig.lasers.n} lasers"
        )
    axis = _parse_axis(args.axis)
    views = measure_observations(cal.rig, obs, sigma, cov)
    names = [v.name for v in obs.views]
    circles = None
    if args.fit_circle:
        circles = [view_circle(vp, axis, name=f"{args.input}: views[{k}] ({names[k]})") for k, vp in enumerate(views)]
    meta = {
        "calibration": str(args.calibration),
        "input": str(args.input),
        "pixel_sigma": sigma,
        "uncertainty": "pixel noise and calibration covariance" if cov is not None else "pixel noise only",
    }
    doc = points_document(names, views, circles, axis if args.fit_circle else None, meta)
    write_json_atomic(args.out, doc)
    _print_points(names, views, circles)
    print(f"pixel sigma {sigma:.3f} px; uncertainty from {meta['uncertainty']}")
    print(f"wrote {args.out}")
    return 0


def _pipe_report(res, paper: bool = True) -> None:
    s = res["summary"]
    print(
        f"pipe {s['true_diameter_mm']:g} mm, {s['poses']} poses, {s['points']} points: "
        f"mean diameter {_fmt(s['mean_diameter_mm'])} mm (median |error| "
        f"{_fmt(s['median_abs_diameter_error_mm'])} mm, rms reported std {_fmt(s['rms_diameter_std_mm'])} mm; "
        f"{s['diameters_within_two_std']} of {s['circles']} within two reported std of the truth)"
    )
    print(
        f"per-point fit error: mean {_fmt(s['fit_error_mean_mm'])} mm, max {_fmt(s['fit_error_max_mm'])} mm; "
        f"point error vs truth rms {_fmt(s['point_error_rms_mm'])} mm (reported std rms "
        f"{_fmt(s['point_std_rms_mm'])} mm, {s['nearly_parallel']} nearly parallel points left out"
        + (f", {s['off_line']} off their laser's line" if s.get("off_line") else "")
        + ")"
    )
    print(
        f"the reflected rays meet the laser lines at a median {_fmt(s['median_ray_line_angle_deg'], 2)} deg: "
        "the smaller the angle, the less a pixel says about the depth along the beam"
    )
    if s["points"] and s["nearly_parallel"] > s["points"] // 2:
        print(
            f"warning: {s['nearly_parallel']} of {s['points']} points are nearly parallel to their rays given the "
            "pixel noise and the calibration's laser directions; these diameters are not reliable (see their std)"
        )
    if paper:
        print("paper (Chen et al. 2019, real sensor): diameter 150.042 mm, fit errors < 3 mm, mean 1.5 mm")


def _write_pipe(out: Path, res: dict, points_name: str, noise: float) -> list[str]:
    """Write a pipe experiment's observations, points (``slcv-points/1``) and plots; their names."""
    from ._io import write_json_atomic
    from ._pipe import points_document
    from ._plots import plot_pipe

    obs = res["observations"]
    write_observations(out / "pipe_observations.json", obs)
    names = [v.name for v in obs.views]
    views, circles = [p["points"] for p in res["poses"]], [p["circle"] for p in res["poses"]]
    meta = {"pixel_sigma": noise, "simulation": obs.extra["simulation"], "summary": res["summary"]}
    write_json_atomic(out / points_name, points_document(names, views, circles, (0.0, 0.0, 1.0), meta))
    plots = plot_pipe(res, out)
    return ["pipe_observations.json", points_name] + [p.name for p in plots]


def _parse_levels(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise ValueError(f"--noise: expected comma-separated pixel sigmas such as 0,0.3,0.6, got {text!r}") from None


def _cmd_sweep(args) -> int:
    import jax

    from ._calibrate import resolve_batch
    from ._sweep import run_sweep, write_sweep

    levels = _parse_levels(args.noise)
    batch = resolve_batch(args.batch)

    print(
        f"sweep: preset {args.preset}, noise {list(levels)} px, {args.trials} trials per level, "
        f"{args.lasers} lasers, {args.views} views; {batch} over the trials on {len(jax.devices())} "
        f"{jax.default_backend()} device(s) (the first calibration compiles, about a minute)",
        flush=True,
    )
    doc = run_sweep(
        args.preset, levels, args.trials, args.seed, args.lasers, args.views, progress=sys.stderr.isatty(), batch=batch
    )
    m = doc["methods"]
    print("noise px   joint pos mm  dir deg   bound pos mm  dir deg   staged pos mm  dir deg")
    for i, s in enumerate(doc["noise"]):
        print(
            f"{s:8.3f}   {m['joint']['position_rms_mm'][i]:10.4f} {m['joint']['direction_rms_deg'][i]:8.4f}"
            f"   {m['bound']['position_rms_mm'][i]:10.4f} {m['bound']['direction_rms_deg'][i]:8.4f}"
            f"   {m['staged']['position_rms_mm'][i]:11.4f} {m['staged']['direction_rms_deg'][i]:8.4f}"
        )
    n = len(doc["trials_detail"])
    print(f"{doc['converged']} of {n} joint calibrations converged; {doc['seconds']:.1f} s")
    files = write_sweep(doc, args.out)
    print(f"wrote {', '.join(str(f) for f in files)}")
    return 0


def _parse_triple(text: str, name: str) -> np.ndarray:
    try:
        vals = [float(x) for x in text.split(",")]
    except ValueError:
        raise ValueError(f"--{name}: expected three comma-separated numbers, got {text!r}") from None
    if len(vals) != 3 or not all(np.isfinite(vals)) or min(vals) < 0:
        raise ValueError(f"--{name}: expected three non-negative numbers, got {text!r}")
    return np.asarray(vals)


def _cmd_design(args) -> int:
    from ._design import Plan, confirm, design_document, optimise, plot_design
    from ._io import write_json_atomic
    from ._simulate import box_scene, paper_rig, paper_views

    if args.views < 1:
        raise ValueError(f"--views must be at least 1, got {args.views}")
    if not (np.isfinite(args.box) and args.box > 0):
        raise ValueError(f"--box must be a positive width in mm, got {args.box}")
    rot = np.radians(_parse_triple(args.rotation, "rotation"))
    tra = _parse_triple(args.translation, "translation")
    rig = paper_rig(args.lasers)
    # the start: the preset's random motions, scaled from the preset's range to this one
    base = paper_views(args.views)
    preset = Plan(rig, base)
    start = base * np.where(preset.scale > 0, np.concatenate([rot, tra]) / preset.scale, 0.0)
    scene = box_scene(rig, start, args.box / 2.0)
    plan = Plan.from_scene(scene, start, noise=args.noise, rotation_range=rot, translation_range=tra)
    if args.measure:
        return _design_lasers(args, plan)
    print(
        f"design: {args.views} views in a {args.box:g} mm box, motion +-{np.degrees(rot).round(2).tolist()} deg, "
        f"+-{tra.tolist()} mm, {args.noise} px (compiling the bound's gradient takes about 30 s)",
        flush=True,
    )
    res = optimise(plan, steps=args.steps, position_weight=args.position_weight, progress=sys.stderr.isatty())
    b, a = res.predicted_before, res.predicted_after
    print("predicted (Cramer-Rao)   position rms mm   direction rms deg   dots  spots")
    for name, x in (("before", b), ("after", a)):
        print(f"  {name:22s} {x.position_rms_mm:15.4f}   {x.direction_rms_deg:17.4f}   {x.n_dots:4d}  {x.n_spots:5d}")
    print(
        f"  ratio                  {a.position_rms_mm / b.position_rms_mm:15.3f}   "
        f"{a.direction_rms_deg / b.direction_rms_deg:17.3f}   "
        f"({len(res.history) - 1} steps, {res.timings['total_s']:.1f} s)"
    )
    confirmed = None
    if args.confirm:
        print(f"confirming by simulation: {args.confirm} calibrations of each plan (each compiles once)", flush=True)
        confirmed = {}
        for name, p in (("before", res.before), ("after", res.after)):
            confirmed[name] = confirm(p, args.confirm, args.seed, progress=sys.stderr.isatty())
            c = confirmed[name]
            print(
                f"  {name:6s} simulated rms: position {_fmt(c['position_rms_mm'], 4)} mm, direction "
                f"{_fmt(c['direction_rms_deg'], 4)} deg ({c['converged']}/{c['trials']} converged"
                + (f", {c['failed']} could not be calibrated: {c['first_failure']}" if c["failed"] else "")
                + ")",
                flush=True,
            )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "design.json", design_document(res, confirmed))
    png = plot_design(res, out / "design.png")
    print(f"wrote {out / 'design.json'}, {png}")
    return 0


def _design_lasers(args, plan) -> int:
    from ._io import write_json_atomic
    from ._laser_design import MeasurePlan, confirm_lasers, laser_design_document, optimise_lasers, plot_laser_design

    diameters = _parse_numbers(args.diameters, "diameters")
    mp = MeasurePlan(
        plan, diameters, elevation_range_deg=args.elevation_range, ring_radius_range_mm=args.ring_radius_range,
        ring_z_range_mm=args.ring_z_range,
    )  # fmt: skip
    print(
        f"laser design for pipes of {', '.join(f'{x:g}' for x in diameters)} mm: elevations +-{args.elevation_range:g} "
        f"deg, ring radius +-{args.ring_radius_range:g} mm, height +-{args.ring_z_range:g} mm "
        "(compiling the prediction and its gradient takes about a minute)",
        flush=True,
    )
    res = optimise_lasers(mp, steps=args.steps, progress=sys.stderr.isatty())
    print("pipe mm    predicted diameter std mm (before -> after)   spots seen   smallest beam-ray angle deg")
    b, a = res.predicted_before, res.predicted_after
    for k, d in enumerate(diameters):
        std_b = "not measurable" if not np.isfinite(b.diameter_std_mm[k]) else f"{b.diameter_std_mm[k]:.3f}"
        std_a = "not measurable" if not np.isfinite(a.diameter_std_mm[k]) else f"{a.diameter_std_mm[k]:.3f}"
        print(
            f"{d:7g}    {std_b:>14s} -> {std_a:<14s}                  {b.spots_seen[k]:2d} -> {a.spots_seen[k]:2d}"
            f"      {_fmt_finite(b.min_angle_deg[k])} -> {_fmt_finite(a.min_angle_deg[k])}"
        )
    if not res.feasible:
        print(
            "no mounting in the range sees every spot in every pipe and keeps the lasers on the calibration walls: "
            "widen the range (--ring-z-range, --elevation-range) or narrow the pipes (--diameters); "
            "the mounting that sees the most spots is written"
        )
    confirmed = None
    if args.confirm:
        print(f"confirming by simulation: {args.confirm} calibrations of each mounting, each measuring every pipe")
        confirmed = {}
        for name, rig in (("before", res.rig_before), ("after", res.rig_after)):
            c = confirm_lasers(mp, rig, args.confirm, args.seed, progress=sys.stderr.isatty())
            confirmed[name] = c
            errs = ", ".join(_fmt(x) for x in c["diameter_error_rms_mm"])
            print(
                f"  {name:6s} simulated rms diameter error mm: {errs}"
                + (f" ({c['failed']} could not be calibrated: {c['first_failure']})" if c["failed"] else ""),
                flush=True,
            )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "laser_design.json", laser_design_document(res, confirmed))
    png = plot_laser_design(res, out / "laser_design.png", confirmed)
    print(f"wrote {out / 'laser_design.json'}, {png}")
    return 0 if res.feasible else 1


def _fmt_finite(x, nd=1, width=5):
    return f"{x:{width}.{nd}f}" if np.isfinite(x) else f"{'-':>{width}s}"


def _parse_numbers(text: str, name: str) -> np.ndarray:
    try:
        vals = np.array([float(x) for x in text.split(",")])
    except ValueError:
        raise ValueError(f"--{name}: expected comma-separated numbers, got {text!r}") from None
    if vals.size < 1 or not np.all(np.isfinite(vals)) or np.any(vals <= 0):
        raise ValueError(f"--{name}: expected positive numbers, got {text!r}")
    return vals


def _cmd_pipe(args) -> int:
    from ._io import read_calibration
    from ._pipe import measurement_inputs, pipe_experiment, pipe_scene
    from ._simulate import paper_rig

    t0 = time.perf_counter()
    out = Path(args.out)
    rig_cov = None
    if args.calibration:
        cal = read_calibration(args.calibration)
        _, rig_cov = measurement_inputs(args.calibration, cal)
        rig = cal.rig
        truth = paper_rig(rig.lasers.n)
        print(f"measuring with {args.calibration}; the pipe is simulated with the true paper rig", flush=True)
    else:
        truth = paper_rig(args.lasers)
        rig = truth
        print("measuring with the true paper rig (give --calibration to use a calibration)", flush=True)
    scene = pipe_scene(truth, args.diameter, args.poses, args.offset, args.tilt, seed=args.seed)
    res = pipe_experiment(rig, scene, args.noise, seed=args.seed, rig_cov=rig_cov)
    files = _write_pipe(out, res, "points.json", args.noise)
    names = [v.name for v in res["observations"].views]
    _print_points(names, [p["points"] for p in res["poses"]], [p["circle"] for p in res["poses"]])
    _pipe_report(res)
    print(f"wrote {out}/ ({', '.join(files)}) in {time.perf_counter() - t0:.1f} s")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="slcvjax", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("simulate", help="simulate a rig's observations and write them with the truth")
    s.add_argument("--preset", default="paper", help="scene preset (default: paper)")
    s.add_argument("--noise", type=float, default=0.0, help="Gaussian pixel noise sigma in px (default 0)")
    s.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    s.add_argument("--lasers", type=int, default=10, help="number of lasers (default 10)")
    s.add_argument("--views", type=int, default=16, help="number of catadioptric views (default 16)")
    s.add_argument("--out", required=True, help="output directory")
    s.add_argument("--render", action="store_true", help="also render DIR/images/ (PNG per view) and setup.json")
    s.add_argument(
        "--pipe",
        type=float,
        default=None,
        metavar="D",
        help="instead: the rig inside a pipe of inner diameter D mm at --views poses (DIR/pipe_observations.json; "
        "--render: DIR/pipe_images/)",
    )
    s.add_argument("--image-noise", type=float, default=1.0, help="sensor noise of rendered images, grey levels")
    s.add_argument("--blur", type=float, default=0.6, help="optical blur of rendered images, px (default 0.6)")
    s.add_argument("--exposure", type=float, default=1.0, help="exposure gain of rendered images (default 1)")
    s.set_defaults(func=_cmd_simulate)

    t = sub.add_parser("detect", help="detect spots, dots, rim and corners in an image folder (with setup.json)")
    t.add_argument("folder", help="image folder holding setup.json (slcv-setup/1)")
    t.add_argument("--out", required=True, help="output slcv-observations/1 file")
    t.set_defaults(func=_cmd_detect)

    c = sub.add_parser("calibrate", help="calibrate the rig from observation files or image folders")
    c.add_argument("inputs", nargs="+", help="slcv-observations/1 file(s) or image folder(s) with setup.json")
    c.add_argument("--out", required=True, help="output file (one input) or directory (several)")
    c.add_argument("--camera", help="a slcv-calibration/1 file whose camera starts the calibration")
    c.add_argument(
        "--from",
        dest="start_from",
        help="a slcv-calibration/1 file whose camera and mirror start the calibration (with --freeze camera,mirror: "
        "only the poses and lasers are fitted, the held-out evaluation of that calibration)",
    )
    c.add_argument("--freeze", help="comma-separated blocks to hold fixed: camera, mirror, lasers, poses, chess_poses")
    c.add_argument(
        "--loss",
        default="huber",
        choices=["huber", "cauchy", "linear"],
        help="robust loss (default huber); linear: plain least squares, no outlier left out",
    )
    c.add_argument("--loss-scale", type=float, default=None, help="robust loss scale in px (default 3 sigma)")
    c.add_argument(
        "--rigid",
        action="store_true",
        help="the targets the observations declare fixed in one box (rigid_boards) as one pose per board in the "
        "box and one sensor pose per view; a board pose that does not fit the box is left out and reported",
    )
    c.add_argument("--export-opencv", help="also write the camera as OpenCV FileStorage YAML")
    c.set_defaults(func=_cmd_calibrate)

    k = sub.add_parser("camera", help="calibrate a plain camera from chessboard images")
    k.add_argument("images", nargs="+")
    k.add_argument("--board", default="9x6", help="inner corners COLSxROWS (default 9x6)")
    k.add_argument("--square", type=float, default=25.0, help="square size in mm (default 25)")
    k.add_argument("--out", required=True, help="output slcv-calibration/1 file (camera only)")
    k.add_argument("--export-opencv", help="also write OpenCV FileStorage YAML")
    k.set_defaults(func=_cmd_camera)

    o = sub.add_parser("omni", help="calibrate a catadioptric camera from chessboard images seen through its mirror")
    o.add_argument("images", nargs="+")
    o.add_argument("--board", required=True, help="inner corners COLSxROWS, e.g. 6x8")
    o.add_argument("--square", type=float, required=True, help="square size in mm")
    o.add_argument("--out", required=True, help="output slcv-calibration/1 file")
    o.add_argument(
        "--mirror",
        default="hyperboloid",
        choices=["hyperboloid", "paraboloid", "sphere", "ellipsoid", "auto"],
        help="the mirror's kind (default hyperboloid: its conic constant estimated unless --conic; "
        "auto: the kind of the least held-out error, by 5-fold cross-validation over the images)",
    )
    o.add_argument("--vertex-radius", type=float, help="the mirror's vertex radius in mm (default: 20, the gauge)")
    o.add_argument("--conic", type=float, help="the mirror's conic constant, where known")
    o.add_argument("--rim", type=float, help="the mirror's rim radius in mm, where known")
    o.add_argument("--telecentric", action="store_true", help="the camera's lens is telecentric (orthographic)")
    o.add_argument("--loss", default="huber", choices=["huber", "cauchy", "linear"])
    o.add_argument("--observations", help="also write the detected corners as slcv-observations/1")
    o.add_argument("--plot", help="the residual plot's PNG (default: OUT's name with _residuals.png)")
    o.add_argument("--no-plot", action="store_true")
    o.set_defaults(func=_cmd_omni)

    m = sub.add_parser("measure", help="3D laser points (and pipe circles) from spots with a calibration")
    m.add_argument("calibration", help="slcv-calibration/1 file")
    m.add_argument(
        "input",
        help="slcv-observations/1 file whose views carry spots (their board may be absent), or a folder of "
        "images (each a view; spots labelled by the calibration's laser lines)",
    )
    m.add_argument("--out", required=True, help="output slcv-points/1 file")
    m.add_argument("--fit-circle", action="store_true", help="fit a circle per view across the axis")
    m.add_argument("--pixel-sigma", type=float, default=None, help="spot pixel noise in px (default: calibration's)")
    m.add_argument("--axis", default=None, help="pipe axis x,y,z in the camera frame (default 0,0,1)")
    m.add_argument(
        "--spot-mm",
        type=float,
        default=None,
        help="images only: the laser spot's Gaussian std on the surface (mm); corrects each centroid for the "
        "mirror's distortion of the spot's image (the surface taken as a pipe's wall about --axis)",
    )
    m.set_defaults(func=_cmd_measure)

    w = sub.add_parser("sweep", help="noise-sensitivity sweep: Monte Carlo calibrations beside the bound")
    w.add_argument("--preset", default="paper", choices=PRESETS, help="simulated scene (default paper)")
    w.add_argument("--noise", default="0,0.3,0.6,0.9", help="pixel noise levels, px (default 0,0.3,0.6,0.9)")
    w.add_argument("--trials", type=int, default=8, help="trials per level (default 8)")
    w.add_argument("--seed", type=int, default=0, help="first seed (trial t of level l uses seed + 1000 l + t)")
    w.add_argument("--lasers", type=int, default=10, help="lasers (default 10)")
    w.add_argument("--views", type=int, default=16, help="catadioptric views (default 16)")
    w.add_argument(
        "--batch",
        default="auto",
        choices=("auto", "loop", "vmap"),
        help="trials one after another (loop) or in lockstep, vmap-ped and sharded over the devices "
        "(default auto: loop on a CPU, vmap on an accelerator)",
    )
    w.add_argument("--out", default="slcvjax-sweep", help="output directory (default ./slcvjax-sweep)")
    w.set_defaults(func=_cmd_sweep)

    g = sub.add_parser("design", help="plan a calibration: predict the lasers' accuracy and optimise the sensor poses")
    g.add_argument("--views", type=int, default=16, help="catadioptric views (default 16)")
    g.add_argument(
        "--box",
        type=float,
        default=2 * PAPER_HALF_WIDTH,
        help=f"box width in mm (default {2 * PAPER_HALF_WIDTH:g}, the preset's)",
    )
    g.add_argument(
        "--rotation", default="3,3,20", help="allowed roll,pitch,yaw of the sensor in the box, +- deg (default 3,3,20)"
    )
    g.add_argument("--translation", default="25,25,8", help="allowed x,y,z motion in the box, +- mm (default 25,25,8)")
    g.add_argument("--noise", type=float, default=0.5, help="pixel noise in px (default 0.5)")
    g.add_argument("--lasers", type=int, default=10, help="lasers (default 10)")
    g.add_argument("--steps", type=int, default=60, help="most gradient steps (default 60)")
    g.add_argument(
        "--position-weight", type=float, default=0.5, help="weight of the position error beside the direction's (0.5)"
    )
    g.add_argument(
        "--measure",
        action="store_true",
        help="design the lasers (elevations, ring radius and height) for measuring pipes instead of the poses",
    )
    g.add_argument(
        "--diameters", default="100,150,200,250,300", help="with --measure: the pipes in mm (default 100,...,300)"
    )
    g.add_argument("--elevation-range", type=float, default=20.0, help="with --measure: +- deg per beam (20)")
    g.add_argument("--ring-radius-range", type=float, default=10.0, help="with --measure: +- mm (10)")
    g.add_argument("--ring-z-range", type=float, default=25.0, help="with --measure: +- mm along the axis (25)")
    g.add_argument("--confirm", type=int, default=0, help="simulate and calibrate each plan N times")
    g.add_argument("--seed", type=int, default=0, help="first seed of the confirmation")
    g.add_argument("--out", default="slcvjax-design", help="output directory (default ./slcvjax-design)")
    g.set_defaults(func=_cmd_design)

    q = sub.add_parser("pipe", help="the paper's pipe experiment on the simulated rig")
    q.add_argument("--calibration", help="measure with this calibration (default: the true rig)")
    q.add_argument("--noise", type=float, default=0.5, help="spot pixel noise in px (default 0.5)")
    q.add_argument("--diameter", type=float, default=150.0, help="pipe diameter in mm (default 150)")
    q.add_argument("--poses", type=int, default=16, help="sensor poses in the pipe (default 16)")
    q.add_argument("--offset", type=float, default=10.0, help="largest offset of the pipe's axis in mm (default 10)")
    q.add_argument("--tilt", type=float, default=0.0, help="pipe axis tilt from the camera z axis in deg (default 0)")
    q.add_argument("--lasers", type=int, default=10, help="lasers of the simulated rig (default 10)")
    q.add_argument("--seed", type=int, default=0)
    q.add_argument("--out", default="slcvjax-pipe", help="output directory (default ./slcvjax-pipe)")
    q.set_defaults(func=_cmd_pipe)

    d = sub.add_parser("demo", help="the main job on the simulated reference rig")
    d.add_argument(
        "--noise",
        type=float,
        default=0.5,
        help="pixel noise of the pipe spots (and of --no-images), px (default 0.5)",
    )
    d.add_argument("--image-noise", type=float, default=1.0, help="sensor noise of the images, grey levels (default 1)")
    d.add_argument(
        "--no-images", action="store_true", help="calibrate the simulated observations directly (no render or detect)"
    )
    d.add_argument(
        "--rigid",
        action="store_true",
        help="calibrate with the rigid target box model (one pose per wall, one sensor pose per view)",
    )
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--views", type=int, default=16, help="catadioptric views (default 16)")
    d.add_argument("--lasers", type=int, default=10, help="lasers (default 10)")
    d.add_argument("--out", default="slcvjax-demo", help="output directory (default ./slcvjax-demo)")
    d.set_defaults(func=_cmd_demo)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (FormatError, ValueError) as e:
        print(f"slcvjax {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
