"""Joint position limits as velocity bounds."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from harvest_qp.configuration import Configuration, as_configuration
from harvest_qp.limits.limit import BoxLimit
from harvest_qp.qp_kernels import position_limit_bounds
from harvest_qp.validation import as_bounds, as_nonnegative_vector, as_scalar


class JointPositionLimit(BoxLimit):
    """Keep ``q + qdot dt`` inside ``[q_min, q_max]``.

    ``gain * (q_min - q) / dt <= qdot <= gain * (q_max - q) / dt`` with ``gain`` in (0, 1]:
    below 1 the joint slows down before the limit instead of stopping on it in one step.
    With ``max_acceleration`` [rad/s^2] the bound is also capped at the braking speed
    ``sqrt(2 a (q_max - q))``, so a joint can always stop within the acceleration limit.

    Args:
        configuration: the robot (its URDF position limits are used by default).
        gain: fraction of the remaining range allowed per step, in (0, 1].
        lower, upper: override limits [rad] (scalar or per joint; ``lower <= upper``;
            ``-inf``/``+inf`` for an unbounded joint).
        max_acceleration: braking deceleration [rad/s^2] (>= 0, scalar or per joint), or None.
    """

    priority = 1

    def __init__(
        self,
        configuration: Configuration,
        *,
        gain: float = 0.95,
        lower: float | np.ndarray | Sequence[float] | None = None,
        upper: float | np.ndarray | Sequence[float] | None = None,
        max_acceleration: float | np.ndarray | Sequence[float] | None = None,
    ) -> None:
        as_configuration(configuration, "JointPositionLimit configuration")
        n = configuration.nv
        self.gain = as_scalar(gain, "JointPositionLimit gain", minimum=0.0, maximum=1.0, exclusive_minimum=True)
        self.lower, self.upper = as_bounds(
            configuration.lower_limits if lower is None else lower,
            configuration.upper_limits if upper is None else upper,
            n,
            "JointPositionLimit",
        )
        self.max_acceleration = (
            None
            if max_acceleration is None
            else as_nonnegative_vector(max_acceleration, n, "JointPositionLimit max_acceleration")
        )
        # The kernel takes an empty array for "no braking bound".
        self._braking = np.zeros(0) if self.max_acceleration is None else self.max_acceleration
        self._model = configuration.model

    def check_configuration(self, configuration: Configuration) -> None:
        self._check_joint_vectors(configuration, lower=self.lower, upper=self.upper)
        if self.max_acceleration is not None:
            self._check_joint_vectors(configuration, max_acceleration=self.max_acceleration)

    def fill_box(
        self,
        configuration: Configuration,
        dt: float,
        previous_qdot: np.ndarray | None,
        lower: np.ndarray,
        upper: np.ndarray,
    ) -> None:
        # The kernel loops over q and reads lower/upper/braking by that index: sizes checked once per model.
        self._ensure_bound(configuration)
        position_limit_bounds(configuration.q, self.lower, self.upper, self.gain, dt, self._braking, lower, upper)
