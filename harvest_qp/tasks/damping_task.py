"""Damping (velocity regularisation) task."""

from __future__ import annotations

import numpy as np

from harvest_qp.configuration import Configuration
from harvest_qp.tasks.task import Task


class DampingTask(Task):
    """``qdot = 0`` with a small weight: the Levenberg-Marquardt damping of the QP.

    With twist tasks of weight 1 and damping weight ``lambda^2`` at the same level, the
    unconstrained QP solution is the damped pseudo-inverse ``J^T (J J^T + lambda^2 I)^-1 V``.
    """

    def __init__(self, nv: int, *, weight: float | np.ndarray = 1e-4, level: int = 1):
        super().__init__(nv, weight=weight, level=level)
        self._zeros = np.zeros(nv)

    def compute(self, configuration: Configuration, dt: float) -> tuple[np.ndarray, np.ndarray]:
        return np.eye(self.dim), np.zeros(self.dim)

    def compute_rows(self, configuration: Configuration, dt: float) -> tuple[None, np.ndarray]:
        return None, self._zeros
