"""The watchdog through DualUR5eRobot on the stand-in: every fault stops both arms with a reason."""

from __future__ import annotations

import numpy as np
import pytest

from harvest_qp.configuration import Configuration
from harvest_qp.exceptions import ConfigError
from harvest_qp.real.errors import WatchdogError
from harvest_qp.real.watchdog import Watchdog, WatchdogConfig
from harvest_qp.robot.description import joint_names
from tests.real.conftest import CAMERA_HOST, GRASP_HOST, ramp

MOTION = np.array([0.1, -0.1, 0.1, 0.1, -0.1, 0.2, 0.05, 0.05, -0.05, 0.1, 0.1, -0.2])


def _assert_both_stopped(robot, cell, lab, after: int) -> None:
    """speedStop at the watchdog's deceleration on both arms since call ``after``; the arms come to rest
    without a faster change of velocity than that deceleration allows."""
    a = robot.cell.watchdog.stop_acceleration
    for host in (CAMERA_HOST, GRASP_HOST):
        stops = [c[3] for c in cell.calls[after:] if c[0] == host and c[2] == "speedStop"]
        assert stops and all(s[0] <= a for s in stops), (host, stops)
    v = [lab.joint_velocities()]
    for _ in range(int(1.0 / robot.control_period)):  # the robot's own ramp, as the runner's stop() waits
        cell.tick()
        v.append(lab.joint_velocities())
    v = np.array(v)
    assert np.abs(v[-1]).max() < 1e-2
    # The measured joints follow the speedStop ramp (a per period) within the lab servo's lag.
    assert np.abs(np.diff(v, axis=0)).max() / robot.control_period < 1.5 * a


def test_stale_data_stops_both_arms(connect, lab):
    robot, cell = connect()
    command = ramp(robot, MOTION, 60, accel=4.0)
    mark = len(cell.calls)
    cell.freeze(1, 100)
    with pytest.raises(WatchdogError, match=r"stale data from the grasping arm at 10\.0\.0\.2.*5 cycles"):
        ramp(robot, MOTION, 10, start=command)
    _assert_both_stopped(robot, cell, lab, mark)
    with pytest.raises(WatchdogError, match="stopped earlier"):  # no command goes out after a stop
        robot.step()


def test_stale_data_below_the_threshold_passes(connect):
    robot, cell = connect()
    command = ramp(robot, MOTION, 30, accel=4.0)
    cell.freeze(0, 3)  # 4 cycles without a new timestamp: under stale_cycles = 5
    ramp(robot, MOTION, 20, start=command)
    assert robot.tripped is None


def test_missed_period_stops_while_moving_not_at_rest(connect, lab):
    robot, cell = connect()
    cell.stall(1.0)  # at rest under a zero command: a long cycle (the first tick loading kernels) moves nothing
    robot.send_joint_velocities(np.zeros(12))
    robot.step()
    command = ramp(robot, MOTION, 40, accel=4.0)
    mark = len(cell.calls)
    cell.stall(0.025)  # > 10 periods
    with pytest.raises(WatchdogError, match=r"missed period: the control cycle took 25\.0 ms, more than 10 periods"):
        ramp(robot, MOTION, 1, start=command)
    assert not [c for c in cell.calls[mark:] if c[2] == "speedJ"]  # checked before the command went out
    _assert_both_stopped(robot, cell, lab, mark)


@pytest.mark.parametrize(("mode", "kind"), [(3, "protective stop"), (7, "emergency stop"), (5, "stop")])
def test_protective_and_emergency_stops(connect, lab, mode, kind):
    robot, cell = connect()
    command = ramp(robot, MOTION, 40, accel=4.0)
    mark = len(cell.calls)
    cell.protective_stop(0, mode)
    with pytest.raises(WatchdogError, match=rf"{kind} reported by the camera arm at 10\.0\.0\.1: safety mode {mode}"):
        ramp(robot, MOTION, 1, start=command)
    stops = [c[0] for c in cell.calls[mark:] if c[2] == "speedStop"]
    assert set(stops) == {CAMERA_HOST, GRASP_HOST}


def test_dropped_connection_stops_the_other_arm(connect, lab):
    robot, cell = connect()
    command = ramp(robot, MOTION, 40, accel=4.0)
    mark = len(cell.calls)
    cell.drop(1)
    with pytest.raises(WatchdogError, match=r"lost connection to the grasping arm at 10\.0\.0\.2"):
        ramp(robot, MOTION, 2, start=command)
    stopped = [c[0] for c in cell.calls[mark:] if c[2] == "speedStop"]
    assert CAMERA_HOST in stopped and GRASP_HOST in stopped  # tried on the lost arm too (it raises there)
    robot.close()
    assert cell.script[0] is False  # the camera arm's script was stopped although the other arm is gone


def test_commands_outside_the_limits(connect, lab):
    robot, cell = connect()
    q0 = lab.joint_positions()
    too_fast = np.zeros(12)
    too_fast[4] = 1.2
    with pytest.raises(WatchdogError, match=r"joint speed limit: cam_wrist_2_joint \+1\.056 rad/s \(limit 1\.05"):
        ramp(robot, too_fast, 400, accel=4.0)
    np.testing.assert_allclose(lab.joint_positions()[:4], q0[:4], atol=1e-3)
    robot, cell = connect()
    jump = np.zeros(12)
    jump[7] = 0.1  # 0.1 rad/s in one 2 ms period: 50 rad/s^2
    robot.send_joint_velocities(jump)
    with pytest.raises(WatchdogError, match=r"acceleration limit: grasp_shoulder_lift_joint changes at 50\.00"):
        robot.step()
    assert not [c for c in cell.calls if c[2] == "speedJ"]


def test_position_limit_by_stopping_distance():
    """Hand-computed: the elbow (limit pi) at 3.0 rad moving 0.5 rad/s would stop at
    3.0 + 0.5 * 0.002 + 0.25 / 8 = 3.03225 rad: inside pi - 0.02; at 3.1 rad it would not."""
    configuration = Configuration.dual_ur5e()
    watchdog = Watchdog(WatchdogConfig(max_joint_acceleration=1e3), 0.002, configuration.lower_limits,
                        configuration.upper_limits, joint_names())
    q = np.zeros(12)
    qdot = np.zeros(12)
    q[2], qdot[2] = 3.0, 0.5
    assert watchdog.command(q, qdot) is None
    q[2] = 3.1
    reason = watchdog.command(q, qdot)
    assert reason is not None and "cam_elbow_joint at +3.100 rad" in reason and "stop at +3.132 rad" in reason
    qdot[2] = -0.5  # moving away from the limit is allowed
    assert watchdog.command(q, qdot) is None


def test_watchdog_config_errors():
    with pytest.raises(ConfigError, match="watchdog.stale_cycles"):
        WatchdogConfig(stale_cycles=0)
    with pytest.raises(ConfigError, match="watchdog.stop_acceleration"):
        WatchdogConfig(stop_acceleration=-1.0)
