"""The acceleration limit yields by the least amount needed; penetrating states are escaped; the stop keeps rows."""

import numpy as np
import quadprog

from harvest_qp import TaskController
from harvest_qp.limits import CollisionAvoidance
from harvest_qp.robot.description import HOME_Q
from harvest_qp.tasks import HARD, DampingTask, FrameTwistTask, PostureTask

DT = 0.002
A_MAX = 10.0


def _feasible(lower, upper, G, h) -> bool:
    """Is {lower <= x <= upper, G x <= h} non-empty? quadprog on min |x|^2, called directly (the oracle)."""
    n = lower.size
    C = np.vstack([-G, -np.eye(n), np.eye(n)])
    b = np.concatenate([-h, -upper, lower])
    try:
        quadprog.solve_qp(np.eye(n), np.zeros(n), C.T.copy(), b, 0)
    except ValueError:
        return False
    return True


def _approaching_fast(configuration, rng, collision, *, speed=2.0):
    """A collision-free state and a previous command that drives the closest arm pair together fast."""
    from benchmarks.bench_fuzz import _pull_arms_together

    while True:
        q = np.clip(HOME_Q + rng.normal(0, 0.25, 12), configuration.lower_limits, configuration.upper_limits)
        q = _pull_arms_together(configuration, collision, q, rng)
        if q is None:
            continue
        configuration.update(q)
        if collision.distances(configuration).min() > collision.safety_distance + 0.005:
            break
    # Previous command: the direction that closes the closest arm pair fastest (minus its row).
    G = collision.compute(configuration, DT).G
    rows = collision.active_pairs
    closest = rows[np.argmin(collision.distances(configuration)[rows])]
    row = G[list(rows).index(closest)]
    prev = row / np.linalg.norm(row) * speed  # G qdot > 0: approach
    return q, np.clip(prev, -np.pi, np.pi)


def test_relaxation_is_the_least_that_makes_the_rows_feasible(configuration, rng):
    """A pair approaching faster than the acceleration limit can brake for: the box widens, minimally.

    Oracle: quadprog called directly says the box widened by s* is feasible and the box widened by
    0.95 s* is not (a feasible smaller slack would contradict min ||s||^2). Bug caught: dropping the
    acceleration limit altogether (a relaxed tick jumped 6.26 rad/s in 2 ms); also reports the
    acceleration commanded.
    """
    collision = CollisionAvoidance.dual_ur5e(configuration, safety_distance=0.02, influence_distance=0.12, gain=0.5)
    cam, grasp = FrameTwistTask("camera"), FrameTwistTask("gripper")
    tasks = [cam, grasp, DampingTask(12, weight=1e-4)]
    relaxed = 0
    for _ in range(8):
        q, prev = _approaching_fast(configuration, rng, collision)
        controller = TaskController(configuration, tasks, [collision], dt=DT, max_acceleration=A_MAX)
        controller.previous_qdot = prev.copy()
        cam.set_reference(rng.normal(0, 0.5, 6))
        grasp.set_reference(rng.normal(0, 0.5, 6))
        step = controller.step(q)
        assert step.ok, step.status
        np.testing.assert_allclose(step.acceleration, (step.qdot - prev) / DT)
        solution = controller.solver_solution
        problem = solution.problems[-1]
        if not solution.relaxed:
            assert np.all(np.abs(step.qdot - prev) <= A_MAX * DT + 1e-9)
            continue
        relaxed += 1
        assert "relaxed JointAccelerationLimit" in step.status and f"{step.max_acceleration:.4g}" in step.status
        s = solution.box_relaxation
        assert np.any(s > 1e-6)
        # The safety box (the speed limit: position limits are far from these states) and the
        # acceleration box, by hand.
        vmax = configuration.velocity_limits
        lo_acc, hi_acc = prev - A_MAX * DT, prev + A_MAX * DT
        G, h = problem.G[problem.h < 1e29], problem.h[problem.h < 1e29]
        lo_safe, hi_safe = -vmax, vmax

        for factor, expected in ((1.0, True), (0.95, False)):
            widened = np.maximum(lo_acc - factor * s, lo_safe), np.minimum(hi_acc + factor * s, hi_safe)
            assert _feasible(*widened, G, h) is expected, factor
        # The command stays within the widened box: no joint changes speed more than needed.
        assert np.all(np.abs(step.qdot - prev) <= A_MAX * DT + s + 1e-8)
    assert relaxed >= 3, "the scenario must actually require relaxation"


