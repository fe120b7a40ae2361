"""Finite-difference checks of every task Jacobian and every collision row."""

import numpy as np
import pinocchio as pin
import pytest

from harvest_qp import Configuration
from harvest_qp.limits import CollisionAvoidance
from harvest_qp.tasks import DampingTask, FramePoseTask, FrameTwistTask, PostureTask, RelativeFrameTask

H = 1e-6


def _states(rng, n=5):
    from harvest_qp.robot.description import HOME_Q

    return [HOME_Q + rng.normal(0.0, 0.4, 12) for _ in range(n)]


def _frame_rate(config: Configuration, frame: str, q, qdot):
    """World-aligned twist of ``frame`` by central differences of its pose."""
    config.update(q - H * qdot)
    a = config.frame_pose(frame).copy()
    config.update(q + H * qdot)
    b = config.frame_pose(frame).copy()
    v = (b.translation - a.translation) / (2 * H)
    w = pin.log3(b.rotation @ a.rotation.T) / (2 * H)
    config.update(q)
    return np.concatenate([v, w])


@pytest.mark.parametrize("frame", ["camera", "gripper", "cutter_tip", "ft_sensor"])
def test_frame_twist_task_jacobian_world(configuration, rng, frame):
    task = FrameTwistTask(frame)
    for q in _states(rng):
        qdot = rng.standard_normal(12)
        configuration.update(q)
        J, _ = task.compute(configuration, 0.002)
        np.testing.assert_allclose(J @ qdot, _frame_rate(configuration, frame, q, qdot), atol=1e-7)


def test_frame_twist_task_local_rows_are_the_local_twist(configuration, rng):
    task = FrameTwistTask("camera", weight_frame="local")
    for q in _states(rng):
        qdot = rng.standard_normal(12)
        configuration.update(q)
        J, v = task.compute(configuration, 0.002)
        R = configuration.frame_rotation("camera")
        twist = _frame_rate(configuration, "camera", q, qdot)
        np.testing.assert_allclose(J @ qdot, np.concatenate([R.T @ twist[:3], R.T @ twist[3:]]), atol=1e-7)


def test_frame_pose_task_error_decreases_along_jacobian(configuration, rng):
    task = FramePoseTask("gripper", gain=2.0)
    configuration.update(_states(rng, 1)[0])
    target = configuration.frame_pose("gripper")
    task.set_target(target.translation + [0.01, -0.02, 0.005], target.rotation @ pin.exp3(np.array([0.002, 0, 0.001])))
    J, v = task.compute(configuration, 0.002)
    e = task.error(configuration)
    np.testing.assert_allclose(v, 2.0 * e)
    # d e/dt = -J qdot to first order (small error: log3 Jacobian ~ identity).
    qdot = rng.standard_normal(12)
    q = configuration.q.copy()
    configuration.update(q + H * qdot)
    e_plus = task.error(configuration)
    configuration.update(q - H * qdot)
    e_minus = task.error(configuration)
    np.testing.assert_allclose((e_plus - e_minus) / (2 * H), -(J @ qdot), atol=5e-3 * np.linalg.norm(J @ qdot))


def test_relative_frame_task_jacobian(configuration, rng):
    task = RelativeFrameTask("cutter_tip", "gripper")
    task.set_target(np.zeros(3), np.eye(3))
    for q in _states(rng):
        qdot = rng.standard_normal(12)
        configuration.update(q)
        J, _ = task.compute(configuration, 0.002)
        configuration.update(q - H * qdot)
        p0, R0 = task.relative_pose(configuration)
        configuration.update(q + H * qdot)
        p1, R1 = task.relative_pose(configuration)
        configuration.update(q)
        _, R = task.relative_pose(configuration)
        lin = (p1 - p0) / (2 * H)
        # Angular rows are R_r^T (w_f - w_r): the rate of R_rel in root coordinates (left).
        ang = pin.log3(R1 @ R0.T) / (2 * H)
        np.testing.assert_allclose(J @ qdot, np.concatenate([lin, ang]), atol=1e-6)


