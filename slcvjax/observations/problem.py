"""Observations packed into flat arrays, padded to shape buckets, and the vectorised residuals.

A :class:`Packed` problem lists every observation once with the index of the pose it
depends on, so the residuals of any number of views, boards and lasers are one
``vmap`` (no Python loop in the traced graph).

**Shape buckets.**  A compiled function is compiled once per shape of its arguments, so
every array that enters one is padded to a bucket size (:func:`bucket`: a coarse ladder
for the joint problem and the staged stages' maps, which visit only the real rows, see
:meth:`Layout.of` and :func:`map_rows`; powers of two where every row is visited), and
the padding is masked out exactly: ``Packed.counts`` holds the real number of dots,
spots, rim pixels and chessboard corners, the padded rows come after the real ones and
are never counted (no cost, no weight, no Jacobian, no degree of freedom), and padded
pose blocks have no observation and a zero freeze mask.  Datasets whose sizes fall in the
same buckets share every compilation.  :class:`Layout` records the real and padded sizes
of a problem and maps results back (:meth:`Layout.unpad_params`, ...).
"""

import dataclasses
import enum
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ..geometry.lasers import Lasers, line_plane_intersection
from ..geometry.mirror import project_through_mirror
from ..geometry.pose import Pose
from ..geometry.rig import Rig, tangent_layout
from ..support.persist import committed
from ..support.recent import Recent
from .formats import Observations


class Kind(enum.IntEnum):
    """The observation kinds, in the order of every per-kind array: :class:`Packed`'s counts,
    the LM's rows and kind weights, the covariance's kind sigmas and the report's tables."""

    DOT = 0  # a board dot seen through the mirror
    SPOT = 1  # a laser spot seen through the mirror
    RIM = 2  # a pixel of the mirror's rim
    CHESS = 3  # a chessboard corner seen directly (or through the mirror, with no lasers)
    STRIPE = 4  # a sample of a line or ring laser's stripe seen through the mirror

    @property
    def label(self) -> str:
        """The kind's name in files and reports (``dot``, ``spot``, ``rim``, ``chess``, ``stripe``)."""
        return self.name.lower()

    @property
    def robust(self) -> bool:
        """Whether the robust loss applies: dots, spots and stripe samples (outliers are
        labelled points); the rim and the corners stay plain least squares (a robust rim made
        the lasers from rendered images worse in ``benchmarks/images_vs_file.py``)."""
        return self in (Kind.DOT, Kind.SPOT, Kind.STRIPE)

    @property
    def rows(self) -> int:
        """Scalar residual rows per observation: 2 for a pixel, 1 for a distance from a curve
        (a rim pixel, a stripe sample)."""
        return 1 if self in (Kind.RIM, Kind.STRIPE) else 2


KIND_NAMES = tuple(k.label for k in Kind)


def kinds_of(pk: "Packed") -> tuple[Kind, ...]:
    """The kinds a problem has rows for: dots, spots, rim, corners, and stripe samples where it
    has stripes (its per-kind arrays, such as its noise sigmas, run over these)."""
    return tuple(Kind)[: np.shape(pk.counts)[0]]


ROBUST_KINDS = tuple(k.robust for k in Kind)


def kind_weights(weight=None) -> Float[Array, "5"]:
    """Each :class:`Kind`'s weight in a solve, as an array (``None``: every kind 1; 0 drops a
    kind).  Four weights (dots, spots, rim, corners) give the stripe samples the spots' weight:
    both are the structured light."""
    if weight is None:
        return jnp.ones(len(Kind))
    w = jnp.asarray(weight, dtype=float)
    return jnp.concatenate([w, w[1:2]]) if w.shape == (4,) else w


