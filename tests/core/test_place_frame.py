"""``Configuration.place_frame`` / ``dual_ur5e(camera_in_flange=...)``: a calibrated camera frame.

A real cell's camera sits where its hand-eye calibration says, not where the robot description
put it. The moved frame is checked against MuJoCo's own kinematics of the flange (an independent
model of the same robot) times the transform, and its Jacobian by finite differences.
"""

import mujoco
import numpy as np
import pinocchio as pin
import pytest

from harvest_qp import Configuration
from harvest_qp.exceptions import InvalidInputError, UnknownFrameError
from harvest_qp.robot import paths
from harvest_qp.robot.description import HOME_Q, camera_mount
from harvest_qp.tasks import FrameTwistTask

H = 1e-6


def _calibrated(rng) -> np.ndarray:
    """A camera 1-2 cm and a few degrees away from the description's mount."""
    X = camera_mount()
    X[:3, :3] = pin.rpy.rpyToMatrix(*rng.uniform(-0.08, 0.08, 3)) @ X[:3, :3]
    X[:3, 3] += rng.uniform(-0.02, 0.02, 3)
    return X


def test_camera_in_flange_puts_the_camera_frame_at_mujocos_flange_times_the_calibration(rng):
    mj = mujoco.MjModel.from_xml_path(str(paths.scene_path()))
    md = mujoco.MjData(mj)
    flange = mj.body("cam_tool").id
    for _ in range(10):
        X = _calibrated(rng)
        q = HOME_Q + rng.normal(0.0, 0.5, 12)
        configuration = Configuration.dual_ur5e(q, camera_in_flange=X)
        md.qpos[:12] = q
        mujoco.mj_kinematics(mj, md)
        T_flange = np.eye(4)
        T_flange[:3, :3], T_flange[:3, 3] = md.xmat[flange].reshape(3, 3), md.xpos[flange]
        np.testing.assert_allclose(configuration.frame_pose("camera").homogeneous, T_flange @ X, atol=1e-9)
        # the description's mount is what None keeps
        site = mj.site("camera").id
        described = Configuration.dual_ur5e(q)
        np.testing.assert_allclose(described.frame_position("camera"), md.site_xpos[site], atol=1e-9)


def test_the_moved_frames_jacobian_matches_finite_differences(rng):
    X = _calibrated(rng)
    configuration = Configuration.dual_ur5e(camera_in_flange=X)
    task = FrameTwistTask("camera")
    for _ in range(5):
        q = HOME_Q + rng.normal(0.0, 0.4, 12)
        qdot = rng.standard_normal(12)
        configuration.update(q - H * qdot)
        a = configuration.frame_pose("camera")
        configuration.update(q + H * qdot)
        b = configuration.frame_pose("camera")
        configuration.update(q)
        J, _ = task.compute(configuration, 0.002)
        twist = np.concatenate([(b.translation - a.translation) / (2 * H),
                                pin.log3(b.rotation @ a.rotation.T) / (2 * H)])
        np.testing.assert_allclose(J @ qdot, twist, atol=1e-7)


def test_place_frame_recomputes_the_pose_at_the_current_q():
    configuration = Configuration.dual_ur5e()
    X = camera_mount()
    X[:3, 3] += (0.0, 0.0, 0.01)
    before = configuration.frame_position("camera")
    configuration.place_frame("camera", "cam_flange", X)
    z = configuration.frame_rotation("cam_flange")[:, 2]
    np.testing.assert_allclose(configuration.frame_position("camera") - before, 0.01 * z, atol=1e-12)


@pytest.mark.parametrize(
    ("pose", "words"),
    [
        (np.eye(3), r"shape \(4, 4\)"),
        (np.diag([1.0, 1.0, 2.0, 1.0]), "rotation matrix"),
        (np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1.0]]), "0 0 0 1"),
        (np.full((4, 4), np.nan), "finite"),
    ],
)
def test_a_pose_that_is_not_a_rigid_transform_is_refused_with_its_value(pose, words):
    with pytest.raises(InvalidInputError, match=words):
        Configuration.dual_ur5e(camera_in_flange=pose)


def test_frames_on_different_joints_or_unknown_names_are_refused():
    configuration = Configuration.dual_ur5e()
    with pytest.raises(InvalidInputError, match="different joints"):
        configuration.place_frame("camera", "gripper", np.eye(4))
    with pytest.raises(UnknownFrameError, match="camara"):
        configuration.place_frame("camara", "cam_flange", np.eye(4))
    with pytest.raises(InvalidInputError, match="another frame than 'camera'"):
        configuration.place_frame("camera", "camera", np.eye(4))


def test_placing_again_replaces_the_pose_and_a_last_row_within_round_off_is_taken():
    configuration = Configuration.dual_ur5e()
    X = camera_mount()
    X[:3, 3] += (0.0, 0.0, 0.01)
    configuration.place_frame("camera", "cam_flange", X)
    configuration.place_frame("camera", "cam_flange", X)
    flange = configuration.frame_pose("cam_flange").homogeneous
    np.testing.assert_allclose(configuration.frame_pose("camera").homogeneous, flange @ X, atol=1e-12)
    X[3, 3] += 1e-9  # a file's round-off
    configuration.place_frame("camera", "cam_flange", X)
    np.testing.assert_allclose(configuration.frame_pose("camera").homogeneous[3], [0, 0, 0, 1], atol=0)
