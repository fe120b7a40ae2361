"""Pose of one frame relative to another (arm to arm)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pinocchio as pin

from harvest_qp.configuration import Configuration
from harvest_qp.exceptions import InvalidInputError
from harvest_qp.tasks.pose_target import PoseTargetTask
from harvest_qp.validation import as_name


def skew(v: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix ``S(v)`` with ``S(v) x = v x x``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


class RelativeFrameTask(PoseTargetTask):
    """Drive the pose of ``frame`` expressed in ``root`` to a target.

    Rows are expressed in the ``root`` frame: linear rows are ``d/dt (R_r^T (p_f - p_r))``
    and angular rows are ``R_r^T (w_f - w_r)``, so e.g. the cutter can keep a fixed
    offset from the gripper while both arms move.

    Args:
        frame, root: frame names (different; checked at the first solve).
        weight: scalar or 6 weights (root axes) [1/(m/s)^2, 1/(rad/s)^2].
        level: priority level.
        gain: error feedback gain [1/s].
    """

    def __init__(
        self, frame: str, root: str, *, weight: float | np.ndarray = 1.0, level: int = 1, gain: float = 1.0
    ) -> None:
        self.frame = as_name(frame, "RelativeFrameTask frame")
        self.root = as_name(root, "RelativeFrameTask root")
        if self.frame == self.root:
            # The pose of a frame in itself never changes: the rows would be all zero.
            raise InvalidInputError(f"RelativeFrameTask frame and root must differ, got both {frame!r}")
        super().__init__(weight=weight, level=level, gain=gain)

    def _label(self) -> str:
        return f"RelativeFrameTask({getattr(self, 'frame', '?')!r}, {getattr(self, 'root', '?')!r})"

    def set_target(
        self, position: np.ndarray | Sequence[float], rotation: np.ndarray | Sequence[Sequence[float]]
    ) -> None:
        """Target position [m] and rotation matrix of ``frame`` in ``root``."""
        self._target_position, self._target_rotation = self._checked_target(position, rotation)

    def check_configuration(self, configuration: Configuration) -> None:
        super().check_configuration(configuration)
        configuration.frame_id(self.frame)  # UnknownFrameError listing the valid names
        configuration.frame_id(self.root)

    def relative_pose(self, configuration: Configuration) -> tuple[np.ndarray, np.ndarray]:
        """Position [m] and rotation of ``frame`` in ``root``."""
        self._ensure_bound(configuration)
        root = configuration.frame_pose(self.root)
        frame = configuration.frame_pose(self.frame)
        Rt = root.rotation.T
        return Rt @ (frame.translation - root.translation), Rt @ frame.rotation

    def jacobian(self, configuration: Configuration) -> np.ndarray:
        """Relative Jacobian (6 x nv) in root coordinates."""
        self._ensure_bound(configuration)
        root = configuration.frame_pose(self.root)
        Jf = configuration.frame_jacobian(self.frame)
        Jr = configuration.frame_jacobian(self.root)
        r = configuration.frame_pose(self.frame).translation - root.translation
        # Velocity of the frame origin relative to the point of the root body at the same place.
        lin = Jf[:3] - Jr[:3] + skew(r) @ Jr[3:]
        ang = Jf[3:] - Jr[3:]
        Rt = root.rotation.T
        return np.vstack([Rt @ lin, Rt @ ang])

    def error(self, configuration: Configuration) -> np.ndarray:
        """Relative pose error [m, rad] in root coordinates."""
        self._require_target()
        p, R = self.relative_pose(configuration)
        return np.concatenate([self.target_position - p, pin.log3(self.target_rotation @ R.T)])

    def compute(self, configuration: Configuration, dt: float) -> tuple[np.ndarray, np.ndarray]:
        return self.jacobian(configuration), self.gain * self.error(configuration)
