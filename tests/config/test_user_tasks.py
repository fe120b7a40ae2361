"""A user's own Task class used from YAML (issue 8, section 3): lookup, params, errors, the episode hook."""

from __future__ import annotations

import itertools
import textwrap

import numpy as np
import pytest

from harvest_qp import Configuration
from harvest_qp.cli import main
from harvest_qp.config import load_controller_config
from harvest_qp.config.settings import check_settings
from harvest_qp.exceptions import ConfigError

_count = itertools.count()

USER_MODULE = '''
import numpy as np
from pydantic import BaseModel, ConfigDict
from harvest_qp.tasks import Task


class JointTarget(Task):
    """Drive one joint to a target: J = e_j^T, v = gain * (target - q_j)."""

    def __init__(self, joint: int, target: float, *, weight=1.0, level=1, gain=1.0):
        super().__init__(1, weight=weight, level=level, gain=gain)
        self.joint, self.target = joint, target

    def compute(self, configuration, dt):
        J = np.zeros((1, configuration.nv))
        J[0, self.joint] = 1.0
        return J, np.array([self.gain * (self.target - configuration.q[self.joint])])


class WithParams(JointTarget):
    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        joint: int
        target: float = 0.5


class NeedsConfiguration(JointTarget):
    def __init__(self, configuration, joint: int):
        super().__init__(joint, float(configuration.q[joint]))


class Broken(JointTarget):
    def __init__(self, joint: int):
        raise RuntimeError("cannot build")


class NotATask:
    def __init__(self, joint: int):
        pass
'''


def _module(tmp_path) -> str:
    """A uniquely named user module next to the config files (not on sys.path)."""
    name = f"user_tasks_{next(_count)}"
    (tmp_path / f"{name}.py").write_text(USER_MODULE)
    return name


def _config(tmp_path, entry: str, name: str = "c.yaml"):
    path = tmp_path / name
    path.write_text(f"tasks:\n  - {entry}\n  - {{type: damping, weight: 1.0e-4}}\n")
    return path


def test_user_task_from_a_module_next_to_the_config_is_built_and_solved(tmp_path):
    """The QP drives joint 3 to the target of a task class that lives in the user's module.

    Oracle: joint 3's own position after the loop (hand-computed target 0.4 rad from q0).
    Catches: params not passed, level/weight/gain from YAML not applied, the task not
    reaching the controller."""
    module = _module(tmp_path)
    configuration = Configuration.dual_ur5e()
    q0 = configuration.q.copy()
    target = float(q0[3] + 0.4)
    path = _config(tmp_path, f"{{type: '{module}:JointTarget', params: {{joint: 3, target: {target}}}, "
                             "level: 1, weight: 2.0, gain: 5.0}")
    config = load_controller_config(path, configuration)
    task = config.tasks[0]
    assert type(task).__name__ == "JointTarget" and task.joint == 3
    assert (task.level, float(task.weight[0]), task.gain) == (1, 2.0, 5.0)
    from harvest_qp import TaskController

    controller = TaskController(configuration, config.tasks, [], dt=0.002)
    q = q0.copy()
    for _ in range(500):  # 1 s at gain 5: exp(-5) of the error left
        q = q + controller.step(q).qdot * 0.002
    assert abs(q[3] - target) < 0.01 * 0.4
    others = np.delete(q - q0, 3)
    assert np.abs(others).max() < 1e-6


def test_file_form_pydantic_params_and_configuration_argument(tmp_path):
    module = _module(tmp_path)
    configuration = Configuration.dual_ur5e()
    path = _config(tmp_path, f"{{type: '{module}.py:WithParams', params: {{joint: 2}}}}")
    task = load_controller_config(path, configuration).tasks[0]
    assert task.target == 0.5 and task.joint == 2  # the Params model's default
    path = _config(tmp_path, f"{{type: '{module}:NeedsConfiguration', params: {{joint: 1}}}}")
    task = load_controller_config(path, configuration).tasks[0]
    assert task.target == configuration.q[1]


