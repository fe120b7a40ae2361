"""Joint-space posture task."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from harvest_qp.configuration import Configuration
from harvest_qp.exceptions import DimensionError, InvalidInputError
from harvest_qp.qp_kernels import scaled_difference
from harvest_qp.tasks.task import Task
from harvest_qp.validation import as_vector, describe


class PostureTask(Task):
    """``qdot = gain (q* - q)``: pull the joints towards a posture [rad] (resolves redundancy).

    Args:
        target: posture ``q*`` [rad], one entry per joint of the model it will run on;
            checked against the model at the first solve
            (:class:`~harvest_qp.exceptions.DimensionError` if its size is not ``nv``).
        weight: scalar or per-joint weights [1/(rad/s)^2].
        level: priority level.
        gain: feedback gain [1/s].
    """

    def __init__(
        self,
        target: np.ndarray | Sequence[float],
        *,
        weight: float | np.ndarray = 1e-3,
        level: int = 1,
        gain: float = 1.0,
    ) -> None:
        try:
            size = None if target is None or isinstance(target, (str, bytes)) else np.shape(target)
        except ValueError:  # a ragged nested sequence
            size = None
        if size is None or len(size) != 1 or size[0] == 0:
            raise InvalidInputError(
                f"PostureTask target must be a non-empty vector of joint positions [rad] (shape (nv,)), "
                f"got {describe(target)}"
            )
        super().__init__(size[0], weight=weight, level=level, gain=gain)
        self.target = target

    @property
    def target(self) -> np.ndarray:
        """Posture ``q*`` [rad] (dim,)."""
        return self._target

    @target.setter
    def target(self, value: np.ndarray | Sequence[float]) -> None:
        self._target = as_vector(value, self.dim, "PostureTask target")

    def set_target(self, target: np.ndarray | Sequence[float]) -> None:
        """New posture [rad] (same size as the first)."""
        self.target = target

    def check_configuration(self, configuration: Configuration) -> None:
        super().check_configuration(configuration)
        if self.dim != configuration.nv:
            raise DimensionError(
                f"PostureTask target must have one entry per joint of the model (nv = {configuration.nv}), "
                f"got {self.dim} entries: {describe(self.target)}"
            )

    def compute(self, configuration: Configuration, dt: float) -> tuple[np.ndarray, np.ndarray]:
        self._ensure_bound(configuration)
        return np.eye(self.dim), self.gain * (self.target - configuration.q)

    def compute_rows(self, configuration: Configuration, dt: float) -> tuple[None, np.ndarray]:
        if self._model is None or getattr(configuration, "model", None) is not self._model:
            self._ensure_bound(configuration)  # the hot path is the one identity test above
        # One compiled call instead of two numpy operations (the target's size was checked
        # against the model's nv when the task was bound; q has nq == nv entries).
        return None, scaled_difference(self._gain, self._target, configuration.q)
