"""The paper's closed loop (Section ``sec:contr``) as one controller for the episode runner.

Data flow, every control tick (2 ms)::

    camera frame (new?) -> perception: S, O, p_sb, (at the switch) p_gd, F
                        -> reference laws (harvest_qp.references): V_cr, V_cu, V_g, feed-forward
                        -> QP task references (5-D camera twist, 6-D gripper twist, roll)
                        -> TaskController (or the paper's pseudo-inverse) -> qdot

:class:`HarvestController` only reads what a real dual UR5e gives (joint positions and
velocities, the wrist force, the camera's labelled cloud and the clock, all from the
:class:`~harvest_qp.runner.Observation`); it never sees the simulator's ground truth and
keeps no robot handle, so the same object can drive two real arms.

Phases (``subsec:biman_coord``): ``approach`` (camera arm reaches and unveils; the grasping
arm holds the crop still) -> ``bimanual`` (V_g of ``eq:superimp_g`` on the grasping arm, V_c'
of ``eq:final_vc`` on the camera arm) -> ``precut`` (force, projected position error and
alignment within tolerance for ``precut.hold_time``; control continues), or ``abort`` (force
above the limit, stem not seen, no stem found, QP failures in a row), which brings the arms
to rest within the acceleration limit and logs the reason.

Where this differs from the paper (measured in ``/work/shared/FINDINGS.md``):

* p_sb is refitted on every frame of the approach (the ROI centre follows it through the
  reaching filter), recomputed on the frame at the switch and then frozen. The paper
  identifies it "only once at the start"; the first fit there is 22-41 mm off (13-20
  points at 0.57 m), while refit-then-freeze gave 2.4-2.7 mm; refitting during the
  bimanual phase drifted 49 mm.
* The ROI centre is the gripper point (the grasped crop, known from the kinematics) until a
  stem base is found.
* The camera's free roll is used by a lower-priority task that turns the cutter (the
  camera's x axis, along which the blade closes) across the stem.
* p_gd is map-aware (``grasping.swing_clearance``): among the free samples of
  ``eq:attr_point``, only those whose swing keeps the gripper and its wrist 2 cm (on the
  obstacle map) from every mapped cell are used; when none of F does, the hanging direction
  itself or the least swing that does. Measured before it (283x160): on seeds 1 and 5 the
  gripper swung the crop into the occluding leaf (``leaf_0``, which hangs on the camera's
  side, where F is; seed 1 also rubbed the branch): a 6 N force-limit abort on seed 1,
  19,068 contact ticks on seed 5 (seeds 2 and 3: 14,456 and 19,706 vine-contact ticks in
  the README's earlier table). After it: success and 0 contacts on the default scene and
  seeds 1-10 (seeds 6-10 unnamed checks).
* The switch rule uses the camera's mean speeds over ``switch.window`` (0.5 s), the angular
  one from the turn of the optical axis (the free roll left out): with V_cu acting the
  camera dithers about a fixed view and its instantaneous speeds never met the thresholds.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

import numpy as np
import pinocchio as pin

from harvest_qp.baseline import PseudoInverseMapper
from harvest_qp.config import _build_limit
from harvest_qp.configuration import Configuration
from harvest_qp.controller import TaskController
from harvest_qp.exceptions import ConfigError, HarvestQPError, InvalidInputError
from harvest_qp.interface import PointCloud, RobotInterface
from harvest_qp.limits import CollisionAvoidance, JointAccelerationLimit
from harvest_qp.loop import _tick_kernels
from harvest_qp.perception import compute_free_space, fit_stem, obstacles_near_stem_base
from harvest_qp.perception.cloud_split import LabelledFrame as _Frame  # _State.frame
from harvest_qp.perception.cloud_split import obstacle_sphere_centres, outside_held_cluster
from harvest_qp.perception.grasp_target import SWING_CAPSULES, SwingCheck, choose_grasp_target
from harvest_qp.references import (
    GraspFeedForward,
    ReachingCentering,
    StemStretching,
    Unveiling,
    predicted_stem_points,
)
from harvest_qp.references._checks import as_position
from harvest_qp.runner import Command, Observation, _command, _PairColumns, _ValueLayout, _ValueRow
from harvest_qp.tasks import DampingTask, FrameTwistTask, PostureTask

__all__ = ["Phase", "HarvestController", "FrameSnapshot", "SwitchSnapshot"]


class Phase(IntEnum):
    """Episode phase, logged per tick as ``value/phase``."""

    APPROACH = 0
    BIMANUAL = 1
    PRECUT = 2
    ABORT = 3


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
    phase: Phase = Phase.APPROACH
    abort_reason: str | None = None
    t_switch: float | None = None
    t_precut: float | None = None
    t_abort: float | None = None
    t_at_rest: float | None = None
    p_sb: np.ndarray | None = None
    p_gd: np.ndarray | None = None
    stem_length: float = float("nan")
    stem_direction: np.ndarray | None = None
    last_stem_time: float = 0.0
    n_stem: int = 0
    qp_failures_in_row: int = 0
    qp_failures: int = 0
    backup_solves: int = 0
    force_filtered: float | None = None
    precut_since: float | None = None
    frame: _Frame | None = None
    hold_pose: pin.SE3 | None = None
    previous_qdot: np.ndarray = field(default_factory=lambda: np.zeros(12))
    camera_history: deque = field(default_factory=deque)
    #: hold_pose's translation and transposed rotation, read once (pinocchio builds a new
    #: array on every attribute access).
    hold_translation: np.ndarray | None = None
    hold_rotation_T: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.hold_pose is not None:
            self.hold_translation = self.hold_pose.translation
            self.hold_rotation_T = self.hold_pose.rotation.T


#: Shared read-only values of the per-tick log and references (the runner copies what it logs).
_NAN3 = np.full(3, np.nan)
_NAN3.setflags(write=False)
_ZEROS6 = np.zeros(6)
_ZEROS6.setflags(write=False)
_FLOAT64 = np.dtype(np.float64)
_INT64 = np.dtype(np.int64)
#: Writable twins of _NAN3 / _ZEROS6, handed only to the compiled row copy (which reads them): numba
#: compiles a read-only array argument as another type (a second compilation, not a second result).
_NAN3_KERNEL = np.full(3, np.nan)
_ZEROS6_KERNEL = np.zeros(6)


#: The values logged every tick (``value/<name>``) after the tick's own ``roll_error`` and
#: ``map_cells``, in :meth:`HarvestController._log_values`'s order, with their shapes.
_LOGGED_VALUES = (
    ("phase", ()), ("p_r", (3,)), ("p_c", (3,)), ("z_c", (3,)), ("x_c", (3,)), ("p_sb", (3,)), ("p_gd", (3,)),
    ("n_c", (3,)), ("V_c", (6,)), ("V_g", (6,)), ("force_nc", ()), ("theta", ()), ("roi_distance", ()),
    ("position_error", ()), ("alignment", ()), ("unveiling_pairs", ()),
)
#: The tick's values as one row for the runner (runner._ValueRow), with and without the map's cell count.
_LAYOUT_WITH_MAP = _ValueLayout((("roll_error", ()), ("map_cells", ()), *_LOGGED_VALUES))
_LAYOUT_WITHOUT_MAP = _ValueLayout((("roll_error", ()), *_LOGGED_VALUES))
_NAN3_LIST = [math.nan] * 3
# The phases as module constants for step's per-tick tests (a global read instead of an
# attribute lookup on the enum class each; the same members, compared by == as before).
_APPROACH, _BIMANUAL, _PRECUT, _ABORT = Phase.APPROACH, Phase.BIMANUAL, Phase.PRECUT, Phase.ABORT


def _pose_matrix(pose: pin.SE3) -> np.ndarray:
    """The ``(4, 4)`` homogeneous matrix of ``pose``: a new C-ordered array (pinocchio's own
    ``homogeneous``, the same numbers as filling ``np.eye(4)``, ~10x cheaper)."""
    return pose.homogeneous


def _missing_names(roll_error: float | None, map_cells: float | None, with_map: bool) -> tuple[str, ...]:
    """The tick's value names not given (``_ValueRow.missing``) of the row layouts."""
    if roll_error is None:
        return ("roll_error", "map_cells") if with_map and map_cells is None else ("roll_error",)
    return ("map_cells",) if with_map and map_cells is None else ()


