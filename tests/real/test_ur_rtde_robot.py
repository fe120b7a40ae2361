"""DualUR5eRobot against the ur-rtde stand-in backed by the lab: API, joints, units, force, stops."""

from __future__ import annotations

import inspect
import re
import subprocess
import sys
import time

import numpy as np
import pytest
import rtde_control
import rtde_receive

from harvest_qp.real.errors import RobotConnectionError
from harvest_qp.real.ur_rtde_robot import GRAVITY, DualUR5eRobot, tool_wrench
from harvest_qp.runtime.interface import RobotInterface
from tests.real.conftest import CAMERA_HOST, GRASP_HOST, ramp

REAL = {"control": rtde_control.RTDEControlInterface, "receive": rtde_receive.RTDEReceiveInterface}


def _parameters(doc: str) -> list[str]:
    """Parameter names of a pybind11 signature line ``name(self: ..., a: float = 0.5, ...) -> ...``."""
    inside = doc.strip().splitlines()[0].split("(", 1)[1].rsplit(") ->", 1)[0]
    return [p.split(":")[0].strip() for p in re.split(r",\s*(?![^\[]*\])", inside) if p.strip()][1:]


def test_adapter_calls_only_ur_rtde_methods_with_their_signatures(connect):
    """Every call the adapter made on the stand-in exists in the installed ur-rtde with that many arguments,
    and the stand-in's methods take ur-rtde's parameter names."""
    robot, cell = connect()
    robot.tare_force()
    ramp(robot, np.full(12, 0.05), 20)
    robot.stop()
    robot.close()
    assert cell.calls
    for _host, kind, name, args in cell.calls:
        real = getattr(REAL[kind], name, None)
        assert real is not None, f"{kind}.{name} is not a ur-rtde method"
        assert len(args) <= len(_parameters(real.__doc__)), (kind, name, args)
    for kind, stand_in in (("control", cell.RTDEControlInterface), ("receive", cell.RTDEReceiveInterface)):
        for name, method in vars(stand_in).items():
            if name.startswith("_") or not callable(method):
                continue
            expected = _parameters(getattr(REAL[kind], name).__doc__)
            assert list(inspect.signature(method).parameters)[1:] == expected, (kind, name)


def test_joint_order_units_and_clock(connect, lab):
    robot, cell = connect()
    assert isinstance(robot, RobotInterface)
    assert robot.control_period == 0.002 and robot.time == 0.0
    np.testing.assert_array_equal(robot.joint_positions(), lab.joint_positions())
    q0 = robot.joint_positions()
    qdot = np.zeros(12)
    qdot[11] = 0.2  # the grasping arm's wrist 3 [rad/s]
    ramp(robot, qdot, 150, accel=4.0)
    q1 = robot.joint_positions()
    moved = np.abs(q1 - q0) > 1e-3
    assert moved.tolist() == [False] * 11 + [True]
    assert robot.joint_velocities()[11] == pytest.approx(0.2, abs=0.01)  # [rad/s], not deg/s
    assert q1[11] - q0[11] == pytest.approx(0.2 * (150 * 0.002 - 0.05 / 2 - 0.002), abs=0.006)  # [rad]
    assert robot.time == pytest.approx(150 * 0.002)
    np.testing.assert_array_equal(robot.joint_positions(), lab.joint_positions())
    # speedJ every cycle on both arms with (6 joints, a, one period); the camera arm paces the loop.
    for host, joints in ((CAMERA_HOST, slice(0, 6)), (GRASP_HOST, slice(6, 12))):
        speedj = [c[3] for c in cell.calls if c[0] == host and c[2] == "speedJ"]
        assert len(speedj) == 150
        last = speedj[-1]
        assert len(last[0]) == 6 and last[0] == pytest.approx(list(qdot[joints])) and last[2] == 0.002
    assert cell.methods_called(CAMERA_HOST, "control").count("waitPeriod") == 150
    assert cell.methods_called(CAMERA_HOST, "control").count("initPeriod") == 151


