"""The calibrated camera: the clouds and the controller's camera task use one frame.

The cell's hand-eye calibration says where the camera really is on the camera arm's flange.
DualUR5eRobot expresses every cloud with it; the controller must drive and reason about the
same frame, or the camera centres the robot description's axis while the stem is seen through
the real one. Oracle: MuJoCo's kinematics of the flange (the lab behind the ur-rtde stand-in)
times the calibration.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pinocchio as pin
import pytest

from harvest_qp.config.settings import load_settings
from harvest_qp.real.calibration import MAX_HAND_EYE_DISTANCE, Calibration
from harvest_qp.real.cell import CellConfig
from harvest_qp.real.episode import run_real_episode
from harvest_qp.real.errors import CalibrationError
from harvest_qp.real.ur_rtde_robot import DualUR5eRobot
from harvest_qp.real.watchdog import WatchdogConfig
from harvest_qp.robot.description import camera_mount
from harvest_qp.robot.paths import tasks_dir
from tests.real.conftest import CAMERA_HOST, GRASP_HOST
from tests.real.standin import LabCell


def _off_mount() -> np.ndarray:
    """A camera 15 mm and 4 deg away from the description's mount (a typical bracket's tolerance)."""
    X = camera_mount()
    X[:3, :3] = pin.rpy.rpyToMatrix(0.04, -0.05, 0.03) @ X[:3, :3]
    X[:3, 3] += (0.010, -0.008, 0.008)
    return X


def _flange_times(lab, q: np.ndarray, X: np.ndarray) -> np.ndarray:
    """MuJoCo's camera-arm flange pose at ``q`` times ``X``."""
    m = lab.model
    data = mujoco.MjData(m)
    data.qpos[:12] = q
    mujoco.mj_kinematics(m, data)
    body = m.body("cam_tool").id
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = data.xmat[body].reshape(3, 3), data.xpos[body]
    return T @ X


def test_the_real_episode_drives_the_calibrated_camera_frame(lab, tmp_path):
    """Bug caught: the controller built on the description's camera frame while the clouds use the
    calibration (15 mm / 4 deg apart here)."""
    lab.reset()
    cell = LabCell(lab, (CAMERA_HOST, GRASP_HOST))
    X = _off_mount()
    robot = DualUR5eRobot(CAMERA_HOST, GRASP_HOST, cell=CellConfig(), hand_eye=X, rtde=cell, clock=cell.clock)
    try:
        settings = load_settings(tasks_dir() / "paper.yaml", ["qp.environment=[]"])
        run_real_episode(settings, robot, duration=0.02, out_dir=tmp_path, figures=False)
        expected_cloud_frame = robot.camera_pose_at(robot.time)
    finally:
        robot.close()
    log = dict(np.load(tmp_path / "episode.npz"))
    q, p_c, z_c, x_c = log["q"][-1], log["value/p_c"][-1], log["value/z_c"][-1], log["value/x_c"][-1]
    T = _flange_times(lab, q, X)
    np.testing.assert_allclose(p_c, T[:3, 3], atol=1e-9)
    np.testing.assert_allclose(z_c, T[:3, 2], atol=1e-9)
    np.testing.assert_allclose(x_c, T[:3, 0], atol=1e-9)
    # the frame the clouds are expressed with (the robot stood still after the stop: same q)
    np.testing.assert_allclose(expected_cloud_frame, _flange_times(lab, lab.joint_positions(), X), atol=1e-9)
    # The roll turns the blade (fixed to the tool: MuJoCo's cam_tool y axis), not the calibrated x_c,
    # across the stem direction (no camera here: the gripper's y axis, MuJoCo's gripper site).
    blade = _flange_times(lab, q, np.eye(4))[:3, 1]
    data = mujoco.MjData(lab.model)
    data.qpos[:12] = q
    mujoco.mj_kinematics(lab.model, data)
    u = data.site_xmat[lab.model.site("gripper").id].reshape(3, 3)[:, 1]

    def phi(y):  # the roll law's angle (docs: eq. of harvest_qp.references.roll), y projected about z_c
        y = y - (y @ z_c) * z_c
        y /= np.linalg.norm(y)
        d = u - (u @ z_c) * z_c
        return (np.arctan2(np.cross(y, d) @ z_c, y @ d) + np.pi / 2) % np.pi - np.pi / 2

    assert log["value/roll_error"][-1] == pytest.approx(phi(blade), abs=1e-9)
    assert abs(phi(blade) - phi(T[:3, 1])) > np.radians(1.0)  # the calibrated y_c is 1.7 deg off here


def test_without_a_calibration_the_robot_uses_the_descriptions_mount(lab):
    lab.reset()
    cell = LabCell(lab, (CAMERA_HOST, GRASP_HOST))
    robot = DualUR5eRobot(CAMERA_HOST, GRASP_HOST, cell=CellConfig(), rtde=cell, clock=cell.clock)
    try:
        T = robot.camera_pose_at(robot.time)
    finally:
        robot.close()
    site = lab.model.site("camera").id
    np.testing.assert_allclose(T[:3, 3], lab.data.site_xpos[site], atol=1e-9)
    np.testing.assert_allclose(T[:3, :3], lab.data.site_xmat[site].reshape(3, 3), atol=1e-9)


@pytest.mark.parametrize("where", ["calibration", "robot"])
def test_a_hand_eye_far_from_the_flange_is_refused_naming_the_distance(lab, where):
    """A file written in millimetres (65 m from the flange) must not reach the controller."""
    X = camera_mount()
    X[:3, 3] = (0.0, 65.0, 45.0)
    with pytest.raises(CalibrationError, match=rf"79\.0569 m from the flange.*within {MAX_HAND_EYE_DISTANCE} m"):
        if where == "calibration":
            Calibration(X)
        else:
            cell = LabCell(lab, (CAMERA_HOST, GRASP_HOST))
            DualUR5eRobot(CAMERA_HOST, GRASP_HOST, cell=CellConfig(), hand_eye=X, rtde=cell, clock=cell.clock)


def test_a_stop_harder_than_the_cells_acceleration_limit_is_refused():
    with pytest.raises(Exception, match=r"stop_acceleration \(12.0 rad/s\^2\) must not exceed.*10.0"):
        WatchdogConfig(stop_acceleration=12.0, max_joint_acceleration=10.0)
    assert WatchdogConfig(stop_acceleration=10.0, max_joint_acceleration=10.0).stop_acceleration == 10.0