@pytest.mark.parametrize(
    ("entry", "words"),
    [
        ("{type: 'no_such_pkg.tasks:Gaze'}", ["'tasks[0].type'", "cannot import module 'no_such_pkg.tasks'"]),
        ("{type: 'MODULE:JointTarjet', params: {joint: 1, target: 0}}",
         ["has no class 'JointTarjet'", "did you mean 'JointTarget'"]),
        ("{type: 'MODULE:NotATask', params: {joint: 1}}", ["is not a harvest_qp Task"]),
        ("{type: 'MODULE:JointTarget', params: {joint: 1}}", ["'tasks[0].params.target' is required"]),
        ("{type: 'MODULE:JointTarget', params: {joint: 1, target: 0, targte: 2}}",
         ["unknown key 'tasks[0].params.targte'", "expected one of: joint, target"]),
        ("{type: 'MODULE:JointTarget', params: {joint: one, target: 0}}",
         ["'tasks[0].params.joint'", "valid integer", "got 'one'"]),
        ("{type: 'MODULE:WithParams', params: {joint: 1, extra: 0}}", ["unknown key 'tasks[0].params.extra'"]),
        ("{type: 'MODULE:JointTarget', params: {joint: 1, target: 0}, level: -1}",
         ["'tasks[0].level' must be an integer >= 0", "got -1"]),
        ("{type: 'MODULE:Broken', params: {joint: 1}}", ["tasks[0]", "raised RuntimeError: cannot build"]),
        ("{type: 'missing.py:X'}", ["no file", "missing.py"]),
    ],
)
def test_user_task_errors_are_one_line_with_the_key_path(tmp_path, capsys, entry, words):
    """Catches: a ModuleNotFoundError/TypeError traceback instead of a config error, a class
    that is not a Task accepted, params not checked before the constructor runs."""
    module = _module(tmp_path)
    path = _config(tmp_path, entry.replace("MODULE", module))
    assert main(["check-config", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err and str(path) in err, err
    for word in words:
        assert word in err, (word, err)


def test_extra_tasks_join_the_paper_controllers_qp_at_their_level(tmp_path, monkeypatch):
    """`qp.extra_tasks` of an episode config end up in the controller's QP (and its backup QP)
    at the level and weight given; a bad entry names `qp.extra_tasks[i]`.

    Catches: the hook missing from HarvestController, or user tasks only in QP-only configs."""
    from harvest_qp.harvest.harvest_controller import HarvestController

    module = _module(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))  # an installed package, as far as Python is concerned
    settings = check_settings({"qp": {"extra_tasks": [
        {"type": f"{module}:JointTarget", "params": {"joint": 4, "target": 0.1}, "level": 3, "weight": 0.5}]}})
    controller = HarvestController(settings)
    extra = [t for t in controller.qp.tasks if type(t).__name__ == "JointTarget"]
    assert len(extra) == 1 and extra[0].level == 3 and float(extra[0].weight[0]) == 0.5
    assert extra[0] in controller.qp_backup.tasks
    assert len(controller.qp.tasks) == 7  # the paper episode's six (gripper translation and turn apart) plus this one
    with pytest.raises(ConfigError, match=r"'qp\.extra_tasks\[0\]\.params\.joint' is required"):
        check_settings({"qp": {"extra_tasks": [{"type": f"{module}:JointTarget", "params": {"target": 0.1}}]}})
    with pytest.raises(ConfigError, match=r"qp\.extra_tasks\[0\] \(damping\)"):
        HarvestController(check_settings({"qp": {"extra_tasks": [{"type": "damping", "weight": [1.0, 2.0]}]}}))


def test_check_config_runs_an_episode_file_with_user_tasks(tmp_path, capsys):
    module = _module(tmp_path)
    path = tmp_path / "episode.yaml"
    path.write_text(textwrap.dedent(f"""\
        qp:
          extra_tasks:
            - {{type: '{module}:JointTarget', params: {{joint: 0, target: 0.0}}, level: 2}}
        """))
    assert main(["check-config", str(path)]) == 0
    assert "1 extra task(s)" in capsys.readouterr().out
