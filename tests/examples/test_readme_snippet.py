"""The README's library snippet runs as written and does what its comments say.

The snippet is read from README.md (the first ```python block) and executed; then its results are
checked against pinocchio forward kinematics straight from the URDF (independent of the library's
Configuration): once the command has ramped up within the acceleration limit (the snippet's first
step starts from rest), the joint velocities move the camera along its reference V_c and the
gripper along V_g. Catches: a README snippet that no longer runs after an API change,
or one whose tasks never reach the solver.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pinocchio as pin

from harvest_qp.robot.paths import urdf_path

README = Path(__file__).resolve().parents[2] / "README.md"


def _snippet() -> str:
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks, "README.md has no ```python block"
    return blocks[0]


def test_readme_snippet_runs_and_moves_the_frames_as_asked():
    scope: dict = {}
    exec(compile(_snippet(), str(README), "exec"), scope)  # noqa: S102 (our own README)
    step, config, controller = scope["step"], scope["config"], scope["controller"]
    assert step.ok, step.status
    for _ in range(200):  # the same state: the acceleration box lets the command ramp up to the references
        step = controller.step(config.q)
        assert step.ok, step.status
    qdot = np.asarray(step.qdot)
    assert qdot.shape == (12,) and np.all(np.isfinite(qdot))
    model = pin.buildModelFromUrdf(str(urdf_path()))
    data = model.createData()
    pin.computeJointJacobians(model, data, config.q)
    pin.updateFramePlacements(model, data)

    def twist(frame: str) -> np.ndarray:
        J = pin.getFrameJacobian(model, data, model.getFrameId(frame), pin.LOCAL_WORLD_ALIGNED)
        return J @ qdot

    v_g = twist("gripper")
    np.testing.assert_allclose(v_g, [0, 0, 0.02, 0, 0, 0], atol=2e-3)  # V_g, world axes
    R_c = data.oMf[model.getFrameId("camera")].rotation
    v_c = twist("camera")
    # References are world-aligned twists; the camera task weighs them in its own axes with the
    # roll about z_c left free: the first five local components follow the reference's.
    reference = np.array([0.05, 0, 0, 0, 0.1, 0])
    local = np.concatenate([R_c.T @ v_c[:3], R_c.T @ v_c[3:]])
    asked = np.concatenate([R_c.T @ reference[:3], R_c.T @ reference[3:]])
    np.testing.assert_allclose(local[:5], asked[:5], atol=2e-3)
