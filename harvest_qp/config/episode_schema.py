"""The paper episode's settings tree (``tasks/paper.yaml``), one pydantic model per section.

Every value of Section ``sec:exper`` of the paper has a key, written as in the paper (gains
``k_*``); every key has its default HERE (the one place), so a file only needs what it
changes. To add a key: add one ``Field`` line to its section below (default, unit and
description); the JSON Schema, ``docs/config.md`` and the checks follow from it.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field, TypeAdapter, field_validator
from pydantic_core import PydanticCustomError

from harvest_qp.config._types import (
    AcuteAngle,
    AcuteAngleOrNull,
    Fraction,
    Level,
    NonNegative,
    NonNegativeInt,
    Positive,
    PositiveInt,
    PositiveOrL,
    PositiveOrNull,
    Real,
    Section,
    Text,
    Vector3,
    Weight,
    Weights6,
    Weights6OrNull,
    expect,
    suggest,
)
from harvest_qp.config.task_schema import LimitEntry, TaskEntry

__all__ = ["EpisodeConfig"]


def _f(default: Any, description: str) -> Any:
    # pydantic copies a mutable default for each instance, so one default object is safe here.
    return Field(default, description=description)


class Episode(Section):
    """Length and end of one episode."""

    duration: Positive = _f(50.0, "[s] episode length (the switch comes at ~6-15 s, pre-cut ~6-14 s after it; "
                                  "the paper's force loop settles ~20 s after the switch)")
    end_after_precut: PositiveOrNull = _f(None, "[s] end this long after 'pre-cut reached' (null: run the full "
                                                "duration)")
    stop_after_abort: NonNegative = _f(0.5, "[s] the episode ends this long after an abort's safe stop")
    log_cloud_every: NonNegativeInt = _f(15, "log every N-th camera frame's cloud for the replay viewer (0: none; "
                                        "15 = 2 Hz at 30 FPS)")
    log_cloud_points: PositiveInt = _f(2000, "points kept per logged cloud (thinned by a regular stride)")


class Scene(Section):
    """The MuJoCo vine scene."""

    randomize: bool = _f(True, "--seed N > 0: VineSceneParams.sample(N); seed 0 is the default (paper) scene")
    params: dict[str, Any] = _f({}, "VineSceneParams fields set explicitly (checked by "
                                    "harvest_qp.sim.VineSceneParams)")

    @field_validator("params", mode="after")
    @classmethod
    def _scene_field_names(cls, value: dict[str, Any]) -> dict[str, Any]:
        import dataclasses

        from harvest_qp.exceptions import InvalidInputError
        from harvest_qp.sim.scene import VineSceneParams

        names = [f.name for f in dataclasses.fields(VineSceneParams)]
        for key in value:
            if key not in names:
                raise PydanticCustomError(
                    "unknown_key", "unknown key '{key}'{hint}; expected one of: {valid}",
                    {"key": str(key), "hint": suggest(str(key), names), "valid": ", ".join(names)},
                )
        try:  # the values, checked by the dataclass itself (cheap: no model is built)
            VineSceneParams(**value)
        except (InvalidInputError, TypeError) as err:
            raise PydanticCustomError("scene_params", "{err}", {"err": " ".join(str(err).split())}) from None
        return value


class Camera(Section):
    """The RGB-D camera on the camera arm (Realsense D415 of the paper: 848x480 at 30 FPS, downsampled by 3)."""

    width: PositiveInt = _f(848, "[px] image width")
    height: PositiveInt = _f(480, "[px] image height")
    downsample: PositiveInt = _f(3, "keep one pixel in `downsample` along each image axis")
    rate: Positive = _f(30.0, "[Hz] frame rate")
    stem_range: Positive = _f(0.7, "[m] the stem is detectable only within this distance")
    depth_noise: NonNegative = _f(0.0, "[m] depth noise standard deviation at 1 m (fault injection)")
    dropout: Fraction = _f(0.0, "fraction of pixels without depth (fault injection)")
    latency: NonNegative = _f(0.0, "[s] delay of every frame (fault injection)")
    frame_loss: Fraction = _f(0.0, "probability that a whole frame is lost (fault injection)")


class ForceSensor(Section):
    """The wrist force-torque sensor of the grasping arm."""

    noise_std: NonNegative = _f(0.0, "[N] force noise standard deviation (fault injection)")
    filter_time_constant: NonNegative = _f(0.0, "[s] first-order low-pass on the measured force (0: none)")


class Reaching(Section):
    """Reaching law of the camera arm, eq:control_signal_rr_world."""

    radius: Positive = _f(0.35, "[m] r, radius of the ROI sphere centred at p_sb")
    k_cp: Positive = _f(1.0, "[1/s] position gain of V_cr")
    k_co: Positive = _f(1.0, "[1/s] orientation gain of V_cr")
    roi_time_constant: NonNegative = _f(0.5, "[s] first-order filter of the ROI centre's moves")
    target_radius_factor: Positive = _f(0.95, "V_cr aims at this x r (1 = the paper; 0.95: it reaches its sphere "
                                              "only asymptotically from outside)")
    min_distance_factor: Fraction = _f(0.9, "beyond the paper: the camera keeps >= this x r from p_r while V_cu acts")
    k_keep_out: Positive = _f(2.0, "[1/s] gain of that outward term")


class LookAround(Section):
    """Beyond the paper, opt-in: for the first seconds of the approach the optical axis sweeps a cone about
    the ROI direction (the camera keeps reaching), so the obstacle map knows more of the camera arm's
    surroundings (harvest_qp/references/look_around.py)."""

    enabled: bool = _f(False, "sweep at the start of the approach (off: on 200 sweep scenes it lost 4 of them to "
                              "the camera arm's wrist singularity; docs/references.md deviation 9)")
    cone_deg: expect(float, "a number in (0, 90) [deg]", gt=0, lt=90) = _f(
        25.0, "[deg] half-angle of the cone the optical axis sweeps")
    period: expect(float, "a number >= 0.5 [s]", ge=0.5) = _f(
        2.5, "[s] time of the one turn around the cone (the arm's 1 rad/s joints need >= ~2 s); the switch waits "
             "for its end")
    gain: Positive = _f(3.0, "[1/s] gain that pulls the optical axis onto the cone")


class Unveiling(Section):
    """Unveiling law of the camera arm, eq:nearest .. eq:v_c2."""

    enabled: bool = _f(True, "use V_cu (false: reaching only)")
    k_c: Positive = _f(0.00025, "gain k_c of V_cu")
    d_a: Positive = _f(0.01, "[m] d_a of the paper")
    d_o: NonNegative = _f(0.001, "[m] d_o of the paper")
    time_constant: NonNegative = _f(0.5, "[s] first-order low-pass on V_cu")
    max_linear: Positive = _f(0.05, "[m/s] bound on the raw V_cu (not in the paper: its raw law reaches 1e4 rad/s)")
    max_angular: Positive = _f(0.1, "[rad/s] bound on the raw V_cu's angular part (not in the paper)")
    min_pivot: NonNegative = _f(0.03, "[m] ray/obstacle pairs with a shorter pivot arm are dropped (not in the "
                                      "paper)")
    predicted_stem: bool = _f(True, "beyond the paper: unveil the predicted stem while none is seen (n_S = 0)")


class Switch(Section):
    """Switch to the bimanual phase, subsec:biman_coord."""

    distance_factor: Positive = _f(1.05, "switch once the camera is within this x r of the ROI centre")
    max_linear_speed: Positive = _f(0.01, "[m/s] and the camera's mean linear speed is below this")
    max_angular_speed: Positive = _f(0.025, "[rad/s] and its mean angular speed is below this (roll about the "
                                            "optical axis left out: it is free)")
    window: Positive = _f(0.5, "[s] the speeds are means over this window (the camera dithers while V_cu acts)")


class Grasping(Section):
    """Grasping arm's law, eq:gr_pos_contr .. eq:superimp_g."""

    k_pg: Positive = _f(0.15, "[1/s] position gain toward p_gd")
    k_og: Positive = _f(0.3, "[1/s] orientation gain")
    k_fp: Positive = _f(0.001, "[m/(N s)] proportional force gain")
    k_fi: NonNegative = _f(0.0002, "[m/(N s^2)] integral force gain")
    f_d: Positive = _f(3.0, "[N] desired stem tension f_d")
    max_speed: Positive = _f(0.05, "[m/s] saturation of the force term (anti-windup holds the integral there)")
    integration_threshold: PositiveOrNull = _f(2.0, "[N] the force integral starts once n_c^T f exceeds it "
                                                    "(null: at once, as the paper)")
    r_o: PositiveOrL = _f("l", "[m] radius of S(p_sb, r_o) bounding O for p_gd; 'l' = the estimated stem length")
    n_samples: PositiveInt = _f(500, "Fibonacci samples of S(p_sb, l)")
    exclude_held_crop: bool = _f(False, "true: O for p_gd leaves out the robot's points and the held crop "
                                        "(beyond the paper)")
    max_swing_deg: AcuteAngleOrNull = _f(
        30.0, "[deg] beyond the paper: p_gd within this angle of the hanging stem, below 90 (more puts the crop "
              "behind p_sb along n_c); null: the paper's whole hemisphere without the map's swing check, the "
              "crop's side of p_sb with it")
    swing_clearance: PositiveOrNull = _f(0.02, "[m] beyond the paper: map distance the gripper keeps along its "
                                               "swing to p_gd (null: not checked)")
    swing_stretch: NonNegative = _f(0.03, "[m] the swing check also moves the gripper this far out along n_c")
    swing_map_bias: NonNegative = _f(0.01, "[m] the obstacle map's cells lie up to this far short of the surface: "
                                           "added to swing_clearance")
    k_yield: NonNegative = _f(0.004, "[m/(N s)] beyond the paper: the gripper yields to the wrist force across "
                                     "n_c beyond yield_deadband (0: the paper's pure position control)")
    yield_deadband: NonNegative = _f(0.5, "[N] force across n_c the gripper does not yield to")
    yield_time_constant: NonNegative = _f(0.1, "[s] low-pass of the wrist force before the yield's deadband "
                                               "(0: the raw force; sensor noise then moves the gripper)")
    k_hold: Positive = _f(1.0, "[1/s] the grasping arm holds the crop still during the approach")
    feed_forward: bool = _f(False, "eq:final_vc's feed-forward term on the camera in the bimanual phase (off: "
                                   "nothing holds the camera's place on the ROI sphere, so the term drifts it; "
                                   "docs/references.md)")


