"""Base class of the QP tasks."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterable

import numpy as np
import pinocchio as pin

from harvest_qp.configuration import Configuration, as_configuration
from harvest_qp.validation import (
    as_instances,
    as_integer,
    as_level,
    as_nonnegative_vector,
    as_positive_scalar,
    as_vector,
)

#: Level of hard tasks: they become equality constraints of every QP in the stack.
HARD = 0


class Task(ABC):
    """A velocity-level objective ``J qdot = v`` with per-row weights.

    At its priority ``level`` the task contributes ``|| diag(sqrt(w)) (J qdot - v) ||^2``
    to the cost. Tasks on the same level trade off by weight (soft priorities); a
    higher level (larger number) optimises only within the optimal set of the levels
    above it (strict priorities); level :data:`HARD` (0) makes ``J qdot = v`` an
    equality constraint.

    ``weight``, ``level`` and ``gain`` may be reassigned at any time; each assignment is
    checked like the constructor's argument.

    A task is checked against the robot model the first time it is computed on it
    (and again whenever it meets another model): :meth:`check_configuration` raises
    :class:`~harvest_qp.exceptions.DimensionError` for a size that does not fit. The solver
    also checks the shapes of the rows every task hands it, before its compiled kernels
    (which do not check bounds) see them.

    Args:
        dim: number of task rows (an integer >= 1).
        weight: scalar or per-row weights (>= 0, unit: 1 / (task unit)^2). A zero weight frees that row.
        level: priority level, 0 (hard), 1 (highest soft), 2, ...
        gain: feedback gain [1/s] of tasks that correct an error.
    """

    def __init__(self, dim: int, *, weight: float | np.ndarray = 1.0, level: int = 1, gain: float = 1.0) -> None:
        self._dim = as_integer(dim, f"{type(self).__name__} dim", minimum=1)
        self.weight = weight
        self.level = level
        self.gain = gain
        #: The pinocchio model this task was last checked against (None: not yet).
        self._model: pin.Model | None = None

    # ------------------------------------------------------------------ checked attributes
    @property
    def dim(self) -> int:
        """Number of task rows."""
        return self._dim

    @property
    def weight(self) -> np.ndarray:
        """Per-row weights (dim,), >= 0."""
        return self._weight

    @weight.setter
    def weight(self, value: float | np.ndarray) -> None:
        self._weight = as_nonnegative_vector(value, self._dim, f"{self._label()} weight")

    @property
    def level(self) -> int:
        """Priority level: 0 (hard), 1 (highest soft), 2, ..."""
        return self._level

    @level.setter
    def level(self, value: int) -> None:
        self._level = as_level(value, f"{self._label()} level")

    @property
    def gain(self) -> float:
        """Feedback gain [1/s] (>= 0)."""
        return self._gain

    @gain.setter
    def gain(self, value: float) -> None:
        self._gain = as_positive_scalar(value, f"{self._label()} gain", allow_zero=True)

    def _label(self) -> str:
        """How messages name this task (subclasses add their frame names)."""
        return type(self).__name__

    # ------------------------------------------------------------------ model checks
    def check_configuration(self, configuration: Configuration) -> None:
        """Raise unless this task can run on ``configuration``'s model.

        Raises:
            InvalidInputError: ``configuration`` is not a :class:`Configuration`.
            DimensionError: a size of this task disagrees with the model's ``nv``.
            UnknownFrameError: the task names a frame the model lacks.
        """
        as_configuration(configuration, f"{self._label()} configuration")

    def _ensure_bound(self, configuration: Configuration) -> None:
        """Check this task against ``configuration``'s model once per model (the hot path is one ``is``)."""
        model = getattr(configuration, "model", None)
        if model is None or model is not self._model:
            self.check_configuration(configuration)
            self._model = model
            self._bind(configuration)

    def _bind(self, configuration: Configuration) -> None:  # noqa: B027 (an optional hook)
        """Hook: cache what depends on the model (frame indices, buffers); called after the check."""

    # ------------------------------------------------------------------ rows
    @abstractmethod
    def compute(self, configuration: Configuration, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Task Jacobian ``J`` (dim x nv) and desired task velocity ``v`` (dim,) for a step of ``dt`` [s]."""

    def compute_rows(self, configuration: Configuration, dt: float) -> tuple[np.ndarray | None, np.ndarray]:
        """Like :meth:`compute`, but ``J`` may be ``None`` meaning the identity (joint-space tasks).

        The solver calls this one so that joint-space tasks skip a dense ``I`` product (it
        checks the shapes it gets, :func:`~harvest_qp.validation.check_task_rows`).
        """
        self._ensure_bound(configuration)
        return self.compute(configuration, dt)

    def residual(self, configuration: Configuration, qdot: np.ndarray, dt: float) -> np.ndarray:
        """Weighted residual ``diag(sqrt(w)) (J qdot - v)`` of a solution ``qdot`` [rad/s]."""
        self._ensure_bound(configuration)
        qdot = as_vector(qdot, configuration.nv, f"{self._label()} residual qdot")
        J, v = self.compute(configuration, dt)
        return np.sqrt(self.weight) * (J @ qdot - v)

    def __repr__(self) -> str:
        return f"{self._label()}(level={self.level}, weight={self.weight.tolist()}, gain={self.gain})"


def check_tasks(
    tasks: Iterable[Task], configuration: Configuration | None = None, *, name: str = "tasks"
) -> list[Task]:
    """The tasks as a list, after checking each is a :class:`Task`.

    The list must not be empty (a QP without a task has no objective). With a
    ``configuration``, each task's sizes and frames are also checked against its model
    (:meth:`Task.check_configuration`), so a wrong task fails when the controller is
    built instead of at its first tick.

    Raises:
        InvalidInputError: not a sequence of tasks, or empty, or an item that is not a Task
            (the message names its position and type, e.g. ``tasks[1] must be a Task, got str``).
        DimensionError: a task's size disagrees with the model.
        UnknownFrameError: a task names a frame the model lacks.
    """
    items = as_instances(tasks, Task, name, allow_empty=False)
    if configuration is not None:
        as_configuration(configuration)
        for task in items:
            task.check_configuration(configuration)
    return items
