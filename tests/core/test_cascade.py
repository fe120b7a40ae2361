"""The strict-priority cascade against an independent reference, and the solver's input errors.

The reference cascade below is written here from the problem statement only (no harvest_qp code):
pinocchio's Jacobians, the tasks' weights and references, and quadprog solving each level

    min  sum_tasks || W^1/2 (J x - v) ||^2     s.t.  lower <= x <= upper,  G x <= h,
                                                     W_j^1/2 J_j x = W_j^1/2 J_j x_j*  (levels above)

written as a QP over the null space of the weighted task rows of the levels above (numpy's SVD),
not as equality rows (the solver hands on orthonormal equality rows from a pivoted QR).
"""

import numpy as np
import pinocchio as pin
import pytest
import quadprog

from harvest_qp import Configuration, InvalidInputError, Solver, TaskController
from harvest_qp.limits import CollisionAvoidance, JointAccelerationLimit, JointPositionLimit, JointVelocityLimit
from harvest_qp.robot.description import HOME_Q
from harvest_qp.tasks import DampingTask, FrameTwistTask, PostureTask, Task

DT = 0.002
LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED


def _jacobian(configuration, frame):
    model = configuration.model
    data = model.createData()
    return pin.computeFrameJacobian(model, data, configuration.q, model.getFrameId(frame), LWA)


def _rotation(configuration, frame):
    model = configuration.model
    data = model.createData()
    pin.framesForwardKinematics(model, data, configuration.q)
    return data.oMf[model.getFrameId(frame)].rotation


def _reference_rows(configuration, task):
    """(J, v) of a task written from its definition (twist tasks: pinocchio; local axes rotated by R^T)."""
    n = configuration.nv
    if isinstance(task, FrameTwistTask):
        J, v = _jacobian(configuration, task.frame), task.gain * task.reference
        if task.weight_frame == "local":
            T = np.kron(np.eye(2), _rotation(configuration, task.frame).T)
            J, v = T @ J, T @ v
        return J, v
    if isinstance(task, PostureTask):
        return np.eye(n), task.gain * (task.target - configuration.q)
    if isinstance(task, DampingTask):
        return np.eye(n), np.zeros(n)
    raise AssertionError(type(task))


def _reference_cascade(configuration, tasks, lower, upper, G, h, reg=1e-10):
    """Each level in the null space of the task rows above it: ``x = x_above + Z y`` (``Z`` from numpy's
    SVD of the stacked weighted rows), quadprog over ``y`` under the box and the rows ``G x <= h``."""
    n = configuration.nv
    C = np.vstack([-G, -np.eye(n), np.eye(n)])
    d = np.concatenate([-h, -upper, lower])
    x, Z, above = np.zeros(n), np.eye(n), np.zeros((0, n))
    for level in sorted({t.level for t in tasks}):
        H, f = reg * np.eye(n), np.zeros(n)
        for task in (t for t in tasks if t.level == level):
            J, v = _reference_rows(configuration, task)
            H += J.T @ np.diag(task.weight) @ J
            f -= J.T @ np.diag(task.weight) @ v
            above = np.vstack([above, np.sqrt(task.weight)[:, None] * J])
        if Z.shape[1] == 0:
            break
        CZ, dz = C @ Z, d - C @ x
        if level != min(t.level for t in tasks):
            # x (the level above's optimum) is feasible: the rows active there hold to round-off only
            assert np.all(dz <= 1e-9)
            dz = np.minimum(dz, 0.0)
        moving = np.abs(CZ).max(axis=1) > 1e-12  # rows the null space cannot move hold at x already
        y = quadprog.solve_qp(Z.T @ H @ Z, -Z.T @ (H @ x + f), CZ[moving].T.copy(), dz[moving], 0)[0]
        x = x + Z @ y
        s, Vt = np.linalg.svd(above)[1:]
        rank = int(np.sum(s > 1e-9 * max(1.0, s[0])))
        Z = Vt[rank:].T
    return x


def _episode_like_tasks(rng, configuration, extra_level=False):
    camera = FrameTwistTask("camera", weight=[1, 1, 1, 1, 1, 0], weight_frame="local", level=1)
    gripper = FrameTwistTask("gripper", level=1)
    roll = FrameTwistTask("camera", weight=[0, 0, 0, 0, 0, 1], weight_frame="local", level=2)
    posture = PostureTask(HOME_Q, weight=1e-3, level=2, gain=2.0)
    damping = DampingTask(12, weight=1e-4, level=2)
    for task in (camera, gripper, roll):
        task.set_reference(rng.normal(0, 0.08, 6))
    tasks = [camera, gripper, roll, posture, damping]
    if extra_level:  # a sixth task on a level of its own
        elbow = FrameTwistTask("camera", weight=[0, 0, 0, 1, 1, 0], level=3)
        elbow.set_reference(rng.normal(0, 0.05, 6))
        tasks.append(elbow)
    return tasks


