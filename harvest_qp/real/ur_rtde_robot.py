"""Two UR5e through ``ur-rtde`` as one :class:`~harvest_qp.runtime.interface.RobotInterface`.

Every control cycle (``control_period``, the paper's 2 ms) :meth:`DualUR5eRobot.step` runs the
watchdog (:mod:`harvest_qp.real.watchdog`) on the cycle time and the held command, sends it to
both arms with ``RTDEControlInterface.speedJ(qd, a, period)``, waits for the end of the period on
the camera arm's interface (``initPeriod``/``waitPeriod``), then reads both arms
(``getActualQ``/``getActualQd``/``getActualTCPForce``, the timestamp, the safety mode and the
status bits) and checks them. A failed check stops both arms with ``speedStop`` at the
watchdog's deceleration and raises :class:`~harvest_qp.real.errors.WatchdogError`, which the
episode runner records as the episode's end (``robot_error``) before calling :meth:`stop`.

:meth:`close` (also the context manager's exit) sends ``speedStop`` and ``stopScript`` to both
arms and disconnects; the command line calls it on every exit path (normal end, abort,
exception, Ctrl-C, lost connection).

Conventions (:mod:`harvest_qp.runtime.interface`): joints camera arm first, each arm base to wrist 3 as
``getActualQ`` gives them [rad, rad/s]; the robot clock is the camera arm's RTDE timestamp since
the connection [s]; the wrist force is in the world frame (the arms' base poses and the flange
poses come from the robot description, :func:`harvest_qp.robot.description.mount_transform` and
:meth:`harvest_qp.configuration.Configuration.dual_ur5e`).
"""

from __future__ import annotations

import socket
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.configuration import Configuration
from harvest_qp.exceptions import InvalidInputError
from harvest_qp.real.calibration import check_hand_eye
from harvest_qp.real.cell import CellConfig
from harvest_qp.real.errors import CameraError, RobotConnectionError, WatchdogError, missing_package
from harvest_qp.real.watchdog import Watchdog
from harvest_qp.robot.description import CAMERA_ARM, GRASP_ARM, camera_mount, joint_names, mount_transform
from harvest_qp.runtime.interface import N_JOINTS, PointCloud, RobotInterface

__all__ = ["DualUR5eRobot", "CloudSource", "tool_wrench", "RTDE_PORT", "GRAVITY"]

#: The UR controller's RTDE port (ur-rtde always connects there).
RTDE_PORT = 30004
#: Gravity in the world frame [m/s^2].
GRAVITY = np.array([0.0, 0.0, -9.81])
_ARMS = (("camera arm", CAMERA_ARM, slice(0, 6)), ("grasping arm", GRASP_ARM, slice(6, 12)))


class CloudSource(Protocol):
    """A camera behind :meth:`DualUR5eRobot.camera_cloud` (e.g. :class:`~harvest_qp.real.realsense.RealSenseSource`)."""

    def attach(self, robot: DualUR5eRobot) -> None:
        """Start delivering clouds; ``robot`` gives the clock and the camera pose at a time."""

    def latest(self) -> PointCloud | None:
        """The newest cloud not yet returned, or None."""

    def close(self) -> None:
        """Stop the stream."""


