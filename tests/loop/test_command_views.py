"""HarvestController's command values and pairs are read-only views that say how to extend them."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from harvest_qp.config.settings import load_settings
from harvest_qp.harvest.harvest_controller import HarvestController
from harvest_qp.robot.paths import tasks_dir
from harvest_qp.runtime.runner import run_episode
from harvest_qp.sim.paper_episode import build_robot, environment_capsules_for


class _AddsInPlace:
    def __init__(self, inner) -> None:
        self.inner = inner

    def reset(self, robot) -> None:
        self.inner.reset(robot)

    def step(self, obs):
        command = self.inner.step(obs)
        command.values["my_metric"] = 1.0
        return command


class _AddsByReplace(_AddsInPlace):
    def step(self, obs):
        command = self.inner.step(obs)
        return dataclasses.replace(command, values={**command.values, "my_metric": 1.0},
                                   collision_pairs=[*command.collision_pairs, ("a", "b", 0.5)])


@pytest.fixture(scope="module")
def setup():
    settings = load_settings(tasks_dir() / "paper.yaml")
    return settings


def _run(settings, wrapper):
    robot = build_robot(settings, 0)
    controller = HarvestController(settings, environment=environment_capsules_for(robot, settings.qp.environment))
    return run_episode(robot, wrapper(controller), duration=0.02)


def test_extending_the_values_in_place_names_the_fix(setup):
    """Bug caught (audit): a wrapper that added a value in place (a dict before the row
    protocol) got only "'ValueRow' object does not support item assignment".

    Oracle: the episode ends as a controller error whose message gives the replacement call.
    """
    result = _run(setup, _AddsInPlace)
    assert result.status == "controller_error"
    assert "dataclasses.replace(command, values={**command.values, name: value})" in result.error


def test_the_documented_way_to_extend_a_command_is_logged(setup):
    """Oracle: the added value and pair appear in the log, next to the controller's own."""
    result = _run(setup, _AddsByReplace)
    assert result.status == "completed", result.error
    assert np.all(result.log["value/my_metric"] == 1.0) and "value/phase" in result.log
    assert "a|b" in set(result.log["collision/pair_names"].tolist())
