"""The simulated dual-UR5e lab: :class:`SimRobot` implements :class:`~harvest_qp.runtime.interface.RobotInterface`.

One control period (2 ms by default) applies the held joint-velocity command through the
``speedj``-like servos (:mod:`harvest_qp.sim.actuation`), integrates the physics, samples
the wrist F/T sensor and, every 1/30 s, captures a camera frame. The state is only ever
changed through the actuators, so the force sensor reads the true interaction force.

At :meth:`SimRobot.reset` the robot starts at ``HOME_Q`` holding the cluster (the paper's
initial state): the grasp weld is activated at the current gripper-cluster pose, the arms
hold still for ``settle_time`` while the scene comes to rest, and the stem's springs are
then re-zeroed so the stem starts unloaded (the gripper carries the cluster) before the
clock is set to 0.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections import deque
from dataclasses import dataclass

import mujoco
import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import HarvestQPError, InvalidInputError
from harvest_qp.robot import description as desc
from harvest_qp.runtime.interface import N_JOINTS, ROBOT, PointCloud, RobotInterface
from harvest_qp.sim.actuation import ActuationConfig, SpeedjServo
from harvest_qp.sim.camera import DEFAULT_CAMERA, CameraConfig, DepthCamera, make_camera
from harvest_qp.sim.contacts import CONTACT_KINDS, ContactMonitor
from harvest_qp.sim.force import ForceSensorConfig, WristForceSensor
from harvest_qp.sim.scene import CAMERA_NAME, VineScene, VineSceneParams, build_vine_scene
from harvest_qp.validation import as_positive_scalar, check_field_types

__all__ = ["SensorFaults", "SimRobot", "SimulationError"]


class SimulationError(HarvestQPError):
    """The physics diverged (MuJoCo warned about bad accelerations or state values)."""


@dataclass(frozen=True)
class SensorFaults:
    """Sensor faults of the simulated robot (all seeded by the robot's ``seed``).

    Attributes:
        frame_loss: probability that a whole camera frame is lost (never delivered).
        frame_latency: delay from capture to delivery of a camera frame [s]; None keeps
            the camera's own ``CameraConfig.latency``.
        force_noise_std: white noise std on each wrist force component [N]; None keeps
            the sensor's own ``ForceSensorConfig.noise_std``.
    """

    frame_loss: float = 0.0
    frame_latency: float | None = None
    force_noise_std: float | None = None

    def __post_init__(self) -> None:
        check_field_types(self)  # text, None or a list never reaches the range checks
        if not isinstance(self.frame_loss, (int, float, np.floating)) or not 0.0 <= self.frame_loss < 1.0:
            raise InvalidInputError(f"SensorFaults.frame_loss must be a probability in [0, 1), got {self.frame_loss!r}")
        for name in ("frame_latency", "force_noise_std"):
            value = getattr(self, name)
            if value is not None and (
                not isinstance(value, (int, float, np.floating)) or not np.isfinite(value) or value < 0
            ):
                raise InvalidInputError(f"SensorFaults.{name} must be None or a finite number >= 0, got {value!r}")


class SimRobot(RobotInterface):
    """MuJoCo simulation of the dual-UR5e in the vine scene.

    Args:
        scene: a built :class:`VineScene`, or parameters to build one (default: the
            paper's setup, ``VineSceneParams()``).
        seed: seed of the sensor noise (camera and force).
        camera: camera settings (default: the paper's D415 setup, :data:`DEFAULT_CAMERA`),
            or None for no camera (faster).
        force: wrist F/T sensor settings.
        actuation: servo settings; the servo gains come from the scene's model, so
            ``bandwidth`` and ``damping_ratio`` only apply when the scene is built here.
        control_period: control cycle [s], a multiple of the physics timestep (2 ms).
        payload_compensation: compensate the held cluster's weight in the grasping arm's
            joint torques, as a UR5e does with its configured payload.
        settle_time: time the scene settles at reset before the clock starts [s].
        faults: sensor faults (lost camera frames, frame latency, force noise).
        vine_distance_every: :meth:`ground_truth` measures ``min_vine_distance`` on every
            this many control ticks and repeats the last value in between (capsule
            bounds of every arm-vine pair, then MuJoCo's distance for the few whose bound
            beats the best: :class:`~harvest_qp.sim.contacts.ContactMonitor`).

    The model's physics options (``model.opt.timestep`` among them), the servo's limits and
    the substep count are read when the robot is built: build a new robot to change them.
    Every physics step runs MuJoCo's full collision detection (``mj_step``'s own), so
    editing ``model``'s collision geometry between steps is honoured at once.
    """

    def __init__(
        self,
        scene: VineScene | VineSceneParams | None = None,
        *,
        seed: int = 0,
        camera: CameraConfig | None = DEFAULT_CAMERA,
        force: ForceSensorConfig | None = None,
        actuation: ActuationConfig | None = None,
        control_period: float = 0.002,
        payload_compensation: bool = True,
        settle_time: float = 0.2,
        faults: SensorFaults | None = None,
        vine_distance_every: int = 1,
    ) -> None:
        for name, value, kind in (("actuation", actuation, ActuationConfig), ("force", force, ForceSensorConfig)):
            if value is not None and not isinstance(value, kind):
                raise InvalidInputError(f"{name} must be a {kind.__name__} or None, got {value!r}")
        control_period = as_positive_scalar(control_period, "control_period")
        settle_time = as_positive_scalar(settle_time, "settle_time", allow_zero=True)
        if not isinstance(payload_compensation, (bool, np.bool_)):
            raise InvalidInputError(f"payload_compensation must be True or False, got {payload_compensation!r}")
        if scene is None or isinstance(scene, VineSceneParams):
            scene = build_vine_scene(scene, actuation=actuation)
        if not isinstance(scene, VineScene):
            raise InvalidInputError(f"scene must be a VineScene or VineSceneParams, got {type(scene).__name__}")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise InvalidInputError(f"seed must be a non-negative integer, got {seed!r}")
        if camera is not None and not isinstance(camera, CameraConfig):
            raise InvalidInputError(f"camera must be a CameraConfig or None, got {type(camera).__name__}")
        if not np.isfinite(settle_time) or settle_time < 0:
            raise InvalidInputError(f"settle_time must be >= 0 [s], got {settle_time!r}")
        if faults is not None and not isinstance(faults, SensorFaults):
            raise InvalidInputError(f"faults must be a SensorFaults or None, got {type(faults).__name__}")
        if (
            isinstance(vine_distance_every, bool)
            or not isinstance(vine_distance_every, (int, np.integer))
            or (vine_distance_every < 1)
        ):
            raise InvalidInputError(f"vine_distance_every must be an integer >= 1, got {vine_distance_every!r}")
        self.faults = faults if faults is not None else SensorFaults()
        self.vine_distance_every = int(vine_distance_every)
        if camera is not None and self.faults.frame_latency is not None:
            camera = dataclasses.replace(camera, latency=float(self.faults.frame_latency))
        force = force if force is not None else ForceSensorConfig()
        if self.faults.force_noise_std is not None:
            force = dataclasses.replace(force, noise_std=float(self.faults.force_noise_std))
        self.scene = scene
        # A private copy: reset() edits the model (weld pose, stem spring rest values), so
        # robots built from the same scene must not share it.
        self.model = copy.deepcopy(scene.model)
        self.data = mujoco.MjData(self.model)
        self.seed = int(seed)
        m = self.model
        dt = float(m.opt.timestep)
        substeps = control_period / dt
        if not np.isfinite(control_period) or control_period <= 0 or abs(substeps - round(substeps)) > 1e-9:
            raise InvalidInputError(
                f"control_period must be a positive multiple of the physics timestep {dt} s, got {control_period!r}"
            )
        self.control_period = float(control_period)
        self._substeps = int(round(substeps))
        self._timestep = dt
        self.payload_compensation = bool(payload_compensation)
        self.settle_time = float(settle_time)

        names = desc.joint_names()
        joint_ids = np.array([m.joint(n).id for n in names])
        self._qpos_ids = m.jnt_qposadr[joint_ids].copy()
        self._dof_ids = m.jnt_dofadr[joint_ids].copy()
        act_ids = np.array([m.actuator(n).id for n in scene.actuator_names])
        self._servo = SpeedjServo(m, act_ids, self._qpos_ids, actuation if actuation is not None else ActuationConfig())
        self._kp = m.actuator_gainprm[act_ids, 0].astype(float)
        ids = scene.ids
        self._ids = ids
        self._force = WristForceSensor(
            m, ids["ft_force"], ids["ft_site"], float(m.body_mass[ids["grasp_tool"]]),
            force, seed=self.seed,
        )  # fmt: skip
        self.camera_config = camera
        self._camera: DepthCamera | None = None
        if camera is not None:
            self._camera = make_camera(
                m, camera, geom_labels=scene.geom_labels, exclude_body=ids["cam_tool"], camera=CAMERA_NAME,
                seed=self.seed,
            )  # fmt: skip
        base = m.body(desc.collision_bodies()[0].link).id
        robot_geoms = np.flatnonzero(scene.geom_labels == ROBOT)
        floor = [g for g in range(m.ngeom) if m.geom(g).name == "floor"]
        self._contacts = ContactMonitor(
            m, arm_geoms=robot_geoms[m.geom_bodyid[robot_geoms] != base],
            stand_geoms=robot_geoms[m.geom_bodyid[robot_geoms] == base], vine_geoms=scene.vine_geoms,
            floor_geoms=np.array(floor, dtype=np.int64),
            wood_geoms=np.array([m.geom(name).id for name in ("branch", "cane")], dtype=np.int64),
            crop_geoms=np.flatnonzero(m.geom_bodyid == m.body("cluster").id),
        )  # fmt: skip
        slide = ids["stem_slide"]
        self._slide_dof = int(m.jnt_dofadr[slide])
        self._slide_stiffness = float(m.jnt_stiffness[slide])
        self._slide_damping = float(m.dof_damping[self._slide_dof])
        self._stem_force_sensor = int(ids["stem_force"])
        self._stem_end_site = int(ids["stem_end_site"])
        self._stem_base = np.array(scene.stem_base, dtype=float)
        self._spring0 = m.qpos_spring.copy()
        self._stem_qpos = self._stem_spring_addresses()
        self._jacp = np.zeros((3, m.nv))
        self._cluster = int(ids["cluster"])
        self._grasp_tool = int(ids["grasp_tool"])
        self._grasp_dofs = self._dof_ids[6:].astype(np.int64)
        self._grasp_ctrl = np.ascontiguousarray(self._servo.ctrl_ids[6:], dtype=np.int64)
        self._grasp_kp = np.ascontiguousarray(self._kp[6:])
        self._viewer = None
        self._viewer_every = 16
        # Live views of the MjData arrays every physics step reads (MjData allocates them once
        # and never moves them; each ``data.x`` builds a new view, ~1-3 us apiece with the
        # caches the rest of the control loop leaves).
        d = self.data
        self._qpos, self._qvel, self._ctrl = d.qpos, d.qvel, d.ctrl
        self._warning_counts = d.warning.number
        self._cluster_com = d.xipos[self._cluster]
        adr = int(m.sensor_adr[self._stem_force_sensor])
        self._stem_rotation = d.site_xmat[self._stem_end_site].reshape(3, 3)
        self._stem_sensor = d.sensordata[adr : adr + 3]
        self._stem_end = d.site_xpos[self._stem_end_site]
        self.reset()

    # ------------------------------------------------------------------ setup

    def _stem_spring_addresses(self) -> NDArray[np.int64]:
        """qpos addresses of the stem and cluster joints, whose springs are re-zeroed at reset."""
        m = self.model
        addrs: list[int] = []
        for j in range(m.njnt):
            name = m.joint(j).name
            if name.startswith("stem_") or name == "cluster_ball":
                n = {int(mujoco.mjtJoint.mjJNT_BALL): 4, int(mujoco.mjtJoint.mjJNT_SLIDE): 1}[int(m.jnt_type[j])]
                addrs.extend(range(m.jnt_qposadr[j], m.jnt_qposadr[j] + n))
        return np.array(addrs, dtype=np.int64)

    def reset(self, *, seed: int | None = None) -> None:
        """Restart the episode: robot at ``home_q`` holding the cluster, clock at 0.

        Args:
            seed: new seed of the sensor noise (default: keep the current one).
        """
        if seed is not None:
            if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
                raise InvalidInputError(f"seed must be a non-negative integer, got {seed!r}")
            self.seed = int(seed)
        m, d = self.model, self.data
        m.qpos_spring[:] = self._spring0
        # A torn stem from the last episode grows back.
        m.jnt_stiffness[self._ids["stem_slide"]] = self._slide_stiffness
        m.dof_damping[self._slide_dof] = self._slide_damping
        self._torn = False
        self._tear_time = float("nan")
        self._max_tension = 0.0
        mujoco.mj_resetData(m, d)
        d.qpos[self._qpos_ids] = self.scene.home_q
        mujoco.mj_forward(m, d)
        self._servo.reset(self.scene.home_q)
        self.set_grasp(True)
        self._ticks = 0
        self._settled = False
        self._failed = False
        self._warnings = np.asarray(d.warning.number, dtype=np.int64).copy()
        # The held cluster's weight [N, world] (model constants; read again at every reset).
        self._payload_weight = m.body_mass[self._cluster] * np.asarray(m.opt.gravity)
        settle = int(round(self.settle_time / m.opt.timestep))
        mujoco.mj_step1(m, d)
        for _ in range(settle // 2):
            self._physics_step()
        # Start with an unloaded stem (the gripper carries the cluster, as in the lab): zero
        # the stem's springs at the settled shape, then shift the axial spring's rest length
        # so it also carries the stem's own weight instead of the cluster.
        m.qpos_spring[self._stem_qpos] = d.qpos[self._stem_qpos]
        for _ in range(settle // 4):
            self._physics_step()
        slide = self._ids["stem_slide"]
        m.qpos_spring[m.jnt_qposadr[slide]] += self.stem_tension() / m.jnt_stiffness[slide]
        for _ in range(settle - settle // 2 - settle // 4):
            self._physics_step()
        self._check_physics()
        self._settled = True
        d.time = 0.0
        self._force.reset(seed=self.seed)
        self._force.update(d, self.control_period)
        self._frames: deque[tuple[float, PointCloud]] = deque()
        self._next_frame_tick = 0
        self._frames_lost = 0
        self._frame_rng = np.random.default_rng([self.seed, 0xF7A3E])
        self._vine_distance_tick = -1
        self._vine_distance = (float("inf"), -1, -1)
        self._min_vine_distance = float("inf")
        self._contact_ticks = dict.fromkeys(CONTACT_KINDS, 0)
        self._counted_tick = -1
        if self._camera is not None:
            self._camera.reset(seed=self.seed)
            self._maybe_capture()

    # ------------------------------------------------------------------ RobotInterface

    @property
    def time(self) -> float:
        """Simulated time since the reset [s]."""
        return self._ticks * self.control_period

    def joint_positions(self) -> NDArray[np.float64]:
        return self._qpos[self._qpos_ids]  # fancy indexing copies

    def joint_velocities(self) -> NDArray[np.float64]:
        return self._qvel[self._dof_ids]

    def wrist_force(self) -> NDArray[np.float64]:
        return self._force.reading()

    def tare_force(self) -> None:
        self._force.tare()

    def camera_cloud(self) -> PointCloud | None:
        latest = None
        frames = self._frames
        now = self.time
        while frames and frames[0][0] <= now + 1e-12:
            latest = frames.popleft()[1]
        return latest

    def send_joint_velocities(self, qdot: ArrayLike) -> None:
        self._servo.command(qdot)

    def step(self) -> None:
        if self._failed:
            raise SimulationError("the simulation diverged earlier; call reset() to start again")
        for _ in range(self._substeps):
            self._physics_step()
            self._check_tear()  # every physics step: the tension may not overshoot for a whole tick
        self._check_physics()
        self._ticks += 1
        self._force.sample(self.data, self.control_period)
        if self._camera is not None and self._ticks >= self._next_frame_tick:
            self._maybe_capture()
        if self._viewer is not None and self._ticks % self._viewer_every == 0:
            self._viewer.sync()

    def stop(self) -> None:
        """Ramp the commands to zero within the acceleration limits and wait until at rest.

        Advances the simulated time by the ramp (at most ``max_velocity / max_acceleration``)
        plus up to 0.2 s for the joints to settle.
        """
        if self._failed:
            return  # nothing left to stop: MuJoCo has reset the diverged state
        self._servo.command(np.zeros(N_JOINTS))
        limit = int(np.ceil(self._servo.config.max_velocity / self._servo.acc_limit.min() / self.control_period)) + 2
        for _ in range(limit):
            if self._servo.at_rest():
                break
            self.step()
        for _ in range(int(0.2 / self.control_period)):
            if np.max(np.abs(self.joint_velocities())) < 1e-3:
                break
            self.step()

    # ------------------------------------------------------------------ simulation extras

    def set_grasp(self, active: bool) -> None:
        """Hold (weld at the current relative pose) or release the cluster.

        The payload compensation follows the grasp, as when a UR5e's payload is updated.
        """
        m, d = self.model, self.data
        eq = self._ids["weld"]
        if active:
            b1, b2 = m.eq_obj1id[eq], m.eq_obj2id[eq]
            R1 = d.xmat[b1].reshape(3, 3)
            # Weld data: anchor, relative position R1^T (x2 - x1), relative quat q1^-1 q2.
            m.eq_data[eq, 0:3] = 0.0
            m.eq_data[eq, 3:6] = R1.T @ (d.xpos[b2] - d.xpos[b1])
            q1inv = np.zeros(4)
            mujoco.mju_negQuat(q1inv, d.xquat[b1])
            mujoco.mju_mulQuat(m.eq_data[eq, 6:10], q1inv, d.xquat[b2])
            m.eq_data[eq, 10] = 1.0
        d.eq_active[eq] = 1 if active else 0
        self._holding = bool(active)

    @property
    def holding(self) -> bool:
        """True while the grasp weld is active."""
        return self._holding

    def stem_force(self) -> NDArray[np.float64]:
        """True force the stem applies to the cluster [N, world] (ground truth, not measurable)."""
        return self._stem_rotation @ self._stem_sensor  # site_force_world on views bound once

    def stem_tension(self) -> float:
        """True stem tension [N]: magnitude of :meth:`stem_force`, negative if it pushes the cluster away."""
        return _signed_tension(self._stem_rotation, self._stem_sensor, self._stem_end, self._stem_base)

    def site_pose(self, name: str) -> NDArray[np.float64]:
        """World pose (4x4) of a site, e.g. ``"camera"``, ``"gripper"``, ``"cutter_tip"``."""
        try:
            sid = self.model.site(name).id
        except KeyError:
            names = [self.model.site(i).name for i in range(self.model.nsite)]
            raise InvalidInputError(f"unknown site {name!r}; valid names: {names}") from None
        T = np.eye(4)
        T[:3, :3] = self.data.site_xmat[sid].reshape(3, 3)
        T[:3, 3] = self.data.site_xpos[sid]
        return T

    def velocity_reference(self) -> NDArray[np.float64]:
        """The acceleration-limited joint velocity reference being tracked (12,) [rad/s]."""
        return self._servo.qd_ref.copy()

    def capture_cloud(self) -> PointCloud:
        """Capture a camera frame now, outside the frame schedule (for tests and tools)."""
        if self._camera is None:
            raise InvalidInputError("this SimRobot has no camera (camera=None)")
        return self._camera.capture(self.data, self.site_pose("camera"), self.time)

    def ground_truth(self) -> dict[str, float | NDArray[np.float64]]:
        """Quantities a real robot cannot measure, for logs and tests (one value per key per tick).

        Keys:
            stem_tension: true stem tension [N] (:meth:`stem_tension`; ~0 once torn).
            stem_force: (3,) true force of the stem on the cluster [N, world].
            qdot_ref: (12,) the servo's acceleration-limited velocity reference [rad/s].
            stem_torn: 1.0 once the stem tension exceeded the scene's ``stem_break_force``
                (the stem tore: its axial spring is released), else 0.0.
            stem_tension_max: largest stem tension since the reset [N].
            contacts_arm_arm, contacts_arm_vine, contacts_arm_stand, contacts_arm_floor,
            contacts_crop_wood, contacts_crop_leaf: active contacts of each kind now, the robot's
                and the held crop's (see :mod:`harvest_qp.sim.contacts`).
            min_vine_distance: smallest true distance between a robot geom and a vine geom
                other than the held stem and cluster [m] (negative: penetration), measured
                every ``vine_distance_every`` ticks.
            min_vine_distance_so_far: smallest ``min_vine_distance`` measured since the reset [m].
            frames_lost: camera frames lost to ``faults.frame_loss`` since the reset.
        """
        out: dict[str, float | NDArray[np.float64]] = {
            "stem_tension": self.stem_tension(),
            "stem_force": self.stem_force(),
            "qdot_ref": self.velocity_reference(),
            "stem_torn": float(self._torn),
            "stem_tension_max": self._max_tension,
        }
        for kind, count in self.contact_counts().items():
            out[f"contacts_{kind}"] = float(count)
        out["min_vine_distance"] = self.min_vine_distance()
        out["min_vine_distance_so_far"] = self._min_vine_distance
        out["frames_lost"] = float(self._frames_lost)
        return out

    def contact_counts(self) -> dict[str, int]:
        """Active contacts by kind now (:data:`~harvest_qp.sim.contacts.CONTACT_KINDS`): the robot's and the
        held crop's."""
        return self._contacts.contact_counts(self.data)

    def min_vine_distance(self, *, with_pair: bool = False) -> float | tuple[float, str, str]:
        """Smallest true robot-vine distance [m] (held stem and cluster excluded), negative if penetrating.

        Measured at most once per tick, every ``vine_distance_every`` ticks (the last value
        in between).

        Args:
            with_pair: also return the names of the robot geom and the vine geom.
        """
        if self._vine_distance_tick < 0 or self._ticks - self._vine_distance_tick >= self.vine_distance_every:
            self._vine_distance = self._contacts.min_vine_distance(self.data)
            self._vine_distance_tick = self._ticks
            self._min_vine_distance = min(self._min_vine_distance, self._vine_distance[0])
        dist, ga, gv = self._vine_distance
        if not with_pair:
            return dist
        name = lambda g: self.model.geom(g).name if g >= 0 else ""  # noqa: E731
        return dist, name(ga), name(gv)

    @property
    def stem_torn(self) -> bool:
        """True once the stem has torn (tension above the scene's ``stem_break_force``)."""
        return self._torn

    @property
    def stem_tear_time(self) -> float:
        """Time of the tear [s] (NaN while intact)."""
        return self._tear_time

    @property
    def frames_lost(self) -> int:
        """Camera frames lost to ``faults.frame_loss`` since the reset."""
        return self._frames_lost

    # ------------------------------------------------------------------ internals

    def _physics_step(self) -> None:
        """One MuJoCo step of the servos and the physics: ``mj_step`` split in its two halves.

        step2 integrates with the forces of the current state; step1 then computes the new
        state's kinematics, sensors and contacts (MuJoCo's full collision detection) so
        every reading refers to the same instant.
        """
        m, d = self.model, self.data
        self._servo.step(self._qpos, self._ctrl, self._timestep)
        if self.payload_compensation and self._holding:
            # Like a UR5e's payload setting: hold the cluster's weight in the joint torques.
            # The weld keeps the cluster's centre of mass fixed on the tool.
            jacp = self._jacp
            mujoco.mj_jac(m, d, jacp, None, self._cluster_com, self._grasp_tool)
            _add_payload_torque(
                jacp, self._grasp_dofs, self._payload_weight, self._ctrl, self._grasp_ctrl, self._grasp_kp
            )  # fmt: skip
        mujoco.mj_step2(m, d)
        mujoco.mj_step1(m, d)

    def _check_tear(self) -> None:
        """Tear the stem when its tension exceeds the break force: release its axial spring."""
        if self._torn:
            return
        tension = self.stem_tension()
        self._max_tension = max(self._max_tension, tension)
        if tension > self.scene.params.stem_break_force:
            m = self.model
            # The stem's top joint then slides freely: the stem no longer holds the cluster.
            m.jnt_stiffness[self._ids["stem_slide"]] = 0.0
            m.dof_damping[self._slide_dof] = 0.0
            self._torn = True
            self._tear_time = self.time

    def _check_physics(self) -> None:
        counts = self._warning_counts
        if _diverged(counts, self._warnings, self._qvel):
            counts = np.asarray(counts, dtype=np.int64)
            new = [mujoco.mjtWarning(i).name for i in np.flatnonzero(counts > self._warnings)]
            self._warnings = counts
            self._failed = True
            when = f"t = {self.time:.3f} s" if self._settled else "while settling the scene at reset"
            raise SimulationError(f"the simulation became unstable {when} (MuJoCo warnings: {new})")

    def _maybe_capture(self) -> None:
        if self._camera is None or self._ticks < self._next_frame_tick:
            return
        t = self.time
        # Draw for every frame, so the loss pattern only depends on the seed and the frame count.
        lost = self._frame_rng.random() < self.faults.frame_loss
        if lost:
            self._frames_lost += 1
        else:
            cloud = self._camera.capture(self.data, self.site_pose("camera"), t)
            self._frames.append((t + self._camera.config.latency, cloud))
        # Frame instants on the control grid closest to k / rate (33.3 ms -> 16-17 ticks).
        k = round(t * self._camera.config.rate) + 1
        self._next_frame_tick = max(self._ticks + 1, int(round(k / self._camera.config.rate / self.control_period)))

    def open_viewer(self, *, sync_every: int = 16) -> None:
        """Show the simulation in MuJoCo's passive viewer (needs a display; headless otherwise).

        Args:
            sync_every: redraw every this many control ticks (16 ticks = 32 ms, ~30 FPS).
        """
        try:
            import mujoco.viewer

            self._viewer = mujoco.viewer.launch_passive(self.model, self.data)
        except Exception as error:  # no display, or macOS without mjpython
            raise HarvestQPError(f"cannot open the MuJoCo viewer: {error}") from error
        self._viewer_every = max(1, int(sync_every))

    def close_viewer(self) -> None:
        """Close the viewer opened by :meth:`open_viewer`, if any."""
        if self._viewer is not None:
            self._viewer.close()
            self._viewer = None

    @property
    def mujoco_warnings(self) -> dict[str, int]:
        """MuJoCo warning counts since the last reset."""
        return {mujoco.mjtWarning(i).name: int(w.number) for i, w in enumerate(self.data.warning)}


def uses_own_ground_truth(robot: object) -> bool:
    """True when ``robot`` is a SimRobot whose ``ground_truth`` is this module's own (not
    overridden on a subclass, patched on SimRobot or set on the instance): it returns a new
    dict per call."""
    return (
        isinstance(robot, SimRobot)
        and type(robot).ground_truth is _OWN_GROUND_TRUTH
        and "ground_truth" not in vars(robot)
    )


_OWN_GROUND_TRUTH = SimRobot.ground_truth


@njit(cache=True)
def _signed_tension(rotation, sensor, end, base):
    """|R f| [N], positive when the world force R f on the cluster points from the stem end towards its base."""
    tension = 0.0
    along = 0.0
    for r in range(3):
        f = rotation[r, 0] * sensor[0] + rotation[r, 1] * sensor[1] + rotation[r, 2] * sensor[2]
        tension += f * f
        along += f * (base[r] - end[r])
    tension = math.sqrt(tension)
    return tension if along >= 0.0 else -tension


@njit(cache=True)
def _add_payload_torque(jacp, dofs, weight, ctrl, ctrl_ids, kp):
    """ctrl[ctrl_ids] += (-J[:, dofs]^T weight) / kp: a held payload's weight in the joint torques."""
    for j in range(dofs.shape[0]):
        tau = 0.0
        for k in range(3):
            tau += -jacp[k, dofs[j]] * weight[k]
        ctrl[ctrl_ids[j]] += tau / kp[j]


@njit(cache=True)
def _diverged(counts, previous, qvel):
    """True when MuJoCo raised a new warning or a joint velocity is not finite."""
    for i in range(counts.shape[0]):
        if counts[i] > previous[i]:
            return True
    for i in range(qvel.shape[0]):
        if not np.isfinite(qvel[i]):
            return True
    return False
