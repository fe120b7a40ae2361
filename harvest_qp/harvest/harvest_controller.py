"""The paper's closed loop (Section ``sec:contr``) as one controller for the episode runner.

Data flow, every control tick (2 ms)::

    camera frame (new?) -> perception: S, O, p_sb, (at the switch) p_gd, F
                        -> reference laws (harvest_qp.references): V_cr, V_cu, V_g, feed-forward
                        -> QP task references (5-D camera twist, 6-D gripper twist, roll)
                        -> TaskController (or the paper's pseudo-inverse) -> qdot

:class:`HarvestController` only reads what a real dual UR5e gives (joint positions and
velocities, the wrist force, the camera's labelled cloud and the clock, all from the
:class:`~harvest_qp.runtime.runner.Observation`); it never sees the simulator's ground truth and
keeps no robot handle, so the same object can drive two real arms.

Phases (``subsec:biman_coord``, :mod:`harvest_qp.harvest.phases`): ``approach`` (camera arm
reaches and unveils; the grasping arm holds the crop still) -> ``bimanual`` (V_g of
``eq:superimp_g`` on the grasping arm, V_c' of ``eq:final_vc`` on the camera arm) -> ``precut``
(force, projected position error and alignment within tolerance for ``precut.hold_time``;
control continues), or ``abort`` (force above the limit, stem not seen, no stem found, QP
failures in a row), which brings the arms to rest within the acceleration limit and logs the reason.

Where this differs from the paper (lab measurements):

* p_sb is refitted on every frame of the approach (the ROI centre follows it through the
  reaching filter), recomputed on the frame at the switch and then frozen. The paper
  identifies it "only once at the start"; the first fit there is 22-41 mm off (13-20
  points at 0.57 m), while refit-then-freeze gave 2.4-2.7 mm; refitting during the
  bimanual phase drifted 49 mm. Each fit's p_sb is moved up its top axis to the highest stem
  point seen from close range over the approach (``perception.stem_memory``,
  :mod:`harvest_qp.perception.stem_memory`): as the camera rose, the branch came to hide the
  stem's top, and the frozen p_sb lay 12-51 mm down the stem on six of 613 sweep scenes.
* The ROI centre is the gripper point (the grasped crop, known from the kinematics) until a
  stem base is found.
* The camera's free roll is used by a lower-priority task that turns the cutter (the
  camera's x axis, along which the blade closes) across the stem.
* p_gd is map-aware (``grasping.swing_clearance``): among the free samples of
  ``eq:attr_point`` within ``grasping.max_swing_deg`` of the stem and below p_sb, only those
  whose swing keeps the grasping arm (gripper, wrist, forearm) 2 cm plus the map's short bias
  from every mapped cell are used; when none does, the arm pulls along the stem itself
  (:func:`~harvest_qp.perception.grasp_target.choose_grasp_target`). Measured before it
  (283x160): on seeds 1 and 5 the gripper swung the crop into the occluding leaf; on held-out
  scenes earlier fallbacks picked targets 55-167 deg off the stem.
* The gripper's turn (``eq:rot_contr``) is a task one level below its translation
  (``qp.alignment_task``): force and position along n_c win when V_g cannot be met whole; a
  motion along n_c the QP does not execute holds the force integral; a translation it does not
  execute for ``safety.unexecuted_timeout`` before pre-cut aborts with that reason.
* The switch rule uses the camera's mean speeds over ``switch.window`` (0.5 s)
  (:mod:`harvest_qp.harvest.phases`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from harvest_qp.config import EpisodeConfig, build_limit, check_settings
from harvest_qp.configuration import Configuration
from harvest_qp.exceptions import ConfigError, HarvestQPError, InvalidInputError
from harvest_qp.harvest.phases import Phase, PhaseMachine, PhaseRules
from harvest_qp.limits import CollisionAvoidance, JointAccelerationLimit
from harvest_qp.perception import StemTopMemory, compute_free_space, fit_stem, obstacles_near_stem_base
from harvest_qp.perception.cloud_split import LabelledFrame as _Frame  # _State.frame
from harvest_qp.perception.cloud_split import obstacle_sphere_centres, outside_held_cluster
from harvest_qp.perception.grasp_target import (
    ARM_SWING_CAPSULES,
    SWING_CAPSULES,
    ArmCapsule,
    SwingCheck,
    arm_capsule_motion,
    choose_grasp_target,
)
from harvest_qp.pinv import PseudoInverseMapper
from harvest_qp.references import (
    GraspFeedForward,
    HoldPose,
    LookAround,
    ReachingCentering,
    StemStretching,
    Unveiling,
    keep_out_velocity,
    predicted_stem_points,
    roll_reference,
)
from harvest_qp.runtime.interface import PointCloud, RobotInterface
from harvest_qp.runtime.log import PairColumns, ValueLayout, ValueRow
from harvest_qp.runtime.runner import Command, Observation
from harvest_qp.task_controller import TaskController
from harvest_qp.tasks import DampingTask, FrameTwistTask, PostureTask

__all__ = ["Phase", "HarvestController", "FrameSnapshot", "SwitchSnapshot"]


@dataclass
class FrameSnapshot:
    """A camera frame kept for the figures (what the controller saw, labels included)."""

    time: float
    pixels: np.ndarray
    labels: np.ndarray
    image_size: tuple[int, int]
    depth: np.ndarray


@dataclass
class SwitchSnapshot:
    """The perception of the frame at the switch (Fig. ``fig:PC_proc``'s panels)."""

    time: float
    camera_pose: np.ndarray
    stem_points: np.ndarray
    non_stem_points: np.ndarray
    stem: Any  # perception.StemModel
    grasp_obstacles: np.ndarray
    free_space: Any  # perception.FreeSpace
    stem_base: np.ndarray
    target: np.ndarray


@dataclass
class _State:
    """What the controller knows of the scene and its own last command (the phase and its
    timers are :class:`~harvest_qp.harvest.phases.PhaseMachine`'s)."""

    phase: Phase = Phase.APPROACH  # PhaseMachine.phase as of the last tick (read by the perception)
    p_sb: np.ndarray | None = None
    p_gd: np.ndarray | None = None
    stem_length: float = float("nan")
    stem_direction: np.ndarray | None = None
    last_stem_time: float = 0.0
    n_stem: int = 0
    frame: _Frame | None = None
    hold: HoldPose | None = None  # the grasping arm's hold of its initial pose in the approach
    previous_qdot: np.ndarray = field(default_factory=lambda: np.zeros(12))
    executed: np.ndarray | None = None  # the gripper's linear velocity [m/s] the last command gives (bimanual)


#: Shared read-only values of the per-tick log and references (the runner copies what it logs).
_NAN3 = np.full(3, np.nan)
_NAN3.setflags(write=False)
_ZEROS6 = np.zeros(6)
_ZEROS6.setflags(write=False)
_FLOAT64 = np.dtype(np.float64)


#: The values logged every tick (``value/<name>``) after the tick's own ``roll_error`` and
#: ``map_cells``, in :meth:`HarvestController._log_row`'s order, with their shapes.
_LOGGED_VALUES = (
    ("phase", ()), ("p_r", (3,)), ("p_c", (3,)), ("z_c", (3,)), ("x_c", (3,)), ("p_sb", (3,)), ("p_gd", (3,)),
    ("n_c", (3,)), ("V_c", (6,)), ("V_g", (6,)), ("force_nc", ()), ("theta", ()), ("roi_distance", ()),
    ("position_error", ()), ("alignment", ()), ("unveiling_pairs", ()),
)
#: The tick's values as one row for the runner (harvest_qp.runtime.log.ValueRow), with and without the map's cell count.
_LAYOUT_WITH_MAP = ValueLayout((("roll_error", ()), ("map_cells", ()), *_LOGGED_VALUES))
_LAYOUT_WITHOUT_MAP = ValueLayout((("roll_error", ()), *_LOGGED_VALUES))




def _missing_names(roll_error: float | None, map_cells: float | None, with_map: bool) -> tuple[str, ...]:
    """The tick's value names not given (``ValueRow.missing``) of the row layouts."""
    if roll_error is None:
        return ("roll_error", "map_cells") if with_map and map_cells is None else ("roll_error",)
    return ("map_cells",) if with_map and map_cells is None else ()


class HarvestController:
    """The paper's bimanual controller behind the runner's ``reset``/``step`` protocol.

    Args:
        settings: the episode's settings (:func:`harvest_qp.config.load_settings`), or a mapping of them
            (checked, every default filled in).
        environment: static capsules of the scene known to the controller (``qp.environment``).
        mapper: ``"qp"`` (the QP of this library) or ``"pinv"`` (the paper's
            ``eq:controlled_system`` on the same references); default from the settings.
        camera_in_flange: where the camera really is on the camera arm's flange (4x4 [m], a real
            cell's hand-eye calibration); the camera task and the reference laws then use that
            frame, the one the cloud is expressed with. None: the robot description's mount.
    """

    def __init__(self, settings: EpisodeConfig | Mapping[str, Any], *, environment=(), mapper: str | None = None,
                 camera_in_flange: np.ndarray | None = None) -> None:
        self.settings = s = check_settings(settings)
        self.mapper_kind = mapper or s.mapper.kind
        if self.mapper_kind not in ("qp", "pinv"):
            raise ConfigError(f"mapper must be 'qp' or 'pinv'; got {self.mapper_kind!r}")
        self.configuration = Configuration.dual_ur5e(camera_in_flange=camera_in_flange)
        qp = s.qp
        self.camera_task = FrameTwistTask(
            "camera", weight=qp.camera_task.weight, weight_frame="local", level=qp.camera_task.level
        )
        gripper_weight = np.broadcast_to(np.asarray(qp.gripper_task.weight, float), (6,)).copy()
        self.alignment_task = None
        if qp.alignment_task is not None:
            # eq:rot_contr on its own, lower level: when map rows or limits make V_g infeasible,
            # the translation (force and position along n_c) wins and the turn takes what is
            # left. One 6-D task let the turn win on held-out scenes: the gripper dragged 31-86 mm
            # sideways, the position error never converged (7 of 100 scenes).
            gripper_weight[3:] = 0.0
            self.alignment_task = FrameTwistTask(
                "gripper", weight=[0.0, 0.0, 0.0, *[qp.alignment_task.weight] * 3], level=qp.alignment_task.level
            )
        self.gripper_task = FrameTwistTask("gripper", weight=gripper_weight, level=qp.gripper_task.level)
        roll_weight = qp.roll_task.weight if s.roll.enabled else 0.0
        self.roll_task = FrameTwistTask(
            "camera", weight=[0, 0, 0, 0, 0, roll_weight], weight_frame="local", level=qp.roll_task.level
        )
        self.posture_task = PostureTask(self.configuration.q, weight=qp.posture.weight,
                                        level=qp.posture.level)
        tasks = [self.camera_task, self.gripper_task, self.roll_task, self.posture_task,
                 DampingTask(self.configuration.nv, weight=qp.damping.weight, level=qp.damping.level)]
        if self.alignment_task is not None:
            tasks.insert(2, self.alignment_task)
        from harvest_qp.config import build_tasks  # qp.extra_tasks: user tasks at their own level (issue 8)
        tasks += build_tasks([t.model_dump() for t in qp.extra_tasks], self.configuration, where="qp.extra_tasks")
        limits = []
        for i, entry in enumerate(e.model_dump() for e in qp.limits):
            where = f"qp.limits[{i}]"
            try:
                limits.append(build_limit(entry, self.configuration, where, environment))
            except ConfigError:
                raise
            except (HarvestQPError, TypeError, ValueError, KeyError) as err:
                raise ConfigError(f"{where} ({entry.get('type')}): {err}") from None
        acceleration = next((lim for lim in limits if isinstance(lim, JointAccelerationLimit)), None)
        self.max_acceleration = (
            np.asarray(acceleration.max_acceleration, float) * np.ones(12) if acceleration is not None
            else 10.0 * np.ones(12)
        )
        self.collision = next((lim for lim in limits if isinstance(lim, CollisionAvoidance)), None)
        self.qp = TaskController(self.configuration, tasks, limits, dt=0.002, solver=qp.solver,
                                 max_acceleration=self.max_acceleration)
        backup = qp.backup_solver
        self.qp_backup = (
            TaskController(self.configuration, tasks, self.qp.limits, dt=0.002, solver=backup,
                           max_acceleration=self.max_acceleration)
            if backup else None
        )
        self.pinv = PseudoInverseMapper(self.configuration, damping=s.mapper.pinv_damping)
        self._camera_id = self.configuration.frame_id("camera")
        self._gripper_id = self.configuration.frame_id("gripper")
        self._blade_id = self.configuration.frame_id("cutter_tip")  # the blade is fixed to the tool, not the camera
        self._build_references()
        self._build_obstacle_map()
        #: (per-sample swing clearance [m], the clearance asked [m]) of the last p_gd choice.
        self.last_swing_clearance = None
        #: How the last p_gd was chosen (``_target_within_swing``'s tier), for metrics.json.
        self.target_choice: str | None = None
        self.state = _State()
        #: The phase and its timers (:mod:`harvest_qp.harvest.phases`).
        self.phases = PhaseMachine(PhaseRules.from_settings(settings))
        self.dt = 0.002
        self.snapshots: dict[str, FrameSnapshot] = {}
        self.switch_snapshot: SwitchSnapshot | None = None
        self._last_pair_names: tuple | None = None  # _active_pair_columns' last names (reused while unchanged)
        #: Set to a dict to collect wall-clock times [s] per tick: "perception" (per new
        #: frame), "references" and "mapper" (the QP step or the pseudo-inverse).
        self.timing: dict[str, list[float]] | None = None

    # ------------------------------------------------------------------ set-up

    def _build_obstacle_map(self) -> None:
        """The persistent obstacle map of issue 11 and its feed to the collision limit.

        Beyond the paper (its collision constraints know only the robot): every camera frame
        updates an :class:`~harvest_qp.perception.obstacle_map.ObstacleMap`, and before each
        QP step a :class:`~harvest_qp.perception.map_feed.MapCollisionFeed` gives the
        closest occupied cells of each arm capsule to the ``CollisionAvoidance`` limit as
        damper rows (pair names ``cell[kx,ky,kz]``). Only with the QP mapper and a collision
        limit; the cloud-sphere option (``obstacles``) feeds the same limit, so not both.
        """
        from harvest_qp.perception.map_feed import MapCapsule, MapCollisionFeed
        from harvest_qp.perception.obstacle_map import ObstacleMap

        m = self.settings.obstacle_map
        self.obstacle_map = None
        self.map_feed = None
        #: The map's prior on partly seen canes and wires (``obstacle_map.line_prior`` > 0).
        self.line_prior = None
        self._swing_capsules = []
        self._arm_swing_capsules = []
        if not m.enabled or self.collision is None or self.mapper_kind != "qp":
            return
        if self.settings.obstacles.enabled:
            raise ConfigError("obstacle_map.enabled and obstacles.enabled both feed the collision limit; "
                              "expected at most one of them true")
        from harvest_qp.robot import description

        prefixes = ("cam_",) if m.arms == "camera" else ("cam_", "grasp_")
        capsules = [
            MapCapsule(b.name, b.link, b.capsule.p0, b.capsule.p1, b.capsule.radius)
            for b in description.collision_bodies() if b.arm and b.name.startswith(prefixes)
        ]
        # The grasping arm's capsules near the tool, which swing with the gripper around p_sb
        # when the stem is stretched (the swing check of p_gd, perception.grasp_target).
        self._swing_capsules = [
            (b.link, np.asarray(b.capsule.p0, float), np.asarray(b.capsule.p1, float), float(b.capsule.radius))
            for b in description.collision_bodies() if b.arm and b.name in SWING_CAPSULES
        ]
        # The rest of the grasping arm, moved with its joints along the swing.
        self._arm_swing_capsules = [
            (b.link, np.asarray(b.capsule.p0, float), np.asarray(b.capsule.p1, float), float(b.capsule.radius))
            for b in description.collision_bodies() if b.arm and b.name in ARM_SWING_CAPSULES
        ]
        try:
            self.obstacle_map = ObstacleMap(resolution=m.resolution, clear_rays=m.clear_rays, erase_excluded=False)
            self.map_feed = MapCollisionFeed(
                self.collision, self.obstacle_map, self.configuration, per_capsule=m.per_capsule,
                min_separation=m.min_separation, margin=m.margin, max_cells=m.max_cells, capsules=capsules,
            )
            # The grasping arm's map rows only stop it ("no further approach"), never push
            # it: the map lies 5-15 mm short of the surface, so a gripper that starts near
            # the branch is inside d_s on the map, and separation rows then pushed it away
            # during the approach and pre-stretched the stem before the tare (seed 1:
            # true tension 5.6 N at the end, the wrist reading 3.0 N).
            self.collision.set_approach_only([c.name for c in capsules if c.name.startswith("grasp_")])
            if m.line_prior > 0.0:
                from harvest_qp.perception.line_prior import LinePrior

                self.line_prior = LinePrior(m.line_prior_direction, extend=m.line_prior,
                                            min_length=m.line_prior_min_length,
                                            max_tilt_deg=m.line_prior_max_tilt_deg)
        except HarvestQPError as err:
            raise ConfigError(f"obstacle_map: {err}") from None

    def map_exclusions(self, T_g: np.ndarray) -> list:
        """Regions never mapped at gripper pose ``T_g``: ``[held cluster, stem up to the latest p_sb]``
        (:func:`~harvest_qp.perception.obstacle_map.held_crop_exclusions`)."""
        from harvest_qp.perception.obstacle_map import held_crop_exclusions

        m = self.settings.obstacle_map
        return held_crop_exclusions(
            T_g, self.state.p_sb, grasp_offset=self.settings.perception.grasp_offset,
            cluster_start=m.cluster_start, cluster_length=m.cluster_length, cluster_radius=m.cluster_radius,
            stem_length=m.stem_length, stem_radius=m.stem_radius,
        )

    def _build_references(self) -> None:
        s = self.settings
        r, u, g = s.reaching, s.unveiling, s.grasping
        # V_cr reaches its sphere only asymptotically from outside (measured 1.01-1.05 r after
        # 15-30 s); aiming at target_radius_factor x r makes the camera end inside the ROI.
        self.reaching = ReachingCentering(
            radius=r.target_radius_factor * r.radius, k_cp=r.k_cp, k_co=r.k_co,
            roi_time_constant=r.roi_time_constant,
        )
        self.unveiling = Unveiling(
            k_c=u.k_c, d_a=u.d_a, d_o=u.d_o, time_constant=u.time_constant, max_linear=u.max_linear,
            max_angular=u.max_angular, min_pivot=u.min_pivot, min_stem_points=self.settings.perception.min_stem_points,
        )
        self.stretching = StemStretching(
            k_pg=g.k_pg, k_og=g.k_og, k_fp=g.k_fp, k_fi=g.k_fi, f_d=g.f_d, max_speed=g.max_speed,
            integration_threshold=g.integration_threshold, k_yield=g.k_yield, yield_deadband=g.yield_deadband,
            yield_time_constant=g.yield_time_constant,
        )
        self.feed_forward = GraspFeedForward()
        p = s.perception
        #: The stem points seen from close range over the approach (``perception.stem_memory``).
        self.stem_memory = StemTopMemory(max_range=p.stem_memory_range) if p.stem_memory else None
        look = s.look_around
        self.look_around = (LookAround(cone=math.radians(look.cone_deg), period=look.period, gain=look.gain)
                            if look.enabled else None)

    def reset(self, robot: RobotInterface) -> None:
        """Read the initial state (joints, control period); no robot handle is kept."""
        q0 = np.asarray(robot.joint_positions(), float)
        self.dt = float(robot.control_period)
        self.qp.dt = self.dt
        self.qp.reset(q0)
        if self.qp_backup is not None:
            self.qp_backup.dt = self.dt
            self.qp_backup.reset(q0)
        self.posture_task.set_target(q0)
        self.camera_task.weight = self.settings.qp.camera_task.weight  # the approach's (see the switch)
        self.configuration.update(q0)
        gripper = self.configuration.frame_pose("gripper").homogeneous
        self.state = _State(hold=HoldPose(gripper, k_hold=self.settings.grasping.k_hold))
        self.phases.reset()
        self.reaching.reset(self.configuration.frame_position("gripper"))
        self.unveiling.reset()
        self.stretching.reset()
        if self.look_around is not None:
            self.look_around.reset()
        self.snapshots = {}
        self.switch_snapshot = None
        self.target_choice = None
        self.last_swing_clearance = None
        if self.line_prior is not None:
            self.line_prior.reset()
        if self.stem_memory is not None:
            self.stem_memory.reset()
        if self.obstacle_map is not None:
            self.obstacle_map.clear()
            self.map_feed.update(q0)

    # ------------------------------------------------------------------ perception

    def _perceive(self, cloud: PointCloud, T_g: np.ndarray) -> None:
        """One camera frame: S and W - S (:class:`~harvest_qp.perception.cloud_split.LabelledFrame`)
        to the unveiling law, the cloud spheres, and during the approach the stem fit p_sb."""
        st, s = self.state, self.settings
        frame = _Frame(cloud)
        st.n_stem = frame.n_stem
        if frame.n_stem > 0:
            st.last_stem_time = frame.time
        snap = FrameSnapshot(cloud.timestamp, cloud.pixels, cloud.labels, cloud.image_size, cloud.depth)
        self.snapshots.setdefault("start", snap)
        self.snapshots["end"] = snap
        if s.unveiling.enabled:
            # Only the predicted mode reads the predicted stem (the law ignores it once
            # min_stem_points stem points are seen): not computed on the other frames.
            law = self.unveiling
            predicted_mode = s.unveiling.predicted_stem and frame.n_stem < law.min_stem_points
            # The paper mode reads only every k-th non-stem row (law.obstacle_stride): only those are
            # gathered (and checked by the law: a non-finite point it reads raises, naming them).
            thin = frame.n_stem > 0 and not predicted_mode
            obstacles = frame.non_stem_every(law.obstacle_stride(frame.n_non_stem)) if thin else frame.non_stem
            law.observe(frame.camera_position, frame.stem, obstacles,
                        predicted_stem_points=self._predicted_stem(T_g) if predicted_mode else None,
                        roi_centre=self.reaching.roi_centre, timestamp=frame.time)
        if self.collision is not None and s.obstacles.enabled:
            self._update_obstacle_spheres(frame.obstacles, T_g)
        if st.phase != Phase.APPROACH:
            return
        p = s.perception
        if frame.n_stem >= p.min_stem_points:
            fit = fit_stem(frame.stem, T_g[:3, 3])
            if fit.valid and np.linalg.norm(fit.base - T_g[:3, 3]) <= p.max_base_distance:
                frame.fit = fit
                if self.stem_memory is not None:
                    self.stem_memory.add(frame.stem, camera_position=frame.camera_position, stem_base=fit.base)
                st.p_sb, st.stem_length = self._stem_base(fit)
                st.stem_direction = fit.top.direction.copy()
                self.reaching.set_roi_centre(st.p_sb)
        st.frame = frame

    def _stem_base(self, fit) -> tuple[np.ndarray, float]:
        """p_sb [m] and the stem length l [m] of a frame's fit, moved up the top axis to the highest stem
        point the approach has seen from close range (``perception.stem_memory``)."""
        if self.stem_memory is None:
            return fit.base.copy(), fit.length
        direction = fit.top.direction
        reach = self.stem_memory.extension(fit.base, direction)
        return fit.base - reach * direction, fit.length + reach

    def _update_obstacle_spheres(self, points: np.ndarray, T_g: np.ndarray) -> None:
        """The vine seen in this frame as collision spheres for the QP (beyond the paper;
        :func:`~harvest_qp.perception.cloud_split.obstacle_sphere_centres`). Measured without
        it (default scene, lab contacts on): the gripper swinging the crop towards p_gd touched
        a leaf at 12 s, the wrist read 6 N of contact force and the episode aborted."""
        o = self.settings.obstacles
        centres = obstacle_sphere_centres(points, T_g, max_distance=o.max_distance, voxel=o.voxel,
                                          cluster_length=o.cluster_length, cluster_radius=o.cluster_radius)
        self.collision.set_obstacle_spheres(centres, o.radius)

    def _grasp_obstacle_candidates(self, frame: _Frame) -> np.ndarray:
        """W - S without the robot's own points and the held crop (both move with the gripper).

        Deviation: the paper's O = (W - S) within S(p_sb, r_o) includes them. Measured on
        seed 1: every free sample within 30 deg of the hanging stem was occupied by the held
        crop's and gripper's own points, so no p_gd existed there and the episode never
        switched. The crop cannot be an obstacle to where it is taken.
        """
        if not self.settings.grasping.exclude_held_crop:
            return frame.non_stem
        o = self.settings.obstacles
        points = frame.obstacles
        return points[outside_held_cluster(points, self._switch_gripper_pose, cluster_length=o.cluster_length,
                                           cluster_radius=o.cluster_radius)]

    def _target_within_swing(self, free, stem_base: np.ndarray, *, T_g: np.ndarray) -> np.ndarray | None:
        """p_gd within ``grasping.max_swing_deg`` of the stem now, map-aware with
        ``grasping.swing_clearance`` (:func:`~harvest_qp.perception.grasp_target.choose_grasp_target`)."""
        g = self.settings.grasping
        swing = None
        if g.swing_clearance is not None and self.obstacle_map is not None and self._swing_capsules:
            config = self.configuration
            capsules = []
            for frame, a, b, radius in self._swing_capsules:
                pose = config.frame_pose(frame)
                capsules.append((pose.act(a), pose.act(b), radius))
            joints = config.support_mask("gripper")  # the grasping arm's joints
            J_g = config.frame_jacobian("gripper")[:, joints]
            arm = []
            for frame, a, b, radius in self._arm_swing_capsules:
                pose = config.frame_pose(frame)
                ends = (pose.act(a), pose.act(b))
                motions = [arm_capsule_motion(config.point_jacobian(frame, e)[:, joints], J_g) for e in ends]
                arm.append(ArmCapsule(*ends, radius, *motions))
            swing = SwingCheck(self.obstacle_map, config.frame_position("gripper"), capsules,
                               clearance=g.swing_clearance, stretch=g.swing_stretch, arm=arm,
                               map_bias=g.swing_map_bias)
        top_of_crop = T_g[:3, 3] - self.settings.perception.grasp_offset * T_g[:3, 1]
        target = choose_grasp_target(free, stem_base, top_of_crop, max_swing_deg=g.max_swing_deg, swing=swing)
        self.target_choice = target.choice
        if target.swing_clearance is not None:
            self.last_swing_clearance = target.swing_clearance
        return target.point

    def _predicted_stem(self, T_g: np.ndarray) -> np.ndarray:
        """Where the stem should be, from what the robot knows (beyond the paper).

        Before the switch: the segment above the grasped crop along the gripper's "up" axis
        (:func:`~harvest_qp.references.predicted_stem_points`). After it: the straight stem
        from the frozen p_sb to the top of the crop, which the grasping arm is stretching.
        """
        st = self.state
        if st.phase == Phase.APPROACH or st.p_sb is None:
            return predicted_stem_points(T_g)
        top_of_crop = T_g[:3, 3] - self.settings.perception.grasp_offset * T_g[:3, 1]
        return top_of_crop + np.linspace(0.0, 1.0, 12)[:, None] * (st.p_sb - top_of_crop)

    def _try_switch(self, t: float, obs: Observation, T_g: np.ndarray) -> bool:
        """Recompute p_sb and p_gd on the latest frame; True (sensor tared, laws retargeted) if both exist."""
        st, g = self.state, self.settings.grasping
        frame = st.frame
        if frame is None or frame.fit is None:
            return False
        fit = frame.fit
        # _perceive set p_sb and l from this very fit (moved up by the stem memory, which only it feeds).
        base, length = st.p_sb.copy(), st.stem_length
        r_o = length if g.r_o == "l" else float(g.r_o)
        obstacles = obstacles_near_stem_base(self._grasp_obstacle_candidates(frame), base, r_o)
        free = compute_free_space(obstacles, base, length, frame.camera_position, n_samples=g.n_samples)
        if not free.valid or free.target is None:
            return False
        target = self._target_within_swing(free, base, T_g=T_g)
        if target is None:
            return False
        st.p_sb, st.p_gd, st.stem_length = base, target, length
        self.switch_snapshot = SwitchSnapshot(
            t, frame.camera_pose, frame.stem, frame.non_stem, fit, obstacles, free, st.p_sb, st.p_gd
        )
        if "end" in self.snapshots:
            self.snapshots["switch"] = self.snapshots["end"]
        self.reaching.set_roi_centre(st.p_sb)
        self.stretching.reset()
        self.stretching.set_target(st.p_sb, st.p_gd)
        obs.tare_force()  # the bimanual phase starts from a tared sensor (subsec:grasp_contr)
        st.last_stem_time = max(st.last_stem_time, t)
        return True

    # ------------------------------------------------------------------ control

    def step(self, obs: Observation) -> Command:
        """One control tick: perception (on a new frame) -> phase -> reference laws -> QP -> log."""
        t = float(obs.time)
        if not math.isfinite(t):  # every timer and the camera-speed window compare against t
            raise InvalidInputError(f"HarvestController.step: observation time must be finite [s], got {obs.time!r}")
        self.configuration.update(obs.q)
        T_c = self.configuration.data.oMf[self._camera_id].homogeneous
        T_g = self.configuration.data.oMf[self._gripper_id].homogeneous
        timing, clock = self.timing, time.perf_counter
        if obs.new_cloud and obs.cloud is not None:
            t0 = clock()
            self._perceive(obs.cloud, T_g)
            if self.obstacle_map is not None:
                cluster, stem = self.map_exclusions(T_g)
                self.obstacle_map.update(obs.cloud, exclude=(cluster, stem))
                # Only the stem's cells are forgotten (seen as an obstacle beyond the stem range
                # before it was recognised). The held cluster's region keeps the crop's points
                # out but erases nothing: it once erased a petiole's cells (42 -> 16) and, with
                # the crop turned, the branch cells next to the gripper, whose rows then vanished
                # (the gripper rested on the branch for ~28 s on a held-out scene).
                self.obstacle_map.erase((stem,))
                if self.line_prior is not None and self.line_prior.due(t):
                    # Never next to the stem base, where the grasping arm must go.
                    self.line_prior.update(self.obstacle_map, t=t,
                                           keep_clear=() if self.state.p_sb is None else (self.state.p_sb,))
            if timing is not None:
                timing.setdefault("perception", []).append(clock() - t0)
        t_references = clock()
        self._advance_phase(t, obs, T_c, T_g)
        references = _NO_REFERENCES if self.phases.phase == Phase.ABORT else self._references(t, obs, T_c, T_g)
        t_mapper = clock()
        qdot, status, map_cells = self._joint_speeds(t, obs.q, references)
        if timing is not None:
            timing.setdefault("references", []).append(t_mapper - t_references)
            timing.setdefault("mapper", []).append(clock() - t_mapper)
        self.state.phase = self.phases.phase  # the perception's view of the phase
        values = self._log_row(T_c, references, map_cells)
        return Command(qdot=qdot, status=status, values=values, collision_pairs=self._active_pair_columns(),
                       done=self.phases.done(t))

    def _advance_phase(self, t: float, obs: Observation, T_c: np.ndarray, T_g: np.ndarray) -> None:
        """The phase machine's tick: the switch test (then p_sb, p_gd at the switch) or the stem watch."""
        phases, st = self.phases, self.state
        if phases.phase == Phase.APPROACH:
            ready = phases.approach(t, T_c, stem_base_found=st.p_sb is not None,
                                    roi_distance=math.dist(self.reaching.roi_centre.tolist(), T_c[:3, 3].tolist()))
            if ready and not self.looking_around(t) and self._try_switch(t, obs, T_g):
                phases.switch(t)
                if self.settings.qp.camera_bimanual_weight is not None:
                    # From here the camera only has to stay in the ROI and centred (see the setting).
                    self.camera_task.weight = self.settings.qp.camera_bimanual_weight
        elif phases.bimanual:
            phases.watch_stem(t, st.last_stem_time)

    def looking_around(self, t: float) -> bool:
        """Whether the camera sweeps its surroundings at ``t`` [s] (:class:`~harvest_qp.references.LookAround`,
        opt-in, the first seconds of the approach; the switch waits for its end)."""
        look = self.look_around
        return look is not None and self.phases.phase == Phase.APPROACH and not look.done(t)

    def _references(self, t: float, obs: Observation, T_c: np.ndarray, T_g: np.ndarray) -> _References:
        """The tick's task references (advances the laws' filters and the grasp's phase tests).

        Camera: V_c = V_cr (``eq:control_signal_rr_world``) + the keep-out term + V_cu (``eq:v_c2``,
        low-passed), its angular part replaced by the look-around's sweep while it runs (opt-in), plus
        in the bimanual phase the feed-forward of ``eq:final_vc``; roll: the
        cutter across the stem. Gripper: the hold of the crop in the approach, then V_g
        (``eq:superimp_g``) on the wrist force (tared at the switch; zero on the switch tick).
        """
        s, st, dt = self.settings, self.state, self.dt
        r = s.reaching
        reaching, stretching = self.reaching, self.stretching
        V_c = reaching.update(T_c, dt)
        V_c += keep_out_velocity(T_c[:3, 3], reaching.roi_centre, min_distance=r.min_distance_factor * r.radius,
                                 gain=r.k_keep_out)
        if s.unveiling.enabled:
            V_c += self.unveiling.update(dt)
        if self.looking_around(t):  # the sweep turns the camera; the translation stays the laws'
            look = self.look_around
            if not look.started:
                look.start(t, T_c, reaching.roi_centre)
            V_c[3:] = look.angular_velocity(t, T_c)
        force_nc = math.nan
        if self.phases.phase == Phase.APPROACH:
            V_g = st.hold.update(T_g)
            direction = st.stem_direction if st.stem_direction is not None else T_g[:3, 1]
        else:
            force = obs.force if t > self.phases.t_switch else np.zeros(3)
            V_g = stretching.update(T_g, force, dt, executed=st.executed)
            force_nc = stretching.force_along_nc
            if s.grasping.feed_forward:
                V_c += self.feed_forward(stretching.v_gt, T_c[:3, 3], st.p_sb)
            top_of_crop = T_g[:3, 3] - s.perception.grasp_offset * T_g[:3, 1]
            self.phases.stretch(t, dt, force_nc, stretching.position_error, stretching.alignment,
                                force_norm=math.hypot(*force), motion_executed=stretching.motion_executed,
                                crop_side=float((top_of_crop - st.p_sb) @ stretching.n_c))
            direction = stretching.n_c
        # the blade is fixed to the tool: with a calibrated camera (camera_in_flange) x_c is off it
        blade_y = self.configuration.data.oMf[self._blade_id].rotation[:, 1]
        roll, roll_error = roll_reference(T_c, direction, k_roll=s.roll.k_roll, blade_y=blade_y)
        return _References(V_c, V_g, roll, roll_error, force_nc, reaching.distance)

    def _joint_speeds(self, t: float, q: np.ndarray, references: _References) -> tuple[np.ndarray, str, float | None]:
        """(qdot [rad/s], status, map cells fed or None): the safe stop after an abort, else the
        pseudo-inverse (``eq:controlled_system``) or the QP on the references."""
        phases, map_cells = self.phases, None
        if phases.phase == Phase.ABORT:
            qdot, status = self._safe_stop(), f"abort: {phases.abort_reason}"
            phases.braking(t, at_rest=not np.any(qdot))
        elif self.mapper_kind == "pinv":
            qdot, status = self.pinv.map(np.concatenate([references.V_c, references.V_g])), "ok"
        else:
            self.camera_task.set_reference(references.V_c)
            self.gripper_task.set_reference(references.V_g)
            if self.alignment_task is not None:
                self.alignment_task.set_reference(references.V_g)
            self.roll_task.set_reference(references.roll)
            if self.map_feed is not None:
                map_cells = float(self.map_feed.update(q))
            qdot, status, ok = self._solve(q)
            phases.solved(t, ok, status)
        qdot = np.asarray(qdot, float)
        # The gripper motion this command gives, against which the next V_g checks its own
        # (StemStretching: the force integral holds, the phase machine aborts after a while).
        self.state.executed = (self.configuration.frame_jacobian_by_id(self._gripper_id)[:3] @ qdot
                               if phases.bimanual else None)
        if phases.phase != Phase.ABORT:
            self.qp.previous_qdot = qdot
        self.state.previous_qdot = qdot
        return qdot, status, map_cells

    def _solve(self, q: np.ndarray) -> tuple[np.ndarray, str, bool]:
        """The QP step (kinematics already updated); a failed step is solved again by the backup
        solver from the same previous command when one is set (stopgap until the QP core retries
        itself, issue 10: daqp answers slightly outside the constraints, 2e-7..1e-6, and the core brakes)."""
        backup_solver = self.qp_backup
        previous = self.qp.previous_qdot.copy() if backup_solver is not None else None
        result = self.qp.step(q, kinematics_updated=True)
        if result.ok or backup_solver is None:
            return result.qdot, result.status, result.ok
        backup_solver.previous_qdot = previous
        backup = backup_solver.step(q, kinematics_updated=True)
        if not backup.ok:
            return result.qdot, result.status, False
        self.phases.backup_solves += 1
        return backup.qdot, f"{backup.status} (backup solver)", True

    def _safe_stop(self) -> np.ndarray:
        """The last command braked by the largest step the acceleration limit allows (to rest)."""
        prev = self.state.previous_qdot
        step = self.max_acceleration * self.dt
        return prev - np.clip(prev, -step, step)

    # ------------------------------------------------------------------ log

    def _log_row(self, T_c: np.ndarray, references: _References, map_cells: float | None) -> ValueRow:
        """The tick's logged values (``value/<name>``: ``roll_error``, ``map_cells`` with the map,
        then :data:`_LOGGED_VALUES`) as one float64 row for the runner (``harvest_qp.runtime.log.ValueRow``);
        NaN where a value is not defined (before the switch, or no references after an abort)."""
        st, phases, reaching, stretching = self.state, self.phases, self.reaching, self.stretching
        nan = math.nan
        switched = phases.t_switch is not None
        roi_distance = references.roi_distance
        if roi_distance is None:
            offset = reaching.roi_centre - T_c[:3, 3]
            roi_distance = math.sqrt(float(offset @ offset))
        with_map = self.map_feed is not None
        roll_error = references.roll_error
        head = [nan if roll_error is None else roll_error, nan if map_cells is None else map_cells][: 1 + with_map]
        row = np.concatenate((
            head, [float(phases.phase)], reaching.roi_centre, T_c[:3, 3], T_c[:3, 2], T_c[:3, 0],
            _NAN3 if st.p_sb is None else st.p_sb, _NAN3 if st.p_gd is None else st.p_gd,
            stretching.n_c if switched else _NAN3, references.V_c, references.V_g,
            [references.force_nc, reaching.theta, roi_distance, stretching.position_error if switched else nan,
             stretching.alignment if switched else nan, float(self.unveiling.n_pairs)],
        ))
        layout = _LAYOUT_WITH_MAP if with_map else _LAYOUT_WITHOUT_MAP
        return ValueRow._built(layout, row, _missing_names(roll_error, map_cells, with_map))

    def _active_pair_columns(self) -> PairColumns | list:
        """The collision pairs active in this tick's QP as three columns (``harvest_qp.runtime.log.PairColumns``:
        first names, second names, distances [m]); ``[]`` without (no limit, the pinv mapper)."""
        lim = self.collision
        if lim is None or self.mapper_kind != "qp":
            return []
        active = np.asarray(getattr(lim, "active_pairs", ()), dtype=np.int64)
        if not active.size:
            return []
        distances = getattr(lim, "_dist", None)
        # Python floats of float64 values (what PairColumns' constructor made of the array).
        if distances is None:
            distances = [math.nan] * active.size
        else:
            distances = distances[active]
            if distances.dtype is not _FLOAT64:  # the limit's own are float64: no conversion
                distances = np.asarray(distances, dtype=np.float64)
            distances = distances.tolist()
        names = lim.capsule_names
        pair_a, pair_b = lim.pair_a, lim.pair_b
        key = active.tobytes()
        last = self._last_pair_names
        # Most ticks keep the last tick's pairs and names: the same name lists then (the
        # runner's log also reuses its indices for them). The limit replaces its pair tables,
        # never changes them in place (CollisionAvoidance._active_pair_snapshot relies on it
        # too): the same table objects and the same active indices (by bytes) are the same
        # capsule index pairs. Names compared by value (the map's feed renames obstacle slots
        # in place).
        if (last is not None and last[0] is pair_a and last[1] is pair_b and last[5] == key
                and last[2] == names):
            first, second = last[3], last[4]
        else:
            lookup = names.__getitem__
            first = list(map(lookup, pair_a[active].tolist()))
            second = list(map(lookup, pair_b[active].tolist()))
            self._last_pair_names = (pair_a, pair_b, list(names), first, second, key)
        return PairColumns._built(first, second, distances)  # lists of one length: no check needed

    # ------------------------------------------------------------------ summary

    @property
    def phase(self) -> Phase:
        return self.phases.phase


class _References(NamedTuple):
    """One tick's task references: V_c, V_g, the roll twist ``(6,)`` [m/s; rad/s] world frame, the
    roll angle [rad] (NaN: no roll), the force along n_c [N] (NaN before the switch) and |p_r - p_c| [m]."""

    V_c: np.ndarray
    V_g: np.ndarray
    roll: np.ndarray | None
    roll_error: float | None
    force_nc: float
    roi_distance: float | None


#: An abort tick's references: none computed (zero twists, logged NaN where undefined).
_NO_REFERENCES = _References(_ZEROS6, _ZEROS6, None, None, math.nan, None)
