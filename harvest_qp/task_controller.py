"""Control-loop wrapper around the QP: one call per control tick that never raises.

:class:`TaskController` owns the configuration, tasks, limits and a persistent
:class:`~harvest_qp.solver.Solver`. Its :meth:`~TaskController.step` returns a
:class:`ControlStep` whose ``qdot`` is always finite and inside the joint position
and velocity limits. The solver already retries failed backends and relaxes the
acceleration limit by the least amount needed (see :mod:`harvest_qp.solver`); only
when the QP still cannot be solved (a hard task beyond the limits, non-finite input)
does the controller stop the arms: a small QP that brakes each joint towards zero
within the acceleration limit while keeping every limit row, collision dampers
included, so no pair is driven into another while braking. Where even that cannot
be computed (no valid measurement) it decelerates the previous command joint by joint.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from harvest_qp.configuration import Configuration
from harvest_qp.exceptions import HarvestQPError
from harvest_qp.limits.collision_avoidance import CollisionAvoidance, pairs_from_snapshot
from harvest_qp.limits.joint_acceleration_limit import JointAccelerationLimit
from harvest_qp.limits.joint_position_limit import JointPositionLimit
from harvest_qp.limits.joint_velocity_limit import JointVelocityLimit
from harvest_qp.limits.limit import Limit, check_limits
from harvest_qp.solver import Solver
from harvest_qp.tasks.task import Task, check_tasks
from harvest_qp.validation import as_nonnegative_vector, as_positive_scalar

OK = "ok"
FALLBACK = "fallback"


class ControlStep:
    """Output of one control tick.

    ``acceleration`` and ``active_pairs`` are computed on first access from what the step kept
    (the previous command; a snapshot of the collision rows), so a loop that never reads them
    does not pay for them.

    Attributes:
        qdot: joint velocity command [rad/s].
        status: ``"ok"``; ``"ok: relaxed JointAccelerationLimit to <a> rad/s^2"`` when a joint had
            to change speed faster than the acceleration limit to keep a position limit or a
            collision row (by the least amount needed, ``a`` the largest commanded acceleration);
            ``"ok: separation asked lowered by ..."`` when a pair inside the safety distance separates
            more slowly than its row asked, to stay within the acceleration limit; ``"ok: retried ..."``
            when a second backend solved the QP; or ``"fallback: <reason>"`` when the arms are being
            brought to rest.
        conflicts: joints whose limit boxes conflicted this tick (the higher-priority limit won).
    """

    def __init__(self, qdot: np.ndarray, status: str, conflicts: list | None = None,
                 acceleration: np.ndarray | None = None, active_pairs: list | None = None, *,
                 previous_qdot: np.ndarray | None = None, dt: float | None = None) -> None:
        self.qdot = qdot
        self.status = status
        self.conflicts = [] if conflicts is None else conflicts
        self._acceleration = acceleration
        # For the lazy acceleration: a copy, so that editing the previous step's command in place later
        # (a speed override, controller.previous_qdot[:] = ...) does not change this step's figure.
        self._previous = None if previous_qdot is None else previous_qdot.copy()
        self._dt = dt
        self._pair_snapshots: list | None = None  # set by TaskController.step (see active_pairs)
        self._active_pairs: list[tuple[str, str, float]] | None = active_pairs

    @property
    def acceleration(self) -> np.ndarray | None:
        """Commanded acceleration ``(qdot - previous qdot) / dt`` [rad/s^2] of this tick (None: unknown), from
        this step's ``qdot`` and a copy of the previous command taken at the step."""
        if self._acceleration is None and self._previous is not None:
            self._acceleration = (self.qdot - self._previous) / self._dt
        return self._acceleration

    @property
    def active_pairs(self) -> list[tuple[str, str, float]]:
        """Collision pairs that were rows of the QP this tick: both bodies' names and the surface
        distance [m] (from every :class:`CollisionAvoidance` among the limits), from the snapshot
        taken at the step."""
        if self._active_pairs is None:
            snapshots = self._pair_snapshots or []
            self._active_pairs = [pair for snapshot in snapshots for pair in pairs_from_snapshot(snapshot)]
        return self._active_pairs

    @active_pairs.setter
    def active_pairs(self, value: list[tuple[str, str, float]]) -> None:
        self._active_pairs = value

    @property
    def ok(self) -> bool:
        """True when the QP was solved (possibly with the acceleration limit relaxed)."""
        return self.status.startswith(OK)

    @property
    def max_acceleration(self) -> float:
        """Largest commanded joint acceleration of this tick [rad/s^2] (0 when unknown)."""
        acceleration = self.acceleration
        return 0.0 if acceleration is None else float(np.max(np.abs(acceleration), initial=0.0))

    def __repr__(self) -> str:
        return f"ControlStep(qdot={self.qdot!r}, status={self.status!r}, conflicts={self.conflicts!r})"


