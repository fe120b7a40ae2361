"""Physical contacts (arm-arm, arm-vine), their ground truth, the stem's tear and sensor faults.

Oracles: MuJoCo's own contact list and ``mj_geomDistance`` over every pair (brute force),
pinocchio kinematics to drive the arms, hand counts of frames and noise statistics.
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np
import pytest

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.runtime.runner import run_episode
from harvest_qp.sim import CameraConfig, SensorFaults, SimRobot, VineSceneParams
from harvest_qp.sim.contacts import ContactMonitor
from tests.sim.helpers import ForcePull, PinocchioArm, arm_qpos_addresses


def _drive_cutter_to(robot: SimRobot, target: np.ndarray, ticks: int, speed: float = 0.25):
    """Move the camera arm's cutter tip straight at ``target`` [m] (pinocchio Jacobian), logging truth."""
    arm = PinocchioArm()
    log, pairs = [], set()
    for _ in range(ticks):
        T, J = arm.frame(robot.joint_positions(), "cutter_tip")
        e = target - T[:3, 3]
        qd = np.zeros(12)
        qd[:6] = np.linalg.lstsq(J[:, :6], np.r_[speed * e / np.linalg.norm(e), 0, 0, 0], rcond=None)[0]
        robot.send_joint_velocities(qd)
        robot.step()
        log.append(robot.ground_truth())
        d = robot.data
        pairs |= {(robot.model.geom(c.geom1).name, robot.model.geom(c.geom2).name) for c in d.contact[: d.ncon]}
    return log, pairs


def _min_true_distance(robot: SimRobot, geoms_a, geoms_b) -> float:
    m, d = robot.model, robot.data
    return min(mujoco.mj_geomDistance(m, d, int(a), int(b), 1.0, None) for a in geoms_a for b in geoms_b)


def _arm_geoms(robot: SimRobot, prefix: str) -> list[int]:
    return [g for g in range(robot.model.ngeom) if robot.model.geom(g).name.startswith(prefix)]


def test_arms_collide_with_each_other():
    """The camera arm driven into the grasping arm is stopped by contact, not passed through.

    Bug caught: robot geoms with conaffinity 0 and no explicit pairs (the arms passed
    through each other). Planted once by generating the MJCF without the <pair> list:
    no arm-arm contact and the capsules interpenetrate by centimetres.
    """
    robot = SimRobot(VineSceneParams(leaf_count=0, canopy_leaves=0), camera=None)
    cam, grasp = _arm_geoms(robot, "cam_"), _arm_geoms(robot, "grasp_")
    deepest = np.inf
    log = []
    arm = PinocchioArm()
    target = robot.site_pose("gripper")[:3, 3]
    for _ in range(1600):
        T, J = arm.frame(robot.joint_positions(), "cutter_tip")
        e = target - T[:3, 3]
        qd = np.zeros(12)
        qd[:6] = np.linalg.lstsq(J[:, :6], np.r_[0.25 * e / np.linalg.norm(e), 0, 0, 0], rcond=None)[0]
        robot.send_joint_velocities(qd)
        robot.step()
        log.append(robot.contact_counts()["arm_arm"])
        deepest = min(deepest, _min_true_distance(robot, cam, grasp))
    assert max(log) > 0
    assert deepest > -5e-3, deepest  # penetration stays at the contact solver's few millimetres


def test_arm_vine_contacts_and_min_vine_distance_on_a_straight_approach():
    """The cutter driven straight at p_sb meets the occluding leaf and the branch: arm-vine contacts.

    Bug caught: leaves and wood not colliding (conaffinity 0) and a ground truth that
    misses them. ``min_vine_distance`` must read ~0 while touching and agree with the
    brute-force distance over every pair.
    """
    robot = SimRobot(camera=None)
    log, pairs = _drive_cutter_to(robot, robot.scene.stem_base, 1700)
    touched = {b for a, b in pairs if a.startswith("cam_")} | {a for a, b in pairs if b.startswith("cam_")}
    assert "leaf_0" in touched
    vine = np.array([entry["contacts_arm_vine"] for entry in log])
    dist = np.array([entry["min_vine_distance"] for entry in log])
    assert vine.max() > 0
    assert np.all(dist[vine > 0] < 1e-3)  # touching: the true distance is ~0 (or a penetration)
    assert dist.min() > -5e-3
    assert log[-1]["min_vine_distance_so_far"] == pytest.approx(dist.min())
    # Arm-arm contacts happened on the way too (the cutter passes the gripper), and the
    # counts by kind sum to the robot's contacts in MuJoCo's list.
    kinds = robot.contact_counts()
    d = robot.data
    robot_like = {"cam_", "grasp_"}
    n_robot = sum(
        any(robot.model.geom(g).name.startswith(tuple(robot_like)) for g in (c.geom1, c.geom2))
        for c in d.contact[: d.ncon]
    )
    assert sum(kinds.values()) == n_robot


