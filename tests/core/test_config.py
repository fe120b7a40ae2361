"""YAML task configs and the CLI."""

import numpy as np
import pytest

from harvest_qp import ConfigError
from harvest_qp.cli import main, run_reach_demo
from harvest_qp.config import load_controller_config
from harvest_qp.limits import CollisionAvoidance
from harvest_qp.robot.paths import tasks_dir
from harvest_qp.tasks import FramePoseTask


def test_shipped_configs_load(configuration):
    # paper*.yaml are episode settings trees (harvest_qp.config.settings, tested in tests/loop, tests/config).
    from harvest_qp.config import config_kind, resolve_file

    paths = sorted(p for p in tasks_dir().glob("*.yaml") if config_kind(resolve_file(p).data) == "tasks")
    assert {p.name for p in paths} == {"reach_targets.yaml", "sim_reach_stem.yaml"}
    assert paths
    for path in paths:
        config = load_controller_config(path, configuration)
        assert config.tasks and config.dt > 0


def test_reach_config_targets_are_offsets_from_start(configuration):
    config = load_controller_config(tasks_dir() / "reach_targets.yaml", configuration)
    cam = next(t for t in config.tasks if isinstance(t, FramePoseTask) and t.frame == "camera")
    np.testing.assert_allclose(cam.target_position, configuration.frame_position("camera") + [0.22, -0.55, 0.10])
    collision = next(lim for lim in config.limits if isinstance(lim, CollisionAvoidance))
    assert collision.safety_distance == 0.02 and "obstacle_0" in collision.capsule_names


@pytest.mark.parametrize(
    "text, match",
    [
        ("tasks: []", r"'tasks': list should have at least 1 item"),
        ("tasks: [{type: spin}]", r"'tasks\[0\]\.type': unknown task type 'spin'"),
        ("tasks: [{type: damping, colour: red}]", r"unknown key 'tasks\[0\]\.colour'; expected one of: type, weight"),
        ("tasks: [{type: frame_twist, frame: elbow}]", "valid frames are"),
        ("tasks: [{type: damping, weight: -1}]", r"'tasks\[0\]\.weight' must be a number >= 0 .*; got -1"),
        ("tasks: [{type: damping}]\nlimits: [{type: joint_velocity, max_velocity: [1, 2]}]", r"shape \(12,\)"),
        ("tasks: [{type: damping}]\ndt: -1", "'dt' must be a number > 0; got -1"),
        ("!!python/object/apply:os.system ['echo unsafe']", "not valid YAML"),
        ("tasks: [{type: damping}]\nlimits: [{type: collision, obstacle_spheres: [{centre: [0, 0, 1]}]}]",
         r"unknown key 'limits\[0\]\.obstacle_spheres\[0\]\.centre' \(did you mean 'center'\?\)"),
    ],
)
def test_bad_configs_name_the_problem(tmp_path, configuration, text, match):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=match):
        load_controller_config(path, configuration)


def test_reach_demo_keeps_arms_apart_and_in_limits():
    summary = run_reach_demo(tasks_dir() / "reach_targets.yaml", duration=1.0)
    assert summary["statuses"] == {"ok": 500}
    assert summary["joints within limits"]
    assert summary["min collision distance [m]"] >= summary["safety distance [m]"] - 1e-4
    assert summary["max joint speed [rad/s]"] <= 1.5 + 1e-9


def test_cli_check_config_reports_errors(tmp_path, capsys):
    path = tmp_path / "bad.yaml"
    path.write_text("tasks: [{type: spin}]")
    assert main(["check-config", str(path)]) == 2
    assert "unknown task type 'spin'" in capsys.readouterr().err
    assert main(["check-config", str(tasks_dir() / "reach_targets.yaml")]) == 0


def test_main_demo_on_the_mujoco_scene_reaches_the_stem_view(tmp_path):
    from harvest_qp.cli import run_sim_demo

    log = tmp_path / "demo.npz"
    summary = run_sim_demo(tasks_dir() / "sim_reach_stem.yaml", duration=4.0, camera=True, log_path=log)
    assert summary["episode"] == "completed"
    assert summary["statuses"] == {"ok": 2000}
    assert summary["camera to viewpoint [m]"] < 0.02
    assert summary["stem off optical axis [deg]"] < 3.0
    assert summary["gripper hold error [mm]"] < 2.0  # the cluster stays held
    assert summary["min collision distance [m]"] > 0.01
    first, last = (int(x) for x in summary["stem points seen first/last"].split(" / "))
    assert first == 0 and last > 20, "the stem is hidden at the start and seen at the viewpoint"
    assert log.is_file()


def test_cli_demo_exit_code(capsys):
    assert main(["demo", "--duration", "0.5", "--no-camera"]) == 0
    out = capsys.readouterr().out
    assert "MuJoCo vine scene" in out and "joints within limits" in out