class Packed(eqx.Module):
    """Flat observation arrays of a calibration.

    Attributes:
        dot_pose: (D,) index into the board poses of each dot seen through the mirror.
        dot_points: (D, 3) the dot in its board's frame.
        dot_pixels: (D, 2) its observed pixel.
        spot_pose: (S,) board pose index of each spot's plane.
        spot_laser: (S,) laser index of each spot.
        spot_pixels: (S, 2) observed pixels.
        rim_pixels: (R, 2) rim edge pixels of all views (the mirror is fixed to the camera).
        chess_pose: (C,) index into the direct-view poses of each chessboard corner.
        chess_points: (C, 3) the corner in its board's frame.
        chess_pixels: (C, 2) its observed pixel.
        counts: (4,) how many dots, spots, rim pixels and corners are real, and (5,) the
            stripe samples where the problem has stripes; the rows after them are padding (see
            the module docstring).
        pose_keys: ``(view index, board name)`` of each board pose (static).
        chess_keys: index of the calibration view of each direct-view pose (static).
        dot_src: ``(view index, board name, dot index)`` of each dot row (static; empty
            where the rows come from elsewhere than :func:`pack`).
        spot_src: ``(view index, spot index in the view)`` of each spot row (static, likewise).
        pair_block: None, or for the rigid box model (:mod:`slcvjax.calibration.rigid`) the pose block of each
            board pose of ``pose_keys`` (its view's sensor pose, or its own for a board outside
            the box); the rows' ``dot_pose`` / ``spot_pose`` still index the board poses.
        pair_box: with ``pair_block``, each board pose's board in the box (an index into
            ``Params.box``; the length of ``Params.box`` for the gauge board and the boards outside
            the box: no box pose, the identity).
        stripe_pose: None (no stripes), or (T,) the board pose of each stripe sample's plane.
        stripe_sheet: (T,) the sample's line or ring laser, its index among the rig's sheets
            (:attr:`slcvjax.geometry.rig.Rig.sheets`).
        stripe_pixels: (T, 2) the sample's pixel on the stripe's centre line.
        stripe_src: ``(view index, stripe index in the view, sample index)`` of each stripe row
            (static; empty where the rows come from elsewhere than :func:`pack`).

    ``spot_laser`` is a spot's laser among the rig's point lasers (``Rig.lasers``), which in a
    rig of point lasers alone is its index in the file.
    """

    dot_pose: Int[Array, " D"]
    dot_points: Float[Array, "D 3"]
    dot_pixels: Float[Array, "D 2"]
    spot_pose: Int[Array, " S"]
    spot_laser: Int[Array, " S"]
    spot_pixels: Float[Array, "S 2"]
    rim_pixels: Float[Array, "R 2"]
    chess_pose: Int[Array, " C"]
    chess_points: Float[Array, "C 3"]
    chess_pixels: Float[Array, "C 2"]
    counts: Int[Array, "4"]
    pose_keys: tuple = eqx.field(static=True)
    chess_keys: tuple = eqx.field(static=True)
    dot_src: tuple = eqx.field(static=True, default=())
    spot_src: tuple = eqx.field(static=True, default=())
    pair_block: Int[Array, " P"] | None = None
    pair_box: Int[Array, " P"] | None = None
    stripe_pose: Int[Array, " T"] | None = None
    stripe_sheet: Int[Array, " T"] | None = None
    stripe_pixels: Float[Array, "T 2"] | None = None
    stripe_src: tuple = eqx.field(static=True, default=())

    @property
    def has_stripes(self) -> bool:
        """Whether the problem has stripe rows (its ``counts`` then has 5 entries)."""
        return self.stripe_pose is not None

    @property
    def n_poses(self) -> int:
        """The number of board poses (``pose_keys``)."""
        return len(self.pose_keys)

    @property
    def n_pose_blocks(self) -> int:
        """The number of the joint problem's board pose blocks: one per board pose, or with the
        rigid box model one per view and one per board pose outside the box."""
        if self.pair_block is None:
            return self.n_poses
        return int(np.max(np.asarray(self.pair_block), initial=-1)) + 1

    @property
    def n_chess(self) -> int:
        return len(self.chess_keys)

    def arrays(self) -> "Packed":
        """The arrays alone, unpadded (no static keys): for a compiled function of this problem's own sizes."""
        return dataclasses.replace(self, pose_keys=(), chess_keys=(), dot_src=(), spot_src=(), stripe_src=())

    def kinds_only(self, keep) -> "Packed":
        """The problem with the rows of each kind where ``keep`` (per kind: dot, spot, rim,
        corner) is 0 counted as padding, which the sums skip (the same arrays)."""
        keep = np.asarray(keep, dtype=np.asarray(self.counts).dtype)
        if keep.shape[0] == 4 and np.shape(self.counts)[0] == 5:  # the stripes as the spots
            keep = np.append(keep, keep[1])
        keep = keep[: np.shape(self.counts)[0]]
        return eqx.tree_at(lambda a: a.counts, self, self.counts * keep)

    def select(self, keep_dots, keep_spots, spot_laser=None) -> "Packed":
        """The problem with only the dots and spots where ``keep_dots`` / ``keep_spots`` (bool,
        over the real rows) hold, and the spots' laser labels replaced by ``spot_laser`` (over
        the real rows, before the selection) where given.  Host arrays, keys kept."""
        n_d, n_s = int(self.counts[Kind.DOT]), int(self.counts[Kind.SPOT])
        kd, ks = np.asarray(keep_dots, bool), np.asarray(keep_spots, bool)
        if kd.shape != (n_d,) or ks.shape != (n_s,):
            raise ValueError(f"select: masks of {n_d} dots and {n_s} spots expected, got {kd.shape} and {ks.shape}")
        labels = np.asarray(self.spot_laser)[:n_s] if spot_laser is None else np.asarray(spot_laser, np.int64)
        c = np.asarray(self.counts).copy()
        c[:2] = kd.sum(), ks.sum()
        return dataclasses.replace(
            self,
            dot_pose=np.asarray(self.dot_pose)[:n_d][kd],
            dot_points=np.asarray(self.dot_points)[:n_d][kd],
            dot_pixels=np.asarray(self.dot_pixels)[:n_d][kd],
            spot_pose=np.asarray(self.spot_pose)[:n_s][ks],
            spot_laser=labels[ks],
            spot_pixels=np.asarray(self.spot_pixels)[:n_s][ks],
            counts=c,
            dot_src=tuple(x for x, k in zip(self.dot_src, kd, strict=True) if k) if self.dot_src else (),
            spot_src=tuple(x for x, k in zip(self.spot_src, ks, strict=True) if k) if self.spot_src else (),
        )

    def select_stripes(self, keep) -> "Packed":
        """The problem with only the stripe samples where ``keep`` (bool, over the real rows)
        holds.  Host arrays, keys kept."""
        if not self.has_stripes:
            return self
        n_t = int(self.counts[Kind.STRIPE])
        k = np.asarray(keep, bool)
        if k.shape != (n_t,):
            raise ValueError(f"select_stripes: a mask of {n_t} stripe samples expected, got {k.shape}")
        c = np.asarray(self.counts).copy()
        c[Kind.STRIPE] = k.sum()
        return dataclasses.replace(
            self,
            stripe_pose=np.asarray(self.stripe_pose)[:n_t][k],
            stripe_sheet=np.asarray(self.stripe_sheet)[:n_t][k],
            stripe_pixels=np.asarray(self.stripe_pixels)[:n_t][k],
            counts=c,
            stripe_src=tuple(x for x, kk in zip(self.stripe_src, k, strict=True) if kk) if self.stripe_src else (),
        )

    def present(self) -> tuple[Bool[Array, " D"], ...]:
        """Per kind (dots, spots, rim pixels, corners, and stripe samples where there are
        stripes): which rows are real, not padding."""
        sizes = (self.dot_pose, self.spot_pose, self.rim_pixels, self.chess_pose)
        if self.has_stripes:
            sizes += (self.stripe_pose,)
        return tuple(jnp.arange(a.shape[0]) < self.counts[k] for k, a in enumerate(sizes))  # type: ignore[return-value]