class Perception(Section):
    """Perception pipeline settings."""

    min_stem_points: PositiveInt = _f(10, "stem points needed to fit the stem")
    max_base_distance: Positive = _f(0.2, "[m] a stem base p_sb further than this from the gripper is rejected")
    grasp_offset: NonNegative = _f(0.015, "[m] from the gripper point up (-y_g) to where the stem enters the crop")
    stem_memory: bool = _f(True, "beyond the paper: p_sb at the highest stem point seen from close range over the "
                                 "approach, not only in the last frame (the branch came to hide the stem's top "
                                 "as the camera rose; harvest_qp.perception.stem_memory)")
    stem_memory_range: Positive = _f(0.45, "[m] only frames whose camera is this close to p_sb add to the memory")


class Roll(Section):
    """Beyond the paper: the free roll of the camera turns the cutter across the stem."""

    enabled: bool = _f(True, "use the roll task")
    k_roll: Positive = _f(1.0, "[1/s] roll gain")


class Obstacles(Section):
    """Beyond the paper: the vine seen near the gripper as QP collision spheres."""

    enabled: bool = _f(False, "off: clustered spheres made daqp fail 25 ticks in a row, and blocked the gripper")
    max_distance: Positive = _f(0.25, "[m] points within this distance of the gripper")
    voxel: Positive = _f(0.02, "[m] one sphere per occupied voxel")
    radius: NonNegative = _f(0.01, "[m] sphere radius")
    cluster_radius: NonNegative = _f(0.075, "[m] the held cluster (a capsule along y_g below the gripper) is "
                                            "left out")
    cluster_length: NonNegative = _f(0.22, "[m] its length")


