"""What the pose tasks share: a checked target position [m] and rotation."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.tasks.task import Task
from harvest_qp.validation import as_rotation, as_vector


class PoseTargetTask(Task):
    """A 6-row task driving a pose to a target (:class:`FramePoseTask`, :class:`RelativeFrameTask`).

    Subclasses say in which frame the target is expressed and compute the rows.
    """

    def __init__(self, *, weight: float | np.ndarray = 1.0, level: int = 1, gain: float = 1.0) -> None:
        super().__init__(6, weight=weight, level=level, gain=gain)
        self._target_position: np.ndarray | None = None
        self._target_rotation: np.ndarray | None = None

    @property
    def target_position(self) -> np.ndarray | None:
        """Target position [m], None before :meth:`set_target`."""
        return self._target_position

    @target_position.setter
    def target_position(self, value: np.ndarray | Sequence[float]) -> None:
        self._target_position = as_vector(value, 3, f"{self._label()} target position")

    @property
    def target_rotation(self) -> np.ndarray | None:
        """Target rotation matrix, None before :meth:`set_target`."""
        return self._target_rotation

    @target_rotation.setter
    def target_rotation(self, value: np.ndarray | Sequence[Sequence[float]]) -> None:
        self._target_rotation = as_rotation(value, f"{self._label()} target rotation")

    def _checked_target(
        self, position: np.ndarray | Sequence[float], rotation: np.ndarray | Sequence[Sequence[float]]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Both checked before either is assigned (a rejected call leaves the old target)."""
        label = self._label()
        return as_vector(position, 3, f"{label} target position"), as_rotation(rotation, f"{label} target rotation")

    def _require_target(self) -> None:
        if self._target_position is None or self._target_rotation is None:
            raise InvalidInputError(f"{self._label()} has no target: call set_target first")
