"""WristSingularityTask: its row by hand, and a closed loop against a hand-solved equilibrium.

Oracles: the row formula evaluated by hand; the equilibrium of two joint-space terms solved by
bisection here (no library code); the camera Jacobian's smallest singular value from numpy's SVD.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from harvest_qp import Configuration, TaskController
from harvest_qp.exceptions import InvalidInputError, UnknownFrameError
from harvest_qp.robot.description import HOME_Q
from harvest_qp.tasks import PostureTask, WristSingularityTask

JOINT = "cam_wrist_2_joint"


def _at(wrist: float) -> tuple[Configuration, int]:
    q = np.asarray(HOME_Q, float).copy()
    config = Configuration.dual_ur5e(q)
    j = config.joint_index(JOINT)
    q[j] = wrist
    config.update(q)
    return config, j


@pytest.mark.parametrize(("wrist", "speed"), [
    (-math.pi + 0.10, +0.25),   # 0.10 rad above -pi: turn up, away from it
    (-math.pi - 0.10, -0.25),   # beyond -pi: turn further down
    (0.20, +0.15),              # near 0
    (-0.20, -0.15),
    (math.pi - 0.05, -0.30),    # near +pi, below it
    (-math.pi / 2, 0.0),        # outside the margin: no row
])
def test_the_row_by_hand(wrist, speed):
    """margin 0.35, gain 1: inside it s = (0.35 - d) / 0.35, row s e_j, target s (0.35 - d) sign.
    Catches: a push towards the singularity (sign), a row outside the margin (a posture task)."""
    config, j = _at(wrist)
    task = WristSingularityTask(JOINT, margin=0.35)
    J, v = task.compute(config, 0.002)
    d = 0.35 - abs(speed)
    s = (0.35 - d) / 0.35 if speed else 0.0
    expected = np.zeros((1, config.nv))
    expected[0, j] = s
    np.testing.assert_allclose(J, expected, atol=1e-12)
    np.testing.assert_allclose(v, [s * speed], atol=1e-12)


def test_bad_input_is_named():
    with pytest.raises(InvalidInputError, match="margin"):
        WristSingularityTask(JOINT, margin=-0.1)
    with pytest.raises(InvalidInputError, match="joint"):
        WristSingularityTask("")
    config, _ = _at(-1.0)
    with pytest.raises(UnknownFrameError, match="cam_wrist_9"):
        WristSingularityTask("cam_wrist_9").compute(config, 0.002)


def _closed_loop(with_task: bool, seconds: float = 20.0, dt: float = 0.002) -> tuple[float, Configuration]:
    """A posture term (weight 0.01, gain 1) pulls the camera arm's wrist 2 from -pi + 0.5 onto -pi;
    returns its final distance to -pi [rad]."""
    config, j = _at(-math.pi + 0.5)
    target = config.q.copy()
    target[j] = -math.pi
    weights = np.zeros(config.nv)
    weights[j] = 0.01
    tasks = [PostureTask(target, weight=weights, level=1)]
    if with_task:
        tasks.append(WristSingularityTask(JOINT, margin=0.35, weight=1.0, gain=1.0))
    controller = TaskController(config, tasks, dt=dt)
    q = config.q.copy()
    for _ in range(int(round(seconds / dt))):
        q = q + dt * controller.step(q).qdot
    return abs(q[j] + math.pi), config


def test_the_wrist_settles_where_the_two_terms_balance():
    """Equilibrium (qdot = 0) of 0.01 (qdot + d)^2 + s^2 (qdot - (m - d))^2, s = (m - d)/m, m = 0.35:
    0.01 d = (m - d)^3 / m^2, solved here by bisection (d* = 0.280 rad). Without the task the
    posture drives the wrist onto -pi, where the camera Jacobian loses rank.
    Catches: a task that does nothing, pushes the wrong way, or acts as a hard stop at the margin."""
    m = 0.35
    lo, hi = 0.0, m
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if 0.01 * mid < (m - mid) ** 3 / m**2 else (lo, mid)
    d_star = 0.5 * (lo + hi)
    with_task, config = _closed_loop(True)
    without, bare = _closed_loop(False)
    assert with_task == pytest.approx(d_star, abs=2e-3)
    assert without < 0.01
    smallest = [np.linalg.svd(c.frame_jacobian("camera")[:, :6], compute_uv=False)[-1] for c in (config, bare)]
    assert smallest[0] > 5 * smallest[1]
