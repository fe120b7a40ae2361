"""The cell file, and the calibrate command through the command line's own entry point."""

from __future__ import annotations

import numpy as np
import pytest

from harvest_qp.cli import main
from harvest_qp.exceptions import ConfigError
from harvest_qp.real.calibration import load_calibration, pose_error
from harvest_qp.real.cell import CellConfig, load_cell
from harvest_qp.robot.description import CAMERA_ARM, HOME_Q
from tests.real.test_calibration import TRUE_HAND_EYE, _hand_eye_views


def test_shipped_cell_file_and_its_example_calibration():
    cell = load_cell()
    assert cell == CellConfig(calibration=cell.calibration)  # the file states the defaults
    calibration = load_calibration(cell.calibration)
    # The example is the robot description's camera mount: the camera frame in the flange frame.
    from harvest_qp.configuration import Configuration

    configuration = Configuration.dual_ur5e(HOME_Q)
    flange, camera = configuration.frame_pose(CAMERA_ARM + "flange"), configuration.frame_pose("camera")
    expected = np.eye(4)
    expected[:3, :3] = flange.rotation.T @ camera.rotation
    expected[:3, 3] = flange.rotation.T @ (camera.translation - flange.translation)
    np.testing.assert_allclose(calibration.hand_eye, expected, atol=1e-9)


@pytest.mark.parametrize(("text", "message"), [
    ("force: {frame: sensor}\n", "force.frame must be 'base' or 'tool'"),
    ("watchdog: {stale_cycle: 3}\n", r"watchdog: unknown key\(s\) \['stale_cycle'\]"),
    ("speedj_acceleration: -1\n", "speedj_acceleration must be a number > 0"),
    ("[1, 2]\n", "must hold a mapping"),
])
def test_cell_file_errors_name_the_file_and_key(tmp_path, text, message):
    path = tmp_path / "cell.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message) as error:
        load_cell(path)
    assert str(path) in str(error.value) and "\n" not in str(error.value)


def test_run_with_a_bad_cell_file_is_exit_code_2(tmp_path, capsys):
    path = tmp_path / "cell.yaml"
    path.write_text("force: {tool_mass: -1}\n")
    code = main(["run", "tasks/paper.yaml", "--robot", "ur", "--camera-arm", "10.0.0.1", "--grasp-arm", "10.0.0.2",
                 "--cell", str(path), "--dry-run"])
    assert code == 2
    assert "force.tool_mass must be a number >= 0" in capsys.readouterr().err


def test_calibrate_board_and_solve_commands(tmp_path, capsys):
    assert main(["calibrate", "board", "--out", str(tmp_path / "board.png")]) == 0
    assert (tmp_path / "board.png").stat().st_size > 1000
    views = tmp_path / "views"
    views.mkdir()
    _hand_eye_views(views, n=12, seed=5)
    assert main(["calibrate", "solve", str(views), "--out", str(tmp_path / "calibration.yaml")]) == 0
    out = capsys.readouterr().out
    assert "hand_eye_views" in out and "hand_eye_board_spread_mm" in out
    position, angle = pose_error(load_calibration(tmp_path / "calibration.yaml").hand_eye, TRUE_HAND_EYE)
    assert position < 2e-3 and angle < 0.5
    assert main(["calibrate", "solve", str(tmp_path / "nothing"), "--out", str(tmp_path / "c.yaml")]) == 2
    assert "cannot read" in capsys.readouterr().err


def test_real_robot_options_are_errors_in_the_lab(capsys):
    assert main(["run", "tasks/paper.yaml", "--dry-run", "--camera-arm", "10.0.0.1"]) == 2
    assert "--camera-arm, --dry-run only apply with --robot ur" in capsys.readouterr().err
