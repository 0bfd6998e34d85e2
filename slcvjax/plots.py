"""Figures people would rather look at than read (matplotlib, written as PNG files)."""

from pathlib import Path

import numpy as np

from .support.mpl import pyplot


def plot_pipe(result: dict, out_dir, axis=(0.0, 0.0, 1.0)) -> list[Path]:
    """The pipe experiment's figures: 3D points, cross-sections with the fitted circles, errors.

    ``result`` is what :func:`slcvjax.images.pipe.pipe_experiment` returns.  Writes
    ``pipe_points.png`` (every measured point in 3D beside the true pipe wall),
    ``pipe_circles.png`` (each pose's cross-section: points, fitted and true circles)
    and ``pipe_errors.png`` (each point's fit error per pose, and each pose's
    diameter with its standard deviation).  Returns the paths.
    """
    from .measurement.measure import plane_basis

    plt = pyplot()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    poses = result["poses"]
    d_true = result["summary"]["true_diameter_mm"]
    paths = []

    fig = plt.figure(figsize=(7, 6))
    ax = fig.add_subplot(projection="3d")
    for i, p in enumerate(poses):
        vp = p["points"]
        ok = ~vp.parallel
        ax.scatter(*vp.xyz[ok].T, s=8, color=plt.cm.viridis(i / max(len(poses) - 1, 1)))
        far = vp.parallel & (np.max(np.abs(vp.xyz[:, :2]), axis=1) < 0.75 * d_true)
        if np.any(far):
            ax.scatter(*vp.xyz[far].T, s=14, marker="x", color="red")
    ang = np.linspace(0, 2 * np.pi, 100)
    good = [p["points"].xyz[~p["points"].parallel] for p in poses]
    z = np.concatenate([g[:, 2] for g in good]) if good and sum(len(g) for g in good) else np.zeros(1)
    lim = 0.75 * d_true  # nearly parallel points can land far away: keep the pipe in view
    for zz in (np.min(z), np.max(z)):
        ax.plot(d_true / 2 * np.cos(ang), d_true / 2 * np.sin(ang), zz, color="0.6", lw=0.8)
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-lim, lim)
    ax.set_zlim(np.min(z) - 0.2 * d_true, np.max(z) + 0.2 * d_true)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    ax.set_title(f"Measured laser points, {len(poses)} poses (x: nearly parallel ray and line, in view)")
    paths.append(out / "pipe_points.png")
    fig.savefig(paths[-1], dpi=110, bbox_inches="tight")
    plt.close(fig)

    n = len(poses)
    cols = int(np.ceil(np.sqrt(n))) if n else 1
    rows = int(np.ceil(n / cols)) if n else 1
    fig, axs = plt.subplots(rows, cols, figsize=(2.6 * cols, 2.6 * rows), squeeze=False)
    basis = plane_basis(axis)
    for i, a in enumerate(axs.ravel()):
        if i >= n:
            a.axis("off")
            continue
        p = poses[i]
        vp = p["points"]
        q = vp.xyz @ basis.T
        a.plot(*q[~vp.parallel].T, "o", ms=3, color="C0")
        if np.any(vp.parallel):
            a.plot(*q[vp.parallel].T, "x", ms=4, color="red")
        qt = p["truth"] @ basis.T
        a.plot(*qt.T, ".", ms=2, color="k")
        c = p["circle"]
        if c is not None:
            a.plot(c.center[0] + c.diameter / 2 * np.cos(ang), c.center[1] + c.diameter / 2 * np.sin(ang), "C1", lw=1)
            a.set_title(f"pose {i}: {c.diameter:.2f} mm", fontsize=8)
        centre = qt[np.all(np.isfinite(qt), axis=1)].mean(axis=0) if np.isfinite(qt).any() else np.zeros(2)
        a.set_xlim(centre[0] - 0.7 * d_true, centre[0] + 0.7 * d_true)
        a.set_ylim(centre[1] - 0.7 * d_true, centre[1] + 0.7 * d_true)
        a.set_aspect("equal")
        a.tick_params(labelsize=6)
    fig.suptitle(f"Cross-sections: points (o), truth (.), nearly parallel (x), fit (line); pipe {d_true:g} mm")
    paths.append(out / "pipe_circles.png")
    fig.savefig(paths[-1], dpi=110, bbox_inches="tight")
    plt.close(fig)

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4))
    for i, p in enumerate(poses):
        c = p["circle"]
        if c is not None:
            a1.plot(np.full(c.residuals.size, i), np.abs(c.residuals), "o", ms=3, color="C0")
    a1.set_xlabel("pose")
    a1.set_ylabel("|fit error| (mm)")
    a1.set_title("Each point's distance to its pose's fitted circle")
    idx = [i for i, p in enumerate(poses) if p["circle"] is not None]
    diam = [poses[i]["circle"].diameter for i in idx]
    dstd = [poses[i]["circle"].diameter_std or 0.0 for i in idx]
    a2.errorbar(idx, diam, yerr=dstd, fmt="o", ms=4, capsize=3)
    a2.axhline(d_true, color="k", lw=0.8, label=f"true {d_true:g} mm")
    if diam:
        a2.axhline(np.mean(diam), color="C1", lw=0.8, ls="--", label=f"mean {np.mean(diam):.3f} mm")
    a2.set_xlabel("pose")
    a2.set_ylabel("diameter (mm)")
    a2.set_title("Fitted diameter with its standard deviation")
    a2.legend(fontsize=8)
    paths.append(out / "pipe_errors.png")
    fig.savefig(paths[-1], dpi=110, bbox_inches="tight")
    plt.close(fig)
    return paths


