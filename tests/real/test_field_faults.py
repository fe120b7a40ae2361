"""Faults an independent audit of the field side found, through the public API, on the auditor's own
ur-rtde fake (tests/real/audit_fake.py, no MuJoCo): each test failed on the code before its fix.

* Ctrl-C or any other failure while the SECOND arm connects: the first arm's control script must
  still get speedStop and stopScript (the issue: every exit path).
* The same address for both arms: refused (both arms' commands would go to one robot).
* An episode without a camera (``--camera none`` outside ``--dry-run``): refused before anything
  connects (the arms would move with no perception).
* A camera that stops delivering frames while the arms move: the watchdog stops both arms.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from harvest_qp.exceptions import HarvestQPError, InvalidInputError
from harvest_qp.real.episode import run_real
from harvest_qp.real.errors import RobotConnectionError, WatchdogError
from harvest_qp.real.ur_rtde_robot import DualUR5eRobot
from tests.real.audit_fake import FakeCell

A, B = "10.9.0.1", "10.9.0.2"
PAPER = Path(__file__).resolve().parents[2] / "tasks" / "paper.yaml"


@pytest.mark.parametrize("exc", [KeyboardInterrupt(), TimeoutError("timed out"), OSError("no route"),
                                 ValueError("bad"), RuntimeError("Could not connect")],
                         ids=lambda e: type(e).__name__)
def test_a_failure_connecting_the_second_arm_stops_the_first(exc):
    fake = FakeCell((A, B))
    fake.fail_connect[B] = exc
    with pytest.raises(RobotConnectionError if isinstance(exc, RuntimeError) else type(exc)):
        DualUR5eRobot(A, B, rtde=fake, clock=fake.clock)
    assert fake.called(A, "speedStop") and fake.called(A, "stopScript"), "camera arm left with its script running"


def test_the_same_address_for_both_arms_is_refused():
    fake = FakeCell((A, B))
    with pytest.raises(InvalidInputError, match="same address '10.9.0.1'"):
        DualUR5eRobot(A, A, rtde=fake, clock=fake.clock)
    assert not fake.called(A, "speedJ")


def test_an_episode_without_a_camera_is_refused_before_anything_moves(tmp_path):
    fake = FakeCell((A, B))
    with pytest.raises(HarvestQPError, match="needs the camera"):
        run_real(PAPER, camera_arm=A, grasp_arm=B, camera=None, out=tmp_path, duration=0.05, figures=False,
                 rtde=fake, clock=fake.clock)
    assert not fake.called(A, "speedJ") and not fake.called(B, "speedJ")


class _SilentFrames:
    """A RealSense frame source that never delivers a frame and never raises (a USB stall)."""

    def try_wait_for_frames(self, timeout_ms):
        time.sleep(min(timeout_ms, 50) / 1e3)
        return False, None

    def stop(self):
        pass


def test_a_camera_that_stops_delivering_stops_the_arms():
    """No camera frame for more than watchdog.camera_timeout (1 s) while the arms move: both arms
    stop within the deceleration limit and the reason names the camera (an audit found a stalled
    stream never noticed: the episode went on with the last cloud)."""
    from harvest_qp.real.realsense import RealSenseSource

    fake = FakeCell((A, B))
    robot = DualUR5eRobot(A, B, rtde=fake, clock=fake.clock, camera=RealSenseSource(_SilentFrames()))
    command = np.zeros(12)
    try:
        with pytest.raises(WatchdogError, match="camera: no new frame"):
            for _ in range(600):  # 1.2 s of robot time
                assert robot.camera_cloud() is None
                command = command + np.clip(0.05 - command, -0.004, 0.004)  # ramp within 2 rad/s^2
                robot.send_joint_velocities(command)
                robot.step()
        assert fake.clock() > 1.0  # not before the timeout
        assert fake.called(A, "speedStop") and fake.called(B, "speedStop")
    finally:
        robot.close()


def test_an_arm_that_never_answers_is_a_one_line_error_within_the_timeout():
    """An address that accepts the connection but never answers (ur-rtde's constructor blocks without a
    limit: an audit saw it hang for 200 s) is a RobotConnectionError naming the address after
    connect_timeout, and the arm that did connect is stopped."""
    import threading

    fake = FakeCell((A, B))
    never = threading.Event()
    real_receive = fake.RTDEReceiveInterface

    def blocking_receive(host, *args):
        if host == B:
            never.wait(30)  # released at the end of the test
        return real_receive(host, *args)

    fake.RTDEReceiveInterface = blocking_receive
    start = time.monotonic()
    try:
        with pytest.raises(RobotConnectionError, match=r"grasping arm at 10\.9\.0\.2 accepted the connection but did "
                                                       r"not answer within 0\.5 s"):
            DualUR5eRobot(A, B, rtde=fake, clock=fake.clock, connect_timeout=0.5)
        assert time.monotonic() - start < 3.0
        assert fake.called(A, "stopScript")
    finally:
        never.set()
