"""Joint position limits as velocity bounds."""

from __future__ import annotations

import numpy as np

from harvest_qp.configuration import Configuration
from harvest_qp.limits.limit import Limit, LimitRows
from harvest_qp.qp_kernels import position_limit_bounds
from harvest_qp.validation import as_positive_scalar, as_vector


class JointPositionLimit(Limit):
    """Keep ``q + qdot dt`` inside ``[q_min, q_max]``.

    ``gain * (q_min - q) / dt <= qdot <= gain * (q_max - q) / dt`` with ``gain`` in (0, 1]:
    below 1 the joint slows down before the limit instead of stopping on it in one step.
    With ``max_acceleration`` [rad/s^2] the bound is also capped at the braking speed
    ``sqrt(2 a (q_max - q))``, so a joint can always stop within the acceleration limit.

    Args:
        configuration: the robot (its URDF position limits are used by default).
        gain: fraction of the remaining range allowed per step, in (0, 1].
        lower, upper: override limits [rad].
        max_acceleration: braking deceleration [rad/s^2] (scalar or per joint), or None.
    """

    priority = 1
    has_box = True

    def __init__(
        self,
        configuration: Configuration,
        *,
        gain: float = 0.95,
        lower: np.ndarray | None = None,
        upper: np.ndarray | None = None,
        max_acceleration: float | np.ndarray | None = None,
    ) -> None:
        n = configuration.nv
        self.gain = as_positive_scalar(gain, "gain")
        if self.gain > 1.0:
            raise ValueError(f"gain must be in (0, 1], got {gain}")
        self.lower = as_vector(configuration.lower_limits if lower is None else lower, n, "lower")
        self.upper = as_vector(configuration.upper_limits if upper is None else upper, n, "upper")
        self.max_acceleration = (
            None if max_acceleration is None else as_vector(max_acceleration, n, "max_acceleration")
        )
        # The kernel takes an empty array for "no braking bound".
        self._braking = np.zeros(0) if self.max_acceleration is None else self.max_acceleration

    def compute(self, configuration: Configuration, dt: float, previous_qdot=None) -> LimitRows:
        lower, upper = np.empty(configuration.nv), np.empty(configuration.nv)
        self.fill_box(configuration, dt, previous_qdot, lower, upper)
        return LimitRows(lower=lower, upper=upper)

    def fill_box(self, configuration: Configuration, dt: float, previous_qdot, lower, upper) -> None:
        position_limit_bounds(configuration.q, self.lower, self.upper, self.gain, dt, self._braking, lower, upper)
