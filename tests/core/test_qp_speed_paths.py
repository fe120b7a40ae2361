"""The QP step's fast paths against what they replaced (numpy, LAPACK's SVD, pinocchio, the eager lists).

Each fast path of the control tick (issue 7 section 7) is compared with an independent
computation of the same quantity: bit for bit where the fast path must not change results,
to round-off where it is a different algorithm (the QR basis of the level rows).
"""

import numpy as np
import pinocchio as pin
import pytest

from harvest_qp import Configuration, TaskController
from harvest_qp.backends import DaqpBackend
from harvest_qp.collision.kernels import clamp_approach_rows
from harvest_qp.limits import CollisionAvoidance
from harvest_qp.qp_kernels import (
    load_daqp_rows,
    orthonormal_rows_qr,
    weighted_identity_rows,
    weighted_rows,
)
from harvest_qp.robot.description import HOME_Q
from harvest_qp.solver import _orthonormal_rows
from harvest_qp.tasks import DampingTask, FrameTwistTask, PostureTask


def _low_rank(rng, m, n, rank, scale):
    return scale * rng.normal(size=(m, rank)) @ rng.normal(size=(rank, n))


@pytest.mark.parametrize("seed", range(6))
def test_orthonormal_rows_span_the_rows_and_keep_the_equalities_like_the_svd(seed):
    """Oracle: numpy's SVD (the basis used before). Same rank, same row space (projectors agree),
    orthonormal rows, and every x with ``A x = c`` satisfies the new rows.

    Bugs caught: a wrong Householder scale (rows not orthonormal), a missing pivot (rank lost
    on a rank-deficient stack), a transposed triangular solve (right-hand side wrong).
    """
    rng = np.random.default_rng(seed)
    for m, rank, scale in ((11, 11, 1.0), (14, 9, 1e-3), (5, 2, 1e3), (13, 12, 1.0), (1, 1, 1.0)):
        A = _low_rank(rng, m, 12, rank, scale)
        x0 = rng.normal(size=12)
        c = A @ x0
        rows, rhs = _orthonormal_rows(A, c)
        s = np.linalg.svd(A, compute_uv=False)
        expected_rank = int(np.sum(s > 1e-9 * max(1.0, s[0])))
        assert rows.shape == (expected_rank, 12)
        np.testing.assert_allclose(rows @ rows.T, np.eye(expected_rank), atol=1e-12)
        Vt = np.linalg.svd(A)[2][:expected_rank]
        np.testing.assert_allclose(rows.T @ rows, Vt.T @ Vt, atol=1e-9)
        np.testing.assert_allclose(rows @ x0, rhs, atol=1e-9 * max(1.0, np.abs(rhs).max()))
        # Another point of the same affine set (x0 plus a null-space direction) satisfies them too.
        null = np.eye(12) - Vt.T @ Vt
        x1 = x0 + null @ rng.normal(size=12)
        np.testing.assert_allclose(rows @ x1, rhs, atol=1e-8 * max(1.0, np.abs(rhs).max()))


def test_orthonormal_rows_drop_an_exactly_repeated_row():
    """Oracle: by hand. Two equal rows and one independent row have rank 2, and the kept rows
    reproduce both right-hand sides. Bug caught: a rank threshold that keeps a zero pivot."""
    A = np.array([[1.0, 2.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 3.0]])
    c = A @ np.array([0.5, -1.0, 2.0])
    rows = np.empty((3, 3))
    rhs = np.empty(3)
    rank = orthonormal_rows_qr(A, c, 1e-9, rows, rhs)
    assert rank == 2
    x = np.linalg.lstsq(rows[:rank], rhs[:rank], rcond=None)[0]
    np.testing.assert_allclose(A @ x, c, atol=1e-12)


def test_weighted_rows_are_bit_identical_to_numpy(configuration, rng):
    """Oracle: ``(np.sqrt(w)[:, None] * J)[w > 0]`` (the expression they replace), bit for bit.
    Bug caught: a row with zero weight kept, or sqrt(w) applied twice."""
    J = np.asfortranarray(rng.normal(size=(6, 12)))  # pinocchio hands out Fortran-ordered Jacobians
    w = np.array([1.0, 0.0, 2.5, 1e-3, 0.0, 7.0])
    out = np.full((20, 12), np.nan)
    end = weighted_rows(J, w, out, 3)
    expected = (np.sqrt(w)[:, None] * J)[w > 0]
    assert end == 3 + expected.shape[0]
    assert np.array_equal(out[3:end], expected)
    wj = rng.uniform(0, 2, 12)
    wj[[2, 7]] = 0.0
    end2 = weighted_identity_rows(wj, out, end)
    assert np.array_equal(out[end:end2], (np.sqrt(wj)[:, None] * np.eye(12))[wj > 0])


def test_load_daqp_rows_writes_what_the_slice_assignments_wrote(rng):
    """Oracle: the numpy slice assignments of the backend before (copied here), bit for bit,
    for a QP with equalities after one with more equalities (slots to clear) and without.
    Bug caught: an equality slot left over from the previous QP (a stale constraint)."""
    n, n_in, inf = 12, 5, 1e30

    def by_slices(A_buf, upper, lower, sense, A, b, G, h, lo, hi, n_eq_before):
        n_eq = A.shape[0]
        if n_eq or n_eq_before:
            A_buf[:n] = 0.0
            A_buf[:n_eq] = A
            upper[n:2 * n] = inf
            lower[n:2 * n] = -inf
            upper[n:n + n_eq] = b
            lower[n:n + n_eq] = b
            sense[n:2 * n] = 0
            sense[n:n + n_eq] = 5
        A_buf[n:] = G
        upper[2 * n:] = h
        upper[:n] = hi
        lower[:n] = lo
        return n_eq if (n_eq or n_eq_before) else n_eq_before

    buffers = [[np.zeros((n + n_in, n)), np.full(2 * n + n_in, inf), np.full(2 * n + n_in, -inf),
                np.zeros(2 * n + n_in, dtype=np.int32)] for _ in range(2)]
    n_eq_before = [0, 0]
    for n_eq in (7, 3, 0, 0, 11):
        A, b = rng.normal(size=(n_eq, n)), rng.normal(size=n_eq)
        G, h = rng.normal(size=(n_in, n)), rng.normal(size=n_in)
        lo, hi = -rng.uniform(size=n), rng.uniform(size=n)
        n_eq_before[0] = load_daqp_rows(*buffers[0], A, b, G, h, lo, hi, n_eq_before[0], inf)
        n_eq_before[1] = by_slices(*buffers[1], A, b, G, h, lo, hi, n_eq_before[1])
        for fast, slow in zip(*buffers):
            assert np.array_equal(fast, slow)


