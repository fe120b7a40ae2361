"""The paper episode through DualUR5eRobot on the stand-in, the dry run, and the stop on every exit path."""

from __future__ import annotations

import argparse
import os
import signal

import numpy as np
import pytest

from harvest_qp.config.settings import load_settings
from harvest_qp.exceptions import HarvestQPError
from harvest_qp.harvest.harvest_controller import HarvestController
from harvest_qp.real.cli import run_ur
from harvest_qp.real.episode import run_real
from harvest_qp.robot.paths import tasks_dir
from harvest_qp.sim.paper_episode import build_robot
from tests.loop import traces
from tests.loop.conftest import SCENE_ARGS
from tests.real.conftest import CAMERA_HOST, GRASP_HOST
from tests.real.standin import LabCamera, LabCell

PAPER = tasks_dir() / "paper.yaml"
#: The loop tests' scene settings (tests/loop/conftest.py), ending 0.2 s after pre-cut instead of 2 s.
OVERRIDES = [a for a in SCENE_ARGS if a != "--set" and not a.startswith("episode.end_after_precut")]
OVERRIDES.append("episode.end_after_precut=0.2")


@pytest.fixture(scope="module")
def scene_lab():
    """The lab of the paper episode, seed 0, with its camera at the scene tests' settings."""
    return build_robot(load_settings(PAPER, OVERRIDES), 0)


def _hooks(lab) -> tuple[LabCell, dict]:
    cell = LabCell(lab, (CAMERA_HOST, GRASP_HOST))
    # warmup=False: this process has run lab episodes already (test_warm_up.py checks the warm-up itself)
    return cell, {"rtde": cell, "camera_source": LabCamera(lab), "clock": cell.clock, "warmup": False}


def _closed_both(cell: LabCell) -> bool:
    """speedStop then stopScript was sent (at least tried) to both arms at the end."""
    for host in (CAMERA_HOST, GRASP_HOST):
        calls = cell.methods_called(host, "control")
        if "stopScript" not in calls or "speedStop" not in calls[: calls.index("stopScript")][-3:]:
            return False
    return True


def test_dry_run_reads_and_moves_nothing(scene_lab, capsys, tmp_path):
    scene_lab.reset()
    q0 = scene_lab.joint_positions()
    cell, hooks = _hooks(scene_lab)
    args = argparse.Namespace(config=PAPER, camera_arm=CAMERA_HOST, grasp_arm=GRASP_HOST, camera="realsense",
                              serial=None, cell=None, dry_run=True, out=tmp_path, duration=None, overrides=OVERRIDES,
                              mapper=None, no_figures=True, viewer="none")
    assert run_ur(args, **hooks) == 0
    out = capsys.readouterr().out
    assert "nothing moved" in out and "camera arm joints [rad]" in out and "wrist force, world, untared [N]" in out
    assert "tasks/real/calibration_example.yaml" in out and "stem" in out and "points of 80x142" in out
    np.testing.assert_array_equal(scene_lab.joint_positions(), q0)
    # A dry run only reads: RTDEControlInterface (which uploads and starts the control script, taking the
    # arm over from the pendant) is never opened on either arm (it was, before: found by an audit).
    assert cell.methods_called(kind="control") == [], cell.methods_called(kind="control")
    assert set(cell.methods_called(kind="receive")) >= {"getActualQ", "disconnect"}


def test_paper_episode_through_the_adapter_reaches_precut_like_the_lab(scene_lab, tmp_path):
    """The whole episode (camera from the lab) against the lab's stored trace of seed 0 (tests/loop/traces)."""
    scene_lab.reset()
    cell, hooks = _hooks(scene_lab)
    metrics = run_real(PAPER, camera_arm=CAMERA_HOST, grasp_arm=GRASP_HOST, overrides=OVERRIDES, out=tmp_path,
                       figures=True, **hooks)
    assert metrics["episode_status"] == "completed" and metrics["phase_reached"] == "precut"
    assert metrics["criteria"]["precut_reached"] and metrics["abort_reason"] is None
    stored = traces.load(0)
    assert stored["metrics"]["phase_reached"] == "precut"
    for key in ("t_bimanual_start", "t_precut", "final_position_error"):
        assert metrics[key] == pytest.approx(stored["metrics"][key], abs=traces.CLOSE_METRICS[key]), key
    log = dict(np.load(tmp_path / "episode.npz"))
    t = log["t"][:: traces.STRIDE]
    n = min(len(t), len(stored["t"]))
    np.testing.assert_allclose(t[:n], stored["t"][:n], atol=1e-9)
    for key in ("q", "value/force_nc", "value/position_error"):
        ours, theirs = log[key][:: traces.STRIDE][:n], stored[key][:n]
        both = np.isfinite(ours) & np.isfinite(theirs)
        assert np.max(np.abs(ours[both] - theirs[both])) <= traces.TOLERANCES[key], key
    assert (tmp_path / "metrics.json").exists()
    assert {"fig_exp_f.png", "fig_exp_reach.png", "fig_exp_unv.png"} <= {p.name for p in tmp_path.glob("*.png")}
    assert _closed_both(cell)
    assert cell.methods_called(GRASP_HOST, "control").count("zeroFtSensor") == 1  # the controller's tare


def _failing_step(at: int, action):
    original = HarvestController.step
    count = {"n": 0}

    def step(self, obs):
        count["n"] += 1
        if count["n"] == at:
            action()
        return original(self, obs)

    return step


@pytest.mark.parametrize("fault", ["exception", "ctrl-c", "sigterm", "lost connection"])
def test_stop_on_every_exit_path(lab, monkeypatch, tmp_path, fault):
    """Whatever ends the episode, both arms get speedStop and stopScript (the lost one at least tried)."""
    lab.reset()
    cell, hooks = _hooks(lab)

    def boom():
        raise RuntimeError("controller bug")

    def interrupt():
        raise KeyboardInterrupt

    def sigterm():
        os.kill(os.getpid(), signal.SIGTERM)

    actions = {"exception": boom, "ctrl-c": interrupt, "sigterm": sigterm, "lost connection": lambda: cell.drop(1)}
    monkeypatch.setattr(HarvestController, "step", _failing_step(4, actions[fault]))
    kwargs = dict(camera_arm=CAMERA_HOST, grasp_arm=GRASP_HOST, overrides=OVERRIDES, out=tmp_path, duration=0.05,
                  figures=False, **hooks)
    if fault in ("ctrl-c", "sigterm"):
        with pytest.raises(KeyboardInterrupt):
            run_real(PAPER, **kwargs)
    else:
        metrics = run_real(PAPER, **kwargs)
        expected = {"exception": ("controller_error", "controller.step failed"),
                    "lost connection": ("robot_error", "lost connection to the grasping arm at 10.0.0.2")}[fault]
        assert metrics["episode_status"] == expected[0] and expected[1] in metrics["stop_reason"]
        assert not metrics["success"]
    assert _closed_both(cell)
    assert signal.getsignal(signal.SIGTERM) is signal.default_int_handler or signal.getsignal(
        signal.SIGTERM) == signal.SIG_DFL


def test_missing_addresses_and_viewer_are_errors(tmp_path):
    args = argparse.Namespace(config=PAPER, camera_arm=None, grasp_arm=GRASP_HOST, viewer="none")
    with pytest.raises(HarvestQPError, match="--camera-arm IP and --grasp-arm IP"):
        run_ur(args)
    args = argparse.Namespace(config=PAPER, camera_arm=CAMERA_HOST, grasp_arm=GRASP_HOST, viewer="meshcat")
    with pytest.raises(HarvestQPError, match="--viewer"):
        run_ur(args)
