"""examples/03_paper_episode.py: a short paper episode through the library API, with and without the viewer."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from harvest_qp.viewer.replay import free_port
from tests.examples._run import pinocchio_frame_positions, run_example, true_stem_base

DURATION = "1.5"


@pytest.fixture(scope="module")
def headless(tmp_path_factory):
    out = tmp_path_factory.mktemp("ex03") / "run"
    stdout = run_example("03_paper_episode", "--duration", DURATION, "--out", str(out))
    return out, stdout


def test_03_short_episode_approaches_the_stem_and_reports_it(headless):
    """Catches an example (or episode API) whose camera arm does not approach the vine in the
    reaching phase, that logs joint positions inconsistent with its metrics, or prints a
    distance other than the one in metrics.json.

    Oracle: pinocchio forward kinematics of the logged joint positions (the URDF, not the
    library's Configuration) and the lab's ground-truth stem base.
    """
    out, stdout = headless
    metrics = json.loads((out / "metrics.json").read_text())
    log = np.load(out / "episode.npz")
    assert metrics["duration"] == float(DURATION) and metrics["phase_reached"] == "approach"
    assert metrics["qp_failures"] == 0 and metrics["contacts"] == 0
    camera = pinocchio_frame_positions(log["q"][[0, -1]], "camera")
    start, end = np.linalg.norm(camera - true_stem_base(0), axis=1)
    # The camera starts ~0.7 m away and moves towards the ROI sphere (r = 0.35 m) around p_sb.
    assert start - end > 0.1, (start, end)
    assert end > 0.35, end
    printed = float(re.search(r"camera to the true stem base at the end: ([0-9.]+) m", stdout).group(1))
    assert abs(printed - end) < 1e-3, (printed, end)
    assert abs(metrics["final_distance_to_roi_center"] - end) < 1e-3


def test_03_with_the_meshcat_viewer_the_episode_is_the_same(headless, tmp_path):
    """``--viewer meshcat`` serves the live view (URL printed) and only observes: the logged
    joint trajectory is the one of the headless run, tick for tick.

    Catches: a viewer that feeds back into the loop (e.g. the extras function mutating the
    controller's values), a crash of the viewer path (an unknown ViewerFrame field), a server
    on another port than asked. Oracle: the headless run of the same episode.
    """
    out, _ = headless
    port = free_port()
    stdout = run_example("03_paper_episode", "--duration", DURATION, "--out", str(tmp_path / "run"),
                         "--viewer", "meshcat", "--fast", "--port", str(port))  # fmt: skip
    assert f"http://127.0.0.1:{port}/" in stdout, stdout
    viewed = np.load(tmp_path / "run" / "episode.npz")
    np.testing.assert_array_equal(viewed["q"], np.load(out / "episode.npz")["q"])
