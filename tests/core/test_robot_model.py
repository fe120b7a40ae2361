"""The shipped dual-UR5e: one source of truth, read alike by pinocchio, MuJoCo, placo and DH."""

import warnings

import mujoco
import numpy as np
import pinocchio as pin
import pytest

from harvest_qp.robot import description as desc
from harvest_qp.robot import generate, paths, ur5e


def test_generated_files_are_up_to_date():
    for name, text in generate.generated_files().items():
        assert (paths.robot_dir() / name).read_text() == text, (
            f"robots/dual_ur5e/{name} is stale: run python -m harvest_qp.robot.generate"
        )


def _random_q(rng, n=12):
    lo = np.array([lim[0] for lim in ur5e.POSITION_LIMITS] * 2)
    hi = np.array([lim[1] for lim in ur5e.POSITION_LIMITS] * 2)
    return rng.uniform(lo, hi)[:n]


def test_pinocchio_mujoco_and_dh_agree_on_flange_and_task_frames(rng):
    model = pin.buildModelFromUrdf(str(paths.urdf_path()))
    data = model.createData()
    mj = mujoco.MjModel.from_xml_path(str(paths.scene_path()))
    md = mujoco.MjData(mj)
    assert [model.names[i] for i in range(1, model.njoints)] == desc.joint_names()
    assert [mj.joint(i).name for i in range(mj.njnt)][:12] == desc.joint_names()
    for _ in range(50):
        q = _random_q(rng)
        pin.framesForwardKinematics(model, data, q)
        md.qpos[:12] = q
        mujoco.mj_kinematics(mj, md)
        for k, prefix in enumerate(desc.ARM_PREFIXES):
            T_dh = ur5e.dh_flange_pose(q[6 * k : 6 * k + 6], desc.mount_transform(prefix))
            tool = desc.TOOLS[prefix].name
            T_pin = data.oMf[model.getFrameId(tool)].homogeneous
            body = mj.body(tool).id
            np.testing.assert_allclose(T_pin, T_dh, atol=1e-9)
            np.testing.assert_allclose(md.xpos[body], T_dh[:3, 3], atol=1e-9)
            np.testing.assert_allclose(md.xmat[body].reshape(3, 3), T_dh[:3, :3], atol=1e-9)
            for frame in desc.TOOLS[prefix].frames:
                oMf = data.oMf[model.getFrameId(frame.name)]
                site = mj.site(frame.name).id
                np.testing.assert_allclose(md.site_xpos[site], oMf.translation, atol=1e-9)
                np.testing.assert_allclose(md.site_xmat[site].reshape(3, 3), oMf.rotation, atol=1e-9)


def test_placo_reads_the_same_urdf():
    placo = pytest.importorskip("placo")
    robot = placo.RobotWrapper(str(paths.urdf_path()), placo.Flags.ignore_collisions)
    q = desc.HOME_Q + 0.1
    for name, value in zip(desc.joint_names(), q):
        robot.set_joint(name, value)
    robot.update_kinematics()
    model = pin.buildModelFromUrdf(str(paths.urdf_path()))
    data = model.createData()
    pin.framesForwardKinematics(model, data, q)
    for frame in ("camera", "gripper", "cutter_tip"):
        T_placo = robot.get_T_world_frame(frame)
        np.testing.assert_allclose(T_placo, data.oMf[model.getFrameId(frame)].homogeneous, atol=1e-9)


def test_mujoco_scene_compiles_and_steps_one_second_without_warnings():
    mj = mujoco.MjModel.from_xml_path(str(paths.scene_path()))
    md = mujoco.MjData(mj)
    md.qpos[:12] = desc.HOME_Q
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for _ in range(int(1.0 / mj.opt.timestep)):
            mujoco.mj_step(mj, md)
    assert all(md.warning[i].number == 0 for i in range(len(md.warning)))
    assert np.all(np.isfinite(md.qpos)) and np.all(np.isfinite(md.qvel))


def test_task_frame_conventions(configuration):
    # {C}: z is the view direction; at home the camera looks forward (+x, towards the vine).
    R_c = configuration.frame_rotation("camera")
    assert R_c[:, 2] @ np.array([1.0, 0, 0]) > 0.99
    # {G}: y is the crop direction; at home the gripper holds the cluster hanging down.
    R_g = configuration.frame_rotation("gripper")
    assert R_g[:, 1] @ np.array([0, 0, -1.0]) > 0.99
    # Camera arm at +y, grasping arm at -y, both in front of the stand.
    assert configuration.frame_position("camera")[1] > configuration.frame_position("gripper")[1]


def test_masses_match_the_datasheet():
    model = pin.buildModelFromUrdf(str(paths.urdf_path()))
    for prefix in desc.ARM_PREFIXES:
        for link, mass in zip(ur5e.LINK_NAMES, ur5e.LINK_MASSES):
            inertia = model.inertias[model.getJointId(prefix + ur5e.JOINT_NAMES[ur5e.LINK_NAMES.index(link)])]
            # The last link also carries the tool (fixed joint merged by pinocchio).
            tool = desc.TOOLS[prefix].mass if link == "wrist_3_link" else 0.0
            assert inertia.mass == pytest.approx(mass + tool)


def test_home_configuration_is_collision_free(configuration):
    from harvest_qp.limits import CollisionAvoidance

    limit = CollisionAvoidance.dual_ur5e(configuration)
    assert limit.distances(configuration).min() > limit.safety_distance
