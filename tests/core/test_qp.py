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
from harvest_qp.limits import JointAccelerationLimit, JointPositionLimit, JointVelocityLimit
from harvest_qp.robot.description import HOME_Q
from harvest_qp.tasks import HARD, DampingTask, FramePoseTask, FrameTwistTask


def _twist_tasks(rng, **kwargs):
    cam = FrameTwistTask("camera", **kwargs)
    grasp = FrameTwistTask("gripper", **kwargs)
    cam.set_reference(rng.normal(0, 0.05, 6))
    grasp.set_reference(rng.normal(0, 0.05, 6))
    return cam, grasp


def _pinocchio_jacobian(configuration, frame):
    """World-aligned 6 x 12 frame Jacobian from pinocchio directly (not through Configuration)."""
    import pinocchio as pin

    model = configuration.model
    data = model.createData()
    return pin.computeFrameJacobian(
        model, data, configuration.q, model.getFrameId(frame), pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
    )


@pytest.mark.parametrize("lam", [1e-3, 1e-2, 0.05])
def test_unconstrained_qp_equals_damped_pseudo_inverse_with_default_regularization(configuration, rng, lam):
    """eq:controlled_system with damping: QP == J^T (J J^T + lambda^2 I)^-1 V to 1e-8 relative.

    The right side is built from pinocchio's Jacobian and numpy, at generic and singular states
    (wrist and elbow). Bug caught: a constant regularization eps I in the Hessian (1e-10 made it
    wrong by 3.4e-5 at lambda = 1e-3) -- the default solver is used, not regularization 0.
    """
    for k in range(6):
        q = HOME_Q + rng.normal(0, 0.3, 12)
        if k % 3 == 1:
            q[4] = q[10] = 0.0  # wrist singularity on both arms
        if k % 3 == 2:
            q[2] = q[8] = 0.0  # stretched elbows
        configuration.update(q)
        cam, grasp = _twist_tasks(rng)
        qdot = Solver().solve(configuration, [cam, grasp, DampingTask(12, weight=lam**2)], [], 0.002).qdot
        J = np.vstack([_pinocchio_jacobian(configuration, "camera"), _pinocchio_jacobian(configuration, "gripper")])
        V = np.concatenate([cam.reference, grasp.reference])
        expected = J.T @ np.linalg.solve(J @ J.T + lam**2 * np.eye(12), V)
        assert np.linalg.norm(qdot - expected) <= 1e-8 * np.linalg.norm(expected)


def test_pseudo_inverse_baseline_meets_the_penrose_conditions_at_singular_states(configuration, rng):
    """eq:controlled_system with damping 0 at rank-deficient J (wrist singular, elbow stretched).

    Oracle: the four Moore-Penrose conditions on J from pinocchio, and J J^+ V equal to the
    projection of V onto range(J) from an SVD. Bug caught: a plain inverse or a transposed block.
    """
    for q_change in ({4: 0.0, 10: 0.0}, {2: 0.0, 8: 0.0}):
        q = HOME_Q + rng.normal(0, 0.2, 12)
        for j, value in q_change.items():
            q[j] = value
        configuration.update(q)
        mapper = PseudoInverseMapper(configuration)
        J = np.vstack([_pinocchio_jacobian(configuration, "camera"), _pinocchio_jacobian(configuration, "gripper")])
        U, sv, _ = np.linalg.svd(J)
        rank = int(np.sum(sv > 1e-9 * sv[0]))
        assert rank < 12, "the state must be singular"
        P = np.column_stack([mapper.map(e) for e in np.eye(12)])  # J^+ column by column
        np.testing.assert_allclose(J @ P @ J, J, atol=1e-9)
        np.testing.assert_allclose(P @ J @ P, P, atol=1e-6)
        np.testing.assert_allclose((J @ P).T, J @ P, atol=1e-9)
        np.testing.assert_allclose((P @ J).T, P @ J, atol=1e-9)
        V = rng.normal(0, 0.1, 12)
        projection = U[:, :rank] @ (U[:, :rank].T @ V)
        np.testing.assert_allclose(J @ mapper.map(V), projection, atol=1e-9)