def test_kinematics_update_is_skipped_only_for_the_same_bits(monkeypatch):
    """Oracle: the bit patterns of q. The same q skips pinocchio; -0.0 for 0.0 or one ulp more
    does not. Bug caught: ``==`` semantics (0.0 == -0.0) skipping an update that changes bits."""
    config = Configuration.dual_ur5e()
    q = np.array(HOME_Q, dtype=float)
    q[0] = 0.0
    config.update(q)
    computed = []
    real = config._set_q
    monkeypatch.setattr(config, "_set_q", lambda value: (computed.append(value.copy()), real(value)))
    config._update_if_changed(q.copy())
    assert computed == []
    minus = q.copy()
    minus[0] = -0.0
    config._update_if_changed(minus)
    assert len(computed) == 1
    ulp = minus.copy()
    ulp[5] = np.nextafter(ulp[5], np.inf)
    config._update_if_changed(ulp)
    assert len(computed) == 2


def test_skipped_kinematics_update_equals_a_fresh_one(rng):
    """Oracle: pinocchio on fresh data. After ``_update_if_changed`` with the same q (skipped),
    with another q, and after the q array handed out by ``Configuration.q`` was changed in
    place, placements and Jacobians are those of the q given.
    Bug caught: comparing against the array the caller can change (a stale update skipped)."""
    config = Configuration.dual_ur5e()
    frame = config.frame_id("camera")

    def check(q):
        data = config.model.createData()
        pin.computeJointJacobians(config.model, data, q)
        pin.updateFramePlacements(config.model, data)
        expected = pin.getFrameJacobian(config.model, data, frame, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
        assert np.array_equal(config.frame_jacobian("camera"), expected)
        assert np.array_equal(config.frame_position("camera"), data.oMf[frame].translation)
        assert np.array_equal(config.q, q)

    q1 = HOME_Q + rng.normal(0, 0.2, 12)
    config.update(q1)
    config._update_if_changed(q1.copy())
    check(q1)
    q2 = q1 + 0.05
    config._update_if_changed(q2.copy())
    check(q2)
    config.q[:] = q1  # changed in place behind the kinematics' back
    config._update_if_changed(q1.copy())
    check(q1)


def test_controller_active_pairs_equal_the_limits_pairs_of_that_tick(rng):
    """Oracle: ``CollisionAvoidance.active_pair_distances`` right after the step. The lazy list
    read after a later step still holds the earlier tick's pairs and distances.
    Bug caught: a snapshot that aliases the limit's buffers (pairs of the wrong tick)."""
    config = Configuration.dual_ur5e(HOME_Q)
    limit = CollisionAvoidance.dual_ur5e(config, influence_distance=0.3)
    limit.set_obstacle_spheres(rng.uniform([0.3, -0.3, 0.9], [0.7, 0.6, 1.3], (6, 3)), 0.05)
    camera = FrameTwistTask("camera")
    camera.set_reference([0.05, 0.0, -0.05, 0.0, 0.0, 0.0])
    controller = TaskController(config, [camera, PostureTask(HOME_Q, weight=1e-3), DampingTask(12)], [limit])
    steps, eager = [], []
    for _ in range(5):
        # Another posture every tick: other pairs (a view of the limit's buffer would show the last tick's).
        q = HOME_Q + rng.normal(0, 0.15, 12)
        controller.reset()
        result = controller.step(q)
        steps.append(result)
        eager.append(limit.active_pair_distances())
    assert any(eager)
    assert len({tuple(pairs) for pairs in eager}) > 1
    for result, pairs in zip(steps, eager):
        assert result.active_pairs == pairs


def test_clamp_approach_rows_matches_the_numpy_mask():
    """Oracle: the numpy expression it replaced. Bug caught: clamping rows of other pairs, or -0.0 rows."""
    h = np.array([-0.2, 0.3, -0.1, -0.0, -0.5, 0.1])
    row_pair = np.array([0, 1, 2, 3, 0, 4])
    approach = np.array([True, False, True, True, False])
    expected = h.copy()
    expected[approach[row_pair] & (expected < 0.0)] = 0.0
    clamp_approach_rows(h, approach, row_pair, 5)  # the last row is not in use: left alone
    expected[5] = 0.1
    assert np.array_equal(h, expected)
    assert np.signbit(h[3])


def test_daqp_backend_fast_check_rejects_what_checked_rejects(rng):
    """Oracle: the scale-relative violation of ``QPProblem.scaled_violation``. An answer outside
    the tolerance raises SolverAccuracyError with the violation; one inside is returned.
    Bug caught: the inlined check returning x without looking at the violation."""
    from harvest_qp.backends import FEASIBILITY_TOLERANCE, SolverAccuracyError
    from harvest_qp.solver import QPProblem

    n = 3
    problem = QPProblem(
        H=np.eye(n), f=rng.normal(size=n), lower=-np.ones(n), upper=np.ones(n),
        A=np.zeros((0, n)), b=np.zeros(0), G=np.array([[1.0, 0.0, 0.0]]), h=np.array([0.2]),
    )
    backend = DaqpBackend()
    x = backend.solve(problem)
    assert problem.scaled_violation(x) <= FEASIBILITY_TOLERANCE

    class Answer:  # stands in for daqp.Model: returns a given x
        def __init__(self, x):
            self.x = x

        def update(self, **kwargs):
            return 0

        def solve(self):
            return self.x.copy(), 0.0, 1, {}

    bad = np.array([0.2 + 1e-5, 0.0, 0.0])  # row off by 1e-5 / (1 + 0.2 + 0.2): ~7e-6 > 1e-7
    backend._model = Answer(bad)
    with pytest.raises(SolverAccuracyError) as info:
        backend.solve(problem)
    assert info.value.violation == pytest.approx(problem.scaled_violation(bad))
    good = np.array([0.2 + 1e-9, 0.0, 0.0])
    backend._model = Answer(good)
    assert np.array_equal(backend.solve(problem), good)


def test_local_twist_rows_shared_between_tasks_follow_the_kinematics(rng):
    """Oracle: ``blkdiag(R^T, R^T)`` times pinocchio's world-aligned Jacobian, by numpy. Two
    local tasks on one frame (the second reuses the first's rows), before and after the
    configuration moves, and with the second task's own reference and gain.
    Bug caught: rows kept across a kinematics update (the second task would see the old pose)."""
    config = Configuration.dual_ur5e(HOME_Q)
    camera = FrameTwistTask("camera", weight_frame="local")
    roll = FrameTwistTask("camera", weight=[0, 0, 0, 0, 0, 1.0], weight_frame="local", gain=0.5)
    for q in (HOME_Q, HOME_Q + rng.normal(0, 0.2, 12)):
        config.update(q)
        camera.set_reference(rng.normal(size=6))
        roll.set_reference(rng.normal(size=6))
        J = pin.getFrameJacobian(config.model, config.data, config.frame_id("camera"),
                                 pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
        R = config.frame_rotation("camera")
        T = np.kron(np.eye(2), R.T)
        for task in (camera, roll):
            rows, v = task.compute_rows(config, 0.002)
            np.testing.assert_allclose(rows, T @ J, atol=1e-14)
            np.testing.assert_allclose(v, T @ (task.gain * task.reference), atol=1e-14)


def test_builtin_boxes_in_one_call_equal_each_limits_own_fill(rng):
    """Oracle: the limits' own ``fill_box`` and the solver's intersection (taken when a limit is
    a subclass). Same box, same conflicts, same command, bit for bit, also where the position
    box and the acceleration box do not overlap (conflicts) and on the first step (no previous).
    Bug caught: the fused kernel intersecting in another order or reading the wrong previous command."""
    from harvest_qp import Solver
    from harvest_qp.limits import JointAccelerationLimit, JointPositionLimit, JointVelocityLimit

    class Velocity(JointVelocityLimit):  # a subclass: the solver must take the checked path
        pass

    config = Configuration.dual_ur5e(HOME_Q)
    camera = FrameTwistTask("camera")
    camera.set_reference([0.2, -0.1, 0.1, 0.3, 0.0, 0.1])
    tasks = [camera, DampingTask(12, weight=1e-3)]

    def limits(velocity_type):
        return [JointPositionLimit(config, max_acceleration=5.0), velocity_type(config, max_velocity=1.5),
                JointAccelerationLimit(config, max_acceleration=5.0)]

    fused_limits, checked_limits = limits(JointVelocityLimit), limits(Velocity)
    fused, checked = Solver(), Solver()
    seen_conflict = False
    for k in range(6):
        q = np.clip(HOME_Q + rng.normal(0, 0.3, 12), config.lower_limits, config.upper_limits)
        if k % 2:
            q[3] = config.upper_limits[3] - 1e-4  # at the position limit: its box conflicts with the acceleration box
        previous = None if k == 0 else rng.normal(0, 1.0, 12)
        config.update(q)
        a = fused.solve(config, tasks, fused_limits, previous_qdot=previous)
        b = checked.solve(config, tasks, checked_limits, previous_qdot=previous)
        assert fused._builtin_trio and not checked._builtin_trio
        assert np.array_equal(a.lower, b.lower) and np.array_equal(a.upper, b.upper)
        expected = [(c.joint, c.limit.replace("Velocity", "JointVelocityLimit") if c.limit == "Velocity" else c.limit)
                    for c in b.conflicts]
        assert [(c.joint, c.limit) for c in a.conflicts] == expected
        assert np.array_equal(a.qdot, b.qdot)
        assert np.array_equal(fused._lowers, checked._lowers) and np.array_equal(fused._uppers, checked._uppers)
        seen_conflict |= bool(a.conflicts)
    assert seen_conflict


@pytest.mark.parametrize("count", [1, 2, 3, 4])
def test_fused_level_assembly_equals_the_per_task_kernels(rng, count):
    """Oracles: the per-task kernels called one by one (bit for bit) and numpy's
    ``sum J^T W J`` / ``-sum J^T W v`` plus the diagonal top-up (to round-off).
    Bug caught: a task skipped, the identity marker read as a 0-row Jacobian (task lost),
    or the top-up before the joint-space tasks' floor is complete."""
    from harvest_qp import qp_kernels as K

    n = 12
    entries = []
    for k in range(count):
        if k % 2:
            entries.append((None, rng.uniform(0, 1e-3, n), rng.normal(size=n)))
        else:
            w = rng.uniform(0, 2, 6)
            w[rng.integers(6)] = 0.0
            entries.append((np.asfortranarray(rng.normal(size=(6, n))), w, rng.normal(size=6)))
    reg = 5e-4

    def fresh():
        block = np.zeros((n + 2, n))
        return block, block[:n], block[n], block[n + 1]

    block_a, H_a, f_a, floor_a = fresh()
    args = []
    for J, w, v in entries:
        args += (K.IDENTITY_ROWS if J is None else J, w, v)
    getattr(K, f"assemble_level_{count}")(H_a, f_a, floor_a, reg, *args)
    block_b, H_b, f_b, floor_b = fresh()
    for J, w, v in entries:
        if J is None:
            K.accumulate_diagonal(H_b, f_b, w, v, floor_b)
        else:
            K.accumulate_task(H_b, f_b, J, w, v)
    K.top_up_diagonal(H_b, floor_b, reg)
    assert np.array_equal(block_a, block_b)
    H = sum(np.diag(w) if J is None else J.T @ np.diag(w) @ J for J, w, _ in entries)
    f = -sum(w * v if J is None else J.T @ (w * v) for J, w, v in entries)
    floor = sum((w for J, w, _ in entries if J is None), np.zeros(n))
    H = H + np.diag(np.maximum(reg - floor, 0.0))
    np.testing.assert_allclose(H_a, H, atol=1e-12)
    np.testing.assert_allclose(f_a, f, atol=1e-12)


@pytest.mark.parametrize("count", [1, 2, 3])
def test_level_equalities_in_one_call_equal_the_stacked_rows_path(rng, count):
    """Oracle: the general path (numpy stacking ``(sqrt(w)[:, None] * J)[w > 0]`` over ``A``,
    ``rows @ x`` by BLAS, then ``_orthonormal_rows``). Same orthonormal rows bit for bit (same
    stack), right-hand side to round-off (the product is summed in another order), and the
    level's solution satisfies them. Bug caught: a task's rows left out of the stack or the
    previous levels' rows ``A`` dropped (a lower level could then undo a higher one)."""
    from harvest_qp import Solver
    from harvest_qp import qp_kernels as K

    n = 12
    A = np.linalg.qr(rng.normal(size=(n, 3)))[0].T  # earlier levels' orthonormal rows
    tasks = []
    for k in range(count):
        task = DampingTask(n) if k % 2 else FrameTwistTask("camera")
        task.weight = rng.uniform(0.1, 1.0, task.dim)
        J = None if k % 2 else np.asfortranarray(rng.normal(size=(6, n)))
        tasks.append((task, J, None))
    x = rng.normal(size=n)
    solver = Solver()
    rows, rhs = solver._level_equalities(A, tasks, n, x)
    stack = np.vstack([A, *[(np.sqrt(t.weight)[:, None] * (np.eye(n) if J is None else J))[t.weight > 0]
                            for t, J, _ in tasks]])
    rows_ref, rhs_ref = _orthonormal_rows(stack, stack @ x)
    assert np.array_equal(rows, rows_ref)
    np.testing.assert_allclose(rhs, rhs_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(rows @ x, rhs, atol=1e-12)
    assert rows.shape[0] == min(stack.shape[0], n) == np.linalg.matrix_rank(stack)
    assert K.IDENTITY_ROWS.shape == (0, 0)


def test_public_step_recomputes_after_a_direct_pinocchio_write():
    """``TaskController.step(q)`` after ``pin.forwardKinematics`` moved ``configuration.data``
    elsewhere gives the command of a fresh controller at ``q``; only the loop's private
    ``_step(..., reuse_kinematics=True)`` may skip the update.

    Catches: the public step skipping the kinematics when q's bytes equal the last update's
    (stale placements and Jacobians after a user's own pinocchio call; found by an audit)."""
    q = np.array(HOME_Q, float)
    other = q + 0.3

    def controller():
        c = Configuration.dual_ur5e(q)
        task = FrameTwistTask("gripper")
        task.set_reference(np.array([0.05, 0.0, 0.02, 0.0, 0.0, 0.1]))
        return c, TaskController(c, [task, DampingTask(12)], dt=0.002)

    c_fresh, fresh = controller()
    expected = fresh.step(q).qdot
    c, tc = controller()
    tc.configuration._set_q(q)
    pin.forwardKinematics(c.model, c.data, other)
    pin.computeJointJacobians(c.model, c.data, other)
    pin.updateFramePlacements(c.model, c.data)
    np.testing.assert_array_equal(tc.step(q).qdot, expected)


def test_fast_built_step_results_carry_the_dataclass_constructors_state(rng):
    """Oracle: the dataclasses' own constructors (``ControlStep(...)``, ``Solution(...)``,
    ``QPProblem(...)``) called with the same values: the hot path's ``object.__new__`` +
    ``__dict__`` objects must hold the same attributes and compare equal, and
    ``ControlStep.active_pairs`` stays ``[]`` without a collision limit.

    Bugs caught: a field left out of a fast-built object (``Solution.relaxed`` missing: the
    controller's status check raises and every tick falls back), ``active_pairs`` not
    initialised (AttributeError on read), a field stored under another name."""
    from dataclasses import fields

    from harvest_qp.controller import ControlStep
    from harvest_qp.solver import QPProblem, Solution

    config = Configuration.dual_ur5e(HOME_Q)
    limit = CollisionAvoidance.dual_ur5e(config, influence_distance=0.3)
    camera = FrameTwistTask("camera")
    camera.set_reference([0.05, 0.0, -0.05, 0.0, 0.0, 0.0])
    posture = PostureTask(HOME_Q, weight=1e-3)
    posture.level = 2
    for limits in ([limit], []):
        controller = TaskController(config, [camera, posture, DampingTask(12)], limits)
        q = HOME_Q + rng.normal(0, 0.1, 12)
        result = controller._step(q, reuse_kinematics=False)
        assert result.status == "ok"
        reference = ControlStep(
            qdot=result.qdot, status=result.status, conflicts=result.conflicts, acceleration=result.acceleration
        )
        assert set(vars(result)) - {"_pair_snapshots"} == set(vars(reference))
        if not limits:
            assert result.active_pairs == [] and result == reference
        else:
            assert result.active_pairs == limit.active_pair_distances()
        solution = controller.solver_solution
        assert set(vars(solution)) == {f.name for f in fields(Solution)}
        assert solution == Solution(**{f.name: getattr(solution, f.name) for f in fields(Solution)})
        assert solution.relaxed == [] and solution.box_relaxation is None and solution.row_relaxation is None
        assert [p.level for p in solution.problems] == [1, 2]
        for problem in solution.problems:
            assert set(vars(problem)) == {f.name for f in fields(QPProblem)}
            rebuilt = QPProblem(**vars(problem))
            assert all(np.array_equal(getattr(rebuilt, f.name), getattr(problem, f.name)) for f in fields(QPProblem))


def test_broadphase_keeps_every_pair_within_the_influence_distance(rng):
    """Oracle: the same kernel with an infinite influence distance (no broadphase: every pair
    gets the exact segment test). Every pair closer than ``d_i`` keeps its exact distance and
    witness parameters bit for bit; a pair the broadphase skipped is truly farther than ``d_i``.

    Bugs caught: a bounding sphere without one capsule's half-length or radius, or the
    squared test comparing against ``d_i`` instead of ``(d_i + r_a + r_b)^2`` (close pairs
    skipped: rows missing)."""
    from harvest_qp.collision import kernels

    config = Configuration.dual_ur5e(HOME_Q)
    limit = CollisionAvoidance.dual_ur5e(config, influence_distance=0.25)
    limit.set_obstacle_spheres(rng.uniform([0.3, -0.3, 0.9], [0.7, 0.6, 1.3], (8, 3)), 0.05)
    influence = limit.influence_distance
    checked = 0
    for _ in range(20):
        config.update(HOME_Q + rng.normal(0, 0.4, 12))
        exact = limit.distances(config)  # influence = inf inside
        w0, w1 = limit._w0, limit._w1
        n = limit.pair_a.shape[0]
        d, s, t = np.empty(n), np.empty(n), np.empty(n)
        kernels.pair_distances(limit.pair_a, limit.pair_b, limit.cap_radius, w0, w1, influence, d, s, t)
        d_all, s_all, t_all = np.empty(n), np.empty(n), np.empty(n)
        kernels.pair_distances(limit.pair_a, limit.pair_b, limit.cap_radius, w0, w1, np.inf, d_all, s_all, t_all)
        assert np.array_equal(d_all, exact)
        close = exact < influence
        checked += int(close.sum())
        assert np.array_equal(d[close], exact[close])
        assert np.array_equal(s[close], s_all[close]) and np.array_equal(t[close], t_all[close])
        skipped = np.isinf(d)
        assert np.all(exact[skipped] >= influence)
    assert checked > 20


def _three_level_problem(config, rng):
    """Tasks on three levels (1, 4 and 1 tasks, joint-space rows with zero weights) and limits with
    collision rows: every branch of the fused DAQP levels (equalities fused, general, none)."""
    camera = FrameTwistTask("camera", weight=np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0]))
    camera.set_reference(rng.normal(0, 0.05, 6))
    gripper = FrameTwistTask("gripper", weight=np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0]), level=2)
    gripper.set_reference(rng.normal(0, 0.05, 6))
    roll = FrameTwistTask("camera", weight=np.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0]), weight_frame="local", level=2)
    roll.set_reference(rng.normal(0, 0.1, 6))
    posture = PostureTask(HOME_Q, weight=np.r_[1e-3, 1e-3, np.zeros(10)], level=2)
    damping2 = DampingTask(12, weight=np.r_[np.zeros(11), 1e-4], level=2)
    damping3 = DampingTask(12, weight=1e-4, level=3)
    limit = CollisionAvoidance.dual_ur5e(config, influence_distance=0.3)
    return [camera, gripper, roll, posture, damping2, damping3], [limit]


