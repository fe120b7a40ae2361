"""Episode runner: a fixed-rate control loop around any :class:`~harvest_qp.runtime.interface.RobotInterface`.

Every control period (2 ms on the paper's UR5e) the runner reads the robot, hands an
:class:`Observation` to the controller, sends the returned joint velocities and steps the
robot. Camera frames arrive at the camera's own rate (30 Hz); the observation carries the
latest one. Everything is logged to arrays, optionally written to a compressed ``.npz``
that is byte-identical for identical runs (fixed zip timestamps, no wall-clock data unless
``log_timing``).

The runner never crashes on a controller error: an exception in ``reset``/``step`` or an
invalid command (wrong shape, NaN) stops the arms within their acceleration limits,
records the status and the error message, and ends the episode.

Controller protocol::

    class MyController:
        def reset(self, robot: RobotInterface) -> None: ...   # read the initial state only
        def step(self, obs: Observation) -> Command | np.ndarray: ...

A controller needs no robot handle after ``reset``: the observation carries the robot
clock (``obs.time``) and ``obs.tare_force()``, which zeroes the wrist force sensor (as a
real F/T sensor's tare) from the next tick on. A :class:`Command` may also carry named
per-tick values (``values``, scalars or fixed-shape arrays, logged as ``value/<name>``),
the collision pairs its QP step had active (``collision_pairs``: ``(name_a, name_b,
distance [m])``), and ``done=True`` to end the episode after this tick.

Log keys (N control ticks, F camera frames):

* ``t`` (N,) [s], ``q`` / ``qdot`` (N, 12) [rad, rad/s], ``qdot_cmd`` (N, 12) [rad/s],
  ``force`` (N, 3) [N, world];
* ``status`` (N,) str: the controller's status per tick (``"error"`` on a failing tick);
* ``stem_points`` (N,) int32: STEM points in the latest cloud (-1 before the first frame),
  ``cloud_time`` (N,) [s]: capture time of the latest cloud (NaN before the first);
* ``task_error/<name>`` (N,): the controller's task errors (NaN on ticks without them);
* ``value/<name>`` (N, ...): the controller's named per-tick values (NaN where absent);
* ``collision/pair_names`` (P,) str ``"a|b"``: every collision pair that was active at
  least once; ``collision/active_pair`` (N, K) int32 index into it (-1 = none) and
  ``collision/active_distance`` (N, K) float32 [m] per tick, K the most pairs active at once;
* ``truth/<name>``: the robot's ``ground_truth()`` per tick when it has one (simulation);
* ``frame_time``, ``frame_n_points``, ``frame_stem_points`` (F,), ``frame_camera_pose`` (F, 4, 4);
  with ``log_clouds``: ``cloud_points`` (P, 3) float32, ``cloud_labels`` (P,) int8,
  ``cloud_offsets`` (C + 1,) int64 (logged cloud j is rows offsets[j]:offsets[j+1]),
  ``cloud_frame`` (C,) int64 (the camera frame each logged cloud is);
* ``episode_status`` (``"completed"``, ``"controller_error"``, ``"invalid_command"`` or
  ``"robot_error"``), ``error`` (message or ""), ``control_period``, ``duration``, ``n_ticks``,
  ``seed`` (when the robot has one), ``meta/<key>`` from ``metadata``;
* with ``log_timing``: ``controller_time`` (N,) [s] of wall-clock per controller step.
"""

from __future__ import annotations

import math
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import HarvestQPError, InvalidInputError
from harvest_qp.runtime.interface import N_JOINTS, STEM, PointCloud, RobotInterface
from harvest_qp.runtime.log import EpisodeLog, PairColumns, ValueRow, write_npz

_FLOAT64 = np.dtype(np.float64)

__all__ = [
    "Observation",
    "Command",
    "Controller",
    "EpisodeResult",
    "run_episode",
    "as_command",
    "write_npz",
]


