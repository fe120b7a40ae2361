"""The dual-UR5e harvester: two UR5e arms side by side on a common stand.

This module is the single source of truth of the robot layout: arm mounts, tools,
task frames and collision capsules. The files in ``robots/dual_ur5e/`` are generated
from it (``python -m harvest_qp.robot.generate``).

World frame: z up, x pointing from the robot towards the vine. The camera arm
(prefix ``cam_``) stands at +y, the grasping arm (prefix ``grasp_``) at -y, both
facing the vine, as in the paper's lab setup.

Task frames (the paper's conventions):

* ``camera`` -- the camera optical frame {C} on the camera arm; its z axis is the
  view direction, x to the right and y down in the image.
* ``cutter_tip`` -- the tip of the cutting tool on the camera arm.
* ``gripper`` -- the grasp frame {G}; its y axis is the grasped crop's direction
  (``eq:rot_contr`` aligns it with the stem direction n_c).
* ``ft_sensor`` -- the wrist force/torque sensor of the grasping arm (at the flange).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from harvest_qp.robot import ur5e
from harvest_qp.robot.ur5e import Capsule

ARM_PREFIXES = ("cam_", "grasp_")
CAMERA_ARM, GRASP_ARM = ARM_PREFIXES


@dataclass(frozen=True)
class Mount:
    """Where an arm's base frame sits in the world: position [m] and yaw [rad] about z."""

    position: tuple[float, float, float]
    yaw: float


@dataclass(frozen=True)
class Frame:
    """A task frame fixed to a link: position [m] and rotation (3x3, row-major) in the link frame."""

    name: str
    parent_link: str
    position: tuple[float, float, float]
    rotation: tuple[tuple[float, float, float], ...] = ((1, 0, 0), (0, 1, 0), (0, 0, 1))


@dataclass(frozen=True)
class Tool:
    """A rigid tool bolted to an arm's flange: mass [kg], centre of mass [m], capsules."""

    name: str
    mass: float
    com: tuple[float, float, float]
    inertia: tuple[float, float, float]
    capsules: tuple[Capsule, ...]
    frames: tuple[Frame, ...] = field(default_factory=tuple)


#: Arm base frames. Yaw pi makes the DH q = 0 stretch point +x (towards the vine).
MOUNTS = {
    CAMERA_ARM: Mount((0.0, 0.36, 0.80), np.pi),
    GRASP_ARM: Mount((0.0, -0.36, 0.80), np.pi),
}

#: Pedestal the two arms stand on: a capsule in the world frame.
STAND_CAPSULE = Capsule("stand", (0.0, 0.0, 0.0), (0.0, 0.0, 0.72), 0.12)
#: Plate across the top of the pedestal carrying both arm bases.
STAND_PLATE_CAPSULE = Capsule("stand_plate", (0.0, 0.42, 0.74), (0.0, -0.42, 0.74), 0.06)

CAMERA_TOOL = Tool(
    name="cam_tool",
    mass=0.45,
    com=(0.0, 0.03, 0.05),
    inertia=(8e-4, 8e-4, 4e-4),
    capsules=(
        Capsule("cutter", (0.0, 0.0, 0.0), (0.0, 0.0, 0.15), 0.02),
        Capsule("camera_housing", (-0.045, 0.065, 0.025), (0.045, 0.065, 0.025), 0.02),
    ),
    frames=(
        Frame("camera", "cam_tool", (0.0, 0.065, 0.045)),
        Frame("cutter_tip", "cam_tool", (0.0, 0.0, 0.15)),
    ),
)

#: The grasping tool's collision capsule ends 5 mm short of the grasp frame (its tip sphere
#: reaches z = 0.135 m, the grasp point is at z = 0.14 m): the fingertips pinch the rachis at
#: the grasp point and the stem rises from the cluster top above them. A capsule reaching past
#: the grasp point (0.11 m + 45 mm = 0.155 m before) swallowed the first 18-19 mm of every stem,
#: which a camera then cannot see (the perceived stem length l shrank by 25-37 %).
GRASP_TOOL = Tool(
    name="grasp_tool",
    mass=0.6,
    com=(0.0, 0.0, 0.06),
    inertia=(1.2e-3, 1.2e-3, 6e-4),
    capsules=(Capsule("gripper", (0.0, 0.0, 0.0), (0.0, 0.0, 0.09), 0.045),),
    frames=(
        Frame("gripper", "grasp_tool", (0.0, 0.0, 0.14)),
        Frame("ft_sensor", "grasp_tool", (0.0, 0.0, 0.0)),
    ),
)