@pytest.mark.parametrize("extra_level", [False, True])
def test_cascade_equals_an_independent_quadprog_cascade_with_collision_rows(rng, extra_level):
    """Oracle: :func:`_reference_cascade` (quadprog level by level, rows from pinocchio). The QP's
    boxes and collision rows are read back from the solution and used as given; the solution must
    agree to 1e-6 rad/s on the episode's five tasks and with a sixth task on a third level.

    Bugs caught (planted once each): the equalities of level 1 not handed to level 2;
    the local-axes rotation dropped from the camera task."""
    configuration = Configuration.dual_ur5e(HOME_Q)
    collision = CollisionAvoidance.dual_ur5e(configuration, influence_distance=0.3)
    collision.set_obstacle_spheres(np.array([[0.45, 0.1, 1.05], [0.5, -0.1, 1.0]]), 0.04)
    limits = [JointVelocityLimit(configuration), JointPositionLimit(configuration),
              JointAccelerationLimit(configuration, max_acceleration=50.0), collision]
    solver = Solver()
    compared = 0
    for _ in range(6):
        configuration.update(HOME_Q + rng.normal(0, 0.2, 12))
        tasks = _episode_like_tasks(rng, configuration, extra_level)
        solution = solver.solve(configuration, tasks, limits, DT, previous_qdot=rng.normal(0, 0.05, 12))
        if solution.relaxed or solution.retries:
            continue
        problem = solution.problems[-1]
        expected = _reference_cascade(configuration, tasks, solution.lower, solution.upper, problem.G, problem.h)
        np.testing.assert_allclose(solution.qdot, expected, atol=1e-6)
        assert len(solution.problems) == (3 if extra_level else 2)
        compared += 1
    assert compared >= 4


def test_hand_computed_two_level_case():
    """Oracle: by hand. Two joints of the model only matter: level 1 asks ``qdot_0 + qdot_1 = 1``,
    level 2 asks ``qdot_0 = 1`` and a tiny damping; the box caps ``qdot_0 <= 0.25``. Level 2 must stay
    on level 1's line and within the box: ``qdot_0 = 0.25``, ``qdot_1 = 0.75``, the rest 0."""

    class Rows(Task):
        def __init__(self, J, v, level):
            super().__init__(len(v), level=level)
            self.J, self.v = np.asarray(J, float), np.asarray(v, float)

        def compute(self, configuration, dt):
            return self.J, self.v

    class Cap(JointVelocityLimit):
        def fill_box(self, configuration, dt, previous_qdot, lower, upper):
            lower[:] = -1.0
            upper[:] = 1.0
            upper[0] = 0.25

    configuration = Configuration.dual_ur5e(HOME_Q)
    n = configuration.nv
    sum01 = np.zeros((1, n))
    sum01[0, :2] = 1.0
    first = np.zeros((1, n))
    first[0, 0] = 1.0
    tasks = [Rows(sum01, [1.0], 1), Rows(first, [1.0], 2), DampingTask(n, weight=1e-9, level=2)]
    qdot = Solver().solve(configuration, tasks, [Cap(configuration)]).qdot
    expected = np.zeros(n)
    expected[:2] = 0.25, 0.75
    np.testing.assert_allclose(qdot, expected, atol=1e-7)


@pytest.mark.parametrize("bad_index", [0, 2])
def test_a_non_task_among_the_tasks_is_named_by_position_and_type(bad_index):
    """Oracle: the position and type planted. Bug caught: an AttributeError from deep inside the solver."""
    configuration = Configuration.dual_ur5e(HOME_Q)
    tasks = [FrameTwistTask("camera"), DampingTask(12), PostureTask(HOME_Q)]
    tasks[bad_index] = {"frame": "camera"}
    for build in (lambda: Solver().solve(configuration, tasks), lambda: TaskController(configuration, tasks)):
        with pytest.raises(InvalidInputError, match=rf"tasks\[{bad_index}\] must be a Task, got dict"):
            build()


def test_a_non_limit_among_the_limits_is_named_by_position_and_type():
    configuration = Configuration.dual_ur5e(HOME_Q)
    tasks = [DampingTask(12)]
    limits = [JointVelocityLimit(configuration), "JointPositionLimit"]
    for build in (lambda: Solver().solve(configuration, tasks, limits), lambda: TaskController(configuration, tasks,
                                                                                                   limits)):
        with pytest.raises(InvalidInputError, match=r"limits\[1\] must be a Limit, got str"):
            build()


def test_a_list_changed_after_a_solve_is_checked_again():
    """The solver checks the lists when they change (not every step): a non-Task put into the
    same list after a good solve, or a non-Limit appended, is still named. Bug caught: a check
    cached on the list object, so the changed list reached the cascade unchecked."""
    configuration = Configuration.dual_ur5e(HOME_Q)
    tasks, limits = [DampingTask(12), PostureTask(HOME_Q)], [JointVelocityLimit(configuration)]
    solver = Solver()
    solver.solve(configuration, tasks, limits)
    tasks[1] = "posture"
    with pytest.raises(InvalidInputError, match=r"tasks\[1\] must be a Task, got str"):
        solver.solve(configuration, tasks, limits)
    tasks[1] = PostureTask(HOME_Q)
    solver.solve(configuration, tasks, limits)
    limits.append(3)
    with pytest.raises(InvalidInputError, match=r"limits\[1\] must be a Limit, got int"):
        solver.solve(configuration, tasks, limits)


def test_controller_step_with_updated_kinematics_equals_the_plain_step(rng):
    """Oracle: the public step that recomputes the kinematics. ``step(q, kinematics_updated=True)`` after
    the loop's own ``configuration.update(q)`` gives the same command."""
    results = []
    for mode in ("plain", "updated"):
        local = np.random.default_rng(3)
        configuration = Configuration.dual_ur5e(HOME_Q)
        tasks = _episode_like_tasks(local, configuration)
        controller = TaskController(configuration, tasks)
        out = []
        for _ in range(3):
            q = HOME_Q + local.normal(0, 0.1, 12)
            if mode == "plain":
                step = controller.step(q)
            else:
                configuration.update(q)
                step = controller.step(q, kinematics_updated=True)
            assert step.ok, step.status
            out.append(step.qdot)
        results.append(np.array(out))
    np.testing.assert_array_equal(results[0], results[1])
