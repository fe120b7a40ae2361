"""Feeds an :class:`~harvest_qp.perception.obstacle_map.ObstacleMap` to the QP's collision limit every tick.

Beyond the paper (its collision constraints know only the robot): each occupied cell near an
arm capsule becomes an obstacle sphere of :class:`~harvest_qp.limits.CollisionAvoidance`,
hence a velocity-damper row with the limit's own d_s / d_i / gain. Typical use::

    obstacle_map = ObstacleMap()
    feed = MapCollisionFeed(collision_limit, obstacle_map, controller.configuration)
    # every tick, before controller.step(q):
    if new_cloud is not None:
        obstacle_map.update(new_cloud, exclude=[held_cluster_region])
    feed.update(q)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.perception import _feed_kernels as FK
from harvest_qp.perception.obstacle_map import DEFAULT_MIN_SEPARATION, ObstacleMap, _positive_int
from harvest_qp.validation import as_positive_scalar

__all__ = ["MapCapsule", "MapCollisionFeed"]


@dataclass(frozen=True)
class MapCapsule:
    """An arm capsule queried against the map: segment ``p0``-``p1`` [m] in frame ``frame``, ``radius`` [m]."""

    name: str
    frame: str
    p0: ArrayLike
    p1: ArrayLike
    radius: float


class MapCollisionFeed:
    """Feeds an :class:`ObstacleMap` to a :class:`~harvest_qp.limits.CollisionAvoidance` before each QP step.

    :meth:`update` finds, for each arm capsule, its ``per_capsule`` closest occupied cells
    within the limit's influence distance plus ``margin`` (cells of one capsule at least
    ``min_separation`` apart), and makes their union the limit's obstacle spheres (each
    covering its cell), so the limit's own closest-pair selection turns them into damper
    rows with its d_s / d_i / gain. The obstacle names in ``limit.capsule_names`` (hence
    ``limit.pair_names()`` and the logged active pairs) are ``cell[kx,ky,kz]``, the cell's
    integer key ``floor(x / resolution)``; unused slots are ``free_slot``.

    The limit gets a fixed number of obstacle slots (``max_cells``), given again through
    ``CollisionAvoidance.set_obstacle_spheres`` only when the fed cells change (22 times in the
    25,000 ticks of the paper episode, measured); unused slots are parked far below the world
    with radius 0, so the limit's broadphase drops them.

    Args:
        limit: the collision limit to feed (its obstacle spheres are replaced).
        obstacle_map: the map.
        configuration: the robot (its model gives the kinematic chain of the capsules).
        per_capsule: cells kept per capsule.
        min_separation: a capsule's cells at least this far apart [m] (see
            :data:`DEFAULT_MIN_SEPARATION`).
        margin: extra query distance [m] beyond the limit's influence distance.
        max_cells: obstacle slots given to the limit; when the capsules' cells are more, the
            closest ones are kept. Every slot is paired with all 15 moving capsules by the
            limit, and it keeps at most ``max_pairs`` (24) rows anyway.
        capsules: the robot capsules to query (``CapsuleGeometry`` attached to frames);
            default: the 15 moving capsules of :func:`harvest_qp.robot.description.collision_bodies`.
    """

    _PARK = np.array([0.0, 0.0, -1.0e3])  # where unused slots wait [m]
    #: How far [m] a capsule end point may move before its candidate cells are gathered again
    #: (they are, anyway, when the map's occupancy changes near them). Only a cost trade-off:
    #: the cells fed are those of a full query whatever it is.
    slack = 0.02

    def __init__(
        self,
        limit,
        obstacle_map: ObstacleMap,
        configuration,
        *,
        per_capsule: int = 4,
        min_separation: float = DEFAULT_MIN_SEPARATION,
        margin: float = 0.01,
        max_cells: int = 24,
        capsules: Sequence | None = None,
    ) -> None:
        from harvest_qp.collision import kernels as collision_kernels
        from harvest_qp.limits.collision_avoidance import KinematicTree
        from harvest_qp.robot import description as desc

        if not isinstance(obstacle_map, ObstacleMap):
            raise InvalidInputError(f"obstacle_map must be an ObstacleMap, got {type(obstacle_map).__name__}")
        if not hasattr(limit, "set_obstacle_spheres") or not hasattr(limit, "influence_distance"):
            raise InvalidInputError(f"limit must be a CollisionAvoidance, got {type(limit).__name__}")
        per_capsule = _positive_int(per_capsule, "per_capsule")
        self.limit = limit
        self._map = obstacle_map
        self.configuration = configuration
        self.per_capsule = int(per_capsule)
        self.margin = as_positive_scalar(margin, "margin", allow_zero=True)
        self.min_separation = as_positive_scalar(min_separation, "min_separation", allow_zero=True)
        if capsules is None:
            bodies = [b for b in desc.collision_bodies() if b.arm]
            items = [(b.name, b.link, b.capsule.p0, b.capsule.p1, b.capsule.radius) for b in bodies]
        else:
            items = [(c.name, c.frame, c.p0, c.p1, c.radius) for c in capsules]
        if not items or any(frame is None for _, frame, *_ in items):
            raise InvalidInputError("capsules must be non-empty and each attached to a frame")
        self.capsule_names = [name for name, *_ in items]
        # Capsule end points in the joint frame that carries them; the world end points come
        # from the collision package's compiled forward kinematics (2 us for both arms,
        # against ~35 us reading pinocchio's placements from Python).
        model = configuration.model
        joints, a_local, b_local = [], [], []
        for _, frame_name, p0, p1, _ in items:
            frame = model.frames[configuration.frame_id(frame_name)]
            joints.append(frame.parentJoint)
            a_local.append(frame.placement.act(np.asarray(p0, dtype=float)))
            b_local.append(frame.placement.act(np.asarray(p1, dtype=float)))
        self._tree = KinematicTree(configuration)
        self._capsule_world = collision_kernels.capsule_world
        self._joints = np.array(joints, dtype=np.int64)
        self._a_local = np.array(a_local)
        self._b_local = np.array(b_local)
        self._radii = np.array([r for *_, r in items], dtype=float)
        self._radii.flags.writeable = False
        n = len(items)
        self._w0 = np.zeros((n, 3))
        self._w1 = np.zeros((n, 3))
        self._index = np.full((n, self.per_capsule), -1, dtype=np.int64)
        self._dist = np.full((n, self.per_capsule), np.inf)
        self._count = np.zeros(n, dtype=np.int64)
        m = 8 * self.per_capsule if self.min_separation > 0 else self.per_capsule
        self._scratch_i = np.zeros(m, dtype=np.int64)
        self._scratch_d = np.zeros(m)
        # Candidate cells kept between map changes (see _feed_kernels); grown on demand.
        self._state = np.zeros(FK.FEED_STATE, dtype=np.int64)
        self._cache_w0 = np.zeros((n, 3))
        self._cache_w1 = np.zeros((n, 3))
        self._cache_distance = np.full(1, np.nan)
        self._cand_start = np.zeros(n + 1, dtype=np.int64)
        self._cand_bound = np.full(n, np.inf)  # see _feed_kernels.feed_update
        self._displacement = np.zeros(n)
        self._cand_index = np.zeros(4096, dtype=np.int64)
        self._cand_xyz = np.zeros((4096, 4))  # x, y, z [m], distance when kept [m]
        self._rel_blocks = np.zeros(4096, dtype=np.int64)
        self._kept_cells = np.zeros((self.per_capsule, 3), dtype=np.int64)
        self._cell_radius = float(obstacle_map.cell_radius)  # the value the kept candidates were built with
        self._q_shape = (configuration.nv,)
        self._names: dict[int, str] = {}
        self.slots = min(n * self.per_capsule, _positive_int(max_cells, "max_cells"))
        self._centres = np.tile(self._PARK, (self.slots, 1))
        self._cells = np.zeros(self.slots, dtype=np.int64)
        self._park = self._PARK.copy()
        limit.set_obstacle_spheres(self._centres, 0.0)
        self._first = len(limit.capsule_names) - self.slots
        self._slot_names = ["free_slot"] * self.slots
        self._last = np.zeros(0, dtype=np.int64)
        #: Linear indices of the cells fed at the last update.
        self.cells = self._last
        #: ``(n_capsules,)`` which capsules are queried (a capsule switched off gets no cells,
        #: e.g. an arm that holds still and must not be pushed by its rows).
        self.active = np.ones(n, dtype=bool)

    @property
    def rebuilds(self) -> int:
        """How many times the candidate cells were gathered again (diagnostics: map changes near a
        capsule, a capsule moved farther than :attr:`slack`, new radii or a new map)."""
        return int(self._state[FK.FEED_REBUILDS])

    @property
    def limit_slots(self) -> slice:
        """Where the fed cells lie in the limit's capsule arrays (``limit.cap_p0[feed.limit_slots]``)."""
        return slice(self._first, self._first + self.slots)

    def capsule_cells(self) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
        """Each capsule's cells at the last :meth:`update`: ``(counts (n,), indices (n, k), distances (n, k) [m])``,
        as :meth:`ObstacleMap.closest_cells` gives them (copies)."""
        return self._count.copy(), self._index.copy(), self._dist.copy()

    def _checked_q(self, q: ArrayLike | None) -> NDArray[np.float64]:
        """``q`` [rad] as the compiled kinematics need it (default: the configuration's)."""
        if q is None:
            q = self.configuration.q
        elif type(q) is np.ndarray and q.dtype == np.float64 and q.shape == (self.configuration.nv,):
            pass  # already what np.asarray(q, dtype=float) gives (the loop's own q, every tick)
        else:
            # The compiled kinematics index q by joint: a short q would be read past its end.
            try:
                q = np.asarray(q, dtype=float)
            except (TypeError, ValueError) as err:
                raise InvalidInputError(f"q must be {self.configuration.nv} joint positions [rad], got {q!r}") from err
            if q.shape != (self.configuration.nv,):
                raise InvalidInputError(
                    f"q must have shape ({self.configuration.nv},) (the model's joints), got shape {q.shape}"
                )
        return q

    def capsule_world(self, q: ArrayLike | None = None) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """World end points ``(p0, p1)`` [m] of the queried capsules at ``q`` [rad] (default: the configuration's)."""
        q = self._checked_q(q)
        tree = self._tree
        tree.update(q)
        self._capsule_world(self._joints, self._a_local, self._b_local, tree.joint_R, tree.joint_p, self._w0, self._w1)
        return self._w0, self._w1

    # The compiled tick keeps candidate cells built from the map and the radii: replacing
    # either must drop them (an audit found a reassigned map or radii changed in place fed
    # stale cells), so both are properties and the radii array is read-only.
    @property
    def map(self) -> ObstacleMap:
        """The obstacle map queried; assigning another one drops the kept candidate cells."""
        return self._map

    @map.setter
    def map(self, obstacle_map: ObstacleMap) -> None:
        if not isinstance(obstacle_map, ObstacleMap):
            raise InvalidInputError(f"map must be an ObstacleMap, got {type(obstacle_map).__name__}")
        self._map = obstacle_map
        self._forget_candidates()

    @property
    def radii(self) -> np.ndarray:
        """``(n_capsules,)`` capsule radii [m] (read-only; assign a new array to change them)."""
        return self._radii

    @radii.setter
    def radii(self, value: ArrayLike) -> None:
        radii = np.array(value, dtype=float)
        if radii.shape != self._radii.shape or not np.all(np.isfinite(radii)) or np.any(radii < 0):
            raise InvalidInputError(
                f"radii must be {self._radii.shape[0]} finite values >= 0 [m] (one per capsule), got {value!r}"
            )
        radii.flags.writeable = False
        self._radii = radii
        self._forget_candidates()

    def _forget_candidates(self) -> None:
        self._state[FK.FEED_VALID] = 0

    def update(self, q: ArrayLike | None = None) -> int:
        """Refresh the limit's obstacle spheres from the map for joint positions ``q`` [rad]
        (default: the configuration's current ones); returns how many cells were fed."""
        if not (type(q) is np.ndarray and q.dtype == np.float64 and q.shape == self._q_shape):
            q = self._checked_q(q)  # the loop's own q skips the call (same test as its fast path)
        active = self.active
        if not (type(active) is np.ndarray and active.dtype == np.bool_ and active.shape == self._radii.shape):
            active = np.asarray(active, dtype=bool)
            if active.shape != self.radii.shape:
                raise InvalidInputError(
                    f"active must be {self.radii.shape[0]} booleans (one per capsule), got shape {active.shape}"
                )
        m = self.map
        # One compiled call: the capsules at q (capsule_world's kernels), finiteness,
        # switched-off capsules parked far below the world, the closest cells (over the
        # candidate cells kept since the last map change: the same result as
        # ObstacleMap.closest_cells, see _feed_kernels), their union.
        if m.cell_radius != self._cell_radius:
            # ObstacleMap.cell_radius (a plain attribute) was edited: the distances must use the
            # new value, as closest_cells does, and the limit must get the new radii even if the
            # cells stay the same (FEED_N_LAST = -1 makes the kernel report them as changed).
            self._forget_candidates()
            self._state[FK.FEED_N_LAST] = -1
            self._cell_radius = float(m.cell_radius)
        tree = self._tree
        while True:
            n = FK.feed_tick(
                q, tree.parent, tree.idx_v, tree.joint_type, tree.axis, tree.place_R, tree.place_p, tree.joint_R,
                tree.joint_p, self._joints, self._a_local, self._b_local, self._w0, self._w1, active, self._park,
                self._radii, self.limit.influence_distance + self.margin, m.cell_radius, self.min_separation,
                self.slack, m.resolution, m.lo_key, m.dims, m._nby, m._nbz, m._block_cells, m._block_count,
                m._block_stamp, m._version, self._state, self._cache_w0, self._cache_w1, self._cache_distance,
                self._cand_start, self._cand_index, self._cand_xyz, self._rel_blocks, self._scratch_i,
                self._scratch_d, self._index, self._dist, self._count, self._cells, self._centres, self._cand_bound,
                self._displacement, self._kept_cells,
            )  # fmt: skip
            if n != -2:
                break
            self._cand_index = np.zeros(2 * self._cand_index.shape[0], dtype=np.int64)
            self._cand_xyz = np.zeros((self._cand_index.shape[0], 4))
            self._rel_blocks = np.zeros(2 * self._rel_blocks.shape[0], dtype=np.int64)
        if n < 0:
            return int(self.cells.shape[0])  # a non-finite q: keep the last cells; the QP step will fall back
        if not self._state[FK.FEED_CHANGED]:
            return int(n)  # same cells: the limit already has them
        cells = self._cells[:n]
        cells = cells.copy()
        radii = np.zeros(self.slots)
        radii[:n] = m.cell_radius
        for j, idx in enumerate(cells):
            name = self._names.get(int(idx))
            if name is None:
                if len(self._names) > 100_000:  # a long episode: keep the cache bounded
                    self._names.clear()
                kx, ky, kz = m.keys(self._centres[j])
                name = self._names[int(idx)] = f"cell[{kx},{ky},{kz}]"
            self._slot_names[j] = name
        for j in range(n, min(self._last.shape[0], self.slots)):
            self._slot_names[j] = "free_slot"
        lim, first = self.limit, self._first
        lim.set_obstacle_spheres(self._centres, radii)
        lim.capsule_names[first:] = self._slot_names
        self._last = cells
        self.cells = cells
        return int(n)
