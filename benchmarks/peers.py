"""Peer IK/QP libraries set up on harvest_qp's dual-UR5e benchmark problem.

This module holds the benchmark problem (:class:`BenchProblem`) shared by
``benchmarks/bench_qp.py`` and one setup function per peer library:

* :func:`setup_placo` -- placo 0.10 (C++ ``KinematicsSolver``), URDF model;
* :func:`setup_mink` -- mink (MuJoCo kinematics, QP through qpsolvers + daqp), MJCF model;
* :func:`setup_pink` -- pink (pinocchio kinematics, QP through qpsolvers + daqp), URDF model.

Each returns a peer with ``step(q, t) -> qdot``: the full per-step work of a
velocity controller (kinematics from ``q``, targets at time ``t``, build and
solve the QP), returning the 12 joint velocities [rad/s] in harvest_qp's joint
order (camera arm first). The differences between what each peer solves and
harvest_qp's problem are listed in ``benchmarks/README.md`` and in
:data:`DIFFERENCES`.

Run ``python benchmarks/peers.py`` to time the peers alone.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

_REPO = Path(__file__).resolve().parents[1]
if str(_REPO) not in sys.path:  # run from a checkout without installing the package
    sys.path.insert(0, str(_REPO))

from harvest_qp.robot import description as desc  # noqa: E402
from harvest_qp.robot import paths  # noqa: E402

#: Frames of the two task-space tasks.
CAMERA_FRAME = "camera"
GRIPPER_FRAME = "gripper"

#: Name prefix of the obstacle spheres (``obstacle_0`` ... ``obstacle_7``).
OBSTACLE_PREFIX = "obstacle_"

#: Obstacle spheres: centre [m] (world) and radius [m]. Placed between the arms
#: and the vine (x 0.4-0.6 m, z 1.0-1.4 m), clear of the robot at HOME_Q, several
#: of them within the influence distance of the tools and wrists.
OBSTACLES: tuple[tuple[tuple[float, float, float], float], ...] = (
    ((0.55, -0.12, 1.30), 0.04),  # above the gripper
    ((0.58, -0.10, 1.00), 0.04),  # below and ahead of the gripper
    ((0.45, 0.05, 1.15), 0.05),  # between the two tools
    ((0.47, 0.45, 1.22), 0.04),  # above and ahead of the camera
    ((0.45, 0.55, 1.06), 0.03),  # below the cutter
    ((0.40, -0.32, 1.30), 0.05),  # beside the grasping arm's wrist
    ((0.60, 0.25, 1.38), 0.04),  # high, between the arms
    ((0.60, -0.35, 1.10), 0.03),  # outside the grasping arm
)


def _default_obstacles() -> tuple:
    return OBSTACLES


@dataclass
class BenchProblem:
    """The dual-UR5e per-step velocity-control problem every contender solves.

    Velocity-space formulation (what harvest_qp solves; peers solve the same
    problem scaled by ``dt`` in displacement space ``dq = qdot * dt``, which has
    the same minimiser)::

        min_qdot  w_camera  ||S_c (J_c qdot - V_c(t))||^2       (5-D: rotation about camera z free)
                + w_gripper ||J_g qdot - V_g(t)||^2              (6-D)
                + w_posture ||qdot - k_posture (q_home - q)||^2
                + w_damping ||qdot||^2
        s.t.  q_min <= q + qdot dt <= q_max                       (URDF position limits)
              |qdot| <= v_max                                     (pi rad/s)
              |qdot - qdot_prev| <= a_max dt                      (qdot_prev: the previous command)
              n^T (J_b(p_b) - J_a(p_a)) qdot >= -xi (d - d_s) / (d_i - d_s)   for every pair with d < d_i

    Twists are 6-D ``[linear; angular]``, world-aligned, at the frame origin
    (pinocchio's LOCAL_WORLD_ALIGNED). ``S_c`` keeps the linear part and the
    angular components about the camera's x and y axes.
    """

    dt: float = 0.002
    q0: np.ndarray = field(default_factory=lambda: desc.HOME_Q.copy())
    q_home: np.ndarray = field(default_factory=lambda: desc.HOME_Q.copy())
    # Reference twists: component i is amp_i * sin(2 pi f_i t) (smooth start at rest).
    lin_amp: float = 0.05  # [m/s] per axis
    ang_amp: float = 0.2  # [rad/s] per axis
    camera_freqs: tuple[float, ...] = (0.50, 0.35, 0.42, 0.30, 0.45, 0.25)  # [Hz]
    gripper_freqs: tuple[float, ...] = (0.40, 0.55, 0.33, 0.38, 0.28, 0.50)  # [Hz]
    # Weights of the weighted (single-level) formulation.
    w_camera: float = 1.0
    w_gripper: float = 1.0
    w_posture: float = 1e-4
    k_posture: float = 1.0  # [1/s]
    w_damping: float = 1e-4
    # Limits.
    v_max: float = np.pi  # [rad/s]
    a_max: float = 10.0  # [rad/s^2], relative to the previous command
    # Collision avoidance (velocity damper).
    d_safe: float = 0.01  # d_s [m]
    d_influence: float = 0.10  # d_i [m]
    xi: float = 0.5  # damper gain [m/s]
    obstacles: tuple = field(default_factory=_default_obstacles)
    #: Arm capsules checked against the obstacles: link index >= this (1: every arm capsule,
    #: 222 pairs in all; 3: forearm, wrists and tools only, as for the stand: 190 pairs).
    obstacle_min_link_index: int = 1

    # -- derived data --------------------------------------------------------
    @property
    def nq(self) -> int:
        return len(self.q0)

    @property
    def urdf_path(self) -> Path:
        return paths.urdf_path()

    @property
    def mjcf_path(self) -> Path:
        return paths.mjcf_path()

    def joint_names(self) -> list[str]:
        return desc.joint_names()

    def obstacle_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """Obstacle sphere centres (n, 3) [m, world] and radii (n,) [m]."""
        centres = np.array([c for c, _ in self.obstacles], dtype=float).reshape(-1, 3)
        radii = np.array([r for _, r in self.obstacles], dtype=float)
        return centres, radii

    def obstacle_names(self) -> list[str]:
        return [f"{OBSTACLE_PREFIX}{i}" for i in range(len(self.obstacles))]

    def collision_pairs(self) -> list[tuple[str, str]]:
        """Robot-robot candidate pairs + every arm capsule against every obstacle sphere.

        Names are those of ``harvest_qp.robot.description.collision_bodies()`` (also the
        MJCF geom names) and ``obstacle_<i>``.
        """
        pairs = list(desc.self_collision_pairs())
        arm_bodies = [b.name for b in desc.collision_bodies() if b.arm and b.link_index >= self.obstacle_min_link_index]
        for obstacle in self.obstacle_names():
            pairs += [(body, obstacle) for body in arm_bodies]
        return pairs

    def __post_init__(self) -> None:
        self.q0 = np.asarray(self.q0, dtype=float).copy()
        self.q_home = np.asarray(self.q_home, dtype=float).copy()
        amps = np.array([self.lin_amp] * 3 + [self.ang_amp] * 3)
        self._twist_amps = np.concatenate([amps, amps])
        self._twist_omegas = 2.0 * np.pi * np.array(tuple(self.camera_freqs) + tuple(self.gripper_freqs))

    def twists(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Reference twists ``(V_c, V_g)`` at time ``t`` [s]: 6-D [linear; angular], world-aligned.

        Component i is ``amp_i sin(2 pi f_i t)``; the amplitudes and frequencies are
        read at construction (make a new problem to change them).
        """
        v = self._twist_amps * np.sin(self._twist_omegas * t)
        return v[:6], v[6:]

    @property
    def collision_gain(self) -> float:
        """Velocity-damper slope xi / (d_i - d_s) [1/s]."""
        return self.xi / (self.d_influence - self.d_safe)


#: Differences between each peer's problem and harvest_qp's (printed by the driver).
DIFFERENCES: dict[str, list[str]] = {
    "all": [
        "Peers are weighted single-level QPs (task weights w_camera, w_gripper, w_posture, w_damping); "
        "they have no strict task priorities.",
        "Peers take pose targets, not twists: each step the target is T* = exp(V dt) T(q) "
        "(position p + v dt, rotation exp(w dt) R), and a unit task gain turns the pose error back into "
        "J dq = V dt. placo uses the world-aligned pose error (exactly V dt); mink and pink use the "
        "body-frame log error and its Jacobian Jlog (equal to V dt up to O(|w dt|^2)).",
        "Peers solve for a displacement dq = qdot dt (cost scaled by dt^2: same minimiser).",
        "Damping: placo RegularizationTask (weight w_damping; placo adds its own 1e-8), mink and "
        "pink DampingTask (cost sqrt(w_damping); solve_ik adds 1e-12). Weights: placo takes w, "
        "mink and pink take a cost c with w = c^2.",
        "The posture term k_posture (q_home - q) is a posture task with gain k_posture dt (mink, pink) "
        "or a joint target q + k_posture dt (q_home - q) reset every step (placo).",
    ],
    "placo": [
        "placo adds a floating base (7 coordinates): it is masked (mask_fbase) and the solution's "
        "first 6 entries are dropped.",
        "Camera task: FrameTask whose orientation part is masked to the target's local x, y axes "
        "(AxisesMask 'xy', local): 5-D, as harvest_qp's.",
        "Acceleration limit: no built-in; added as a hard joint-space half-space constraint "
        "A (q + dq) <= b whose b is refreshed every step.",
        "Collision: the URDF's cylinder + 2 spheres per capsule are replaced by coal capsules in placo's "
        "pinocchio collision model (one object per capsule, same as harvest_qp) and the 8 obstacle "
        "spheres are added to it; only the benchmark's pairs are registered.",
        "Collision constraint: d + n^T J dq >= d_s for pairs with d < d_i, hard: no damper gain, i.e. "
        "it allows closing the whole gap in one step (equivalent slope 1/dt = 500 1/s instead of "
        "xi/(d_i - d_s)). Distances are computed for every registered pair every step (C++).",
        "A hard undamped collision row and the hard acceleration limit conflict: approaching an "
        "obstacle at speed, the step that reaches d_s needs a stop in one step and the QP is "
        "infeasible (QPError; seen with the gripper driven up into a sphere at 0.1 m/s). The "
        "benchmark's trajectory never gets there.",
        "placo's distances() allocates a pinocchio GeometryData and computes every registered pair "
        "every step, even those far beyond d_i.",
        "solve(False): the solution is not integrated into placo's state (the state is set from q every step).",
        "QP: placo's own dense solver (C++).",
    ],
    "mink": [
        "Model: the MJCF (real capsule geoms) with the 8 obstacle spheres added to a mocap body "
        "(a world geom is skipped by mink's parent-child filter against the shoulders).",
        "The robot geoms' conaffinity is set to 1 in the benchmark's model copy: with the "
        "generated contype=1/conaffinity=0 mink's contype filter drops every robot-robot pair.",
        "Camera task: FrameTask with orientation cost (c, c, 0) in the frame's local axes: 5-D.",
        "Acceleration limit: no built-in; a mink.Limit subclass bounds dq to dt (qdot_prev +- a_max dt).",
        "Collision: CollisionAvoidanceLimit bounds the normal displacement by gain (d - d_s)/dt; the "
        "gain is set to xi dt^2/(d_i - d_s) so that the bound equals harvest_qp's damper. Every pair "
        "gives a row (an inactive one has h = inf); pairs beyond d_i are culled by its broadphase.",
        "ConfigurationLimit gain 1.0 (default 0.95) to match q + qdot dt within the limits.",
        "QP: qpsolvers -> daqp (dense), problem rebuilt every step.",
    ],
    "pink": [
        "Collision model: pinocchio GeometryModel with one coal capsule per robot capsule and the 8 "
        "obstacle spheres, only the benchmark's pairs registered (the URDF's cylinder + 2 spheres "
        "are not used).",
        "Camera task: FrameTask with orientation cost (c, c, 0) in the frame's local axes: 5-D.",
        "Acceleration limit: pink's AccelerationLimit (also bounds the velocity by the braking "
        "distance sqrt(2 a_max (q_max - q)) to the position limits).",
        "Collision: SelfCollisionBarrier J qdot >= -gain (d - d_s) with gain = xi/(d_i - d_s) and no "
        "safe-displacement cost term; it keeps a row for every pair (its N closest with N = all "
        "pairs): no influence-distance cut-off. Configuration.update() runs pinocchio "
        "computeCollisions and computeDistances on every pair and the Jacobian rows are built in "
        "a Python loop.",
        "ConfigurationLimit gain 1.0 (default 0.5) to match q + qdot dt within the limits.",
        "QP: qpsolvers -> daqp (dense), problem rebuilt every step.",
    ],
}


# ---------------------------------------------------------------------------------------------
# Small geometry helpers
# ---------------------------------------------------------------------------------------------


def _rotation_z_to(axis: np.ndarray) -> np.ndarray:
    """A rotation matrix whose z axis is the unit vector ``axis``."""
    z = axis / np.linalg.norm(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.column_stack([x, y, z])


def _capsule_local_pose(capsule) -> tuple[np.ndarray, np.ndarray, float]:
    """(rotation, centre, length) of a capsule's cylinder axis in its link frame."""
    p0, p1 = np.asarray(capsule.p0, float), np.asarray(capsule.p1, float)
    return _rotation_z_to(p1 - p0), 0.5 * (p0 + p1), float(np.linalg.norm(p1 - p0))


def build_pinocchio_collision_model(model, problem: BenchProblem, fbase_joint: int = 0):
    """A pinocchio GeometryModel with one coal capsule per robot capsule and the obstacle spheres.

    ``model`` is a pinocchio model of the URDF (with or without a floating base);
    obstacles hang on the universe joint. Only ``problem.collision_pairs()`` are
    registered. Returns ``(geometry_model, name -> geometry index)``.
    """
    import coal
    import pinocchio as pin

    gm = pin.GeometryModel()
    index: dict[str, int] = {}
    for body in desc.collision_bodies():
        frame_id = model.getFrameId(body.link)
        frame = model.frames[frame_id]
        R, c, length = _capsule_local_pose(body.capsule)
        placement = frame.placement * pin.SE3(R, c)
        geom = pin.GeometryObject(
            body.name, frame.parentJoint, frame_id, placement, coal.Capsule(body.capsule.radius, length)
        )
        index[body.name] = gm.addGeometryObject(geom)
    for name, (centre, radius) in zip(problem.obstacle_names(), problem.obstacles, strict=True):
        geom = pin.GeometryObject(name, 0, 0, pin.SE3(np.eye(3), np.asarray(centre, float)), coal.Sphere(radius))
        index[name] = gm.addGeometryObject(geom)
    for a, b in problem.collision_pairs():
        gm.addCollisionPair(pin.CollisionPair(index[a], index[b]))
    return gm, index


# ---------------------------------------------------------------------------------------------
# Evaluation (independent of the peers): twists achieved and distances, with pinocchio + coal
# ---------------------------------------------------------------------------------------------


class Evaluator:
    """Achieved task twists and pair distances for a joint configuration (pinocchio + coal)."""

    def __init__(self, problem: BenchProblem):
        import pinocchio as pin

        self.pin = pin
        self.problem = problem
        self.model = pin.buildModelFromUrdf(str(problem.urdf_path))
        self.data = self.model.createData()
        self.fid_c = self.model.getFrameId(CAMERA_FRAME)
        self.fid_g = self.model.getFrameId(GRIPPER_FRAME)
        self.gm, _ = build_pinocchio_collision_model(self.model, problem)
        self.gd = pin.GeometryData(self.gm)

    def twist_errors(self, q: np.ndarray, qdot: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(camera 5-D error, gripper 6-D error) of J(q) qdot against the reference twists at t."""
        pin = self.pin
        pin.computeJointJacobians(self.model, self.data, q)
        pin.updateFramePlacements(self.model, self.data)
        lwa = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
        J_c = pin.getFrameJacobian(self.model, self.data, self.fid_c, lwa)
        J_g = pin.getFrameJacobian(self.model, self.data, self.fid_g, lwa)
        v_c, v_g = self.problem.twists(t)
        e_c = J_c @ qdot - v_c
        R_c = self.data.oMf[self.fid_c].rotation
        e_c5 = np.concatenate([e_c[:3], (R_c.T @ e_c[3:])[:2]])
        return e_c5, J_g @ qdot - v_g

    def distances(self, q: np.ndarray) -> np.ndarray:
        """Distances [m] of every benchmark pair (in ``problem.collision_pairs()`` order)."""
        pin = self.pin
        pin.computeDistances(self.model, self.data, self.gm, self.gd, q)
        return np.array([r.min_distance for r in self.gd.distanceResults])


# ---------------------------------------------------------------------------------------------
# placo
# ---------------------------------------------------------------------------------------------


class PlacoPeer:
    """placo ``KinematicsSolver`` on the dual-UR5e URDF."""

    name = "placo"

    def __init__(self, problem: BenchProblem, collision: bool):
        import pinocchio as pin
        import placo

        self.problem = problem
        self.dt = dt = problem.dt
        self.collision = collision
        self._exp3 = pin.exp3
        robot = placo.RobotWrapper(str(problem.urdf_path), placo.Flags.ignore_collisions)
        self.robot = robot
        self.joint_names = problem.joint_names()
        self._q_offsets = np.array([robot.get_joint_offset(n) for n in self.joint_names])
        if not np.array_equal(self._q_offsets, np.arange(7, 7 + problem.nq)):
            raise RuntimeError(f"unexpected placo joint layout {self._q_offsets}")
        robot.state.q[:7] = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
        robot.state.q[7:] = problem.q0
        robot.update_kinematics()

        solver = placo.KinematicsSolver(robot)
        self.solver = solver
        solver.mask_fbase(True)
        solver.dt = dt
        solver.enable_joint_limits(True)
        solver.enable_velocity_limits(True)
        robot.set_velocity_limits(problem.v_max)

        self.fid_c = robot.model.getFrameId(CAMERA_FRAME)
        self.fid_g = robot.model.getFrameId(GRIPPER_FRAME)
        self.task_c = solver.add_frame_task(CAMERA_FRAME, robot.get_T_world_frame(CAMERA_FRAME))
        self.task_c.configure("camera", "soft", problem.w_camera, problem.w_camera)
        self.task_c.orientation().mask.set_axises("xy", "local")
        self.task_g = solver.add_frame_task(GRIPPER_FRAME, robot.get_T_world_frame(GRIPPER_FRAME))
        self.task_g.configure("gripper", "soft", problem.w_gripper, problem.w_gripper)
        self.posture = solver.add_joints_task()
        self.posture.set_joints(dict(zip(self.joint_names, problem.q0.tolist(), strict=True)))
        self.posture.configure("posture", "soft", problem.w_posture)
        self.regularization = solver.add_regularization_task(problem.w_damping)

        # Acceleration limit: A (q + dq) <= b with A = [I; -I] on the joints (placo ignores fbase columns).
        n = problem.nq
        A = np.zeros((2 * n, 7 + n))
        A[:n, 7:] = np.eye(n)
        A[n:, 7:] = -np.eye(n)
        self.acc = solver.add_joint_space_half_spaces_constraint(A, np.zeros(2 * n))
        self.acc.configure("acceleration", "hard", 1.0)
        self.qdot_prev = np.zeros(n)
        self._a_dt2 = problem.a_max * dt * dt

        if collision:
            gm = robot.collision_model  # a reference to placo's pinocchio GeometryModel
            gm.removeAllCollisionPairs()
            for name in [g.name for g in gm.geometryObjects]:
                gm.removeGeometryObject(name)
            built, _ = build_pinocchio_collision_model(robot.model, problem)
            for geom in built.geometryObjects:
                gm.addGeometryObject(geom)
            for pair in built.collisionPairs:
                gm.addCollisionPair(pin.CollisionPair(pair.first, pair.second))
            self.n_pairs = len(robot.collision_model.collisionPairs)
            self.col = solver.add_avoid_self_collisions_constraint()
            self.col.self_collisions_margin = problem.d_safe
            self.col.self_collisions_trigger = problem.d_influence
            self.col.configure("collisions", "hard", 1.0)
        else:
            self.n_pairs = 0

    def step(self, q: np.ndarray, t: float) -> np.ndarray:
        p, dt, robot, exp3 = self.problem, self.dt, self.robot, self._exp3
        robot.state.q[7:] = q
        robot.update_kinematics()
        v_c, v_g = p.twists(t)
        T = robot.get_T_world_frame(CAMERA_FRAME)
        T[:3, 3] += v_c[:3] * dt
        T[:3, :3] = exp3(v_c[3:] * dt) @ T[:3, :3]
        self.task_c.T_world_frame = T
        T = robot.get_T_world_frame(GRIPPER_FRAME)
        T[:3, 3] += v_g[:3] * dt
        T[:3, :3] = exp3(v_g[3:] * dt) @ T[:3, :3]
        self.task_g.T_world_frame = T
        q_post = q + (p.k_posture * dt) * (p.q_home - q)
        self.posture.set_joints(dict(zip(self.joint_names, q_post.tolist(), strict=True)))
        q_next = q + dt * self.qdot_prev  # where the previous command would take q
        self.acc.b = np.concatenate([q_next + self._a_dt2, self._a_dt2 - q_next])
        dq = self.solver.solve(False)
        qdot = dq[6:] / dt
        self.qdot_prev = qdot
        return qdot


def setup_placo(problem: BenchProblem, collision: bool) -> PlacoPeer:
    return PlacoPeer(problem, collision)


# ---------------------------------------------------------------------------------------------
# mink
# ---------------------------------------------------------------------------------------------


def _mink_model(problem: BenchProblem):
    """MuJoCo model: the robot MJCF + the obstacle spheres on a mocap body; robot conaffinity = 1."""
    import mujoco

    from harvest_qp.robot.meshes import strip_visual_meshes

    spec = mujoco.MjSpec.from_file(str(problem.mjcf_path))
    strip_visual_meshes(spec)  # drawing-only UR5e meshes: mink sees the capsule robot, as before
    body = spec.worldbody.add_body(name="obstacles", mocap=True)
    for name, (centre, radius) in zip(problem.obstacle_names(), problem.obstacles, strict=True):
        body.add_geom(
            name=name,
            type=mujoco.mjtGeom.mjGEOM_SPHERE,
            size=[radius, 0.0, 0.0],
            pos=list(centre),
            contype=1,
            conaffinity=1,
        )
    model = spec.compile()
    model.geom_conaffinity[:] = 1
    model.geom_contype[:] = 1
    return model


class MinkPeer:
    """mink ``solve_ik`` (qpsolvers + daqp) on the dual-UR5e MJCF."""

    name = "mink"

    def __init__(self, problem: BenchProblem, collision: bool):
        import mink
        import mujoco

        self.mujoco = mujoco
        self.mink = mink
        self.problem = problem
        self.dt = dt = problem.dt
        self.collision = collision
        model = _mink_model(problem)
        self.model = model
        names = problem.joint_names()
        self._qadr = np.array([model.jnt_qposadr[model.joint(n).id] for n in names])
        self._dadr = np.array([model.jnt_dofadr[model.joint(n).id] for n in names])
        if not (np.array_equal(self._qadr, np.arange(problem.nq)) and model.nq == problem.nq):
            raise RuntimeError(f"unexpected MuJoCo joint layout {self._qadr}")
        self.configuration = mink.Configuration(model, problem.q0.copy())
        self.sid_c = model.site(CAMERA_FRAME).id
        self.sid_g = model.site(GRIPPER_FRAME).id

        cost_c, cost_g = np.sqrt(problem.w_camera), np.sqrt(problem.w_gripper)
        self.task_c = mink.FrameTask(CAMERA_FRAME, "site", cost_c, [cost_c, cost_c, 0.0], gain=1.0)
        self.task_g = mink.FrameTask(GRIPPER_FRAME, "site", cost_g, cost_g, gain=1.0)
        self.posture = mink.PostureTask(model, cost=np.sqrt(problem.w_posture), gain=problem.k_posture * dt)
        self.posture.set_target(problem.q_home)
        self.damping = mink.DampingTask(model, cost=np.sqrt(problem.w_damping))
        self.tasks = [self.task_c, self.task_g, self.posture, self.damping]

        peer = self

        class AccelerationLimit(mink.Limit):
            """|dq/dt - qdot_prev| <= a_max dt on every joint."""

            def __init__(self):
                n = model.nv
                self.G = np.vstack([np.eye(n), -np.eye(n)])

            def compute_qp_inequalities(self, configuration, dt):
                a_dt = problem.a_max * dt
                v = peer.qdot_prev
                return mink.Constraint(G=self.G, h=np.concatenate([dt * (v + a_dt), -dt * (v - a_dt)]))

        self.qdot_prev = np.zeros(problem.nq)
        self.limits = [
            mink.ConfigurationLimit(model, gain=1.0),
            mink.VelocityLimit(model, {n: problem.v_max for n in names}),
            AccelerationLimit(),
        ]
        self.n_pairs = 0
        if collision:
            pairs = [([a], [b]) for a, b in problem.collision_pairs()]
            limit = mink.CollisionAvoidanceLimit(
                model,
                pairs,
                gain=problem.xi * dt * dt / (problem.d_influence - problem.d_safe),
                minimum_distance_from_collisions=problem.d_safe,
                collision_detection_distance=problem.d_influence,
            )
            self.n_pairs = len(limit.geom_id_pairs)
            self.limits.append(limit)

    def _target_pose(self, sid: int, v: np.ndarray):
        """exp(V dt) T(q) for a site: position + v dt, rotation exp(w dt) R (= R exp(R^T w dt))."""
        mujoco, data, dt = self.mujoco, self.configuration.data, self.dt
        target = np.empty(7)  # wxyz_xyz
        xmat = data.site_xmat[sid]
        mujoco.mju_mat2Quat(target[:4], xmat)
        mujoco.mju_quatIntegrate(target[:4], xmat.reshape(3, 3).T @ v[3:], dt)
        target[4:] = data.site_xpos[sid] + v[:3] * dt
        return self.mink.SE3(wxyz_xyz=target)

    def step(self, q: np.ndarray, t: float) -> np.ndarray:
        self.configuration.update(q)
        v_c, v_g = self.problem.twists(t)
        self.task_c.set_target(self._target_pose(self.sid_c, v_c))
        self.task_g.set_target(self._target_pose(self.sid_g, v_g))
        qdot = self.mink.solve_ik(self.configuration, self.tasks, self.dt, "daqp", limits=self.limits)
        self.qdot_prev = qdot
        return qdot


def setup_mink(problem: BenchProblem, collision: bool) -> MinkPeer:
    return MinkPeer(problem, collision)


# ---------------------------------------------------------------------------------------------
# pink
# ---------------------------------------------------------------------------------------------


class PinkPeer:
    """pink ``solve_ik`` (qpsolvers + daqp) on the dual-UR5e URDF (pinocchio)."""

    name = "pink"

    def __init__(self, problem: BenchProblem, collision: bool):
        import pink
        import pinocchio as pin
        from pink.barriers import SelfCollisionBarrier
        from pink.limits import AccelerationLimit, ConfigurationLimit, VelocityLimit
        from pink.tasks import DampingTask, FrameTask, PostureTask

        self.pin = pin
        self.pink = pink
        self.problem = problem
        self.dt = dt = problem.dt
        self.collision = collision
        model = pin.buildModelFromUrdf(str(problem.urdf_path))
        names = problem.joint_names()
        idx_q = [model.joints[model.getJointId(n)].idx_q for n in names]
        if idx_q != list(range(problem.nq)) or model.nq != problem.nq:
            raise RuntimeError(f"unexpected pinocchio joint layout {idx_q}")
        model.velocityLimit[:] = problem.v_max
        self.model = model
        data = model.createData()
        self.n_pairs = 0
        if collision:
            gm, _ = build_pinocchio_collision_model(model, problem)
            self.n_pairs = len(gm.collisionPairs)
            self.configuration = pink.Configuration(model, data, problem.q0.copy(), collision_model=gm)
        else:
            self.configuration = pink.Configuration(model, data, problem.q0.copy())

        cost_c, cost_g = float(np.sqrt(problem.w_camera)), float(np.sqrt(problem.w_gripper))
        self.task_c = FrameTask(CAMERA_FRAME, position_cost=cost_c, orientation_cost=[cost_c, cost_c, 0.0])
        self.task_g = FrameTask(GRIPPER_FRAME, position_cost=cost_g, orientation_cost=cost_g)
        self.posture = PostureTask(cost=float(np.sqrt(problem.w_posture)), gain=problem.k_posture * dt)
        self.posture.set_target(problem.q_home.copy())
        self.damping = DampingTask(cost=float(np.sqrt(problem.w_damping)))
        self.tasks = [self.task_c, self.task_g, self.posture, self.damping]
        self.acc = AccelerationLimit(model, np.full(model.nv, problem.a_max))
        self.limits = [ConfigurationLimit(model, config_limit_gain=1.0), VelocityLimit(model), self.acc]
        self.barriers = []
        if collision:
            self.barriers.append(
                SelfCollisionBarrier(
                    n_collision_pairs=self.n_pairs,
                    gain=problem.collision_gain,
                    safe_displacement_gain=0.0,
                    d_min=problem.d_safe,
                )
            )
        self.fid_c = model.getFrameId(CAMERA_FRAME)
        self.fid_g = model.getFrameId(GRIPPER_FRAME)
        self.qdot_prev = np.zeros(problem.nq)

    def _target_pose(self, fid: int, v: np.ndarray):
        pin, dt = self.pin, self.dt
        T = self.configuration.data.oMf[fid]
        return pin.SE3(pin.exp3(v[3:] * dt) @ T.rotation, T.translation + v[:3] * dt)

    def step(self, q: np.ndarray, t: float) -> np.ndarray:
        self.configuration.update(q)
        v_c, v_g = self.problem.twists(t)
        self.task_c.set_target(self._target_pose(self.fid_c, v_c))
        self.task_g.set_target(self._target_pose(self.fid_g, v_g))
        self.acc.set_last_integration(self.qdot_prev, self.dt)
        qdot = self.pink.solve_ik(
            self.configuration,
            self.tasks,
            self.dt,
            solver="daqp",
            limits=self.limits,
            barriers=self.barriers or None,
            safety_break=False,
        )
        self.qdot_prev = qdot
        return qdot


def setup_pink(problem: BenchProblem, collision: bool) -> PinkPeer:
    return PinkPeer(problem, collision)


# ---------------------------------------------------------------------------------------------
# Timing and checks
# ---------------------------------------------------------------------------------------------


def time_step(fn: Callable[[], object], n_warmup: int, n: int, after: Callable | None = None) -> float:
    """Median wall time [us] of ``fn()`` over ``n`` calls after ``n_warmup`` untimed ones.

    ``after(result)``, if given, runs after each call outside the timed region
    (e.g. to integrate the closed loop).
    """
    clock = time.perf_counter_ns
    for _ in range(n_warmup):
        result = fn()
        if after is not None:
            after(result)
    samples = np.empty(n)
    for i in range(n):
        t0 = clock()
        result = fn()
        samples[i] = clock() - t0
        if after is not None:
            after(result)
    return float(np.median(samples)) * 1e-3


def time_closed_loop(
    step: Callable[[np.ndarray, float], np.ndarray], problem: BenchProblem, n_warmup: int = 100, n: int = 2000
) -> float:
    """Median [us] of ``step(q, t)`` in closed loop from ``problem.q0`` (q += qdot dt, t += dt)."""
    state = {"q": problem.q0.copy(), "t": 0.0}

    def call():
        return step(state["q"], state["t"])

    def advance(qdot):
        state["q"] = state["q"] + np.asarray(qdot) * problem.dt
        state["t"] += problem.dt

    return time_step(call, n_warmup, n, advance)


def check_closed_loop(
    step: Callable[[np.ndarray, float], np.ndarray],
    problem: BenchProblem,
    n_steps: int = 200,
    evaluator: Evaluator | None = None,
) -> dict:
    """Run ``n_steps`` closed-loop steps from ``problem.q0`` and measure what came out.

    Returns finite (bool), twist tracking errors (RMS over steps of the norms of
    the linear [m/s] and angular [rad/s] error parts; camera angular part is the
    2-D one about the camera x, y axes), the largest joint speed and acceleration,
    and the smallest pair distance met [m].
    """
    ev = evaluator or Evaluator(problem)
    q = problem.q0.copy()
    qdot_prev = np.zeros_like(q)
    e_c = np.empty((n_steps, 5))
    e_g = np.empty((n_steps, 6))
    max_v = max_a = 0.0
    min_d = np.inf
    finite = True
    for k in range(n_steps):
        t = k * problem.dt
        qdot = np.asarray(step(q, t), dtype=float)
        if qdot.shape != q.shape or not np.all(np.isfinite(qdot)):
            finite = False
            break
        e_c[k], e_g[k] = ev.twist_errors(q, qdot, t)
        max_v = max(max_v, float(np.max(np.abs(qdot))))
        max_a = max(max_a, float(np.max(np.abs(qdot - qdot_prev))) / problem.dt)
        qdot_prev = qdot
        q = q + qdot * problem.dt
        min_d = min(min_d, float(ev.distances(q).min()))
    finite = finite and bool(np.all(np.isfinite(q)))

    def rms(x):
        return float(np.sqrt(np.mean(np.sum(x * x, axis=1)))) if finite else float("nan")

    return {
        "finite": finite,
        "steps": n_steps,
        "camera_lin_rms": rms(e_c[:, :3]),
        "camera_ang_rms": rms(e_c[:, 3:]),
        "gripper_lin_rms": rms(e_g[:, :3]),
        "gripper_ang_rms": rms(e_g[:, 3:]),
        "max_speed": max_v,
        "max_accel": max_a,
        "min_distance": min_d,
    }


PEERS: dict[str, Callable[[BenchProblem, bool], object]] = {
    "placo": setup_placo,
    "mink": setup_mink,
    "pink": setup_pink,
}


def run_peers(
    problem: BenchProblem | None = None,
    n: int = 2000,
    n_warmup: int = 100,
    n_check: int = 200,
    details: dict | None = None,
    verbose: bool = True,
    peers: tuple[str, ...] = ("placo", "mink", "pink"),
) -> dict:
    """Time every peer with and without collision avoidance.

    Returns ``{placo_us, placo_collision_us, mink_us, mink_collision_us, pink_us,
    pink_collision_us}`` (medians [us] of ``step``; None for a peer that could not
    be set up or failed). ``details``, if given, receives per-variant entries with
    the closed-loop check (:func:`check_closed_loop`), the pair count and the
    reason of a failure.
    """
    problem = problem or BenchProblem()
    evaluator = Evaluator(problem) if n_check else None
    results: dict = {}
    for name in peers:
        for collision in (False, True):
            key = f"{name}_collision_us" if collision else f"{name}_us"
            results[key] = None
            info: dict = {}
            if details is not None:
                details[key] = info
            try:
                peer = PEERS[name](problem, collision)
            except Exception as exc:  # noqa: BLE001 - report and skip a peer that cannot be set up
                info["error"] = f"setup failed: {type(exc).__name__}: {exc}"
                if verbose:
                    print(f"  {key}: skipped ({info['error']})")
                continue
            info["pairs"] = getattr(peer, "n_pairs", 0)
            try:
                if n_check:
                    info["check"] = check_closed_loop(peer.step, problem, n_check, evaluator)
                    peer = PEERS[name](problem, collision)  # fresh state for timing
                results[key] = time_closed_loop(peer.step, problem, n_warmup, n)
            except Exception as exc:  # noqa: BLE001 - report and skip a peer that fails while running
                info["error"] = f"run failed: {type(exc).__name__}: {exc}"
                if verbose:
                    print(f"  {key}: failed ({info['error']})")
                continue
            if verbose:
                print(format_result(key, results[key], info))
    return results


def format_result(key: str, median_us: float | None, info: dict) -> str:
    """One line: median, pair count and closed-loop check of a benchmark variant."""
    line = f"  {key:22s} " + ("     None   " if median_us is None else f"{median_us:9.1f} us")
    if info.get("pairs"):
        line += f"  pairs {info['pairs']}"
    check = info.get("check")
    if check:
        line += (
            f"  | {check['steps']} steps finite={check['finite']}"
            f" cam err {check['camera_lin_rms'] * 1e3:.2f} mm/s {check['camera_ang_rms'] * 1e3:.2f} mrad/s"
            f" grip err {check['gripper_lin_rms'] * 1e3:.2f} mm/s {check['gripper_ang_rms'] * 1e3:.2f} mrad/s"
            f" |qd|max {check['max_speed']:.2f} |qdd|max {check['max_accel']:.1f}"
            f" dmin {check['min_distance'] * 1e3:.1f} mm"
        )
    if info.get("error"):
        line += f"  ({info['error']})"
    return line


def describe_problem(problem: BenchProblem) -> str:
    """A few lines summarising the problem (pair count, active pairs at q0)."""
    pairs = problem.collision_pairs()
    n_self = len(desc.self_collision_pairs())
    ev = Evaluator(problem)
    d0 = ev.distances(problem.q0)
    return (
        f"dual UR5e, 12 joints, dt = {problem.dt * 1e3:.0f} ms; collision pairs: {len(pairs)} "
        f"({n_self} robot-robot + {len(pairs) - n_self} arm-obstacle, {len(problem.obstacles)} spheres); "
        f"at q0: {int(np.sum(d0 < problem.d_influence))} pairs within d_i = {problem.d_influence} m, "
        f"closest {d0.min() * 1e3:.1f} mm"
    )


def main(argv: list[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-n", type=int, default=2000, help="timed steps per peer")
    parser.add_argument("--check", type=int, default=200, help="closed-loop check steps (0: none)")
    parser.add_argument("--peers", default="placo,mink,pink", help="comma-separated subset")
    parser.add_argument(
        "--obstacle-min-link",
        type=int,
        default=1,
        help="arm capsules checked against obstacles: link index >= this (1: all, 222 pairs; 3: 190)",
    )
    parser.add_argument("--differences", action="store_true", help="print the setup differences")
    args = parser.parse_args(argv)
    problem = BenchProblem(obstacle_min_link_index=args.obstacle_min_link)
    print(describe_problem(problem))
    if args.differences:
        for who, lines in DIFFERENCES.items():
            print(f"differences ({who}):")
            for line in lines:
                print(f"  - {line}")
    details: dict = {}
    results = run_peers(
        problem,
        n=args.n,
        n_check=args.check,
        details=details,
        peers=tuple(p for p in args.peers.split(",") if p),
    )
    import json

    print(json.dumps({k: (None if v is None else round(v, 2)) for k, v in results.items()}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