def _cone_mesh(mirror, n_az: int = 48, n_s: int = 8):
    """Surface points of the cone mirror as (3, n_s, n_az) grids for ``plot_surface``."""
    from .support.safe import orthonormal_basis

    apex, axis = np.asarray(mirror.apex), np.asarray(mirror.axis)
    e1, e2 = (np.asarray(e) for e in orthonormal_basis(mirror.axis))
    s = np.linspace(0.0, float(mirror.height), n_s)[:, None, None]
    a = np.linspace(0.0, 2 * np.pi, n_az)[None, :, None]
    ring = np.cos(a) * e1 + np.sin(a) * e2
    pts = apex + s * axis + (s * float(mirror.radius) / float(mirror.height)) * ring
    return pts[..., 0], pts[..., 1], pts[..., 2]


def sheet_lines(sheets, j: int, length: float, n: int = 24) -> list[np.ndarray]:
    """Line segments (each (2, 3) or (n+1, 3), mm) that draw sheet ``j`` of ``sheets``: a cone's
    generatrices from its apex to ``length`` mm and the circle joining their ends; a plane's
    (half-angle 90 deg) spokes and rim of a disc of radius ``length`` about its point."""
    from .support.safe import orthonormal_basis

    apex, axis = np.asarray(sheets.apex[j], float), np.asarray(sheets.axis[j], float)
    theta = float(sheets.half_angle[j])
    e1, e2 = (np.asarray(v, float) for v in orthonormal_basis(axis))
    phi = np.linspace(0.0, 2 * np.pi, n + 1)
    dirs = np.cos(theta) * axis[None] + np.sin(theta) * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    ends = apex[None] + length * dirs
    spokes = [np.stack([apex, x]) for x in ends[:-1:3]]
    return spokes + [ends]


