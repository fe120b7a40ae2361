"""The numbered examples run headless and do what their docstrings say.

Each example is loaded from ``examples/`` by path (they are scripts, not a package) and
run with a small step count; its outcome is checked with an oracle independent of the
library code it exercises.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pinocchio as pin

from harvest_qp.robot.paths import urdf_path

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _frame_position(q: np.ndarray, frame: str) -> np.ndarray:
    model = pin.buildModelFromUrdf(str(urdf_path()))
    data = model.createData()
    pin.framesForwardKinematics(model, data, q)
    return data.oMf[model.getFrameId(frame)].translation.copy()


def test_01_qp_two_tasks_moves_camera_along_x_and_holds_gripper():
    """Catches a wrong twist convention (local vs world axes, linear/angular order) or a
    task that does not reach the solver: the camera must move ~+x, the gripper must stay.

    Oracle: pinocchio forward kinematics of the final joint vector straight from the URDF,
    not the library's Configuration.
    """
    out = _load("01_qp_two_tasks").run(steps=500)
    q0 = _load("01_qp_two_tasks").Configuration.dual_ur5e().q
    moved = _frame_position(out["q"], "camera") - _frame_position(q0, "camera")
    assert 0.06 < moved[0] < 0.101, moved
    assert np.all(np.abs(moved[1:]) < 0.005), moved
    drift = _frame_position(out["q"], "gripper") - _frame_position(q0, "gripper")
    assert np.linalg.norm(drift) < 1e-3, drift
