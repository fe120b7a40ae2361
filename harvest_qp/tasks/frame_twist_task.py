"""Track a reference twist of a frame: the paper's reference velocities as a QP task."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pinocchio as pin

from harvest_qp.configuration import Configuration
from harvest_qp.qp_kernels import all_finite, rotate_twist_rows
from harvest_qp.tasks.task import Task
from harvest_qp.validation import as_choice, as_name, as_vector

WEIGHT_FRAMES = ("world", "local")
_LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
_frame_jacobian = pin.getFrameJacobian
_FLOAT64 = np.dtype(np.float64)
_SHAPE6 = (6,)


class FrameTwistTask(Task):
    """``J_frame qdot = V_ref``: the frame moves with the reference twist ``[v; w]`` [m/s, rad/s].

    This is how the paper's end-effector references (``eq:superimposition``,
    ``eq:superimp_g``, ``eq:final_vc``) enter the QP instead of the pseudo-inverse
    of ``eq:controlled_system``.

    Weights are per axis, ``[vx, vy, vz, wx, wy, wz]``, in the world frame
    (``weight_frame="world"``) or in the task frame's own axes (``"local"``). The
    camera task uses ``"local"`` with weight 0 on ``wz``, leaving the roll about the
    optical axis free: the paper's 5-DOF task with 1 DOF of redundancy.

    Args:
        frame: frame name in the model (checked at the first solve).
        weight: scalar or 6 per-axis weights [1/(m/s)^2, 1/(rad/s)^2].
        weight_frame: ``"world"`` or ``"local"``.
        level: priority level (see :class:`Task`).
        gain: scale applied to the reference (1 = track it as given).
    """

    def __init__(
        self,
        frame: str,
        *,
        weight: float | np.ndarray = 1.0,
        weight_frame: str = "world",
        level: int = 1,
        gain: float = 1.0,
    ) -> None:
        self._frame = as_name(frame, "FrameTwistTask frame")
        super().__init__(6, weight=weight, level=level, gain=gain)
        self.weight_frame = weight_frame
        self.reference = np.zeros(6)

    def _label(self) -> str:
        return f"FrameTwistTask({getattr(self, '_frame', '?')!r})"

    @property
    def frame(self) -> str:
        """Name of the task frame; reassigning it re-checks it against the model at the next solve."""
        return self._frame

    @frame.setter
    def frame(self, value: str) -> None:
        self._frame = as_name(value, f"{self._label()} frame")
        self._model = None  # the cached frame index belongs to the old name

    @property
    def weight_frame(self) -> str:
        """Axes the weights act on: ``"world"`` or ``"local"``."""
        return self._weight_frame

    @weight_frame.setter
    def weight_frame(self, value: str) -> None:
        self._weight_frame = as_choice(value, f"{self._label()} weight_frame", WEIGHT_FRAMES)
        self._local = self._weight_frame == "local"

    @property
    def reference(self) -> np.ndarray:
        """Reference twist ``[v; w]`` [m/s, rad/s], world-aligned at the frame origin."""
        return self._reference

    @reference.setter
    def reference(self, twist: np.ndarray | Sequence[float]) -> None:
        # The control loop sets three references every tick: a finite float64 6-vector is
        # copied as as_vector would copy it, without building the error message's name first.
        if type(twist) is np.ndarray and twist.dtype is _FLOAT64 and twist.shape == _SHAPE6 and all_finite(twist):
            self._reference = twist.copy()
        else:
            self._reference = as_vector(twist, 6, f"{self._label()} reference twist")

    def set_reference(self, twist: np.ndarray | Sequence[float]) -> None:
        """Set the reference twist ``[v; w]`` [m/s, rad/s], world-aligned at the frame origin.

        Goes through the ``reference`` setter (as it always has), so a subclass overriding either
        one keeps working (an audit found the reversed delegation recursing or bypassing it)."""
        self.reference = twist

    def check_configuration(self, configuration: Configuration) -> None:
        super().check_configuration(configuration)
        configuration.frame_id(self._frame)  # UnknownFrameError listing the valid names

    def _bind(self, configuration: Configuration) -> None:
        # The index and the local-row buffers are per model: a task moved to another
        # model (other nv) must never hand the kernel buffers of the old size.
        self._frame_id = configuration.frame_id(self._frame)
        self._J_local = np.empty((6, configuration.nv))
        self._v_local = np.empty(6)

    def compute(self, configuration: Configuration, dt: float) -> tuple[np.ndarray, np.ndarray]:
        J, v = self.compute_rows(configuration, dt)
        return J.copy(), v.copy()

    def compute_rows(self, configuration: Configuration, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Like :meth:`compute`, into buffers reused at the next call (the solver's path)."""
        if self._model is None or getattr(configuration, "model", None) is not self._model:
            self._ensure_bound(configuration)
        v = self._reference if self._gain == 1.0 else self._gain * self._reference
        # The frame index was checked against this model when the task was bound.
        J = _frame_jacobian(configuration.model, configuration.data, self._frame_id, _LWA)
        if not self._local:
            return J, v
        # Rotate rows into the frame's axes so that weights act on local axes.
        rotate_twist_rows(configuration.data.oMf[self._frame_id].rotation, J, v, self._J_local, self._v_local)
        return self._J_local, self._v_local
