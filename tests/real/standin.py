"""A stand-in for two UR5e behind ur-rtde, backed by the MuJoCo lab (:class:`harvest_qp.sim.SimRobot`).

:class:`LabCell` holds one SimRobot and answers ur-rtde's ``RTDEControlInterface`` and
``RTDEReceiveInterface`` calls (same names and argument lists, checked against the installed
ur-rtde in test_standin_matches_ur_rtde) for the two arm addresses, as a UR5e would:

* ``getActualQ``/``getActualQd``: the lab's joints of that arm [rad, rad/s], base to wrist 3;
* ``getActualTCPForce``: the wrench *on* the tool from outside (the lab's wrist sensor negated,
  the tool's weight included: the pendant's payload is 0), in the arm's base frame (``force_frame
  = "base"``) or the flange frame, minus what ``zeroFtSensor`` removed in the sensor frame;
* ``speedJ(qd, a, t)``: the arm's target velocity, reached at ``a`` [rad/s^2]; ``speedStop(a)``
  ramps to zero at ``a``; ``waitPeriod`` on the camera arm's interface advances the lab one
  control period (the camera arm's control interface paces the loop, as in DualUR5eRobot);
* ``getTimestamp``: the lab's clock plus the controller's uptime; ``getSafetyMode``: 1 (normal);
  ``getRobotStatus``: power on + program running until ``stopScript``.

Faults for the watchdog tests: :meth:`LabCell.freeze` (no fresh data), :meth:`LabCell.stall`
(the next period takes longer), :meth:`LabCell.protective_stop`, :meth:`LabCell.drop`
(connection lost: ``isConnected`` False, commands raise ``RuntimeError`` as ur-rtde's do).
Every call is recorded in :attr:`LabCell.calls` as (host, interface, method, args).
"""

from __future__ import annotations

import datetime

import numpy as np

from harvest_qp.robot.description import CAMERA_ARM, GRASP_ARM, mount_transform
from harvest_qp.sim import SimRobot

UPTIME = 1234.5  # [s] the robot controller's clock at the lab's t = 0


