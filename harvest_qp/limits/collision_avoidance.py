"""Collision avoidance between capsules, environment primitives and obstacle spheres.

Each close pair (a, b) gives one velocity-damper row (Faverjon and Tournassoud):

    d_dot >= -xi (d - d_s) / (d_i - d_s)        active while d < d_i,

where ``d`` is the surface distance [m], ``d_s`` the safety distance, ``d_i`` the
influence distance and ``xi`` [m/s] the approach speed allowed at ``d = d_i``.
A bounding-sphere broadphase skips far pairs, then the ``max_pairs`` closest pairs
within ``d_i`` are kept every step (a fixed pair subset would let the arms collide).
Point clouds enter as obstacle spheres (:meth:`CollisionAvoidance.set_obstacle_spheres`).

Two deviations from a single damper row per pair, each from a measured failure:

* The capsule distance is a minimum of smooth pieces (the closest points of the
  segments' interiors and the four end-point-to-segment distances). A row on the
  closest piece alone let near-parallel links turn about their witness point while
  their other ends closed in, and the witness jumped there a tick too late. End-point
  pieces within ``d_i`` whose witness lies more than ``end_point_offset`` from the
  closest points get their own damper row (at most ``max_extra_rows`` of them).
* Inside ``d_s`` the row asks for the separation speed ``(d_s - d) / recovery_time``
  instead of the damper's slow ``xi (d_s - d) / (d_i - d_s)``; the solver lowers what
  the acceleration limit cannot give (to "no further approach" at worst), so a
  penetrating state is escaped, not frozen. These rows are marked relaxable by
  :attr:`CollisionAvoidance.separation_rows`.

One option beyond the paper (issue 11): robot capsules named by
:meth:`CollisionAvoidance.set_approach_only` get "no further approach" rows against the
obstacle spheres (``h >= 0``: the bound is clamped at 0 inside ``d_s``), never a separation
demand. Measured reason: the map's cells lie 5-15 mm short of the true surface, so a gripper
that starts 9.8 mm (true) from the branch is inside ``d_s`` on the map (seed 1 of
``tasks/paper.yaml``); separation rows pushed it away during the approach and pre-stretched
the stem to 2.5 N before the force tare (true tension 5.6 N at the end while the wrist read
3.0 N). Arm-arm pairs and fixed environment primitives keep the separation rows.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from harvest_qp.collision import kernels
from harvest_qp.configuration import Configuration
from harvest_qp.exceptions import InvalidInputError, ModelError
from harvest_qp.limits.limit import Limit, LimitRows
from harvest_qp.validation import as_positive_scalar


@dataclass(frozen=True)
class CapsuleGeometry:
    """A capsule: segment ``p0``-``p1`` [m] and ``radius`` [m].

    ``frame`` is the model frame that carries it (end points in that frame), or
    ``None`` for a primitive fixed in the world (end points in the world frame).
    A sphere is a capsule with ``p0 == p1``.
    """

    name: str
    frame: str | None
    p0: tuple[float, float, float]
    p1: tuple[float, float, float]
    radius: float


def _as_count(value, name: str, *, minimum: int = 0) -> int:
    """An integer >= ``minimum`` (a bool, float with a fraction, string or None is rejected)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer, float, np.floating)):
        raise InvalidInputError(f"{name} must be an integer >= {minimum}, got {value!r} ({type(value).__name__})")
    if not np.isfinite(value) or int(value) != value or value < minimum:
        raise InvalidInputError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