def test_strict_priorities_match_the_null_space_projection_with_a_rank_deficient_level_1(configuration, rng):
    """Level 1 holds two contradicting gripper translation tasks (6 rows, rank 3), level 2 the camera.

    Oracle (Siciliano-Slotine, numpy pinv): qdot = J1^+ v1 + (J2 N1)^+ (v2 - J2 J1^+ v1), with
    N1 = I - J1^+ J1, the minimum-norm solution that a tiny level-3 damping selects. The level-1
    task velocity must be the average of the two references (hand-computed least squares).
    Bug caught: a level that leaks into the one above (e.g. equality rows of level 1 dropped or
    built from a full-rank assumption), which residual norms with a full-rank level 1 never showed.
    """
    for _ in range(5):
        configuration.update(HOME_Q + rng.normal(0, 0.3, 12))
        first = FrameTwistTask("gripper", weight=[1, 1, 1, 0, 0, 0], level=1)
        second = FrameTwistTask("gripper", weight=[1, 1, 1, 0, 0, 0], level=1)
        first.set_reference(np.concatenate([rng.normal(0, 0.1, 3), np.zeros(3)]))
        second.set_reference(np.concatenate([rng.normal(0, 0.1, 3), np.zeros(3)]))
        camera = FrameTwistTask("camera", level=2)
        camera.set_reference(rng.normal(0, 0.1, 6))
        tasks = [first, second, camera, DampingTask(12, weight=1e-9, level=3)]
        qdot = Solver().solve(configuration, tasks).qdot
        Jg = _pinocchio_jacobian(configuration, "gripper")[:3]
        J1 = np.vstack([Jg, Jg])
        v1 = np.concatenate([first.reference[:3], second.reference[:3]])
        J2, v2 = _pinocchio_jacobian(configuration, "camera"), camera.reference
        P1 = np.linalg.pinv(J1)
        N1 = np.eye(12) - P1 @ J1
        expected = P1 @ v1 + np.linalg.pinv(J2 @ N1) @ (v2 - J2 @ P1 @ v1)
        np.testing.assert_allclose(Jg @ qdot, 0.5 * (first.reference[:3] + second.reference[:3]), atol=1e-8)
        np.testing.assert_allclose(qdot, expected, atol=1e-6)


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
    with pytest.raises(SolverNotAvailableError, match="daqp.*proxsuite.*quadprog.*qpsolvers"):
        Solver("cplex").solve(configuration, [DampingTask(12)], [], 0.002)
    with pytest.raises(SolverNotAvailableError, match="available"):
        Solver("qpsolvers:not_a_solver").solve(configuration, [DampingTask(12)], [], 0.002)


def test_configuration_rejects_nan_q():
    with pytest.raises(InvalidInputError, match="finite"):
        Configuration.dual_ur5e(q=np.full(12, np.nan))


def test_box_conflicts_keep_the_higher_priority_box(configuration):
    """Speed limit beats position limit beats acceleration limit, joint by joint (oracle: by hand)."""
    from harvest_qp.solver import combine_boxes

    n = 3
    vel = (JointVelocityLimit(configuration), -np.ones(n), np.ones(n))
    pos = (JointPositionLimit(configuration), np.array([-5.0, -0.5, 2.0]), np.array([5.0, 0.5, 3.0]))
    acc = (JointAccelerationLimit(configuration), np.array([0.8, -0.2, -1.0]), np.array([0.9, 0.1, 1.0]))
    ordered = [vel, pos, acc]  # priority order
    lower, upper, conflicts = combine_boxes(
        [limit for limit, _, _ in ordered], np.array([lo for _, lo, _ in ordered]),
        np.array([hi for _, _, hi in ordered]), n,
    )
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