def test_contact_counts_by_kind_match_a_hand_classification():
    """Random arm states: each MuJoCo contact classified by geom name equals ``contact_counts``.

    Bug caught: a stand or floor contact counted as arm-vine, or a kind dropped.
    """
    robot = SimRobot(camera=None)
    m, d = robot.model, robot.data
    rng = np.random.default_rng(5)
    totals = dict.fromkeys(("arm_arm", "arm_vine", "arm_stand", "arm_floor", "crop_wood", "crop_leaf"), 0)
    vine_names = {m.geom(int(g)).name for g in robot.scene.vine_geoms}
    crop_names = {m.geom(int(g)).name for g in range(m.ngeom) if m.geom_bodyid[g] == m.body("cluster").id}
    for _ in range(300):
        d.qpos[arm_qpos_addresses(m)] = robot.scene.home_q + rng.normal(0, 0.6, 12)
        mujoco.mj_forward(m, d)
        expected = dict.fromkeys(totals, 0)
        for c in d.contact[: d.ncon]:
            a, b = m.geom(c.geom1).name, m.geom(c.geom2).name
            arm = [n.startswith(("cam_", "grasp_")) for n in (a, b)]
            crop = [n in crop_names for n in (a, b)]
            if any(crop) and not any(arm):
                other = b if crop[0] else a
                if other in ("branch", "cane"):
                    expected["crop_wood"] += 1
                elif other in vine_names:
                    expected["crop_leaf"] += 1
                continue
            if not any(arm):
                continue
            other = b if arm[0] else a
            if all(arm):
                expected["arm_arm"] += 1
            elif other.startswith("stand"):
                expected["arm_stand"] += 1
            elif other == "floor":
                expected["arm_floor"] += 1
            elif other in vine_names:
                expected["arm_vine"] += 1
        got = robot.contact_counts()
        assert got == expected
        for k in totals:
            totals[k] += got[k]
    assert totals["arm_arm"] > 0 and totals["arm_vine"] > 0 and totals["arm_stand"] > 0


def test_min_vine_distance_equals_brute_force_over_every_pair():
    """The capsule-bounded search returns the smallest ``mj_geomDistance`` over all arm x vine pairs.

    Bug caught: a bounding volume that is not conservative (an ellipsoid leaf's enclosing
    capsule too thin), a pruning that stops early, or the wrong pair reported. 150 random
    states near the vine; the robot's own ``min_vine_distance`` on the ticks of a motion.
    Planted and caught: the ellipsoid capsule's radius taken from its smallest semi-axis.
    """
    robot = SimRobot(VineSceneParams.sample(3), camera=None)
    m, d = robot.model, robot.data
    arm = _arm_geoms(robot, "cam_") + _arm_geoms(robot, "grasp_")
    monitor = ContactMonitor(m, arm_geoms=arm, stand_geoms=[], vine_geoms=robot.scene.vine_geoms, floor_geoms=[])
    rng = np.random.default_rng(11)
    for _ in range(150):
        d.qpos[arm_qpos_addresses(m)] = robot.scene.home_q + rng.normal(0, 0.25, 12)
        mujoco.mj_forward(m, d)
        got, ga, gv = monitor.min_vine_distance(d)
        brute = _min_true_distance(robot, arm, robot.scene.vine_geoms)
        assert got == pytest.approx(brute, abs=1e-9)
        assert mujoco.mj_geomDistance(m, d, ga, gv, 1.0, None) == pytest.approx(brute, abs=1e-9)
    robot.reset()
    robot.send_joint_velocities(np.r_[0.3, -0.2, 0.2, 0.0, 0.0, 0.0, np.zeros(6)])
    for _ in range(3):
        robot.advance(0.05)
        brute = _min_true_distance(robot, arm, robot.scene.vine_geoms)
        assert robot.min_vine_distance() == pytest.approx(brute, abs=1e-9)


