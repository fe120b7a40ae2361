"""The default scene and seeds 1-5 succeed, each from the CLI's own code path (issue 7, section 6).

Every episode runs through ``harvest_qp.cli.main(["run", ...])``, exactly what
``harvest-qp run tasks/paper.yaml --seed N`` executes, and each success criterion is then
checked separately against the simulator's ground truth, which the controller never sees:
the true contacts (MuJoCo's contact list, sorted by kind), the true stem tension (the stem
tendon's spring), the true stem base (the scene), the true tear flag, and the gripper's pose
recomputed with pinocchio from the logged joint positions.

Cost (the suite must stay under ~9 min on 2 cores): the episodes end 2 s after "pre-cut
reached" (``episode.end_after_precut``; the success criteria are the pre-cut tolerances,
held for 1 s) and run at 141x80 (``camera.downsample=6``, ``conftest.SCENE_ARGS``). Measured
at this resolution and at the paper's 283x160 on the same seeds, with the same outcome
(success, 0 contacts); the README's table is at 283x160 (``benchmarks/run_paper_scenes.py``).
"""

from __future__ import annotations

import numpy as np
import pytest

from harvest_qp.configuration import Configuration
from harvest_qp.sim import VineSceneParams, build_vine_scene

SEEDS = [0, 1, 2, 3, 4, 5]


@pytest.fixture(scope="module", params=SEEDS, ids=[f"seed{s}" for s in SEEDS])
def episode(request, cli_episode):
    seed = request.param
    code, metrics, log, _ = cli_episode(seed, *cli_episode.scene_args)
    return seed, code, metrics, log


def _true_stem_base(seed: int) -> np.ndarray:
    params = VineSceneParams.sample(seed) if seed > 0 else VineSceneParams()
    return np.asarray(build_vine_scene(params).stem_base, float)


