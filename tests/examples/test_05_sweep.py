"""examples/05_sweep.py: a two-seed sweep through the library API, then resumed."""

from __future__ import annotations

import csv

import numpy as np

from tests.examples._run import pinocchio_frame_positions, run_example, true_stem_base


def test_05_sweep_rows_belong_to_their_seeds_and_a_rerun_resumes(tmp_path):
    """Catches a sweep whose rows do not belong to their seeds (every worker running the same
    scene, rows swapped, the seed not reaching the episode), a custom metric that is lost,
    or a re-run that runs finished seeds again.

    Oracle: for each seed, pinocchio forward kinematics of the episode's last logged joint
    positions against the ground-truth stem base of ``VineSceneParams.sample(seed)``; the
    seeds' scenes differ, so a row of the wrong seed misses by centimetres.
    """
    out = tmp_path / "sweep"
    args = ("--seeds", "1:3", "--duration", "0.6", "--workers", "2", "--out", str(out), "--no-figures")
    stdout = run_example("05_sweep", *args)
    assert "ran seeds [" in stdout and "skipped (already done) []" in stdout, stdout
    with open(out / "sweep.csv", newline="") as f:
        rows = {int(r["seed"]): r for r in csv.DictReader(f)}
    assert sorted(rows) == [1, 2]
    bases = {seed: true_stem_base(seed) for seed in rows}
    assert np.linalg.norm(bases[1] - bases[2]) > 0.01  # different scenes: the check below can tell
    for seed, row in rows.items():
        assert row["status"] == "ok", row
        log = np.load(out / "episodes" / f"seed_{seed}" / "episode.npz")
        camera = pinocchio_frame_positions(log["q"][-1], "camera")[0]
        assert abs(float(row["final_distance_to_roi_center"]) - np.linalg.norm(camera - bases[seed])) < 1e-3
        path = np.linalg.norm(np.diff(log["value/p_c"], axis=0), axis=1).sum()
        assert abs(float(row["camera_path_length"]) - path) < 1e-6 and path > 0.01
    before = (out / "sweep.csv").read_text()
    stdout = run_example("05_sweep", *args)
    assert "ran seeds []" in stdout and "skipped (already done) [1, 2]" in stdout, stdout
    assert (out / "sweep.csv").read_text() == before