def test_stem_tears_beyond_its_break_force():
    """Pulling past ``stem_break_force`` tears the stem once; below it never does.

    Bug caught: a tear that never triggers, triggers at the wrong tension, or leaves the
    stem holding. Oracle: the true tension logged each tick.
    """
    params = VineSceneParams(stem_break_force=6.0)
    robot = SimRobot(params, camera=None)
    direction = robot.scene.stem_end - robot.scene.stem_base
    result = run_episode(robot, ForcePull(direction, force=20.0), duration=2.5, stop_at_end=False)
    assert result.ok, result.error
    torn = result.log["truth/stem_torn"]
    tension = result.log["truth/stem_tension"]
    k = int(np.argmax(torn > 0))
    assert torn[-1] == 1.0 and np.all(torn[k:] == 1.0) and np.all(torn[:k] == 0.0)
    # Torn on the tick the tension first exceeded 6 N, within one tick's rise (< 0.1 N).
    assert tension[k] > 6.0 and np.all(tension[:k] <= 6.0)
    assert tension[k] < 6.1
    assert robot.stem_torn and robot.stem_tear_time == pytest.approx(result.log["t"][k], abs=0.0041)
    # The stem no longer holds: its tension collapses within 0.2 s.
    assert np.abs(tension[k + 100 :]).max() < 0.3
    # The same pull to 3 N never tears it, and a reset heals it.
    robot.reset()
    assert not robot.stem_torn
    result = run_episode(robot, ForcePull(direction, force=3.0), duration=2.5, stop_at_end=False)
    assert np.all(result.log["truth/stem_torn"] == 0.0)
    assert result.log["truth/stem_tension_max"][-1] == pytest.approx(result.log["truth/stem_tension"].max())


def _frame_log(robot: SimRobot, seconds: float) -> tuple[list[float], list[float]]:
    stamps, arrivals = [], []
    for _ in range(int(round(seconds / robot.control_period))):
        cloud = robot.camera_cloud()
        if cloud is not None:
            stamps.append(cloud.timestamp)
            arrivals.append(robot.time)
        robot.step()
    return stamps, arrivals


def test_lost_frames_are_seeded_and_come_at_the_requested_rate():
    """30 % of whole frames lost: seeded, at the rate, and the rest still on the 30 Hz grid.

    Bug caught: loss not applied, not seeded (unreproducible episodes), or losing single
    pixels instead of frames.
    """
    camera = CameraConfig(width=96, height=60, downsample=1)  # tiny frames: the schedule is what counts
    faults = SensorFaults(frame_loss=0.3)
    a = SimRobot(camera=camera, faults=faults, seed=3, settle_time=0.0)
    b = SimRobot(camera=camera, faults=faults, seed=3, settle_time=0.0)
    c = SimRobot(camera=camera, faults=faults, seed=4, settle_time=0.0)
    sa, sb, sc = (_frame_log(r, 4.0)[0] for r in (a, b, c))
    assert sa == sb and sa != sc
    scheduled = 4 * 30  # frames 0 .. 119 at 30 Hz in 4 s
    assert len(sa) + a.frames_lost == scheduled
    # Binomial(120, 0.3): mean 36, std 5; 4 std.
    assert 16 <= a.frames_lost <= 56
    grid = np.round(np.array(sa) * 30)
    np.testing.assert_allclose(np.array(sa) * 30, grid, atol=0.07)
    assert a.ground_truth()["frames_lost"] == a.frames_lost
    # Each delivered frame is whole: same size as an unfaulted frame of the same view.
    clean = SimRobot(camera=camera, seed=3, settle_time=0.0)
    assert len(clean.capture_cloud()) == len(a.capture_cloud())


