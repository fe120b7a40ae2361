"""The task QP: pseudo-inverse equivalence, solver agreement, bounds, priorities, bad input."""

import numpy as np
import pytest

from harvest_qp import (
    Configuration,
    InvalidInputError,
    PseudoInverseMapper,
    Solver,
    SolverNotAvailableError,
    TaskController,
    UnknownFrameError,
)
from harvest_qp.limits import CollisionAvoidance, JointAccelerationLimit, JointPositionLimit, JointVelocityLimit
from harvest_qp.robot.description import HOME_Q
from harvest_qp.tasks import HARD, DampingTask, FramePoseTask, FrameTwistTask, PostureTask


def _twist_tasks(rng, **kwargs):
    cam = FrameTwistTask("camera", **kwargs)
    grasp = FrameTwistTask("gripper", **kwargs)
    cam.set_reference(rng.normal(0, 0.05, 6))
    grasp.set_reference(rng.normal(0, 0.05, 6))
    return cam, grasp


def test_unconstrained_qp_equals_damped_pseudo_inverse(configuration, rng):
    lam = 0.05
    for _ in range(5):
        configuration.update(HOME_Q + rng.normal(0, 0.3, 12))
        cam, grasp = _twist_tasks(rng)
        qdot = Solver("daqp", regularization=0.0).solve(
            configuration, [cam, grasp, DampingTask(12, weight=lam**2)], [], 0.002
        ).qdot
        mapper = PseudoInverseMapper(configuration, damping=lam)
        expected = mapper.map(np.concatenate([cam.reference, grasp.reference]))
        np.testing.assert_allclose(qdot, expected, atol=1e-9)


def test_pseudo_inverse_baseline_tracks_the_twists(configuration, rng):
    """eq:controlled_system: with a full-rank J, J J^+ V = V exactly."""
    configuration.update(HOME_Q + rng.normal(0, 0.2, 12))
    V = rng.normal(0, 0.1, 12)
    mapper = PseudoInverseMapper(configuration)
    np.testing.assert_allclose(mapper.jacobian() @ mapper.map(V), V, atol=1e-10)


def _collision_free_state(configuration, rng, spread=0.3):
    """A random state near home whose self-distances all exceed twice d_s."""
    limit = CollisionAvoidance.dual_ur5e(configuration)
    while True:
        q = HOME_Q + rng.normal(0, spread, 12)
        configuration.update(np.clip(q, configuration.lower_limits, configuration.upper_limits))
        if limit.distances(configuration).min() > 2 * limit.safety_distance:
            return configuration.q.copy()


def _collision_problem(configuration, rng):
    """Collision limit with 8 obstacle spheres near, but clear of, the robot (d > d_s)."""
    limit = CollisionAvoidance.dual_ur5e(configuration, influence_distance=0.15, gain=0.2)
    centers = []
    while len(centers) < 8:
        c = rng.uniform([0.25, -0.35, 0.95], [0.65, 0.65, 1.35])
        limit.set_obstacle_spheres(np.array([c]), 0.04)
        obstacle_pairs = [k for k, (_, b) in enumerate(limit.pair_names()) if b.startswith("obstacle")]
        if limit.distances(configuration)[obstacle_pairs].min() > 2 * limit.safety_distance:
            centers.append(c)
    limit.set_obstacle_spheres(np.array(centers), 0.04)
    return limit


def test_backends_agree_on_qps_with_active_collision_rows(configuration, rng):
    pytest.importorskip("quadprog")
    solvers = {name: Solver(name) for name in ("daqp", "proxsuite", "qpsolvers:quadprog")}
    n_active = 0
    for _ in range(30):
        _collision_free_state(configuration, rng)
        limit = _collision_problem(configuration, rng)
        # Drive the arms hard towards each other so the dampers bind.
        cam, grasp = FrameTwistTask("camera"), FrameTwistTask("gripper")
        gap = configuration.frame_position("gripper") - configuration.frame_position("camera")
        cam.set_reference(np.concatenate([0.5 * gap, np.zeros(3)]))
        grasp.set_reference(np.concatenate([-0.5 * gap, np.zeros(3)]))
        tasks = [cam, grasp, PostureTask(HOME_Q, weight=1e-3), DampingTask(12)]
        limits = [JointPositionLimit(configuration), JointVelocityLimit(configuration), limit]
        results = {name: s.solve(configuration, tasks, limits, 0.002) for name, s in solvers.items()}
        problem = results["daqp"].problems[-1]
        x = results["daqp"].qdot
        n_active += int(np.sum(np.abs(problem.G @ x - problem.h) < 1e-7))
        for name, result in results.items():
            np.testing.assert_allclose(result.qdot, x, atol=1e-6, err_msg=name)
    assert n_active >= 5, "the recorded QPs must include active collision rows"


