"""Joint speed limits."""

from __future__ import annotations

import numpy as np

from harvest_qp.configuration import Configuration
from harvest_qp.limits.limit import Limit, LimitRows
from harvest_qp.validation import as_nonnegative_vector


class JointVelocityLimit(Limit):
    """``|qdot| <= v_max`` [rad/s] (the model's limits, pi rad/s on a UR5e, by default)."""

    priority = 0
    has_box = True

    def __init__(self, configuration: Configuration, *, max_velocity: float | np.ndarray | None = None):
        v = configuration.velocity_limits if max_velocity is None else max_velocity
        self.max_velocity = as_nonnegative_vector(v, configuration.nv, "max_velocity")

    def compute(self, configuration: Configuration, dt: float, previous_qdot=None) -> LimitRows:
        return LimitRows(lower=-self.max_velocity, upper=self.max_velocity.copy())

    def fill_box(self, configuration: Configuration, dt: float, previous_qdot, lower, upper) -> None:
        np.negative(self.max_velocity, out=lower)
        upper[:] = self.max_velocity
