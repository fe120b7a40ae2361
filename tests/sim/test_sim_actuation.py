"""UR5e-like speedj actuation: tracking, acceleration/velocity/torque limits, stop, joint limits."""

from __future__ import annotations

import numpy as np
import pytest

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.robot import ur5e
from harvest_qp.runtime.interface import RobotInterface
from harvest_qp.sim import ActuationConfig, SimRobot, build_vine_scene
from tests.sim.helpers import arm_dof_addresses, arm_qpos_addresses


def test_sim_robot_implements_the_interface(blind_robot):
    assert isinstance(blind_robot, RobotInterface)
    assert blind_robot.control_period == 0.002
    assert blind_robot.time == 0.0
    q = blind_robot.joint_positions()
    assert q.shape == (12,) and blind_robot.joint_velocities().shape == (12,)
    np.testing.assert_allclose(q, blind_robot.scene.home_q, atol=1e-3)
    q[:] = 0.0  # returned arrays are copies
    assert np.any(blind_robot.joint_positions() != 0.0)


def _track(robot: SimRobot, amplitude, duration: float) -> tuple[np.ndarray, float]:
    """Joint errors against the integral of ``amplitude * sin(pi t)`` commands [rad], max tension [N].

    The motion must stay free of contacts (arms and vine collide physically): a contact
    would stop the arm and this would no longer measure the servo.
    """
    q_ref = robot.joint_positions()
    errors, tension = [], 0.0
    dt = robot.control_period
    for k in range(int(round(duration / dt))):
        qd = amplitude * np.sin(np.pi * k * dt)
        robot.send_joint_velocities(qd)
        robot.step()
        q_ref = q_ref + qd * dt
        errors.append(robot.joint_positions() - q_ref)
        tension = max(tension, abs(robot.stem_tension()))
        assert not any(robot.contact_counts().values()), (k, robot.contact_counts())
    return np.array(errors), tension


#: 0.6 rad/s on every joint, with signs that keep both arms clear of each other, of
#: themselves and of the vine (all +0.6 folds the camera arm's wrist onto its upper arm).
FREE_SWING = np.tile([-0.6, 0.6, -0.6, 0.6, 0.6, 0.6], 2)


def test_velocity_tracking_on_a_smooth_reference(blind_robot):
    """0.6 sin(pi t) rad/s on all 12 joints for 3 s: < 5 mrad rms (the notes measured ~1)."""
    # Released: the grasping arm would otherwise stretch the stem by decimetres.
    blind_robot.set_grasp(False)
    errors, _ = _track(blind_robot, FREE_SWING, 3.0)
    rms = np.sqrt(np.mean(errors**2))
    assert rms < 5e-3, rms
    assert np.abs(errors).max() < 1e-2


def test_velocity_tracking_while_holding_the_cluster(blind_robot):
    """The camera arm at 0.6 rad/s, the grasping arm gently (the stem pulls back at 400 N/m)."""
    amplitude = np.r_[FREE_SWING[:6], np.full(6, 0.03)]
    errors, tension = _track(blind_robot, amplitude, 2.0)
    assert np.sqrt(np.mean(errors**2)) < 5e-3
    assert blind_robot.holding and tension > 1.0  # the stem did pull back


def test_acceleration_and_velocity_limits_are_respected():
    amax = 4.0
    robot = SimRobot(camera=None, actuation=ActuationConfig(max_acceleration=amax))
    robot.set_grasp(False)  # free arms: the held stem would stop the grasping arm
    dt = robot.control_period
    cmd = np.zeros(12)
    # Pans and wrist-3 joints: the arms stay clear of each other and of the vine (2 pi is
    # clipped to the 180 deg/s limit).
    cmd[[0, 5, 6, 11]] = [1.0, -1.5, -2.0 * np.pi, 0.8]
    robot.send_joint_velocities(cmd)
    refs, vels, torques = [], [], []
    for _ in range(600):
        robot.step()
        refs.append(robot.velocity_reference())
        vels.append(robot.joint_velocities())
        torques.append(robot.data.qfrc_actuator[arm_dof_addresses(robot.model)].copy())
        assert not any(robot.contact_counts().values())
    refs, vels, torques = np.array(refs), np.array(vels), np.array(torques)
    # The reference ramps at exactly the acceleration limit and stops at the speed limit.
    assert np.abs(np.diff(refs, axis=0)).max() <= amax * dt + 1e-12
    np.testing.assert_allclose(refs[-1], np.clip(cmd, -np.pi, np.pi), atol=1e-12)
    # The joints follow it: measured accelerations stay near the limit, speeds below 180 deg/s.
    acc = np.diff(vels, axis=0) / dt
    assert np.abs(acc).max() < 1.5 * amax
    assert np.abs(vels).max() < np.pi * 1.02
    assert np.abs(vels[-1] - refs[-1]).max() < 0.02
    # Torques within the UR5e limits (gravity compensation included).
    limits = np.tile(ur5e.TORQUE_LIMITS, 2)
    assert np.all(np.abs(torques) <= limits + 1e-9)


def test_stop_brings_the_arms_to_rest_within_the_acceleration_limit():
    robot = SimRobot(camera=None, actuation=ActuationConfig(max_acceleration=5.0))
    robot.set_grasp(False)
    robot.send_joint_velocities(np.full(12, 0.5))
    robot.advance(0.3)
    assert np.abs(robot.joint_velocities()).max() > 0.45
    t0 = robot.time
    refs = [robot.velocity_reference()]
    robot.stop()
    refs.append(robot.velocity_reference())
    # 0.5 rad/s at 5 rad/s^2 takes 0.1 s to ramp down (no faster); stop returns once at rest.
    assert 0.1 - 1e-9 <= robot.time - t0 <= 0.35
    assert np.abs(robot.joint_velocities()).max() < 1e-3
    assert np.all(refs[-1] == 0.0)


