"""The control loop never raises, never emits NaN and stops safely when it cannot solve."""

import numpy as np
import pytest

from harvest_qp import Configuration, TaskController
from harvest_qp.limits import CollisionAvoidance, JointVelocityLimit
from harvest_qp.robot.description import HOME_Q
from harvest_qp.tasks import HARD, DampingTask, FramePoseTask, FrameTwistTask, PostureTask

DT = 0.002


def test_infeasible_problem_decelerates_within_acceleration_limit(configuration):
    # A hard task faster than the speed limit allows is infeasible.
    hard = FrameTwistTask("gripper", level=HARD)
    hard.set_reference([5.0, 0, 0, 0, 0, 0])
    controller = TaskController(configuration, [hard, DampingTask(12)], dt=DT, max_acceleration=8.0)
    controller.previous_qdot = np.full(12, 0.5)
    q = HOME_Q.copy()
    previous = controller.previous_qdot.copy()
    for _ in range(100):
        step = controller.step(q)
        assert step.status.startswith("fallback")
        assert np.all(np.isfinite(step.qdot))
        assert np.all(np.abs(step.qdot - previous) <= 8.0 * DT + 1e-12)
        assert np.all(np.abs(step.qdot) <= np.abs(previous) + 1e-12)
        previous = step.qdot
        q = q + step.qdot * DT
    np.testing.assert_allclose(step.qdot, 0.0)
    assert "InfeasibleProblemError" in step.status


def test_nan_measurement_gives_a_finite_stop_command(configuration):
    task = FrameTwistTask("camera")
    task.set_reference([0.05, 0, 0, 0, 0, 0])
    controller = TaskController(configuration, [task, DampingTask(12)], dt=DT)
    assert controller.step(HOME_Q).ok
    q = HOME_Q.copy()
    q[3] = np.nan
    step = controller.step(q)
    assert step.status.startswith("fallback") and "finite" in step.status
    assert np.all(np.isfinite(step.qdot))


def test_joint_outside_its_range_returns_at_most_at_the_speed_limit(configuration):
    q = HOME_Q.copy()
    q[2] = np.pi + 0.2  # elbow beyond its +-pi limit (e.g. after a restart)
    controller = TaskController(configuration, [PostureTask(HOME_Q), DampingTask(12)], dt=DT)
    step = controller.step(q)
    assert step.ok, step.status
    assert step.qdot[2] < 0
    assert np.all(np.abs(step.qdot) <= configuration.velocity_limits + 1e-12)


def test_arms_driven_to_crossing_targets_never_closer_than_safety_distance(configuration):
    """Closed loop: each gripper/camera is sent to the other arm's side; collisions stop them.

    Distances are measured with pinocchio frame placements + coal capsules, not with the
    constrained kernel. Bug caught: a dropped or mis-signed collision row (the arms pass through).
    """
    from benchmarks.bench_fuzz import CoalGeometry

    collision = CollisionAvoidance.dual_ur5e(configuration, safety_distance=0.02, influence_distance=0.12)
    cam = FramePoseTask("camera", gain=2.0, weight=[1, 1, 1, 0.1, 0.1, 0.1])
    grasp = FramePoseTask("gripper", gain=2.0, weight=[1, 1, 1, 0.1, 0.1, 0.1])
    p_cam = configuration.frame_pose("camera")
    p_grasp = configuration.frame_pose("gripper")
    # Swap sides: the camera goes where the gripper is and vice versa, so paths cross.
    cam.set_target(p_grasp.translation + [0.0, 0.0, 0.05], p_cam.rotation)
    grasp.set_target(p_cam.translation + [0.0, 0.0, -0.05], p_grasp.rotation)
    tasks = [cam, grasp, PostureTask(HOME_Q, weight=1e-3), DampingTask(12, weight=1e-4)]
    controller = TaskController(
        configuration, tasks, [collision, JointVelocityLimit(configuration, max_velocity=1.5)], dt=DT
    )
    geometry = CoalGeometry(configuration, collision)
    q = HOME_Q.copy()
    min_distance = np.inf
    moved = 0.0
    for _ in range(1500):  # 3 s
        step = controller.step(q)
        assert np.all(np.isfinite(step.qdot))
        assert step.ok, step.status
        q = q + step.qdot * DT
        configuration.update(q)
        min_distance = min(min_distance, geometry.min_distance(q)[0])
        moved = max(moved, np.linalg.norm(configuration.frame_position("camera") - p_cam.translation))
    assert moved > 0.2, "the arms must actually move towards each other"
    assert min_distance >= collision.safety_distance - 1e-4
    # The dampers were really active, not trivially satisfied.
    assert min_distance < collision.influence_distance