@dataclass(frozen=True, eq=False)
class Observation:
    """What the controller sees at one control tick.

    Attributes:
        time: robot clock [s].
        q: joint positions (12,) [rad].
        qdot: joint velocities (12,) [rad/s].
        force: wrist force (3,) [N, world] (see :meth:`RobotInterface.wrist_force`).
        cloud: the latest camera frame received so far (None before the first).
        new_cloud: True when ``cloud`` arrived at this tick.
        tare_force: zeroes the wrist force sensor at its current reading (the robot's
            :meth:`RobotInterface.tare_force`); readings from the next tick on are tared.
    """

    time: float
    q: NDArray[np.float64]
    qdot: NDArray[np.float64]
    force: NDArray[np.float64]
    cloud: PointCloud | None
    new_cloud: bool
    tare_force: Callable[[], None] = field(default=lambda: None, repr=False)




@dataclass
class Command:
    """A controller's output for one tick.

    Attributes:
        qdot: joint velocities (12,) [rad/s].
        status: solver/controller status, logged per tick (e.g. ``"ok"``, ``"infeasible"``).
        task_errors: task name -> scalar error, logged per tick.
        values: name -> scalar or fixed-shape array, logged per tick as ``value/<name>``
            (the shape of a name's first value fixes it for the episode).
        collision_pairs: ``(name_a, name_b, distance [m])`` of the collision rows active
            in this tick's QP.
        done: end the episode after this tick (e.g. a controller that has stopped).

    The library's own :class:`~harvest_qp.harvest.HarvestController` hands ``values`` and
    ``collision_pairs`` as read-only views (a row and columns the runner logs in one copy); a
    wrapper that adds its own builds a new command, e.g.
    ``dataclasses.replace(command, values={**command.values, "x": 1.0})``.
    """

    qdot: ArrayLike
    status: str = "ok"
    task_errors: Mapping[str, float] = field(default_factory=dict)
    values: Mapping[str, ArrayLike] = field(default_factory=dict)
    collision_pairs: Sequence[tuple[str, str, float]] = ()
    done: bool = False


@runtime_checkable
class Controller(Protocol):
    """A controller the runner can drive."""

    def reset(self, robot: RobotInterface) -> None:
        """Prepare for an episode (read the initial state, tare the force sensor, ...)."""

    def step(self, obs: Observation) -> Command | ArrayLike:
        """Joint velocity command for this tick (a :class:`Command` or a (12,) array)."""


@dataclass(eq=False)
class EpisodeResult:
    """Outcome of :func:`run_episode`.

    Attributes:
        status: ``"completed"``, ``"controller_error"``, ``"invalid_command"`` or ``"robot_error"``.
        error: the error message with its traceback (None when completed).
        n_ticks: control ticks run.
        sim_time: robot time at the end [s].
        wall_time: wall-clock duration [s].
        log: the logged arrays (see the module docstring).
        log_path: where the log was written, if anywhere.
    """

    status: str
    error: str | None
    n_ticks: int
    sim_time: float
    wall_time: float
    log: dict[str, NDArray[Any]]
    log_path: Path | None

    @property
    def ok(self) -> bool:
        """True when the episode ran to the end without error."""
        return self.status == "completed"

    @property
    def realtime_factor(self) -> float:
        """Simulated time per wall-clock time."""
        return self.sim_time / self.wall_time if self.wall_time > 0 else math.inf


