"""A persistent obstacle map built from the camera's labelled clouds, fed to the QP's collision rows.

:class:`ObstacleMap` is an occupancy grid in the world frame updated from every camera frame
(:class:`~harvest_qp.runtime.interface.PointCloud`) with OctoMap's probabilistic rules (Hornung et
al. 2013): each obstacle point is a *hit* on its cell, each cell a ray crosses from the
camera to a measured point is a *miss*, log-odds are summed and clamped, and a cell is
occupied while its log-odds is above 0. So a leaf that moved away, or a noise point, is
cleared after a few frames by the rays that now pass through it, while what has left the
field of view is remembered. Unknown space counts as free, as in the paper (its collision
constraints only know the robot and what is seen).

What is inserted (the rules of the harvester, not of OctoMap):

* only points labelled :data:`~harvest_qp.runtime.interface.OBSTACLE`; the robot's own points
  (:data:`~harvest_qp.runtime.interface.ROBOT`) never, the stem (:data:`~harvest_qp.runtime.interface.STEM`)
  never: an occupied cell a stem point falls in is forgotten unless an obstacle point hit
  it in the same frame, so a stem seen as an obstacle beyond the camera's stem range leaves the map
  once it is recognised as the stem;
* never points inside the caller's exclusion regions (capsules, e.g. the cluster held by
  the gripper, which moves with it, or the stem model); the occupied cells inside them
  are forgotten at each update (``erase_excluded``), so one hit brings an obstacle back
  once the region has moved on;
* non-finite points and points farther than ``max_range`` from the camera are ignored
  (neither inserted nor used for clearing; OctoMap would clear up to ``max_range`` along
  them, but a return far beyond the camera's range is a faulty one).

The grid is dense and bounded (``bounds``, the space the arms can reach) and the
work is done by numba kernels (:mod:`._map_kernels`); clearing rays are traced for the
pixels of a ``clear_stride`` grid whose phase turns every frame, so every pixel clears
once every ``clear_stride**2`` frames, and near the camera, where rays crowd, only those
of the twice coarser grid (see :class:`ObstacleMap`). Measured speeds and the choice of the defaults:
``benchmarks/bench_map.py`` and the module constants below.

:class:`~harvest_qp.perception.map_feed.MapCollisionFeed` (its own module) turns the map into
:class:`~harvest_qp.limits.CollisionAvoidance` obstacle spheres before each QP step: for each
arm capsule, its closest occupied cells within the influence distance, each a sphere covering
its cell (radius sqrt(3)/2 times the resolution), so each becomes a velocity-damper row with
the limit's own d_s / d_i / gain, and its pair name tells the cell (``cell[kx,ky,kz]``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.perception import _map_kernels as K
from harvest_qp.perception._validation import as_grid_points, as_point
from harvest_qp.runtime.interface import PointCloud
from harvest_qp.validation import as_matrix, as_positive_scalar, as_scalar

__all__ = [
    "DEFAULT_BOUNDS",
    "DEFAULT_CLEAR_RAYS",
    "DEFAULT_MIN_SEPARATION",
    "DEFAULT_RESOLUTION",
    "CellQuery",
    "ExclusionRegion",
    "held_crop_exclusions",
    "MapUpdateStats",
    "ObstacleMap",
]

#: Cell edge [m]. 1 cm: the arms' capsules are 2-6.5 cm in radius, d_s is 1 cm; the
#: map's capsule distance is within sqrt(3) cells of the truth (see ObstacleMap), 1.7 cm
#: here; 2 cm cells would make it 3.5 cm, a third of the 10 cm influence distance.
DEFAULT_RESOLUTION = 0.01
#: Grid bounds [m] (lower corner, upper corner): where the arms work (bases at (0, +-0.36, 0.8),
#: the vine at x ~0.4-0.9 m), from just behind the stand to 1.2 m in front of it, +-1.2 m
#: sideways, 0.2-2.0 m high; obstacle points outside are not mapped. 7.1 M cells at 1 cm,
#: 57 MB (log-odds, frame stamps, per-block lists of occupied cells).
DEFAULT_BOUNDS = ((-0.4, -1.2, 0.2), (1.2, 1.2, 2.0))
#: Cells of one capsule's rows at least this far apart [m] (MapCollisionFeed): the 4 closest
#: cells of a wall are neighbours whose damper rows are nearly parallel, and daqp then
#: returned solutions 1e-6 outside the constraints (rejected by the solver's 1e-7 check,
#: so the controller fell back to a stop) in a gripper-to-wall approach; 3 cm apart, the
#: rows of one capsule differ by ~30 deg and the same approach ran without a fallback.
DEFAULT_MIN_SEPARATION = 0.03
#: Clearing rays traced per frame (about; the pixel stride is the nearest integer to
#: sqrt(pixels / DEFAULT_CLEAR_RAYS)): stride 3 at 283x160 and 8 at 848x480, rays 12-14 mm
#: apart at 1 m, so at 1 cm every cell in front of the surfaces within ~0.7 m is crossed
#: every frame and farther ones within a few frames (the grid's phase turns every frame).
#: Was 12000 (stride 2 / 6, 9 mm): measured on the paper episode's own frames (seeds 0 and
#: 3, 283x160 and 848x480) 6000 saves ~0.5 ms per 283x160 frame (1.95 -> 1.45 ms; 3.98 ->
#: 3.67 at 848x480), the map is as good against the lab's geometry (0 false obstacles with
#: either, 1-2 % more true surface cells kept) and the paper episodes' joint trajectories
#: are the same bit for bit; the cost: a moved leaf 0.5 m from the camera leaves the map
#: in ~39 frames instead of ~18 (at 0.28 m in 9 frames with either, the clamp's minimum).
DEFAULT_CLEAR_RAYS = 6000


def _logodds(probability: float) -> np.float32:
    # As OctoMap (log in double, stored as float), so both maps hold the same values.
    return np.float32(math.log(probability / (1.0 - probability)))


@dataclass(frozen=True)
class ExclusionRegion:
    """A capsule [m] whose points are never obstacles: segment ``p0``-``p1``, ``radius``.

    A sphere is a capsule with ``p0 == p1`` (:meth:`sphere`).
    """

    p0: tuple[float, float, float]
    p1: tuple[float, float, float]
    radius: float

    def __post_init__(self) -> None:
        for name in ("p0", "p1"):
            value = getattr(self, name)
            try:
                point = np.asarray(value, dtype=float)
            except (TypeError, ValueError):
                point = np.full(1, np.nan)
            if isinstance(value, (str, bytes)) or point.shape != (3,) or not np.all(np.isfinite(point)):
                raise InvalidInputError(f"ExclusionRegion.{name} must be 3 finite coordinates [m], got {value!r}")
        r = self.radius
        if isinstance(r, (bool, np.bool_)) or not isinstance(r, (int, float, np.integer, np.floating)) or not (
            np.isfinite(r) and r >= 0
        ):
            raise InvalidInputError(f"ExclusionRegion.radius must be a finite number >= 0 [m], got {r!r}")

    @classmethod
    def sphere(cls, center: ArrayLike, radius: float) -> ExclusionRegion:
        """A sphere of ``radius`` [m] around ``center`` [m]."""
        try:
            c = tuple(float(x) for x in np.asarray(center, dtype=float).ravel())
        except (TypeError, ValueError):
            raise InvalidInputError(f"center must be 3 finite coordinates [m], got {center!r}") from None
        return cls(c, c, radius)  # type: ignore[arg-type]


def held_crop_exclusions(
    gripper_pose: NDArray[np.float64],
    stem_base: NDArray[np.float64] | None,
    *,
    grasp_offset: float,
    cluster_start: float,
    cluster_length: float,
    cluster_radius: float,
    stem_length: float,
    stem_radius: float,
) -> list[ExclusionRegion]:
    """Regions never mapped at gripper pose ``gripper_pose`` (4x4): the held cluster and the stem.

    The cluster hangs along y_g from the gripper point and moves with it: a capsule of radius
    ``cluster_radius`` whose axis runs from ``cluster_start`` to ``cluster_length`` [m] below the
    gripper point (its rounded top reaches ``cluster_radius - cluster_start`` above it, so the
    branch at the stem base stays in the map). The stem runs from the top of the crop
    (``grasp_offset`` [m] above the gripper point) to p_sb ``stem_base`` (before a fit,
    ``stem_length`` along -y_g), radius ``stem_radius``: beyond the camera's stem range it is
    labelled an obstacle, and it must never constrain the camera's approach to it nor the
    gripper that holds it.
    """
    gripper_pose = as_matrix(gripper_pose, (4, 4), "gripper_pose")
    if stem_base is not None:
        stem_base = as_point("stem_base", stem_base)
    grasp_offset = as_scalar(grasp_offset, "grasp_offset")
    cluster_start = as_scalar(cluster_start, "cluster_start")
    cluster_length = as_scalar(cluster_length, "cluster_length")
    stem_length = as_positive_scalar(stem_length, "stem_length", allow_zero=True)
    # the radii are checked by ExclusionRegion itself
    p_g, y_g = gripper_pose[:3, 3], gripper_pose[:3, 1]
    cluster = ExclusionRegion(tuple(p_g + cluster_start * y_g), tuple(p_g + cluster_length * y_g), cluster_radius)
    top_of_crop = p_g - grasp_offset * y_g
    stem_end = stem_base if stem_base is not None else top_of_crop - stem_length * y_g
    return [cluster, ExclusionRegion(tuple(top_of_crop), tuple(stem_end), stem_radius)]


@dataclass(frozen=True)
class MapUpdateStats:
    """What one :meth:`ObstacleMap.update` did with a frame (point counts unless said)."""

    frame_rejected: str
    """Why the whole frame was ignored ("" when it was used)."""
    invalid: int
    """Non-finite points or unknown labels (ignored)."""
    out_of_range: int
    """Points farther than ``max_range`` from the camera (ignored)."""
    inserted: int
    """Obstacle points that updated a cell as a hit (one per cell per frame)."""
    excluded: int
    """Obstacle points inside an exclusion region (not inserted)."""
    outside_grid: int
    """Obstacle points outside the grid bounds (not inserted)."""
    stem_erased: int
    """Occupied cells forgotten because a stem point fell in them."""
    rays: int
    """Clearing rays traced to measured points."""
    no_return_rays: int
    """Clearing rays traced for pixels without a return (``no_return_range``)."""
    cells_cleared: int
    """Cells that got a miss."""
    region_erased: int
    """Occupied cells forgotten because they lie in an exclusion region."""


@dataclass(frozen=True)
class CellQuery:
    """The closest occupied cells to each capsule, closest first.

    Attributes:
        counts: ``(n,)`` number of cells found for each capsule.
        distances: ``(n, k)`` surface distance [m] from each capsule to the sphere
            covering each cell (``inf`` past ``counts``).
        centres: ``(n, k, 3)`` cell centres [m] (NaN past ``counts``).
        keys: ``(n, k, 3)`` integer cell keys ``floor(x / resolution)`` (0 past ``counts``).
        indices: ``(n, k)`` the map's linear cell indices (-1 past ``counts``).
    """

    counts: NDArray[np.int64]
    distances: NDArray[np.float64]
    centres: NDArray[np.float64]
    keys: NDArray[np.int64]
    indices: NDArray[np.int64]

    def min_distances(self) -> NDArray[np.float64]:
        """``(n,)`` distance [m] to each capsule's closest cell (``inf`` when none in range)."""
        return self.distances[:, 0].copy()


