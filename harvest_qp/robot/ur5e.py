"""UR5e kinematic and inertial data from the public datasheet.

This module together with :mod:`harvest_qp.robot.description` is the single
source of truth of the robot: the URDF (read by pinocchio and placo) and the
MJCF (read by MuJoCo) in ``robots/dual_ur5e/`` are generated from it by
``python -m harvest_qp.robot.generate`` and a test checks they are up to date.

Frames follow the standard Denavit-Hartenberg convention
``T_i = Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``; each link body sits at its DH frame
and its hinge turns about the local z axis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Link offsets along the previous z axis [m].
DH_D = (0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996)
#: Link lengths along x [m].
DH_A = (0.0, -0.425, -0.3922, 0.0, 0.0, 0.0)
#: Link twists about x [rad].
DH_ALPHA = (np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0)

#: Link masses [kg], shoulder to wrist 3.
LINK_MASSES = (3.761, 8.058, 2.846, 1.37, 1.3, 0.365)
#: Joint speed limit [rad/s] (180 deg/s on every joint).
VELOCITY_LIMIT = np.pi
#: Joint torque limits [N m].
TORQUE_LIMITS = (150.0, 150.0, 150.0, 28.0, 28.0, 28.0)
#: Joint position limits [rad]; the elbow is restricted to +-pi as usual in practice.
POSITION_LIMITS = (
    (-2 * np.pi, 2 * np.pi),
    (-2 * np.pi, 2 * np.pi),
    (-np.pi, np.pi),
    (-2 * np.pi, 2 * np.pi),
    (-2 * np.pi, 2 * np.pi),
    (-2 * np.pi, 2 * np.pi),
)
#: Joint names (without the arm prefix), in kinematic order.
JOINT_NAMES = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)
#: Link names (without the arm prefix); ``LINK_NAMES[i]`` is moved by joint ``i``.
LINK_NAMES = (
    "shoulder_link",
    "upper_arm_link",
    "forearm_link",
    "wrist_1_link",
    "wrist_2_link",
    "wrist_3_link",
)


@dataclass(frozen=True)
class Capsule:
    """A capsule fixed to a link: segment ``p0``-``p1`` [m] in the link frame, ``radius`` [m]."""

    name: str
    p0: tuple[float, float, float]
    p1: tuple[float, float, float]
    radius: float


#: Collision capsules per link, in the link's DH frame. The UR5e's lateral offsets
#: (0.138 m at the shoulder, -0.131 m at the elbow) are folded into DH d4; the tubes
#: are placed at their real offsets along the joint axes so the capsules cover the
#: physical arm.
LINK_CAPSULES: dict[str, tuple[Capsule, ...]] = {
    "shoulder_link": (Capsule("shoulder", (0.0, 0.0, 0.0), (0.0, 0.0, 0.17), 0.065),),
    "upper_arm_link": (Capsule("upper_arm", (0.0, 0.0, 0.138), (-0.425, 0.0, 0.138), 0.06),),
    "forearm_link": (Capsule("forearm", (0.0, 0.0, 0.007), (-0.3922, 0.0, 0.007), 0.05),),
    "wrist_1_link": (Capsule("wrist_1", (0.0, 0.0, 0.04), (0.0, 0.0, 0.1333), 0.045),),
    "wrist_2_link": (Capsule("wrist_2", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0997), 0.045),),
    "wrist_3_link": (Capsule("wrist_3", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0996), 0.04),),
}


def dh_transform(a: float, d: float, alpha: float, theta: float) -> np.ndarray:
    """Homogeneous transform ``Rz(theta) Tz(d) Tx(a) Rx(alpha)`` (4x4)."""
    ct, st = np.cos(theta), np.sin(theta)
    ca, sa = np.cos(alpha), np.sin(alpha)
    return np.array(
        [
            [ct, -st * ca, st * sa, a * ct],
            [st, ct * ca, -ct * sa, a * st],
            [0.0, sa, ca, d],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def dh_flange_pose(q: np.ndarray, base: np.ndarray | None = None) -> np.ndarray:
    """Flange pose (4x4, in the frame of ``base``) by the DH formula, for 6 joint angles [rad]."""
    T = np.eye(4) if base is None else np.array(base, dtype=float)
    for i in range(6):
        T = T @ dh_transform(DH_A[i], DH_D[i], DH_ALPHA[i], float(q[i]))
    return T


def cylinder_inertia(mass: float, radius: float, length: float, axis: int) -> np.ndarray:
    """Diagonal inertia [kg m^2] of a solid cylinder along ``axis`` (0, 1, 2) about its centre."""
    axial = 0.5 * mass * radius**2
    transverse = mass * (3 * radius**2 + length**2) / 12.0
    inertia = np.full(3, transverse)
    inertia[axis] = axial
    return inertia
