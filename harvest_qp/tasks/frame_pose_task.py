"""Drive a frame to a target pose."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pinocchio as pin

from harvest_qp.configuration import Configuration
from harvest_qp.tasks.pose_target import PoseTargetTask
from harvest_qp.validation import as_name, as_vector


class FramePoseTask(PoseTargetTask):
    """``J qdot = gain * e + V_ff`` with the pose error ``e = [p* - p; log(R* R^T)]`` (world).

    Args:
        frame: frame name (checked at the first solve).
        weight: scalar or 6 per-axis weights (world axes) [1/(m/s)^2, 1/(rad/s)^2].
        level: priority level.
        gain: error feedback gain [1/s].
    """

    def __init__(self, frame: str, *, weight: float | np.ndarray = 1.0, level: int = 1, gain: float = 1.0) -> None:
        self.frame = as_name(frame, "FramePoseTask frame")
        super().__init__(weight=weight, level=level, gain=gain)
        self._feedforward = np.zeros(6)

    def _label(self) -> str:
        return f"FramePoseTask({getattr(self, 'frame', '?')!r})"

    @property
    def feedforward(self) -> np.ndarray:
        """Feed-forward twist [m/s, rad/s] (world) added to the feedback."""
        return self._feedforward

    @feedforward.setter
    def feedforward(self, value: np.ndarray | Sequence[float]) -> None:
        self._feedforward = as_vector(value, 6, f"{self._label()} feedforward")

    def set_target(
        self,
        position: np.ndarray | Sequence[float],
        rotation: np.ndarray | Sequence[Sequence[float]],
        *,
        feedforward: np.ndarray | Sequence[float] | None = None,
    ) -> None:
        """Target position [m] and rotation matrix (world), optional feed-forward twist [m/s, rad/s]."""
        # Check everything before assigning anything: a rejected call leaves the old target.
        position, rotation = self._checked_target(position, rotation)
        feedforward = np.zeros(6) if feedforward is None else as_vector(feedforward, 6, f"{self._label()} feedforward")
        self._target_position, self._target_rotation, self._feedforward = position, rotation, feedforward

    def set_target_from_configuration(self, configuration: Configuration) -> None:
        """Hold the frame where it is now."""
        self._ensure_bound(configuration)
        pose = configuration.frame_pose(self.frame)
        self.set_target(pose.translation, pose.rotation)

    def check_configuration(self, configuration: Configuration) -> None:
        super().check_configuration(configuration)
        configuration.frame_id(self.frame)  # UnknownFrameError listing the valid names

    def error(self, configuration: Configuration) -> np.ndarray:
        """Pose error ``[p* - p; log3(R* R^T)]`` [m, rad] in the world frame."""
        self._require_target()
        self._ensure_bound(configuration)
        pose = configuration.frame_pose(self.frame)
        rot = pin.log3(self.target_rotation @ pose.rotation.T)
        return np.concatenate([self.target_position - pose.translation, rot])

    def compute(self, configuration: Configuration, dt: float) -> tuple[np.ndarray, np.ndarray]:
        v = self.gain * self.error(configuration) + self.feedforward  # checks the configuration first
        return configuration.frame_jacobian(self.frame), v
