"""A start for a catadioptric camera seen only through its mirror: no direct views, no rim.

A perspective camera at the far focus of a hyperboloid is a central camera: every reflected
ray passes through the mirror's inner focus.  The start searches such central rigs (camera
at the origin looking along +z, distortion-free, its principal point at the image centre,
the mirror's axis along +z) for the one under which the boards' dots fit best: for each
candidate the generalized planar PnP of :func:`slcvjax.calibration.staged.board_poses` poses every board and
reports the first-order pixel RMS.  The joint calibration then frees everything (the camera's
distortion and principal point, the mirror's pose: the camera need not sit at the focus).

Unknowns of the search: the eccentricity ``e = sqrt(-kappa)`` (where the conic constant is
not given) and the image scale ``g = f / D`` (pixels per mm of mirror at the vertex's
distance ``D``); for a hyperboloid the far focus fixes ``D = R / (e - 1)``.  Mirrors with no
such focus (sphere, paraboloid, ellipsoid) search the distance ``D`` instead.  The scale is
the vertex radius ``R``: a central camera's images do not change when mirror and distance
grow together, so ``R`` (the datasheet's, or :data:`GAUGE_VERTEX_RADIUS`) is held as the gauge
and the calibration keeps it.  A coarse grid over both gives the seeds (per value of the first
its best scale, no two seeds neighbours on the grid: one per valley of the fit), and a
Nelder-Mead simplex refines each within its seed's neighbours; the joint fit runs from each
(:func:`slcvjax.calibration.calibrate.calibrate`) and keeps the lowest cost.

A telecentric camera (parallel rays along +z, :class:`slcvjax.geometry.camera.Camera`) makes a paraboloid
central (every reflected ray through its focus); the search is then over the scale ``g``
alone (and a hyperboloid's eccentricity where not given): the camera's unit is the vertex
radius, its depth a gauge (the vertex :data:`TELECENTRIC_DEPTH` vertex radii ahead).
"""

import itertools

import numpy as np

from ..geometry.camera import Camera
from ..geometry.conic import ConicMirror
from ..observations.problem import Packed
from .base import CalibrationError, StageReport
from .staged import board_poses

GAUGE_VERTEX_RADIUS = 20.0  # mm: the scale where the shape's vertex radius is not given
ECCENTRICITIES = (1.005, 1.02, 1.06, 1.15, 1.3, 1.55, 2.0, 3.0)
DISTANCES = (1.5, 2.5, 4.0, 7.0, 12.0, 20.0, 35.0)  # in vertex radii, mirrors without a far focus
SCALES = tuple(np.geomspace(1.0, 200.0, 12))  # px per mm of mirror
MAX_EVALUATIONS = 60  # of each simplex search
N_STARTS = 3
TELECENTRIC_DEPTH = 10.0  # in vertex radii: the vertex's depth before a telecentric camera (a gauge)


def _rig(conic: float, d: float, g: float, R: float, size: tuple[int, int], radius: float | None):
    """The candidate camera and mirror: the vertex at distance ``d`` (mm) on the camera's axis."""
    w, h = size
    k1 = 1.0 + conic
    if radius is None:  # the rim: anywhere for an open conic, inside the widest circle of a closed one
        radius = 10.0 * R if k1 <= 0 else 0.99 * R / np.sqrt(k1)
    cam = Camera.create(g * d, g * d, (w - 1) / 2.0, (h - 1) / 2.0, np.zeros(5), w, h)
    return cam, ConicMirror.create([0.0, 0.0, d], [0.0, 0.0, 1.0], 1.0 / R, conic, radius)


