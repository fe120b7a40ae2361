"""Collision avoidance between capsules, environment primitives and obstacle spheres.

Each close pair (a, b) gives one velocity-damper row (Faverjon and Tournassoud):

    d_dot >= -xi (d - d_s) / (d_i - d_s)        active while d < d_i,

where ``d`` is the surface distance [m], ``d_s`` the safety distance, ``d_i`` the
influence distance and ``xi`` [m/s] the approach speed allowed at ``d = d_i``.
A bounding-sphere broadphase skips far pairs, then the ``max_pairs`` closest pairs
within ``d_i`` are kept every step (a fixed pair subset would let the arms collide).
Point clouds enter as obstacle spheres (:meth:`CollisionAvoidance.set_obstacle_spheres`).
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
        max_pairs: rows kept per step (the closest pairs).
    """

    priority = 5

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
    ) -> None:
        self.safety_distance = as_positive_scalar(safety_distance, "safety_distance", allow_zero=True)
        self.influence_distance = as_positive_scalar(influence_distance, "influence_distance")
        if self.influence_distance <= self.safety_distance:
            raise InvalidInputError(
                f"influence_distance ({influence_distance}) must exceed safety_distance ({safety_distance})"
            )
        self.gain = as_positive_scalar(gain, "gain")
        if int(max_pairs) < 1:
            raise InvalidInputError(f"max_pairs must be >= 1, got {max_pairs}")
        self.max_pairs = int(max_pairs)
        self.tree = KinematicTree(configuration)
        model = configuration.model
        names, joints, p0, p1, radius = [], [], [], [], []
        for cap in environment:
            if cap.frame is not None:
                raise InvalidInputError(f"environment primitive {cap.name!r} must be fixed in the world (frame=None)")
        for cap in list(capsules) + list(environment):
            if cap.radius < 0 or not np.isfinite(cap.radius):
                raise InvalidInputError(f"capsule {cap.name!r} radius must be >= 0, got {cap.radius}")
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

    def set_obstacle_spheres(self, centers: np.ndarray, radii: np.ndarray | float) -> None:
        """Replace the obstacle spheres (world centres [m], radii [m]); e.g. from a point cloud."""
        centers = np.asarray(centers, dtype=float)
        if centers.ndim != 2 or centers.shape[1] != 3:
            raise InvalidInputError(f"obstacle centers must have shape (n, 3), got {centers.shape}")
        radii = np.broadcast_to(np.asarray(radii, dtype=float), (centers.shape[0],))
        if not (np.all(np.isfinite(centers)) and np.all(np.isfinite(radii)) and np.all(radii >= 0)):
            raise InvalidInputError("obstacle centers must be finite and radii finite and >= 0")
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
        self._G = np.zeros((self.max_pairs, self.tree.support.shape[0] - 1))
        self._h = np.full(self.max_pairs, 1e30)
        self.normals = np.zeros((self.max_pairs, 3))
        self._selected = np.zeros(self.max_pairs, dtype=np.int64)
        self.active_pairs = self._selected[:0]

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

    def pair_names(self) -> list[tuple[str, str]]:
        """Candidate pairs by capsule name, in the order of :meth:`distances`."""
        return [(self.capsule_names[a], self.capsule_names[b]) for a, b in zip(self.pair_a, self.pair_b)]

    def compute(self, configuration: Configuration, dt: float, previous_qdot=None) -> LimitRows:
        tree = self.tree
        n_rows = kernels.collision_step(
            configuration.q, tree.parent, tree.idx_v, tree.joint_type, tree.axis, tree.place_R, tree.place_p,
            tree.joint_R, tree.joint_p, self.cap_joint, self.cap_p0, self.cap_p1, self.cap_radius,
            self._w0, self._w1, self.pair_a, self.pair_b, self._dist, self._s, self._t,
            tree.support, self.safety_distance, self.influence_distance, self.gain, self.max_pairs,
            self._G, self._h, self.normals, self._selected,
        )
        self.active_pairs = self._selected[:n_rows]
        return LimitRows(G=self._G, h=self._h)
