"""SimRobot's tick: stem tension and tear, divergence, payload compensation and its ground truth.

Oracles: the stem's force sensor through numpy (``site_force_world``) and the stem's
geometry, the robot's public per-quantity methods, the scene's break force, MuJoCo's own
physics (a held payload without compensation sags).
"""

from __future__ import annotations

import dataclasses
import math
from unittest import mock

import mujoco
import numpy as np
import pytest

from harvest_qp.sim import SimRobot, SimulationError, build_vine_scene
from harvest_qp.sim.force import site_force_world
from tests.sim.helpers import arm_qpos_addresses


def test_stem_tension_is_the_sensor_force_signed_towards_the_stem_base():
    """Bug caught: a wrong row/column of the site rotation or a wrong sign of the tension.

    Oracle: numpy's ``site_force_world`` (R f) and the direction from the stem end to the
    stem base, over states of a pulled and pushed stem.
    """
    robot = SimRobot(camera=None)
    m, d = robot.model, robot.data
    ids = robot.scene.ids
    rng = np.random.default_rng(2)
    signs = set()
    for _ in range(40):
        robot.send_joint_velocities(np.r_[np.zeros(6), rng.normal(0, 0.3, 6)])
        for _ in range(5):
            robot.step()
        f = site_force_world(m, d, ids["stem_force"], ids["stem_end_site"])
        towards_base = np.asarray(robot.scene.stem_base) - d.site_xpos[ids["stem_end_site"]]
        expected = math.copysign(np.linalg.norm(f), 1.0 if f @ towards_base >= 0 else -1.0)
        assert robot.stem_tension() == pytest.approx(expected, rel=1e-12, abs=1e-12)
        np.testing.assert_allclose(robot.stem_force(), f, rtol=1e-12, atol=1e-12)
        signs.add(expected > 0)
    assert True in signs


def test_stem_tears_on_the_first_tick_above_the_break_force_of_a_replaced_scene():
    """Bug caught (audit): a break force cached at construction, so that after ``robot.scene``
    was replaced by one with a lower break force the robot never tore; a tear a tick late.

    Oracle: the replaced scene's break force (0.5 N) and the true tension of each tick: the
    stem tears on the first tick whose tension (or maximum tension) exceeds it, not before.
    """
    scene = build_vine_scene()  # break force far above what this pull reaches
    lowered = dataclasses.replace(scene, params=dataclasses.replace(scene.params, stem_break_force=0.5))
    robot = SimRobot(scene, camera=None)
    robot.scene = lowered
    robot.send_joint_velocities(np.r_[np.zeros(6), 0.3, -0.3, 0.3, 0.0, 0.0, 0.0])
    for _ in range(400):
        robot.step()
        truth = robot.ground_truth()
        if robot.stem_torn:
            assert truth["stem_tension_max"] > 0.5 and truth["stem_torn"] == 1.0
            assert robot.time - robot.control_period - 1e-12 <= robot.stem_tear_time <= robot.time
            break
        assert truth["stem_tension_max"] <= 0.5
    assert robot.stem_torn


def test_a_diverged_state_is_refused(default_scene):
    """Bug caught: a NaN velocity stepped on silently, or a wrist sample taken from it.

    Oracle: a non-finite joint velocity must raise SimulationError, leave the wrist reading
    as it was, and refuse every later step until a reset.
    """
    robot = SimRobot(default_scene, camera=None)
    robot.step()
    before = robot.wrist_force()
    original = mujoco.mj_step1

    def poisoned(m, d):
        original(m, d)
        d.qvel[0] = np.nan

    with mock.patch.object(mujoco, "mj_step1", poisoned), pytest.raises(SimulationError, match="unstable"):
        robot.step()
    np.testing.assert_array_equal(robot.wrist_force(), before)
    with pytest.raises(SimulationError, match="reset"):
        robot.step()
    robot.reset()
    robot.step()


