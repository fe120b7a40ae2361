"""``harvest-qp run``'s progress line: simulated time, phase and real-time factor, only observing."""

from __future__ import annotations

import io
from types import SimpleNamespace

from harvest_qp.cli import main
from harvest_qp.runtime.progress import ProgressController, wants_progress
from tests.loop.conftest import PAPER, SCENE_ARGS


class _Phase:
    name = "BIMANUAL"


class _Controller:
    phase = _Phase()

    def reset(self, robot):
        self.robot = robot

    def step(self, obs):
        return ("command", obs.time)


def test_progress_line_forwards_and_draws():
    stream = io.StringIO()
    inner = _Controller()
    wall = iter([100.0, 104.0])  # reset at 100 s, the step 4 s of wall time later
    shown = ProgressController(inner, stream=stream, duration=50.0, every=0.0, clock=lambda: next(wall))
    shown.reset("robot")
    assert inner.robot == "robot"
    assert shown.step(SimpleNamespace(time=12.3)) == ("command", 12.3)  # the command is the controller's
    shown.finish()
    text = stream.getvalue()
    assert text.startswith("\r  t  12.3 / 50.0 s  phase bimanual  3.1x real time")
    assert text.endswith("\n")
    assert shown.phase is inner.phase  # metrics and figures read the wrapped controller's attributes


def test_no_progress_off_a_terminal():
    assert not wants_progress(io.StringIO())


def test_cli_run_draws_progress_on_request(tmp_path, capsys):
    code = main(["run", str(PAPER), "--out", str(tmp_path), "--duration", "0.5", "--no-figures", "--progress",
                 *SCENE_ARGS])
    err = capsys.readouterr().err
    assert code in (0, 1)
    assert "phase approach" in err and "/ 0.5 s" in err and err.endswith("\n")