def _as_command(out: Any) -> Command:
    """Any controller output normalised to a validated :class:`Command` (the general case of :func:`as_command`)."""
    cmd = out if isinstance(out, Command) else Command(qdot=out)
    try:
        qd = np.asarray(cmd.qdot, dtype=float)
    except (TypeError, ValueError) as error:
        raise InvalidInputError(f"command qdot must be numeric (12,) [rad/s]: {error}") from None
    if qd.shape != (N_JOINTS,):
        raise InvalidInputError(f"command qdot must have shape ({N_JOINTS},) [rad/s], got shape {qd.shape}")
    if not np.all(np.isfinite(qd)):
        raise InvalidInputError(f"command qdot must be finite [rad/s], got {qd.tolist()}")
    if not isinstance(cmd.status, str):
        raise InvalidInputError(f"command status must be a str, got {type(cmd.status).__name__}")
    errors = {}
    for name, value in dict(cmd.task_errors).items():
        if not isinstance(name, str):
            raise InvalidInputError(f"task error names must be str, got {name!r}")
        try:
            errors[name] = float(value)
        except (TypeError, ValueError):
            raise InvalidInputError(f"task error {name!r} must be a number, got {value!r}") from None
    values = {}
    for name, value in dict(cmd.values).items():
        if not isinstance(name, str):
            raise InvalidInputError(f"value names must be str, got {name!r}")
        try:
            values[name] = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            raise InvalidInputError(f"value {name!r} must be numeric, got {value!r}") from None
    pairs = []
    for pair in cmd.collision_pairs:
        try:
            a, b, distance = pair
            pairs.append((str(a), str(b), float(distance)))
        except (TypeError, ValueError):
            raise InvalidInputError(
                f"collision_pairs entries must be (name_a, name_b, distance), got {pair!r}"
            ) from None
    return Command(qdot=qd, status=cmd.status, task_errors=errors, values=values, collision_pairs=pairs,
                   done=bool(cmd.done))


def as_command(out: Any) -> Command:
    """A controller's output as a checked :class:`Command` (what the runner logs and sends).

    The common case is accepted as it is, without rebuilding it:

    A :class:`Command` whose qdot is a finite float64 (12,) array, whose task errors and
    values are floats or float64 arrays and whose collision pairs are ``(str, str, float)``
    tuples is returned with the same contents as :func:`_as_command` gives (qdot, values
    and pairs are passed through, as ``np.asarray`` would pass them); anything else goes
    through :func:`_as_command`, which raises the same errors as before.

    The library's own controller hands its values as a :class:`ValueRow` and its pairs as
    :class:`PairColumns`: the row's dtype and length are checked here and the command is
    passed through as it is (nothing to normalise); the log checks a pair's names when it
    first meets them. Any controller may hand plain dicts and tuples: same log.
    """
    if type(out) is not Command:
        return _as_command(out)
    qd = out.qdot
    if (
        type(qd) is not np.ndarray
        or qd.dtype is not _FLOAT64
        or qd.shape != (N_JOINTS,)
        # On the 12 Python floats (a fifth of np.isfinite(qd).all()'s time): a finite sum has
        # only finite terms (a NaN or an infinity stays in a float sum). A sum that is not finite
        # (a bad entry, or finite entries overflowing) takes _as_command's full check.
        or not math.isfinite(sum(qd.tolist()))
        or type(out.status) is not str
    ):
        return _as_command(out)
    errors = out.task_errors
    if errors:
        if type(errors) is not dict:
            return _as_command(out)
        for name, value in errors.items():
            if type(name) is not str or type(value) is not float:
                return _as_command(out)
    values = out.values
    if type(values) is ValueRow:
        # The library's controller's row (checked when built): passed through, logged in one copy.
        row = values.row
        if type(row) is not np.ndarray or row.dtype is not _FLOAT64 or row.shape != (values.layout.width,):
            return _as_command(out)
    else:
        if values:
            if type(values) is not dict:
                return _as_command(out)
            for name, value in values.items():
                kind = type(value)
                scalar = kind is float or kind is np.float64
                if type(name) is not str or not (scalar or (kind is np.ndarray and value.dtype is _FLOAT64)):
                    return _as_command(out)
        values = dict(values)
    pairs = out.collision_pairs
    if type(pairs) is PairColumns:
        # Names are checked by the log when it first meets a pair; distances are floats by
        # construction. Nothing to normalise: the command itself is what _as_command would build.
        if type(values) is ValueRow and type(errors) is dict and type(out.done) is bool:
            return out
        return Command(qdot=qd, status=out.status, task_errors=dict(errors), values=values,
                       collision_pairs=pairs, done=bool(out.done))
    if type(pairs) is not list and type(pairs) is not tuple:
        return _as_command(out)  # e.g. a generator, which the check below would consume
    if pairs:
        for pair in pairs:
            if (
                type(pair) is not tuple
                or len(pair) != 3
                or type(pair[0]) is not str
                or type(pair[1]) is not str
                or type(pair[2]) is not float
            ):
                return _as_command(out)
    return Command(qdot=qd, status=out.status, task_errors=dict(errors), values=values,
                   collision_pairs=list(pairs), done=bool(out.done))