def _untared_oracle(lab) -> tuple[np.ndarray, np.ndarray]:
    """Force and torque (about the flange) the tool applies to what it holds, world frame, from MuJoCo's
    wrist sensors: what the wrist applies to the tool rotated to the world, plus the tool's weight."""
    m, d = lab.model, lab.data
    ids = lab.scene.ids
    R = d.site_xmat[ids["ft_site"]].reshape(3, 3)
    f_adr, t_adr = m.sensor_adr[ids["ft_force"]], m.sensor_adr[ids["ft_torque"]]
    mass = m.body_mass[ids["grasp_tool"]]
    com = R @ m.body_ipos[ids["grasp_tool"]]
    weight = mass * np.asarray(m.opt.gravity)
    return R @ d.sensordata[f_adr:f_adr + 3] + weight, R @ d.sensordata[t_adr:t_adr + 3] + np.cross(com, weight)


@pytest.mark.parametrize("frame", ["base", "tool"])
def test_wrist_force_world_frame_weight_and_tare(connect, lab, frame):
    robot, cell = connect(frame)
    qdot = np.zeros(12)
    qdot[9:12] = [0.15, -0.2, 0.4]  # turn the grasping wrist: the flange frame rotates under the reading
    command = None
    for _ in range(3):
        command = ramp(robot, qdot, 60, accel=3.0, start=command)
        force, torque = robot.wrist_wrench()
        expected_force, expected_torque = _untared_oracle(lab)
        np.testing.assert_allclose(force, expected_force, atol=1e-9)
        np.testing.assert_allclose(torque, expected_torque, atol=1e-9)
        np.testing.assert_allclose(robot.wrist_force(), expected_force, atol=1e-9)
    np.testing.assert_allclose(robot.wrist_force(), lab.wrist_force(), atol=1e-9)  # the lab's own reading
    # Tare: zeroFtSensor once; then the reading is the change since the tare, in the world frame,
    # while the flange keeps turning (the sensor's zero lives in the sensor frame).
    at_tare = _untared_oracle(lab)[0]
    robot.tare_force()
    assert cell.methods_called(GRASP_HOST, "control").count("zeroFtSensor") == 1
    assert not cell.methods_called(CAMERA_HOST, "control").count("zeroFtSensor")
    for _ in range(3):
        command = ramp(robot, -qdot, 60, accel=3.0, start=command)
        np.testing.assert_allclose(robot.wrist_force(), _untared_oracle(lab)[0] - at_tare, atol=1e-9)


def test_tool_wrench_hand_computed():
    """A 0.6 kg tool, centre of mass 0.06 m along the flange z, holding 1 kg 0.1 m along it; flange pointing
    along world +x, the reading in the base frame (base rotated 180 deg about z)."""
    R_sensor = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # flange z -> world +x
    R_base = np.diag([-1.0, -1.0, 1.0])
    g = 9.81
    # Outside the tool: its own weight and the held 1 kg pull down; torques about the flange origin.
    external_world = np.array([0.0, 0.0, -1.6 * g])
    torque_world = np.cross([0.06, 0, 0], [0, 0, -0.6 * g]) + np.cross([0.1, 0, 0], [0, 0, -1.0 * g])
    reading = np.concatenate([R_base.T @ external_world, R_base.T @ torque_world])
    force, torque = tool_wrench(reading, R_base, R_sensor, np.zeros(6), 0.6, np.array([0.0, 0.0, 0.06]))
    np.testing.assert_allclose(force, [0.0, 0.0, 1.0 * g], atol=1e-12)  # it holds the 1 kg up
    np.testing.assert_allclose(torque, [0.0, -0.1 * g, 0.0], atol=1e-12)
    assert GRAVITY[2] == -g