def pack(obs: Observations, use_views: bool = True, use_direct: bool = True) -> Packed:
    """Pack ``obs``: a board pose per (view, board) seen, a pose per direct view with corners.
    Stripes (line and ring lasers) give one row per sample, on a board with a pose in its view."""
    keys: list[tuple[int, str]] = []
    local = obs.local_index()

    def cat(parts, width):
        return np.concatenate(parts).astype(float) if parts else np.zeros((0, width))

    index: dict[tuple[int, str], int] = {}

    def key(vi, b):
        if (vi, b) not in index:
            index[(vi, b)] = len(keys)
            keys.append((vi, b))
        return index[(vi, b)]

    dp, dpts, dpx, sp, sl, spx, rim, dsrc, ssrc = [], [], [], [], [], [], [], [], []
    for vi, v in enumerate(obs.views if use_views else []):
        for b, (px, seen) in v.boards.items():
            if not seen.any():
                continue
            k = key(vi, b)
            dp.extend([k] * int(seen.sum()))
            dpts.append(obs.boards[b][seen])
            dpx.append(px[seen])
            dsrc.extend((vi, b, int(j)) for j in np.flatnonzero(seen))
        for j, s in enumerate(v.spots):
            if s.board is None or (vi, s.board) not in index:
                continue  # no plane for it: no board, or a board with no dots (so no pose) in this view
            sp.append(key(vi, s.board))
            sl.append(int(local[s.laser]))
            spx.append(s.pixel)
            ssrc.append((vi, j))
        rim.append(np.asarray(v.rim, float).reshape(-1, 2))
    tp, tl, tpx, tsrc = [], [], [], []
    for vi, v in enumerate(obs.views if use_views else []):
        for j, s in enumerate(v.stripes):
            if s.board is None or (vi, s.board) not in index or not len(s.pixels):
                continue
            m = len(s.pixels)
            tp.extend([index[(vi, s.board)]] * m)
            tl.extend([int(local[s.laser])] * m)
            tpx.append(np.asarray(s.pixels, float).reshape(-1, 2))
            tsrc.extend((vi, j, k) for k in range(m))
    stripes = {}
    if obs.n_sheets:
        stripes = {
            "stripe_pose": np.array(tp, dtype=np.int64),
            "stripe_sheet": np.array(tl, dtype=np.int64),
            "stripe_pixels": cat(tpx, 2),
            "stripe_src": tuple(tsrc),
        }
    cp, cpts, cpx, ckeys = [], [], [], []
    for ci, cv in enumerate(obs.calibration_views if use_direct else []):
        if not cv.seen.any():
            continue
        cp.extend([len(ckeys)] * int(cv.seen.sum()))
        ckeys.append(ci)
        cpts.append(obs.boards[cv.board][cv.seen])
        cpx.append(cv.pixels[cv.seen])

    # host (numpy) arrays: a device array of each dataset's own size would compile its own
    # small copies and slices; the compiled functions take them padded (Layout.pad_packed)
    return Packed(
        np.array(dp, dtype=np.int64),
        cat(dpts, 3),
        cat(dpx, 2),
        np.array(sp, dtype=np.int64),
        np.array(sl, dtype=np.int64),
        np.array(spx, dtype=float).reshape(-1, 2),
        cat(rim, 2),
        np.array(cp, dtype=np.int64),
        cat(cpts, 3),
        cat(cpx, 2),
        np.array(
            [len(dp), len(sp), sum(len(r) for r in rim), len(cp)] + ([len(tp)] if stripes else []), dtype=np.int64
        ),
        tuple(keys),
        tuple(ckeys),
        tuple(dsrc),
        tuple(ssrc),
        **stripes,
    )


