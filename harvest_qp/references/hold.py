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

__all__ = ["hold_twist"]


def hold_twist(gripper_pose: ArrayLike, hold_pose: ArrayLike, *, k_hold: float) -> NDArray[np.float64]:
    """V_h ``(6,)`` [m/s; rad/s], world frame, from the gripper pose {G} and the held pose {G_0}
    (both ``(4, 4)``), gain ``k_hold`` [1/s]."""
    pose = as_pose(gripper_pose, "gripper_pose")
    hold = as_pose(hold_pose, "hold_pose")
    k_hold = as_positive_scalar(k_hold, "k_hold", allow_zero=True)
    twist = np.empty(6)
    twist[:3] = -k_hold * (pose[:3, 3] - hold[:3, 3])
    twist[3:] = -k_hold * pin.log3(pose[:3, :3] @ hold[:3, :3].T)
    return twist
