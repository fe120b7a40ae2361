"""Joint acceleration limits relative to the previous command (UR ``speedj``'s ``a``)."""

from __future__ import annotations

import numpy as np

from harvest_qp.configuration import Configuration
from harvest_qp.limits.limit import BoxLimit
from harvest_qp.qp_kernels import acceleration_bounds
from harvest_qp.validation import as_nonnegative_vector


class JointAccelerationLimit(BoxLimit):
    """``|qdot - qdot_prev| <= a_max dt`` with ``a_max`` [rad/s^2].

    Without a previous command (first step) the previous command is taken as zero.
    """

    priority = 2

    def __init__(self, configuration: Configuration, *, max_acceleration: float | np.ndarray = 10.0):
        self.max_acceleration = as_nonnegative_vector(max_acceleration, configuration.nv, "max_acceleration")
        self._zeros = np.zeros(configuration.nv)
        self._model = configuration.model

    def check_configuration(self, configuration: Configuration) -> None:
        """Raise :class:`~harvest_qp.exceptions.DimensionError` unless the limit fits ``configuration``'s model."""
        self._check_joint_vectors(configuration, max_acceleration=self.max_acceleration)

    def fill_box(self, configuration: Configuration, dt: float, previous_qdot, lower, upper) -> None:
        # The compiled bounds read max_acceleration by joint: a limit built for a smaller
        # model would be read past its end. previous_qdot is validated once by the solver.
        self._ensure_bound(configuration)
        prev = self._zeros if previous_qdot is None else previous_qdot
        acceleration_bounds(prev, self.max_acceleration, dt, lower, upper)
