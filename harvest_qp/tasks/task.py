"""Base class of the QP tasks."""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

from harvest_qp.configuration import Configuration
from harvest_qp.exceptions import InvalidInputError
from harvest_qp.validation import as_nonnegative_vector

#: Level of hard tasks: they become equality constraints of every QP in the stack.
HARD = 0


class Task(ABC):
    """A velocity-level objective ``J qdot = v`` with per-row weights.

    At its priority ``level`` the task contributes ``|| diag(sqrt(w)) (J qdot - v) ||^2``
    to the cost. Tasks on the same level trade off by weight (soft priorities); a
    higher level (larger number) optimises only within the optimal set of the levels
    above it (strict priorities); level :data:`HARD` (0) makes ``J qdot = v`` an
    equality constraint.

    Args:
        dim: number of task rows.
        weight: scalar or per-row weights (>= 0). A zero weight frees that row.
        level: priority level, 0 (hard), 1 (highest soft), 2, ...
        gain: feedback gain [1/s] of tasks that correct an error.
    """

    def __init__(self, dim: int, *, weight: float | np.ndarray = 1.0, level: int = 1, gain: float = 1.0):
        self.dim = dim
        self.weight = as_nonnegative_vector(weight, dim, f"{type(self).__name__} weight")
        if int(level) != level or level < 0:
            raise InvalidInputError(f"level must be an integer >= 0 (0 = hard), got {level!r}")
        self.level = int(level)
        gain = float(gain)
        if not np.isfinite(gain) or gain < 0.0:
            raise InvalidInputError(f"{type(self).__name__} gain must be finite and >= 0, got {gain}")
        self.gain = gain

    @abstractmethod
    def compute(self, configuration: Configuration, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Task Jacobian ``J`` (dim x nv) and desired task velocity ``v`` (dim,)."""

    def compute_rows(self, configuration: Configuration, dt: float) -> tuple[np.ndarray | None, np.ndarray]:
        """Like :meth:`compute`, but ``J`` may be ``None`` meaning the identity (joint-space tasks).

        The solver calls this one so that joint-space tasks skip a dense ``I`` product.
        """
        return self.compute(configuration, dt)

    def residual(self, configuration: Configuration, qdot: np.ndarray, dt: float) -> np.ndarray:
        """Weighted residual ``diag(sqrt(w)) (J qdot - v)`` of a solution."""
        J, v = self.compute(configuration, dt)
        return np.sqrt(self.weight) * (J @ qdot - v)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(level={self.level}, weight={self.weight.tolist()}, gain={self.gain})"