class _GeneralDaqp(DaqpBackend):
    """DAQP's backend as a subclass: the solver gives it the general path (its own ``solve``)."""


def test_fused_daqp_levels_equal_the_general_path_bit_for_bit(rng):
    """Oracles: the general path of the same solver class (each level through
    ``DaqpBackend.solve``, the separate check, clip and equality kernels), forced by making the
    backends a subclass; and quadprog (another QP solver) on the deepest level's problem.
    Over random states and previous commands, three levels with collision rows: the same
    command and the same H, f, A, b of every level, bit for bit, and DAQP's buffers alike.

    Bugs caught (planted and seen failing): the fused check-and-clip skipping the clip; the
    last level returned without the check and clip."""
    import quadprog

    config = Configuration.dual_ur5e(HOME_Q)
    tasks, limits = _three_level_problem(config, rng)
    fused, general = TaskController(config, tasks, limits).solver, TaskController(config, tasks, limits).solver
    controller = TaskController(config, tasks, limits)
    limits = controller.limits
    # Levels 2 and 3 leave joints free: a diagonal of 1e-5 keeps their Hessians well conditioned
    # (with 1e-10 DAQP and quadprog report such levels infeasible and proxsuite, not bit-for-bit
    # repeatable, answers).
    fused.regularization = general.regularization = 1e-5
    fused_levels = []  # the levels the fused path solved (a spy: every level from the second step on)
    inner = fused._daqp_level
    fused._daqp_level = lambda *args: fused_levels.append(args[1]) or inner(*args)
    for _ in range(12):
        # States away from the position limits and previous commands within the acceleration
        # box of a feasible QP (an infeasible one goes to the fallback backends, compared below).
        q = HOME_Q + rng.normal(0, 0.15, 12)
        previous = rng.normal(0, 0.005, 12)
        config.update(q)
        for backend in general._backends.values():
            backend.__class__ = _GeneralDaqp  # the general path, every level
        a = fused.solve(config, tasks, limits, previous_qdot=previous)
        b = general.solve(config, tasks, limits, previous_qdot=previous)
        assert np.array_equal(a.qdot, b.qdot)
        assert a.retries == b.retries == []
        assert [p.level for p in a.problems] == [1, 2, 3]
        for pa, pb in zip(a.problems, b.problems):
            for name in ("H", "f", "A", "b", "lower", "upper", "G", "h"):
                assert np.array_equal(getattr(pa, name), getattr(pb, name)), name
        for key, backend in fused._backends.items():
            other = general._backends[key]
            assert np.array_equal(backend._A, other._A) and np.array_equal(backend._sense, other._sense)
            assert np.array_equal(backend._upper, other._upper) and backend._n_eq == other._n_eq
        # Level 1 by quadprog: its optimum holds the equalities level 2 was given (the fused
        # level 1 found the same task velocities); the command keeps every level's equalities.
        first = a.problems[0]
        rows = [-first.G[first.h < 1e29], -np.eye(12), np.eye(12)]
        bounds = [-first.h[first.h < 1e29], -first.upper, first.lower]
        x1 = quadprog.solve_qp(first.H, -first.f, np.vstack(rows).T.copy(), np.concatenate(bounds))[0]
        np.testing.assert_allclose(a.problems[1].A @ x1, a.problems[1].b, atol=1e-6)
        np.testing.assert_allclose(a.problems[2].A @ a.qdot, a.problems[2].b, atol=1e-9)
    assert fused_levels == [1, 2, 3] * 11
    assert all(type(b) is DaqpBackend and b._shape == (12, limits[0]._G.shape[0])
                                for b in fused._backends.values())