def _fit_pinhole(points, pixels, pose) -> tuple[float, float, float] | None:
    """Focal length and principal point [pixels] of the camera that took the cloud, or None.

    ``col + 0.5 = f x / z + cx`` and ``row + 0.5 = f y / z + cy`` in the camera frame, fitted
    by least squares on up to 2,000 points; None when fewer than 20 finite points or an
    RMS residual above 0.5 pixel (not a pinhole image).
    """
    n = points.shape[0]
    if n < 20:
        return None
    take = np.linspace(0, n - 1, min(n, 2000)).astype(np.int64)
    pc = (points[take] - pose[:3, 3]) @ pose[:3, :3]
    ok = np.all(np.isfinite(pc), axis=1) & (pc[:, 2] > 1e-6)
    if ok.sum() < 20:
        return None
    x, y = pc[ok, 0] / pc[ok, 2], pc[ok, 1] / pc[ok, 2]
    u, v = pixels[take][ok, 1] + 0.5, pixels[take][ok, 0] + 0.5
    m = ok.sum()
    A = np.zeros((2 * m, 3))
    A[:m, 0], A[:m, 1] = x, 1.0
    A[m:, 0], A[m:, 2] = y, 1.0
    sol, *_ = np.linalg.lstsq(A, np.concatenate([u, v]), rcond=None)
    rms = float(np.sqrt(np.mean((A @ sol - np.concatenate([u, v])) ** 2)))
    if not np.all(np.isfinite(sol)) or sol[0] <= 0 or rms > 0.5:
        return None
    return float(sol[0]), float(sol[1]), float(sol[2])