def _penetrating_states(configuration, collision, rng, count):
    """States with an arm-arm pair 0.5..(d_s - 0.5 mm) deep inside d_s and no pair touching.

    From a collision-free state, bisect towards a random configuration with the arms swung
    together until the closest arm-arm pair is at a random target distance inside d_s.
    """
    from benchmarks.bench_fuzz import _arm_pair_mask

    arm_pair = _arm_pair_mask(collision)
    d_s = collision.safety_distance
    lo_q, hi_q = configuration.lower_limits, configuration.upper_limits
    states = []
    while len(states) < count:
        q_far = np.clip(HOME_Q + rng.normal(0, 0.25, 12), lo_q, hi_q)
        q_near = q_far + rng.normal(0, 0.5, 12)
        q_near[0] -= 1.2  # both shoulders pan towards the other arm (the other sign swings them apart)
        q_near[6] += 1.2
        q_near = np.clip(q_near, lo_q, hi_q)
        target = rng.uniform(0.001, d_s - 0.001)

        def distances(t, q_far=q_far, q_near=q_near):
            configuration.update(q_far + t * (q_near - q_far))
            return collision.distances(configuration)

        if distances(0.0).min() <= d_s or distances(1.0)[arm_pair].min() >= target:
            continue  # not collision-free to start with, or the arms never get that close
        lo, hi = 0.0, 1.0
        for _ in range(30):
            t = 0.5 * (lo + hi)
            lo, hi = (t, hi) if distances(t)[arm_pair].min() > target else (lo, t)
        d = distances(hi)
        if 0.0005 < d.min() and d[arm_pair].min() < d_s - 0.0005:
            states.append(configuration.q.copy())
    return states


def test_penetrating_states_are_escaped_within_the_acceleration_limit(configuration, rng):
    """100 states with an arm pair inside d_s, from rest, tasks pulling the arms further together.

    Oracle: distances from pinocchio placements + coal, the acceleration limit by hand. Bugs
    caught: a state inside d_s frozen or braked (fallback; FINDINGS measured 76 % of such states
    falling back) instead of separated; separation asked faster than the acceleration limit
    allows (the solver must lower the separation asked, never relax the acceleration limit);
    the penetrating pair, or any other pair, moving closer.
    """
    from benchmarks.bench_fuzz import CoalGeometry

    collision = CollisionAvoidance.dual_ur5e(configuration, safety_distance=0.02, influence_distance=0.1)
    geometry = CoalGeometry(configuration, collision)
    states = _penetrating_states(configuration, collision, rng, 100)
    cam, grasp = FrameTwistTask("camera"), FrameTwistTask("gripper")
    tasks = [cam, grasp, PostureTask(HOME_Q, weight=1e-3), DampingTask(12, weight=1e-4)]
    controller = TaskController(configuration, tasks, [collision], dt=DT, max_acceleration=A_MAX)
    lowered = 0
    for q in states:
        controller.reset(q)
        gap = configuration.frame_position("gripper") - configuration.frame_position("camera")
        cam.set_reference(np.concatenate([gap, np.zeros(3)]))  # towards each other
        grasp.set_reference(np.concatenate([-gap, np.zeros(3)]))
        d0, pair = geometry.min_distance(q)
        assert d0 < collision.safety_distance
        previous, d_prev = np.zeros(12), d0
        for _ in range(25):  # 50 ms
            step = controller.step(q)
            assert step.ok, step.status
            assert "relaxed" not in step.status, "separation must fit the acceleration limit"
            lowered += "separation asked lowered" in step.status
            assert np.all(np.abs(step.qdot - previous) <= A_MAX * DT + 1e-9)
            previous = step.qdot
            q = q + step.qdot * DT
            d = geometry.pair_distances(q, [pair])[pair]
            assert d >= d_prev - 2e-6, "the penetrating pair moved closer"
            assert geometry.min_distance(q)[0] >= d0 - 2e-6, "another pair went deeper than the start"
            d_prev = d
        assert d_prev > d0 + 1e-4, f"not escaping: {pair} {d0:.5f} -> {d_prev:.5f} m in 50 ms"
    assert lowered > 0, "the scenario must ask for more separation than the acceleration limit gives"


def test_safe_stop_keeps_collision_rows(configuration, rng):
    """When the QP is infeasible (a hard task beyond the speed limit) the stop does not drive pairs together.

    From states with a pair approaching fast near d_s, the stop QP brakes within the acceleration
    limit and keeps the dampers: no pair (coal) goes below d_s. Bug caught: the joint-wise brake,
    which took a pair from 10.9 mm to 7.6 mm (2.4 mm below d_s).
    """
    from benchmarks.bench_fuzz import CoalGeometry

    collision = CollisionAvoidance.dual_ur5e(configuration, safety_distance=0.02, influence_distance=0.12, gain=0.5)
    geometry = CoalGeometry(configuration, collision)
    impossible = FrameTwistTask("gripper", level=HARD)
    impossible.set_reference([50.0, 0, 0, 0, 0, 0])  # beyond any speed limit: infeasible
    worst = np.inf
    for _ in range(3):
        q, prev = _approaching_fast(configuration, rng, collision, speed=1.0)
        controller = TaskController(configuration, [impossible, DampingTask(12)], [collision], dt=DT,
                                    max_acceleration=A_MAX)
        controller.previous_qdot = prev.copy()
        for _ in range(100):
            step = controller.step(q)
            assert step.status.startswith("fallback") and "stop QP failed" not in step.status, step.status
            q = q + step.qdot * DT
            worst = min(worst, geometry.min_distance(q)[0])
        assert np.max(np.abs(step.qdot)) < 0.2, "the arms are coming to rest"
    assert worst >= collision.safety_distance - 1e-4