def test_solver_error_carries_a_replayable_problem(configuration):
    from harvest_qp import InfeasibleProblemError, Solver

    hard = FrameTwistTask("gripper", level=HARD)
    hard.set_reference([5.0, 0, 0, 0, 0, 0])  # beyond the speed limit: infeasible
    with pytest.raises(InfeasibleProblemError) as info:
        Solver().solve(configuration, [hard, DampingTask(12)], [JointVelocityLimit(configuration)], DT)
    problem = info.value.problem
    assert info.value.backend == "daqp"
    assert problem.A.shape == (6, 12) and np.allclose(problem.upper, configuration.velocity_limits)
    # Replaying it on another backend confirms the diagnosis.
    with pytest.raises(InfeasibleProblemError):
        from harvest_qp.backends import make_backend

        make_backend("proxsuite").solve(problem)


def test_previous_qdot_set_to_none_means_at_rest_and_step_never_raises():
    """Bug caught (audit, pre-existing): ``previous_qdot = None`` made ``step`` (documented
    "never raises") raise ``TypeError`` on the solve path and in the safe stop.

    Oracle: a fresh controller (previous command zero): the same command and acceleration;
    a bad ``q`` with ``previous_qdot = None`` takes the safe stop (zeros from rest).
    """
    from harvest_qp.limits import JointAccelerationLimit, JointPositionLimit

    def make():
        config = Configuration.dual_ur5e()
        camera = FrameTwistTask("camera")
        camera.set_reference(np.full(6, 0.1))
        limits = [JointVelocityLimit(config), JointPositionLimit(config), JointAccelerationLimit(config)]
        return TaskController(config, [camera, DampingTask(12, level=2)], limits)

    fresh, forgetful = make(), make()
    forgetful.previous_qdot = None
    a, b = fresh.step(HOME_Q), forgetful.step(HOME_Q)
    assert a.ok and b.ok
    assert np.array_equal(a.qdot, b.qdot) and np.array_equal(a.acceleration, b.acceleration)
    forgetful.previous_qdot = None
    bad = HOME_Q.copy()
    bad[0] = np.nan
    stopped = forgetful.step(bad)
    assert stopped.status.startswith("fallback") and np.array_equal(stopped.qdot, np.zeros(12))


def test_step_acceleration_is_the_command_change_at_the_step_despite_later_edits():
    """ControlStep.acceleration is computed when read: catches it following an in-place edit of the
    previous command made after the step (a speed override; found by an independent review)."""
    config = Configuration.dual_ur5e()
    camera = FrameTwistTask("camera")
    camera.set_reference(np.full(6, 0.1))
    controller = TaskController(config, [camera, DampingTask(12, level=2)])
    first = controller.step(HOME_Q)
    second = controller.step(HOME_Q)
    expected = (second.qdot - first.qdot) / controller.dt  # hand oracle, taken before any edit
    first.qdot *= 0.0  # the previous command edited in place after the step
    np.testing.assert_array_equal(second.acceleration, expected)
    assert second.max_acceleration == pytest.approx(np.max(np.abs(expected)))
