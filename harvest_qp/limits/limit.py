"""Base class of the QP limits (hard constraints on the joint velocities)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from harvest_qp.configuration import Configuration


@dataclass
class LimitRows:
    """What a limit contributes to the QP on ``qdot`` [rad/s].

    Either a box ``lower <= qdot <= upper`` or inequality rows ``G qdot <= h`` (or both).
    """

    lower: np.ndarray | None = None
    upper: np.ndarray | None = None
    G: np.ndarray | None = None
    h: np.ndarray | None = None


class Limit(ABC):
    """A hard constraint on the joint velocities.

    Box limits are intersected in ``priority`` order (lower number first): where two
    boxes do not overlap, the earlier one wins and the later one is moved onto it,
    so the speed limit always holds and joint position limits beat acceleration limits.
    """

    #: Order in which box limits are intersected (velocity 0, position 1, acceleration 2).
    priority: int = 10
    #: True for limits whose :meth:`compute` returns a box (``lower``/``upper``) and no rows.
    #: The solver then calls :meth:`fill_box`, which writes into its buffers.
    has_box: bool = False

    def fill_box(
        self,
        configuration: Configuration,
        dt: float,
        previous_qdot: np.ndarray | None,
        lower: np.ndarray,
        upper: np.ndarray,
    ) -> None:
        """Write this limit's box [rad/s] into ``lower`` and ``upper`` (box limits only).

        The default goes through :meth:`compute`; the built-in limits override it to
        skip the allocations (it runs every control tick).
        """
        rows = self.compute(configuration, dt, previous_qdot)
        lower[:] = rows.lower
        upper[:] = rows.upper

    @abstractmethod
    def compute(
        self, configuration: Configuration, dt: float, previous_qdot: np.ndarray | None = None
    ) -> LimitRows:
        """Rows of this limit at the configuration's state, for a step of ``dt`` [s]."""
