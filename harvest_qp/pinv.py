"""The paper's plain pseudo-inverse mapping, kept as a baseline to compare with the QP."""

from __future__ import annotations

import numpy as np
import scipy.linalg

from harvest_qp.configuration import Configuration
from harvest_qp.validation import as_positive_scalar, as_vector


class PseudoInverseMapper:
    """``qdot = J^+(q) V_r`` with ``J = diag(J_c, J_g)`` (``eq:controlled_system``).

    ``V_r = [V_c; V_g]`` stacks the camera-arm and grasping-arm twists (12,) [m/s, rad/s],
    world-aligned at the frame origins. ``damping`` > 0 gives the damped least-squares
    inverse ``J^T (J J^T + damping^2 I)^-1``; 0 gives the Moore-Penrose pseudo-inverse.
    No joint limits or collisions are considered: that is the point of the baseline.

    Args:
        configuration: the robot.
        camera_frame, grasp_frame: frame names of {C} and {G}.
        damping: damping factor (>= 0).
    """

    def __init__(
        self,
        configuration: Configuration,
        *,
        camera_frame: str = "camera",
        grasp_frame: str = "gripper",
        damping: float = 0.0,
    ) -> None:
        self.configuration = configuration
        self.frames = (camera_frame, grasp_frame)
        for name in self.frames:
            configuration.frame_id(name)  # fail early with the list of valid names
        self.damping = as_positive_scalar(damping, "damping", allow_zero=True)

    def jacobian(self) -> np.ndarray:
        """The extended Jacobian (12 x nv): camera twist rows then grasp twist rows."""
        return np.vstack([self.configuration.frame_jacobian(name) for name in self.frames])

    def map(self, twist: np.ndarray) -> np.ndarray:
        """Joint velocities [rad/s] for the stacked reference twist ``V_r`` (12,)."""
        V = as_vector(twist, 12, "V_r")
        J = self.jacobian()
        if self.damping == 0.0:
            return np.linalg.pinv(J) @ V
        JJt = J @ J.T + self.damping**2 * np.eye(J.shape[0])
        return J.T @ scipy.linalg.solve(JJt, V, assume_a="pos")
