"""The paper episode end to end from the CLI's own code path (``harvest-qp run``).

One episode on the default scene at reduced resolution (141x80: 848x480 downsampled by 6),
shared with ``test_paper_scenes.py`` (``conftest.cli_episode``), keeps the suite fast; the
default scene and seeds 1-5 at the paper's 283x160, with both mappers, are run by
``benchmarks/run_paper_scenes.py`` (minutes).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from harvest_qp.cli import main
from harvest_qp.robot.paths import tasks_dir
from harvest_qp.sim import build_vine_scene

PAPER = tasks_dir() / "paper.yaml"
METRIC_KEYS = {
    "success", "phase_reached", "t_bimanual_start", "final_distance_to_roi_center", "roi_radius", "final_theta_deg",
    "visible_stem_points_start", "visible_stem_points_switch", "visible_stem_points_end", "final_position_error",
    "final_alignment_deg", "final_cutter_stem_angle_deg", "force_mean_last_1s", "force_max", "f_d",
    "min_collision_distance", "contacts", "stem_torn", "max_joint_limit_violation", "qp_failures", "abort_reason",
    "realtime_factor",
}
FIGURES = ["fig_exp_reach", "fig_exp_center", "fig_exp_unv", "fig_exp_ep", "fig_exp_eo", "fig_exp_f",
           "fig_exp_proc", "fig_PC_proc"]
LOW_RES = ["--set", "camera.downsample=6", "--set", "perception.min_stem_points=6",
           "--set", "episode.end_after_precut=1.0"]


@pytest.fixture(scope="module")
def default_episode(cli_episode):
    # The same episode as test_paper_scenes.py's default scene (run once, with the figures).
    return cli_episode(0, *cli_episode.scene_args, figures=True)


def test_run_writes_metrics_log_and_figures(default_episode):
    code, metrics, log, out = default_episode
    assert code == (0 if metrics["success"] else 1)
    assert METRIC_KEYS <= set(metrics)
    for name in FIGURES:
        png = out / f"{name}.png"
        assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000
    n = len(log["t"])
    for key, shape in (("value/phase", (n,)), ("value/p_r", (n, 3)), ("value/p_sb", (n, 3)), ("value/p_gd", (n, 3)),
                       ("value/n_c", (n, 3)), ("value/V_c", (n, 6)), ("value/V_g", (n, 6)), ("force", (n, 3)),
                       ("stem_points", (n,))):
        assert log[key].shape == shape, key
    assert "collision/pair_names" in log and log["collision/active_pair"].shape[0] == n


def test_default_scene_reaches_the_bimanual_phase_safely(default_episode):
    """The closed loop on the paper's scene: switch, stretch, no contact, no tear, bounded force.

    Oracles from the simulator's ground truth, independent of the controller: the true stem
    base (scene), the true stem tension, the capsule distances recomputed from the logged
    joint positions."""
    _, metrics, log, _ = default_episode
    assert metrics["t_bimanual_start"] is not None
    assert metrics["phase_reached"] in ("bimanual", "precut", "abort")
    assert not metrics["stem_torn"]
    scene = build_vine_scene()
    p_sb = log["value/p_sb"][-1]
    assert np.linalg.norm(p_sb - scene.stem_base) < 0.015  # the frozen estimate vs the true base
    # Until a contact disturbs the wrist, the measured (tared) force along n_c is the true stem
    # tension (success, contacts included, is checked in test_paper_scenes.py).
    t = log["t"]
    contact = np.zeros(len(t), dtype=bool)
    for key in [k for k in log if k.startswith("truth/contacts_")]:
        contact |= log[key] > 0
    first_contact = t[contact][0] if np.any(contact) else np.inf
    after = (t > metrics["t_bimanual_start"] + 1.0) & (t < first_contact) & (log["value/phase"] < 3)
    tension = log["truth/stem_tension"][after]
    assert np.count_nonzero(after) > 1000
    assert np.max(np.abs(log["value/force_nc"][after] - tension)) < 0.5
    assert metrics["force_max"] <= 2 * metrics["f_d"]
    assert metrics["true_tension_max"] <= 2 * metrics["f_d"]


def test_force_limit_below_f_d_aborts_before_the_stem_tears(tmp_path):
    """Safety: a force limit set below f_d ends the episode on the force limit, safely.

    The abort must come from the force limit (reason logged), the stem must never tear (the
    simulator's ground truth), the arms must come to rest, and the measured force along n_c
    must never exceed the limit by more than the largest one-tick rise seen before the abort.
    Catches: a force check on the wrong axis or sign, a missing abort, an abort that keeps
    pulling."""
    out = tmp_path / "limit"
    code = main(["run", str(PAPER), "--seed", "0", "--out", str(out), "--no-figures", *LOW_RES,
                 "--set", "safety.force_limit=1.5"])
    metrics = json.loads((out / "metrics.json").read_text())
    log = dict(np.load(out / "episode.npz"))
    assert code == 1 and not metrics["success"]
    assert metrics["abort_reason"] is not None and "above the limit 1.50 N" in metrics["abort_reason"]
    assert not metrics["stem_torn"] and not np.any(log["truth/stem_torn"] > 0)
    n_c = log["value/n_c"][-1]
    along = log["force"] @ n_c
    bimanual = log["value/phase"] >= 1
    rises = np.diff(along[bimanual])
    aborted = log["value/phase"] == 3
    first = int(np.flatnonzero(aborted)[0])
    assert np.max(along[first:]) <= 1.5 + np.max(rises[: first - int(np.flatnonzero(bimanual)[0])]) + 1e-9
    assert np.abs(log["qdot"][-1]).max() < 1e-2  # at rest at the end
