"""Control-loop wrapper around the QP: one call per control tick that never raises.

:class:`TaskController` owns the configuration, tasks, limits and a persistent
:class:`~harvest_qp.solver.Solver`. Its :meth:`~TaskController.step` returns a
:class:`ControlStep` whose ``qdot`` is always finite and inside the joint position
and velocity limits: when the QP cannot be solved (backend failure, infeasible
constraints, non-finite input) it decelerates the previous command to zero within
the acceleration limit and reports the failure in ``status``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from harvest_qp.configuration import Configuration
from harvest_qp.exceptions import HarvestQPError
from harvest_qp.limits.joint_acceleration_limit import JointAccelerationLimit
from harvest_qp.limits.joint_position_limit import JointPositionLimit
from harvest_qp.limits.joint_velocity_limit import JointVelocityLimit
from harvest_qp.limits.limit import Limit
from harvest_qp.solver import Solver
from harvest_qp.tasks.task import Task
from harvest_qp.validation import as_nonnegative_vector, as_positive_scalar

OK = "ok"
FALLBACK = "fallback"


@dataclass
class ControlStep:
    """Output of one control tick."""

    qdot: np.ndarray
    """Joint velocity command [rad/s]."""
    status: str
    """``"ok"``, ``"ok: relaxed JointAccelerationLimit"`` when braking harder than the
    acceleration limit was needed to stay safe, or ``"fallback: <reason>"`` when the
    arms are being brought to rest."""
    conflicts: list = field(default_factory=list)
    """Joints whose limit boxes conflicted this tick (the higher-priority limit won)."""

    @property
    def ok(self) -> bool:
        """True when the QP was solved (possibly with the acceleration limit relaxed)."""
        return self.status.startswith(OK)


class TaskController:
    """QP task controller for a velocity-controlled robot.

    Args:
        configuration: the robot; updated in place at every step.
        tasks: the QP tasks.
        limits: hard limits; when they contain no joint position, velocity or
            acceleration limit, the model's limits are added.
        dt: control period [s] (0.002 on a UR5e).
        solver: QP backend name (see :class:`~harvest_qp.solver.Solver`).
        max_acceleration: deceleration used by the safe stop [rad/s^2].
    """

    def __init__(
        self,
        configuration: Configuration,
        tasks: Sequence[Task],
        limits: Sequence[Limit] = (),
        *,
        dt: float = 0.002,
        solver: str = "daqp",
        max_acceleration: float | np.ndarray = 10.0,
    ) -> None:
        self.configuration = configuration
        self.tasks = list(tasks)
        self.dt = as_positive_scalar(dt, "dt")
        self.max_acceleration = as_nonnegative_vector(max_acceleration, configuration.nv, "max_acceleration")
        limits = list(limits)
        kinds = {type(limit) for limit in limits}
        if JointPositionLimit not in kinds:
            limits.append(JointPositionLimit(configuration, max_acceleration=self.max_acceleration))
        if JointVelocityLimit not in kinds:
            limits.append(JointVelocityLimit(configuration))
        if JointAccelerationLimit not in kinds:
            limits.append(JointAccelerationLimit(configuration, max_acceleration=self.max_acceleration))
        self.limits = limits
        self.solver = Solver(solver)
        self.previous_qdot = np.zeros(configuration.nv)
        self.last_error: HarvestQPError | Exception | None = None
        self.solver_solution = None

    def reset(self, q: np.ndarray | None = None) -> None:
        """Forget the previous command (the arms are at rest) and optionally set ``q`` [rad]."""
        self.previous_qdot = np.zeros(self.configuration.nv)
        if q is not None:
            self.configuration.update(q)

    def step(self, q: np.ndarray) -> ControlStep:
        """Joint velocities [rad/s] for the measured joint positions ``q`` [rad]. Never raises."""
        try:
            self.configuration.update(q)
            # previous_qdot is this controller's own finite output: skip re-validating it.
            solution = self.solver._solve(self.configuration, self.tasks, self.limits, self.dt, self.previous_qdot)
            self.solver_solution = solution
            status = OK if not solution.relaxed else f"{OK}: relaxed {', '.join(solution.relaxed)}"
            result = ControlStep(qdot=solution.qdot, status=status, conflicts=solution.conflicts)
        except Exception as err:  # the loop must keep commanding the robot: stop it safely
            self.last_error = err
            result = ControlStep(qdot=self.safe_stop(), status=f"{FALLBACK}: {type(err).__name__}: {err}")
        self.previous_qdot = result.qdot
        return result

    def safe_stop(self) -> np.ndarray:
        """Previous command decelerated towards zero by at most ``max_acceleration * dt``.

        Also clipped to the joint velocity limits and, where ``q`` is known, to the
        position limits, so the stop itself never drives a joint out of range.
        """
        prev = np.nan_to_num(self.previous_qdot, nan=0.0, posinf=0.0, neginf=0.0)
        step = self.max_acceleration * self.dt
        qdot = prev - np.clip(prev, -step, step)
        vmax = self.configuration.velocity_limits
        qdot = np.clip(qdot, -vmax, vmax)
        q = self.configuration.q
        if np.all(np.isfinite(q)):
            lo = (self.configuration.lower_limits - q) / self.dt
            hi = (self.configuration.upper_limits - q) / self.dt
            qdot = np.clip(qdot, np.minimum(lo, 0.0), np.maximum(hi, 0.0))
        return qdot
