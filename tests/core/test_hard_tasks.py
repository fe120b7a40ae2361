"""Hard (level-0) tasks: least-squares compromise when they conflict, safe stop on a NaN Jacobian.

The speed work compressed every equality block with a pivoted QR, which is exact only for
consistent rows; hard tasks keep the SVD least-squares basis (an independent audit found
the QR made the result depend on the tasks' order and silently dropped a NaN row).
"""

from __future__ import annotations

import numpy as np

from harvest_qp import Configuration, TaskController
from harvest_qp.robot import description as desc
from harvest_qp.solver import Solver
from harvest_qp.tasks import DampingTask, FrameTwistTask
from harvest_qp.tasks.task import Task


def _twist(reference, level=0):
    task = FrameTwistTask("gripper", level=level)
    task.set_reference(np.asarray(reference, float))
    return task


def test_conflicting_hard_tasks_get_the_least_squares_compromise_in_any_order():
    """Two hard gripper twists 0.1 m/s apart: the residual is numpy lstsq's, split evenly.

    Catches: the pivoted QR on hard rows (the first task met exactly, the whole 0.1 m/s
    error on the second, so swapping the tasks changes the command)."""
    c = Configuration.dual_ur5e(desc.HOME_Q)
    J = c.frame_jacobian("gripper")
    a, b = np.array([0.10, 0, 0, 0, 0, 0]), np.zeros(6)
    rows, target = np.vstack([J, J]), np.concatenate([a, b])
    least = np.linalg.norm(rows @ np.linalg.lstsq(rows, target, rcond=None)[0] - target)
    x_ab = Solver().solve(c, [_twist(a), _twist(b), DampingTask(12)], [], 0.002).qdot
    x_ba = Solver().solve(c, [_twist(b), _twist(a), DampingTask(12)], [], 0.002).qdot
    residual = rows @ x_ab - target
    assert np.linalg.norm(residual) <= least + 1e-9
    assert abs(residual[0] + 0.05) < 1e-9 and abs(residual[6] - 0.05) < 1e-9
    np.testing.assert_allclose(x_ab, x_ba, atol=1e-12)


class _NaNJacobian(Task):
    """A user task whose Jacobian holds one NaN (a broken user model)."""

    def __init__(self) -> None:
        super().__init__(3, level=0, weight=1.0)

    def compute_rows(self, configuration, dt):
        J = configuration.frame_jacobian("gripper")[:3].copy()
        J[1, 2] = np.nan
        return J, np.array([0.01, 0.0, 0.0])

    def compute(self, configuration, dt):
        return self.compute_rows(configuration, dt)


def test_a_nan_in_a_hard_task_jacobian_stops_the_arms_safely():
    """TaskController.step reports a fallback and commands a finite safe stop.

    Catches: the NaN row silently skipped by the QR's pivot search (status "ok" on a broken task)."""
    c = Configuration.dual_ur5e(desc.HOME_Q)
    step = TaskController(c, [_NaNJacobian(), DampingTask(12)], dt=0.002).step(np.array(desc.HOME_Q))
    assert step.status.startswith("fallback")
    assert np.all(np.isfinite(step.qdot))


class _NaNTarget(Task):
    """A user hard task whose target holds a NaN."""

    def __init__(self) -> None:
        super().__init__(3, level=0, weight=1.0)

    def compute_rows(self, configuration, dt):
        return configuration.frame_jacobian("gripper")[:3].copy(), np.array([0.01, np.nan, 0.0])

    def compute(self, configuration, dt):
        return self.compute_rows(configuration, dt)


def test_a_nan_hard_target_stops_the_arms_safely_naming_the_task():
    """Catches: a NaN hard target reported as "ok: retried after daqp" (the retry dropped the
    task without a word; an audit)."""
    c = Configuration.dual_ur5e(desc.HOME_Q)
    step = TaskController(c, [_NaNTarget(), DampingTask(12)], dt=0.002).step(np.array(desc.HOME_Q))
    assert step.status.startswith("fallback") and "_NaNTarget" in step.status and "non-finite" in step.status
    assert np.all(np.isfinite(step.qdot))
