"""Fixtures of the field-side tests: one lab robot per session behind the ur-rtde stand-in."""

from __future__ import annotations

import numpy as np
import pytest

from harvest_qp.real.cell import CellConfig, ForceConfig
from harvest_qp.real.ur_rtde_robot import DualUR5eRobot
from harvest_qp.robot.description import GRASP_TOOL
from harvest_qp.sim import SimRobot
from tests.real.standin import LabCell

CAMERA_HOST, GRASP_HOST = "10.0.0.1", "10.0.0.2"


@pytest.fixture(scope="session")
def lab() -> SimRobot:
    """The lab without its camera (the arms and the wrist sensor are what the stand-in serves)."""
    return SimRobot(camera=None)


@pytest.fixture
def connect(lab):
    """``connect(frame="base", **cell) -> (robot, cell)``: a fresh lab episode behind the stand-in."""
    opened = []

    def make(force_frame: str = "base", **cell_options) -> tuple[DualUR5eRobot, LabCell]:
        lab.reset()
        cell = LabCell(lab, (CAMERA_HOST, GRASP_HOST), force_frame=force_frame)
        force = ForceConfig(frame=force_frame, tool_mass=GRASP_TOOL.mass, tool_com=GRASP_TOOL.com)
        robot = DualUR5eRobot(CAMERA_HOST, GRASP_HOST, cell=CellConfig(force=force, **cell_options), rtde=cell,
                              clock=cell.clock)
        opened.append(robot)
        return robot, cell

    yield make
    for robot in opened:
        robot.close()


def ramp(robot: DualUR5eRobot, qdot: np.ndarray, ticks: int, accel: float = 2.0,
         start: np.ndarray | None = None) -> np.ndarray:
    """Command ``qdot`` [rad/s], reached at ``accel`` [rad/s^2] from ``start`` (default rest), for ``ticks``
    periods; returns the last command."""
    dt = robot.control_period
    current = np.zeros(12) if start is None else np.asarray(start, float)
    for _ in range(ticks):
        current = current + np.clip(qdot - current, -accel * dt, accel * dt)
        robot.send_joint_velocities(current)
        robot.step()
    return current