class _Answer:
    """Stands in for ``daqp.Model``: returns a given x and exit flag."""

    def __init__(self, x, flag=1):
        self.x, self.flag = x, flag

    def update(self, *args, **kwargs):
        return 0

    def solve(self):
        return self.x.copy(), 0.0, self.flag, {}


@pytest.mark.parametrize("level", [1, 2, 3])
@pytest.mark.parametrize("flag, offset", [(1, 1.0), (-2, 0.0), (-1, 0.0)])
def test_fused_daqp_level_recovers_from_a_rejected_answer_like_the_general_path(rng, flag, offset, level):
    """Oracle: the general path (``DaqpBackend.solve`` inside ``_solve_qp``) given the same wrong
    answer. A DAQP answer far outside the constraints (SolverAccuracyError), a cycling flag or an
    infeasibility flag on any level (fused equalities, general equalities, last level) is handed
    to the fallback backends: the same retries, the same command bit for bit, and after a
    failure flag the DAQP model is dropped in both.

    Bug caught (planted and seen failing): the last level accepting x without the check (the
    answer 1 rad/s outside the box became the command after the clip)."""
    config = Configuration.dual_ur5e(HOME_Q)
    tasks, limits = _three_level_problem(config, rng)
    limits = TaskController(config, tasks, limits).limits
    solvers = [TaskController(config, tasks, limits).solver for _ in range(2)]
    for solver in solvers:
        solver.regularization = 1e-5  # see test_fused_daqp_levels_equal_the_general_path_bit_for_bit
    q = np.clip(HOME_Q + rng.normal(0, 0.2, 12), config.lower_limits, config.upper_limits)
    config.update(q)
    results = []
    for which, solver in enumerate(solvers):
        solver.solve(config, tasks, limits)  # sets the DAQP models up
        backend = solver._backends[("daqp", level)]
        if which:
            backend.__class__ = _GeneralDaqp
        backend._model = _Answer(config.velocity_limits + offset, flag)
        results.append(solver.solve(config, tasks, limits))
        assert (backend._model is None) == (flag < 0)
    a, b = results
    assert a.retries == b.retries and a.retries and a.retries[0].startswith("daqp: ")
    assert np.array_equal(a.qdot, b.qdot)
    assert np.all(np.abs(a.qdot) <= config.velocity_limits)