def plot_rig(rig, path, walls=(), truth=None, title: str | None = None, omit=()) -> Path:
    """A 3D view of the sensor (the paper's Fig. 5): camera, cone mirror, laser lines, line and ring
    lasers' sheets of light (a plane as a disc of 150 mm about its point, a cone by its
    generatrices to 150 mm) and targets.

    Args:
        rig: the calibrated :class:`~slcvjax.geometry.rig.Rig`.
        path: the PNG file to write.
        walls: ``(name, T_cam_board, points_board)`` of the targets to draw (one view's
            walls, say); each laser line is drawn up to the farthest wall it meets in front
            of its origin, or 300 mm without walls.
        truth: a second rig drawn dashed (the simulator's truth), for comparison.
        omit: lasers not to draw (a calibration's undetermined lasers, held at a placeholder).
    """
    from .geometry.lasers import line_plane_intersection

    plt = pyplot()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig = plt.figure(figsize=(8, 7))
    ax = fig.add_subplot(projection="3d")
    from .geometry.mirror import ConeMirror

    if isinstance(rig.mirror, ConeMirror):  # a cone: its surface
        ax.plot_surface(*_cone_mesh(rig.mirror), color="silver", alpha=0.5, linewidth=0)
    else:  # another mirror of revolution: its rim
        ax.plot(*np.asarray(rig.mirror.rim_points(np.linspace(0.0, 2 * np.pi, 73))).T, color="0.4", lw=1.0)
    ax.scatter([0], [0], [0], marker="s", s=40, color="k")
    size = 0.6 * float(rig.mirror.height if isinstance(rig.mirror, ConeMirror) else rig.mirror.radius) + 10.0
    for k, c in enumerate(("r", "g", "b")):  # the camera frame's axes
        ax.plot([0, size * (k == 0)], [0, size * (k == 1)], [0, size * (k == 2)], color=c, lw=1.5)
    ax.text(0, 0, -0.5 * size, "camera", fontsize=8)
    spans = []
    for name, T, pts in walls:
        x = np.asarray(T.apply(np.asarray(pts, dtype=float)))
        ax.scatter(*x.T, s=2, color="0.3")
        cx = x.mean(axis=0)
        ax.text(*cx, name, fontsize=7, color="0.3")
        spans.append(x)

    def reach(las, i):
        """The line from its origin to the wall it meets within the wall's extent (else 300 mm)."""
        p, d = np.asarray(las.points[i]), np.asarray(las.directions[i])
        hits = []
        for _, T, pts in walls:
            x, ok = line_plane_intersection(las.points[i], las.directions[i], T)
            s = float(np.dot(np.asarray(x) - p, d))
            xb = np.asarray(T.inverse().apply(x))[:2]
            lo, hi = np.min(pts, axis=0)[:2], np.max(pts, axis=0)[:2]
            pad = 0.25 * (hi - lo) + 1.0
            if bool(ok) and s > 0 and np.all(xb >= lo - pad) and np.all(xb <= hi + pad):
                hits.append(s)
        return p, p + (min(hits) if hits else 300.0) * d

    n_el = len(rig.element_kinds) if rig.kinds else rig.lasers.n
    colors = plt.cm.tab10(np.arange(max(n_el, 1)) % 10)
    point_el = rig.point_elements if rig.kinds else np.arange(rig.lasers.n)
    for i in range(rig.lasers.n):
        if i in omit:
            continue
        e = int(point_el[i])  # its index in the file
        a, b = reach(rig.lasers, i)
        ax.plot(*np.stack([a, b]).T, color=colors[e], lw=1.2, label=f"laser {e}" if n_el <= 12 else None)
        ax.scatter(*a, s=10, color=colors[e])
        spans.append(np.stack([a, b]))
        if truth is not None:
            a, b = reach(truth.lasers, i)
            ax.plot(*np.stack([a, b]).T, color=colors[e], lw=0.8, ls="--")
    for j in range(rig.sheets.apex.shape[0] if rig.has_sheets else 0):
        e = int(rig.sheet_elements[j])
        kind = rig.sheets.kinds[j]
        lines = sheet_lines(rig.sheets, j, 150.0)
        for k, seg in enumerate(lines):
            label = f"laser {e} ({'line' if kind == 'plane' else 'ring'})" if k == 0 and n_el <= 12 else None
            ax.plot(*seg.T, color=colors[e], lw=0.6, alpha=0.8, label=label)
        spans.append(np.concatenate(lines))
    allp = np.concatenate(spans + [np.zeros((1, 3))])
    mid, half = (allp.max(0) + allp.min(0)) / 2, (allp.max(0) - allp.min(0)).max() / 2
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[1] - half, mid[1] + half)
    ax.set_zlim(mid[2] - half, mid[2] + half)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    if 0 < n_el <= 12:  # a camera without lasers has nothing to name
        ax.legend(fontsize=7, loc="upper left")
    extra = " (dashed: truth)" if truth is not None else ""
    ax.set_title(
        title
        or f"Camera, {'cone ' if isinstance(rig.mirror, ConeMirror) else ''}mirror and "
        f"{'lasers' if rig.has_sheets else 'laser lines'}{extra}"
    )
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def plot_detections(image, view, predicted: dict, path, gain: float | None = None) -> Path:
    """A catadioptric image with its detections and the calibrated model's reprojections.

    Args:
        image: the image (H, W, 3) BGR uint8 (as OpenCV reads it).
        view: the view's :class:`~slcvjax.observations.formats.ViewObs` (detected dots, spots and rim pixels).
        predicted: the reprojections, keyed ``"dots"`` -> ``{board: (M, 2)}`` (aligned
            with the view's board pixels), ``"spots"`` -> (S, 2) aligned with
            ``view.spots`` (NaN where none), ``"rim"`` -> (K, 2) points of the rim curve.
        path: the PNG file to write.
        gain: residual vectors are drawn this many times their length (by default a round
            factor that draws the median residual about 10 px long).
    """
    plt = pyplot()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    h, w = image.shape[:2]
    fig, ax = plt.subplots(figsize=(w / 80, h / 80))
    ax.imshow(image[..., ::-1], interpolation="nearest")
    res = []
    for b, (px, seen) in view.boards.items():
        q = predicted.get("dots", {}).get(b)
        obs = px[seen]
        ax.plot(*obs.T, "o", ms=4, mfc="none", mec="lime", mew=0.8)
        if q is not None:
            qq = q[seen]
            ok = np.all(np.isfinite(qq), axis=1)
            res.append((obs[ok], qq[ok]))
    if view.spots:
        sp = np.stack([s.pixel for s in view.spots])
        ax.plot(*sp.T, "+", ms=8, color="yellow", mew=1.0)
        q = predicted.get("spots")
        if q is not None:
            ok = np.all(np.isfinite(q), axis=1)
            res.append((sp[ok], q[ok]))
    if len(view.rim):
        ax.plot(*view.rim.T, ".", ms=1.5, color="cyan")
    rim = predicted.get("rim")
    if rim is not None and len(rim):
        ax.plot(*np.vstack([rim, rim[:1]]).T, "-", lw=0.6, color="magenta")
    if gain is None:  # the median residual drawn about 10 px long, at a round gain
        norms = np.concatenate([np.linalg.norm(q - o, axis=1) for o, q in res]) if res else np.zeros(0)
        med = float(np.median(norms)) if norms.size else 0.0
        gain = min((g for g in (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000) if g * med >= 10.0), default=1000.0)
    for obs, q in res:
        d = (q - obs) * gain
        ax.quiver(
            obs[:, 0], obs[:, 1], d[:, 0], d[:, 1], angles="xy", scale_units="xy", scale=1, color="red", width=0.002
        )
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_title(
        f"{view.name}: dots (o), spots (+), rim pixels (.), model rim (line); reprojection error x{gain:g} (arrows)",
        fontsize=8,
    )
    ax.axis("off")
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return path
