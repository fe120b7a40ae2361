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

Phases (``subsec:biman_coord``, :mod:`harvest_qp.loop.phases`): ``approach`` (camera arm
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
* The switch rule uses the camera's mean speeds over ``switch.window`` (0.5 s)
  (:mod:`harvest_qp.loop.phases`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numba import njit

from harvest_qp.baseline import PseudoInverseMapper
from harvest_qp.config import _build_limit
from harvest_qp.configuration import Configuration
from harvest_qp.controller import TaskController
from harvest_qp.exceptions import ConfigError, HarvestQPError, InvalidInputError
from harvest_qp.interface import OBSTACLE, STEM, PointCloud, RobotInterface
from harvest_qp.limits import CollisionAvoidance, JointAccelerationLimit
from harvest_qp.loop.phases import Phase, PhaseMachine, PhaseRules
from harvest_qp.perception import compute_free_space, fit_stem, obstacles_near_stem_base
from harvest_qp.references import (
    GraspFeedForward,
    HoldPose,
    ReachingCentering,
    StemStretching,
    Unveiling,
    keep_out_velocity,
    predicted_stem_points,
    roll_reference,
)
from harvest_qp.runner import Command, Observation, _command, _PairColumns, _ValueLayout, _ValueRow
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


class _Frame:
    """Perception of one frame during the approach.

    ``obstacles`` and ``non_stem`` (``(n, 3)`` [m]) are gathered from the cloud on first use:
    only the frame at the switch needs them (~0.3 ms per 848x480 frame otherwise).
    """

    def __init__(self, time: float, camera_position: np.ndarray, camera_pose: np.ndarray, stem: np.ndarray,
                 non_stem: _LabelRows, obstacles: _LabelRows, fit: Any = None) -> None:
        self.time = time
        self.camera_position = camera_position
        self.camera_pose = camera_pose
        self.stem = stem
        self._non_stem = non_stem
        self._obstacles = obstacles
        self.fit = fit

    @property
    def non_stem(self) -> np.ndarray:
        return self._non_stem[::1]

    @property
    def obstacles(self) -> np.ndarray:
        return self._obstacles[::1]


@dataclass
class _State:
    """What the controller knows of the scene and its own last command (the phase and its
    timers are :class:`~harvest_qp.loop.phases.PhaseMachine`'s)."""

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


@dataclass(frozen=True)
class _MapCapsule:
    """An arm capsule queried against the obstacle map (MapCollisionFeed's ``capsules``)."""

    name: str
    frame: str
    p0: Any
    p1: Any
    radius: float


#: Capsules of the grasping arm checked along the swing to p_gd: the gripper and the two wrist
#: links next to it, which move (nearly) rigidly with the gripper while it swings the crop.
_SWING_CAPSULES = ("grasp_gripper", "grasp_wrist_3", "grasp_wrist_2")

#: Fractions of the swing (hanging stem -> p_gd) at which the gripper is checked against the map.
_SWING_FRACTIONS = (0.25, 0.5, 0.75, 1.0)


def _rotations_between(a: np.ndarray, b: np.ndarray, fractions) -> np.ndarray:
    """Rotations by ``fractions`` of the shortest turn from unit ``a`` to each unit ``b[i]``: ``(n, f, 3, 3)``."""
    axis = np.cross(a, b)
    sin = np.linalg.norm(axis, axis=1)
    cos = np.clip(b @ a, -1.0, 1.0)
    angle = np.arctan2(sin, cos)
    unit = np.where(sin[:, None] > 1e-12, axis / np.maximum(sin, 1e-12)[:, None], 0.0)
    K = np.zeros((len(b), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -unit[:, 2], unit[:, 1], -unit[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = unit[:, 2], -unit[:, 1], unit[:, 0]
    K2 = K @ K
    f = np.asarray(fractions, float)
    th = angle[:, None] * f[None, :]
    return (np.eye(3) + np.sin(th)[..., None, None] * K[:, None] + (1 - np.cos(th))[..., None, None] * K2[:, None])


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
#: The tick's values as one row for the runner (runner._ValueRow), with and without the map's cell count.
_LAYOUT_WITH_MAP = _ValueLayout((("roll_error", ()), ("map_cells", ()), *_LOGGED_VALUES))
_LAYOUT_WITHOUT_MAP = _ValueLayout((("roll_error", ()), *_LOGGED_VALUES))


_ROW = np.dtype((np.void, 24))


def _rows(points: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``points[mask]`` for ``(n, 3)`` points and a boolean ``(n,)`` mask, as a new array.

    numpy's boolean indexing of a 2-D array copies element by element (measured 3.0 ms for
    190k of 193k rows at 848x480); on a view with one 24-byte record per row it copies whole
    rows (0.5 ms). The bytes, hence the values, are the same.
    """
    if points.dtype == np.float64 and points.ndim == 2 and points.shape[1] == 3 and points.flags.c_contiguous:
        return points.view(_ROW).reshape(-1)[mask].view(np.float64).reshape(-1, 3)
    return points[mask]


@njit(cache=True)
def _scan_cloud(points, labels, stem_label):  # pragma: no cover (compiled)
    """(number of rows labelled ``stem_label``, whether every coordinate is finite).

    Two branch-free loops that LLVM vectorises: the label count, and ``x - x != 0`` (true
    for NaN and +-inf only) OR-ed over the flat coordinates."""
    n_stem = 0
    for i in range(labels.shape[0]):
        n_stem += labels[i] == stem_label
    flat = points.reshape(-1)
    bad = False
    for i in range(flat.shape[0]):
        x = flat[i]
        bad |= (x - x) != 0.0
    return n_stem, not bad


@njit(cache=True)
def _gather_labelled(points, labels, label, equal, stride, count):  # pragma: no cover (compiled)
    """Every ``stride``-th row of ``points`` whose label is (``equal``) / is not (not ``equal``)
    ``label``, in order: ``points[labels == label][::stride]``; ``count`` is that number of rows."""
    out = np.empty((count, 3))
    skip = 0  # matching rows left to pass over before the next one taken
    k = 0
    for i in range(labels.shape[0]):
        if (labels[i] == label) == equal:
            if skip == 0:
                if k < count:  # never past the end, whatever the caller's count
                    out[k, 0] = points[i, 0]
                    out[k, 1] = points[i, 1]
                    out[k, 2] = points[i, 2]
                k += 1
                skip = stride - 1
            else:
                skip -= 1
    if k != count:
        raise ValueError("_gather_labelled: the row count does not match the labels")
    return out


@njit(cache=True)
def _count_label(labels, label):  # pragma: no cover (compiled)
    """Number of ``labels`` equal to ``label`` (a branch-free loop LLVM vectorises)."""
    n = 0
    for i in range(labels.shape[0]):
        n += labels[i] == label
    return n


@njit(cache=True)
def _split_labelled(points, labels, label, n_label, stride, n_other):  # pragma: no cover (compiled)
    """``(points[labels == label], points[labels != label][::stride], every coordinate finite)``
    in one pass over the cloud; ``n_label``, ``n_other``: the two row counts (``n_other``
    after the stride)."""
    first = np.empty((n_label, 3))
    other = np.empty((n_other, 3))
    skip = 0
    j = 0
    k = 0
    bad = False
    for i in range(labels.shape[0]):
        x0 = points[i, 0]
        x1 = points[i, 1]
        x2 = points[i, 2]
        bad |= ((x0 - x0) + (x1 - x1) + (x2 - x2)) != 0.0  # NaN only from a NaN or an inf
        if labels[i] == label:
            if j < n_label:
                first[j, 0] = x0
                first[j, 1] = x1
                first[j, 2] = x2
            j += 1
        elif skip == 0:
            if k < n_other:
                other[k, 0] = x0
                other[k, 1] = x1
                other[k, 2] = x2
            k += 1
            skip = stride - 1
        else:
            skip -= 1
    if j != n_label or k != n_other:
        raise ValueError("_split_labelled: the row counts do not match the labels")
    return first, other, not bad


def _compiled_cloud(points: np.ndarray, labels: np.ndarray) -> bool:
    """Whether the compiled split (:func:`_scan_cloud`, :func:`_gather_labelled`) takes this cloud."""
    return (points.dtype == np.float64 and points.ndim == 2 and points.shape[1] == 3 and points.flags.c_contiguous
            and labels.dtype == np.int8
            and labels.ndim == 1 and labels.shape[0] == points.shape[0])


def _labelled_rows(points: np.ndarray, labels: np.ndarray, label: int, *, equal: bool = True, stride: int = 1,
                   n_match: int | None = None) -> np.ndarray:
    """``points[(labels == label) if equal else (labels != label)][::stride]`` as a new ``(m, 3)`` array.

    One compiled pass for a float64 cloud with int8 labels (numpy needs the mask, its
    negation and a row gather: ~0.5 ms for the ~190k non-stem rows of an 848x480 frame, and
    a thinned law then still gathered all of them); the same bytes as numpy's
    (tests/loop/test_fast_paths.py). ``n_match``: the number of matching rows if known."""
    if not _compiled_cloud(points, labels):
        mask = labels == label if equal else labels != label
        return _rows(points, mask)[::stride]
    if n_match is None:
        n_match = int(np.count_nonzero(labels == label))
        if not equal:
            n_match = points.shape[0] - n_match
    count = len(range(0, n_match, stride))
    return _gather_labelled(points, labels, label, equal, stride, count)


class _LabelRows:
    """The rows of ``points`` [m] labelled (``equal``) / not labelled ``label``, gathered on first use.

    Supports ``.shape`` and slicing (``rows[::1]``: all of them). No mask is computed per
    frame: the frame's obstacle rows (and, when the unveiling law thins them, its full
    non-stem rows) are only needed at the switch (~0.3 ms each per 848x480 frame otherwise).
    """

    __slots__ = ("_points", "_labels", "_label", "_equal", "_n_match", "_all")

    def __init__(self, points: np.ndarray, labels: np.ndarray, label: int, *, equal: bool = True,
                 n_match: int | None = None, rows: np.ndarray | None = None) -> None:
        self._points = points
        self._labels = labels
        self._label = label
        self._equal = equal
        self._n_match = n_match
        self._all = rows

    @property
    def shape(self) -> tuple[int, int]:
        return self[::1].shape

    def __len__(self) -> int:
        return len(self[::1])

    def __getitem__(self, key) -> np.ndarray:
        if self._all is None:
            self._all = _labelled_rows(self._points, self._labels, self._label, equal=self._equal,
                                       n_match=self._n_match)
        return self._all[key]


def _first_in_each_voxel(points: np.ndarray, voxel: float) -> np.ndarray:
    """Indices of the first point in each occupied voxel of edge ``voxel`` [m], ascending.

    The same as ``np.sort(np.unique(keys, axis=0, return_index=True)[1])`` on the integer
    voxel keys, whose row-wise unique sorts (n, 3) records; here the three keys are packed
    into one int64 (21 bits each, offset by their minimum) and a 1-D unique does it (both
    return each key's first occurrence). Keys spanning more than 2^21 voxels fall back.
    """
    keys = np.floor(points / voxel).astype(np.int64)
    keys -= keys.min(axis=0)
    if int(keys.max()) >= 1 << 21:
        _, first = np.unique(keys, axis=0, return_index=True)
    else:
        _, first = np.unique((keys[:, 0] << 42) | (keys[:, 1] << 21) | keys[:, 2], return_index=True)
    return np.sort(first)


def _missing_names(roll_error: float | None, map_cells: float | None, with_map: bool) -> tuple[str, ...]:
    """The tick's value names not given (``_ValueRow.missing``) of the row layouts."""
    if roll_error is None:
        return ("roll_error", "map_cells") if with_map and map_cells is None else ("roll_error",)
    return ("map_cells",) if with_map and map_cells is None else ()


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
        #: The phase and its timers (:mod:`harvest_qp.loop.phases`).
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
        QP step a :class:`~harvest_qp.perception.obstacle_map.MapCollisionFeed` gives the
        closest occupied cells of each arm capsule to the ``CollisionAvoidance`` limit as
        damper rows (pair names ``cell[kx,ky,kz]``). Only with the QP mapper and a collision
        limit; the cloud-sphere option (``obstacles``) feeds the same limit, so not both.
        """
        from harvest_qp.perception.obstacle_map import MapCollisionFeed, ObstacleMap

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
            _MapCapsule(b.name, b.link, b.capsule.p0, b.capsule.p1, b.capsule.radius)
            for b in description.collision_bodies() if b.arm and b.name.startswith(prefixes)
        ]
        # The grasping arm's capsules near the tool, which swing with the gripper around p_sb
        # when the stem is stretched (the swing check of p_gd, _swing_clearance).
        self._swing_capsules = [
            (self.configuration.frame_id(b.link), np.asarray(b.capsule.p0, float), np.asarray(b.capsule.p1, float),
             float(b.capsule.radius))
            for b in description.collision_bodies() if b.arm and b.name in _SWING_CAPSULES
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
        """Regions never mapped at gripper pose ``T_g``: the held cluster and the stem.

        The cluster hangs along y_g from the gripper point and moves with it (a capsule of
        radius ``cluster_radius`` whose axis runs from ``cluster_start`` to ``cluster_length``
        below the gripper point; its rounded top reaches ``cluster_radius - cluster_start``
        above it, so the branch at the stem base stays in the map). The stem
        runs from the top of the crop to p_sb (the latest fit; before one, ``stem_length``
        along -y_g): beyond the camera's stem range it is labelled an obstacle, and it must
        never constrain the camera's approach to it nor the gripper that holds it.
        """
        from harvest_qp.perception.obstacle_map import ExclusionRegion

        m, st = self.settings["obstacle_map"], self.state
        p_g, y_g = T_g[:3, 3], T_g[:3, 1]
        cluster = ExclusionRegion(tuple(p_g + m["cluster_start"] * y_g), tuple(p_g + m["cluster_length"] * y_g),
                                  m["cluster_radius"])
        top_of_crop = p_g - self.settings["perception"]["grasp_offset"] * y_g
        stem_end = st.p_sb if st.p_sb is not None else top_of_crop - m["stem_length"] * y_g
        stem = ExclusionRegion(tuple(top_of_crop), tuple(stem_end), m["stem_radius"])
        return [cluster, stem]

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
        gripper = self.configuration.frame_pose("gripper").homogeneous
        self.state = _State(hold=HoldPose(gripper, k_hold=self.settings["grasping"]["k_hold"]))
        self.phases.reset()
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
        # Speed (per camera frame): compiled loops count the stem rows (_count_label), then
        # check the cloud's finiteness and gather the stem rows and only the non-stem rows the
        # unveiling law keeps (every k-th) in one pass (_split_labelled); all non-stem rows
        # are gathered lazily where the switch or the predicted mode needs them, the obstacle
        # rows only at the switch (numpy's masks and row gathers: 0.8 ms at 848x480, these
        # 0.4 ms). The unveiling law then gets the split points unchecked (its public
        # observe() checks the same points again, ~0.3 ms at 848x480). The same bytes as
        # numpy's boolean indexing (tests/loop/test_fast_paths.py).
        st, s = self.state, self.settings
        labels = cloud.labels
        points = cloud.points
        unveiling = self.unveiling
        compiled = _compiled_cloud(points, labels)
        n_stem = _count_label(labels, STEM) if compiled else int(np.count_nonzero(labels == STEM))
        n_non_stem = int(points.shape[0]) - n_stem
        non_stem = _LabelRows(points, labels, STEM, equal=False, n_match=n_non_stem)
        # The non-stem rows the unveiling law's paper mode uses (every k-th), gathered with
        # the stem rows in the pass that checks the cloud's finiteness; None where the paper
        # mode cannot run on this frame (no stem, the unveiling law off, or fewer than
        # min_stem_points stem points with a predicted stem: its next-best-view step reads
        # every non-stem row).
        predicted_mode = s["unveiling"]["predicted_stem"] and n_stem < unveiling.min_stem_points
        thinned = None
        if compiled and n_stem > 0 and s["unveiling"]["enabled"] and not predicted_mode:
            stride = unveiling.obstacle_stride(n_non_stem)
            stem, thinned, finite = _split_labelled(points, labels, STEM, n_stem, stride,
                                                    len(range(0, n_non_stem, stride)))
            if not finite:
                thinned = None
            elif stride == 1:
                non_stem = _LabelRows(points, labels, STEM, equal=False, n_match=n_non_stem, rows=thinned)
        elif compiled:
            finite = _scan_cloud(points, labels, STEM)[1]
            stem = _gather_labelled(points, labels, STEM, True, 1, n_stem)
        else:
            stem = _rows(points, labels == STEM)
            finite = bool(np.isfinite(points).all())
        approach = st.phase == Phase.APPROACH
        spheres = self.collision is not None and s["obstacles"]["enabled"]
        obstacles = _LabelRows(points, labels, OBSTACLE) if approach or spheres else None
        st.n_stem = n_stem
        if n_stem > 0:
            st.last_stem_time = cloud.timestamp
        p_c = cloud.camera_position
        snap = FrameSnapshot(cloud.timestamp, cloud.pixels, labels, cloud.image_size, cloud.depth)
        self.snapshots.setdefault("start", snap)
        self.snapshots["end"] = snap
        if s["unveiling"]["enabled"]:
            # Only the predicted mode reads the predicted stem (the law ignores it once
            # min_stem_points stem points are seen): not computed on the other frames.
            predicted = self._predicted_stem(T_g) if predicted_mode else None
            if finite:
                unveiling._observe_points(p_c, stem, non_stem, predicted_stem_points=predicted,
                                          roi_centre=self.reaching.roi_centre, timestamp=cloud.timestamp,
                                          thinned_obstacles=thinned)
            else:  # the checked call raises the package's error naming the bad points
                unveiling.observe(p_c, stem, non_stem[::1], predicted_stem_points=predicted,
                                  roi_centre=self.reaching.roi_centre, timestamp=cloud.timestamp)
        if spheres:
            self._update_obstacle_spheres(obstacles[::1], T_g)
        if not approach:
            return
        frame = _Frame(cloud.timestamp, p_c.copy(), cloud.camera_pose.copy(), stem, non_stem, obstacles)
        if st.n_stem >= s["perception"]["min_stem_points"]:
            fit = fit_stem(stem, T_g[:3, 3])
            if fit.valid and np.linalg.norm(fit.base - T_g[:3, 3]) <= s["perception"]["max_base_distance"]:
                frame.fit = fit
                st.p_sb = fit.base.copy()
                st.stem_length = fit.length
                st.stem_direction = fit.top.direction.copy()
                self.reaching.set_roi_centre(st.p_sb)
        st.frame = frame

    def _update_obstacle_spheres(self, points: np.ndarray, T_g: np.ndarray) -> None:
        """The vine seen in this frame as collision spheres for the QP (beyond the paper).

        Non-stem, non-robot points within ``obstacles.max_distance`` of the gripper, one
        sphere per occupied voxel, minus the held cluster (a capsule along y_g below the
        gripper, which moves with it). Measured without it (default scene, lab contacts on):
        the gripper swinging the crop towards p_gd touched a leaf at 12 s, the wrist read
        6 N of contact force and the episode aborted on the force limit.
        """
        o = self.settings["obstacles"]
        p_g, y_g = T_g[:3, 3], T_g[:3, 1]
        offset = points - p_g
        near = np.einsum("ij,ij->i", offset, offset) < o["max_distance"] ** 2
        points, offset = points[near], offset[near]
        along = np.clip(offset @ y_g, 0.0, o["cluster_length"])
        radial = offset - along[:, None] * y_g
        outside_cluster = np.einsum("ij,ij->i", radial, radial) > o["cluster_radius"] ** 2
        points = points[outside_cluster]
        if len(points):
            centres = points[_first_in_each_voxel(points, o["voxel"])]
        else:
            centres = np.zeros((0, 3))
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
        points = frame.obstacles
        T_g = self._switch_gripper_pose
        o = self.settings["obstacles"]
        offset = points - T_g[:3, 3]
        along = np.clip(offset @ T_g[:3, 1], 0.0, o["cluster_length"])
        radial = offset - along[:, None] * T_g[:3, 1]
        return points[np.einsum("ij,ij->i", radial, radial) > o["cluster_radius"] ** 2]

    def _target_within_swing(self, free, stem_base: np.ndarray, *, T_g: np.ndarray) -> np.ndarray | None:
        """p_gd of ``eq:attr_point`` over the free samples within ``grasping.max_swing_deg`` of the stem now.

        The stem's direction now is from p_sb to the top of the held crop (gripper pose and
        ``perception.grasp_offset``). Deviation from the paper (which takes the whole
        free-space hemisphere): measured on the default scene and seed 1, p_gd 48-53 deg off
        the hanging stem swung the crop up beside the branch and the gripper touched it
        (arm-vine contacts from 0.8 s after the switch, wrist reading 6 N from the contact).
        ``null`` keeps the paper's choice.

        With ``grasping.swing_clearance`` and an obstacle map (beyond the paper), the samples
        are first filtered by the clearance of the gripper's swing on the map
        (:meth:`_swing_clearance`), in tiers: free, in the cone and clear (then
        ``eq:attr_point`` among them); free and clear (the least swing); the hanging
        direction itself or the least swing of the cone that is clear (leaving F: measured on
        seeds 1 and 5, no sample of F swung clear of the occluding leaf); else the most
        clearance. "Clear" is ``swing_clearance``, or the gripper's clearance now if that is
        less (a gripper already close to the branch must not get closer).
        """
        g = self.settings["grasping"]
        max_swing = g["max_swing_deg"]
        swing_clearance = g["swing_clearance"]
        map_check = swing_clearance is not None and self.obstacle_map is not None and bool(self._swing_capsules)
        self.target_choice = "eq:attr_point over the free samples in the cone"
        if max_swing is None and not map_check:
            self.target_choice = "eq:attr_point"
            return free.target.copy()
        if not np.any(free.free):
            return None
        top_of_crop = T_g[:3, 3] - self.settings["perception"]["grasp_offset"] * T_g[:3, 1]
        hanging = top_of_crop - stem_base
        hanging /= float(np.linalg.norm(hanging))
        samples = free.samples
        directions = (samples - stem_base) / np.linalg.norm(samples - stem_base, axis=1)[:, None]
        cos_swing = directions @ hanging
        in_cone = free.free & (cos_swing >= (np.cos(np.radians(max_swing)) if max_swing is not None else -1.0))
        if map_check:
            # Map-aware p_gd (beyond the paper): the gripper and its wrist swing around p_sb with
            # the crop and then move out along n_c as the stem stretches; a sample whose swing
            # brings them within swing_clearance of a mapped cell (measured: the occluding leaf
            # the crop is pulled towards on seeds 1 and 5, the branch) is used only when no other
            # is left. A gripper already closer than that must not get closer.
            limit = 2.0 * swing_clearance
            clearance = self._swing_clearance(samples, stem_base, hanging, limit=limit)
            now = self._swing_clearance(top_of_crop[None], stem_base, hanging, limit=limit, fractions=(0.0,),
                                        stretches=(0.0,))[0]
            needed = min(swing_clearance, now)
            self.last_swing_clearance = (clearance, needed)
            clear = clearance >= needed - 1e-9
            if np.any(in_cone & clear):
                in_cone = in_cone & clear
                self.target_choice = "free, in the cone, swing clear (eq:attr_point among them)"
            elif np.any(free.free & clear):  # outside the cone: the least swing that is clear
                pool = np.flatnonzero(free.free & clear)
                self.target_choice = "free, swing clear, outside the cone (least swing)"
                return samples[pool[np.argmax(cos_swing[pool])]].copy()
            else:
                # No sample of F swings clear (measured on seeds 1 and 5: F lies on the camera's
                # side, where the occluding leaf hangs). Leave F: the sample of the cone (or the
                # hanging direction itself, no swing at all) that swings clear with the least
                # swing, else the one that keeps the most clearance.
                hang_point = stem_base + free.radius * hanging
                hang_clearance = self._swing_clearance(hang_point[None], stem_base, hanging, limit=limit)[0]
                cone = cos_swing >= (np.cos(np.radians(max_swing)) if max_swing is not None else -1.0)
                pool = np.flatnonzero(cone & clear)
                if hang_clearance >= needed - 1e-9:
                    self.target_choice = "no free sample swings clear: the hanging direction (no swing)"
                    return hang_point
                if pool.size:
                    self.target_choice = "no free sample swings clear: the least clear swing of the cone"
                    return samples[pool[np.argmax(cos_swing[pool])]].copy()
                pool = np.flatnonzero(cone) if np.any(cone) else np.arange(len(samples))
                best = pool[np.argmax(clearance[pool])]
                self.target_choice = "no sample swings clear: the most clearance"
                return samples[best].copy() if clearance[best] > hang_clearance else hang_point
        if not np.any(in_cone):  # nothing free within the cone: the free sample nearest to it
            self.target_choice = "nothing free in the cone: the free sample nearest to it"
            closest = np.flatnonzero(free.free)[np.argmax(cos_swing[free.free])]
            return samples[closest].copy()
        candidates = samples[in_cone]
        obstacles = free.projected_obstacles
        if len(obstacles) == 0:
            return candidates[np.argmax(cos_swing[in_cone])].copy()
        from scipy.spatial import cKDTree

        projected_clearance, _ = cKDTree(obstacles).query(candidates)
        return candidates[int(np.argmax(projected_clearance))].copy()

    def _swing_clearance(self, samples: np.ndarray, stem_base: np.ndarray, hanging: np.ndarray, *, limit: float,
                         fractions=_SWING_FRACTIONS, stretches=None) -> np.ndarray:
        """Smallest map distance [m] of the gripper's capsules along its swing to each sample (capped at ``limit``).

        The swing to a sample: the gripper point turns about p_sb with the stem, from its
        hanging direction ``hanging`` (unit, p_sb -> top of the crop) to the sample's, while
        the gripper turns by the same rotation about its own point, twice as fast
        (``k_og`` = 2 ``k_pg`` in ``eq:superimp_g``: when the position has done a fraction f
        of its way, the orientation has done 1 - (1 - f)^2); the gripper and the wrist links
        next to it move rigidly with it. At the end of the turn the gripper also moves out
        along n_c by each of ``stretches`` (the stem's slack and stretch: measured 22 mm beyond
        the sphere S(p_sb, l) on seed 5 at 3 N). The held cluster and the stem are never in
        the map (``map_exclusions``), so they do not count.
        """
        if stretches is None:
            stretch = self.settings["grasping"]["swing_stretch"]
            stretches = (0.5 * stretch, stretch) if stretch > 0 else ()
        fractions = np.asarray(fractions, float)
        turn = np.concatenate([1.0 - (1.0 - fractions) ** 2, np.ones(len(stretches))])
        move = np.concatenate([fractions, np.ones(len(stretches))])
        out = np.concatenate([np.zeros(len(fractions)), np.asarray(stretches, float)])
        directions = samples - stem_base
        directions /= np.linalg.norm(directions, axis=1)[:, None]
        R_move = _rotations_between(hanging, directions, move)  # (n, m, 3, 3)
        R_turn = _rotations_between(hanging, directions, turn)
        data = self.configuration.data
        gripper = data.oMf[self._gripper_id]
        p_g = gripper.translation
        # positions of the gripper point along the swing
        points = (stem_base + np.einsum("nmij,j->nmi", R_move, p_g - stem_base)
                  + out[None, :, None] * directions[:, None])
        p0, p1, radii = [], [], []
        for frame, a, b, radius in self._swing_capsules:
            pose = data.oMf[frame]
            for end, ends in ((a, p0), (b, p1)):
                relative = pose.rotation @ end + pose.translation - p_g  # world offset from the gripper point now
                ends.append(points + np.einsum("nmij,j->nmi", R_turn, relative))
            radii.append(radius)
        n, m = R_move.shape[:2]
        p0 = np.stack(p0, axis=2).reshape(-1, 3)
        p1 = np.stack(p1, axis=2).reshape(-1, 3)
        r = np.tile(np.asarray(radii), n * m)
        query = self.obstacle_map.closest_cells(p0, p1, r, max_distance=limit, per_capsule=1)
        distance = np.minimum(query.min_distances(), limit).reshape(n, m * len(radii))
        return distance.min(axis=1)

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

    def _try_switch(self, t: float, obs: Observation, T_g: np.ndarray) -> bool:
        """Recompute p_sb and p_gd on the latest frame; True (sensor tared, laws retargeted) if both exist."""
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
        target = self._target_within_swing(free, fit.base, T_g=T_g)
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
                self.obstacle_map.update(obs.cloud, exclude=self.map_exclusions(T_g))
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
        return _command(qdot, status, values, self._active_pair_columns(), self.phases.done(t))

    def _advance_phase(self, t: float, obs: Observation, T_c: np.ndarray, T_g: np.ndarray) -> None:
        """The phase machine's tick: the switch test (then p_sb, p_gd at the switch) or the stem watch."""
        phases, st = self.phases, self.state
        if phases.phase == Phase.APPROACH:
            ready = phases.approach(t, T_c, stem_base_found=st.p_sb is not None,
                                    roi_distance=math.dist(self.reaching.roi_centre.tolist(), T_c[:3, 3].tolist()))
            if ready and self._try_switch(t, obs, T_g):
                phases.switch(t)
        elif phases.bimanual:
            phases.watch_stem(t, st.last_stem_time)

    def _references(self, t: float, obs: Observation, T_c: np.ndarray, T_g: np.ndarray) -> _References:
        """The tick's task references (advances the laws' filters and the grasp's phase tests).

        Camera: V_c = V_cr (``eq:control_signal_rr_world``) + the keep-out term + V_cu (``eq:v_c2``,
        low-passed), plus in the bimanual phase the feed-forward of ``eq:final_vc``; roll: the
        cutter across the stem. Gripper: the hold of the crop in the approach, then V_g
        (``eq:superimp_g``) on the wrist force (tared at the switch; zero on the switch tick).
        """
        s, st, dt = self.settings, self.state, self.dt
        r = s["reaching"]
        reaching, stretching = self.reaching, self.stretching
        V_c = reaching.update(T_c, dt)
        V_c += keep_out_velocity(T_c[:3, 3], reaching.roi_centre, min_distance=r["min_distance_factor"] * r["radius"],
                                 gain=r["k_keep_out"])
        if s["unveiling"]["enabled"]:
            V_c += self.unveiling.update(dt)
        force_nc = math.nan
        if self.phases.phase == Phase.APPROACH:
            V_g = st.hold.update(T_g)
            direction = st.stem_direction if st.stem_direction is not None else T_g[:3, 1]
        else:
            force = obs.force if t > self.phases.t_switch else np.zeros(3)
            V_g = stretching.update(T_g, force, dt)
            force_nc = stretching.force_along_nc
            if s["grasping"]["feed_forward"]:
                V_c += self.feed_forward(stretching.v_gt, T_c[:3, 3], st.p_sb)
            self.phases.stretch(t, dt, force_nc, stretching.position_error, stretching.alignment)
            direction = stretching.n_c
        roll, roll_error = roll_reference(T_c, direction, k_roll=s["roll"]["k_roll"])
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
            self.roll_task.set_reference(references.roll)
            if self.map_feed is not None:
                map_cells = float(self.map_feed.update(q))
            qdot, status, ok = self._solve(q)
            phases.solved(t, ok, status)
        qdot = np.asarray(qdot, float)
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

    def _log_row(self, T_c: np.ndarray, references: _References, map_cells: float | None) -> _ValueRow:
        """The tick's logged values (``value/<name>``: ``roll_error``, ``map_cells`` with the map,
        then :data:`_LOGGED_VALUES`) as one float64 row for the runner (``runner._ValueRow``);
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
        return _ValueRow._built(layout, row, _missing_names(roll_error, map_cells, with_map))

    def _active_pair_columns(self) -> _PairColumns | list:
        """The collision pairs active in this tick's QP as three columns (``runner._PairColumns``:
        first names, second names, distances [m]); ``[]`` without (no limit, the pinv mapper)."""
        lim = self.collision
        if lim is None or self.mapper_kind != "qp":
            return []
        active = np.asarray(getattr(lim, "active_pairs", ()), dtype=np.int64)
        if not active.size:
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
