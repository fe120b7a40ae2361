"""p_sb from the approach's close frames, in the closed loop (issue 20: the camera ended off centre).

Scene: sweep seed 16291 of ``tasks/paper.yaml`` (development range, the scene the memory was built on).
The unveiling law raises the camera from 6 to 17 deg above the stem base while more of the stem comes
into view, and the branch with a petiole comes to hide the stem's top 12 mm. On main without the memory
p_sb froze 13 mm down the stem at the switch (17.26 s) and the camera ended 2.2 deg off the true base.
Oracle: the lab's stem base (the MuJoCo scene's), not the controller's fit.
"""

from __future__ import annotations

import numpy as np

from harvest_qp.config import load_settings
from harvest_qp.harvest.harvest_controller import HarvestController
from harvest_qp.robot.paths import tasks_dir
from harvest_qp.runtime.runner import run_episode
from harvest_qp.sim.paper_episode import build_robot, environment_capsules_for
from tests.helpers import ResetRobot

SEED = 16291
DURATION = 18.0  # past the switch (17.3 s) by 0.7 s
# The camera's path on which the branch hid the stem's top: the one of the turn weighted like the travel
# (the default before issue 20's camera-weight change; with the default's 0.3 this scene's camera rises
# less and the frame's own fit is 3.8 mm off at the switch, so the scene would no longer test the memory).
PATH = ["qp.camera_task.weight=[1, 1, 1, 1, 1, 0]"]


def test_the_switch_freezes_the_stem_base_the_approach_saw_not_the_last_frames():
    """At the switch the frame's own fit lies more than 10 mm down the stem from the lab's base, the
    frozen p_sb within 8 mm of it. Catches: p_sb from the last frame alone (``perception.stem_memory:
    false`` gives 13.2 mm), a memory that is never fed, or one whose extension goes the wrong way."""
    settings = load_settings(tasks_dir() / "paper.yaml", PATH)
    robot = build_robot(settings, SEED)
    true_base = np.asarray(robot.scene.stem_base, float)
    controller = HarvestController(settings, environment=environment_capsules_for(robot, settings.qp.environment))
    result = run_episode(robot, controller, duration=DURATION)
    assert result.ok, result.error
    switch = controller.switch_snapshot
    assert switch is not None, "no switch in 18 s"
    assert np.linalg.norm(switch.stem.base - true_base) > 0.010
    assert np.linalg.norm(switch.stem_base - true_base) < 0.008
    assert np.linalg.norm(controller.state.p_sb - true_base) < 0.008


def test_a_new_episode_starts_with_an_empty_stem_memory():
    """Catches the memory kept across ``reset``: the last episode's stem would lift the next one's p_sb."""
    from harvest_qp.robot.description import HOME_Q

    controller = HarvestController(load_settings(tasks_dir() / "paper.yaml"))
    q = np.array(HOME_Q, float)
    controller.reset(ResetRobot(q))
    stem = np.array([0.5, -0.1, 1.2]) + np.linspace(0.0, 0.05, 30)[:, None] * np.array([0.0, 0.0, -1.0])
    assert controller.stem_memory.add(stem, camera_position=stem[0] + [-0.3, 0.0, 0.0], stem_base=stem[0])
    assert controller.stem_memory.points.shape[0] > 0
    controller.reset(ResetRobot(q))
    assert controller.stem_memory.points.shape == (0, 3)
    assert controller.stem_memory.extension(stem[-1], [0.0, 0.0, -1.0]) == 0.0
