"""Wrist F/T sensor: world frame, tool weight removed, tare, noise, and the 3 N stem pull."""

from __future__ import annotations

import numpy as np
import pytest

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.runtime.runner import run_episode
from harvest_qp.sim import ForceSensorConfig, SimRobot, VineSceneParams
from tests.sim.helpers import ForcePull, PinocchioArm


def test_pinocchio_and_mujoco_agree_on_the_gripper(blind_robot):
    arm = PinocchioArm()
    T, _ = arm.frame(blind_robot.joint_positions(), "gripper")
    np.testing.assert_allclose(T, blind_robot.site_pose("gripper"), atol=1e-9)


def test_untared_force_is_the_weight_the_gripper_holds(blind_robot):
    """World frame, tool weight removed: holding the cluster reads its weight, upwards."""
    cluster_weight = 9.81 * blind_robot.model.body_mass[blind_robot.scene.ids["cluster"]]
    f = blind_robot.wrist_force()
    np.testing.assert_allclose(f, [0.0, 0.0, cluster_weight], atol=0.03)
    # Released, the cluster hangs from its stem and the empty gripper reads ~0 (its own
    # weight is removed): after the swing settles.
    blind_robot.set_grasp(False)
    blind_robot.advance(1.5)
    np.testing.assert_allclose(blind_robot.wrist_force(), 0.0, atol=0.03)
    assert blind_robot.stem_tension() == pytest.approx(cluster_weight, rel=0.05)


def test_tare_zeroes_the_reading(blind_robot):
    blind_robot.tare_force()
    np.testing.assert_allclose(blind_robot.wrist_force(), 0.0, atol=1e-6)
    blind_robot.advance(0.2)
    np.testing.assert_allclose(blind_robot.wrist_force(), 0.0, atol=0.01)


@pytest.mark.parametrize("seed", [None, 11])
def test_pulling_to_3n_reads_the_true_tension(seed):
    """Paper's grasping task: pull the stem to f_d = 3 N; the tared F/T matches the true tension."""
    params = VineSceneParams() if seed is None else VineSceneParams.sample(seed)
    robot = SimRobot(params, camera=None)
    scene = robot.scene
    direction = scene.stem_end - scene.stem_base  # away from the branch, along the stem
    result = run_episode(robot, ForcePull(direction, force=3.0), duration=4.0, stop_at_end=False)
    assert result.ok, result.error
    log = result.log
    force, stem = log["force"], log["truth/stem_force"]
    tension = log["truth/stem_tension"]
    pulling = tension > 0.5
    assert pulling.sum() > 500
    # While pulling, the tared reading equals the force the stem resists with.
    err = np.linalg.norm(force[pulling] + stem[pulling], axis=1)
    assert err.max() < 0.1, err.max()
    # It reaches and holds 3 N (the F/T magnitude within 0.1 N of the true tension there).
    final = slice(-250, None)
    assert np.abs(tension[final] - 3.0).max() < 0.15
    assert np.abs(np.linalg.norm(force[final], axis=1) - tension[final]).max() < 0.1


def test_force_noise_is_seeded_and_has_the_configured_std():
    cfg = ForceSensorConfig(noise_std=0.05)
    a = SimRobot(camera=None, force=cfg, seed=2)
    b = SimRobot(camera=None, force=cfg, seed=2)
    c = SimRobot(camera=None, force=cfg, seed=3)
    fa, fb, fc = [], [], []
    for _ in range(400):
        for robot, out in ((a, fa), (b, fb), (c, fc)):
            robot.step()
            out.append(robot.wrist_force())
    fa, fb, fc = np.array(fa), np.array(fb), np.array(fc)
    np.testing.assert_array_equal(fa, fb)
    assert not np.array_equal(fa, fc)
    assert 0.04 < np.std(fa[:, 0]) < 0.06
    # A tare averages the last samples, so it removes the offset without the noise of one sample.
    a.tare_force()
    tared = np.array([(a.step(), a.wrist_force())[1] for _ in range(400)])
    assert abs(tared[:, 2].mean()) < 0.02


def test_force_config_validation():
    with pytest.raises(InvalidInputError, match="noise_std"):
        ForceSensorConfig(noise_std=-1.0)
    with pytest.raises(InvalidInputError, match="tare_samples"):
        ForceSensorConfig(tare_samples=0)
