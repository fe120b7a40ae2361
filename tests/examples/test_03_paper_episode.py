"""examples/03_paper_episode.py: a short paper episode through the library API."""

from __future__ import annotations

import json
import re

import numpy as np

from tests.examples._run import pinocchio_frame_positions, run_example, true_stem_base


def test_03_short_episode_approaches_the_stem_and_reports_it(tmp_path):
    """Catches an example (or episode API) whose camera arm does not approach the vine in the
    reaching phase, that logs joint positions inconsistent with its metrics, or prints a
    distance other than the one in metrics.json.

    Oracle: pinocchio forward kinematics of the logged joint positions (the URDF, not the
    library's Configuration) and the lab's ground-truth stem base.
    """
    out = tmp_path / "run"
    stdout = run_example("03_paper_episode", "--duration", "1.5", "--out", str(out))
    metrics = json.loads((out / "metrics.json").read_text())
    log = np.load(out / "episode.npz")
    assert metrics["duration"] == 1.5 and metrics["phase_reached"] == "approach"
    assert metrics["qp_failures"] == 0 and metrics["contacts"] == 0
    camera = pinocchio_frame_positions(log["q"][[0, -1]], "camera")
    start, end = np.linalg.norm(camera - true_stem_base(0), axis=1)
    # The camera starts ~0.7 m away and moves towards the ROI sphere (r = 0.35 m) around p_sb.
    assert start - end > 0.1, (start, end)
    assert end > 0.35, end
    printed = float(re.search(r"camera to the true stem base at the end: ([0-9.]+) m", stdout).group(1))
    assert abs(printed - end) < 1e-3, (printed, end)
    assert abs(metrics["final_distance_to_roi_center"] - end) < 1e-3