def test_commands_stop_at_the_joint_limits():
    """A joint driven at its limit stops within the margin (the servo reads the model's ranges).

    The limit is narrowed on the camera wrist 3 (the elbow cannot reach its +-pi limits: the
    folded forearm's wrist hits the upper arm first, a physical contact now).
    """
    scene = build_vine_scene()
    wrist = scene.model.joint("cam_wrist_3_joint").id
    hi = float(scene.home_q[5] + 0.6)
    scene.model.jnt_range[wrist, 1] = hi
    robot = SimRobot(scene, camera=None)
    cmd = np.zeros(12)
    cmd[5] = 3.0  # camera wrist 3 towards the narrowed limit
    robot.send_joint_velocities(cmd)
    robot.advance(1.0)
    margin = ActuationConfig().position_margin
    assert hi - margin - 0.02 < robot.joint_positions()[5]
    assert robot.joint_positions()[5] <= hi - margin + 2e-3
    assert abs(robot.joint_velocities()[5]) < 0.05


def test_invalid_commands_are_rejected(blind_robot):
    with pytest.raises(InvalidInputError, match="shape"):
        blind_robot.send_joint_velocities(np.zeros(6))
    with pytest.raises(InvalidInputError, match="finite"):
        blind_robot.send_joint_velocities(np.full(12, np.nan))
    # Not numbers at all: the package's error naming the value (was numpy's ValueError; an audit).
    for bad in ("x", ["a"] * 12, {"q": 1}):
        with pytest.raises(InvalidInputError, match="12 numbers"):
            blind_robot.send_joint_velocities(bad)
    with pytest.raises(InvalidInputError, match="duration"):
        blind_robot.advance(-1.0)


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [({"bandwidth": 0.0}, "bandwidth"), ({"max_acceleration": (1.0, 2.0)}, "max_acceleration"),
     ({"max_following_error": -1.0}, "max_following_error")],
)  # fmt: skip
def test_actuation_config_validation(kwargs, words):
    with pytest.raises(InvalidInputError, match=words):
        ActuationConfig(**kwargs)


def test_control_period_must_be_a_multiple_of_the_timestep(default_scene):
    with pytest.raises(InvalidInputError, match="control_period"):
        SimRobot(default_scene, camera=None, control_period=0.003)
    robot = SimRobot(default_scene, camera=None, control_period=0.004)
    robot.step()
    assert robot.time == pytest.approx(0.004)


def test_servo_update_matches_the_speedj_law_step_by_step(default_scene):
    """The compiled servo step against the speedj law written out with numpy (the oracle).

    Per joint and tick: qd_ref ramps towards the command within a_max dt, q_ref integrates
    it, stops at the joint limits (qd_ref = 0 there), stays within the following-error
    bound of the measured joint, and ctrl = q_ref + (kv / kp) qd_ref. Random commands,
    joint positions near the limits and far from the reference make every branch act.
    Catches a kernel that forgets to zero qd_ref at a limit, clamps in the wrong order or
    writes the controls of the wrong actuators.
    """
    from harvest_qp.sim.actuation import ActuationConfig, SpeedjServo

    robot = SimRobot(default_scene, camera=None)
    m, d = robot.model, robot.data
    actuators = np.array([m.actuator(name).id for name in default_scene.actuator_names])
    qpos_ids = arm_qpos_addresses(m)
    fresh = SpeedjServo(m, actuators, qpos_ids, ActuationConfig())
    ctrl_ids = m.actuator_ctrladr[actuators]
    # The servo's constants from the model: joint range less the margin, kv / kp feed-forward.
    joints = m.actuator_trnid[actuators, 0]
    lo = m.jnt_range[joints, 0] + fresh.config.position_margin
    hi = m.jnt_range[joints, 1] - fresh.config.position_margin
    feed_forward = -m.actuator_biasprm[actuators, 2] / m.actuator_gainprm[actuators, 0]
    rng = np.random.default_rng(3)
    q_ref = rng.uniform(lo, hi)
    fresh.reset(q_ref)
    qd_ref = np.zeros(12)
    dt, e = 0.002, fresh.config.max_following_error
    limits_hit = clamped = 0
    for k in range(400):
        if k % 20 == 0:
            fresh.command(rng.uniform(-3.0, 3.0, 12))
            # Some joints next to a limit, some far from the reference.
            q_ref[:3] = np.where(rng.random(3) < 0.5, lo[:3] + 1e-4, hi[:3] - 1e-4)
            fresh.q_ref[:] = q_ref
        d.qpos[qpos_ids] = q_ref + rng.normal(0.0, 0.06, 12)
        # Oracle: the law in numpy.
        step = fresh.acc_limit * dt
        qd = qd_ref + np.clip(fresh.qd_cmd - qd_ref, -step, step)
        target = q_ref + qd * dt
        clipped = np.clip(target, lo, hi)
        qd[clipped != target] = 0.0
        q = d.qpos[qpos_ids]
        expected_ref = np.clip(clipped, q - e, q + e)
        expected_ctrl = expected_ref + feed_forward * qd
        limits_hit += int(np.sum(clipped != target))
        clamped += int(np.sum(expected_ref != clipped))
        fresh.update(d, dt)
        np.testing.assert_array_equal(fresh.qd_ref, qd)
        np.testing.assert_array_equal(fresh.q_ref, expected_ref)
        np.testing.assert_array_equal(d.ctrl[ctrl_ids], expected_ctrl)
        qd_ref, q_ref = qd, expected_ref
    assert limits_hit > 10 and clamped > 10
