"""Seeded vine scene around the dual-UR5e: branch, cane, leaves, a bending stem and a grape cluster.

The scene reproduces the paper's lab (Section ``sec:exper``): plastic branches and leaves
around a grape cluster whose red stem is 0.07 m long; the grasping arm already holds the
cluster and the camera arm starts away from the region of interest.

Everything is placed relative to the grasping arm's gripper frame {G} at ``HOME_Q``
(about (0.50, -0.12, 1.15) m, pointing +x with y_G down):

* the cluster top (where the stem ends) sits ``grasp_offset`` above the gripper point,
  along -y_G, and the berries hang below it along y_G;
* the stem rises from there to the stem base p_sb in ``stem_segments`` capsules; its rest
  shape is an arc of total angle ``stem_bend`` leaning towards ``stem_bend_azimuth``;
* the branch passes just above p_sb, rising from it into the canopy (away from the robot)
  along ``branch_yaw`` / ``branch_pitch``; the cane runs along y through the branch's far end;
* one leaf (the occluder, ``occlude_stem``) hangs between the straight approach and the
  stem and hides ``occluder_coverage`` of it as seen from the approach viewpoint 0.35 m
  from p_sb (all of it, along the whole approach, when 1); the other leaves are scattered
  around the stem, ``canopy_leaves`` hang from the cane behind the cluster (the foliage
  wall the camera sees from its start pose, which looks +x past the cluster) and
  ``other_clusters`` grape clusters hang from the cane; none of these crosses a line of
  sight from the straight approach to the stem;
* at ``HOME_Q`` the stem is outside the camera's field of view (and, on the default scene,
  beyond the 0.7 m stem range): the start view sees no stem whatever the leaves.

Physics: the branch, cane and leaves are static. The stem is a chain of capsules on ball
joints (bending stiffness ``stem_bend_stiffness``) whose top joint also has an axial slide
spring (``stem_axial_stiffness``, about 400 N/m), so pulling the cluster stretches it. The
cluster is one rigid body of sphere berries on a ball joint at the stem end. A weld
equality between the ``grasp_tool`` body and the cluster is the grasp (activated by
:class:`harvest_qp.sim.SimRobot` at the current relative pose).

Contacts: the branch, cane, leaves, petioles and other clusters collide with the robot and
with the held cluster (leaves and berries with a softer contact, as they yield); the robot's own
self-collision pairs are explicit contact pairs of the robot model. The held cluster never
collides with the robot (touching the gripper would fight the weld) nor with its own stem,
and the stem collides with nothing. The stem tears when its tension exceeds
``stem_break_force`` (:class:`harvest_qp.sim.SimRobot` releases its axial spring).

Randomisation: :meth:`VineSceneParams.sample` draws every scalar uniformly from
:data:`PARAM_RANGES`; leaf poses and berry positions are drawn from ``seed`` in both the
default and sampled scenes (see :data:`LEAF_LAYOUT` for their ranges). The parameters and
the placement of the vine's parts live in :mod:`harvest_qp.sim.vine`; this module builds
the MuJoCo model from them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import InvalidInputError, ModelError
from harvest_qp.robot import description as desc
from harvest_qp.robot import paths
from harvest_qp.robot.meshes import strip_visual_meshes
from harvest_qp.runtime.interface import OBSTACLE, ROBOT, STEM
from harvest_qp.sim.actuation import ActuationConfig, add_joint_actuators
from harvest_qp.sim.vine import (
    _LEAF_THICKNESS,
    _PETIOLE_RADIUS,
    APPROACH_RADIUS,
    HIDDEN_APPROACH_MIN,
    HIDDEN_STEM_PROBABILITY,
    LEAF_LAYOUT,
    PARAM_RANGES,
    VineSceneParams,
    _approach_views,
    _berry_positions,
    _frame_from_z,
    _leaf_layout,
    _other_clusters,
    _quat,
    _robot_home,
    _rotate,
    _stem_polyline,
    _stem_samples,
    _unit,
)
from harvest_qp.validation import as_positive_scalar

#: Contact bits (MuJoCo's contype/conaffinity): the robot's geoms have contype 1, the held
#: crop's contype 2; the vine accepts both (conaffinity 3), the robot and the crop accept none.
_ROBOT_BIT = 1
_HELD_CROP_BIT = 2

__all__ = [
    "APPROACH_RADIUS",
    "HIDDEN_APPROACH_MIN",
    "HIDDEN_STEM_PROBABILITY",
    "PARAM_RANGES",
    "LEAF_LAYOUT",
    "VineSceneParams",
    "VineScene",
    "build_vine_scene",
    "STEM_COLOR",
    "CAMERA_NAME",
]

#: Stem colour (red, as the paper's painted stem); every other colour has a red share
#: below 45 % of R + G + B so colour-based stem detection can tell them apart.
STEM_COLOR = (0.85, 0.08, 0.08, 1.0)
LEAF_COLOR = (0.22, 0.55, 0.16, 1.0)
BRANCH_COLOR = (0.40, 0.30, 0.20, 1.0)
BERRY_COLOR = (0.33, 0.14, 0.42, 1.0)
RACHIS_COLOR = (0.35, 0.45, 0.18, 1.0)

#: Name of the MuJoCo camera on the camera arm used by the OpenGL renderer.
CAMERA_NAME = "rgbd_camera"

_WELD_SOLREF = (0.004, 1.0)  # stiff grasp: 2 timesteps, critically damped
#: Leaves, petioles and other clusters yield: a 50 ms contact time constant against the wood's (and
#: MuJoCo's default) 20 ms; their solmix makes it the one every contact with them uses (MuJoCo
#: averages two geoms' solref by solmix weights).
_FOLIAGE_SOLREF = (0.05, 1.0)
_FOLIAGE_SOLMIX = 1e3


@dataclass(eq=False)
class VineScene:
    """A compiled vine scene with the robot, and where its parts are.

    Attributes:
        params: the parameters it was built from.
        spec: the MuJoCo spec (``spec.to_xml()`` gives the MJCF).
        model: the compiled model.
        home_q: (12,) initial joint positions [rad].
        gripper_home: (4, 4) gripper frame {G} at ``home_q``.
        camera_home: (4, 4) camera frame {C} at ``home_q``.
        stem_polyline: (stem_segments + 1, 3) rest-shape stem points from the stem end
            (cluster top) up to the stem base p_sb [m].
        geom_labels: (ngeom,) int8 camera label of every geom (STEM / OBSTACLE / ROBOT).
        ids: ids of named parts: ``cluster`` (body), ``weld`` (equality),
            ``cam_tool`` / ``grasp_tool`` (bodies), ``stem_slide`` (joint),
            ``occluder`` (geom, -1 if none), sensor ids ``ft_force``, ``ft_torque``, ``stem_force``.
        stem_geoms / leaf_geoms / berry_geoms: geom ids of those parts (``berry_geoms``:
            the held cluster's).
        actuator_names: the 12 joint servo names in joint order.
        vine_geoms: geom ids of every vine part the robot collides with (branch, cane,
            leaves, petioles): all but the held stem and cluster.
        camera_start: where the straight approach starts [m] (``params.camera_start`` or
            the camera position at ``home_q``).
        cluster_centre: middle of the held cluster's axis at rest [m] (the paper's ROI
            centre before the stem is seen).
    """

    params: VineSceneParams
    spec: mujoco.MjSpec
    model: mujoco.MjModel
    home_q: NDArray[np.float64]
    gripper_home: NDArray[np.float64]
    camera_home: NDArray[np.float64]
    stem_polyline: NDArray[np.float64]
    geom_labels: NDArray[np.int8]
    ids: dict[str, int]
    stem_geoms: NDArray[np.int32]
    leaf_geoms: NDArray[np.int32]
    berry_geoms: NDArray[np.int32]
    actuator_names: list[str] = field(default_factory=list)
    vine_geoms: NDArray[np.int32] = field(default_factory=lambda: np.zeros(0, np.int32))
    camera_start: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    cluster_centre: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))

    def approach_pose(self, distance: float, *, target: ArrayLike | None = None) -> NDArray[np.float64]:
        """Camera pose (4x4 {C}) on the straight approach, ``distance`` [m] from ``target``.

        The position lies on the line from :attr:`camera_start` to ``target`` (default:
        the stem base p_sb, the ROI centre); the orientation is the home camera orientation
        turned by the smallest rotation that points its optical axis at ``target`` (what
        the paper's V_cr does, leaving the roll about the view direction alone).
        """
        distance = as_positive_scalar(distance, "distance")
        try:
            goal = self.stem_base if target is None else np.asarray(target, dtype=float)
        except (TypeError, ValueError):
            goal = np.full(1, np.nan)  # reported below
        if goal.shape != (3,) or not np.all(np.isfinite(goal)):
            raise InvalidInputError(f"target must be 3 finite coordinates [m] or None, got {target!r}")
        position = goal + distance * _unit(self.camera_start - goal)
        z0 = self.camera_home[:3, 2]
        z1 = _unit(goal - position)
        axis = np.cross(z0, z1)
        angle = float(np.arctan2(np.linalg.norm(axis), np.dot(z0, z1)))
        R0 = self.camera_home[:3, :3]
        R = R0 if np.linalg.norm(axis) < 1e-12 else np.column_stack(
            [_rotate(R0[:, k], _unit(axis), angle) for k in range(3)]
        )  # fmt: skip
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = position
        return T

    @property
    def stem_base(self) -> NDArray[np.float64]:
        """Rest position of the stem base p_sb [m] (where it joins the branch)."""
        return self.stem_polyline[-1]

    @property
    def stem_end(self) -> NDArray[np.float64]:
        """Rest position of the stem end at the cluster top [m]."""
        return self.stem_polyline[0]


def build_vine_scene(
    params: VineSceneParams | None = None,
    *,
    home_q: NDArray[np.float64] | None = None,
    actuation: ActuationConfig | None = None,
) -> VineScene:
    """Build and compile the vine scene with the dual-UR5e, its servos and sensors.

    Args:
        params: scene parameters (default: the paper's setup, :class:`VineSceneParams`).
        home_q: (12,) initial joint positions [rad] the cluster is placed for
            (default ``HOME_Q``).
        actuation: joint servo settings (default :class:`ActuationConfig`).

    Returns:
        The compiled :class:`VineScene`.
    """
    p = params if params is not None else VineSceneParams()
    if not isinstance(p, VineSceneParams):
        raise InvalidInputError(f"params must be a VineSceneParams, got {type(p).__name__}")
    try:
        q0 = np.array(desc.HOME_Q if home_q is None else home_q, dtype=float)
    except (TypeError, ValueError):
        q0 = np.full(1, np.nan)  # reported below
    if isinstance(home_q, (str, bytes)) or q0.shape != (12,) or not np.all(np.isfinite(q0)):
        raise InvalidInputError(f"home_q must be 12 finite joint positions [rad], got {home_q!r}")
    actuation = actuation if actuation is not None else ActuationConfig()
    if not isinstance(actuation, ActuationConfig):
        raise InvalidInputError(f"actuation must be an ActuationConfig or None, got {actuation!r}")

    try:
        spec = mujoco.MjSpec.from_file(str(paths.scene_path()))
    except Exception as error:  # mujoco raises plain ValueError on parse errors
        raise ModelError(f"cannot load the robot scene {paths.scene_path()}: {error}") from error
    # The robot file's UR5e meshes are for drawing only: the lab (physics, depth camera,
    # contact checks, geom ids) is the capsule robot alone (harvest_qp.robot.meshes).
    strip_visual_meshes(spec)
    spec.modelname = f"vine_scene_seed{p.seed}"
    home = _robot_home(spec, q0)
    G = home["gripper"]
    y_g = G[:3, 1]  # crop direction, down the cluster
    up = -y_g
    stem_end = G[:3, 3] + p.grasp_offset * up
    stem = _stem_polyline(p, stem_end, up)
    stem_base = stem[-1]
    rng = np.random.default_rng([int(p.seed), 0x1EAF])

    world = spec.worldbody
    # ---- branch and cane (static, collide with the robot)
    b_dir = np.array(
        [
            np.cos(p.branch_pitch) * np.cos(p.branch_yaw),
            np.cos(p.branch_pitch) * np.sin(p.branch_yaw),
            np.sin(p.branch_pitch),
        ]
    )
    b_axis = stem_base + (p.branch_radius + 0.5 * p.stem_radius) * np.array([0.0, 0.0, 1.0])
    b0 = b_axis - 0.03 * b_dir
    b1 = b_axis + p.branch_length * b_dir
    vine = world.add_body(name="vine")
    wood = dict(contype=0, conaffinity=_ROBOT_BIT | _HELD_CROP_BIT, group=1, rgba=list(BRANCH_COLOR))
    vine.add_geom(
        name="branch",
        type=mujoco.mjtGeom.mjGEOM_CAPSULE,
        fromto=[*b0, *b1],
        size=[p.branch_radius, 0, 0],
        **wood,
    )
    cane_r = 1.5 * p.branch_radius + 0.004
    cane = (b1 - np.array([0.0, 0.8, 0.0]), b1 + np.array([0.0, 0.8, 0.0]))
    vine.add_geom(
        name="cane",
        type=mujoco.mjtGeom.mjGEOM_CAPSULE,
        fromto=[*cane[0], *cane[1]],
        size=[cane_r, 0, 0],
        **wood,
    )
    vine.add_site(name="stem_base", pos=list(stem_base), group=4)

    # ---- stem: chain of capsules on ball joints, axial slide spring at the top
    n = p.stem_segments
    seg_len = p.stem_length / n
    lean_hint = stem[-1] - stem[0]
    parent_R, parent_p = np.eye(3), np.zeros(3)
    parent = world
    seg_mass = max(1000.0 * np.pi * p.stem_radius**2 * seg_len, 0.002)
    stem_names = []
    for k in range(n):
        top, bot = stem[n - k], stem[n - k - 1]
        R = _frame_from_z(bot - top, lean_hint)
        body = parent.add_body(name=f"stem_{k}", pos=list(parent_R.T @ (top - parent_p)), quat=_quat(parent_R.T @ R))
        body.add_joint(
            name=f"stem_ball_{k}",
            type=mujoco.mjtJoint.mjJNT_BALL,
            stiffness=[p.stem_bend_stiffness, 0, 0],
            damping=[0.002, 0, 0],
            armature=1e-5,
        )
        if k == 0:
            body.add_joint(
                name="stem_slide",
                type=mujoco.mjtJoint.mjJNT_SLIDE,
                axis=[0, 0, 1],
                stiffness=[p.stem_axial_stiffness, 0, 0],
                damping=[2.0, 0, 0],
                armature=1e-3,
            )
        body.add_geom(
            name=f"stem_seg_{k}",
            type=mujoco.mjtGeom.mjGEOM_CAPSULE,
            fromto=[0, 0, 0, 0, 0, seg_len],
            size=[p.stem_radius, 0, 0],
            mass=seg_mass,
            contype=0,
            conaffinity=0,
            group=1,
            rgba=list(STEM_COLOR),
        )
        stem_names.append(f"stem_seg_{k}")
        parent, parent_R, parent_p = body, R, top

    # ---- cluster: rachis + berries in one body hanging on a ball joint at the stem end
    R_c = _frame_from_z(y_g, G[:3, 2])
    cluster = parent.add_body(
        name="cluster", pos=list(parent_R.T @ (stem_end - parent_p)), quat=_quat(parent_R.T @ R_c)
    )
    cluster.add_joint(
        name="cluster_ball", type=mujoco.mjtJoint.mjJNT_BALL, stiffness=[p.stem_bend_stiffness, 0, 0],
        damping=[0.002, 0, 0], armature=1e-5,
    )  # fmt: skip
    cluster.add_site(name="stem_end", pos=[0, 0, 0], group=4)
    # The held crop collides with the wood (hard) and the foliage (soft), never with the robot
    # (it would fight the weld) nor its own stem: its own contact bit, which only the vine accepts.
    # Without it the crop sat 12-16 mm inside the branch on a held-out scene, uncounted.
    soft = dict(contype=_HELD_CROP_BIT, conaffinity=0, group=1)
    rachis_mass = 0.01
    cluster.add_geom(
        name="rachis", type=mujoco.mjtGeom.mjGEOM_CAPSULE, fromto=[0, 0, 0, 0, 0, 0.7 * p.cluster_length],
        size=[0.004, 0, 0], mass=rachis_mass, rgba=list(RACHIS_COLOR), **soft,
    )  # fmt: skip
    berries = _berry_positions(p, rng)
    berry_mass = (p.cluster_mass - rachis_mass) / len(berries)
    for i, c in enumerate(berries):
        cluster.add_geom(
            name=f"berry_{i}", type=mujoco.mjtGeom.mjGEOM_SPHERE, pos=list(c), size=[p.berry_radius, 0, 0],
            mass=berry_mass, rgba=list(BERRY_COLOR), **soft,
        )  # fmt: skip

    # ---- leaves
    camera_start = home["camera"][:3, 3] if p.camera_start is None else np.asarray(p.camera_start, float)
    cluster_axis = (stem_end, stem_end + (p.grasp_offset + 0.03 + p.cluster_length) * y_g)
    tool_axis = (home["ft_sensor"][:3, 3], G[:3, 3])
    approach_views, coverage_view = _approach_views(camera_start, stem_base, cluster_axis)
    leaves = _leaf_layout(
        p, rng, stem=stem, cluster_axis=cluster_axis, tool_axis=tool_axis, branch=(b0, b1), cane=cane,
        coverage_view=coverage_view, approach_views=approach_views, robot_capsules=home["robot_capsules"],
    )  # fmt: skip
    # Leaves and petioles collide with the robot and the held crop (not with the stem); a softer
    # contact than the wood's, as real leaves yield.
    foliage = dict(contype=0, conaffinity=_ROBOT_BIT | _HELD_CROP_BIT, group=1, solref=list(_FOLIAGE_SOLREF),
                   solmix=_FOLIAGE_SOLMIX)
    for i, leaf in enumerate(leaves):
        shade = 1.0 + 0.12 * (rng.uniform() - 0.5)
        rgba = [LEAF_COLOR[0] * shade, LEAF_COLOR[1] * shade, LEAF_COLOR[2] * shade, 1.0]
        vine.add_geom(
            name=f"leaf_{i}", type=mujoco.mjtGeom.mjGEOM_ELLIPSOID, pos=list(leaf.centre),
            quat=_quat(leaf.rotation),
            size=[leaf.half_length, leaf.half_width, _LEAF_THICKNESS], rgba=rgba, **foliage,
        )  # fmt: skip
        a, b = leaf.petiole
        if np.linalg.norm(b - a) > 1e-3:
            vine.add_geom(
                name=f"petiole_{i}", type=mujoco.mjtGeom.mjGEOM_CAPSULE, fromto=[*a, *b],
                size=[_PETIOLE_RADIUS, 0, 0], rgba=list(RACHIS_COLOR), **foliage,
            )  # fmt: skip

    # ---- other clusters hanging from the cane: static, green stems, soft berries
    sight_from = np.repeat(approach_views, 13, axis=0)
    sight_to = np.tile(_stem_samples(stem, 13), (len(approach_views), 1))
    keep_clear = [
        (cluster_axis[0], cluster_axis[1], p.cluster_radius), (tool_axis[0], tool_axis[1], 0.06),
        (stem[0], stem[-1], 0.02), (camera_start, camera_start, 0.1),
    ]  # fmt: skip
    others = _other_clusters(p, rng, cane=cane, keep_clear=keep_clear, sight=(sight_from, sight_to))
    for i, other in enumerate(others):
        a, b = other.stem
        vine.add_geom(
            name=f"other_cluster_{i}_stem", type=mujoco.mjtGeom.mjGEOM_CAPSULE, fromto=[*a, *b],
            size=[0.003, 0, 0], rgba=list(RACHIS_COLOR), **foliage,
        )  # fmt: skip
        for j, c in enumerate(other.berries):
            vine.add_geom(
                name=f"other_cluster_{i}_berry_{j}", type=mujoco.mjtGeom.mjGEOM_SPHERE, pos=list(c),
                size=[other.berry_radius, 0, 0], rgba=list(BERRY_COLOR), **foliage,
            )  # fmt: skip

    # ---- grasp, sensors, camera, servos
    spec.add_equality(
        name="grasp", type=mujoco.mjtEq.mjEQ_WELD, name1=desc.GRASP_TOOL.name, name2="cluster",
        objtype=mujoco.mjtObj.mjOBJ_BODY, solref=list(_WELD_SOLREF),
    )  # fmt: skip
    spec.add_sensor(
        name="ft_force",
        type=mujoco.mjtSensor.mjSENS_FORCE,
        objtype=mujoco.mjtObj.mjOBJ_SITE,
        objname="ft_sensor",
    )
    spec.add_sensor(
        name="ft_torque",
        type=mujoco.mjtSensor.mjSENS_TORQUE,
        objtype=mujoco.mjtObj.mjOBJ_SITE,
        objname="ft_sensor",
    )
    spec.add_sensor(
        name="stem_force",
        type=mujoco.mjtSensor.mjSENS_FORCE,
        objtype=mujoco.mjtObj.mjOBJ_SITE,
        objname="stem_end",
    )
    cam_site = spec.site("camera")
    # MuJoCo cameras look along -z with y up; {C} looks along +z with y down: turn by pi about x.
    site_R = np.zeros(9)
    mujoco.mju_quat2Mat(site_R, np.asarray(cam_site.quat, float))
    cam_R = site_R.reshape(3, 3) @ np.diag([1.0, -1.0, -1.0])
    spec.body(desc.CAMERA_TOOL.name).add_camera(name=CAMERA_NAME, pos=list(cam_site.pos), quat=_quat(cam_R), fovy=40.0)
    actuator_names = add_joint_actuators(spec, home["inertia"], actuation)

    try:
        model = spec.compile()
    except Exception as error:
        raise ModelError(f"the vine scene (seed {p.seed}) does not compile: {error}") from error

    robot_bodies = {model.body(desc.collision_bodies()[0].link).id}
    for b in range(model.nbody):
        name = model.body(b).name
        if name.startswith(desc.ARM_PREFIXES) or name in (desc.CAMERA_TOOL.name, desc.GRASP_TOOL.name):
            robot_bodies.add(b)
    labels = np.full(model.ngeom, OBSTACLE, dtype=np.int8)
    for g in range(model.ngeom):
        if int(model.geom_bodyid[g]) in robot_bodies:
            labels[g] = ROBOT
    stem_ids = np.array([model.geom(nm).id for nm in stem_names], dtype=np.int32)
    labels[stem_ids] = STEM
    ids = {
        "cluster": model.body("cluster").id,
        "weld": model.equality("grasp").id,
        "cam_tool": model.body(desc.CAMERA_TOOL.name).id,
        "grasp_tool": model.body(desc.GRASP_TOOL.name).id,
        "stem_slide": model.joint("stem_slide").id,
        "occluder": model.geom("leaf_0").id if (p.occlude_stem and leaves) else -1,
        "ft_force": model.sensor("ft_force").id,
        "ft_torque": model.sensor("ft_torque").id,
        "stem_force": model.sensor("stem_force").id,
        "camera_site": model.site("camera").id,
        "gripper_site": model.site("gripper").id,
        "ft_site": model.site("ft_sensor").id,
        "stem_end_site": model.site("stem_end").id,
    }
    geom_names = [model.geom(g).name for g in range(model.ngeom)]
    return VineScene(
        params=p,
        spec=spec,
        model=model,
        home_q=q0,
        gripper_home=G,
        camera_home=home["camera"],
        stem_polyline=stem,
        geom_labels=labels,
        ids=ids,
        stem_geoms=stem_ids,
        leaf_geoms=np.array([g for g, nm in enumerate(geom_names) if nm.startswith("leaf_")], dtype=np.int32),
        berry_geoms=np.array([g for g, nm in enumerate(geom_names) if nm.startswith("berry_")], dtype=np.int32),
        actuator_names=actuator_names,
        vine_geoms=np.flatnonzero(model.geom_bodyid == model.body("vine").id).astype(np.int32),
        camera_start=np.array(camera_start, dtype=float),
        cluster_centre=0.5 * (cluster_axis[0] + cluster_axis[1]),
    )