def test_frame_latency_and_force_noise_faults():
    """``frame_latency`` delays delivery by exactly that; ``force_noise_std`` sets the F/T noise [N].

    Bug caught: the fault options ignored (the camera's own latency or the sensor's own
    noise used instead).
    """
    camera = CameraConfig(width=96, height=60, downsample=1)
    robot = SimRobot(camera=camera, faults=SensorFaults(frame_latency=0.05, force_noise_std=0.2), settle_time=0.0)
    stamps, arrivals = _frame_log(robot, 1.0)
    delay = np.array(arrivals) - np.array(stamps)
    assert np.all(delay >= 0.05 - 1e-9) and np.all(delay < 0.05 + 0.002 + 1e-9)
    assert len(stamps) in (28, 29)  # 1 s at 30 Hz minus the 50 ms latency
    forces = []
    for _ in range(1000):
        robot.step()
        forces.append(robot.wrist_force())
    assert np.std(np.array(forces), axis=0) == pytest.approx([0.2] * 3, rel=0.12)


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [({"frame_loss": 1.0}, "frame_loss"), ({"frame_latency": -0.1}, "frame_latency"),
     ({"force_noise_std": float("nan")}, "force_noise_std")],
)  # fmt: skip
def test_sensor_faults_validation(kwargs, words):
    with pytest.raises(InvalidInputError, match=words):
        SensorFaults(**kwargs)


def test_ground_truth_keys_are_numeric_and_fixed():
    """Every ground-truth value is a number or a fixed-size array (the runner logs them per tick)."""
    robot = SimRobot(camera=None)
    first = robot.ground_truth()
    robot.advance(0.01)
    second = robot.ground_truth()
    assert first.keys() == second.keys()
    for key, value in second.items():
        assert np.shape(value) == np.shape(first[key]), key
        assert np.all(np.isfinite(np.asarray(value, float))), key
    assert dataclasses.is_dataclass(SensorFaults())


def _crop_wood_distance(robot: SimRobot) -> float:
    """Smallest true distance [m] between the held cluster's geoms and the branch or cane (MuJoCo's
    ``mj_geomDistance``; negative: penetration)."""
    m = robot.model
    crop = [g for g in range(m.ngeom) if m.geom(g).name.startswith("berry_") or m.geom(g).name == "rachis"]
    return _min_true_distance(robot, crop, [m.geom("branch").id, m.geom("cane").id])


def test_held_crop_driven_into_the_branch_is_stopped_and_counted():
    """The grasping arm swings the held cluster up into the branch: crop-wood contacts, bounded depth.

    The gripper turns at 1 rad/s about its tool axis (world x) and rises at 10 mm/s for 3.4 s
    (pinocchio Jacobian of the ``gripper`` frame); the cluster swings up beside the stem into the
    branch while the gripper itself stays clear of the wood (no arm-vine contact). Oracle: the
    true crop-wood distance from MuJoCo's geometry (``mj_geomDistance``) and MuJoCo's contact list.

    Bug caught: the held cluster not colliding with the wood (its geoms with contype 0, as before
    issue 20), so the lab let the crop sit inside the branch uncounted. Planted once (the crop
    geoms' contype set back to 0 in the scene): no crop-wood contact is ever counted and the crop
    reaches 20.6 mm inside the branch, failing both assertions below; with the contact it stops
    within 5 mm (the weld's and the contact's compliance under a servo that keeps pushing).
    """
    robot = SimRobot(VineSceneParams(leaf_count=0, canopy_leaves=0, other_clusters=0), camera=None)
    assert robot.contact_counts()["crop_wood"] == 0 and _crop_wood_distance(robot) > 0.03  # clear at reset
    arm = PinocchioArm()
    deepest, crop_ticks, arm_vine = np.inf, 0, 0
    for k in range(1700):
        _, J = arm.frame(robot.joint_positions(), "gripper")
        qd = np.zeros(12)
        qd[6:] = np.linalg.lstsq(J[:, 6:], np.r_[0.0, 0.0, 0.01, 1.0, 0.0, 0.0], rcond=None)[0]
        robot.send_joint_velocities(qd)
        robot.step()
        counts = robot.contact_counts()
        crop_ticks += counts["crop_wood"] > 0
        arm_vine += counts["arm_vine"]
        if k % 5 == 0:
            deepest = min(deepest, _crop_wood_distance(robot))
    assert arm_vine == 0  # only the crop touched the wood
    assert crop_ticks > 100  # the crop rested on the branch for the last ~0.8 s
    assert deepest > -0.007, deepest  # without the contact: 20 mm deep