# ----------------------------------------------------------------------------- shape buckets

MIN_BUCKET = 8
# the joint problem's ladders (see :meth:`Layout.of`): (floor, step) of observation rows and of pose blocks
OBSERVATION_LADDER = (4096, 4)
POSE_LADDER = (64, 4)
# the lasers' ladder: every rig of 1 to 8 lasers shares the joint problem's compilations (a
# padded laser has no spot and is held, and its 4 columns only widen the dense global block)
LASER_LADDER = (8, 2)


def bucket(n: int, floor: int = MIN_BUCKET, step: int = 2) -> int:
    """The padded size of an axis of ``n`` rows: the smallest ``floor * step**k`` that holds
    them (0 stays 0).

    The default (powers of two from 8) serves the functions that evaluate every row, padding
    included (trials in lockstep under ``vmap``): a dataset pays at most twice its rows and a
    size range of 2x shares one compilation.
    """
    if n < 0:
        raise ValueError(f"a size cannot be negative, got {n}")
    if n == 0:
        return 0
    size = floor
    while size < n:
        size *= step
    return size


def pad_rows(x, size: int, fill=None) -> np.ndarray:
    """``x`` (host or device array) padded along its first axis to ``size`` rows.

    The padding repeats ``fill`` (one row) or, by default, the first row of ``x`` (zeros
    if it has none), so that padded rows hold values the model evaluates without trouble.
    """
    x = np.asarray(x)
    n = x.shape[0]
    if size < n:
        raise ValueError(f"cannot pad {n} rows to {size}")
    if size == n:
        return x
    row = (x[0] if n else np.zeros(x.shape[1:], x.dtype)) if fill is None else np.asarray(fill, x.dtype)
    return np.concatenate([x, np.broadcast_to(row, (size - n,) + x.shape[1:])])


