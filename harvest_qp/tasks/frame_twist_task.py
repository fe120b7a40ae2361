"""Track a reference twist of a frame: the paper's reference velocities as a QP task."""

from __future__ import annotations

import numpy as np

from harvest_qp.configuration import Configuration
from harvest_qp.exceptions import InvalidInputError
from harvest_qp.qp_kernels import rotate_twist_rows
from harvest_qp.tasks.task import Task
from harvest_qp.validation import as_vector


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
        frame: frame name in the model.
        weight: scalar or 6 per-axis weights.
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
        super().__init__(6, weight=weight, level=level, gain=gain)
        if weight_frame not in ("world", "local"):
            raise InvalidInputError(f"weight_frame must be 'world' or 'local', got {weight_frame!r}")
        self.frame = frame
        self.weight_frame = weight_frame
        self.reference = np.zeros(6)
        self._frame_id: int | None = None

    def set_reference(self, twist: np.ndarray) -> None:
        """Set the reference twist ``[v; w]`` [m/s, rad/s], world-aligned at the frame origin."""
        self.reference = as_vector(twist, 6, f"{self.frame} reference twist")

    def compute(self, configuration: Configuration, dt: float) -> tuple[np.ndarray, np.ndarray]:
        J, v = self.compute_rows(configuration, dt)
        return J.copy(), v.copy()

    def compute_rows(self, configuration: Configuration, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Like :meth:`compute`, into buffers reused at the next call (the solver's fast path)."""
        if self._frame_id is None:
            self._frame_id = configuration.frame_id(self.frame)
            self._J_local = np.empty((6, configuration.nv))
            self._v_local = np.empty(6)
        J = configuration.frame_jacobian_by_id(self._frame_id)
        v = self.reference if self.gain == 1.0 else self.gain * self.reference
        if self.weight_frame == "local":
            # Rotate rows into the frame's axes so that weights act on local axes.
            rotate_twist_rows(configuration.data.oMf[self._frame_id].rotation, J, v, self._J_local, self._v_local)
            return self._J_local, self._v_local
        return J, v
