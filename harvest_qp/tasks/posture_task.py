"""Joint-space posture task."""

from __future__ import annotations

import numpy as np

from harvest_qp.configuration import Configuration
from harvest_qp.exceptions import InvalidInputError
from harvest_qp.tasks.task import Task
from harvest_qp.validation import as_vector


class PostureTask(Task):
    """``qdot = gain (q* - q)``: pull the joints towards a posture [rad] (resolves redundancy).

    Args:
        target: posture [rad] (nv,).
        weight: scalar or per-joint weights.
        level: priority level.
        gain: feedback gain [1/s].
    """

    def __init__(self, target: np.ndarray, *, weight: float | np.ndarray = 1e-3, level: int = 1, gain: float = 1.0):
        target = np.asarray(target, dtype=float)
        if target.ndim != 1 or target.size == 0:
            raise InvalidInputError(f"posture target must have shape (nv,), got shape {target.shape}")
        super().__init__(target.shape[0], weight=weight, level=level, gain=gain)
        self.target = as_vector(target, self.dim, "posture target")

    def set_target(self, target: np.ndarray) -> None:
        """New posture [rad]."""
        self.target = as_vector(target, self.dim, "posture target")

    def compute(self, configuration: Configuration, dt: float) -> tuple[np.ndarray, np.ndarray]:
        return np.eye(self.dim), self.gain * (self.target - configuration.q)

    def compute_rows(self, configuration: Configuration, dt: float) -> tuple[None, np.ndarray]:
        return None, self.gain * (self.target - configuration.q)