class ObstacleMap(Section):
    """Issue 11 (beyond the paper): what the camera saw becomes QP collision rows."""

    enabled: bool = _f(True, "OctoMap-style grid from every frame; unknown space is free")
    resolution: Positive = _f(0.01, "[m] cell edge (the map's distance is up to sqrt(3) cells short of the surface)")
    arms: expect(Literal["camera", "both"], "one of: camera, both") = _f(
        "both", "whose capsules get the map's rows (the grasping arm's only stop it: no further approach "
                "inside d_s, never a push)")
    clear_rays: PositiveInt = _f(6000, "clearing rays per frame (about)")
    per_capsule: PositiveInt = _f(4, "closest cells per arm capsule within d_i + margin")
    max_cells: PositiveInt = _f(24, "cells fed to the collision limit in all (the closest)")
    min_separation: NonNegative = _f(0.03, "[m] one capsule's cells at least this far apart (near-parallel rows "
                                           "upset daqp)")
    margin: NonNegative = _f(0.01, "[m] query beyond the influence distance")
    cluster_length: NonNegative = _f(0.22, "[m] the held cluster, a capsule along y_g from the gripper point, is "
                                           "never mapped")
    cluster_radius: NonNegative = _f(0.08, "[m] its radius")
    cluster_start: Real = _f(0.04, "[m] its axis starts this far below the gripper point (along y_g)")
    stem_radius: NonNegative = _f(0.02, "[m] a capsule around the stem (top of the crop to p_sb) is never mapped")
    stem_length: Positive = _f(0.08, "[m] the stem's length along -y_g before a stem base is found")
    line_prior: NonNegative = _f(0.3, "[m] a long structure along the row seen in part (a cane, a wire) is "
                                      "believed to go on this far past each seen end (0: off; "
                                      "perception.line_prior)")
    line_prior_direction: Vector3 = _f([0.0, 1.0, 0.0], "the row's direction in the world frame (the platform "
                                                        "drives along it)")
    line_prior_min_length: Positive = _f(0.25, "[m] the shortest seen part that counts as such a structure")
    line_prior_max_tilt_deg: Positive = _f(20.0, "[deg] only structures within this angle of the row count")


