"""Joint speed limits."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from harvest_qp.configuration import Configuration, as_configuration
from harvest_qp.limits.limit import BoxLimit
from harvest_qp.validation import as_nonnegative_vector


class JointVelocityLimit(BoxLimit):
    """``|qdot| <= v_max`` [rad/s] (the model's limits, pi rad/s on a UR5e, by default).

    Args:
        configuration: the robot.
        max_velocity: speed limit [rad/s] (>= 0, scalar or per joint), or None for the model's.
    """

    priority = 0

    def __init__(
        self, configuration: Configuration, *, max_velocity: float | np.ndarray | Sequence[float] | None = None
    ) -> None:
        as_configuration(configuration, "JointVelocityLimit configuration")
        v = configuration.velocity_limits if max_velocity is None else max_velocity
        self.max_velocity = as_nonnegative_vector(v, configuration.nv, "JointVelocityLimit max_velocity")
        self._model = configuration.model

    def check_configuration(self, configuration: Configuration) -> None:
        self._check_joint_vectors(configuration, max_velocity=self.max_velocity)

    def fill_box(
        self,
        configuration: Configuration,
        dt: float,
        previous_qdot: np.ndarray | None,
        lower: np.ndarray,
        upper: np.ndarray,
    ) -> None:
        self._ensure_bound(configuration)
        np.negative(self.max_velocity, out=lower)
        upper[:] = self.max_velocity