class KinematicTree:
    """The model's joint tree as flat arrays for the compiled kernels."""

    def __init__(self, configuration: Configuration) -> None:
        model = configuration.model
        nj = model.njoints
        self.parent = np.array([model.parents[j] for j in range(nj)], dtype=np.int64)
        self.idx_v = np.zeros(nj, dtype=np.int64)
        self.joint_type = np.zeros(nj, dtype=np.int64)
        self.axis = np.zeros((nj, 3))
        self.place_R = np.tile(np.eye(3), (nj, 1, 1))
        self.place_p = np.zeros((nj, 3))
        for j in range(1, nj):
            joint = model.joints[j]
            name = joint.shortname()
            self.idx_v[j] = joint.idx_v
            if name in ("JointModelRX", "JointModelRY", "JointModelRZ"):
                self.axis[j, "XYZ".index(name[-1])] = 1.0
            elif name in ("JointModelPX", "JointModelPY", "JointModelPZ"):
                self.joint_type[j] = kernels.PRISMATIC
                self.axis[j, "XYZ".index(name[-1])] = 1.0
            elif name == "JointModelRevoluteUnaligned":
                self.axis[j] = joint.extract().axis
            else:
                raise ModelError(f"collision kernels support 1-DOF joints only, joint {model.names[j]} is {name}")
            self.place_R[j] = model.jointPlacements[j].rotation
            self.place_p[j] = model.jointPlacements[j].translation
        self.support = np.zeros((nj, nj), dtype=np.bool_)
        for j in range(nj):
            for k in model.supports[j]:
                self.support[j, k] = True
        self.joint_R = np.zeros((nj, 3, 3))
        self.joint_p = np.zeros((nj, 3))

    def update(self, q: np.ndarray) -> None:
        """World placements of all joints at ``q`` [rad]."""
        kernels.forward_kinematics(
            q, self.parent, self.idx_v, self.joint_type, self.axis, self.place_R, self.place_p,
            self.joint_R, self.joint_p,
        )