def test_check_clip_leaves_a_rejected_answer_untouched(rng):
    """Oracle: ``max_scaled_violation`` and ``np.clip``. Accepted: x clipped in place exactly as
    ``np.clip``; rejected: x unchanged (the error keeps DAQP's own answer) and no equality rows.
    Bug caught: clipping before the check (a rejected answer made to look feasible)."""
    from harvest_qp import qp_kernels as K

    n = 4
    lower, upper = -np.ones(n), np.ones(n)
    A, b = np.zeros((0, n)), np.zeros(0)
    G, h = np.array([[1.0, 1.0, 0.0, 0.0]]), np.array([0.5])
    inside = np.array([0.2, 0.3 - 1e-9, 1.0 + 1e-12, -1.0 - 1e-12])
    assert K.max_scaled_violation(inside, lower, upper, A, b, G, h) <= 1e-7
    expected = np.clip(inside, lower, upper)
    assert K.check_clip(inside, lower, upper, A, b, G, h, 1e-7) and np.array_equal(inside, expected)
    outside = np.array([0.4, 0.4, 2.0, 0.0])
    kept = outside.copy()
    accepted, rows, rhs = K.check_clip_equalities_1(outside, lower, upper, A, b, G, h, 1e-7, 1e-9,
                                                    np.empty((n, n)), K.IDENTITY_ROWS, np.ones(n))
    assert not accepted and rows.shape == (0, n) and rhs.shape == (0,)
    assert np.array_equal(outside, kept)


