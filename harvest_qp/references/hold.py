"""Hold reference of the grasping arm during the approach (beyond the paper).

Before the switch (``subsec:biman_coord``) the grasping arm holds the crop still at the pose
{G_0} it had at the start::

    V_h = -k_h [ p_g - p_g0 ;  log3(R_g R_g0^T) ]

(a proportional pose servo; log3 is SO(3)'s logarithm, pinocchio's ``log3``), so the arm's
own QP task resists what the camera arm's motion and the stem's pull would otherwise move.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike, NDArray

from harvest_qp.references._checks import as_pose, as_positive_scalar
from harvest_qp.references._vec3 import scale, sub

__all__ = ["HoldPose"]


class HoldPose:
    """V_h of the grasping arm: a pose servo to the held pose {G_0}.

    Args:
        hold_pose: {G_0}, ``(4, 4)`` homogeneous pose (world).
        k_hold: gain k_h [1/s].
    """

    def __init__(self, hold_pose: ArrayLike, *, k_hold: float) -> None:
        pose = as_pose(hold_pose, "hold_pose")
        self.k_hold = as_positive_scalar(k_hold, "k_hold", allow_zero=True)
        self.position = pose[:3, 3].tolist()
        self.rotation_T = pose[:3, :3].T.copy()  # R_g0^T

    def update(self, gripper_pose: ArrayLike) -> NDArray[np.float64]:
        """V_h ``(6,)`` [m/s; rad/s], world frame, at the gripper pose {G} ``(4, 4)``."""
        pose = as_pose(gripper_pose, "gripper_pose")
        linear = sub(pose[:3, 3].tolist(), self.position)
        angular = pin.log3(pose[:3, :3] @ self.rotation_T).tolist()
        return np.array((*scale(-self.k_hold, linear), *scale(-self.k_hold, angular)))