def _positive_int(value, name: str) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < 1:
        raise InvalidInputError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def _as_regions(exclude) -> NDArray[np.float64]:
    """Exclusion regions as an ``(n, 7)`` array ``(x0, y0, z0, x1, y1, z1, radius)``."""
    if exclude is None:
        return np.zeros((0, 7))
    if isinstance(exclude, ExclusionRegion):
        exclude = [exclude]
    expected = "ExclusionRegion objects or an (n, 7) array of (x0, y0, z0, x1, y1, z1, radius) [m]"
    if isinstance(exclude, (str, bytes, dict)) or not hasattr(exclude, "__iter__"):
        raise InvalidInputError(f"exclude must be {expected}, got {exclude!r}")
    try:
        if isinstance(exclude, np.ndarray):
            arr = np.asarray(exclude, dtype=float)
        else:
            rows = []
            for region in exclude:
                if isinstance(region, ExclusionRegion):
                    rows.append([*region.p0, *region.p1, region.radius])
                else:
                    rows.append(np.asarray(region, dtype=float).ravel())
            arr = np.array(rows, dtype=float) if rows else np.zeros((0, 7))
    except (TypeError, ValueError):
        raise InvalidInputError(f"exclude must be {expected}, got {exclude!r}") from None
    if arr.ndim == 1 and arr.size == 7:
        arr = arr.reshape(1, 7)
    if arr.ndim != 2 or arr.shape[1] != 7:
        raise InvalidInputError(
            f"exclude must be ExclusionRegion objects or an (n, 7) array of (x0, y0, z0, x1, y1, z1, radius), "
            f"got shape {arr.shape}"
        )
    if not np.all(np.isfinite(arr)) or np.any(arr[:, 6] < 0):
        raise InvalidInputError(f"exclude regions must be finite with radius >= 0 [m], got {arr.tolist()}")
    return np.ascontiguousarray(arr)