def tool_wrench(reading: NDArray, R_world_frame: NDArray, R_world_sensor: NDArray, sensor_offset: NDArray,
                mass: float, com: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The force [N] and torque [Nm] (about the flange, world frame) the tool applies to what it holds.

    Args:
        reading: ``getActualTCPForce`` (6,): the external wrench on the tool, expressed in the
            frame whose world rotation is ``R_world_frame`` (the arm's base or the flange).
        R_world_sensor: the flange's world rotation at the same time.
        sensor_offset: (6,) what ``zeroFtSensor`` removed, in the sensor (flange) frame.
        mass, com: the tool's mass not compensated by the robot [kg], its centre of mass in the
            flange frame [m].

    The tool is at rest under its weight ``m g``, the external wrench ``E`` and the held object's
    reaction, so it applies ``m g - E`` to the object (torque ``c x m g - E_t``).
    """
    R_f, R_s = np.asarray(R_world_frame, float), np.asarray(R_world_sensor, float)
    external_force = R_f @ reading[:3] + R_s @ sensor_offset[:3]
    external_torque = R_f @ reading[3:] + R_s @ sensor_offset[3:]
    weight = mass * GRAVITY
    c = R_s @ np.asarray(com, float)
    # c x weight (np.cross costs ~15 us per call, a tenth of the adapter's tick)
    moment = np.array([c[1] * weight[2] - c[2] * weight[1], c[2] * weight[0] - c[0] * weight[2],
                       c[0] * weight[1] - c[1] * weight[0]])
    return weight - external_force, moment - external_torque


def _probe(host: str, role: str, timeout: float) -> None:
    """Fail within ``timeout`` when nothing answers on the RTDE port (a dropped packet would hang ur-rtde)."""
    try:
        with socket.create_connection((host, RTDE_PORT), timeout=timeout):
            pass
    except OSError as err:
        why = "timed out" if isinstance(err, TimeoutError) else (err.strerror or str(err))
        raise RobotConnectionError(f"cannot reach the UR5e {role} at {host}:{RTDE_PORT} ({why}); check the cable, "
                                   "the address, and that the robot is on with remote control enabled") from None


class _NoAnswer(Exception):
    """A ur-rtde constructor still blocked after the connect timeout."""


def _within(timeout: float, make: Callable[..., Any], *args: Any) -> Any:
    """``make(*args)`` in a helper thread, or :class:`_NoAnswer` after ``timeout`` [s]: ur-rtde's constructors
    block without a limit on an address that accepts TCP and never answers (the daemon thread may stay
    blocked until the process ends)."""
    box: dict[str, Any] = {}

    def run() -> None:
        try:
            box["value"] = make(*args)
        except BaseException as err:  # handed to the caller's thread
            box["error"] = err

    thread = threading.Thread(target=run, name="ur-rtde connect", daemon=True)
    thread.start()
    thread.join(timeout)
    if thread.is_alive():
        raise _NoAnswer(f"no answer within {timeout} s")
    if "error" in box:
        raise box["error"]
    return box["value"]


class _Arm:
    """One UR5e's RTDE control and receive interfaces."""

    def __init__(self, role: str, prefix: str, joints: slice, host: str, rtde: Any, frequency: float,
                 connect_timeout: float = 10.0, *, control: bool = True) -> None:
        self.role, self.prefix, self.joints, self.host = role, prefix, joints, host
        self.receive = self.control = None
        try:
            self.receive = _within(connect_timeout, rtde.RTDEReceiveInterface, host, frequency)
            if control:  # RTDEControlInterface uploads and starts its control script: it takes the arm over
                self.control = _within(connect_timeout, rtde.RTDEControlInterface, host, frequency)
        except _NoAnswer:
            self.close(stop_acceleration=None)
            raise RobotConnectionError(
                f"the UR5e {role} at {host} accepted the connection but did not answer within {connect_timeout:g} s "
                "(a controller still booting, or another device at this address?)") from None
        except RuntimeError as err:
            self.close(stop_acceleration=None)
            raise RobotConnectionError(f"cannot connect to the UR5e {role} at {host}: {' '.join(str(err).split())}; "
                                       "is remote control enabled on the pendant?") from None
        except BaseException:  # Ctrl-C or any other failure while connecting: leave no script running
            self.close(stop_acceleration=None)
            raise

    def close(self, stop_acceleration: float | None) -> list[str]:
        """speedStop, stopScript, disconnect; every call tried, failures returned as text."""
        problems = []
        calls: list[tuple[Any, str, tuple]] = []
        if self.control is not None:
            if stop_acceleration is not None:
                calls.append((self.control, "speedStop", (stop_acceleration,)))
            calls += [(self.control, "stopScript", ()), (self.control, "disconnect", ())]
        if self.receive is not None:
            calls.append((self.receive, "disconnect", ()))
        for target, name, args in calls:
            try:
                getattr(target, name)(*args)
            except Exception as err:  # keep going: the other calls (and the other arm) must still run
                problems.append(f"{self.role} {self.host}: {name} failed: {err}")
        self.control = self.receive = None
        return problems


class DualUR5eRobot(RobotInterface):
    """The dual UR5e through ur-rtde (see the module docstring).

    Args:
        camera_arm, grasp_arm: the arms' IP addresses.
        cell: the cell file's settings (:func:`harvest_qp.real.cell.load_cell`).
        hand_eye: the camera optical frame in the camera arm's flange (4x4 [m], from the calibration;
            None: the robot description's mount, :func:`~harvest_qp.robot.description.camera_mount`).
            The clouds are expressed with it, and :func:`~harvest_qp.real.episode.run_real_episode`
            hands it to the controller, whose camera task then drives the same frame.
        camera: where :meth:`camera_cloud` gets its clouds (None: no camera).
        rtde: a module-like object with ``RTDEControlInterface`` and ``RTDEReceiveInterface``
            (default: ur-rtde's ``rtde_control``/``rtde_receive``); tests pass a stand-in.
        clock: monotonic wall clock [s] for the cycle time (tests pass the stand-in's).
        probe_timeout: seconds to wait for the RTDE port before connecting (None: no probe).
        connect_timeout: seconds each ur-rtde interface may take to connect (an address that accepts
            the connection and never answers is then a one-line error naming it, not a hang).
        read_only: open only the arms' receive interfaces (``--dry-run``): no control script is
            started on the robots (the pendant's program keeps running, local mode is fine) and
            :meth:`step` raises :class:`RobotConnectionError`.

    Raises:
        CalibrationError: ``hand_eye`` not a rigid 4x4 transform within 0.5 m of the flange.
        InvalidInputError: the same address for both arms.
        RobotConnectionError: an arm that cannot be reached or is not ready.
    """

    def __init__(self, camera_arm: str, grasp_arm: str, *, cell: CellConfig | None = None,
                 hand_eye: ArrayLike | None = None, camera: CloudSource | None = None, rtde: Any = None,
                 clock: Callable[[], float] = time.perf_counter, probe_timeout: float | None = 2.0,
                 connect_timeout: float = 10.0, read_only: bool = False) -> None:
        self.cell = cell if cell is not None else CellConfig()
        self._read_only = bool(read_only)
        self.control_period = float(self.cell.control_period)
        self.hosts = {"camera arm": str(camera_arm), "grasping arm": str(grasp_arm)}
        if self.hosts["camera arm"].strip() == self.hosts["grasping arm"].strip():
            raise InvalidInputError(f"the camera arm and the grasping arm have the same address {camera_arm!r}; "
                                    "each UR5e has its own controller and address")
        if rtde is None:
            rtde = _ur_rtde()
            for role, host in self.hosts.items():
                if probe_timeout is not None:
                    _probe(host, role, probe_timeout)
        self.clock = clock
        self.hand_eye = camera_mount() if hand_eye is None else check_hand_eye(hand_eye)
        self._configuration = Configuration.dual_ur5e()
        self._camera_configuration = Configuration.dual_ur5e()  # used by the camera's thread only
        self._camera_lock = threading.Lock()
        self._base_rotation = {prefix: mount_transform(prefix)[:3, :3] for _, prefix, _ in _ARMS}
        self._tool_com = np.array(self.cell.force.tool_com, dtype=float)
        self.watchdog = Watchdog(self.cell.watchdog, self.control_period, self._configuration.lower_limits,
                                 self._configuration.upper_limits, joint_names())
        self._arms: list[_Arm] = []
        self._closed = False
        frequency = 1.0 / self.control_period
        try:
            for role, prefix, joints in _ARMS:
                self._arms.append(_Arm(role, prefix, joints, self.hosts[role], rtde, frequency, connect_timeout,
                                       control=not read_only))
        except BaseException:  # the first arm connected, the second failed (or Ctrl-C): stop the first
            self.close()
            raise
        self.camera = camera
        self._q = np.zeros(N_JOINTS)
        self._qd = np.zeros(N_JOINTS)
        self._reading = np.zeros(6)
        self._sensor_offset = np.zeros(6)
        self._pending_zero: NDArray[np.float64] | None = None
        self._tare = np.zeros(3)
        self._force = np.zeros(3)
        self._torque = np.zeros(3)
        self._command = np.zeros(N_JOINTS)
        self._stamp = 0.0
        self._t0: float | None = None
        self._robot_watchdog_armed = False
        self._ticks = 0
        self.tripped: str | None = None
        self._camera_error: str | None = None
        self._last_frame_clock = self.clock()  # a camera that never delivers is stale after camera_timeout
        self.stops = 0
        self._history: deque[tuple[float, float, NDArray[np.float64]]] = deque(maxlen=512)
        reason = self._read()
        if reason is not None:
            self.close()
            raise RobotConnectionError(f"the arms are not ready: {reason}")
        self._t0 = self._stamp
        self._history.clear()
        self._remember()
        self._cycle_start = None if self._read_only else self._clock_arm.control.initPeriod()
        self._cycle_clock = self.clock()
        if camera is not None:
            camera.attach(self)

    @property
    def read_only(self) -> bool:
        """True for a read-only connection (no control interface: it cannot command the arms)."""
        return self._read_only

    # ------------------------------------------------------------------ RobotInterface

    @property
    def time(self) -> float:
        """The camera arm's RTDE timestamp since the connection [s]."""
        return self._stamp - (self._t0 or 0.0)

    def joint_positions(self) -> NDArray[np.float64]:
        return self._q.copy()

    def joint_velocities(self) -> NDArray[np.float64]:
        return self._qd.copy()

    def wrist_force(self) -> NDArray[np.float64]:
        return self._force - self._tare

    def wrist_wrench(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Untared force [N] and torque about the flange [Nm] the tool applies to what it holds (world frame)."""
        return self._force.copy(), self._torque.copy()

    def tare_force(self) -> None:
        self._tare = self._force.copy()
        if self.cell.force.zero_on_tare and not self._read_only:
            grasp = self._arms[1]
            R_frame, R_sensor = self._rotations()
            # From now on the sensor reports minus this (in its own frame): keep it, so the world
            # reading stays continuous while the flange turns.
            to_sensor = R_sensor.T @ R_frame
            removed = np.concatenate([to_sensor @ self._reading[:3], to_sensor @ self._reading[3:]])
            try:
                grasp.control.zeroFtSensor()
            except RuntimeError as err:
                self._trip(f"lost connection to the grasping arm at {grasp.host}: zeroFtSensor failed: {err}")
            self._pending_zero = removed

    def camera_cloud(self) -> PointCloud | None:
        if self.camera is None:
            return None
        try:
            cloud = self.camera.latest()
        except CameraError as err:  # ends the episode at the next step, through the watchdog's stop
            self._camera_error = str(err)
            return None
        if cloud is not None:
            self._last_frame_clock = self.clock()
        return cloud

    def send_joint_velocities(self, qdot: ArrayLike) -> None:
        qd = np.asarray(qdot, dtype=float)
        if qd.shape != (N_JOINTS,):
            raise InvalidInputError(f"qdot must have shape ({N_JOINTS},) [rad/s], got {qd.shape}")
        self._command = qd.copy()

    def step(self) -> None:
        """Check, send the held command to both arms, wait for the period's end, read both arms."""
        if self._closed:
            raise RobotConnectionError("the robot connection is closed")
        if self._read_only:
            raise RobotConnectionError("a read-only connection (a dry run) sends no command: connect with "
                                       "read_only=False to move the arms")
        if self.tripped is not None:
            raise WatchdogError(f"stopped earlier: {self.tripped}")
        if self._camera_error is not None:
            self._trip(self._camera_error)
        moving = bool(np.any(self._command != 0.0) or np.any(self.watchdog.previous_command != 0.0)
                      or np.max(np.abs(self._qd)) > 1e-3)
        timeout = self.cell.watchdog.camera_timeout
        if self.camera is not None and moving and self.clock() - self._last_frame_clock > timeout:
            self._trip(f"camera: no new frame for more than {timeout:g} s (a stalled stream)")
        elapsed = self.clock() - self._cycle_clock
        # At rest under a zero command a long cycle moves nothing (the first tick loads the kernels).
        reason = (self.watchdog.cycle(elapsed) if moving else None) or self.watchdog.command(self._q, self._command)
        if reason is not None:
            self._trip(reason)
        if moving and not self._robot_watchdog_armed and self.cell.robot_watchdog_hz > 0:
            self._call_all("setWatchdog", self.cell.robot_watchdog_hz)
            self._robot_watchdog_armed = True
        a, period = self.cell.speedj_acceleration, self.control_period
        for arm in self._arms:
            try:
                accepted = arm.control.speedJ(self._command[arm.joints].tolist(), a, period)
                if self._robot_watchdog_armed:
                    arm.control.kickWatchdog()
            except RuntimeError as err:
                self._trip(f"lost connection to the {arm.role} at {arm.host}: speedJ failed: {err}")
            if accepted is False:
                # The robot's own state says why (a protective stop between two reads), if it does.
                self._trip(self._read() or f"the {arm.role} at {arm.host} refused speedJ (its control script is "
                           "not running)")
        self._wait()
        reason = self._read()
        if reason is not None:
            self._trip(reason)
        self._ticks += 1

    def stop(self) -> None:
        """``speedStop`` both arms at the watchdog's deceleration and wait until they are at rest."""
        if self._closed:
            return
        a = self.cell.watchdog.stop_acceleration
        self._call_all("speedStop", a)
        self._command = np.zeros(N_JOINTS)
        self.watchdog.previous_command = np.zeros(N_JOINTS)
        self.stops += 1
        limit = int(np.ceil((self.cell.watchdog.max_joint_speed / a + 0.5) / self.control_period))
        for _ in range(limit):
            try:
                self._wait()
            except RobotConnectionError:
                return
            if self._read() is not None:
                return  # no data to wait on: the robot's own stop is all there is
            if np.max(np.abs(self._qd)) < 1e-3:
                return

    # ------------------------------------------------------------------ life cycle

    def close(self) -> None:
        """``speedStop`` and ``stopScript`` on both arms, disconnect, stop the camera (idempotent)."""
        if self._closed:
            return
        self._closed = True
        problems = []
        for arm in self._arms:
            problems += arm.close(self.cell.watchdog.stop_acceleration)
        camera = getattr(self, "camera", None)
        if camera is not None:
            try:
                camera.close()
            except Exception as err:
                problems.append(f"camera: close failed: {err}")
        for line in problems:
            print(f"harvest-qp: while closing: {line}", file=sys.stderr)

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self) -> DualUR5eRobot:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ camera support

    def robot_time_at(self, wall: float) -> float:
        """The robot clock [s] at the wall-clock instant ``wall`` (of :attr:`clock`)."""
        stamp, clock_now, _ = self._history[-1]
        return stamp - (self._t0 or 0.0) + (wall - clock_now)

    def joints_at(self, t: float) -> NDArray[np.float64]:
        """The measured joints (12,) at robot time ``t`` [s], interpolated in the recent history."""
        history = list(self._history)
        times = np.array([h[0] for h in history]) - (self._t0 or 0.0)
        if t <= times[0]:
            return history[0][2].copy()
        if t >= times[-1]:
            return history[-1][2].copy()
        i = int(np.searchsorted(times, t))
        w = (t - times[i - 1]) / max(times[i] - times[i - 1], 1e-12)
        return (1 - w) * history[i - 1][2] + w * history[i][2]

    def camera_pose_at(self, t: float) -> NDArray[np.float64]:
        """World pose (4x4) of the camera optical frame at robot time ``t``: flange (measured joints,
        robot description) times the hand-eye transform. Safe to call from the camera's thread."""
        q = self.joints_at(t)
        with self._camera_lock:
            self._camera_configuration.update(q)
            flange = self._camera_configuration.frame_pose(CAMERA_ARM + "flange")
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = flange.rotation, flange.translation
        return T @ self.hand_eye

    # ------------------------------------------------------------------ internals

    @property
    def _clock_arm(self) -> _Arm:
        return self._arms[0]

    def _wait(self) -> None:
        control = self._clock_arm.control
        if control is None:
            raise RobotConnectionError("the robot connection is closed")
        control.waitPeriod(self._cycle_start)
        self._cycle_start = control.initPeriod()
        self._cycle_clock = self.clock()

    def _call_all(self, name: str, *args: Any) -> None:
        """Call a control method on both arms, each tried even if the other fails."""
        for arm in self._arms:
            try:
                if arm.control is not None:
                    getattr(arm.control, name)(*args)
            except RuntimeError as err:
                print(f"harvest-qp: {arm.role} {arm.host}: {name} failed: {err}", file=sys.stderr)

    def _trip(self, reason: str) -> None:
        """Stop both arms within the deceleration limit and end the episode with ``reason``."""
        self.tripped = reason
        self._call_all("speedStop", self.cell.watchdog.stop_acceleration)
        self._command = np.zeros(N_JOINTS)
        raise WatchdogError(reason)

    def _rotations(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """World rotations of the force reading's frame and of the grasping flange (measured joints)."""
        self._configuration.update(self._q)
        R_sensor = self._configuration.frame_rotation(GRASP_ARM + "flange")
        R_frame = self._base_rotation[GRASP_ARM] if self.cell.force.frame == "base" else R_sensor
        return R_frame, R_sensor

    def _read(self) -> str | None:
        """Read both arms into the cache; a reason when a check fails."""
        for arm in self._arms:
            receive = arm.receive
            try:
                if not receive.isConnected():
                    return f"lost connection to the {arm.role} at {arm.host}"
                stamp = float(receive.getTimestamp())
                q = np.asarray(receive.getActualQ(), dtype=float)
                qd = np.asarray(receive.getActualQd(), dtype=float)
                force = np.asarray(receive.getActualTCPForce(), dtype=float) if arm.prefix == GRASP_ARM else None
                safety, status = int(receive.getSafetyMode()), int(receive.getRobotStatus())
            except RuntimeError as err:
                return f"lost connection to the {arm.role} at {arm.host}: {err}"
            ok = q.shape == (6,) and qd.shape == (6,) and bool(np.all(np.isfinite(q)) and np.all(np.isfinite(qd)))
            if force is not None:
                ok = ok and force.shape == (6,) and bool(np.all(np.isfinite(force)))
            if ok:
                self._q[arm.joints], self._qd[arm.joints] = q, qd
                if force is not None:
                    self._reading = force
            if arm.prefix == CAMERA_ARM:
                self._stamp = stamp
            reason = self.watchdog.fresh(f"{arm.role} at {arm.host}", stamp, ok) or self.watchdog.robot_state(
                f"{arm.role} at {arm.host}", safety, status, script=not self._read_only)
            if reason is not None:
                return reason
        self._update_force()
        self._remember()
        return None

    def _update_force(self) -> None:
        R_frame, R_sensor = self._rotations()
        if self._pending_zero is not None:
            # The zero shows once the reading (in the sensor frame) has dropped by about what was removed.
            now = R_sensor.T @ R_frame @ self._reading[:3]
            removed = np.linalg.norm(self._pending_zero[:3])
            if removed == 0.0 or np.linalg.norm(now) < 0.5 * removed:
                self._sensor_offset = self._sensor_offset + self._pending_zero
                self._pending_zero = None
        self._force, self._torque = tool_wrench(self._reading, R_frame, R_sensor, self._sensor_offset,
                                                self.cell.force.tool_mass, self._tool_com)

    def _remember(self) -> None:
        self._history.append((self._stamp, self.clock(), self._q.copy()))


def _ur_rtde():
    """ur-rtde's two modules as one namespace."""
    try:
        import rtde_control
        import rtde_receive
    except ImportError:
        raise missing_package("ur-rtde", "the UR5e driver (--robot ur)") from None

    class _Namespace:
        RTDEControlInterface = rtde_control.RTDEControlInterface
        RTDEReceiveInterface = rtde_receive.RTDEReceiveInterface

    return _Namespace
