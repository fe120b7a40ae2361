"""Hand-eye and base-to-base calibration on rendered ChArUco views through a known camera."""

from __future__ import annotations

import cv2
import numpy as np
import pinocchio as pin
import pytest
import yaml

from harvest_qp.configuration import Configuration
from harvest_qp.real.calibration import (
    Board,
    Calibration,
    calibrate_folder,
    detect_board,
    flange_poses,
    load_calibration,
    pose_error,
    save_calibration,
    solve_bases,
)
from harvest_qp.real.errors import CalibrationError
from harvest_qp.robot.description import CAMERA_ARM, GRASP_ARM, HOME_Q, mount_transform

W, H = 848, 480
K = np.array([[615.0, 0.0, 424.0], [0.0, 615.0, 240.0], [0.0, 0.0, 1.0]])  # a D415 colour stream's
BOARD = Board(squares=(7, 5), square=0.04, marker=0.03)
PPS, MARGIN = 60, 40  # board image: pixels per square, white margin [px]


def _rotation(axis, angle_deg: float) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(axis, float) / np.linalg.norm(axis) * np.radians(angle_deg))[0]


def _pose(R, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _look_at(position, target, roll_deg: float = 0.0) -> np.ndarray:
    z = (np.asarray(target) - position) / np.linalg.norm(np.asarray(target) - position)
    x = np.cross([0.0, 0.0, -1.0], z)
    x /= np.linalg.norm(x)
    R = np.column_stack([x, np.cross(z, x), z]) @ _rotation([0, 0, 1], roll_deg)
    return _pose(R, position)


def render(board_in_camera: np.ndarray, supersample: int = 3) -> np.ndarray:
    """The board seen by the pinhole K from ``board_in_camera`` (grey image, OpenCV pixel centres), drawn at
    ``supersample`` times the resolution and averaged down, as a sensor integrates over its pixels."""
    cols, rows = BOARD.squares
    image = BOARD.image(PPS, MARGIN)
    assert image.shape == (rows * PPS + 2 * MARGIN, cols * PPS + 2 * MARGIN)
    s = BOARD.square / PPS
    to_metres = np.array([[s, 0.0, (0.5 - MARGIN) * s], [0.0, s, (0.5 - MARGIN) * s], [0.0, 0.0, 1.0]])
    n = supersample
    fine = np.array([[n, 0.0, (n - 1) / 2], [0.0, n, (n - 1) / 2], [0.0, 0.0, 1.0]])  # pixel centres of the fine grid
    R, t = board_in_camera[:3, :3], board_in_camera[:3, 3]
    homography = fine @ K @ np.column_stack([R[:, 0], R[:, 1], t]) @ to_metres
    drawn = cv2.warpPerspective(image, homography, (n * W, n * H), flags=cv2.INTER_LINEAR, borderValue=170)
    return cv2.resize(drawn, (W, H), interpolation=cv2.INTER_AREA)


def _ik(target: np.ndarray, q: np.ndarray) -> np.ndarray | None:
    """Camera-arm joints putting its flange at the world pose ``target`` (Newton steps on the description)."""
    configuration = Configuration.dual_ur5e(q)
    q = q.copy()
    for _ in range(100):
        configuration.update(q)
        pose = configuration.frame_pose(CAMERA_ARM + "flange")
        error = np.concatenate([target[:3, 3] - pose.translation, pin.log3(target[:3, :3] @ pose.rotation.T)])
        if np.linalg.norm(error) < 1e-10:
            return q
        J = configuration.frame_jacobian(CAMERA_ARM + "flange")[:, :6]
        q[:6] += np.linalg.solve(J, error)
    return None


#: The true hand-eye transform: the description's camera mount, off by 6 mm and 2 degrees.
TRUE_HAND_EYE = _pose(_rotation([0.3, -1.0, 0.5], 2.0), [0.004, 0.069, 0.049])


def test_detect_board_pose_through_rendering():
    truth = _look_at(np.array([0.05, -0.02, -0.5]), [0.12, 0.08, 0.0], roll_deg=10)
    board_in_camera = np.linalg.inv(truth)  # the camera in the board frame -> the board in the camera frame
    found = detect_board(render(board_in_camera), BOARD, K)
    assert found is not None
    position, angle = pose_error(found, board_in_camera)
    assert position < 1e-3 and angle < 0.2, (position, angle)
    assert detect_board(np.full((H, W), 170, np.uint8), BOARD, K) is None


def _hand_eye_views(tmp_path, n: int = 15, seed: int = 3) -> list:
    """Views of a board fixed 0.45 m in front of the home camera, from camera poses tilted 15-35 deg about
    varied axes and rolled up to 60 deg (the procedure's advice), the camera arm's joints by inverse
    kinematics; written as views.yaml and images, as `harvest-qp calibrate capture` writes them."""
    rng = np.random.default_rng(seed)
    home = Configuration.dual_ur5e(HOME_Q)
    pose = home.frame_pose(CAMERA_ARM + "flange")
    camera_home = _pose(pose.rotation, pose.translation) @ TRUE_HAND_EYE
    board = camera_home @ _pose(_rotation([0, 0, 1], 5.0), [-0.14, -0.1, 0.45])  # world frame
    centre = board[:3, :3] @ [0.14, 0.1, 0.0] + board[:3, 3]
    normal = board[:3, 2]
    views = []
    while len(views) < n:
        axis = np.cross(normal, rng.normal(size=3))
        direction = _rotation(axis, rng.uniform(15, 35)) @ -normal  # from the board towards the camera
        camera = _look_at(centre + rng.uniform(0.4, 0.5) * direction, centre + rng.uniform(-0.02, 0.02, 3),
                          rng.uniform(-60, 60))
        q = _ik(camera @ np.linalg.inv(TRUE_HAND_EYE), HOME_Q)
        if q is None or np.any(np.abs(q - HOME_Q) > 2.0):
            continue
        configuration = Configuration.dual_ur5e(q)
        flange = configuration.frame_pose(CAMERA_ARM + "flange")
        board_in_camera = np.linalg.inv(_pose(flange.rotation, flange.translation) @ TRUE_HAND_EYE) @ board
        name = f"view_{len(views):02d}.png"
        cv2.imwrite(str(tmp_path / name), render(board_in_camera))
        views.append({"image": name, "kind": "hand_eye", "q": [float(x) for x in q]})
    data = {"board": BOARD.as_dict(), "intrinsics": {"K": K.tolist(), "dist": [0.0] * 5}, "views": views}
    (tmp_path / "views.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return views


def test_hand_eye_from_a_views_folder_recovers_the_transform(tmp_path):
    _hand_eye_views(tmp_path)
    calibration = calibrate_folder(tmp_path)
    position, angle = pose_error(calibration.hand_eye, TRUE_HAND_EYE)
    assert position < 2e-3 and angle < 0.5, (position, angle)
    assert calibration.info["hand_eye_views"] >= 10 and calibration.grasp_base_in_camera_base is None
    # Written and read back as YAML (safe_dump / safe_load), as the cell file refers to it.
    path = save_calibration(tmp_path / "calibration.yaml", calibration)
    again = load_calibration(path)
    np.testing.assert_allclose(again.hand_eye, calibration.hand_eye, atol=1e-12)
    assert yaml.safe_load(path.read_text())["format"] == "harvest_qp calibration 1"


def test_base_to_base_from_a_board_on_the_grasping_flange():
    """The grasping base truly 4 mm and 0.4 deg off the description: the solve finds it, the check reports it."""
    rng = np.random.default_rng(7)
    described = np.linalg.inv(mount_transform(CAMERA_ARM)) @ mount_transform(GRASP_ARM)
    true_base = described @ _pose(_rotation([0.2, 0.5, 1.0], 0.4), [0.003, -0.002, 0.0015])
    board_on_flange = _pose(_rotation([1, 0, 0], 180.0), [0.0, 0.0, 0.12])  # facing out of the flange
    camera_flanges, boards, grasp_flanges = [], [], []
    for _ in range(14):
        q = HOME_Q.copy()
        q[6:9] += rng.uniform(-0.05, 0.05, 3)
        q[9:12] += rng.uniform(-0.35, 0.35, 3)
        _, grasp_flange = flange_poses(q)
        board = true_base @ grasp_flange @ board_on_flange  # in the camera-arm base
        # The camera arm looks at the board's centre from 0.4-0.5 m, tilted up to 30 deg from its normal.
        centre, normal = board[:3, :3] @ [0.14, 0.1, 0.0] + board[:3, 3], board[:3, 2]
        direction = _rotation(np.cross(normal, rng.normal(size=3)), rng.uniform(0, 30)) @ -normal
        camera = _look_at(centre + rng.uniform(0.4, 0.5) * direction, centre, rng.uniform(-40, 40))
        found = detect_board(render(np.linalg.inv(camera) @ board), BOARD, K)
        assert found is not None
        camera_flanges.append(camera @ np.linalg.inv(TRUE_HAND_EYE))
        boards.append(found)
        grasp_flanges.append(grasp_flange)
    base, board_in_flange = solve_bases(camera_flanges, TRUE_HAND_EYE, boards, grasp_flanges)
    position, angle = pose_error(base, true_base)
    assert position < 2e-3 and angle < 0.5, (position, angle)
    assert pose_error(board_in_flange, board_on_flange)[0] < 2e-3
    discrepancy = Calibration(TRUE_HAND_EYE, base).base_discrepancy()
    assert discrepancy[0] == pytest.approx(np.linalg.norm([0.003, -0.002, 0.0015]), abs=2e-3)
    assert discrepancy[1] == pytest.approx(0.4, abs=0.5)


def test_bad_calibration_files_are_one_line_errors(tmp_path):
    with pytest.raises(CalibrationError, match="cannot read the calibration file"):
        load_calibration(tmp_path / "missing.yaml")
    (tmp_path / "other.yaml").write_text("a: 1\n")
    with pytest.raises(CalibrationError, match="not a harvest_qp calibration file"):
        load_calibration(tmp_path / "other.yaml")
    (tmp_path / "skew.yaml").write_text("format: harvest_qp calibration 1\nhand_eye: [[1,0,0,0],[0,2,0,0],[0,0,1,0],"
                                        "[0,0,0,1]]\n")
    with pytest.raises(CalibrationError, match="not a rigid transform"):
        load_calibration(tmp_path / "skew.yaml")
    with pytest.raises(CalibrationError, match="3 or more"):
        (tmp_path / "views.yaml").write_text(yaml.safe_dump(
            {"board": BOARD.as_dict(), "intrinsics": {"K": K.tolist()}, "views": []}))
        calibrate_folder(tmp_path)