class CollisionAvoidance(Limit):
    """Velocity-damper collision constraints over candidate capsule pairs.

    Args:
        configuration: the robot.
        capsules: robot capsules (attached to frames) and fixed world primitives.
        pairs: candidate pairs by capsule name; moving capsules are also paired with
            every ``environment`` primitive and every obstacle sphere set later.
        environment: primitives fixed in the world (``frame=None``), e.g. the vine's
            branch and cane, paired with every moving capsule.
        safety_distance: ``d_s`` [m], never to be crossed.
        influence_distance: ``d_i`` [m], rows are active below it.
        gain: ``xi`` [m/s], approach speed allowed at ``d_i``.
        max_pairs: pairs kept per step (the closest ones), one row each at their closest points.
        max_extra_rows: end-point rows added on top (default ``max(4, max_pairs // 3)``).
        end_point_offset: an end-point piece gets a row when its witness points lie
            more than this [m] from the pair's closest points.
        recovery_time: inside ``d_s``, the separation speed asked is ``(d_s - d) / recovery_time`` [s].
    """

    priority = 5
    #: Rows with a negative bound ask for separation and may be lowered to "no approach".
    separation_rows = True

    def __init__(
        self,
        configuration: Configuration,
        capsules: Sequence[CapsuleGeometry],
        pairs: Sequence[tuple[str, str]],
        *,
        environment: Sequence[CapsuleGeometry] = (),
        safety_distance: float = 0.01,
        influence_distance: float = 0.10,
        gain: float = 0.5,
        max_pairs: int = 24,
        max_extra_rows: int | None = None,
        end_point_offset: float = 0.01,
        recovery_time: float = 0.02,
    ) -> None:
        self.safety_distance = as_positive_scalar(safety_distance, "safety_distance", allow_zero=True)
        self.influence_distance = as_positive_scalar(influence_distance, "influence_distance")
        if self.influence_distance <= self.safety_distance:
            raise InvalidInputError(
                f"influence_distance ({influence_distance}) must exceed safety_distance ({safety_distance})"
            )
        self.gain = as_positive_scalar(gain, "gain")
        self.max_pairs = _as_count(max_pairs, "max_pairs", minimum=1)
        self.max_extra_rows = (
            max(4, self.max_pairs // 3) if max_extra_rows is None else _as_count(max_extra_rows, "max_extra_rows")
        )
        self.end_point_offset = as_positive_scalar(end_point_offset, "end_point_offset")
        self.recovery_time = as_positive_scalar(recovery_time, "recovery_time")
        self.tree = KinematicTree(configuration)
        model = configuration.model
        names, joints, p0, p1, radius = [], [], [], [], []
        for cap in environment:
            if cap.frame is not None:
                raise InvalidInputError(f"environment primitive {cap.name!r} must be fixed in the world (frame=None)")
        for cap in list(capsules) + list(environment):
            if not isinstance(cap, CapsuleGeometry):
                raise InvalidInputError(f"capsules must be CapsuleGeometry, got {type(cap).__name__}: {cap!r}")
            try:
                cap_radius = float(cap.radius)
            except (TypeError, ValueError):
                cap_radius = np.nan
            if not np.isfinite(cap_radius) or cap_radius < 0:
                raise InvalidInputError(f"capsule {cap.name!r} radius must be finite and >= 0 [m], got {cap.radius!r}")
            for end in ("p0", "p1"):
                point = getattr(cap, end)
                try:
                    point = np.asarray(point, dtype=float)
                except (TypeError, ValueError):
                    point = np.full(1, np.nan)
                if point.shape != (3,) or not np.all(np.isfinite(point)):
                    raise InvalidInputError(
                        f"capsule {cap.name!r} {end} must be 3 finite coordinates [m], got {getattr(cap, end)!r}"
                    )
            if cap.frame is None:
                joint, placement = 0, None
            else:
                frame = model.frames[configuration.frame_id(cap.frame)]
                joint, placement = frame.parentJoint, frame.placement
            a, b = np.asarray(cap.p0, float), np.asarray(cap.p1, float)
            if placement is not None:
                a, b = placement.act(a), placement.act(b)
            names.append(cap.name)
            joints.append(joint)
            p0.append(a)
            p1.append(b)
            radius.append(cap.radius)
        if len(set(names)) != len(names):
            raise InvalidInputError("capsule names must be unique")
        self._robot = dict(names=names, joints=joints, p0=p0, p1=p1, radius=radius)
        index = {n: i for i, n in enumerate(names)}
        try:
            self._self_pairs = np.array([(index[a], index[b]) for a, b in pairs], dtype=np.int64).reshape(-1, 2)
        except KeyError as err:
            raise InvalidInputError(
                f"collision pair names unknown capsule {err.args[0]!r}; capsules are: {', '.join(names)}"
            ) from None
        self._moving = np.array([i for i, j in enumerate(joints) if j != 0], dtype=np.int64)
        env_index = np.array([index[cap.name] for cap in environment], dtype=np.int64)
        env_pairs = np.stack(np.meshgrid(self._moving, env_index, indexing="ij"), -1).reshape(-1, 2)
        self._self_pairs = np.vstack([self._self_pairs, env_pairs])
        self._approach_only = np.zeros(len(names), dtype=bool)
        self.set_obstacle_spheres(np.zeros((0, 3)), np.zeros(0))

    # ------------------------------------------------------------------ set-up
    @classmethod
    def dual_ur5e(cls, configuration: Configuration, **kwargs) -> CollisionAvoidance:
        """The shipped harvester's capsules and candidate pairs (same arm, arm to arm, stand).

        Keyword arguments (``environment``, distances, gain, ``max_pairs``) go to the constructor.
        """
        from harvest_qp.robot import description as desc

        capsules = [
            CapsuleGeometry(b.name, b.link, b.capsule.p0, b.capsule.p1, b.capsule.radius)
            for b in desc.collision_bodies()
        ]
        return cls(configuration, capsules, desc.self_collision_pairs(), **kwargs)

    def set_approach_only(self, names: Sequence[str]) -> None:
        """Give the robot capsules ``names`` "no further approach" rows against obstacle spheres.

        Their rows with an obstacle sphere never ask for separation: inside ``d_s`` the
        bound is 0 (the distance may not decrease) instead of the separation speed, so the
        spheres only stop these capsules, never push them. Outside ``d_s`` the damper is
        unchanged. Pairs with other capsules and environment primitives are unchanged.
        ``names=()`` restores the separation rows everywhere.

        Raises:
            InvalidInputError: a name that is not a moving robot capsule of this limit.
        """
        if isinstance(names, str):
            names = [names]
        robot = self._robot["names"]
        mask = np.zeros(len(robot), dtype=bool)
        for name in names:
            if name not in robot or self._robot["joints"][robot.index(name)] == 0:
                moving = ", ".join(robot[i] for i in self._moving)
                raise InvalidInputError(
                    f"approach-only capsule {name!r} is not a moving capsule; expected one of: {moving}"
                )
            mask[robot.index(name)] = True
        self._approach_only = mask
        self._update_approach_pairs()

    @property
    def approach_only_capsules(self) -> list[str]:
        """Robot capsules whose obstacle-sphere rows never ask for separation (:meth:`set_approach_only`)."""
        return [n for n, hold in zip(self._robot["names"], self._approach_only) if hold]

    @property
    def approach_only_pairs(self) -> list[tuple[str, str]]:
        """Candidate pairs (by capsule name) whose rows never ask for separation (:meth:`set_approach_only`)."""
        return [self.pair_names()[k] for k in np.flatnonzero(self._approach_pair)]

    def _update_approach_pairs(self) -> None:
        """Which candidate pairs are (approach-only capsule, obstacle sphere)."""
        nr = len(self._robot["names"])
        a = np.minimum(self.pair_a, nr - 1)
        self._approach_pair = self._approach_only[a] & (self.pair_a < nr) & (self.pair_b >= nr)
        self._any_approach_only = bool(self._approach_pair.any())

    def set_obstacle_spheres(self, centers: np.ndarray, radii: np.ndarray | float) -> None:
        """Replace the obstacle spheres (world centres [m], radii [m]); e.g. from a point cloud.

        Raises:
            InvalidInputError: centres not (n, 3) finite numbers, radii neither a scalar nor
                n values, or a radius negative or non-finite.
        """
        try:
            centers = np.asarray(centers, dtype=float)
        except (TypeError, ValueError):
            raise InvalidInputError(
                f"obstacle centers must be an (n, 3) array of numbers [m], got {centers!r}"
            ) from None
        if centers.ndim != 2 or centers.shape[1] != 3:
            raise InvalidInputError(f"obstacle centers must have shape (n, 3), got {centers.shape}")
        try:
            radii = np.asarray(radii, dtype=float)
        except (TypeError, ValueError):
            raise InvalidInputError(f"obstacle radii must be numbers [m], got {radii!r}") from None
        if radii.ndim > 1 or (radii.ndim == 1 and radii.shape[0] != centers.shape[0]):
            raise InvalidInputError(
                f"obstacle radii must be a scalar or one per centre ({centers.shape[0]}), got shape {radii.shape}"
            )
        radii = np.broadcast_to(radii, (centers.shape[0],))
        if not np.all(np.isfinite(centers)):
            raise InvalidInputError(f"obstacle centers must be finite, got {centers[~np.isfinite(centers).all(1)][:3]}")
        if not (np.all(np.isfinite(radii)) and np.all(radii >= 0)):
            bad = radii[~(np.isfinite(radii) & (radii >= 0))][:3]
            raise InvalidInputError(f"obstacle radii must be finite and >= 0 [m], got {bad}")
        r = self._robot
        nr = len(r["names"])
        self.capsule_names = r["names"] + [f"obstacle_{i}" for i in range(centers.shape[0])]
        self.cap_joint = np.array(r["joints"] + [0] * centers.shape[0], dtype=np.int64)
        self.cap_p0 = np.vstack([np.array(r["p0"]).reshape(-1, 3), centers])
        self.cap_p1 = np.vstack([np.array(r["p1"]).reshape(-1, 3), centers])
        self.cap_radius = np.concatenate([np.array(r["radius"], float), radii])
        obstacle = np.arange(nr, nr + centers.shape[0], dtype=np.int64)
        env_pairs = np.stack(np.meshgrid(self._moving, obstacle, indexing="ij"), -1).reshape(-1, 2)
        pairs = np.vstack([self._self_pairs, env_pairs])
        self.pair_a = np.ascontiguousarray(pairs[:, 0])
        self.pair_b = np.ascontiguousarray(pairs[:, 1])
        n_caps, n_pairs = len(self.capsule_names), len(pairs)
        self._w0 = np.zeros((n_caps, 3))
        self._w1 = np.zeros((n_caps, 3))
        self._dist = np.full(n_pairs, np.inf)
        self._s = np.zeros(n_pairs)
        self._t = np.zeros(n_pairs)
        rows = self.max_pairs + self.max_extra_rows
        self._G = np.zeros((rows, self.tree.support.shape[0] - 1))
        self._h = np.full(rows, 1e30)
        self.normals = np.zeros((rows, 3))
        self._selected = np.zeros(self.max_pairs, dtype=np.int64)
        self._row_pair = np.zeros(rows, dtype=np.int64)
        self._row_s = np.zeros(rows)
        self._row_t = np.zeros(rows)
        self._row_d = np.zeros(rows)
        self._limit_rows = LimitRows(G=self._G, h=self._h)  # the same buffers every step
        self.active_pairs = self._selected[:0]
        self.num_rows = 0
        self._update_approach_pairs()

    @property
    def num_candidate_pairs(self) -> int:
        """Number of candidate pairs checked each step."""
        return int(self.pair_a.shape[0])

    # ------------------------------------------------------------------ evaluation
    def _distances(self, configuration: Configuration, influence: float) -> np.ndarray:
        tree = self.tree
        tree.update(configuration.q)
        kernels.capsule_world(self.cap_joint, self.cap_p0, self.cap_p1, tree.joint_R, tree.joint_p, self._w0, self._w1)
        kernels.pair_distances(
            self.pair_a, self.pair_b, self.cap_radius, self._w0, self._w1, influence, self._dist, self._s, self._t
        )
        return self._dist

    def distances(self, configuration: Configuration) -> np.ndarray:
        """Exact surface distance [m] of every candidate pair (no broadphase), in pair order."""
        return self._distances(configuration, np.inf).copy()

    def capsule_segments(self, configuration: Configuration) -> tuple[np.ndarray, np.ndarray]:
        """World end points [m] (two arrays, one row per capsule, in ``capsule_names`` order) at
        the configuration's ``q``."""
        self._distances(configuration, 0.0)
        return self._w0.copy(), self._w1.copy()

    def pair_names(self) -> list[tuple[str, str]]:
        """Candidate pairs by capsule name, in the order of :meth:`distances`."""
        return [(self.capsule_names[a], self.capsule_names[b]) for a, b in zip(self.pair_a, self.pair_b)]

    def compute(self, configuration: Configuration, dt: float, previous_qdot=None) -> LimitRows:
        """The damper rows ``G qdot <= h`` of the closest pairs at the configuration's ``q``.

        One compiled call: the distances, the rows, then (with approach-only capsules) "no
        further approach" for those capsules against obstacle spheres (a negative bound inside
        ``d_s`` would push the capsule away). Rows ``0..len(active_pairs)-1`` belong to
        :attr:`active_pairs` in order; end-point rows follow.
        """
        tree = self.tree
        n_pairs, n_rows = kernels.collision_step_clamped(
            configuration.q,
            tree.parent, tree.idx_v, tree.joint_type, tree.axis, tree.place_R, tree.place_p,
            tree.joint_R, tree.joint_p, self.cap_joint, self.cap_p0, self.cap_p1, self.cap_radius,
            self._w0, self._w1, self.pair_a, self.pair_b, self._dist, self._s, self._t,
            tree.support, self.safety_distance, self.influence_distance, self.gain, self.recovery_time,
            self.max_pairs, self.max_extra_rows, self.end_point_offset,
            self._G, self._h, self.normals, self._selected, self._row_pair, self._row_s, self._row_t, self._row_d,
            self._approach_pair, self._any_approach_only,
        )
        self.active_pairs = self._selected[:n_pairs]
        self.num_rows = n_rows
        return self._limit_rows

    def active_pair_distances(self) -> list[tuple[str, str, float]]:
        """Pairs that were rows of the last :meth:`compute`: both capsule names and distance [m]."""
        return pairs_from_snapshot(self.active_pair_snapshot())

    def active_pair_snapshot(self) -> tuple:
        """What :meth:`active_pair_distances` needs, frozen now (names and distances change next tick)."""
        active = self.active_pairs
        # capsule_names is changed in place by the obstacle map's feed: copy it (a shallow copy);
        # pair_a / pair_b are replaced, never changed in place.
        return list(self.capsule_names), self.pair_a, self.pair_b, active.copy(), self._dist[active]

    @property
    def row_pairs(self) -> np.ndarray:
        """Pair index of every row of the last :meth:`compute` (closest-point rows, then end-point rows)."""
        return self._row_pair[: self.num_rows]


def pairs_from_snapshot(snapshot: tuple) -> list[tuple[str, str, float]]:
    """``(name_a, name_b, distance [m])`` of each pair of a ``CollisionAvoidance.active_pair_snapshot``."""
    names, pair_a, pair_b, active, distances = snapshot
    return [(names[pair_a[k]], names[pair_b[k]], float(d)) for k, d in zip(active.tolist(), distances.tolist())]
