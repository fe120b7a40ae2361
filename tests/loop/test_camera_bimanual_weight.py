"""``qp.camera_bimanual_weight``: the camera task's weights from the switch on (the approach keeps
``qp.camera_task.weight``), and back at the next reset.

Oracle: the settings' own values, read through the public task; the switch time from the phase machine.
"""

from __future__ import annotations

import numpy as np

from harvest_qp.config import load_settings
from harvest_qp.harvest.harvest_controller import HarvestController
from harvest_qp.robot.paths import tasks_dir
from harvest_qp.runtime.runner import run_episode
from harvest_qp.sim.paper_episode import build_robot

BIMANUAL = [0.1, 0.1, 0.1, 1.0, 1.0, 0.0]


def test_camera_weights_change_at_the_switch_and_come_back_at_reset():
    settings = load_settings(tasks_dir() / "paper.yaml", [f"qp.camera_bimanual_weight={BIMANUAL}"])
    robot = build_robot(settings, 0)
    controller = HarvestController(settings)
    approach = np.asarray(settings.qp.camera_task.weight, float)
    run_episode(robot, controller, duration=2.0)  # the default scene switches at ~8.3 s
    assert controller.phases.t_switch is None
    np.testing.assert_array_equal(controller.camera_task.weight, approach)
    run_episode(robot, controller, duration=10.0)
    assert controller.phases.t_switch is not None
    np.testing.assert_array_equal(controller.camera_task.weight, BIMANUAL)
    robot.reset()
    controller.reset(robot)
    np.testing.assert_array_equal(controller.camera_task.weight, approach)