def test_reused_q_is_taken_only_for_the_same_bits_of_a_native_float64_vector():
    """Oracle: ``as_vector`` (the check the loop's q passed at its update). ``_reuse_current_q``
    takes a q only when its bytes equal the last checked q's: then the stored q is a copy with
    those values; any other q (other bits, -0.0, float32, another length, a list) returns None
    and the caller checks it. Bug caught: a float32 or short q taken (the kernels would read
    past its end) or the stored q aliasing the caller's array."""
    q = np.array(HOME_Q, float)
    config = Configuration.dual_ur5e(q)
    same = q.copy()
    stored = config._reuse_current_q(same)
    assert stored is not None and stored is not same and config.q is stored and np.array_equal(stored, q)
    minus = q.copy()
    minus[q == 0.0] = -0.0
    assert (q == 0.0).any() and config._reuse_current_q(minus) is None
    assert config._reuse_current_q(q.astype(np.float32)) is None
    assert config._reuse_current_q(q.astype(">f8")) is None
    assert config._reuse_current_q(q[:11]) is None
    assert config._reuse_current_q(list(q)) is None
    assert config._reuse_current_q(np.r_[q, q][::2]) is None  # other values (every other entry)
    # The loop's path: a NaN q is not the last checked one, so the step checks it and falls back.
    controller = TaskController(config, [DampingTask(12)])
    bad = q.copy()
    bad[0] = np.nan
    result = controller._step(bad, reuse_kinematics=True)
    assert result.status.startswith("fallback") and "finite" in result.status


def test_reference_fast_path_copies_and_checks_like_as_vector(rng):
    """Oracle: ``as_vector`` (the checked path). A float64 6-vector is stored as a copy with the
    same bits; NaN, a wrong length, a float32 or byte-swapped array and a list take the checked
    path (the same errors and messages naming the task). Bug caught (planted and seen failing):
    the fast path storing the caller's array itself (a later in-place change of the caller's
    array moved the reference)."""
    from harvest_qp.exceptions import InvalidInputError
    from harvest_qp.validation import as_vector

    task = FrameTwistTask("camera", weight_frame="local")
    twist = rng.normal(size=6)
    task.set_reference(twist)
    stored = task.reference
    assert stored is not twist and np.array_equal(stored, as_vector(twist, 6, "x"))
    twist[0] += 1.0
    assert not np.array_equal(task.reference, twist)
    for other in (twist.astype(np.float32), twist.astype(">f8"), list(twist)):
        task.reference = other
        assert task.reference.dtype == np.float64 and np.array_equal(task.reference, as_vector(other, 6, "x"))
    bad = twist.copy()
    bad[2] = np.nan
    with pytest.raises(InvalidInputError, match=r"FrameTwistTask\('camera'\) reference twist must be finite"):
        task.set_reference(bad)
    with pytest.raises(InvalidInputError, match=r"reference twist must have shape \(6,\)"):
        task.set_reference(np.zeros(5))


def test_posture_rows_equal_the_numpy_formula_bit_for_bit(configuration, rng):
    """Oracle: numpy's ``gain * (target - q)``. The compiled posture rows give the same bits
    and a fresh array each call. Bug caught (planted and seen failing): the difference taken
    the other way round (``q - target``: the posture pushed away from its target)."""
    task = PostureTask(HOME_Q + rng.normal(0, 0.2, 12), weight=1e-3, gain=0.7)
    configuration.update(HOME_Q + rng.normal(0, 0.2, 12))
    J, v = task.compute_rows(configuration, 0.002)
    assert J is None
    assert np.array_equal(v, 0.7 * (task.target - configuration.q))
    _, again = task.compute_rows(configuration, 0.002)
    assert again is not v and np.array_equal(again, v)


def test_collision_rows_with_the_clamp_fused_equal_the_unclamped_rows_masked(rng):
    """Oracle: the same limit's rows without approach-only capsules, clamped by a numpy mask
    (``h = 0`` where the row's pair is (approach-only capsule, obstacle sphere) and ``h < 0``).
    With obstacle spheres inside ``d_s`` of approach-only capsules, the fused kernel gives the
    same G bit for bit and the masked h. Bug caught (planted and seen failing): the fused call
    skipping the clamp (an approach-only capsule pushed away by the map's cells)."""
    config = Configuration.dual_ur5e(HOME_Q)
    limit = CollisionAvoidance.dual_ur5e(config, influence_distance=0.2)
    moving = [limit.capsule_names[i] for i in limit._moving]
    chosen = [name for name in moving if name.startswith("grasp_")][:3]
    assert chosen
    ends = [limit._w0, limit._w1]
    limit.compute(config, 0.002)  # world end points of the capsules at HOME_Q
    index = [limit.capsule_names.index(name) for name in chosen]
    centres = np.array([ends[k % 2][i] for k, i in enumerate(index)]) + rng.normal(0, 1e-3, (len(index), 3))
    limit.set_obstacle_spheres(centres, 0.0)
    limit.set_approach_only(())
    free = limit.compute(config, 0.002)
    G_free, h_free, n = free.G.copy(), free.h.copy(), limit.num_rows
    row_pair = limit.row_pairs.copy()
    limit.set_approach_only(chosen)
    clamped = limit.compute(config, 0.002)
    mask = np.zeros_like(h_free, dtype=bool)
    mask[:n] = limit._approach_pair[row_pair] & (h_free[:n] < 0.0)
    assert mask.any()
    expected = h_free.copy()
    expected[mask] = 0.0
    assert limit.num_rows == n and np.array_equal(limit.row_pairs, row_pair)
    assert np.array_equal(clamped.G, G_free) and np.array_equal(clamped.h, expected)


