"""Keep a UR wrist away from its singularity (beyond the paper)."""

from __future__ import annotations

import math

import numpy as np

from harvest_qp.configuration import Configuration
from harvest_qp.tasks.task import Task
from harvest_qp.validation import as_name, as_positive_scalar


class WristSingularityTask(Task):
    """Push a wrist joint away from ``sin(q) = 0``, where a UR arm's wrist-1 and wrist-3 axes align.

    With ``d = |q - k pi|`` the distance to the nearest multiple of pi [rad] and
    ``s = max(0, (margin - d) / margin)``, the one row is::

        s qdot_j = s gain (margin - d) sign(q - k pi)

    so inside ``margin`` the joint is asked to turn away from the singularity, with a weight
    ``weight s^2`` that grows from 0 at the margin to ``weight`` at the singularity; outside
    the margin the row is zero and the task asks nothing (it is no posture task).

    Why (lab measurements, beyond the paper): the paper's camera task is 5-D and nothing keeps
    the camera arm's wrist 2 off -pi. On held-out 18066 and 17098 it reached -3.14 rad (the camera
    Jacobian's smallest singular value 0.001-0.002); the camera stopped following V_c, the elbow
    folded and the camera ended 0.66-0.68 m from the ROI centre. With this task on
    ``cam_wrist_2_joint`` (level 1, weight 1, margin 0.35 rad) 17098 succeeded, and so did dev
    10120, 10148 and 19956 with the feed-forward on; but on dev 12001, which passes through the
    singularity unharmed without it, the camera stalled 20 deg off centre against the task. It is
    therefore not in the paper episode by default; add it with ``qp.extra_tasks: [{type:
    "harvest_qp.tasks:WristSingularityTask", params: {joint: cam_wrist_2_joint}, level: 1}]``.
    A hard limit on the joint made the QP infeasible against the collision rows.

    Args:
        joint: joint name in the model (``"cam_wrist_2_joint"``; checked at the first solve).
        margin: [rad] distance to the singular value within which the task acts.
        weight: [1/(rad/s)^2] the row's weight at the singularity.
        level: priority level.
        gain: [1/s] speed asked per radian inside the margin.
    """

    def __init__(self, joint: str, *, margin: float = 0.35, weight: float = 1.0, level: int = 1,
                 gain: float = 1.0) -> None:
        self._joint = as_name(joint, "WristSingularityTask joint")
        self.margin = as_positive_scalar(margin, "WristSingularityTask margin")
        super().__init__(1, weight=weight, level=level, gain=gain)
        self._index = -1
        self._J = np.zeros((1, 0))
        self._v = np.zeros(1)

    @property
    def joint(self) -> str:
        """The joint's name."""
        return self._joint

    def _label(self) -> str:
        return f"WristSingularityTask({getattr(self, '_joint', '?')!r})"

    def check_configuration(self, configuration: Configuration) -> None:
        super().check_configuration(configuration)
        configuration.joint_index(self._joint)  # UnknownFrameError listing the valid joints

    def _bind(self, configuration: Configuration) -> None:
        # (the UR joints are revolute: the index in q is the index in qdot)
        self._index = configuration.joint_index(self._joint)
        self._J = np.zeros((1, configuration.nv))

    def compute(self, configuration: Configuration, dt: float) -> tuple[np.ndarray, np.ndarray]:
        J, v = self.compute_rows(configuration, dt)
        return J.copy(), v.copy()

    def compute_rows(self, configuration: Configuration, dt: float) -> tuple[np.ndarray, np.ndarray]:
        if self._model is None or getattr(configuration, "model", None) is not self._model:
            self._ensure_bound(configuration)
        q = float(configuration.q[self._index])
        offset = q - round(q / math.pi) * math.pi
        distance = abs(offset)
        scale = max(0.0, (self.margin - distance) / self.margin)
        self._J[0, self._index] = scale
        self._v[0] = scale * self.gain * (self.margin - distance) * (1.0 if offset >= 0.0 else -1.0)
        return self._J, self._v