def test_stop_and_close_on_both_arms(connect, lab):
    robot, cell = connect()
    ramp(robot, np.full(12, 0.1) * np.tile([1, -1, 1, -1, 1, 1], 2), 100, accel=3.0)
    robot.stop()
    assert np.abs(lab.joint_velocities()).max() < 1e-2
    for host in (CAMERA_HOST, GRASP_HOST):
        stops = [c[3] for c in cell.calls if c[0] == host and c[2] == "speedStop"]
        assert stops and stops[-1][0] <= robot.cell.watchdog.stop_acceleration
    robot.close()
    robot.close()  # idempotent
    for host in (CAMERA_HOST, GRASP_HOST):
        calls = cell.methods_called(host, "control")
        assert calls[-3:] == ["speedStop", "stopScript", "disconnect"]
    assert cell.script == [False, False]
    with pytest.raises(RobotConnectionError):
        robot.step()


def test_read_only_connection_reads_and_starts_no_control_script(lab):
    """A read-only robot (the dry run) reads the joints and force but never opens RTDEControlInterface, whose
    constructor uploads and starts the control script on the arm; step() refuses with the package's error."""
    from harvest_qp.real.cell import CellConfig
    from tests.real.standin import LabCell

    lab.reset()
    cell = LabCell(lab, (CAMERA_HOST, GRASP_HOST))
    robot = DualUR5eRobot(CAMERA_HOST, GRASP_HOST, cell=CellConfig(), rtde=cell, clock=cell.clock, read_only=True)
    q0 = lab.joint_positions()
    np.testing.assert_array_equal(robot.joint_positions(), q0)
    assert np.all(np.isfinite(robot.wrist_force()))
    robot.tare_force()  # software tare only: zeroFtSensor is a control call
    robot.send_joint_velocities(np.full(12, 0.1))
    with pytest.raises(RobotConnectionError, match="read-only"):
        robot.step()
    robot.stop()
    robot.close()
    assert cell.methods_called(kind="control") == []
    assert cell.script == [False, False]
    np.testing.assert_array_equal(lab.joint_positions(), q0)  # the lab never advanced: nothing was sent
    with pytest.raises(AttributeError):
        robot.read_only = False  # cannot be turned into a commanding connection


def test_read_only_connection_to_a_powered_off_arm_says_power():
    """The watchdog's state check for a read-only connection needs power, not our (never started) script."""
    from harvest_qp.real.watchdog import Watchdog, WatchdogConfig

    dog = Watchdog(WatchdogConfig(), 0.002, -np.ones(12), np.ones(12), [f"j{i}" for i in range(12)])
    assert dog.robot_state("camera arm", 1, 0b01, script=False) is None  # powered, no program: fine read-only
    assert "not powered on" in dog.robot_state("camera arm", 1, 0b00, script=False)
    assert "control script is not running" in dog.robot_state("camera arm", 1, 0b01)


def test_unreachable_robot_is_one_line_naming_the_address():
    """Nothing listens on 127.0.0.1's RTDE port here: refused at once, by the probe and by ur-rtde itself."""
    t0 = time.monotonic()
    with pytest.raises(RobotConnectionError, match=r"127\.0\.0\.1") as probe:
        DualUR5eRobot("127.0.0.1", "127.0.0.2")
    with pytest.raises(RobotConnectionError, match=r"127\.0\.0\.1") as direct:
        DualUR5eRobot("127.0.0.1", "127.0.0.2", probe_timeout=None)
    assert time.monotonic() - t0 < 5.0
    assert "\n" not in str(probe.value) and "\n" not in str(direct.value)


def test_cli_unreachable_robot_exit_code_and_one_line(tmp_path):
    """The command line: exit code 2, one line on stderr naming the address, no traceback, within seconds."""
    t0 = time.monotonic()
    done = subprocess.run(
        [sys.executable, "-m", "harvest_qp.cli", "run", "tasks/paper.yaml", "--robot", "ur", "--camera-arm",
         "127.0.0.1", "--grasp-arm", "127.0.0.3", "--camera", "none", "--dry-run"],
        capture_output=True, text=True, timeout=120, cwd=str(__import__("pathlib").Path(__file__).parents[2]))
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "127.0.0.1" in lines[0] and "Traceback" not in done.stderr
    assert time.monotonic() - t0 < 60  # mostly the interpreter's imports