def padded_lasers(lasers: Lasers, cap: int | None = None) -> Lasers:
    """``lasers`` padded to ``cap`` lines (by default their :data:`LASER_LADDER` bucket) with
    copies of the first: a function of the rig compiled once serves every laser count of a
    bucket, and the padded lines' outputs are cut off by the caller."""
    cap = bucket(lasers.n, *LASER_LADDER) if cap is None else cap
    if cap == lasers.n:
        return lasers
    return Lasers(jax.device_put(pad_rows(lasers.points, cap)), jax.device_put(pad_rows(lasers.directions, cap)))


def map_rows(vfn, chunk: int = 256):
    """``vfn(*consts, rows)`` (a map over the rows' first axis; ``rows`` an array or a pytree of
    arrays with the same first axis) as ``f(*consts, rows, count)`` that evaluates only the first
    ``count`` rows, in a loop over chunks of ``chunk`` (the rest of the output is zeros): padded
    rows then cost nothing.  For :func:`map_padded`."""

    def run(*a):
        *consts, rows, count = a
        tree = jax.tree_util.tree_map
        n = jax.tree_util.tree_leaves(rows)[0].shape[0]
        k = min(chunk, n)
        if k == 0:
            return vfn(*consts, rows)
        shapes = jax.eval_shape(vfn, *consts, tree(lambda r: r[:k], rows))
        out = tree(lambda sd: jnp.zeros((n,) + sd.shape[1:], sd.dtype), shapes)

        def body(i, out):
            start = jnp.minimum(i * k, n - k)  # the last chunk moved back to fit: rows done twice, alike
            part = vfn(*consts, tree(lambda r: jax.lax.dynamic_slice_in_dim(r, start, k), rows))
            return tree(lambda o, p: jax.lax.dynamic_update_slice_in_dim(o, p, start, 0), out, part)

        return jax.lax.fori_loop(0, (count + k - 1) // k, body, out)

    return run


def map_padded(fn, *args, rows):
    """``fn(*args, rows, count)`` (see :func:`map_rows`) with ``rows`` padded to the joint
    problem's bucket (:data:`OBSERVATION_LADDER`) and every output cut back to the real rows:
    one compilation for every size of a bucket, and the padding costs nothing."""
    n = np.shape(rows)[0]
    out = fn(*args, jnp.asarray(pad_rows(rows, bucket(n, *OBSERVATION_LADDER))), jnp.asarray(n))
    return jax.tree_util.tree_map(lambda x: np.asarray(x)[:n], out)


_PADDED = Recent(8)  # the last calls of Layout.pad_packed


class Layout(NamedTuple):
    """The real and padded sizes of a problem: dots, spots, rim pixels, corners, board poses,
    direct-view poses, and (``lasers``: real, padded) the rig's lasers (None: not padded)."""

    n: tuple[int, int, int, int, int, int]
    cap: tuple[int, int, int, int, int, int]
    lasers: tuple[int, int] | None = None
    stripes: tuple[int, int] | None = None  # stripe samples (real, padded); None: no stripes
    sheet_dim: int = 0  # the tangent columns of the rig's sheets (its point lasers' padding goes after them)

    @staticmethod
    def of(
        pk: "Packed",
        n_poses: int | None = None,
        n_chess: int | None = None,
        fine: bool = False,
        n_lasers: int | None = None,
        sheet_dim: int = 0,
    ) -> "Layout":
        """The layout of ``pk`` (its real rows) with every size rounded up by :func:`bucket`.

        The joint problem's ladders are coarse (:data:`OBSERVATION_LADDER`: 4096 rows, then
        steps of 4x; :data:`POSE_LADDER`: 64 poses, then 4x): its loops visit only the real
        rows (``slcvjax.calibration.linearise.accumulate``), so the padding costs little (measured by
        ``benchmarks/bench_compile.py``'s padding part), and every dataset up to 4096
        observations of each kind and 64 poses of each kind shares one compilation.

        ``n_poses`` / ``n_chess``: the number of board / direct-view poses (by default
        those of ``pk``'s keys).  ``fine``: powers of two instead, for solves that visit
        every row, padding included (trials in lockstep under ``vmap``).  ``n_lasers``: the
        rig's point lasers, padded by :data:`LASER_LADDER` (None: the lasers as they are);
        ``sheet_dim``: the tangent columns of its sheets (the padded point lasers' columns
        follow every real element's).
        """
        c = np.asarray(pk.counts)
        n = (
            int(c[0]),
            int(c[1]),
            int(c[2]),
            int(c[3]),
            pk.n_pose_blocks if n_poses is None else n_poses,
            pk.n_chess if n_chess is None else n_chess,
        )
        obs, poses = ((MIN_BUCKET, 2),) * 2 if fine else (OBSERVATION_LADDER, POSE_LADDER)
        cap = tuple(bucket(k, *(obs if i < 4 else poses)) for i, k in enumerate(n))
        lasers = None if n_lasers is None else (n_lasers, bucket(n_lasers, *LASER_LADDER))
        stripes = None
        if pk.has_stripes:
            n_t = int(c[Kind.STRIPE])
            stripes = (n_t, bucket(n_t, *obs))
        return Layout(n, cap, lasers, stripes, int(sheet_dim))  # type: ignore[arg-type]

    def _laser_gap(self) -> tuple[int, int]:
        """Where the padded lasers' columns start in the padded global block, and how many there are."""
        if self.lasers is None:
            return 0, 0
        n, cap = self.lasers
        real = tangent_layout((Lasers.DOF,) * n).dim
        return real + self.sheet_dim, tangent_layout((Lasers.DOF,) * cap).dim - real

    def pad_lasers(self, lasers: Lasers) -> Lasers:
        """The rig's lasers padded with copies of the first (held, with no spot: see :func:`pad_glob`)."""
        return lasers if self.lasers is None else padded_lasers(lasers, self.lasers[1])

    def unpad_lasers(self, lasers: Lasers) -> Lasers:
        """The real lasers of padded ones (host arrays)."""
        if self.lasers is None:
            return lasers
        n = self.lasers[0]
        return Lasers(np.asarray(lasers.points)[:n], np.asarray(lasers.directions)[:n])

    def pad_glob(self, x) -> np.ndarray:
        """A global-block vector (camera, mirror, lasers, box poses) with zeros inserted for the
        padded lasers' columns (in a mask: held)."""
        x = np.asarray(x)
        at, k = self._laser_gap()
        return np.concatenate([x[:at], np.zeros(k, x.dtype), x[at:]]) if k else x

    def glob_index(self, size: int) -> np.ndarray:
        """The real entries of a padded global-block axis of ``size`` (the padded lasers' cut):
        an index that also selects them from a traced array."""
        at, k = self._laser_gap()
        return np.r_[:at, at + k : size]

    def unpad_glob(self, x, axes: tuple[int, ...] = (0,)) -> np.ndarray:
        """A padded global-block array with the padded lasers' rows cut from each of ``axes``."""
        x = np.asarray(x)
        if not self._laser_gap()[1]:
            return x
        for ax in axes:
            x = np.take(x, self.glob_index(x.shape[ax]), axis=ax)
        return x

    def pad_packed(self, pk: "Packed") -> "Packed":
        """``pk``'s arrays padded to the layout's sizes, without the static keys (which would
        make every dataset its own compilation), committed to the device.  The last few
        results are kept: a fit pads the same observations for each of its tables and passes,
        which then take them as they are."""
        return _PADDED.get((pk,), self, lambda: self._pad_packed(pk))

    def _pad_packed(self, pk: "Packed") -> "Packed":
        d, s, r, c = self.cap[:4]
        pairs = {}
        if pk.pair_block is not None:
            n_pairs = np.shape(pk.pair_block)[0]
            size = bucket(n_pairs, *POSE_LADDER)
            pairs = {
                "pair_block": jnp.asarray(pad_rows(pk.pair_block, size)),
                "pair_box": jnp.asarray(pad_rows(pk.pair_box, size)),
            }
        stripes = {}
        if self.stripes is not None:
            t = self.stripes[1]
            stripes = {
                "stripe_pose": jnp.asarray(pad_rows(pk.stripe_pose[: self.stripes[0]], t)),
                "stripe_sheet": jnp.asarray(pad_rows(pk.stripe_sheet[: self.stripes[0]], t)),
                "stripe_pixels": jnp.asarray(pad_rows(pk.stripe_pixels[: self.stripes[0]], t)),
            }
        padded = Packed(
            jnp.asarray(pad_rows(pk.dot_pose[: self.n[0]], d)),
            jnp.asarray(pad_rows(pk.dot_points[: self.n[0]], d)),
            jnp.asarray(pad_rows(pk.dot_pixels[: self.n[0]], d)),
            jnp.asarray(pad_rows(pk.spot_pose[: self.n[1]], s)),
            jnp.asarray(pad_rows(pk.spot_laser[: self.n[1]], s)),
            jnp.asarray(pad_rows(pk.spot_pixels[: self.n[1]], s)),
            jnp.asarray(pad_rows(pk.rim_pixels[: self.n[2]], r)),
            jnp.asarray(pad_rows(pk.chess_pose[: self.n[3]], c)),
            jnp.asarray(pad_rows(pk.chess_points[: self.n[3]], c)),
            jnp.asarray(pad_rows(pk.chess_pixels[: self.n[3]], c)),
            jnp.asarray(self.n[:4] + ((self.stripes[0],) if stripes else ()), dtype=jnp.int64),
            (),
            (),
            **pairs,
            **stripes,
        )
        return committed(padded)

    def pad_poses(self, poses: Pose, chess: bool = False) -> Pose:
        """Stacked board poses (or direct-view poses) padded with copies of the first (on the device)."""
        size = self.cap[5 if chess else 4]
        return committed(Pose(pad_rows(poses.R, size, np.eye(3)), pad_rows(poses.t, size)))

    def unpad_poses(self, poses: Pose, chess: bool = False) -> Pose:
        """The real poses of padded ones (host arrays)."""
        k = self.n[5 if chess else 4]
        return Pose(np.asarray(poses.R)[:k], np.asarray(poses.t)[:k])

    def pad_blocks(self, x, fill=0.0) -> np.ndarray:
        """A per-pose-block array (board poses, then direct-view poses) padded with ``fill``."""
        x = np.asarray(x)
        p, c = self.n[4], self.n[5]
        return np.concatenate(
            [
                pad_rows(x[:p], self.cap[4], np.full(x.shape[1:], fill)),
                pad_rows(x[p : p + c], self.cap[5], np.full(x.shape[1:], fill)),
            ]
        )

    def block_index(self) -> np.ndarray:
        """The real entries of a padded per-pose-block axis (board poses, then direct-view poses):
        an index that also selects them from a traced array."""
        return np.r_[: self.n[4], self.cap[4] : self.cap[4] + self.n[5]]

    def unpad_blocks(self, x) -> np.ndarray:
        """A per-pose-block array of the padded problem restricted to the real blocks."""
        return np.asarray(x)[self.block_index()]

    def unpad_observations(self, x) -> np.ndarray:
        """A per-observation array of the padded problem (dots, spots, rim, corners) restricted to the real ones."""
        x = np.asarray(x)
        parts, start = [], 0
        for k in range(4):
            parts.append(x[start : start + self.n[k]])
            start += self.cap[k]
        if self.stripes is not None:
            parts.append(x[start : start + self.stripes[0]])
        return np.concatenate(parts)


def stack_poses(poses: list[Pose]) -> Pose:
    """A list of poses as one :class:`Pose` with leading axis (P, ...), stacked on the host.

    Host code only (not under ``jit``): host arrays, copied to the device (padded) by the
    compiled functions that take them.
    """
    return Pose(np.stack([np.asarray(p.R) for p in poses]), np.stack([np.asarray(p.t) for p in poses]))


def unstack_poses(poses: Pose) -> list[Pose]:
    """Stacked poses (P, ...) as a list of P poses, copied to the host once (numpy fields).

    Indexing a device array pose by pose costs a dispatch each; host code that loops
    over the poses reads them from this list instead.
    """
    R, t = np.asarray(poses.R), np.asarray(poses.t)
    return [Pose(R[k], t[k]) for k in range(R.shape[0])]


def dot_residuals(
    rig: Rig, poses: Pose, packed: Packed, implicit: bool = True
) -> tuple[Float[Array, "D 2"], Bool[Array, " D"]]:
    """Predicted minus observed pixel of every dot, and whether the prediction is valid."""

    def one(k, x_board, px):
        pose = Pose(poses.R[k], poses.t[k])
        res = project_through_mirror(rig.camera, rig.mirror, pose.apply(x_board), implicit=implicit)
        return res.uv - px, res.valid

    return jax.vmap(one)(packed.dot_pose, packed.dot_points, packed.dot_pixels)


def spot_residuals(
    rig: Rig, poses: Pose, packed: Packed, implicit: bool = True
) -> tuple[Float[Array, "S 2"], Bool[Array, " S"]]:
    """Predicted minus observed pixel of every laser spot, and validity."""

    def one(k, laser, px):
        pose = Pose(poses.R[k], poses.t[k])
        x, ok = line_plane_intersection(
            rig.lasers.points[laser], rig.lasers.directions[laser], pose, forward_only=False
        )
        res = project_through_mirror(rig.camera, rig.mirror, x, implicit=implicit)
        return res.uv - px, ok & res.valid

    return jax.vmap(one)(packed.spot_pose, packed.spot_laser, packed.spot_pixels)
