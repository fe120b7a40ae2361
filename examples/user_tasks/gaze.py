"""``GazeTask``: point one axis of a frame at a world point (user code, not part of harvest_qp).

Used from YAML as ``type: user_tasks.gaze:GazeTask`` with ``params: {frame, target, axis}``;
harvest_qp checks ``params`` against :class:`GazeTask.Params` before building the task.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from harvest_qp import Configuration
from harvest_qp.tasks import Task

_AXES = {"x": 0, "y": 1, "z": 2}


class GazeTask(Task):
    """Turn ``frame``'s ``axis`` toward ``target``: ``omega = gain * (a x d)`` on the frame's angular rows.

    ``a`` is the frame's axis and ``d`` the unit direction from the frame to the target, both in
    the world; ``|a x d| = sin(angle)``, so the rows rotate the axis onto the target along the
    shortest arc (the frame's translation is left to other tasks). 3 rows, in [rad/s].
    """

    class Params(BaseModel):
        """What YAML may set (checked by harvest_qp before the constructor runs)."""

        model_config = ConfigDict(extra="forbid")
        frame: str = Field(description="frame whose axis looks at the target")
        target: tuple[float, float, float] = Field(description="[m] world point to look at")
        axis: Literal["x", "y", "z"] = Field("z", description="the frame axis that looks (z: a camera's optical axis)")

    def __init__(self, frame: str, target, axis: str = "z", *, weight=1.0, level: int = 1, gain: float = 2.0):
        super().__init__(3, weight=weight, level=level, gain=gain)
        self.frame = frame
        self.target = np.asarray(target, dtype=float)
        self.axis = _AXES[axis]

    def check_configuration(self, configuration: Configuration) -> None:
        super().check_configuration(configuration)
        configuration.frame_id(self.frame)  # an unknown frame fails here, with the valid names

    def angle(self, configuration: Configuration) -> float:
        """[rad] between the axis and the direction to the target."""
        a = configuration.frame_rotation(self.frame)[:, self.axis]
        d = self.target - configuration.frame_position(self.frame)
        return float(np.arccos(np.clip(a @ d / np.linalg.norm(d), -1.0, 1.0)))

    def compute(self, configuration: Configuration, dt: float) -> tuple[np.ndarray, np.ndarray]:
        a = configuration.frame_rotation(self.frame)[:, self.axis]
        d = self.target - configuration.frame_position(self.frame)
        omega = self.gain * np.cross(a, d / np.linalg.norm(d))
        return configuration.frame_jacobian(self.frame)[3:], omega