class LabCell:
    """Two UR5e stand-ins on one SimRobot (see the module docstring)."""

    def __init__(self, robot: SimRobot, hosts: tuple[str, str] = ("10.0.0.1", "10.0.0.2"),
                 force_frame: str = "base") -> None:
        self.robot = robot
        self.hosts = {hosts[0]: 0, hosts[1]: 1}
        self.force_frame = force_frame
        self.dt = robot.control_period
        self.calls: list[tuple[str, str, str, tuple]] = []
        self.target = np.zeros(12)
        self.current = np.zeros(12)
        self.accel = np.full(2, 1.0)
        self.safety = [1, 1]
        self.script = [False, False]
        self.connected = [False, False]
        self.frozen = [0, 0]
        self.sensor_offset = np.zeros(6)
        self.extra_time = 0.0  # stalls [s] added to the clock
        self.refused = set()
        m = robot.model
        ids = robot.scene.ids
        self._site = ids["ft_site"]
        self._force_adr = int(m.sensor_adr[ids["ft_force"]])
        self._torque_adr = int(m.sensor_adr[ids["ft_torque"]])
        self._snapshot = [self._state(0), self._state(1)]
        cell = self

        class Control:
            def __init__(self, hostname: str, frequency: float = -1.0, flags: int = 1, ur_cap_port: int = 50002,
                         rt_priority: int = 0) -> None:
                self.host = hostname
                cell.calls.append((hostname, "control", "__init__", ()))  # the control script starts here
                self.arm = cell._connect(hostname, "control")
                cell.script[self.arm] = True

            def __getattribute__(self, name):
                attr = object.__getattribute__(self, name)
                if not name.startswith("_") and name not in ("host", "arm") and callable(attr):
                    def call(*args, _attr=attr, _name=name):
                        cell.calls.append((object.__getattribute__(self, "host"), "control", _name, args))
                        return _attr(*args)
                    return call
                return attr

            def _live(self) -> None:
                if not cell.connected[self.arm]:
                    raise RuntimeError("RTDE control script is not running!")

            def speedJ(self, qd: list, acceleration: float = 0.5, time: float = 0.0) -> bool:
                self._live()
                if self.arm in cell.refused or not cell.script[self.arm] or cell.safety[self.arm] != 1:
                    return False
                cell.target[6 * self.arm:6 * self.arm + 6] = qd
                cell.accel[self.arm] = acceleration
                return True

            def speedStop(self, a: float = 10.0) -> bool:
                self._live()
                cell.target[6 * self.arm:6 * self.arm + 6] = 0.0
                cell.accel[self.arm] = a
                return True

            def stopScript(self) -> None:
                self._live()
                cell.target[6 * self.arm:6 * self.arm + 6] = 0.0
                cell.script[self.arm] = False

            def disconnect(self) -> None:
                cell.connected[self.arm] = False

            def isConnected(self) -> bool:
                return cell.connected[self.arm]

            def initPeriod(self) -> datetime.timedelta:
                return datetime.timedelta(seconds=cell.clock())

            def waitPeriod(self, arg0: datetime.timedelta) -> None:
                if self.arm == 0:
                    cell.tick()

            def zeroFtSensor(self) -> bool:
                self._live()
                if self.arm == 1:
                    cell.sensor_offset = cell.external_wrench_sensor()
                return True

            def setWatchdog(self, min_frequency: float = 10.0) -> bool:
                self._live()
                return True

            def kickWatchdog(self) -> bool:
                self._live()
                return True

            def getRobotStatus(self) -> int:
                return 3 if cell.script[self.arm] else 1

            def isProgramRunning(self) -> bool:
                return cell.script[self.arm]

        class Receive:
            def __init__(self, hostname: str, frequency: float = -1.0, variables: list | None = None,
                         verbose: bool = False, use_upper_range_registers: bool = False,
                         rt_priority: int = 0) -> None:
                self.host = hostname
                self.arm = cell._connect(hostname, "receive")

            def __getattribute__(self, name):
                attr = object.__getattribute__(self, name)
                if not name.startswith("_") and name not in ("host", "arm") and callable(attr):
                    def call(*args, _attr=attr, _name=name):
                        cell.calls.append((object.__getattribute__(self, "host"), "receive", _name, args))
                        return _attr(*args)
                    return call
                return attr

            def _snap(self) -> dict:
                return cell._snapshot[self.arm]

            def getActualQ(self) -> list:
                return list(self._snap()["q"])

            def getActualQd(self) -> list:
                return list(self._snap()["qd"])

            def getActualTCPForce(self) -> list:
                return list(self._snap()["wrench"])

            def getTimestamp(self) -> float:
                return self._snap()["stamp"]

            def getSafetyMode(self) -> int:
                return cell.safety[self.arm]

            def getRobotStatus(self) -> int:
                return 3 if cell.script[self.arm] else 1

            def isConnected(self) -> bool:
                return cell.connected[self.arm]

            def disconnect(self) -> None:
                pass

            def isProtectiveStopped(self) -> bool:
                return cell.safety[self.arm] == 3

            def isEmergencyStopped(self) -> bool:
                return cell.safety[self.arm] in (6, 7)

        self.RTDEControlInterface = Control
        self.RTDEReceiveInterface = Receive

    # ------------------------------------------------------------------ the lab behind it

    def _connect(self, host: str, kind: str) -> int:
        if host not in self.hosts:
            raise RuntimeError(f"Could not connect to: {host} at 30004")
        arm = self.hosts[host]
        self.connected[arm] = True
        return arm

    def clock(self) -> float:
        """The cell's wall clock [s]: the lab's time plus any stalls."""
        return self.robot.time + self.extra_time

    def external_wrench_sensor(self) -> np.ndarray:
        """The wrench on the tool from outside, in the sensor (flange) frame, before any zeroing."""
        d = self.robot.data
        return -np.concatenate([d.sensordata[self._force_adr:self._force_adr + 3],
                                d.sensordata[self._torque_adr:self._torque_adr + 3]])

    def _state(self, arm: int) -> dict:
        q = self.robot.joint_positions()[6 * arm:6 * arm + 6]
        qd = self.robot.joint_velocities()[6 * arm:6 * arm + 6]
        wrench = np.zeros(6)
        if arm == 1:
            w = self.external_wrench_sensor() - self.sensor_offset
            if self.force_frame == "base":
                R = mount_transform(GRASP_ARM)[:3, :3].T @ self.robot.data.site_xmat[self._site].reshape(3, 3)
                w = np.concatenate([R @ w[:3], R @ w[3:]])
            wrench = w
        return {"q": q, "qd": qd, "wrench": wrench, "stamp": UPTIME + self.robot.time}

    def tick(self) -> None:
        """One control period: ramp each arm's velocity to its target at its acceleration, step the lab."""
        step = np.repeat(self.accel, 6) * self.dt
        self.current = self.current + np.clip(self.target - self.current, -step, step)
        self.robot.send_joint_velocities(self.current)
        self.robot.step()
        for arm in (0, 1):
            if self.frozen[arm] > 0:
                self.frozen[arm] -= 1
            elif self.connected[arm]:
                self._snapshot[arm] = self._state(arm)

    # ------------------------------------------------------------------ faults

    def freeze(self, arm: int, cycles: int) -> None:
        """No fresh data from ``arm`` for ``cycles`` periods (the last packet repeats)."""
        self.frozen[arm] = cycles

    def stall(self, seconds: float) -> None:
        """The clock jumps: the current cycle looks ``seconds`` longer."""
        self.extra_time += seconds

    def protective_stop(self, arm: int, mode: int = 3) -> None:
        """The arm reports safety mode ``mode`` (3 protective stop, 7 robot e-stop) and halts."""
        self.safety[arm] = mode
        self.target[6 * arm:6 * arm + 6] = 0.0
        self.accel[arm] = 20.0

    def drop(self, arm: int) -> None:
        """The arm's connection is lost (its last packet stays, its commands raise)."""
        self.connected[arm] = False

    def methods_called(self, host: str | None = None, kind: str | None = None) -> list[str]:
        return [c[2] for c in self.calls if (host is None or c[0] == host) and (kind is None or c[1] == kind)]


class LabCamera:
    """The lab's own camera frames as a :class:`~harvest_qp.real.ur_rtde_robot.CloudSource`."""

    def __init__(self, robot: SimRobot) -> None:
        self.robot = robot
        self.closed = False

    def attach(self, robot) -> None:
        pass

    def latest(self):
        return self.robot.camera_cloud()

    def close(self) -> None:
        self.closed = True


__all__ = ["LabCell", "LabCamera", "CAMERA_ARM", "UPTIME"]