def test_posture_task_rows_are_the_decay_of_pinocchio_configuration_difference(configuration, rng):
    """Oracle: pinocchio's own configuration difference ``e = q* (-) q`` (``pin.difference``).

    The task asks ``de/dt = -J qdot = -gain e``: ``J qdot`` must equal ``-de/dt`` by finite
    differences of ``e`` along ``qdot``, and ``v`` must be ``gain e``. Catches a sign flip
    (``q - q*``), a permuted or partial identity, and the gain applied wrongly, on both the
    dense path (``compute``) and the solver's path (``compute_rows``, ``J = None`` = identity).
    """
    model = configuration.model
    target = rng.uniform(-1, 1, 12)
    posture = PostureTask(target, gain=3.0)
    q = _states(rng, 1)[0]
    configuration.update(q)
    qdot = rng.standard_normal(12)
    de_dt = (pin.difference(model, q + H * qdot, target) - pin.difference(model, q - H * qdot, target)) / (2 * H)
    J, v = posture.compute(configuration, 0.002)
    np.testing.assert_allclose(J @ qdot, -de_dt, atol=1e-8)
    np.testing.assert_allclose(v, 3.0 * pin.difference(model, q, target), atol=1e-12)
    J_rows, v_rows = posture.compute_rows(configuration, 0.002)
    np.testing.assert_allclose((qdot if J_rows is None else J_rows @ qdot), -de_dt, atol=1e-8)
    np.testing.assert_allclose(v_rows, 3.0 * pin.difference(model, q, target), atol=1e-12)


def test_posture_task_alone_is_solved_per_joint_and_clipped_by_the_speed_box(configuration, rng):
    """Hand-computed: with a posture task alone the QP is separable per joint, so with any
    positive weights ``qdot_i = clip(gain (q*_i - q_i), -v_max_i, v_max_i)``.

    Catches the joint-space kernel adding a weight or target to the wrong joint, a wrong
    sign of ``f``, or the weights leaking into the minimiser.
    """
    from harvest_qp import Solver
    from harvest_qp.limits import JointVelocityLimit

    q = _states(rng, 1)[0]
    configuration.update(q)
    target = q + rng.uniform(-0.3, 0.3, 12)
    weight = rng.uniform(1e-3, 10.0, 12)
    v_max = rng.uniform(0.2, 1.0, 12)
    posture = PostureTask(target, weight=weight, gain=4.0)
    qdot = Solver().solve(configuration, [posture], [JointVelocityLimit(configuration, max_velocity=v_max)]).qdot
    np.testing.assert_allclose(qdot, np.clip(4.0 * (target - q), -v_max, v_max), rtol=1e-7, atol=1e-9)


@pytest.mark.parametrize("per_joint", [False, True], ids=["scalar", "per-joint"])
def test_damping_task_gives_the_hand_computed_damped_least_squares(configuration, rng, per_joint):
    """Oracle: the damped least-squares solution written out with numpy and a Jacobian from
    pinocchio directly (``computeFrameJacobian`` on a fresh ``Data``):
    ``qdot = (J^T J + diag(w) + eps I)^-1 J^T V``, ``eps`` the solver's regularization; for a
    scalar ``w = lambda^2`` also ``J^T (J J^T + lambda^2 I)^-1 V`` (eps = 0 there, 1e-8 relative).

    Catches damping applied to the wrong joints or with the wrong weight, a damping task that
    also pulls towards a non-zero velocity, and a dimension mix-up of the damping rows.
    """
    from harvest_qp import Solver

    q = _states(rng, 1)[0]
    configuration.update(q)
    model, data = configuration.model, configuration.model.createData()
    J = pin.computeFrameJacobian(model, data, q, model.getFrameId("gripper"), pin.LOCAL_WORLD_ALIGNED)
    V = rng.uniform(-0.2, 0.2, 6)
    w = rng.uniform(1e-3, 1e-1, 12) if per_joint else np.full(12, 1e-2)
    twist = FrameTwistTask("gripper")
    twist.set_reference(V)
    solver = Solver()
    qdot = solver.solve(configuration, [twist, DampingTask(12, weight=w if per_joint else 1e-2)]).qdot
    expected = np.linalg.solve(J.T @ J + np.diag(w) + solver.regularization * np.eye(12), J.T @ V)
    np.testing.assert_allclose(qdot, expected, rtol=1e-7, atol=1e-10)
    if not per_joint:
        dls = J.T @ np.linalg.solve(J @ J.T + 1e-2 * np.eye(6), V)
        np.testing.assert_allclose(qdot, dls, rtol=1e-6, atol=1e-10)
    # Residual by hand: sqrt(w) * (qdot - 0).
    np.testing.assert_allclose(DampingTask(12, weight=w).residual(configuration, qdot, 0.002), np.sqrt(w) * qdot)


