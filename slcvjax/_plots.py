"""Figures people would rather look at than read (matplotlib, written as PNG files)."""

from pathlib import Path

import numpy as np


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_pipe(result: dict, out_dir, axis=(0.0, 0.0, 1.0)) -> list[Path]:
    """The pipe experiment's figures: 3D points, cross-sections with the fitted circles, errors.

    ``result`` is what :func:`slcvjax._pipe.pipe_experiment` returns.  Writes
    ``pipe_points.png`` (every measured point in 3D beside the true pipe wall),
    ``pipe_circles.png`` (each pose's cross-section: points, fitted and true circles)
    and ``pipe_errors.png`` (each point's fit error per pose, and each pose's
    diameter with its standard deviation).  Returns the paths.
    """
    from ._measure import plane_basis

    plt = _plt()
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
