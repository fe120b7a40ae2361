"""Hard limits of the velocity QP: one limit per file."""

from harvest_qp.limits.collision_avoidance import CapsuleGeometry, CollisionAvoidance
from harvest_qp.limits.joint_acceleration_limit import JointAccelerationLimit
from harvest_qp.limits.joint_position_limit import JointPositionLimit
from harvest_qp.limits.joint_velocity_limit import JointVelocityLimit
from harvest_qp.limits.limit import BoxLimit, Limit, LimitRows

__all__ = [
    "BoxLimit",
    "CapsuleGeometry",
    "CollisionAvoidance",
    "JointAccelerationLimit",
    "JointPositionLimit",
    "JointVelocityLimit",
    "Limit",
    "LimitRows",
]