def _reference_buffers(out: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``out`` (``_tick_kernels.camera_references``' output) and 1-element views of its roll slots:
    np.arctan2 on arrays, written with ``out=``, costs a third of its call on two scalars."""
    k = _tick_kernels
    return out, out[k.ROLL_Y:k.ROLL_Y + 1], out[k.ROLL_X:k.ROLL_X + 1], out[k.ROLL_ANGLE:k.ROLL_ANGLE + 1]


def _wrap_half_turn(angle: float) -> float:
    """An angle between two undirected lines, in [-pi/2, pi/2]."""
    # On Python floats: the same IEEE operations as on numpy's float64 scalars (numpy's and
    # Python's floor remainder are both fmod then one correction towards the divisor's sign).
    angle = float(angle)
    return (angle + math.pi / 2) % math.pi - math.pi / 2


class HarvestController:
    """The paper's bimanual controller behind the runner's ``reset``/``step`` protocol.

    Args:
        settings: the checked settings tree of :func:`harvest_qp.loop.settings.load_settings`.
        environment: static capsules of the scene known to the controller (``qp.environment``).
        mapper: ``"qp"`` (the QP of this library) or ``"pinv"`` (the paper's
            ``eq:controlled_system`` on the same references); default from the settings.
    """

    def __init__(self, settings: dict, *, environment=(), mapper: str | None = None) -> None:
        self.settings = settings
        s = settings
        self.mapper_kind = mapper or s["mapper"]["kind"]
        if self.mapper_kind not in ("qp", "pinv"):
            raise ConfigError(f"mapper must be 'qp' or 'pinv'; got {self.mapper_kind!r}")
        self.configuration = Configuration.dual_ur5e()
        qp = s["qp"]
        self.camera_task = FrameTwistTask(
            "camera", weight=qp["camera_task"]["weight"], weight_frame="local", level=qp["camera_task"]["level"]
        )
        self.gripper_task = FrameTwistTask(
            "gripper", weight=qp["gripper_task"]["weight"], level=qp["gripper_task"]["level"]
        )
        roll_weight = qp["roll_task"]["weight"] if s["roll"]["enabled"] else 0.0
        self.roll_task = FrameTwistTask(
            "camera", weight=[0, 0, 0, 0, 0, roll_weight], weight_frame="local", level=qp["roll_task"]["level"]
        )
        self.posture_task = PostureTask(self.configuration.q, weight=qp["posture"]["weight"],
                                        level=qp["posture"]["level"])
        tasks = [self.camera_task, self.gripper_task, self.roll_task, self.posture_task,
                 DampingTask(self.configuration.nv, weight=qp["damping"]["weight"], level=qp["damping"]["level"])]
        from harvest_qp.config import build_tasks  # qp.extra_tasks: user tasks at their own level (issue 8)
        tasks += build_tasks(qp.get("extra_tasks", ()), self.configuration, where="qp.extra_tasks")
        limits = []
        for i, entry in enumerate(qp["limits"]):
            where = f"qp.limits[{i}]"
            if not isinstance(entry, dict) or "type" not in entry:
                raise ConfigError(f"{where}: each entry must be a mapping with a 'type' key, got {entry!r}")
            try:
                limits.append(_build_limit(entry, self.configuration, where, environment))
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
        self.qp = TaskController(self.configuration, tasks, limits, dt=0.002, solver=qp["solver"],
                                 max_acceleration=self.max_acceleration)
        backup = qp.get("backup_solver")
        self.qp_backup = (
            TaskController(self.configuration, tasks, self.qp.limits, dt=0.002, solver=backup,
                           max_acceleration=self.max_acceleration)
            if backup else None
        )
        self.pinv = PseudoInverseMapper(self.configuration, damping=s["mapper"]["pinv_damping"])
        self._camera_id = self.configuration.frame_id("camera")
        self._gripper_id = self.configuration.frame_id("gripper")
        self._build_references()
        self._build_obstacle_map()
        #: (per-sample swing clearance [m], the clearance asked [m]) of the last p_gd choice.
        self.last_swing_clearance = None
        #: How the last p_gd was chosen (``_target_within_swing``'s tier), for metrics.json.
        self.target_choice: str | None = None
        self.state = _State()
        self.dt = 0.002
        self._force_fraction_key: tuple[float, float] | None = None
        self._force_fraction = 0.0
        self.snapshots: dict[str, FrameSnapshot] = {}
        self.switch_snapshot: SwitchSnapshot | None = None
        #: Hand the runner the tick's values as one row and the active pairs as columns (its
        #: fast path); False: a dict and a list of tuples (the generic protocol, the same log).
        self._row_log = True
        self._last_pair_names: tuple | None = None  # _active_pair_columns' last names (reused while unchanged)
        # _camera_references' kernel output and views of its roll slots (for np.arctan2's out=).
        self._references_buffers = _reference_buffers(np.empty(_tick_kernels.OUT_SIZE))
        # (pinocchio data, its camera and gripper placements): live views of data.oMf's entries
        # (indexing oMf builds a new proxy each time, ~0.5 us), made again for another data
        # object and dropped on copy (__getstate__: a copied proxy would be a frozen copy).
        self._pose_refs: tuple | None = None
        # R_g R_hold^T, the approach's hold rotation before log3 (a scratch buffer of step's).
        self._hold_rotation = np.empty((3, 3))
        self._filter_fractions_key: tuple | None = None
        self._filter_fractions = (0.0, 0.0)
        #: Set to a dict to collect wall-clock times [s] per tick: "perception" (per new
        #: frame), "references" and "mapper" (the QP step or the pseudo-inverse).
        self.timing: dict[str, list[float]] | None = None

    def __getstate__(self) -> dict[str, Any]:
        # The cached placement proxies are live views into this controller's pinocchio data;
        # a copy (deepcopy, pickle) would hold frozen copies of them: made again on first use.
        state = self.__dict__.copy()
        state["_pose_refs"] = None
        return state

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

        m = self.settings["obstacle_map"]
        self.obstacle_map = None
        self.map_feed = None
        self._swing_capsules = []
        if not m["enabled"] or self.collision is None or self.mapper_kind != "qp":
            return
        if self.settings["obstacles"]["enabled"]:
            raise ConfigError("obstacle_map.enabled and obstacles.enabled both feed the collision limit; "
                              "expected at most one of them true")
        from harvest_qp.robot import description

        prefixes = ("cam_",) if m["arms"] == "camera" else ("cam_", "grasp_")
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
        try:
            self.obstacle_map = ObstacleMap(resolution=m["resolution"], clear_rays=m["clear_rays"])
            self.map_feed = MapCollisionFeed(
                self.collision, self.obstacle_map, self.configuration, per_capsule=m["per_capsule"],
                min_separation=m["min_separation"], margin=m["margin"], max_cells=m["max_cells"], capsules=capsules,
            )
            # The grasping arm's map rows only stop it ("no further approach"), never push
            # it: the map lies 5-15 mm short of the surface, so a gripper that starts near
            # the branch is inside d_s on the map, and separation rows then pushed it away
            # during the approach and pre-stretched the stem before the tare (seed 1:
            # true tension 5.6 N at the end, the wrist reading 3.0 N).
            self.collision.set_approach_only([c.name for c in capsules if c.name.startswith("grasp_")])
        except HarvestQPError as err:
            raise ConfigError(f"obstacle_map: {err}") from None

    def map_exclusions(self, T_g: np.ndarray) -> list:
        """Regions never mapped at gripper pose ``T_g``: the held cluster and the stem up to the
        latest p_sb (:func:`~harvest_qp.perception.obstacle_map.held_crop_exclusions`)."""
        from harvest_qp.perception.obstacle_map import held_crop_exclusions

        m = self.settings["obstacle_map"]
        return held_crop_exclusions(
            T_g, self.state.p_sb, grasp_offset=self.settings["perception"]["grasp_offset"],
            cluster_start=m["cluster_start"], cluster_length=m["cluster_length"], cluster_radius=m["cluster_radius"],
            stem_length=m["stem_length"], stem_radius=m["stem_radius"],
        )

    def _build_references(self) -> None:
        s = self.settings
        r, u, g = s["reaching"], s["unveiling"], s["grasping"]
        # V_cr reaches its sphere only asymptotically from outside (measured 1.01-1.05 r after
        # 15-30 s); aiming at target_radius_factor x r makes the camera end inside the ROI.
        self.reaching = ReachingCentering(
            radius=r["target_radius_factor"] * r["radius"], k_cp=r["k_cp"], k_co=r["k_co"],
            roi_time_constant=r["roi_time_constant"],
        )
        self.unveiling = Unveiling(
            k_c=u["k_c"], d_a=u["d_a"], d_o=u["d_o"], time_constant=u["time_constant"], max_linear=u["max_linear"],
            max_angular=u["max_angular"], min_pivot=u["min_pivot"], min_stem_points=self.settings["perception"][
                "min_stem_points"],
        )
        self.stretching = StemStretching(
            k_pg=g["k_pg"], k_og=g["k_og"], k_fp=g["k_fp"], k_fi=g["k_fi"], f_d=g["f_d"], max_speed=g["max_speed"],
            integration_threshold=g["integration_threshold"],
        )
        self.feed_forward = GraspFeedForward()

    @property
    def force_limit(self) -> float:
        """Abort above this stem force along n_c [N] (default 2 f_d)."""
        limit = self.settings["safety"]["force_limit"]
        return 2.0 * self.settings["grasping"]["f_d"] if limit is None else float(limit)

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
        self.configuration.update(q0)
        self.state = _State(hold_pose=self.configuration.frame_pose("gripper"))
        self.reaching.reset(self.configuration.frame_position("gripper"))
        self.unveiling.reset()
        self.stretching.reset()
        self.snapshots = {}
        self.switch_snapshot = None
        self.target_choice = None
        self.last_swing_clearance = None
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
        if s["unveiling"]["enabled"]:
            # Only the predicted mode reads the predicted stem (the law ignores it once
            # min_stem_points stem points are seen): not computed on the other frames.
            law = self.unveiling
            predicted_mode = s["unveiling"]["predicted_stem"] and frame.n_stem < law.min_stem_points
            # The paper mode reads only every k-th non-stem row (law.obstacle_stride): only those are
            # gathered (and checked by the law: a non-finite point it reads raises, naming them).
            thin = frame.n_stem > 0 and not predicted_mode
            obstacles = frame.non_stem_every(law.obstacle_stride(frame.n_non_stem)) if thin else frame.non_stem
            law.observe(frame.camera_position, frame.stem, obstacles,
                        predicted_stem_points=self._predicted_stem(T_g) if predicted_mode else None,
                        roi_centre=self.reaching.roi_centre, timestamp=frame.time)
        if self.collision is not None and s["obstacles"]["enabled"]:
            self._update_obstacle_spheres(frame.obstacles, T_g)
        if st.phase != Phase.APPROACH:
            return
        p = s["perception"]
        if frame.n_stem >= p["min_stem_points"]:
            fit = fit_stem(frame.stem, T_g[:3, 3])
            if fit.valid and np.linalg.norm(fit.base - T_g[:3, 3]) <= p["max_base_distance"]:
                frame.fit = fit
                st.p_sb = fit.base.copy()
                st.stem_length = fit.length
                st.stem_direction = fit.top.direction.copy()
                self.reaching.set_roi_centre(st.p_sb)
        st.frame = frame

    def _update_obstacle_spheres(self, points: np.ndarray, T_g: np.ndarray) -> None:
        """The vine seen in this frame as collision spheres for the QP (beyond the paper;
        :func:`~harvest_qp.perception.cloud_split.obstacle_sphere_centres`). Measured without
        it (default scene, lab contacts on): the gripper swinging the crop towards p_gd touched
        a leaf at 12 s, the wrist read 6 N of contact force and the episode aborted."""
        o = self.settings["obstacles"]
        centres = obstacle_sphere_centres(points, T_g, max_distance=o["max_distance"], voxel=o["voxel"],
                                          cluster_length=o["cluster_length"], cluster_radius=o["cluster_radius"])
        self.collision.set_obstacle_spheres(centres, o["radius"])

    def _grasp_obstacle_candidates(self, frame: _Frame) -> np.ndarray:
        """W - S without the robot's own points and the held crop (both move with the gripper).

        Deviation: the paper's O = (W - S) within S(p_sb, r_o) includes them. Measured on
        seed 1: every free sample within 30 deg of the hanging stem was occupied by the held
        crop's and gripper's own points, so no p_gd existed there and the episode never
        switched. The crop cannot be an obstacle to where it is taken.
        """
        if not self.settings["grasping"]["exclude_held_crop"]:
            return frame.non_stem
        o = self.settings["obstacles"]
        points = frame.obstacles
        return points[outside_held_cluster(points, self._switch_gripper_pose, cluster_length=o["cluster_length"],
                                           cluster_radius=o["cluster_radius"])]

    def _target_within_swing(self, free, stem_base: np.ndarray, *, T_g: np.ndarray) -> np.ndarray | None:
        """p_gd within ``grasping.max_swing_deg`` of the stem now, map-aware with
        ``grasping.swing_clearance`` (:func:`~harvest_qp.perception.grasp_target.choose_grasp_target`)."""
        g = self.settings["grasping"]
        swing = None
        if g["swing_clearance"] is not None and self.obstacle_map is not None and self._swing_capsules:
            capsules = []
            for frame, a, b, radius in self._swing_capsules:
                pose = self.configuration.frame_pose(frame)
                capsules.append((pose.act(a), pose.act(b), radius))
            swing = SwingCheck(self.obstacle_map, self.configuration.frame_position("gripper"), capsules,
                               clearance=g["swing_clearance"], stretch=g["swing_stretch"])
        top_of_crop = T_g[:3, 3] - self.settings["perception"]["grasp_offset"] * T_g[:3, 1]
        target = choose_grasp_target(free, stem_base, top_of_crop, max_swing_deg=g["max_swing_deg"], swing=swing)
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
        top_of_crop = T_g[:3, 3] - self.settings["perception"]["grasp_offset"] * T_g[:3, 1]
        return top_of_crop + np.linspace(0.0, 1.0, 12)[:, None] * (st.p_sb - top_of_crop)

    def _try_switch(self, t: float, obs: Observation) -> bool:
        """Recompute p_sb and p_gd on the latest frame; switch to the bimanual phase if both exist."""
        st, g = self.state, self.settings["grasping"]
        frame = st.frame
        if frame is None or frame.fit is None:
            return False
        fit = frame.fit
        length = fit.length
        r_o = length if g["r_o"] == "l" else float(g["r_o"])
        obstacles = obstacles_near_stem_base(self._grasp_obstacle_candidates(frame), fit.base, r_o)
        free = compute_free_space(obstacles, fit.base, length, frame.camera_position, n_samples=g["n_samples"])
        if not free.valid or free.target is None:
            return False
        target = self._target_within_swing(free, fit.base, T_g=self._switch_gripper_pose)
        if target is None:
            return False
        st.p_sb, st.p_gd, st.stem_length = fit.base.copy(), target, length
        self.switch_snapshot = SwitchSnapshot(
            t, frame.camera_pose, frame.stem, frame.non_stem, fit, obstacles, free, st.p_sb, st.p_gd
        )
        if "end" in self.snapshots:
            self.snapshots["switch"] = self.snapshots["end"]
        self.reaching.set_roi_centre(st.p_sb)
        self.stretching.reset()
        self.stretching.set_target(st.p_sb, st.p_gd)
        obs.tare_force()  # the bimanual phase starts from a tared sensor (subsec:grasp_contr)
        st.phase, st.t_switch = Phase.BIMANUAL, t
        st.last_stem_time = max(st.last_stem_time, t)
        return True

    # ------------------------------------------------------------------ control

    def _abort(self, t: float, reason: str) -> None:
        st = self.state
        if st.phase != Phase.ABORT:
            st.phase, st.abort_reason, st.t_abort = Phase.ABORT, reason, t

    def _safe_stop(self) -> np.ndarray:
        prev = self.state.previous_qdot
        step = self.max_acceleration * self.dt
        return prev - np.clip(prev, -step, step)

    def _camera_speeds(self, t: float, T_c: np.ndarray, *, measure: bool = True) -> tuple[float, float]:
        """Mean camera speeds over the last ``switch.window`` [m/s], [rad/s] for the switch rule.

        Linear: displacement of p_c over the window / window; angular: the angle turned by the
        optical axis z_c over the window / window, so the free roll about z_c is left out.
        Deviation: the paper compares the instantaneous tip speeds; with V_cu acting, the
        camera dithers about a fixed view (measured +-0.06 rad/s on seed 1) and never met
        0.025 rad/s in 35 s, while its mean motion was nil.

        Records the pose (:meth:`_record_camera`); (inf, inf) until the window is full or
        without ``measure``. :meth:`step` records every tick and computes only the speeds
        the switch test reaches (:meth:`_linear_speed`, :meth:`_angular_speed`).
        """
        start = self._record_camera(t, T_c)
        if not measure or start is None:
            return float("inf"), float("inf")
        return self._linear_speed(T_c, start), self._angular_speed(T_c, start)

    def _record_camera(self, t: float, T_c: np.ndarray) -> tuple | None:
        """Add this tick's camera pose to the window; (t, t0, T0) of its first entry once the
        window spans ``switch.window``, else None."""
        history = self.state.camera_history
        # T_c is this tick's own new array (never modified): kept whole, p_c and z_c read
        # from it when a speed is computed.
        history.append((t, T_c))
        window = self.settings["switch"]["window"]
        while len(history) > 1 and history[1][0] <= t - window + 1e-12:
            history.popleft()
        t0, T0 = history[0]
        return None if t - t0 < window - 1e-9 else (t, t0, T0)

    @staticmethod
    def _linear_speed(T_c: np.ndarray, start: tuple) -> float:
        t, t0, T0 = start
        moved = T_c[:3, 3] - T0[:3, 3]
        return math.sqrt(float(moved.dot(moved))) / (t - t0)  # = np.linalg.norm, bit for bit

    @staticmethod
    def _angular_speed(T_c: np.ndarray, start: tuple) -> float:
        t, t0, T0 = start
        z0 = T0[:3, 2]
        # np.arccos, not math.acos: the two differ in the last bit on ~10 % of arguments.
        return float(np.arccos(min(max(float(z0.dot(T_c[:3, 2])), -1.0), 1.0))) / (t - t0)

    def _camera_twist(self, T_c: np.ndarray, dt: float, rows: list | None = None) -> list[float]:
        """V_cr + keep-out + V_cu of this tick as 6 Python floats [m/s; rad/s] (advances the
        p_r and V_cu filters).

        Speed (every tick): element-wise steps on Python floats, each the IEEE operation of the
        numpy expression it replaces (``reaching.update(T_c, dt) + self._keep_out(T_c) +
        unveiling.update(dt)``), in the same order, and numpy's own dot products: the same
        bits (tests/loop/test_fast_paths.py) at a fraction of the cost. ``rows``:
        ``T_c[:3].tolist()`` if the caller has it.
        """
        s = self.settings
        reaching = self.reaching
        if rows is None:
            rows = T_c[:3].tolist()
        V = reaching._update_floats(T_c, dt, rows)  # V_cr
        # The keep-out term (_keep_out); |p_c - p_r| is bit for bit reaching's |p_r - p_c|.
        distance = reaching.distance
        r = s["reaching"]
        minimum = r["min_distance_factor"] * r["radius"]
        if minimum > 0 and 1e-9 < distance < minimum:
            gain = r["k_keep_out"] * (minimum - distance)
            (_, _, _, c0), (_, _, _, c1), (_, _, _, c2) = rows
            p0, p1, p2 = reaching.roi_centre.tolist()
            V = [V[0] + gain * (c0 - p0) / distance, V[1] + gain * (c1 - p1) / distance,
                 V[2] + gain * (c2 - p2) / distance, V[3] + 0.0, V[4] + 0.0, V[5] + 0.0]
            if s["unveiling"]["enabled"]:
                return [v + u for v, u in zip(V, self.unveiling._update_list(dt))]
            return [v + 0.0 for v in V]
        # V_cr + zeros (as the numpy sum did: -0.0 becomes 0.0), then + V_cu or + zeros.
        if s["unveiling"]["enabled"]:
            return [(v + 0.0) + u for v, u in zip(V, self.unveiling._update_list(dt))]
        return [(v + 0.0) + 0.0 for v in V]

    def _camera_references(self, T_c: np.ndarray, dt: float, rows: list,
                           direction: np.ndarray) -> tuple[list[float], np.ndarray, float]:
        """:meth:`_camera_twist` and :meth:`_roll_reference` of one tick: (V as 6 Python floats,
        the roll twist, the roll angle [rad] or NaN), advancing the p_r and V_cu filters.

        Speed (every tick): one compiled call (``_tick_kernels.camera_references``: the same
        IEEE operations, numpy's dot products reproduced bit for bit) instead of ~20 small
        numpy calls; np.arctan2 stays numpy's. The two Python methods remain the reference and
        take over where the kernel does not apply (a zero filter time constant, no ROI centre
        yet, the degenerate minimum rotation). ``rows``: ``T_c[:3].tolist()``.
        """
        reaching, unveiling = self.reaching, self.unveiling
        s = self.settings
        unveil = s["unveiling"]["enabled"]
        tau_r, tau_u = reaching.roi_time_constant, unveiling.time_constant
        if (
            tau_r != 0.0
            and (tau_u != 0.0 or not unveil)
            and reaching.roi_centre is not None
            and reaching._roi_target is not None
        ):
            key = (dt, tau_r, tau_u)
            if self._filter_fractions_key != key:  # the filters' -expm1(-dt / tau), per (dt, tau)
                self._filter_fractions_key = key
                self._filter_fractions = (-math.expm1(-dt / tau_r), -math.expm1(-dt / tau_u) if tau_u else 0.0)
            fraction_r, fraction_u = self._filter_fractions
            r = s["reaching"]
            buffers = self._references_buffers
            out, roll_y, roll_x, roll_angle = buffers
            if roll_angle.base is not out:  # a copied controller (deepcopy, pickle): views made again
                out, roll_y, roll_x, roll_angle = self._references_buffers = _reference_buffers(out)
            p_r = np.empty(3)
            value = np.empty(6)
            u0, u1, u2 = direction.tolist()
            code = _tick_kernels.camera_references(
                T_c, reaching.roi_centre, reaching._roi_target, fraction_r, reaching.radius**2,
                reaching.k_cp, reaching.k_co, r["min_distance_factor"] * r["radius"], r["k_keep_out"],
                unveil, unveiling.value, unveiling.raw, fraction_u, u0, u1, u2, out, p_r, value,
            )
            if code != _tick_kernels.DEGENERATE:
                if code == _tick_kernels.DONE:
                    # np.arctan2 (not math.atan2, which differs in the last bit), as _roll_reference,
                    # on views of the kernel's output and into it (a third of the scalar call's time).
                    np.arctan2(roll_y, roll_x, out=roll_angle)
                v0, v1, v2, v3, v4, v5, theta, distance, _, _, angle = out.tolist()
                reaching.roi_centre = p_r
                reaching.theta = theta
                reaching.distance = distance
                if unveil:
                    unveiling.value = value
                V = [v0, v1, v2, v3, v4, v5]
                if code != _tick_kernels.DONE:
                    return V, np.zeros(6), float("nan")
                angle = (angle + math.pi / 2) % math.pi - math.pi / 2  # _wrap_half_turn
                gain = s["roll"]["k_roll"] * angle
                (_, _, z0, _), (_, _, z1, _), (_, _, z2, _) = rows
                # np.zeros and three items: the array np.array((0.0, 0.0, 0.0, ...)) built (cheaper).
                roll = np.zeros(6)
                roll[3], roll[4], roll[5] = gain * z0, gain * z1, gain * z2
                return V, roll, angle
        V = self._camera_twist(T_c, dt, rows)
        roll, roll_error = self._roll_reference(T_c, direction, rows)
        return V, roll, roll_error

    def _hold_twist(self, T_g: np.ndarray) -> np.ndarray:
        """V_g of the approach: the grasping arm held at its initial pose (gain ``grasping.k_hold``).

        -k_hold [p_g - p_hold; log3(R_g R_hold^T)] in a new array: k (p_g - p_hold) and
        R_g R_hold^T in one compiled call (numpy's expression bit for bit,
        _tick_kernels.hold_terms, which writes the first three slots; the rotation goes to a
        scratch buffer), then k log3(...) (pinocchio's log3) into the last three
        (tests/loop/test_fast_paths.py, tests/loop/test_tick_caches.py)."""
        k = -self.settings["grasping"]["k_hold"]
        st = self.state
        twist = np.empty(6)
        rotation = self._hold_rotation
        _tick_kernels.hold_terms(T_g, st.hold_translation, st.hold_rotation_T, k, twist, rotation)
        w0, w1, w2 = pin.log3(rotation).tolist()
        twist[3], twist[4], twist[5] = k * w0, k * w1, k * w2
        return twist

    def _keep_out(self, T_c: np.ndarray) -> np.ndarray:
        """Outward speed below the minimum distance from the ROI centre (beyond the paper).

        Inside the ROI V_cr's translation is zero, so nothing in the paper's laws stops the
        camera drifting inwards while V_cu acts (measured: from 0.43 m to 0.05 m from p_sb on
        the default scene without occluder, colliding with the vine and blind below the
        camera's 0.1 m minimum depth). :meth:`step` computes the same on Python floats.
        """
        r = self.settings["reaching"]
        minimum = r["min_distance_factor"] * r["radius"]
        offset = T_c[:3, 3] - self.reaching.roi_centre
        distance = float(np.linalg.norm(offset))
        twist = np.zeros(6)
        if minimum > 0 and 1e-9 < distance < minimum:
            twist[:3] = r["k_keep_out"] * (minimum - distance) * offset / distance
        return twist

    def _roll_reference(self, T_c: np.ndarray, direction: np.ndarray | None,
                        rows: list | None = None) -> tuple[np.ndarray, float]:
        """World twist turning the camera about z_c so that the blade (x_c) is across the stem.

        Python floats for the element-wise steps, numpy for the dot products and arctan2: the
        same bits as the numpy formula (tests/loop/test_fast_paths.py). ``rows``:
        ``T_c[:3].tolist()`` if the caller has it."""
        if direction is None:
            return np.zeros(6), float("nan")
        z, y = T_c[:3, 2], T_c[:3, 1]
        (_, y0, z0, _), (_, y1, z1, _), (_, y2, z2, _) = T_c[:3].tolist() if rows is None else rows
        along = float(direction.dot(z))  # a Python float: the element-wise steps below on floats
        u0, u1, u2 = direction.tolist()
        d0, d1, d2 = u0 - along * z0, u1 - along * z1, u2 - along * z2  # direction - (direction @ z) z
        d = np.array((d0, d1, d2))
        if math.sqrt(float(d.dot(d))) < 1e-6:  # = np.linalg.norm, bit for bit
            return np.zeros(6), float("nan")
        cross = np.array((y1 * d2 - y2 * d1, y2 * d0 - y0 * d2, y0 * d1 - y1 * d0))  # y x d
        # np.arctan2 (not math.atan2, which differs in the last bit) on the same numpy scalars.
        angle = _wrap_half_turn(float(np.arctan2(cross.dot(z), y.dot(d))))
        gain = self.settings["roll"]["k_roll"] * angle
        return np.array((0.0, 0.0, 0.0, gain * z0, gain * z1, gain * z2)), angle

    def step(self, obs: Observation) -> Command:
        # Speed (this runs every 2 ms tick): the reference laws are called through their
        # unchecked private paths (the arguments are the loop's own, already well-formed) and
        # the 3-vector arithmetic runs on Python floats; every numpy dot product and numpy
        # transcendental of the checked version is kept, so the results are bit-identical.
        st, s = self.state, self.settings
        t = float(obs.time)
        if not math.isfinite(t):
            # Checked here: the camera-speed window and every timer compare against t, and a
            # NaN would stay in the window and stop it sliding (an audit of the fast paths).
            raise InvalidInputError(f"HarvestController.step: observation time must be finite [s], got {obs.time!r}")
        config = self.configuration
        config.update(obs.q)
        data = config.data
        poses = self._pose_refs
        if poses is None or poses[0] is not data:
            poses = self._pose_refs = (data, data.oMf[self._camera_id], data.oMf[self._gripper_id])
        # The same matrices as _pose_matrix(data.oMf[i]) (the proxies read the live placements).
        T_c = poses[1].homogeneous
        T_g = poses[2].homogeneous
        rows_c = T_c[:3].tolist()  # the camera pose's first three rows as floats, read by several laws
        timing = self.timing
        if obs.new_cloud and obs.cloud is not None:
            t0 = time.perf_counter()
            self._perceive(obs.cloud, T_g)
            if self.obstacle_map is not None:
                self.obstacle_map.update(obs.cloud, exclude=self.map_exclusions(T_g))
            if timing is not None:
                timing.setdefault("perception", []).append(time.perf_counter() - t0)
        t_ref = time.perf_counter() if timing is not None else 0.0

        phase = st.phase
        if phase == _APPROACH:
            if st.p_sb is None and t > s["safety"]["no_stem_timeout"]:
                self._abort(t, f"no stem base found within {s['safety']['no_stem_timeout']} s")
            else:
                start = self._record_camera(t, T_c)
                self._switch_gripper_pose = T_g
                if st.p_sb is not None and start is not None:
                    # switch_ready's test (subsec:biman_coord; a window not yet full is never
                    # ready), each speed computed only if the test gets to it.
                    sw = s["switch"]
                    offset = self.reaching.roi_centre - T_c[:3, 3]
                    distance = math.sqrt(float(offset.dot(offset)))  # = np.linalg.norm, bit for bit
                    if (
                        distance <= sw["distance_factor"] * s["reaching"]["radius"]
                        and self._linear_speed(T_c, start) < sw["max_linear_speed"]
                        and self._angular_speed(T_c, start) < sw["max_angular_speed"]
                    ):
                        self._try_switch(t, obs)
        elif phase == _BIMANUAL or phase == _PRECUT:
            if t - st.last_stem_time > s["safety"]["stem_lost_timeout"]:
                self._abort(t, f"stem not seen for {s['safety']['stem_lost_timeout']} s in the bimanual phase")

        roll_error = None  # logged as value/roll_error when the references ran
        map_cells = None  # logged as value/map_cells when the map fed the QP
        V_c = _ZEROS6
        V_g = _ZEROS6
        roll = None
        force_nc = float("nan")
        roi_distance = None
        phase = st.phase
        if phase != _ABORT:
            dt = self.dt
            if phase == _APPROACH:
                direction = st.stem_direction if st.stem_direction is not None else T_g[:3, 1]
            else:
                direction = self.stretching.n_c  # set at the switch (StemStretching.set_target)
            # V_cr + keep-out + V_cu (6 floats) and the roll reference of the blade across the stem.
            V, roll, roll_error = self._camera_references(T_c, dt, rows_c, direction)
            roi_distance = self.reaching.distance  # |p_r - p_c| with this tick's filtered p_r
            if phase == _APPROACH:
                V_g = self._hold_twist(T_g)
            else:
                # The wrist force is the robot's reading: checked as StemStretching.update does
                # (a float64 (3,) array's finiteness by the compiled law, before any state changes).
                force = obs.force if t > st.t_switch else np.zeros(3)
                if type(force) is not np.ndarray or force.dtype is not _FLOAT64 or force.shape != (3,):
                    force = as_position(force, "force")
                stretching = self.stretching
                V_g_floats = stretching._update_floats(T_g, force, dt, check_force="force")
                V_g = np.array(V_g_floats)
                force_nc = stretching.force_along_nc  # float(n_c @ force)
                if s["grasping"]["feed_forward"]:
                    (_, _, _, c0), (_, _, _, c1), (_, _, _, c2) = rows_c
                    b0, b1, b2 = st.p_sb.tolist()
                    terms = self.feed_forward._terms(V_g_floats[:3], [c0 - b0, c1 - b1, c2 - b2])
                    V = [v + w for v, w in zip(V, terms)]
                if force_nc > self.force_limit:
                    self._abort(t, f"stem force {force_nc:.2f} N above the limit {self.force_limit:.2f} N")
                else:
                    # The pre-cut test uses the force low-passed over precut.force_time_constant:
                    # with 0.2 N sensor noise the raw samples leave the +-10 % band on ~13 % of ticks.
                    tau = s["precut"]["force_time_constant"]
                    if st.force_filtered is None or tau == 0:
                        st.force_filtered = force_nc
                    else:
                        st.force_filtered += self._force_filter_fraction(dt, tau) * (force_nc - st.force_filtered)
                    self._check_precut(t, st.force_filtered)
            V_c = np.array(V)

        t_map = time.perf_counter() if timing is not None else 0.0
        phase = st.phase
        if phase == _ABORT:
            qdot = self._safe_stop()
            status = f"abort: {st.abort_reason}"
            if st.t_at_rest is None and not np.any(qdot):
                st.t_at_rest = t
        elif self.mapper_kind == "pinv":
            qdot = self.pinv.map(np.concatenate([V_c, V_g]))
            status = "ok"
        else:
            self.camera_task.set_reference(V_c)
            self.gripper_task.set_reference(V_g)
            self.roll_task.set_reference(roll)
            if self.map_feed is not None:
                map_cells = float(self.map_feed.update(obs.q))
            backup_solver = self.qp_backup
            previous = self.qp.previous_qdot.copy() if backup_solver is not None else None
            result = self.qp._step(obs.q, reuse_kinematics=True)
            ok = result.ok
            if not ok and backup_solver is not None:
                # Stopgap until the QP core retries itself (issue 10 section 1): daqp answers
                # slightly outside the constraints (2e-7..1e-6) and the core brakes; the same
                # problem is re-solved by the backup backend from the same previous command.
                backup_solver.previous_qdot = previous
                backup = backup_solver._step(obs.q, reuse_kinematics=True)
                if backup.ok:
                    st.backup_solves += 1
                    result = backup
                    result.status = f"{backup.status} (backup solver)"
                    ok = True  # backup.ok: its status, with a suffix, starts as an ok status
            qdot, status = result.qdot, result.status
            if ok:
                st.qp_failures_in_row = 0
            else:
                st.qp_failures += 1
                st.qp_failures_in_row += 1
                if st.qp_failures_in_row >= s["safety"]["max_qp_failures"]:
                    self._abort(t, f"{st.qp_failures_in_row} QP failures in a row ({status})")
        if timing is not None:
            t_end = time.perf_counter()
            timing.setdefault("references", []).append(t_map - t_ref)
            timing.setdefault("mapper", []).append(t_end - t_map)
        if type(qdot) is not np.ndarray or qdot.dtype is not _FLOAT64:
            qdot = np.asarray(qdot, float)
        phase = st.phase
        if phase != _ABORT:
            self.qp.previous_qdot = qdot
        st.previous_qdot = qdot

        if self._row_log:
            values = self._log_row(T_c, V_c, V_g, force_nc, roi_distance, roll_error, map_cells, rows=rows_c)
            pairs = self._active_pair_columns()
        else:  # the generic protocol: a dict of values, a list of pair tuples
            values = {}
            if roll_error is not None:
                values["roll_error"] = roll_error
            if map_cells is not None:
                values["map_cells"] = map_cells
            self._log_values(T_c, V_c, V_g, force_nc, into=values, roi_distance=roi_distance)
            pairs = self._active_pairs()
        done = False
        if phase == _PRECUT:
            end_after = s["episode"]["end_after_precut"]
            done = end_after is not None and t - st.t_precut >= end_after
        elif phase == _ABORT:
            done = st.t_at_rest is not None and t - st.t_at_rest >= s["episode"]["stop_after_abort"]
        return _command(qdot, status, values, pairs, done)

    def _force_filter_fraction(self, dt: float, tau: float) -> float:
        """-expm1(-dt / tau), the pre-cut force filter's step fraction: numpy's expm1 (as
        before; libm's may differ in the last bit), computed once per (dt, tau)."""
        key = (dt, tau)
        if self._force_fraction_key != key:
            self._force_fraction_key = key
            # A Python float (the same value): the filter and the pre-cut test then run on
            # Python floats, not numpy scalars (the same IEEE operations, cheaper).
            self._force_fraction = float(-np.expm1(-dt / tau))
        return self._force_fraction

    def _check_precut(self, t: float, force_nc: float) -> None:
        st, p, g = self.state, self.settings["precut"], self.settings["grasping"]
        within = (
            abs(force_nc - g["f_d"]) <= p["force_tolerance"] * g["f_d"]
            and self.stretching.position_error <= p["position_tolerance"]
            # math.degrees: x * (180 / pi), the same product as np.degrees (tests/loop/test_tick_paths.py).
            and math.degrees(self.stretching.alignment) <= p["alignment_tolerance_deg"]
        )
        if not within:
            st.precut_since = None
            return
        if st.precut_since is None:
            st.precut_since = t
        if st.phase == Phase.BIMANUAL and t - st.precut_since >= p["hold_time"]:
            st.phase, st.t_precut = Phase.PRECUT, t

    def _log_values(self, T_c: np.ndarray, V_c: np.ndarray, V_g: np.ndarray, force_nc: float, *,
                    into: dict[str, Any] | None = None, roi_distance: float | None = None) -> dict[str, Any]:
        """The per-tick values for the log (``value/<name>``), added to ``into`` (a new dict by default).

        ``roi_distance``: |p_r - p_c| [m] if already computed this tick with the current p_r
        (:attr:`ReachingCentering.distance` right after its update), else computed here.
        The arrays are the controller's own (views of this tick's poses, the reference laws'
        latest outputs, a shared read-only NaN vector): the runner copies them into its log.
        """
        st = self.state
        values = {} if into is None else into
        bimanual = st.phase == Phase.BIMANUAL or st.phase == Phase.PRECUT or st.t_switch is not None
        reaching, stretching = self.reaching, self.stretching
        if roi_distance is None:
            offset = reaching.roi_centre - T_c[:3, 3]
            roi_distance = math.sqrt(float(offset @ offset))  # = np.linalg.norm, bit for bit
        nan = math.nan
        # One dict display merged in (the same keys in the same order as item by item).
        values.update({
            "phase": float(st.phase),
            "p_r": reaching.roi_centre,
            "p_c": T_c[:3, 3],
            "z_c": T_c[:3, 2],
            "x_c": T_c[:3, 0],
            "p_sb": st.p_sb if st.p_sb is not None else _NAN3,
            "p_gd": st.p_gd if st.p_gd is not None else _NAN3,
            "n_c": stretching.n_c if bimanual else _NAN3,
            "V_c": V_c,
            "V_g": V_g,
            "force_nc": force_nc,
            "theta": reaching.theta,
            "roi_distance": roi_distance,
            "position_error": stretching.position_error if bimanual else nan,
            "alignment": stretching.alignment if bimanual else nan,
            "unveiling_pairs": float(self.unveiling.n_pairs),
        })
        return values

    def _active_pair_indices(self) -> tuple[Any, np.ndarray | None]:
        """The collision limit and the indices (int64) of its pairs active in this tick's QP;
        ``(limit, None)`` when there are none (no limit, the pinv mapper, no active pair)."""
        lim = self.collision
        if lim is None or self.mapper_kind != "qp":
            return lim, None
        active = getattr(lim, "active_pairs", ())
        if type(active) is not np.ndarray or active.dtype is not _INT64:  # (identity: no dtype built)
            active = np.asarray(active, dtype=np.int64)
        return lim, (active if active.size else None)

    def _active_pairs(self) -> list[tuple[str, str, float]]:
        lim, active = self._active_pair_indices()
        if active is None:
            return []
        names = lim.capsule_names
        distances = getattr(lim, "_dist", None)
        # One fancy index and tolist() per column instead of numpy scalar indexing per pair,
        # and the tuples built by zip (tolist() already gives Python floats).
        first = lim.pair_a[active].tolist()
        second = lim.pair_b[active].tolist()
        gaps = distances[active].tolist() if distances is not None else [float("nan")] * len(first)
        lookup = names.__getitem__
        return list(zip(map(lookup, first), map(lookup, second), gaps))

    def _log_row(self, T_c: np.ndarray, V_c: np.ndarray, V_g: np.ndarray, force_nc: float,
                 roi_distance: float | None, roll_error: float | None, map_cells: float | None, *,
                 rows: list | None = None) -> _ValueRow:
        """:meth:`_log_values` (after ``roll_error`` and ``map_cells``, each given when not None) as
        one float64 row for the runner (``runner._ValueRow``; it reads as the same mapping).

        Speed (every tick): one array built from a list of Python floats (the same float64
        values: conversions between float64 and Python floats are exact), which the runner
        copies into its log in one assignment, instead of ~18 entries checked and copied one
        by one (tests/loop/test_tick_paths.py compares it with :meth:`_log_values`, and whole
        episodes' logs with the generic protocol).
        """
        st = self.state
        phase = st.phase
        bimanual = phase == _BIMANUAL or phase == _PRECUT or st.t_switch is not None
        reaching, stretching = self.reaching, self.stretching
        if roi_distance is None:
            offset = reaching.roi_centre - T_c[:3, 3]
            roi_distance = math.sqrt(float(offset @ offset))  # = np.linalg.norm, bit for bit
        if type(V_c) is np.ndarray and type(V_g) is np.ndarray and reaching.roi_centre is not None:
            # The loop's path (V_c and V_g are the arrays it handed to the QP): the row written
            # by one compiled copy (_tick_kernels.log_row) instead of ~8 tolist and a list of 44
            # floats; the same values (copies), NaN where the floats below put NaN.
            nan = math.nan
            with_map = self.map_feed is not None
            layout = _LAYOUT_WITH_MAP if with_map else _LAYOUT_WITHOUT_MAP
            row = np.empty(layout.width)
            _tick_kernels.log_row(
                row, with_map, nan if roll_error is None else roll_error, nan if map_cells is None else map_cells,
                float(phase), reaching.roi_centre, T_c, _NAN3_KERNEL if st.p_sb is None else st.p_sb,
                _NAN3_KERNEL if st.p_gd is None else st.p_gd, stretching.n_c if bimanual else _NAN3_KERNEL,
                _ZEROS6_KERNEL if V_c is _ZEROS6 else V_c, _ZEROS6_KERNEL if V_g is _ZEROS6 else V_g, force_nc,
                reaching.theta, roi_distance, stretching.position_error if bimanual else nan,
                stretching.alignment if bimanual else nan, float(self.unveiling.n_pairs),
            )
            return _ValueRow._built(layout, row, _missing_names(roll_error, map_cells, with_map))
        (x0, _, z0, c0), (x1, _, z1, c1), (x2, _, z2, c2) = T_c[:3].tolist() if rows is None else rows
        nan = math.nan
        with_map = self.map_feed is not None
        row = [nan if roll_error is None else roll_error]
        if with_map:
            row.append(nan if map_cells is None else map_cells)
        row += [float(phase), *reaching.roi_centre.tolist(), c0, c1, c2, z0, z1, z2, x0, x1, x2]
        row += _NAN3_LIST if st.p_sb is None else st.p_sb.tolist()
        row += _NAN3_LIST if st.p_gd is None else st.p_gd.tolist()
        row += stretching.n_c.tolist() if bimanual else _NAN3_LIST
        row += V_c if type(V_c) is list else V_c.tolist()  # the loop hands its V_c floats
        row += V_g if type(V_g) is list else V_g.tolist()  # the hold twist's floats in the approach
        row += (force_nc, reaching.theta, roi_distance, stretching.position_error if bimanual else nan,
                stretching.alignment if bimanual else nan, float(self.unveiling.n_pairs))
        missing = _missing_names(roll_error, map_cells, with_map)
        layout = _LAYOUT_WITH_MAP if with_map else _LAYOUT_WITHOUT_MAP
        # np.fromiter: each Python float to float64 exactly, half the time of np.array(row).
        # The missing names' slots hold NaN already (built above): no check needed (_built).
        return _ValueRow._built(layout, np.fromiter(row, np.float64, layout.width), missing)

    def _active_pair_columns(self) -> _PairColumns | list:
        """:meth:`_active_pairs` as three columns (``runner._PairColumns``, read as the same
        tuples): no tuple built per pair here, none checked by the runner."""
        lim, active = self._active_pair_indices()
        if active is None:
            return []
        distances = getattr(lim, "_dist", None)
        # Python floats of float64 values (what _PairColumns' constructor made of the array).
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
        return _PairColumns._built(first, second, distances)  # lists of one length: no check needed

    # ------------------------------------------------------------------ summary

    @property
    def phase(self) -> Phase:
        return self.state.phase