class Safety(Section):
    """Aborts."""

    force_limit: PositiveOrNull = _f(None, "[N] abort when the wrist force along n_c or its magnitude is above it "
                                           "(null: 2 f_d)")
    off_axis_force_limit: PositiveOrNull = _f(None, "[N] abort when the wrist force's part across n_c is above it "
                                                    "(null: f_d)")
    stem_lost_timeout: Positive = _f(5.0, "[s] abort when no stem point is seen this long in the bimanual phase")
    no_stem_timeout: Positive = _f(30.0, "[s] abort when no valid stem base is ever found this long")
    max_qp_failures: PositiveInt = _f(25, "abort after this many QP failures in a row")
    unexecuted_timeout: Positive = _f(10.0, "[s] before pre-cut, abort when the gripper's translation that V_g "
                                            "asks for is not executed this long (obstacle rows or limits)")
    switch_timeout: Positive = _f(40.0, "[s] abort when the switch to the bimanual phase has not come this long "
                                        "after the start (the longest in 500 sweep scenes: 23 s)")
    precut_timeout: Positive = _f(30.0, "[s] abort when pre-cut has not come this long after the switch (the "
                                        "longest in 500 sweep scenes: 21 s); the reason names the failing tests")


class Precut(Section):
    """'Pre-cut reached' when all of these hold for hold_time."""

    force_tolerance: Fraction = _f(0.1, "|f - f_d| within this fraction of f_d")
    position_tolerance: Positive = _f(0.005, "[m] projected position error")
    alignment_tolerance_deg: Positive = _f(5.0, "[deg] cutter-stem alignment")
    hold_time: NonNegative = _f(1.0, "[s] all tolerances held this long")
    force_time_constant: NonNegative = _f(0.2, "[s] low-pass on the force for this test (sensor noise)")
    max_force_angle_deg: AcuteAngle = _f(20.0, "[deg] the wrist force within this angle of n_c")


class TaskSlot(Section):
    """Priority level and weight of one of the episode's built-in QP tasks."""

    level: Level = Field(1, description="priority level (1 is the highest soft priority)")
    weight: Weight = Field(1.0, description="[1/(task unit)^2] weight (>= 0)")


class TwistTaskSlot(TaskSlot):
    """A 6-D twist task: one weight or one per axis (vx, vy, vz, wx, wy, wz)."""

    weight: Weights6 = Field(1.0, description="[1/(m/s)^2, 1/(rad/s)^2] a weight or 6 per-axis weights")


_DEFAULT_LIMITS = TypeAdapter(list[LimitEntry]).validate_python([
    {"type": "joint_position"},
    {"type": "joint_velocity", "max_velocity": 1.0},
    {"type": "joint_acceleration", "max_acceleration": 5.0},
    {"type": "collision", "safety_distance": 0.01, "influence_distance": 0.1, "gain": 0.3},
])


