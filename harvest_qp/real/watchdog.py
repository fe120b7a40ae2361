"""The checks :class:`~harvest_qp.real.ur_rtde_robot.DualUR5eRobot` runs before every command.

Each check returns None when all is well, or a one-line reason; the robot then stops both arms
with ``speedStop`` at the configured deceleration and ends the episode with that reason
(:class:`~harvest_qp.real.errors.WatchdogError`, logged by the runner as ``robot_error``).

* stale or missing data: an arm's RTDE timestamp did not advance, or its joint data was missing
  or not finite, for ``stale_cycles`` cycles in a row;
* a missed period: a control cycle took more than ``max_cycle_periods`` control periods;
* a command outside the joint speed limit, or changing faster than the joint acceleration
  limit, or leading out of the joint position limits (the position where the joint would come
  to rest if stopped now at ``stop_acceleration``, within ``position_margin`` of a limit);
* the robot's own state: a safety mode other than normal/reduced (protective stop, e-stop,
  safeguard stop, violation, fault) or the control script no longer running.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from harvest_qp.exceptions import ConfigError

__all__ = ["WatchdogConfig", "Watchdog", "SAFETY_MODES", "ROBOT_STATUS_PROGRAM_RUNNING"]

#: UR safety modes (RTDE ``safety_mode``); 1 and 2 allow motion.
SAFETY_MODES = {
    1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY", 5: "SAFEGUARD_STOP",
    6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP", 8: "VIOLATION", 9: "FAULT", 10: "VALIDATE_JOINT_ID",
    11: "UNDEFINED_SAFETY_MODE", 12: "AUTOMATIC_MODE_SAFEGUARD_STOP", 13: "SYSTEM_THREE_POSITION_ENABLING_STOP",
}
_MOVING_ALLOWED = (1, 2)
#: RTDE ``robot_status_bits``: bit 0 power on, bit 1 program running.
ROBOT_STATUS_POWER_ON = 1
ROBOT_STATUS_PROGRAM_RUNNING = 2


@dataclass(frozen=True)
class WatchdogConfig:
    """Thresholds of the watchdog (the cell file's ``watchdog`` section).

    Attributes:
        stale_cycles: cycles in a row without fresh robot data before stopping.
        max_cycle_periods: longest control cycle, in control periods (a camera frame's perception
            tick can take a few periods; the lab's worst is in docs/real_robots.md).
        max_joint_speed: joint speed limit of a command [rad/s] (the QP's own limit is 1.0).
        max_joint_acceleration: limit of the change of a joint's command per period [rad/s^2].
        position_margin: keep this far inside the joint position limits [rad].
        stop_acceleration: deceleration of every stop (``speedStop``) [rad/s^2], at most
            ``max_joint_acceleration``.
        camera_timeout: longest time [s] without a new camera frame while the arms move (a camera that
            stops delivering, a USB stall, with no error): the arms stop.
    """

    stale_cycles: int = 5
    max_cycle_periods: float = 10.0
    max_joint_speed: float = 1.05
    max_joint_acceleration: float = 10.0
    position_margin: float = 0.02
    stop_acceleration: float = 4.0
    camera_timeout: float = 1.0

    def __post_init__(self) -> None:
        if isinstance(self.stale_cycles, bool) or not isinstance(self.stale_cycles, int) or self.stale_cycles < 1:
            raise ConfigError(f"watchdog.stale_cycles must be an integer >= 1, got {self.stale_cycles!r}")
        for name in ("max_cycle_periods", "max_joint_speed", "max_joint_acceleration", "stop_acceleration",
                     "camera_timeout"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value <= 0:
                raise ConfigError(f"watchdog.{name} must be a number > 0, got {value!r}")
        if self.max_cycle_periods < 1:
            raise ConfigError(f"watchdog.max_cycle_periods must be >= 1, got {self.max_cycle_periods!r}")
        if self.stop_acceleration > self.max_joint_acceleration:
            # a stop is a command too: braking harder than the cell allows any command to change
            raise ConfigError(f"watchdog.stop_acceleration ({self.stop_acceleration!r} rad/s^2) must not exceed "
                              f"watchdog.max_joint_acceleration ({self.max_joint_acceleration!r} rad/s^2)")
        m = self.position_margin
        if isinstance(m, bool) or not isinstance(m, (int, float)) or not np.isfinite(m) or m < 0:
            raise ConfigError(f"watchdog.position_margin must be a number >= 0 [rad], got {m!r}")


class Watchdog:
    """Stateful checks for one episode (the stale counters and the previous command).

    Args:
        config: thresholds.
        period: control period [s].
        lower, upper: (12,) joint position limits [rad].
        joint_names: (12,) names used in the reasons.
    """

    def __init__(self, config: WatchdogConfig, period: float, lower: NDArray, upper: NDArray,
                 joint_names: list[str]) -> None:
        self.config = config
        self.period = float(period)
        self.lower = np.asarray(lower, float)
        self.upper = np.asarray(upper, float)
        self.joint_names = list(joint_names)
        self.reset()

    def reset(self) -> None:
        """Forget the stale counters and the previous command (the arms are at rest)."""
        self._stale: dict[str, int] = {}
        self._stamp: dict[str, float] = {}
        self.previous_command = np.zeros(len(self.joint_names))
        self.longest_cycle = 0.0

    def fresh(self, arm: str, timestamp: float | None, data_ok: bool) -> str | None:
        """Count an arm's reading: ``timestamp`` its RTDE timestamp [s] (None: unreadable)."""
        stale = timestamp is None or not data_ok or timestamp == self._stamp.get(arm)
        if timestamp is not None:
            self._stamp[arm] = timestamp
        count = self._stale[arm] = self._stale.get(arm, 0) + 1 if stale else 0
        if count >= self.config.stale_cycles:
            what = "no joint data" if not data_ok else "no fresh state (RTDE timestamp unchanged)"
            return f"stale data from the {arm}: {what} for {count} cycles"
        return None

    def robot_state(self, arm: str, safety_mode: int, robot_status: int, *, script: bool = True) -> str | None:
        """The robot's own safety mode and status bits (``script``: our control script must be running;
        False for a read-only connection, which starts none)."""
        if safety_mode not in _MOVING_ALLOWED:
            name = SAFETY_MODES.get(int(safety_mode), "UNKNOWN")
            kind = "emergency stop" if "EMERGENCY" in name else "protective stop" if "PROTECTIVE" in name else "stop"
            return f"{kind} reported by the {arm}: safety mode {int(safety_mode)} ({name})"
        powered = bool(robot_status & ROBOT_STATUS_POWER_ON)
        if script and not (powered and robot_status & ROBOT_STATUS_PROGRAM_RUNNING):
            return (f"the {arm}'s control script is not running (robot status bits {int(robot_status):#06b}: "
                    "power on = bit 0, program running = bit 1)")
        if not powered:
            return (f"the {arm} is not powered on (robot status bits {int(robot_status):#06b}: power on = bit 0); "
                    "power it on from the pendant")
        return None

    def cycle(self, elapsed: float) -> str | None:
        """The time since the cycle started [s]."""
        self.longest_cycle = max(self.longest_cycle, elapsed)
        limit = self.config.max_cycle_periods * self.period
        if elapsed > limit:
            return (f"missed period: the control cycle took {1e3 * elapsed:.1f} ms, more than "
                    f"{self.config.max_cycle_periods:g} periods ({1e3 * limit:.1f} ms)")
        return None

    def command(self, q: NDArray[np.float64], qdot: NDArray[np.float64]) -> str | None:
        """A command ``qdot`` (12,) [rad/s] from the measured ``q`` (12,) [rad]."""
        c = self.config
        if not np.all(np.isfinite(qdot)):
            return f"command not finite: {np.asarray(qdot).tolist()}"
        speed = np.abs(qdot)
        j = int(np.argmax(speed))
        if speed[j] > c.max_joint_speed * (1 + 1e-9):
            return f"command outside the joint speed limit: {self.joint_names[j]} {qdot[j]:+.3f} rad/s " \
                   f"(limit {c.max_joint_speed:g} rad/s)"
        change = np.abs(qdot - self.previous_command) / self.period
        j = int(np.argmax(change))
        if change[j] > c.max_joint_acceleration * (1 + 1e-6) + 1e-9:
            return f"command outside the joint acceleration limit: {self.joint_names[j]} changes at " \
                   f"{change[j]:.2f} rad/s^2 (limit {c.max_joint_acceleration:g} rad/s^2)"
        # Where each joint would come to rest if stopped after this period at stop_acceleration.
        rest = q + qdot * self.period + qdot * np.abs(qdot) / (2.0 * c.stop_acceleration)
        high = (rest > self.upper - c.position_margin) & (qdot > 0)
        low = (rest < self.lower + c.position_margin) & (qdot < 0)
        if np.any(high | low):
            j = int(np.flatnonzero(high | low)[0])
            limit = self.upper[j] if high[j] else self.lower[j]
            return f"command leads out of the joint position limits: {self.joint_names[j]} at {q[j]:+.3f} rad " \
                   f"moving {qdot[j]:+.3f} rad/s would stop at {rest[j]:+.3f} rad (limit {limit:+.3f} rad, " \
                   f"margin {c.position_margin:g} rad)"
        self.previous_command = np.array(qdot, dtype=float)
        return None
