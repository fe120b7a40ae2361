"""examples/04_custom_task_from_yaml.py: a task defined in user code, used from YAML, does its job."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pinocchio as pin

from harvest_qp.robot.paths import urdf_path

ROOT = Path(__file__).resolve().parents[2]


def _gaze_angle_deg(model, data, q, frame: str, target) -> tuple[float, np.ndarray]:
    pin.framesForwardKinematics(model, data, np.asarray(q))
    pose = data.oMf[model.getFrameId(frame)]
    d = np.asarray(target) - pose.translation
    cos = pose.rotation[:, 2] @ d / np.linalg.norm(d)
    return float(np.degrees(np.arccos(np.clip(cos, -1, 1)))), pose.translation.copy()


def test_04_user_gaze_task_from_yaml_turns_the_camera_to_its_target(tmp_path):
    """Run as a user would (a subprocess, from another working directory, the user's module found
    next to the YAML file) and measure the task's own error independently: the angle between the
    camera's optical axis and the target, from pinocchio forward kinematics of the URDF.

    Catches: a user task that is parsed but never reaches the QP (angle unchanged), its
    ``level``/``gain`` from YAML not applied, or a module looked up only on sys.path/cwd."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run(
        [sys.executable, str(ROOT / "examples" / "04_custom_task_from_yaml.py"), "--steps", "400", "--json"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300, check=False,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["gaze_level"] == 1 and out["gaze_gain"] == 2.0 and out["statuses"] == ["ok"]
    model = pin.buildModelFromUrdf(str(urdf_path()))
    data = model.createData()
    start, _ = _gaze_angle_deg(model, data, out["q_start"], "camera", out["target"])
    end, _ = _gaze_angle_deg(model, data, out["q_end"], "camera", out["target"])
    assert 30.0 < start < 50.0, start  # the example starts ~39 deg off
    assert end < 0.25 * start, (start, end)  # exp(-2 * 0.8 s) = 0.2 of the start, rate-limited
    pin.framesForwardKinematics(model, data, np.asarray(out["q_start"]))
    g0 = data.oMf[model.getFrameId("gripper")].translation.copy()
    pin.framesForwardKinematics(model, data, np.asarray(out["q_end"]))
    g1 = data.oMf[model.getFrameId("gripper")].translation.copy()
    assert np.linalg.norm(g1 - g0) < 2e-3  # the built-in frame_pose task of the same file holds the gripper
