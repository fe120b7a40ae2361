"""An episode whose controller fails before its first tick reports why, not a KeyError."""

from __future__ import annotations

import pytest

from harvest_qp import EpisodeError, HarvestQPError
from harvest_qp.config.settings import load_settings
from harvest_qp.robot.paths import tasks_dir
from harvest_qp.sim.paper_episode import run_paper_episode


class _FailsOnFirstStep:
    """A wrapper (as a viewer or a user's logger would be) whose step raises at once."""

    def __init__(self, inner) -> None:
        self.inner = inner

    def reset(self, robot) -> None:
        self.inner.reset(robot)

    def step(self, obs):
        raise RuntimeError("the wrapper failed on purpose")


def test_a_controller_failing_on_its_first_tick_raises_an_episode_error_naming_it(tmp_path):
    """Bug caught (audit, pre-existing): the metrics read ``value/phase`` from a log with no
    tick and the user saw ``KeyError: 'value/phase'`` instead of the controller's error.

    Oracle: the runner's own status and the wrapper's message appear in the package's error.
    """
    settings = load_settings(tasks_dir() / "paper.yaml")
    with pytest.raises(EpisodeError) as info:
        run_paper_episode(settings, duration=0.05, out_dir=tmp_path, figures=False,
                          wrap_controller=lambda robot, controller: _FailsOnFirstStep(controller))
    message = str(info.value)
    assert "controller_error" in message and "the wrapper failed on purpose" in message
    assert isinstance(info.value, HarvestQPError)  # the CLI turns it into a one-line error, exit 2


class _DropsTheValues:
    """A wrapper that returns only the joint velocities (no logged values)."""

    def __init__(self, inner) -> None:
        self.inner = inner

    def reset(self, robot) -> None:
        self.inner.reset(robot)

    def step(self, obs):
        return self.inner.step(obs).qdot


def test_a_wrapper_dropping_the_values_is_told_what_the_metrics_need(tmp_path):
    """Bug caught (audit): with ticks logged but no ``value/phase``, the error said the episode
    ended before the first tick.

    Oracle: the message gives the number of ticks run and names the missing values (planted:
    the first-tick message for every missing value/phase, as before the fix).
    """
    settings = load_settings(tasks_dir() / "paper.yaml")
    with pytest.raises(EpisodeError, match=r"\(25 ticks, status 'completed'\) logged no value/phase"):
        run_paper_episode(settings, duration=0.05, out_dir=tmp_path, figures=False,
                          wrap_controller=lambda robot, controller: _DropsTheValues(controller))