def test_ten_thousand_random_states_never_nan_nor_out_of_bounds(configuration, rng):
    """Random collision-free states, references and previous commands through the controller."""
    collision = _collision_problem(configuration, rng)
    cam = FrameTwistTask("camera", weight=[1, 1, 1, 1, 1, 0], weight_frame="local")
    grasp = FrameTwistTask("gripper")
    tasks = [cam, grasp, PostureTask(HOME_Q, weight=1e-3), DampingTask(12)]
    controller = TaskController(configuration, tasks, [collision], dt=0.002, max_acceleration=15.0)
    lo, hi = configuration.lower_limits, configuration.upper_limits
    vmax = configuration.velocity_limits
    states = [_collision_free_state(configuration, rng, spread=0.6) for _ in range(200)]
    worst, solved = 0.0, 0
    for i in range(10_000):
        q = states[i % len(states)] + rng.normal(0, 0.01, 12)
        cam.set_reference(rng.normal(0, 1.0, 6))
        grasp.set_reference(rng.normal(0, 1.0, 6))
        controller.previous_qdot = rng.uniform(-0.3, 0.3, 12) * vmax
        step = controller.step(q)
        x = step.qdot
        assert np.all(np.isfinite(x)), step.status
        worst = max(worst, np.max(np.abs(x) - vmax), np.max(q + x * 0.002 - hi), np.max(lo - (q + x * 0.002)))
        if step.ok:
            solved += 1
            p = controller.solver_solution.problems[-1]
            worst = max(worst, np.max(p.lower - x), np.max(x - p.upper), np.max(p.G @ x - p.h))
    assert worst <= 1e-9
    assert solved >= 9_500, f"only {solved} of 10000 random QPs solved"


def test_strict_priorities_lower_level_never_changes_higher_residual(configuration, rng):
    improved = 0
    for _ in range(10):
        configuration.update(HOME_Q + rng.normal(0, 0.3, 12))
        high = FrameTwistTask("gripper", level=1)
        high.set_reference(rng.normal(0, 0.2, 6))
        cam_high = FrameTwistTask("camera", weight=[1, 1, 0, 0, 0, 0], level=1)
        cam_high.set_reference(rng.normal(0, 0.2, 6))
        limits = [JointVelocityLimit(configuration, max_velocity=0.5)]  # level 1 often unachievable
        solver = Solver("daqp")
        alone = solver.solve(configuration, [high, cam_high, DampingTask(12, level=2)], limits, 0.002).qdot
        low = FrameTwistTask("camera", level=2)
        low.set_reference(rng.normal(0, 1.0, 6))
        posture = PostureTask(rng.uniform(-2, 2, 12), weight=1.0, level=3)
        both = solver.solve(
            configuration, [high, cam_high, low, posture, DampingTask(12, level=4)], limits, 0.002
        ).qdot
        for task in (high, cam_high):
            r_alone = np.linalg.norm(task.residual(configuration, alone, 0.002))
            r_both = np.linalg.norm(task.residual(configuration, both, 0.002))
            assert r_both == pytest.approx(r_alone, abs=1e-6)
        # ... and the lower level did improve within the optimal set of the levels above.
        r_low_alone = np.linalg.norm(low.residual(configuration, alone, 0.002))
        r_low_both = np.linalg.norm(low.residual(configuration, both, 0.002))
        assert r_low_both <= r_low_alone + 1e-9
        improved += r_low_both < r_low_alone - 1e-3
    assert improved >= 5


def test_hard_task_is_met_exactly(configuration, rng):
    hard = FrameTwistTask("gripper", level=HARD)
    hard.set_reference([0.02, 0, -0.01, 0, 0.05, 0])
    soft = FrameTwistTask("camera")
    soft.set_reference(rng.normal(0, 0.1, 6))
    qdot = Solver().solve(configuration, [hard, soft, DampingTask(12)], [], 0.002).qdot
    np.testing.assert_allclose(configuration.frame_jacobian("gripper") @ qdot, hard.reference, atol=1e-9)


def test_pose_task_converges(configuration):
    task = FramePoseTask("gripper", gain=5.0)
    start = configuration.frame_pose("gripper")
    task.set_target(start.translation + [0.05, 0.03, -0.04], start.rotation)
    controller = TaskController(configuration, [task, DampingTask(12, weight=1e-6)], dt=0.002)
    q = configuration.q.copy()
    for _ in range(1500):
        step = controller.step(q)
        assert step.ok, step.status
        q = q + step.qdot * 0.002
    configuration.update(q)
    assert np.linalg.norm(task.error(configuration)) < 1e-3


# ----------------------------------------------------------------------------- bad input


def test_unknown_frame_lists_valid_names(configuration):
    with pytest.raises(UnknownFrameError, match="valid frames are:.*camera.*gripper"):
        FrameTwistTask("nope").compute(configuration, 0.002)
    with pytest.raises(KeyError):  # still a KeyError for generic handlers
        configuration.frame_id("nope")