def _levels_problem(config, rng, counts):
    """Tasks on levels 1, 2, ... with ``counts`` tasks each (frame twists, local roll rows, posture and
    damping rows with zero weights), and collision rows."""
    makers = [
        lambda level: FrameTwistTask("camera", weight=np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0]), level=level),
        lambda level: FrameTwistTask("gripper", weight=np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0]), level=level),
        lambda level: FrameTwistTask("camera", weight=np.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0]),
                                     weight_frame="local", level=level),
        lambda level: PostureTask(HOME_Q, weight=np.r_[1e-3, 1e-3, np.zeros(10)], level=level),
        lambda level: DampingTask(12, weight=np.r_[np.zeros(11), 1e-4], level=level),
    ]
    tasks, k = [], 0
    for level, count in enumerate(counts, start=1):
        for _ in range(count):
            task = makers[k % len(makers)](level)
            k += 1
            if isinstance(task, FrameTwistTask):
                task.set_reference(rng.normal(0, 0.05, 6))
            tasks.append(task)
    return tasks, [CollisionAvoidance.dual_ur5e(config, influence_distance=0.3)]


def _same_solution(a, b):
    assert np.array_equal(a.qdot, b.qdot)
    assert a.retries == b.retries and a.relaxed == b.relaxed and a.conflicts == b.conflicts
    for name in ("box_relaxation", "row_relaxation"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None and y is None) or np.array_equal(x, y), name
    assert [p.level for p in a.problems] == [p.level for p in b.problems]
    for pa, pb in zip(a.problems, b.problems):
        for name in ("H", "f", "A", "b", "lower", "upper", "G", "h"):
            assert np.array_equal(getattr(pa, name), getattr(pb, name)), name


@pytest.mark.parametrize("counts", [(2, 3), (1, 3, 1), (3, 4), (2, 1, 2), (1, 4, 1), (5, 1)])
def test_solve_step_equals_the_general_solve_bit_for_bit(rng, counts):
    """Oracle: the general path (``Solver._solve`` with every level through ``DaqpBackend.solve``,
    forced by a subclass) on a twin solver. ``_solve_step`` (the loop's path: the cascade inline,
    levels handing over in one compiled call, the acceleration in the last one) gives the same
    command, the same problems bit for bit, DAQP's buffers alike, and an acceleration equal to
    ``(qdot - previous) / dt``; structures it cannot fuse (4 tasks above a level, 5 tasks) take
    ``_cascade`` and still agree. A spy checks which path ran.

    Bugs caught (planted and seen failing): the hand-over kernel assembling the lower level on the
    upper level's A (not the equalities just computed); the acceleration as ``(previous - x) / dt``."""
    config = Configuration.dual_ur5e(HOME_Q)
    tasks, limits = _levels_problem(config, rng, counts)
    fast, general = TaskController(config, tasks, limits).solver, TaskController(config, tasks, limits).solver
    limits = TaskController(config, tasks, limits).limits
    fast.regularization = general.regularization = 1e-5  # see test_fused_daqp_levels_equal_the_general_path
    fast.fallback_backends = general.fallback_backends = ("quadprog",)  # proxsuite is not bit-for-bit repeatable
    cascades = []
    inner = fast._cascade
    fast._cascade = lambda *args, **kwargs: cascades.append(1) or inner(*args, **kwargs)
    fusable = all(c <= 3 for c in counts[:-1]) and counts[-1] <= 4
    dt = 0.002
    retried = 0
    for step in range(10):
        q = HOME_Q + rng.normal(0, 0.15, 12)
        previous = rng.normal(0, 0.005, 12)
        config.update(q)
        for backend in general._backends.values():
            backend.__class__ = _GeneralDaqp
        a, accel = fast._solve_step(config, tasks, limits, dt, previous)
        b = general._solve(config, tasks, limits, dt, previous)
        _same_solution(a, b)  # retries included (a level DAQP reports infeasible goes to quadprog in both)
        retried += bool(a.retries)
        if accel is not None:
            assert np.array_equal(accel, (b.qdot - previous) / dt)
        # Computed by the last level's kernel when every level fused and the last was accepted.
        if fusable and len(cascades) == 1 and step > 0 and not a.retries:
            assert accel is not None
        if not fusable:
            assert accel is None
        for key, backend in fast._backends.items():
            other = general._backends[key]
            if isinstance(backend, DaqpBackend):
                assert np.array_equal(backend._A, other._A) and np.array_equal(backend._sense, other._sense)
                assert np.array_equal(backend._upper, other._upper) and np.array_equal(backend._lower, other._lower)
                assert backend._n_eq == other._n_eq
    # The first step sets the DAQP models up (the general cascade); later ones fuse if they can
    # (after a DAQP failure flag its model is set up again by the general cascade).
    # (a relaxation solves the cascade once more).
    assert (1 <= len(cascades) <= 1 + retried) if fusable else len(cascades) >= 10, (len(cascades), retried)


def _outcome(call):
    """The solution, or the type and message of the exception the call raised."""
    try:
        return call()
    except Exception as err:  # noqa: BLE001 - compared between the two paths
        return type(err), str(err)


def _same_outcome(a, b):
    assert type(a) is type(b)
    if isinstance(a, tuple):
        assert a == b
    else:
        _same_solution(a, b)


