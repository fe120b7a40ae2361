"""Drive a frame to a target pose."""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from harvest_qp.configuration import Configuration
from harvest_qp.exceptions import InvalidInputError
from harvest_qp.tasks.task import Task
from harvest_qp.validation import as_matrix, as_vector


class FramePoseTask(Task):
    """``J qdot = gain * e + V_ff`` with the pose error ``e = [p* - p; log(R* R^T)]`` (world).

    Args:
        frame: frame name.
        weight: scalar or 6 per-axis weights (world axes).
        level: priority level.
        gain: error feedback gain [1/s].
    """

    def __init__(self, frame: str, *, weight: float | np.ndarray = 1.0, level: int = 1, gain: float = 1.0):
        super().__init__(6, weight=weight, level=level, gain=gain)
        self.frame = frame
        self.target_position: np.ndarray | None = None
        self.target_rotation: np.ndarray | None = None
        self.feedforward = np.zeros(6)

    def set_target(self, position: np.ndarray, rotation: np.ndarray, *, feedforward: np.ndarray | None = None):
        """Target position [m] and rotation matrix (world), optional feed-forward twist."""
        self.target_position = as_vector(position, 3, "target position")
        R = as_matrix(rotation, (3, 3), "target rotation")
        if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
            raise InvalidInputError("target rotation must be a rotation matrix (orthonormal, det +1)")
        self.target_rotation = R
        self.feedforward = np.zeros(6) if feedforward is None else as_vector(feedforward, 6, "feedforward")

    def set_target_from_configuration(self, configuration: Configuration) -> None:
        """Hold the frame where it is now."""
        pose = configuration.frame_pose(self.frame)
        self.set_target(pose.translation, pose.rotation)

    def error(self, configuration: Configuration) -> np.ndarray:
        """Pose error ``[p* - p; log3(R* R^T)]`` [m, rad] in the world frame."""
        if self.target_position is None:
            raise InvalidInputError(f"FramePoseTask({self.frame!r}) has no target: call set_target first")
        pose = configuration.frame_pose(self.frame)
        rot = pin.log3(self.target_rotation @ pose.rotation.T)
        return np.concatenate([self.target_position - pose.translation, rot])

    def compute(self, configuration: Configuration, dt: float) -> tuple[np.ndarray, np.ndarray]:
        return configuration.frame_jacobian(self.frame), self.gain * self.error(configuration) + self.feedforward
