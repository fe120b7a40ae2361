"""Joint acceleration limits relative to the previous command (UR ``speedj``'s ``a``)."""

from __future__ import annotations

import numpy as np

from harvest_qp.configuration import Configuration
from harvest_qp.limits.limit import Limit, LimitRows
from harvest_qp.validation import as_nonnegative_vector


class JointAccelerationLimit(Limit):
    """``|qdot - qdot_prev| <= a_max dt`` with ``a_max`` [rad/s^2].

    Without a previous command (first step) the previous command is taken as zero.
    """

    priority = 2

    def __init__(self, configuration: Configuration, *, max_acceleration: float | np.ndarray = 10.0):
        self.max_acceleration = as_nonnegative_vector(max_acceleration, configuration.nv, "max_acceleration")

    def compute(self, configuration: Configuration, dt: float, previous_qdot=None) -> LimitRows:
        # previous_qdot is validated once by the solver for all limits.
        prev = np.zeros(configuration.nv) if previous_qdot is None else previous_qdot
        step = self.max_acceleration * dt
        return LimitRows(lower=prev - step, upper=prev + step)