@pytest.mark.parametrize("level", [1, 2, 3])
@pytest.mark.parametrize("flag, offset", [(1, 1.0), (-2, 0.0), (-1, 0.0)])
def test_solve_step_recovers_from_a_rejected_answer_like_the_general_path(rng, flag, offset, level):
    """Oracle: the general path (``_solve`` through ``DaqpBackend.solve``) given the same wrong DAQP
    answer on one level (outside the box: SolverAccuracyError; cycling; infeasible): the same
    retries, command and problems bit for bit (or the same error), and DAQP's model dropped or
    kept alike.

    Bug caught (planted and seen failing): a rejected upper level's hand-over leaving the lower
    level's block assembled on stale equalities (the lower level solved on the wrong rows)."""
    config = Configuration.dual_ur5e(HOME_Q)
    tasks, limits = _levels_problem(config, rng, (1, 3, 1))
    limits = TaskController(config, tasks, limits).limits
    solvers = [TaskController(config, tasks, limits).solver for _ in range(2)]
    q = np.clip(HOME_Q + rng.normal(0, 0.2, 12), config.lower_limits, config.upper_limits)
    config.update(q)
    previous = np.zeros(12)
    results, models = [], []
    for which, solver in enumerate(solvers):
        solver.regularization = 1e-5
        solver.fallback_backends = ("quadprog",)  # proxsuite is not bit-for-bit repeatable
        solver._solve(config, tasks, limits, 0.002, previous)  # sets the DAQP models up
        backend = solver._backends[("daqp", level)]
        if which:
            backend.__class__ = _GeneralDaqp
        backend._model = _Answer(config.velocity_limits + offset, flag)
        if which:
            results.append(_outcome(lambda s=solver: s._solve(config, tasks, limits, 0.002, previous)))
        else:
            results.append(_outcome(lambda s=solver: s._solve_step(config, tasks, limits, 0.002, previous)[0]))
        models.append(type(backend._model))
    _same_outcome(*results)
    assert models[0] is models[1]
    if not isinstance(results[0], tuple):  # retried, or relaxed after every backend failed
        solution = results[0]
        assert (solution.retries and solution.retries[0].startswith("daqp: ")) or solution.box_relaxation is not None


def test_solve_step_relaxes_like_the_general_path():
    """Oracle: the general path (``_solve``). Over fuzz-like states (wide joint spread, previous
    commands up to half the speed limit, collision rows) some of which relax the acceleration
    box or the separation rows: the same solution bit for bit (relaxations included) or the
    same error, every state.

    Bug caught (planted and seen failing): the relaxation given the cascade's last equalities
    (``A, b`` instead of the problem's own ``A0, b0``)."""
    rng = np.random.default_rng(11)
    config = Configuration.dual_ur5e(HOME_Q)
    tasks, limits = _levels_problem(config, rng, (2, 3))
    limits = TaskController(config, tasks, limits).limits
    fast, general = (TaskController(config, tasks, limits).solver for _ in range(2))
    # proxsuite is not bit-for-bit repeatable (the general path differs from itself by ~1e-11
    # after it): the exact fallback only.
    fast.fallback_backends = general.fallback_backends = ("quadprog",)
    relaxed = 0
    for _ in range(60):
        q = np.clip(HOME_Q + rng.normal(0, 0.6, 12), config.lower_limits, config.upper_limits)
        previous = rng.uniform(-0.5, 0.5, 12) * config.velocity_limits
        config.update(q)
        a = _outcome(lambda p=previous: fast._solve_step(config, tasks, limits, 0.002, p)[0])
        b = _outcome(lambda p=previous: general._solve(config, tasks, limits, 0.002, p))
        _same_outcome(a, b)
        relaxed += not isinstance(a, tuple) and a.box_relaxation is not None
    assert relaxed >= 2


def test_controller_loop_step_equals_the_public_step_bit_for_bit(rng):
    """Oracle: the public ``step`` (checks, kinematics recomputed, the general solve) on a twin
    controller. The loop's ``_step(q, reuse_kinematics=True)`` after ``configuration.update(q)``
    gives the same command, acceleration and status every tick, and the same problems.
    Bug caught (planted and seen failing): the fast path's acceleration divided by the wrong dt."""
    results = []
    for fast in (True, False):
        r = np.random.default_rng(7)
        config = Configuration.dual_ur5e(HOME_Q)
        tasks, limits = _levels_problem(config, r, (2, 3))
        controller = TaskController(config, tasks, limits, dt=0.004)
        controller.solver.fallback_backends = ("quadprog",)  # proxsuite is not bit-for-bit repeatable
        out = []
        for _ in range(8):
            q = HOME_Q + r.normal(0, 0.1, 12)
            if fast:
                config.update(q)
                step = controller._step(q, reuse_kinematics=True)
            else:
                step = controller.step(q)
            out.append((step, controller.solver_solution))
        results.append(out)
    for (a, sa), (b, sb) in zip(*results):
        assert a.status == b.status and a.ok
        assert np.array_equal(a.qdot, b.qdot) and np.array_equal(a.acceleration, b.acceleration)
        _same_solution(sa, sb)


def test_frame_twist_reference_subclass_overrides_keep_working():
    """Bug caught (audit): ``set_reference`` and the ``reference`` setter swapped which one
    delegates, so a subclass whose ``set_reference`` assigns ``self.reference`` recursed forever
    and a subclass overriding the setter was bypassed by ``set_reference`` (the loop's call).

    Oracle: each subclass's own rule (a clip, a halving) applied to the stored reference.
    """

    class Clipped(FrameTwistTask):
        def set_reference(self, twist):
            self.reference = np.clip(np.asarray(twist, float), -0.1, 0.1)

    class Halved(FrameTwistTask):
        @FrameTwistTask.reference.setter
        def reference(self, twist):
            FrameTwistTask.reference.fset(self, 0.5 * np.asarray(twist, float))

    clipped, halved = Clipped("camera"), Halved("camera")
    clipped.set_reference(np.ones(6))
    halved.set_reference(np.ones(6))
    assert np.array_equal(clipped.reference, np.full(6, 0.1))
    assert np.array_equal(halved.reference, np.full(6, 0.5))


def test_solve_step_without_a_previous_command_equals_the_general_solve():
    """Oracle: ``_solve`` with ``previous_qdot=None`` (the acceleration box around zero). The loop's
    path given None takes the general cascade (no acceleration to compute) with the same result.
    Bug caught (planted and seen failing): the None guard dropped (the rate kernel given None)."""
    rng = np.random.default_rng(5)
    config = Configuration.dual_ur5e(HOME_Q)
    tasks, limits = _levels_problem(config, rng, (2, 3))
    limits = TaskController(config, tasks, limits).limits
    fast, general = (TaskController(config, tasks, limits).solver for _ in range(2))
    fast.fallback_backends = general.fallback_backends = ("quadprog",)  # proxsuite is not repeatable
    for _ in range(3):
        config.update(HOME_Q + rng.normal(0, 0.1, 12))
        a, accel = fast._solve_step(config, tasks, limits, 0.002, None)
        _same_solution(a, general._solve(config, tasks, limits, 0.002, None))
        assert accel is None
