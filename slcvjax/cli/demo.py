"""``slcvjax demo``: the main job on the simulated reference rig: render, detect, calibrate, measure, report."""

import logging
import sys
import time
from pathlib import Path

import numpy as np

from ..observations.formats import write_calibration, write_observations, write_text_atomic
from .common import fmt, pipe_report, print_placed, print_report, summary, write_pipe

log = logging.getLogger(__name__)


def run(args) -> int:
    from ..calibration.bound import cramer_rao, laser_errors
    from ..calibration.report import reprojections, to_calibration
    from ..images.centroids import calibrate_detected
    from ..observations.problem import KIND_NAMES
    from ..observations.simulate import make_scene, simulate

    t0 = time.perf_counter()
    out = Path(args.out)
    images = not args.no_images
    steps = 5 if images else 4
    step = iter(range(1, steps + 1))
    log.info("slcvjax demo: the simulated reference rig (paper preset)")
    log.info(f"[{next(step)}/{steps}] simulate")
    scene = make_scene("paper", n_lasers=args.lasers, n_views=args.views)
    exact, truth = simulate(scene, noise=0.0 if images else args.noise, seed=args.seed)
    write_observations(out / "observations.json", exact)
    write_calibration(out / "truth.json", truth)
    log.info(summary(exact, truth))
    timings = {}
    if images:
        from ..images.detect import detect_folder, read_image
        from ..images.render import RenderOptions, render_scene

        log.info(f"[{next(step)}/{steps}] render the images, then detect")
        t1 = time.perf_counter()
        opts = RenderOptions(noise=args.image_noise, seed=args.seed)
        render_scene(scene, out / "images", opts, progress=sys.stderr.isatty())
        timings["render"] = time.perf_counter() - t1
        t1 = time.perf_counter()
        obs, rep = detect_folder(out / "images", progress=sys.stderr.isatty())
        timings["detect"] = time.perf_counter() - t1
        log.info(rep.summary() + " (each image's list: detection_report.txt)")
        write_text_atomic(out / "detection_report.txt", "\n".join(rep.lines()) + "\n")
        write_observations(out / "detected.json", obs)
        n_dots = sum(int(s.sum()) for v in obs.views for _, s in v.boards.values())
        n_spots = sum(len(v.spots) for v in obs.views)
        log.info(f"detected {n_dots} dots and {n_spots} spots in {len(obs.views)} views, "
                 f"{sum(int(c.seen.sum()) for c in obs.calibration_views)} chessboard corners")  # fmt: skip
    else:
        obs = exact
    log.info(f"[{next(step)}/{steps}] calibrate: staged, then joint (the first run compiles, about a minute)")
    t1 = time.perf_counter()
    rigid = not args.free_poses
    if rigid:
        log.info("  the box's walls as one rigid box: one pose per wall, one sensor pose per view")
    res, obs, notes = calibrate_detected(obs, rigid=rigid)
    print_placed(notes)
    timings["calibration"] = time.perf_counter() - t1
    cal = to_calibration(res, obs)
    write_calibration(out / "calibration.json", cal)
    print_report(cal, "calibration")
    log.info(f"[{next(step)}/{steps}] compare with the truth and the Cramer-Rao bound")
    # the bound at the simulated noise, or for images at each kind's noise as the calibration
    # estimated it (the detector's: spots noisier than dots, the rim's fitted edge far less)
    if images:
        pooled = float(res.cov.sigma)
        names = [k for k in KIND_NAMES if k in res.kind_sigma]  # the kinds the problem has
        sigma = [v if v is not None and np.isfinite(v) else pooled for v in (res.kind_sigma[k] for k in names)]
    else:
        sigma = max(args.noise, 1e-3)
    # with the boards the calibration gave the spots detected without one (else they are left out)
    bound = cramer_rao(truth, obs, sigma, packed=res.packed, rigid=rigid)
    pos, ang = laser_errors(res.rig, truth.rig, bound["x_ref"])
    st = res.staged
    pos_s, ang_s = laser_errors(st.rig, truth.rig, bound["x_ref"])
    unc = cal.extra["uncertainty"]["lasers"]
    if images:
        each = ", ".join(f"{k} {v:.3g}" for k, v in zip(names, sigma, strict=True))
        log.info(f"bound at each kind's noise as the calibration estimated it ({each} px)")
    else:
        log.info(f"bound at sigma {sigma:.3f} px")
    log.info("laser  error (mm, deg)    reported std (mm, deg)   bound std (mm, deg)   staged error (mm, deg)")
    held = list(res.undetermined_lasers)
    for i in range(len(pos)):
        if i in held:
            log.info(f"{i:5d}  undetermined: its spots cannot fix a line (held; left out of the RMS below)")
            continue
        log.info(
            f"{i:5d}  {pos[i]:6.3f} {np.degrees(ang[i]):6.3f}     {fmt(unc[i]['position_std_mm']):>6s} "
            f"{fmt(unc[i]['direction_std_deg']):>6s}          {bound['position_std_mm'][i]:6.3f} "
            f"{np.degrees(bound['direction_std_rad'][i]):6.3f}       {pos_s[i]:7.3f} {np.degrees(ang_s[i]):6.3f}"
        )
    if held:  # the figures below over the lasers the data fix
        keep = np.setdiff1d(np.arange(len(pos)), held)
        pos, ang, pos_s, ang_s = pos[keep], ang[keep], pos_s[keep], ang_s[keep]
        bound = bound | {
            "position_rms_mm": float(np.sqrt(np.mean(np.square(bound["position_std_mm"][keep])))),
            "direction_rms_rad": float(np.sqrt(np.mean(np.square(bound["direction_std_rad"][keep])))),
        }
    rms = lambda x: float(np.sqrt(np.mean(np.square(x))))  # noqa: E731
    log.info(
        f"RMS    {rms(pos):6.3f} {np.degrees(rms(ang)):6.3f}     bound {bound['position_rms_mm']:.3f} "
        f"{np.degrees(bound['direction_rms_rad']):.3f}     staged {rms(pos_s):.3f} {np.degrees(rms(ang_s)):.3f}"
    )
    from ..plots import plot_detections, plot_rig

    v0 = 0
    walls = [(b, cal.board_poses[v0][b], obs.boards[b]) for b in sorted(cal.board_poses[v0])]
    plots = [plot_rig(res.rig, out / "rig_3d.png", walls, truth=truth.rig).name]
    if images:
        img = read_image(out / "images" / f"{obs.views[v0].name}.png", tuple(obs.image_size))
        plots.append(plot_detections(img, obs.views[v0], reprojections(cal, obs, v0), out / "detections.png").name)
    from ..images.pipe import measurement_inputs, pipe_experiment, pipe_scene, spots_from_images

    t2 = time.perf_counter()
    sigma_cal, rig_cov = measurement_inputs("calibration.json", cal)
    pipe_sc = pipe_scene(truth.rig, seed=args.seed)
    if images:
        from ..images.render import render_pipe

        log.info(f"[{next(step)}/{steps}] measure: the sensor rendered in a 150 mm pipe at 16 poses, its spots "
                 "detected and labelled by this calibration's laser lines")  # fmt: skip
        render_pipe(pipe_sc, out / "pipe_images", opts, progress=sys.stderr.isatty())
        # the demo knows its laser's spot size (the renderer's): the centroids are corrected for it
        observed, problems = spots_from_images(
            out / "pipe_images",
            res.rig,
            sigma_cal,
            rig_cov,
            spot_sigma_mm=opts.spot_sigma_mm,
            undetermined=res.undetermined_lasers,
        )
        for name, probs in ((k, v) for k, v in problems.items() if v):
            log.info(f"  {name}: " + "; ".join(probs))
        pipe = pipe_experiment(
            res.rig,
            pipe_sc,
            args.noise,
            args.seed,
            pixel_sigma=sigma_cal,
            rig_cov=rig_cov,
            observed=observed,
            undetermined=res.undetermined_lasers,
        )
        pixel_note = sigma_cal
    else:
        log.info(f"[{next(step)}/{steps}] measure: the sensor in a 150 mm pipe at 16 poses, {args.noise:g} px, "
                 "with this calibration")  # fmt: skip
        pipe = pipe_experiment(
            res.rig, pipe_sc, args.noise, args.seed, rig_cov=rig_cov, undetermined=res.undetermined_lasers
        )
        pixel_note = args.noise
    pipe_files = write_pipe(out, pipe, "pipe_points.json", pixel_note)
    pipe_report(pipe)
    timings["pipe"] = time.perf_counter() - t2
    log.info(
        "timings: "
        + ", ".join(f"{k} {v:.1f} s" for k, v in timings.items())
        + f" (compilation included), total {time.perf_counter() - t0:.1f} s"
    )
    files = ["observations.json", "truth.json"]
    files += ["images/", "detected.json", "detection_report.txt"] if images else []
    files += ["calibration.json"] + plots + (["pipe_images/"] if images else []) + pipe_files
    log.info(f"wrote {out}/ ({', '.join(files)})")
    return 0
