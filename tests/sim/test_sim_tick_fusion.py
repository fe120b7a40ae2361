"""The fused per-tick simulation paths equal MuJoCo's own functions and the unfused step.

Speed work folded the payload Jacobian into the servo kernel, the divergence check and the
wrist sensor's sample into one call, and the ground truth into fewer calls. Oracles:
``mujoco.mj_jac`` (bit for bit), a reference step written with the unfused calls
(``mj_jac``, the servo and payload kernels, ``mj_step2``/``mj_step1``, the tear check, the
sensor's own ``_sample``), and the robot's public per-quantity methods.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from harvest_qp.sim import SimRobot, VineSceneParams, build_vine_scene
from harvest_qp.sim.actuation import _servo_step
from harvest_qp.sim.robot import SimulationError, _add_payload_torque, _payload_jacobian


@pytest.fixture(scope="module")
def robots(default_scene):
    """Two robots in the same scene: one stepped by the library, one by the reference step."""
    return SimRobot(default_scene, camera=None), SimRobot(default_scene, camera=None)


def test_payload_jacobian_equals_mj_jac_bit_for_bit(robots):
    """Bug caught: a wrong cross-product term, offset origin or dof chain in the in-kernel Jacobian.

    Oracle: ``mujoco.mj_jac`` at the held cluster's centre of mass on the gripper body, over
    random arm poses (every one of the 3 x nv entries compared, zeros included).
    Planted and caught: ``t1 = cdof[i, 0] * o2 - cdof[i, 2] * o0`` (terms swapped).
    """
    robot = robots[0]
    m, d = robot.model, robot.data
    rng = np.random.default_rng(5)
    home = robot.scene.home_q
    for _ in range(200):
        d.qpos[robot._qpos_ids] = home + rng.normal(0.0, 0.8, 12)
        mujoco.mj_forward(m, d)
        expected = np.zeros((3, m.nv))
        mujoco.mj_jac(m, d, expected, None, robot._cluster_xipos, robot._grasp_tool)
        got = np.full((3, m.nv), np.nan)  # every entry must be written
        _payload_jacobian(got, d.cdof, d.subtree_com, robot._jac_root, robot._cluster_xipos,
                          robot._jac_last_dof, robot._dof_parentid)  # fmt: skip
        np.testing.assert_array_equal(got, expected)
        assert np.count_nonzero(got[:, robot._grasp_dofs]) > 6  # the grasp arm's columns are live
    robot.reset()


def _reference_tick(robot: SimRobot) -> None:
    """SimRobot.step before the fusion: mj_jac, servo + payload, step2/step1, tear, physics check, sample."""
    m, d, servo = robot.model, robot.data, robot._servo
    for _ in range(robot._substeps):
        if robot.payload_compensation and robot._holding:
            mujoco.mj_jac(m, d, robot._jacp, None, robot._cluster_xipos, robot._grasp_tool)
            _servo_step(servo.qd_ref, servo.qd_cmd, servo.acc_limit, m.opt.timestep, servo.q_ref, servo._q_lo,
                        servo._q_hi, d.qpos, servo.qpos_ids, servo.config.max_following_error, servo._ff, d.ctrl,
                        servo.ctrl_ids)  # fmt: skip
            _add_payload_torque(robot._jacp, robot._grasp_dofs, robot._payload_weight, d.ctrl, robot._grasp_ctrl,
                                robot._grasp_kp)  # fmt: skip
        else:
            servo.update(d, m.opt.timestep)
        mujoco.mj_step2(m, d)
        mujoco.mj_step1(m, d)
        robot._check_tear()
    robot._check_physics()
    robot._ticks += 1
    robot._force._sample(d, robot.control_period)


def test_fused_step_equals_the_unfused_step_bit_for_bit(robots):
    """Bug caught: a fused call that reads a stale buffer, skips the payload torque or mis-writes the sample.

    Oracle: the same robot stepped by ``_reference_tick`` (the unfused calls). Joint state,
    controls, wrist readings (and the tare history), stem tension and its maximum must be
    equal bit for bit over 300 ticks of changing commands, through a release of the grasp.
    Planted and caught: ``last[c] = site_force[c]`` (tool weight dropped) in ``_finish_tick``.
    """
    fused, reference = robots
    fused.reset()
    reference.reset()
    assert fused._force._plain
    rng = np.random.default_rng(11)
    for k in range(300):
        if k % 20 == 0:
            qdot = np.r_[rng.normal(0, 0.2, 6), rng.normal(0, 0.2, 6)]
            fused.send_joint_velocities(qdot)
            reference.send_joint_velocities(qdot)
        if k == 150:  # without the payload term too
            fused.set_grasp(False)
            reference.set_grasp(False)
        fused.step()
        _reference_tick(reference)
        np.testing.assert_array_equal(fused.data.qpos, reference.data.qpos)
        np.testing.assert_array_equal(fused.data.qvel, reference.data.qvel)
        np.testing.assert_array_equal(fused.data.ctrl, reference.data.ctrl)
        np.testing.assert_array_equal(fused.wrist_force(), reference.wrist_force())
        assert fused._force._count == reference._force._count
        assert fused._ticks == reference._ticks
        assert fused._max_tension == reference._max_tension
    np.testing.assert_array_equal(fused._force._history, reference._force._history)
    fused.tare_force()
    reference.tare_force()
    np.testing.assert_array_equal(fused.wrist_force(), reference.wrist_force())


def test_fused_tear_check_tears_on_the_same_tick():
    """Bug caught: the fused tension measured on a stale state, or the tear applied a tick late.

    Oracle: the unfused reference step on a twin robot whose stem tears at 0.5 N: both tear
    on the same tick, at the same time, with the same maximum tension, and stay equal after.
    """
    scene = build_vine_scene(VineSceneParams(stem_break_force=0.5))
    fused, reference = SimRobot(scene, camera=None), SimRobot(scene, camera=None)
    qdot = np.r_[np.zeros(6), 0.3, -0.3, 0.3, 0.0, 0.0, 0.0]
    fused.send_joint_velocities(qdot)
    reference.send_joint_velocities(qdot)
    for _ in range(400):
        fused.step()
        _reference_tick(reference)
        assert fused.stem_torn == reference.stem_torn
        assert fused._max_tension == reference._max_tension
        np.testing.assert_array_equal(fused.data.qpos, reference.data.qpos)
    assert fused.stem_torn and fused.stem_tear_time == reference.stem_tear_time


def test_break_force_of_a_scene_replaced_after_construction_is_honoured():
    """Bug caught (audit): the fused tick compared the tension with a break force cached at
    construction, so after ``robot.scene`` was replaced by one with a lower break force the
    plain-sensor robot never tore while a noisy-sensor robot (the unfused path) did.

    Oracle: the unfused path (a robot with a force-noise fault takes it) and the scene's own
    break force: both tear, on the same tick, once the replaced scene's 0.5 N is exceeded.
    """
    import dataclasses

    from harvest_qp.sim.robot import SensorFaults

    scene = build_vine_scene()  # break force far above what this pull reaches
    lowered = dataclasses.replace(scene, params=dataclasses.replace(scene.params, stem_break_force=0.5))
    ticks = []
    for faults in (None, SensorFaults(force_noise_std=1e-9)):
        robot = SimRobot(scene, camera=None, **({"faults": faults} if faults else {}))
        robot.scene = lowered
        robot.send_joint_velocities(np.r_[np.zeros(6), 0.3, -0.3, 0.3, 0.0, 0.0, 0.0])
        torn_at = None
        for k in range(400):
            robot.step()
            if robot.stem_torn:
                torn_at = k
                break
        ticks.append(torn_at)
    assert ticks[0] is not None and ticks[0] == ticks[1]


def test_fused_step_still_refuses_a_diverged_state(default_scene):
    """Bug caught: the fused divergence check lost (a NaN velocity would be stepped on silently).

    Oracle: a non-finite joint velocity must raise SimulationError, and the wrist sensor
    must not take a sample from the diverged state. Planted and caught: ``_finish_tick``
    without its ``_diverged`` test.
    """
    robot = SimRobot(default_scene, camera=None)
    robot.step()
    count = robot._force._count
    # After step1 the velocity is read as is: a NaN written after a step is what the check sees.
    original = mujoco.mj_step1

    def poisoned(m, d):
        original(m, d)
        d.qvel[0] = np.nan

    mujoco.mj_step1 = poisoned
    try:
        with pytest.raises(SimulationError, match="unstable"):
            robot.step()
    finally:
        mujoco.mj_step1 = original
    assert robot._force._count == count


def test_inlined_ground_truth_equals_its_parts_and_honours_overrides(default_scene):
    """Bug caught: the inlined ground truth reporting another value than the public method of
    that quantity, dropping or reordering a key, or ignoring a subclass's or an instance's override.

    Oracle: the robot's public per-quantity methods (``stem_tension``, ``stem_force``,
    ``velocity_reference``, ``contact_counts``, ``min_vine_distance``) on the same state.
    Planted and caught: ``"stem_tension_max": self._max_tension`` replaced by the tension now.
    """
    robot = SimRobot(default_scene, camera=None)
    pull = np.r_[np.zeros(6), 0.2, -0.2, 0.2, 0.0, 0.0, 0.0]
    for k in range(120):
        if k % 60 == 0:
            robot.send_joint_velocities(pull if k == 0 else -pull)  # pull, then ease off
        robot.step()
        got = robot.ground_truth()
        expected = {
            "stem_tension": robot.stem_tension(),
            "stem_force": robot.stem_force(),
            "qdot_ref": robot.velocity_reference(),
            "stem_torn": float(robot.stem_torn),
            "stem_tension_max": robot._max_tension,
            **{f"contacts_{kind}": float(n) for kind, n in robot.contact_counts().items()},
            "min_vine_distance": robot.min_vine_distance(),
            "min_vine_distance_so_far": robot._min_vine_distance,
            "frames_lost": float(robot.frames_lost),
        }
        assert list(got) == list(expected)
        for key, value in expected.items():
            np.testing.assert_array_equal(got[key], value, err_msg=key)
    assert robot._max_tension > robot.stem_tension()  # the maximum is not the value now

    class Shifted(SimRobot):
        def stem_tension(self) -> float:
            return 123.0

    shifted = Shifted(default_scene, camera=None)
    assert shifted.ground_truth()["stem_tension"] == 123.0
    robot.contact_counts = lambda: {"arm_arm": 7, "arm_vine": 0, "arm_stand": 0, "arm_floor": 0}
    assert robot.ground_truth()["contacts_arm_arm"] == 7.0


def test_ground_truth_honours_a_part_patched_on_the_class(default_scene):
    """Bug caught (audit): the inlined ground truth decided at construction whether a part was
    overridden, so ``mock.patch.object(SimRobot, "stem_tension", ...)`` (the usual way a test
    fakes a reading), made before or after the robot was built, was never seen.

    Oracle: the patched method's own value, for a robot built before and one built inside the
    patch; the real reading again once the patch is gone.
    """
    from unittest import mock

    from harvest_qp.loop.episode import episode_ground_truth

    before = SimRobot(default_scene, camera=None)
    real = before.ground_truth()["stem_tension"]
    with mock.patch.object(SimRobot, "stem_tension", lambda self: 123.0):
        assert before.ground_truth()["stem_tension"] == 123.0
        assert SimRobot(default_scene, camera=None).ground_truth()["stem_tension"] == 123.0
        assert episode_ground_truth(before)()["stem_tension"] == 123.0
    assert before.ground_truth()["stem_tension"] == real
    with mock.patch.object(SimRobot, "ground_truth", lambda self: {"stem_tension": 99.0}):
        assert episode_ground_truth(before)()["stem_tension"] == 99.0
