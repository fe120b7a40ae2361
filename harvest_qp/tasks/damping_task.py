"""Damping (velocity regularisation) task."""

from __future__ import annotations

import numpy as np

from harvest_qp.configuration import Configuration
from harvest_qp.exceptions import DimensionError
from harvest_qp.tasks.task import Task
from harvest_qp.validation import as_integer


class DampingTask(Task):
    """``qdot = 0`` with a small weight: the Levenberg-Marquardt damping of the QP.

    With twist tasks of weight 1 and damping weight ``lambda^2`` at the same level, the
    unconstrained QP solution is the damped pseudo-inverse ``J^T (J J^T + lambda^2 I)^-1 V``.

    Args:
        nv: number of joints of the model it will run on (``configuration.nv``, 12 for the
            dual UR5e); checked against the model at the first solve
            (:class:`~harvest_qp.exceptions.DimensionError` if it differs).
        weight: scalar or per-joint weights ``lambda^2`` [1/(rad/s)^2].
        level: priority level.
    """

    def __init__(self, nv: int, *, weight: float | np.ndarray = 1e-4, level: int = 1) -> None:
        super().__init__(as_integer(nv, "DampingTask nv", minimum=1), weight=weight, level=level)
        self._zeros = np.zeros(self.dim)

    def check_configuration(self, configuration: Configuration) -> None:
        super().check_configuration(configuration)
        if self.dim != configuration.nv:
            raise DimensionError(f"DampingTask nv must equal the model's nv = {configuration.nv}, got {self.dim}")

    def compute(self, configuration: Configuration, dt: float) -> tuple[np.ndarray, np.ndarray]:
        self._ensure_bound(configuration)
        return np.eye(self.dim), np.zeros(self.dim)

    def compute_rows(self, configuration: Configuration, dt: float) -> tuple[None, np.ndarray]:
        if self._model is None or getattr(configuration, "model", None) is not self._model:
            self._ensure_bound(configuration)  # the hot path is the one identity test above
        return None, self._zeros