def test_point_jacobian(configuration, rng):
    q = _states(rng, 1)[0]
    configuration.update(q)
    point = configuration.frame_position("gripper") + [0.05, -0.02, 0.1]
    Jp = configuration.point_jacobian("gripper", point)
    qdot = rng.standard_normal(12)
    local = configuration.frame_pose("gripper").actInv(point)
    configuration.update(q + H * qdot)
    p1 = configuration.frame_pose("gripper").act(local)
    configuration.update(q - H * qdot)
    p0 = configuration.frame_pose("gripper").act(local)
    np.testing.assert_allclose(Jp @ qdot, (p1 - p0) / (2 * H), atol=1e-7)


def test_every_collision_row_matches_finite_differences(configuration, rng):
    limit = CollisionAvoidance.dual_ur5e(configuration, influence_distance=0.3, max_pairs=60)
    limit.set_obstacle_spheres(rng.uniform([0.3, -0.4, 0.9], [0.7, 0.6, 1.4], (8, 3)), 0.04)
    checked = 0
    kinds = set()
    for q in _states(rng, 8):
        qdot = rng.standard_normal(12)
        configuration.update(q)
        rows = limit.compute(configuration, 0.002)
        active = limit.active_pairs.copy()
        configuration.update(q + H * qdot)
        d_plus = limit.distances(configuration)[active]
        configuration.update(q - H * qdot)
        d_minus = limit.distances(configuration)[active]
        rate = (d_plus - d_minus) / (2 * H)
        # Rows are -d_dot/dqdot: G qdot <= h  <=>  d_dot >= -h.
        np.testing.assert_allclose(-rows.G[: len(active)] @ qdot, rate, atol=1e-6)
        checked += len(active)
        for k in active:
            a, b = limit.pair_names()[k]
            kinds.add("obstacle" if b.startswith("obstacle") else ("arm-arm" if a[:3] != b[:3] else "self"))
    assert checked > 20
    assert {"obstacle", "arm-arm"} <= kinds


def test_collision_distance_matches_brute_force_sampling(configuration, rng):
    """Capsule distances equal a dense sampling of both segments (exact kernel check)."""
    limit = CollisionAvoidance.dual_ur5e(configuration)
    configuration.update(_states(rng, 1)[0])
    d = limit.distances(configuration)
    (w0, w1), r = limit.capsule_segments(configuration), limit.cap_radius
    s = np.linspace(0, 1, 401)
    for k in rng.choice(len(d), 25, replace=False):
        a, b = limit.pair_a[k], limit.pair_b[k]
        pa = w0[a] + s[:, None] * (w1[a] - w0[a])
        pb = w0[b] + s[:, None] * (w1[b] - w0[b])
        brute = np.min(np.linalg.norm(pa[:, None] - pb[None], axis=-1)) - r[a] - r[b]
        assert d[k] <= brute + 1e-12
        assert d[k] == pytest.approx(brute, abs=2e-3)


def test_environment_primitives_pair_with_every_moving_capsule(configuration, rng):
    from harvest_qp.limits import CapsuleGeometry

    branch = CapsuleGeometry("branch", None, (0.55, -0.5, 1.35), (0.55, 0.6, 1.35), 0.02)
    limit = CollisionAvoidance.dual_ur5e(configuration, environment=[branch], influence_distance=0.5, max_pairs=200)
    names = limit.pair_names()
    moving = {a for a, b in names if b == "branch"}
    assert len(moving) == 15 and "stand" not in moving
    # Branch rows are finite-difference exact too (the branch does not move).
    q = configuration.q.copy()
    qdot = rng.standard_normal(12)
    rows = limit.compute(configuration, 0.002)
    active = [k for k in limit.active_pairs if names[k][1] == "branch"]
    assert active
    configuration.update(q + H * qdot)
    d1 = limit.distances(configuration)[active]
    configuration.update(q - H * qdot)
    d0 = limit.distances(configuration)[active]
    row_of = {k: r for r, k in enumerate(limit.active_pairs)}
    G = rows.G[[row_of[k] for k in active]]
    np.testing.assert_allclose(-G @ qdot, (d1 - d0) / (2 * H), atol=1e-6)
