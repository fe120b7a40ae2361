"""HarvestController through reset/step without a scene (no camera frames); its laws are tested in
tests/references, its phase machine in tests/loop/test_phases.py."""

from __future__ import annotations

import numpy as np

from harvest_qp.config.settings import DEFAULTS, check_settings
from harvest_qp.harvest.harvest_controller import HarvestController, Phase
from harvest_qp.robot.description import HOME_Q
from harvest_qp.runtime.runner import Observation
from tests.helpers import ResetRobot


def test_without_a_stem_it_aborts_and_brakes_to_rest_within_the_acceleration_limit():
    """No camera frame: the approach commands the arms (hold + reaching), then the no-stem timeout
    aborts; from there each tick lowers every joint speed by at most a_max dt, to exactly zero,
    and the episode ends ``stop_after_abort`` after rest. Oracle: the acceleration limit of the
    settings, the timeout and stop time set here. Catches: a safe stop that jumps to zero or
    overshoots, an abort that keeps the QP running, an episode that never ends."""
    settings = check_settings({"safety": {"no_stem_timeout": 0.05}, "episode": {"stop_after_abort": 0.02}})
    a_max = DEFAULTS.qp.limits[2].max_acceleration
    controller = HarvestController(settings)
    q = np.asarray(HOME_Q, float) + 0.05
    controller.reset(ResetRobot(q))
    previous, t, done, speeds = np.zeros(12), 0.0, False, []
    while not done and t < 2.0:
        t += 0.002
        command = controller.step(Observation(time=t, q=q, qdot=previous, force=np.zeros(3), cloud=None,
                                              new_cloud=False))
        qdot, done = np.asarray(command.qdot), command.done
        if controller.phase == Phase.ABORT:
            assert np.all(np.abs(qdot - previous) <= a_max * 0.002 + 1e-12)
            assert np.all(np.abs(qdot) <= np.abs(previous) + 1e-12)
            assert command.status.startswith("abort: no stem base found within 0.05 s")
        speeds.append(float(np.abs(qdot).max()))
        previous = qdot
    assert controller.phase == Phase.ABORT and done
    assert max(speeds) > 0.0 and not np.any(previous)  # it moved in the approach, and stopped
    assert "roll_error" not in command.values and np.isnan(command.values["force_nc"])  # no references ran