def _as_int8_labels(labels: NDArray) -> NDArray[np.int8]:
    """The cloud's labels as int8 for the kernel; integer labels outside int8 become -1 (an
    unknown label, ignored like the others) instead of wrapping round to a valid one."""
    labels = np.asarray(labels)
    if labels.dtype.kind not in "iub":
        raise InvalidInputError(
            f"cloud.labels must be integers (STEM, OBSTACLE, ROBOT), got dtype {labels.dtype}"
        )
    if labels.dtype == np.int8:
        return np.ascontiguousarray(labels)
    wide = labels.astype(np.int64)
    return np.where((wide < -128) | (wide > 127), -1, wide).astype(np.int8)


class ObstacleMap:
    """Occupancy grid of what the camera has seen, in the world frame.

    Args:
        resolution: cell edge [m].
        bounds: ``((x_min, y_min, z_min), (x_max, y_max, z_max))`` [m], the mapped box;
            it is grown to whole 8-cell blocks aligned on multiples of ``resolution``.
        max_range: points farther than this from the camera are ignored [m].
        min_range: points closer than this to the camera are ignored [m].
        prob_hit, prob_miss: occupancy probability of a hit / a miss (OctoMap's defaults).
        clamp_min, clamp_max: probability clamps (OctoMap's defaults): a cell at
            ``clamp_max`` (log-odds 3.51) is free after 9 frames of misses (-0.405 each);
            an unknown cell is occupied after 1 hit (+0.847), a cell cleared down to
            ``clamp_min`` (-2.0) after 3.
        clear_stride: pixel stride of the clearing rays (their phase turns every frame);
            None: the nearest integer to ``sqrt(pixels / clear_rays)``.
        clear_rays: target number of clearing rays per frame when ``clear_stride`` is None.
            With a stride > 1, within ``0.6 * resolution * f / (2 * stride)`` of the camera
            (f: focal length [pixels] fitted once to the cloud; 0.33 m for the D415 at
            283x160 and 848x480), where the rays of the twice coarser grid are 0.6 cell
            apart, only those clear; the others start there (-25 % CPU, measured).
        no_return_range: ``(start, end)`` [m]: pixels of the clearing grid with no point in
            the cloud (nothing within the camera's depth range) clear their ray from
            ``start`` to ``end`` (on a pixel grid twice as coarse as ``clear_stride``), so
            a leaf that moved away from an empty background disappears too. Off (None)
            by default, as in OctoMap: a missing return also comes from dropout, dark or
            specular surfaces and objects nearer than the camera's minimum depth. The
            rays follow a pinhole fitted to the cloud's pixels and points (kept per image
            size for frames that cannot be fitted: too few points or worse than 0.5 pixel
            RMS).
        erase_excluded: at each update, erase the cells inside the exclusion regions.

    Distances: a cell counts as the sphere of radius ``sqrt(3)/2 * resolution`` around its
    centre (it covers the cell), so the distance from a capsule to the map is never more
    than to the seen surface and at most ``sqrt(3) * resolution`` less.
    """

    def __init__(
        self,
        *,
        resolution: float = DEFAULT_RESOLUTION,
        bounds: tuple[ArrayLike, ArrayLike] = DEFAULT_BOUNDS,
        max_range: float = 2.5,
        min_range: float = 0.0,
        prob_hit: float = 0.7,
        prob_miss: float = 0.4,
        clamp_min: float = 0.1192,
        clamp_max: float = 0.971,
        clear_stride: int | None = None,
        clear_rays: int = DEFAULT_CLEAR_RAYS,
        no_return_range: tuple[float, float] | None = None,
        erase_excluded: bool = True,
    ) -> None:
        self.resolution = as_positive_scalar(resolution, "resolution")
        self.max_range = as_positive_scalar(max_range, "max_range")
        self.min_range = as_positive_scalar(min_range, "min_range", allow_zero=True)
        if self.min_range >= self.max_range:
            raise InvalidInputError(f"min_range ({min_range} m) must be below max_range ({max_range} m)")
        for name, p in (("prob_hit", prob_hit), ("prob_miss", prob_miss), ("clamp_min", clamp_min),
                        ("clamp_max", clamp_max)):  # fmt: skip
            if not (isinstance(p, (int, float, np.floating)) and 0.0 < p < 1.0):
                raise InvalidInputError(f"{name} must be a probability in (0, 1), got {p!r}")
        if not (prob_hit > 0.5 > prob_miss and clamp_min < 0.5 < clamp_max):
            raise InvalidInputError(
                f"need prob_hit > 0.5 > prob_miss and clamp_min < 0.5 < clamp_max, got prob_hit={prob_hit}, "
                f"prob_miss={prob_miss}, clamp_min={clamp_min}, clamp_max={clamp_max}"
            )
        self.hit = _logodds(prob_hit)
        self.miss = _logodds(prob_miss)
        self.clamp_min = _logodds(clamp_min)
        self.clamp_max = _logodds(clamp_max)
        self.clear_stride = None if clear_stride is None else _positive_int(clear_stride, "clear_stride")
        self.clear_rays = _positive_int(clear_rays, "clear_rays")
        if not isinstance(erase_excluded, (bool, np.bool_)):
            raise InvalidInputError(f"erase_excluded must be True or False, got {erase_excluded!r}")
        self.erase_excluded = bool(erase_excluded)
        if no_return_range is not None:
            try:
                start, end = (float(x) for x in no_return_range)
            except (TypeError, ValueError):
                raise InvalidInputError(
                    f"no_return_range must be (start, end) [m] or None, got {no_return_range!r}"
                ) from None
            if not (np.isfinite(start) and np.isfinite(end) and 0.0 <= start < end):
                raise InvalidInputError(f"no_return_range must satisfy 0 <= start < end [m], got {no_return_range!r}")
            no_return_range = (start, end)
        self.no_return_range = no_return_range
        self._returned = np.zeros((1, 1), dtype=np.bool_)
        self._pinhole: dict[tuple[int, int], tuple[float, float, float]] = {}
        try:
            lo = np.asarray(bounds[0], dtype=float).reshape(3)
            hi = np.asarray(bounds[1], dtype=float).reshape(3)
        except (TypeError, ValueError, IndexError, KeyError):
            raise InvalidInputError(f"bounds must be ((x, y, z) lower, (x, y, z) upper) [m], got {bounds!r}") from None
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(hi > lo)):
            raise InvalidInputError(f"bounds must be finite with upper > lower [m], got {bounds!r}")
        res = self.resolution
        self.lo_key = np.floor(lo / res).astype(np.int64)
        n_cells = np.ceil(hi / res).astype(np.int64) - self.lo_key
        n_blocks = (n_cells + K.BLOCK - 1) // K.BLOCK
        if int(np.prod(n_blocks)) * K.BLOCK_CELLS > 200_000_000:
            raise InvalidInputError(
                f"bounds {bounds!r} at resolution {resolution} m need {int(np.prod(n_blocks)) * K.BLOCK_CELLS} "
                "cells; at most 200 M are allowed"
            )
        self.dims = (n_blocks * K.BLOCK).astype(np.int64)
        self.n_blocks = n_blocks
        self._nby, self._nbz = int(n_blocks[1]), int(n_blocks[2])
        n_total = int(np.prod(self.dims))
        self.log_odds = np.zeros(n_total, dtype=np.float32)
        self._stamp = np.zeros(n_total, dtype=np.uint16)
        nb = int(np.prod(n_blocks))
        self._dirty = np.zeros(nb, dtype=np.bool_)
        self._dirty_list = np.zeros(nb, dtype=np.int64)
        self._n_dirty = np.zeros(1, dtype=np.int64)
        self._block_cells = np.zeros((nb, K.BLOCK_CELLS), dtype=np.int16)
        self._block_count = np.zeros(nb, dtype=np.int64)
        # Occupancy version: +1 at every change of the occupied cells; each block is stamped with
        # the version of its last change (MapCollisionFeed keeps its candidate cells until a block
        # it depends on changes).
        self._version = 0
        self._block_stamp = np.zeros(nb, dtype=np.int64)
        self._frame = 0
        self.frames = 0
        # Linear indices of the cells the last prior marked occupied (set_prior): one hit's
        # log-odds each, plus what frames added since.
        self._prior = np.zeros(0, dtype=np.int64)
        #: Radius [m] of the sphere that covers a cell.
        self.cell_radius = 0.5 * math.sqrt(3.0) * res

    # ------------------------------------------------------------------ geometry
    @property
    def lower_corner(self) -> NDArray[np.float64]:
        """World position [m] of the grid's lower corner."""
        return self.lo_key * self.resolution

    @property
    def upper_corner(self) -> NDArray[np.float64]:
        """World position [m] of the grid's upper corner."""
        return (self.lo_key + self.dims) * self.resolution

    @property
    def num_occupied(self) -> int:
        """Number of occupied cells."""
        return int(self._block_count.sum())

    def clear(self) -> None:
        """Forget everything (all cells unknown, i.e. free)."""
        self.log_odds[:] = 0.0
        self._stamp[:] = 0
        self._block_count[:] = 0
        self._version += 1
        self._block_stamp[:] = self._version
        self._dirty[:] = False
        self._n_dirty[0] = 0
        self._frame = 0
        self.frames = 0
        self._prior = np.zeros(0, dtype=np.int64)

    def keys(self, points: ArrayLike) -> NDArray[np.int64]:
        """Integer cell keys ``floor(p / resolution)`` of ``(n, 3)`` points [m]."""
        return np.floor(np.asarray(points, dtype=float) * (1.0 / self.resolution)).astype(np.int64)

    def occupied_centres(self, *, observed_only: bool = False) -> NDArray[np.float64]:
        """``(n, 3)`` centres [m] of all occupied cells; with ``observed_only``, without the
        cells that only a prior (:meth:`set_prior`) marks."""
        idx = self._occupied_indices()
        if observed_only and self._prior.shape[0]:
            idx = idx[~np.isin(idx, self._live_prior())]
        return self._centres(idx)

    def occupied_keys(self) -> NDArray[np.int64]:
        """``(n, 3)`` integer keys of all occupied cells."""
        return self.keys(self.occupied_centres())

    def prior_centres(self) -> NDArray[np.float64]:
        """``(n, 3)`` centres [m] of the cells occupied by the prior alone (no hit since it was set)."""
        return self._centres(self._live_prior())

    def _centres(self, idx: NDArray[np.int64]) -> NDArray[np.float64]:
        out = np.empty((idx.shape[0], 3))
        K.cell_centres(idx, self.resolution, self.lo_key, self._nby, self._nbz, out)
        return out

    def _live_prior(self) -> NDArray[np.int64]:
        # Occupied only because of the prior: no hit since it was set (a miss lowers it).
        lo = self.log_odds[self._prior]
        return self._prior[(lo > 0.0) & (lo <= self.hit)]

    def set_prior(self, points: ArrayLike) -> int:
        """Believe the never-seen cells holding ``(n, 3)`` points [m] occupied, replacing the last prior.

        Each such cell gets one hit's log-odds, as if a frame had seen a point there once: it
        becomes a collision row like any seen cell, and the frames that later see the space
        free clear it (three misses) as they clear a seen one. Cells a frame has updated (seen
        free or occupied) get no prior. The previous prior's belief is taken out of its cells
        first: what frames added since stays (a cell never updated becomes unknown again).
        Returns the number of cells marked.

        Raises:
            InvalidInputError: ``points`` is not ``(n, 3)`` finite [m].
        """
        pts = np.ascontiguousarray(as_grid_points("points", points))
        out = np.empty(pts.shape[0], dtype=np.int64)
        n = K.replace_prior(
            pts, self.hit, self.clamp_min, self._prior, self.resolution, self.lo_key, self.dims, self._nby,
            self._nbz, self.log_odds, self._dirty, self._dirty_list, self._n_dirty, out,
        )  # fmt: skip
        self._prior = out[:n].copy()
        self._finish_update()
        return int(n)

    def _occupied_indices(self) -> NDArray[np.int64]:
        out = np.empty(self.num_occupied, dtype=np.int64)
        K.occupied_indices(self._block_cells, self._block_count, out)
        return out

    def log_odds_at(self, points: ArrayLike) -> NDArray[np.float32]:
        """Log-odds of the cells holding ``(n, 3)`` points [m] (0: unknown or outside the grid)."""
        pts = np.ascontiguousarray(np.asarray(points, dtype=float).reshape(-1, 3))
        out = np.zeros(pts.shape[0], dtype=np.float32)
        K.log_odds_at(pts, self.resolution, self.lo_key, self.dims, self._nby, self._nbz, self.log_odds, out)
        return out

    def is_occupied(self, points: ArrayLike) -> NDArray[np.bool_]:
        """Whether the cells holding ``(n, 3)`` points [m] are occupied."""
        return self.log_odds_at(points) > 0.0

    # ------------------------------------------------------------------ update
    def update(
        self, cloud: PointCloud, *, exclude: Sequence[ExclusionRegion] | ArrayLike | None = None
    ) -> MapUpdateStats:
        """Integrate one camera frame.

        Args:
            cloud: the frame (world-frame points, labels, camera pose, pixels).
            exclude: regions whose points are never inserted (and whose cells are
                erased when ``erase_excluded``): the cluster held by the gripper at its
                current pose, the stem model, ...: :class:`ExclusionRegion` objects or an
                ``(n, 7)`` array of ``(x0, y0, z0, x1, y1, z1, radius)`` [m].

        A frame whose camera pose is not finite is ignored whole; invalid points are
        skipped one by one (see :class:`MapUpdateStats`). Never raises on the cloud's
        content; raises :class:`~harvest_qp.exceptions.InvalidInputError` when ``cloud``
        is not a :class:`PointCloud` or ``exclude`` is malformed.
        """
        if not isinstance(cloud, PointCloud):
            raise InvalidInputError(f"cloud must be a PointCloud, got {type(cloud).__name__}")
        labels = _as_int8_labels(cloud.labels)
        regions = _as_regions(exclude)
        counters = np.zeros(K.N_COUNTERS, dtype=np.int64)
        origin = np.ascontiguousarray(cloud.camera_pose[:3, 3], dtype=float)
        if not np.all(np.isfinite(cloud.camera_pose)):
            return self._stats("camera_pose is not finite", counters, 0)
        if np.abs(origin).max() > 1e6:  # keeps every key computation far from integer overflow
            return self._stats(f"camera position {origin.tolist()} is more than 1000 km away", counters, 0)
        region_erased = 0
        if self.erase_excluded and regions.shape[0]:
            region_erased = K.erase_regions(
                regions, self.resolution, self.lo_key, self.dims, self._nby, self._nbz, self.log_odds,
                self._dirty, self._dirty_list, self._n_dirty, self._block_cells, self._block_count,
            )  # fmt: skip
        if len(cloud) == 0 and (self.no_return_range is None or tuple(cloud.image_size) not in self._pinhole):
            self._finish_update()
            return self._stats("", counters, region_erased)
        self._next_frame()
        h, w = cloud.image_size
        stride = self.clear_stride
        if stride is None:
            stride = max(1, int(round(math.sqrt(max(h * w, 1) / self.clear_rays))))
        phase = self.frames % (stride * stride)
        # Rays without a return cross empty space all the way: half as dense is enough
        # (7 mm apart at 0.4 m at 283x160) and halves their cost.
        nr_stride = 2 * stride
        nr_phase = self.frames % (nr_stride * nr_stride)
        points = np.ascontiguousarray(cloud.points, dtype=np.float64)
        pixels = np.ascontiguousarray(cloud.pixels, dtype=np.int32)
        rotation = np.ascontiguousarray(cloud.camera_pose[:3, :3], dtype=float)
        no_return = np.zeros(2)
        intrinsics = np.zeros(3)
        # The camera's pinhole, fitted once per image size (the first frame that allows it).
        fit = self._pinhole.get((h, w))
        if fit is None and (stride > 1 or self.no_return_range is not None):
            fit = _fit_pinhole(points, pixels, cloud.camera_pose)
            if fit is not None:
                self._pinhole[(h, w)] = fit
        near_skip = 0.0
        if fit is not None and stride > 1:
            # Rays of the 2 * stride grid are 2 * stride / f rad apart: up to this range they
            # are at most 0.6 cell apart, so they alone cross every cell there.
            near_skip = 0.6 * self.resolution * fit[0] / (2 * stride)
        if self.no_return_range is not None:
            if fit is not None:
                no_return[:] = self.no_return_range
                intrinsics[:] = fit
                if self._returned.shape != (h, w):
                    self._returned = np.zeros((h, w), dtype=np.bool_)
        K.integrate_frame(
            points, labels, pixels, np.array((max(int(h), 0), max(int(w), 0)), dtype=np.int64), origin, rotation,
            regions,
            stride, phase // stride, phase % stride, near_skip, self.min_range, self.max_range, no_return,
            nr_stride, nr_phase // nr_stride, nr_phase % nr_stride, intrinsics,
            self._returned, self.resolution, self.lo_key, self.dims, self._nby, self._nbz, self.log_odds,
            self._stamp, self._frame, self.hit, self.miss, self.clamp_min, self.clamp_max,
            self._dirty, self._dirty_list, self._n_dirty, counters,
        )  # fmt: skip
        self.frames += 1
        self._finish_update()
        return self._stats("", counters, region_erased)

    def erase(self, regions: Sequence[ExclusionRegion] | ArrayLike) -> int:
        """Forget (make unknown, i.e. free) the occupied cells whose centres lie in ``regions``; returns how many."""
        arr = _as_regions(regions)
        n = K.erase_regions(
            arr, self.resolution, self.lo_key, self.dims, self._nby, self._nbz, self.log_odds,
            self._dirty, self._dirty_list, self._n_dirty, self._block_cells, self._block_count,
        )  # fmt: skip
        self._finish_update()
        return int(n)

    def _next_frame(self) -> None:
        self._frame += 1
        if self._frame > np.iinfo(np.uint16).max:  # stamps wrap: forget them (one memset per ~36 min at 30 Hz)
            self._stamp[:] = 0
            self._frame = 1

    def _finish_update(self) -> None:
        n = int(self._n_dirty[0])
        if n:
            self._version += 1
            K.rebuild_blocks(
                self._dirty_list, n, self._dirty, self.log_odds, self._block_cells, self._block_count,
                self._block_stamp, self._version,
            )  # fmt: skip
            self._n_dirty[0] = 0

    @staticmethod
    def _stats(rejected: str, c: NDArray[np.int64], region_erased: int) -> MapUpdateStats:
        return MapUpdateStats(
            frame_rejected=rejected, invalid=int(c[K.N_INVALID]), out_of_range=int(c[K.N_OUT_OF_RANGE]),
            inserted=int(c[K.N_INSERTED]), excluded=int(c[K.N_EXCLUDED]), outside_grid=int(c[K.N_OUTSIDE]),
            stem_erased=int(c[K.N_STEM_ERASED]), rays=int(c[K.N_RAYS]), no_return_rays=int(c[K.N_NO_RETURN_RAYS]),
            cells_cleared=int(c[K.N_CELLS_CLEARED]), region_erased=int(region_erased),
        )  # fmt: skip

    # ------------------------------------------------------------------ queries
    def closest_cells(
        self,
        p0: ArrayLike,
        p1: ArrayLike,
        radii: ArrayLike,
        *,
        max_distance: float,
        per_capsule: int = 4,
        min_separation: float = 0.0,
        candidates: int | None = None,
    ) -> CellQuery:
        """The ``per_capsule`` closest occupied cells within ``max_distance`` [m] of each capsule.

        Args:
            p0, p1: ``(n, 3)`` capsule end points [m] (world frame).
            radii: ``(n,)`` capsule radii [m] (or one for all).
            max_distance: largest surface distance [m] reported.
            per_capsule: cells kept per capsule, closest first.
            min_separation: a cell closer than this [m] to a closer kept cell of the same
                capsule is skipped (0: the plain k closest).
            candidates: how many closest cells the separation rule picks from (default
                ``8 * per_capsule`` with a separation, else ``per_capsule``).
        """
        a = np.ascontiguousarray(np.asarray(p0, dtype=float).reshape(-1, 3))
        b = np.ascontiguousarray(np.asarray(p1, dtype=float).reshape(-1, 3))
        if a.shape != b.shape:
            raise InvalidInputError(f"p0 and p1 must have the same shape (n, 3), got {a.shape} and {b.shape}")
        r = np.ascontiguousarray(np.broadcast_to(np.asarray(radii, dtype=float), (a.shape[0],)))
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b)) and np.all(np.isfinite(r)) and np.all(r >= 0)):
            raise InvalidInputError("capsule end points must be finite and radii finite and >= 0 [m]")
        max_distance = as_positive_scalar(max_distance, "max_distance", allow_zero=True)
        per_capsule = _positive_int(per_capsule, "per_capsule")
        min_separation = as_positive_scalar(min_separation, "min_separation", allow_zero=True)
        n, k = a.shape[0], int(per_capsule)
        if candidates is None:
            candidates = 8 * k if min_separation > 0 else k
        if _positive_int(candidates, "candidates") < k:
            raise InvalidInputError(f"candidates must be an integer >= per_capsule ({k}), got {candidates!r}")
        index = np.full((n, k), -1, dtype=np.int64)
        dist = np.full((n, k), np.inf)
        count = np.zeros(n, dtype=np.int64)
        scratch_i = np.zeros(int(candidates), dtype=np.int64)
        scratch_d = np.zeros(int(candidates))
        K.closest_cells(
            a, b, r, max_distance, self.cell_radius, min_separation, self.resolution, self.lo_key, self.dims,
            self._nby, self._nbz, self._block_cells, self._block_count, scratch_i, scratch_d, index, dist, count,
        )  # fmt: skip
        centres = np.full((n, k, 3), np.nan)
        valid = index >= 0
        flat = np.empty((int(valid.sum()), 3))
        K.cell_centres(index[valid], self.resolution, self.lo_key, self._nby, self._nbz, flat)
        centres[valid] = flat
        keys = np.zeros((n, k, 3), dtype=np.int64)
        keys[valid] = self.keys(flat)
        return CellQuery(counts=count, distances=dist, centres=centres, keys=keys, indices=index)