class _BrakeTask(Task):
    """Joint-space target ``qdot = target`` [rad/s] used by the safe stop."""

    def __init__(self, nv: int) -> None:
        super().__init__(nv, weight=1.0, level=1)
        self.target = np.zeros(nv)

    def compute(self, configuration: Configuration, dt: float) -> tuple[np.ndarray, np.ndarray]:
        return np.eye(self.dim), self.target

    def compute_rows(self, configuration: Configuration, dt: float) -> tuple[None, np.ndarray]:
        return None, self.target


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
        # A wrong task or limit fails here, naming it, instead of safe-stopping every tick.
        self.tasks = check_tasks(tasks, configuration)
        self.dt = as_positive_scalar(dt, "dt")
        self.max_acceleration = as_nonnegative_vector(max_acceleration, configuration.nv, "max_acceleration")
        limits = check_limits(limits, configuration)
        kinds = {type(limit) for limit in limits}
        if JointPositionLimit not in kinds:
            limits.append(JointPositionLimit(configuration, max_acceleration=self.max_acceleration))
        if JointVelocityLimit not in kinds:
            limits.append(JointVelocityLimit(configuration))
        if JointAccelerationLimit not in kinds:
            limits.append(JointAccelerationLimit(configuration, max_acceleration=self.max_acceleration))
        self.limits = limits
        self.solver = Solver(solver)
        self._stop_solver = Solver(solver)
        self._brake = _BrakeTask(configuration.nv)
        self._collisions = [limit for limit in limits if isinstance(limit, CollisionAvoidance)]
        self.previous_qdot = np.zeros(configuration.nv)
        self.last_error: HarvestQPError | Exception | None = None
        self.solver_solution = None

    def reset(self, q: np.ndarray | None = None) -> None:
        """Forget the previous command (the arms are at rest) and optionally set ``q`` [rad]."""
        self.previous_qdot = np.zeros(self.configuration.nv)
        if q is not None:
            self.configuration.update(q)

    def step(self, q: np.ndarray, *, kinematics_updated: bool = False) -> ControlStep:
        """Joint velocities [rad/s] for the measured joint positions ``q`` [rad]. Never raises.

        With ``kinematics_updated`` the caller has just updated ``configuration`` to this very
        ``q`` (a control loop that runs its reference laws first): the kinematics are then
        recomputed only when ``q``'s bytes differ from that update's
        (:meth:`Configuration.update_if_changed`). By default they are always recomputed (a
        caller may have moved ``configuration.data`` with pinocchio in between).
        """
        measured = False
        if self.previous_qdot is None:
            # A caller forgetting the last command: at rest, as reset() does (the safe stop
            # and the acceleration box both need a vector).
            self.previous_qdot = np.zeros(self.configuration.nv)
        try:
            if kinematics_updated:
                self.configuration.update_if_changed(q)
            else:
                self.configuration.update(q)
            measured = True
            previous = self.previous_qdot
            solution = self.solver.solve(self.configuration, self.tasks, self.limits, self.dt, previous_qdot=previous)
            self.solver_solution = solution
            result = ControlStep(solution.qdot, OK, solution.conflicts, previous_qdot=previous, dt=self.dt)
            if solution.relaxed:
                result.status = (f"{OK}: relaxed {', '.join(solution.relaxed)} to {result.max_acceleration:.4g} "
                                 "rad/s^2")
            elif solution.row_relaxation is not None and np.any(solution.row_relaxation > 0):
                result.status = f"{OK}: separation asked lowered by up to {np.max(solution.row_relaxation):.3g} m/s"
            elif solution.retries:
                result.status = f"{OK}: retried after {'; '.join(solution.retries)}"
        except Exception as err:  # the loop must keep commanding the robot: stop it safely
            self.last_error = err
            qdot, how = self._safe_stop_command(measured)
            result = ControlStep(
                qdot=qdot,
                status=f"{FALLBACK}: {type(err).__name__}: {err}{how}",
                acceleration=(qdot - np.nan_to_num(self.previous_qdot)) / self.dt,
            )
        if measured and self._collisions:
            result._pair_snapshots = [limit.active_pair_snapshot() for limit in self._collisions]
        self.previous_qdot = result.qdot
        return result

    def _safe_stop_command(self, measured: bool) -> tuple[np.ndarray, str]:
        """The stop QP when the state is known, else the joint-wise brake; and a note for the status."""
        if measured and np.all(np.isfinite(self.previous_qdot)):
            self._brake.target[:] = self.safe_stop()
            try:
                solution = self._stop_solver.solve(
                    self.configuration, [self._brake], self.limits, self.dt, previous_qdot=self.previous_qdot
                )
                return solution.qdot, ""
            except Exception as err:  # noqa: BLE001 - fall through to the plain brake
                return self.safe_stop(), f" (stop QP failed: {type(err).__name__})"
        return self.safe_stop(), ""

    def safe_stop(self) -> np.ndarray:
        """Previous command decelerated towards zero by at most ``max_acceleration * dt``.

        Also clipped to the joint velocity limits and, where ``q`` is known, to the
        position limits, so the stop itself never drives a joint out of range. This is
        the joint-wise brake; :meth:`step` uses it as the target of a stop QP that also
        keeps the collision rows.
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