def _format_error(error: BaseException) -> str:
    return (
        "".join(traceback.format_exception_only(type(error), error)).strip()
        + "\n"
        + "".join(traceback.format_tb(error.__traceback__))
    )


def run_episode(
    robot: RobotInterface,
    controller: Controller,
    *,
    duration: float,
    log_path: str | Path | None = None,
    metadata: Mapping[str, Any] | None = None,
    stop_at_end: bool = True,
    log_clouds: bool | int = False,
    cloud_max_points: int | None = None,
    log_timing: bool = False,
    ground_truth: Callable[[], Mapping[str, Any]] | None = None,
) -> EpisodeResult:
    """Run ``controller`` on ``robot`` for ``duration`` seconds at the robot's control rate.

    Args:
        robot: the robot (simulated or real), already reset to the episode's start.
        controller: object with ``reset(robot)`` and ``step(obs) -> Command | array``.
        duration: episode length [s] (rounded to whole control periods).
        log_path: where to write the compressed ``.npz`` log (None: not written).
        metadata: scalars or strings stored as ``meta/<key>`` in the log.
        stop_at_end: bring the arms to rest after the last tick (not logged).
        log_clouds: also log the camera frames' points and labels: ``True`` every frame, an
            integer ``N > 0`` every N-th frame (``cloud_frame`` says which), 0 or False none.
        cloud_max_points: thin each logged cloud by a regular stride to at most this many points.
        log_timing: log the controller's wall-clock time per step (makes logs differ
            between runs).
        ground_truth: what to log as ``truth/<name>`` per tick (default: the robot's
            ``ground_truth()`` method, if it has one). Never shown to the controller.

    Returns:
        The :class:`EpisodeResult` (also when the controller failed).
    """
    if not isinstance(robot, RobotInterface):
        raise InvalidInputError(f"robot must implement RobotInterface, got {type(robot).__name__}")
    if not callable(getattr(controller, "step", None)) or not callable(getattr(controller, "reset", None)):
        raise InvalidInputError(
            f"controller must have reset(robot) and step(obs) methods, got {type(controller).__name__}"
        )
    if not isinstance(duration, (int, float)) or not np.isfinite(duration) or duration <= 0:
        raise InvalidInputError(f"duration must be a finite time > 0 [s], got {duration!r}")
    n_ticks = int(round(duration / robot.control_period))
    truth_fn = ground_truth if ground_truth is not None else getattr(robot, "ground_truth", None)
    if truth_fn is not None and not callable(truth_fn):
        truth_fn = None
    truth0 = truth_fn() if truth_fn is not None else None
    if isinstance(log_clouds, float) or not isinstance(log_clouds, (bool, int, np.integer)) or log_clouds < 0:
        raise InvalidInputError(f"log_clouds must be a bool or an integer >= 0 (every N-th frame), got {log_clouds!r}")
    bad_count = isinstance(cloud_max_points, bool) or not isinstance(cloud_max_points, (int, np.integer))
    if cloud_max_points is not None and (bad_count or cloud_max_points < 1):
        raise InvalidInputError(f"cloud_max_points must be an integer >= 1 or None, got {cloud_max_points!r}")
    log = EpisodeLog(n_ticks, truth0, log_timing, log_clouds, cloud_max_points)
    send = robot.send_joint_velocities
    truth_log = log.truth
    # The log's per-tick arrays and methods, looked up once (the same objects every tick).
    log_t, log_q, log_qdot, log_force = log.t, log.q, log.qdot, log.force
    log_qdot_cmd, log_status = log.qdot_cmd, log.status
    log_stem_points, log_cloud_time, log_controller_time = log.stem_points, log.cloud_time, log.controller_time
    log_value, log_pairs = log.value, log.pairs
    perf_counter = time.perf_counter

    status, error = "completed", None
    latest: PointCloud | None = None
    latest_stem = -1
    wall0 = time.perf_counter()
    k = 0
    try:
        try:
            controller.reset(robot)
        except Exception as exc:
            status, error = "controller_error", "controller.reset failed: " + _format_error(exc)
        while status == "completed" and k < n_ticks:
            cloud = robot.camera_cloud()
            if cloud is not None:
                latest, latest_stem = cloud, cloud.count(STEM)
                log.frame(cloud, latest_stem)
            now, q, qdot, force = robot.time, robot.joint_positions(), robot.joint_velocities(), robot.wrist_force()
            obs = Observation(time=now, q=q, qdot=qdot, force=force, cloud=latest, new_cloud=cloud is not None,
                              tare_force=robot.tare_force)
            log_t[k], log_q[k], log_qdot[k], log_force[k] = now, q, qdot, force
            if latest is not None:
                log_stem_points[k] = latest_stem
                log_cloud_time[k] = latest.timestamp
            if truth_fn is not None:
                for name, value in truth_fn().items():
                    truth_log[name][k] = value
            t0 = perf_counter()
            try:
                out = controller.step(obs)
            except Exception as exc:
                status, error = "controller_error", "controller.step failed: " + _format_error(exc)
            else:
                try:
                    cmd = as_command(out)
                    # The log refuses a value whose shape changes from tick to tick.
                    if cmd.task_errors:
                        log.task(k, cmd.task_errors)
                    log_value(k, cmd.values)
                    log_pairs(k, cmd.collision_pairs)  # a new pair's names are checked here
                except InvalidInputError as exc:
                    status, error = "invalid_command", str(exc)
            if log_controller_time is not None:
                log_controller_time[k] = perf_counter() - t0
            if status != "completed":
                log_status[k] = "error"
                k += 1
                break
            log_qdot_cmd[k] = cmd.qdot
            log_status[k] = cmd.status
            send(cmd.qdot)
            k += 1
            try:
                robot.step()
            except HarvestQPError as exc:
                status, error = "robot_error", "robot.step failed: " + _format_error(exc)
                break
            if cmd.done:
                break
    finally:
        # Whatever happened (controller error, end of episode, Ctrl-C), leave the arms at rest.
        if status in ("controller_error", "invalid_command") or stop_at_end:
            try:
                robot.stop()
            except HarvestQPError as exc:
                if status == "completed":
                    status, error = "robot_error", "robot.stop failed: " + _format_error(exc)
    wall = time.perf_counter() - wall0

    arrays = log.arrays(k)
    arrays["episode_status"] = np.array(status)
    arrays["error"] = np.array(error or "")
    arrays["control_period"] = np.array(robot.control_period)
    arrays["duration"] = np.array(float(duration))
    arrays["n_ticks"] = np.array(k)
    seed = getattr(robot, "seed", None)
    if isinstance(seed, (int, np.integer)):
        arrays["seed"] = np.array(int(seed))
    for key, value in (metadata or {}).items():
        arrays[f"meta/{key}"] = np.asarray(value)
    path = write_npz(log_path, arrays) if log_path is not None else None
    return EpisodeResult(
        status=status,
        error=error,
        n_ticks=k,
        sim_time=k * robot.control_period,
        wall_time=wall,
        log=arrays,
        log_path=path,
    )
