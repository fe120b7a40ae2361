"""An episode that ends in the bimanual phase says which pre-cut tests still failed.

The pre-cut timeout (``safety.precut_timeout``, 30 s after the switch) cannot fire when the switch
comes late in a 50 s episode; such an episode used to end with no reason at all (a review found
it). Oracle: the phase machine's own tests fed by hand, and the episode's logged grasp state.
"""

from __future__ import annotations

import dataclasses
import math

from harvest_qp.config.settings import check_settings, load_settings
from harvest_qp.harvest.phases import PhaseMachine, PhaseRules
from harvest_qp.robot.paths import tasks_dir
from harvest_qp.sim.paper_episode import run_paper_episode
from harvest_qp.sweep.stats import failure_reason
from tests.loop.conftest import SCENE_ARGS

OVERRIDES = [a for a in SCENE_ARGS if a != "--set"]


def test_precut_misses_names_the_failing_tests_of_the_last_tick():
    rules = dataclasses.replace(PhaseRules.from_settings(check_settings({})), f_d=3.0, force_limit=6.0,
                                position_tolerance=0.005, alignment_tolerance_deg=5.0, force_time_constant=0.0)
    machine = PhaseMachine(rules)
    assert machine.precut_misses() is None
    machine.switch(1.0)
    machine.stretch(1.002, 0.002, 2.0, 0.012, math.radians(3.0), force_norm=2.0)
    assert machine.precut_misses() == "force along n_c 2.00 N (f_d 3.00 N +- 10 %), position error 12.0 mm (> 5.0 mm)"
    machine.stretch(1.004, 0.002, 3.0, 0.001, math.radians(9.0), force_norm=3.0)
    assert machine.precut_misses() == "alignment 9.0 deg (> 5.0 deg)"


def test_an_episode_cut_short_after_the_switch_reports_why_it_had_no_precut(tmp_path):
    """The default scene switches at ~8 s and reaches pre-cut at ~15 s: cut at 10 s, it ends in the
    bimanual phase, and its end_reason names the tests that failed on its last logged tick."""
    settings = load_settings(tasks_dir() / "paper.yaml", OVERRIDES)
    report = run_paper_episode(settings, seed=0, duration=10.0, out_dir=tmp_path, figures=False)
    m = report.metrics
    assert m["phase_reached"] == "bimanual" and m["abort_reason"] is None and not m["success"]
    reason = m["end_reason"]
    assert reason.startswith(f"no pre-cut when the episode ended {10.0 - m['t_bimanual_start']:.1f} s after the switch")
    # the logged state at the end agrees with what the reason names
    error_mm = 1000 * m["final_position_error"]
    assert (f"position error {error_mm:.1f} mm" in reason) == (error_mm > 5.0)
    assert failure_reason({**m, "status": "ok"}) == reason


def test_a_successful_or_aborted_episode_has_no_end_reason(tmp_path):
    settings = load_settings(tasks_dir() / "paper.yaml", OVERRIDES)
    m = run_paper_episode(settings, seed=0, duration=5.0, out_dir=tmp_path, figures=False).metrics
    assert m["phase_reached"] == "approach" and m["end_reason"] is None


def test_an_episode_that_never_reached_precut_is_not_a_success(tmp_path):
    """Every end criterion holds (camera, force, true tension, alignment, position, no contact) but the
    pre-cut test never held for its ``hold_time``: not a harvest. Bug caught (an independent review):
    ``success`` was the end state alone and read true with ``phase_reached`` "bimanual" and no
    ``t_precut``. Planted back (the criterion left out): success is true here."""
    settings = load_settings(tasks_dir() / "paper.yaml", [*OVERRIDES, "precut.hold_time=1000"])
    m = run_paper_episode(settings, seed=0, duration=20.0, out_dir=tmp_path, figures=False).metrics
    assert m["phase_reached"] == "bimanual" and m["t_precut"] is None
    others = {k: ok for k, ok in m["criteria"].items() if k != "precut_reached"}
    assert all(others.values()), others  # the end state alone would pass
    assert m["success"] is False and m["criteria"].get("precut_reached") is False


class _FailsAfter:
    """A wrapper whose step raises once the robot's clock passes ``t`` [s]."""

    def __init__(self, inner, t: float) -> None:
        self.inner, self.t = inner, t

    def reset(self, robot) -> None:
        self.inner.reset(robot)

    def step(self, obs):
        if obs.time > self.t:
            raise RuntimeError("the wrapper failed on purpose")
        return self.inner.step(obs)


def test_a_controller_that_fails_mid_episode_fails_the_episode_and_says_why(tmp_path):
    """The runner stops the arms when the controller raises; the metrics then carry the error's first
    line and the ``completed`` criterion fails (it read ``no_abort`` true and named no error)."""
    settings = load_settings(tasks_dir() / "paper.yaml", OVERRIDES)
    report = run_paper_episode(settings, seed=0, duration=0.5, out_dir=tmp_path, figures=False,
                               wrap_controller=lambda robot, controller: _FailsAfter(controller, 0.2))
    m = report.metrics
    assert m["episode_status"] == "controller_error" and not m["success"]
    assert m["criteria"]["completed"] is False
    assert "the wrapper failed on purpose" in m["episode_error"]