TOOLS = {CAMERA_ARM: CAMERA_TOOL, GRASP_ARM: GRASP_TOOL}

#: Joint configuration the episodes start from [rad], camera arm then grasping arm.
#: Both tools point forward (+x) with their y axis down: the camera at about
#: (0.30, 0.55, 1.10) m, outside the region of interest, and the gripper at about
#: (0.50, -0.12, 1.15) m, where the scene hangs the grape cluster.
HOME_Q = np.array([0.311, -1.613, 2.576, -4.104, -1.882, 0.0, 0.359, -1.317, 2.288, -4.112, -1.93, 0.0])


def camera_mount() -> np.ndarray:
    """The description's camera optical frame in the camera arm's flange ``cam_flange`` (4x4, [m]):
    what a hand-eye calibration replaces."""
    frame = next(f for f in CAMERA_TOOL.frames if f.name == "camera")
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = np.asarray(frame.rotation, float), frame.position
    return T


def joint_names() -> list[str]:
    """All 12 actuated joint names, camera arm first (the paper's q = [q_c; q_g])."""
    return [p + j for p in ARM_PREFIXES for j in ur5e.JOINT_NAMES]


def mount_transform(prefix: str) -> np.ndarray:
    """World pose (4x4) of the base frame of the arm with ``prefix``."""
    mount = MOUNTS[prefix]
    c, s = np.cos(mount.yaw), np.sin(mount.yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = mount.position
    return T


@dataclass(frozen=True)
class CollisionBody:
    """A collision capsule and the link (frame name in the model) that carries it."""

    name: str
    link: str
    capsule: Capsule
    arm: str  # "cam_", "grasp_" or "" for the fixed environment
    link_index: int  # 0 = arm base, 1..6 = link moved by joint i, 7 = tool


def collision_bodies() -> list[CollisionBody]:
    """Every robot collision capsule, with its carrying link, in a fixed order."""
    bodies = [
        CollisionBody(STAND_CAPSULE.name, "base", STAND_CAPSULE, "", 0),
        CollisionBody(STAND_PLATE_CAPSULE.name, "base", STAND_PLATE_CAPSULE, "", 0),
    ]
    for prefix in ARM_PREFIXES:
        for i, link in enumerate(ur5e.LINK_NAMES):
            for cap in ur5e.LINK_CAPSULES[link]:
                bodies.append(CollisionBody(prefix + cap.name, prefix + link, cap, prefix, i + 1))
        tool = TOOLS[prefix]
        for cap in tool.capsules:
            bodies.append(CollisionBody(prefix + cap.name, tool.name, cap, prefix, 7))
    return bodies


#: Same-arm pairs closer than this many links apart never collide by construction.
MIN_LINK_SEPARATION = 3


def self_collision_pairs() -> list[tuple[str, str]]:
    """Candidate robot-robot capsule pairs: same arm (links >= 3 apart), arm to arm, arm to stand.

    The base column and the upper arm of an arm are always near the stand, so stand
    pairs only involve the forearm, wrist and tool capsules (link index >= 3).
    """
    bodies = collision_bodies()
    pairs = []
    for ia, a in enumerate(bodies):
        for b in bodies[ia + 1 :]:
            if a.arm == "" and b.arm == "":
                continue
            if a.arm == "" or b.arm == "":
                arm_body = b if a.arm == "" else a
                if arm_body.link_index >= 3:
                    pairs.append((a.name, b.name))
            elif a.arm == b.arm:
                if abs(a.link_index - b.link_index) >= MIN_LINK_SEPARATION:
                    pairs.append((a.name, b.name))
            else:
                pairs.append((a.name, b.name))
    return pairs