def _gripper_axes(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gripper point [m] and y axis from the logged joint positions (pinocchio, not the controller)."""
    config = Configuration.dual_ur5e()
    config.update(q)
    pose = config.frame_pose("gripper")
    return pose.translation.copy(), pose.rotation[:, 1].copy()


def _check_success(seed: int, code: int, metrics: dict, log: dict) -> None:
    """Each criterion of issue 7 section 5 against the ground truth, then ``success`` itself."""
    t = log["t"]
    phase = log["value/phase"]
    f_d = metrics["f_d"]
    r = metrics["roi_radius"]
    label = f"seed {seed}"
    # no abort: the phase never became ABORT (3), and pre-cut (2) was reached
    assert not np.any(phase == 3), f"{label}: aborted ({metrics['abort_reason']})"
    assert np.any(phase == 2), f"{label}: pre-cut never reached (phase {metrics['phase_reached']})"
    # no contact: MuJoCo's contact list, every robot contact kind, every tick
    for key in [k for k in log if k.startswith("truth/contacts_")]:
        ticks = np.flatnonzero(log[key] > 0)
        assert ticks.size == 0, f"{label}: {key} in {ticks.size} ticks from t = {t[ticks[0]]:.2f} s"
    # no tear: the simulated stem's break flag
    assert not np.any(log["truth/stem_torn"] > 0), f"{label}: the stem tore"
    # force: the TRUE stem tension (the tendon's spring), not the wrist sensor
    tension = log["truth/stem_tension"]
    last = t >= t[-1] - 1.0
    assert abs(np.mean(tension[last]) - f_d) <= 0.1 * f_d, f"{label}: true tension {np.mean(tension[last]):.2f} N"
    assert np.max(log["truth/stem_tension_max"]) <= 2 * f_d, f"{label}: true tension peaked above 2 f_d"
    # the camera inside the ROI around the TRUE stem base (the estimate's own error allowed:
    # p_sb within 15 mm of the truth, checked here too)
    base = _true_stem_base(seed)
    p_sb = log["value/p_sb"][-1]
    assert np.linalg.norm(p_sb - base) < 0.015, f"{label}: p_sb {1e3 * np.linalg.norm(p_sb - base):.1f} mm off"
    camera = log["value/p_c"][-1]
    assert np.linalg.norm(camera - base) <= 1.02 * r + 0.015, f"{label}: camera outside the ROI"
    # centred: the true stem base within 2 deg (+ the p_sb error's angle) of the optical axis
    z_c = log["value/z_c"][-1]
    to_base = (base - camera) / np.linalg.norm(base - camera)
    assert np.degrees(np.arccos(np.clip(z_c @ to_base, -1, 1))) < 2.0 + np.degrees(0.015 / 0.3), label
    # unveiled: the visible stem points at the end >= 3x those at the start (>= 1)
    frames, frame_time = log["frame_stem_points"], log["frame_time"]
    end = np.median(frames[frame_time >= frame_time[-1] - 0.5])
    assert end >= 3 * max(frames[0], 1), f"{label}: stem points {frames[0]} -> {end}"
    # position error and alignment from the gripper pose (pinocchio on the logged q): the
    # gripper on the line p_sb -> p_gd within 5 mm, y_g along it within 5 deg
    p_g, y_g = _gripper_axes(log["q"][-1])
    p_gd = log["value/p_gd"][-1]
    n_c = (p_gd - p_sb) / np.linalg.norm(p_gd - p_sb)
    offset = p_g - p_gd
    assert np.linalg.norm(offset - (offset @ n_c) * n_c) < 0.005, f"{label}: projected position error"
    assert np.degrees(np.arccos(np.clip(y_g @ n_c, -1, 1))) < 5.0, f"{label}: alignment"
    # the true stem (base -> where it enters the crop) is where the controller pulls it
    stem = log["truth/stem_end"][-1] - base
    assert np.degrees(np.arccos(np.clip(stem @ n_c / np.linalg.norm(stem), -1, 1))) < 15.0, label
    # the grasp target chosen at the switch: below the stem base, and the metric's angle off the
    # true hanging stem is this one (not asserted within the 30 deg swing bound: seed 2's target is
    # 43.9 deg off the true stem although its episode succeeds, an issue-20 case left open)
    k = int(np.flatnonzero(phase >= 1)[0])
    to_target, hanging = log["value/p_gd"][k] - base, log["truth/stem_end"][k] - base
    angle = np.degrees(np.arccos(np.clip(to_target @ hanging / np.linalg.norm(to_target) / np.linalg.norm(hanging),
                                         -1, 1)))
    assert log["value/p_gd"][k][2] < base[2], f"{label}: target above the stem base"
    assert metrics["target_angle_off_stem_deg"] == pytest.approx(angle, abs=0.5)
    assert metrics["target_above_stem_base"] is False
    assert metrics["success"] and code == 0, f"{label}: {metrics['criteria']}"


def test_scene_succeeds_on_every_criterion(episode):
    """The default scene and seeds 1-5 succeed, every criterion checked on the ground truth.

    Catches (each seen to fail it): the gripper swinging the crop into the occluding leaf
    (seeds 1 and 5 without the map-aware p_gd, ``grasping.swing_clearance=null``: grasp_gripper
    against leaf_0 3-5 s after the switch, and a 6 N force-limit abort on seed 1); a stem
    pre-stretched before the switch's tare (the grasping arm's map rows asking for separation
    instead of only "no further approach", ``CollisionAvoidance.set_approach_only`` left out:
    on seed 1 they push the gripper off the branch during the approach, the wrist then reads
    3.0-3.1 N while the true tension is 5.65-5.7 N and ``metrics.json`` says success)."""
    seed, code, metrics, log = episode
    _check_success(seed, code, metrics, log)


def test_faults_still_succeed(cli_episode):
    """Issue 7 section 6: 30 % of the camera frames lost, 50 ms frame latency, 0.2 N force noise.

    The default scene must still succeed on every criterion (ground truth as above), and the
    faults must have been applied (the simulator counts the lost frames; the logged force
    along n_c is noisy)."""
    code, metrics, log, _ = cli_episode(0, *cli_episode.scene_args, "--set", "camera.frame_loss=0.3",
                                        "--set", "camera.latency=0.05", "--set", "force_sensor.noise_std=0.2")
    n_frames = len(log["frame_time"])
    lost = log["truth/frames_lost"][-1]
    assert 0.2 < lost / (lost + n_frames) < 0.4
    assert np.std(np.diff(log["force"][-500:, 2])) > 0.1  # the noise was on
    _check_success(0, code, metrics, log)