class QPSection(Section):
    """The QP mapper: backends, the built-in tasks' levels and weights, limits, user tasks."""

    solver: Text = _f("daqp", "QP backend: daqp | proxsuite | qpsolvers:<name>")
    backup_solver: expect(str | None, "a string or null") = _f(
        "proxsuite", "re-solves a tick the main backend failed (null: none)")
    camera_task: TwistTaskSlot = _f(TwistTaskSlot(level=1, weight=[1.0, 1.0, 1.0, 0.3, 0.3, 0.0]),
                                    "camera twist task (local axes; 5-D: roll about z_c free; the turn weighted "
                                    "below the travel so that near the wrist singularity the camera keeps its place)")
    camera_bimanual_weight: Weights6OrNull = _f(
        None, "[1/(m/s)^2, 1/(rad/s)^2] the camera task's weights from the switch on, when the camera only has "
              "to stay in the ROI and centred (null: camera_task.weight)")
    gripper_task: TwistTaskSlot = _f(TwistTaskSlot(level=1, weight=1.0),
                                     "gripper twist task (its translation only while alignment_task is set)")
    alignment_task: TaskSlot | None = _f(
        TaskSlot(level=2, weight=1.0),
        "the gripper's turn (eq:rot_contr) on its own level below the translation, so force and position "
        "along n_c win when both cannot be met (null: one 6-D gripper task, the paper's superposition)")
    roll_task: TaskSlot = _f(TaskSlot(level=2, weight=1.0), "camera roll task (section `roll`)")
    posture: TaskSlot = _f(TaskSlot(level=2, weight=1.0e-4), "posture task toward the start configuration")
    damping: TaskSlot = _f(TaskSlot(level=2, weight=1.0e-3), "joint-velocity damping task")
    limits: list[LimitEntry] = _f(_DEFAULT_LIMITS, "limits of the QP (entries as in QP task configs)")
    environment: list[str] = _f([], "static capsule geoms of the scene known to the controller (e.g. [branch, "
                                    "cane])")
    extra_tasks: list[TaskEntry] = _f([], "more QP tasks (built-in or a user's `module:Class`) appended at their "
                                          "own level and weight; QP mapper only")

    @field_validator("solver", "backup_solver", mode="after")
    @classmethod
    def _known_backend(cls, value: str | None) -> str | None:
        from harvest_qp.backends import backend_name_problem

        problem = None if value is None else backend_name_problem(value)
        if problem is not None:
            raise PydanticCustomError("qp_backend", "{problem}", {"problem": problem})
        return value


class Mapper(Section):
    """How the references become joint velocities."""

    kind: expect(Literal["qp", "pinv"], "one of: pinv, qp") = _f(
        "qp", "qp (this library's QP) or pinv (the paper's eq:controlled_system)")
    pinv_damping: NonNegative = _f(0.0, "damping of the pseudo-inverse (0: none, as the paper)")


class EpisodeConfig(Section):
    """The paper's experiment (Section sec:exper) in the MuJoCo lab: ``harvest-qp run FILE``."""

    extends: expect(str | list[str] | None, "a file name or a list of file names") = _f(
        None, "file(s) this one extends (relative to this file); its keys override theirs (deep merge)")
    description: Text = _f("", "what this configuration is for")
    episode: Episode = _f(Episode(), Episode.__doc__)
    scene: Scene = _f(Scene(), Scene.__doc__)
    camera: Camera = _f(Camera(), Camera.__doc__)
    force_sensor: ForceSensor = _f(ForceSensor(), ForceSensor.__doc__)
    reaching: Reaching = _f(Reaching(), Reaching.__doc__)
    look_around: LookAround = _f(LookAround(), LookAround.__doc__)
    unveiling: Unveiling = _f(Unveiling(), Unveiling.__doc__)
    switch: Switch = _f(Switch(), Switch.__doc__)
    grasping: Grasping = _f(Grasping(), Grasping.__doc__)
    perception: Perception = _f(Perception(), Perception.__doc__)
    roll: Roll = _f(Roll(), Roll.__doc__)
    obstacles: Obstacles = _f(Obstacles(), Obstacles.__doc__)
    obstacle_map: ObstacleMap = _f(ObstacleMap(), ObstacleMap.__doc__)
    safety: Safety = _f(Safety(), Safety.__doc__)
    precut: Precut = _f(Precut(), Precut.__doc__)
    qp: QPSection = _f(QPSection(), QPSection.__doc__)
    mapper: Mapper = _f(Mapper(), Mapper.__doc__)