def central_start(
    pk: Packed,
    image_size: tuple[int, int],
    kind: str = "hyperboloid",
    vertex_radius: float | None = None,
    conic: float | None = None,
    radius: float | None = None,
    n_starts: int = N_STARTS,
    telecentric: bool = False,
) -> list[tuple[Camera, ConicMirror, StageReport]]:
    """The best central (or, without a far focus, on-axis) rigs for the boards of ``pk``: one
    per valley of the fit, at most ``n_starts``, best first (the joint fit from each may end in
    a different minimum: the fits' errors are not those of the starts).

    Args:
        pk: the packed observations (the dots of every view's boards are used).
        image_size: (width, height) in pixels.
        kind: the mirror's kind: hyperboloid (the default: central with the camera at its far
            focus), paraboloid, sphere or ellipsoid.
        vertex_radius: the mirror's vertex radius (mm); the gauge of the scale
            (:data:`GAUGE_VERTEX_RADIUS` where not given).
        conic: the conic constant where known (a hyperboloid's: below -1; an ellipsoid's:
            above -1); searched where not.
        radius: the rim's radius (mm) where known; else the rim is put where it bounds nothing
            (ten vertex radii, or inside a closed conic's widest circle).
        telecentric: the camera is telecentric (see the module docstring).

    Returns per start the camera, the mirror and the stage's report (the first-order RMS of the
    boards' fit).  Raises :class:`slcvjax.calibration.base.CalibrationError` where no candidate poses every board.
    """
    if kind not in ("hyperboloid", "paraboloid", "sphere", "ellipsoid"):
        raise ValueError(f"central_start: no start for a {kind} mirror")
    if kind == "ellipsoid" and conic is None:
        raise CalibrationError(
            "mirror_shape.conic_constant: an ellipsoid's is needed (the start searches a hyperboloid's)"
        )
    R = float(vertex_radius or GAUGE_VERTEX_RADIUS)
    if kind == "hyperboloid":
        first = ECCENTRICITIES if conic is None else (float(np.sqrt(-conic)),)
        free_first = conic is None
    elif telecentric:  # the depth is a gauge: the scale alone
        first, free_first = (TELECENTRIC_DEPTH,), False
    else:
        first = DISTANCES
        free_first = True
    fixed_conic = {"sphere": 0.0, "paraboloid": -1.0}.get(kind, conic)

    def candidate(a: float, g: float) -> tuple[Camera, ConicMirror]:
        """``a``: the eccentricity of a hyperboloid (its far focus at the camera), else the
        vertex's distance in vertex radii."""
        if telecentric:
            k = (-a * a if conic is None else conic) if kind == "hyperboloid" else fixed_conic
            cam, mir = _rig(k, TELECENTRIC_DEPTH * R, g, R, image_size, radius)
            w, h = image_size
            return Camera.create(g * R, g * R, cam.cx, cam.cy, np.zeros(5), w, h, True, R), mir
        if kind == "hyperboloid":
            return _rig(-a * a if conic is None else conic, R / (a - 1.0), g, R, image_size, radius)
        return _rig(fixed_conic, a * R, g, R, image_size, radius)

    tried: dict[tuple[float, float], float] = {}

    def rms(a: float, g: float) -> float:
        key = (round(a, 12), round(g, 12))
        if key not in tried:
            try:
                err = board_poses(*candidate(a, g), pk, flips=False)[1].rms
            except CalibrationError:  # some board's dots miss this mirror
                err = np.inf
            tried[key] = err if np.isfinite(err) else np.inf
        return tried[key]

    grid = {ag: rms(*ag) for ag in itertools.product(first, SCALES)}
    # per value of the first unknown its best scale; the starts are the best of those, no two
    # neighbours on the grid (a valley of the fit is one start)
    profile = {a: min(SCALES, key=lambda g, a=a: grid[(a, g)]) for a in first}
    order = sorted(first, key=lambda a: grid[(a, profile[a])])
    seeds: list[float] = []
    for a in order:
        if np.isfinite(grid[(a, profile[a])]) and all(abs(first.index(a) - first.index(b)) > 1 for b in seeds):
            seeds.append(a)
    if not seeds:
        raise CalibrationError(f"views: no central {kind} rig poses every board (tried {len(tried)} candidates)")

    # Nelder-Mead in (log(e - 1) or log of the distance, log g) from each seed (only log g where
    # the first is given): the two trade off along a narrow curved valley, which a simplex
    # follows where steps along the axes stall
    def log_a(a: float) -> float:
        return float(np.log(a - 1.0) if kind == "hyperboloid" else np.log(a))

    def of_x(x: np.ndarray, a0: float) -> tuple[float, float]:
        if not free_first:
            return a0, float(np.exp(x[0]))
        # each start stays between its seed's neighbours on the grid: the starts stay apart
        k = first.index(a0)
        lo, hi = log_a(first[max(k - 1, 0)]), log_a(first[min(k + 1, len(first) - 1)])
        y = float(np.exp(np.clip(x[0], lo, hi)))
        return (1.0 + y if kind == "hyperboloid" else y), float(np.exp(x[1]))

    from scipy.optimize import minimize  # here: SciPy's import is 0.4 s of every process's start

    out = []
    for a0 in seeds[:n_starts]:
        g0 = profile[a0]
        x0 = np.array(([log_a(a0)] if free_first else []) + [np.log(g0)])
        simplex = np.vstack([x0, x0 + 0.3 * np.eye(len(x0))])
        opts = {"initial_simplex": simplex, "xatol": 1e-4, "fatol": 1e-6, "maxfev": MAX_EVALUATIONS}
        fit = minimize(lambda x, a0=a0: rms(*of_x(x, a0)), x0, method="Nelder-Mead", options=opts)
        a, g = of_x(fit.x, a0) if rms(*of_x(fit.x, a0)) < rms(a0, g0) else (a0, g0)
        cam, mir = candidate(a, g)
        if kind == "hyperboloid":
            what = f"eccentricity {a:.4g}"
        else:
            what = f"vertex at {a * R:.4g} mm" + (" (the depth's gauge)" if telecentric else "")
        lens = f"telecentric, {g:.5g} px per mm" if telecentric else f"focal length {float(cam.fx):.5g} px"
        notes = [f"central start: {kind}, vertex radius {R:g} mm (the gauge), {what}, {lens}"]
        out.append((cam, mir, StageReport("central_start", rms(a, g), "px (first order)", notes)))
    out.sort(key=lambda c: c[2].rms)
    for k, (_, _, rep) in enumerate(out):
        rep.notes.append(f"start {k + 1} of {len(out)}; {len(tried)} rigs tried")
    return out