def test_wrong_shapes_name_the_expected_shape(configuration):
    with pytest.raises(InvalidInputError, match=r"shape \(6,\)"):
        FrameTwistTask("camera").set_reference(np.zeros(5))
    with pytest.raises(InvalidInputError, match=r"shape \(12,\)"):
        configuration.update(np.zeros(11))
    with pytest.raises(InvalidInputError, match=r"shape \(6,\)"):
        FrameTwistTask("camera", weight=np.ones(3))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_references_are_rejected(bad):
    ref = np.zeros(6)
    ref[2] = bad
    with pytest.raises(InvalidInputError, match="finite"):
        FrameTwistTask("camera").set_reference(ref)


def test_negative_weights_and_gains_are_rejected():
    with pytest.raises(InvalidInputError, match=">= 0"):
        FrameTwistTask("camera", weight=-1.0)
    with pytest.raises(InvalidInputError, match="gain"):
        FramePoseTask("camera", gain=-2.0)
    with pytest.raises(InvalidInputError, match="level"):
        FrameTwistTask("camera", level=-1)


def test_unknown_backend_names_the_choices(configuration):
    with pytest.raises(SolverNotAvailableError, match="daqp.*proxsuite.*qpsolvers"):
        Solver("cplex").solve(configuration, [DampingTask(12)], [], 0.002)
    with pytest.raises(SolverNotAvailableError, match="available"):
        Solver("qpsolvers:not_a_solver").solve(configuration, [DampingTask(12)], [], 0.002)


def test_configuration_rejects_nan_q():
    with pytest.raises(InvalidInputError, match="finite"):
        Configuration.dual_ur5e(q=np.full(12, np.nan))


def test_box_conflicts_keep_the_higher_priority_box(configuration):
    """Speed limit beats position limit beats acceleration limit, joint by joint."""
    from harvest_qp.solver import combine_boxes

    n = 3
    vel = (JointVelocityLimit(configuration), -np.ones(n), np.ones(n))
    pos = (JointPositionLimit(configuration), np.array([-5.0, -0.5, 2.0]), np.array([5.0, 0.5, 3.0]))
    acc = (JointAccelerationLimit(configuration), np.array([0.8, -0.2, -1.0]), np.array([0.9, 0.1, 1.0]))
    lower, upper, conflicts = combine_boxes([acc, pos, vel], n)
    # joint 0: all overlap -> [0.8, 0.9]; joint 1: acc inside pos -> [-0.2, 0.1];
    # joint 2: pos [2, 3] misses vel [-1, 1] -> pos yields onto 1, then acc contains 1.
    np.testing.assert_allclose(lower, [0.8, -0.2, 1.0])
    np.testing.assert_allclose(upper, [0.9, 0.1, 1.0])
    assert [(c.joint, c.limit) for c in conflicts] == [(2, "JointPositionLimit")]


def test_pseudo_inverse_hand_computed_case(configuration):
    """eq:controlled_system: the twist one joint alone produces maps back to that joint alone."""
    mapper = PseudoInverseMapper(configuration)
    J = mapper.jacobian()  # 12 x 12, full rank away from singularities
    for k in (0, 4, 7, 11):
        expected = np.zeros(12)
        expected[k] = 0.3  # [rad/s]
        np.testing.assert_allclose(mapper.map(J @ expected), expected, atol=1e-10)
    # Block structure: a camera-only twist moves only the camera arm (J = diag(J_c, J_g)).
    V = np.concatenate([J[:6] @ np.full(12, 0.1), np.zeros(6)])
    assert np.allclose(mapper.map(V)[6:], 0.0, atol=1e-10)


def test_custom_limits_box_and_rows(configuration):
    """User limits: a box through the default fill_box, rows through compute."""
    from harvest_qp.limits import Limit, LimitRows

    class ElbowSpeed(Limit):
        has_box = True
        priority = 0

        def compute(self, configuration, dt, previous_qdot=None):
            lower, upper = np.full(12, -10.0), np.full(12, 10.0)
            lower[2], upper[2] = -0.01, 0.01
            return LimitRows(lower=lower, upper=upper)

    class NoCameraDescent(Limit):
        def compute(self, configuration, dt, previous_qdot=None):
            J = configuration.frame_jacobian("camera")
            return LimitRows(G=-J[2:3], h=np.zeros(1))  # v_z >= 0

    task = FrameTwistTask("camera")
    task.set_reference([0.0, 0.0, -0.2, 0.0, 0.0, 0.0])
    qdot = Solver().solve(configuration, [task, DampingTask(12)], [ElbowSpeed(), NoCameraDescent()], 0.002).qdot
    assert abs(qdot[2]) <= 0.01 + 1e-12
    assert configuration.frame_jacobian("camera")[2] @ qdot >= -1e-9

    class Forgetful(Limit):  # returns a box but does not declare it
        def compute(self, configuration, dt, previous_qdot=None):
            return LimitRows(lower=-np.ones(12), upper=np.ones(12))

    with pytest.raises(InvalidInputError, match="has_box = True"):
        Solver().solve(configuration, [task], [Forgetful()], 0.002)