def test_payload_compensation_is_the_clusters_weight_through_the_tool_jacobian(default_scene):
    """Bug caught: the payload torque with a wrong sign, on the wrong joints, at the wrong point
    or missing.

    Oracle: finite differences. Two identical robots step once from the same state, one
    with the compensation switched off: the grasping arm's controls differ by
    ``-(J^T m g) / kp``, J the tool-fixed point at the cluster's centre of mass
    differentiated joint by joint (``mj_kinematics`` on perturbed joints), m the cluster's
    mass, kp the servo gains. Planted and caught: the torque subtracted instead of added.
    """
    on, off = SimRobot(default_scene, camera=None), SimRobot(default_scene, camera=None)
    off.payload_compensation = False
    m = on.model
    ids = on.scene.ids
    tool, cluster = ids["grasp_tool"], ids["cluster"]
    qpos_ids = arm_qpos_addresses(m)[6:]
    scratch = mujoco.MjData(m)
    scratch.qpos[:] = on.data.qpos
    mujoco.mj_kinematics(m, scratch)
    point = scratch.xipos[cluster].copy()
    local = scratch.xmat[tool].reshape(3, 3).T @ (point - scratch.xpos[tool])
    jac = np.zeros((3, 6))
    eps = 1e-6
    for k, adr in enumerate(qpos_ids):
        moved = []
        for sign in (1.0, -1.0):
            scratch.qpos[:] = on.data.qpos
            scratch.qpos[adr] += sign * eps
            mujoco.mj_kinematics(m, scratch)
            moved.append(scratch.xpos[tool] + scratch.xmat[tool].reshape(3, 3) @ local)
        jac[:, k] = (moved[0] - moved[1]) / (2 * eps)
    weight = m.body_mass[cluster] * m.opt.gravity
    actuators = np.array([m.actuator(name).id for name in on.scene.actuator_names])[6:]
    expected = -(jac.T @ weight) / m.actuator_gainprm[actuators, 0]
    on.step()
    off.step()
    ctrl = m.actuator_ctrladr[actuators]
    np.testing.assert_allclose(on.data.ctrl[ctrl] - off.data.ctrl[ctrl], expected, rtol=1e-5, atol=1e-9)
    assert np.abs(expected).max() > 1e-4  # the weight does load the arm
    np.testing.assert_array_equal(on.data.ctrl[m.actuator_ctrladr[:6]], off.data.ctrl[m.actuator_ctrladr[:6]])


def test_ground_truth_equals_its_parts_and_honours_overrides(default_scene):
    """Bug caught: the ground truth reporting another value than the public method of that
    quantity, dropping or reordering a key, or ignoring a subclass's, an instance's or a
    class patch's override (``mock.patch.object``, the usual way a test fakes a reading).

    Oracle: the robot's public per-quantity methods on the same state.
    """
    from harvest_qp.sim.paper_episode import episode_ground_truth

    robot = SimRobot(default_scene, camera=None)
    pull = np.r_[np.zeros(6), 0.2, -0.2, 0.2, 0.0, 0.0, 0.0]
    tensions = []
    for k in range(120):
        if k % 60 == 0:
            robot.send_joint_velocities(pull if k == 0 else -pull)  # pull, then ease off
        robot.step()
        tensions.append(robot.stem_tension())
        got = robot.ground_truth()
        expected = {
            "stem_tension": robot.stem_tension(),
            "stem_force": robot.stem_force(),
            "qdot_ref": robot.velocity_reference(),
            "stem_torn": float(robot.stem_torn),
            "stem_tension_max": max([0.0, *tensions]),  # from 0 at the reset
            **{f"contacts_{kind}": float(n) for kind, n in robot.contact_counts().items()},
            "min_vine_distance": robot.min_vine_distance(),
            "min_vine_distance_so_far": got["min_vine_distance_so_far"],
            "frames_lost": float(robot.frames_lost),
        }
        assert list(got) == list(expected)
        for key, value in expected.items():
            np.testing.assert_array_equal(got[key], value, err_msg=key)
    assert max(tensions) > robot.stem_tension()  # the maximum is not the value now

    class Shifted(SimRobot):
        def stem_tension(self) -> float:
            return 123.0

    assert Shifted(default_scene, camera=None).ground_truth()["stem_tension"] == 123.0
    robot.contact_counts = lambda: {"arm_arm": 7, "arm_vine": 0, "arm_stand": 0, "arm_floor": 0}
    assert robot.ground_truth()["contacts_arm_arm"] == 7.0
    before = SimRobot(default_scene, camera=None)
    real = before.ground_truth()["stem_tension"]
    with mock.patch.object(SimRobot, "stem_tension", lambda self: 123.0):
        assert before.ground_truth()["stem_tension"] == 123.0
        assert episode_ground_truth(before)()["stem_tension"] == 123.0
    assert before.ground_truth()["stem_tension"] == real
    with mock.patch.object(SimRobot, "ground_truth", lambda self: {"stem_tension": 99.0}):
        assert episode_ground_truth(before)()["stem_tension"] == 99.0
