"""The real episode loads no compiled kernel inside its control loop after ``warm_up``.

numba loads each kernel from its on-disk cache at the kernel's first call in a process (50-170 ms
a batch on a warm cache, seconds on a cold one). Without the warm-up those first calls came in the
real episode's control loop, mid-approach and at the switch, while the arms moved: cycles far
beyond the watchdog's 20 ms, which stop the arms. Oracle: numba's own record of the signatures
each dispatcher has loaded, in a fresh interpreter (this process has run lab episodes already).

Bug it catches (planted once: ``warm=False`` below): the real episode then loads the stem fit's,
the map's, the collision rows' and the grasp target's kernels (29 dispatchers) inside the loop; with
the fallback backends left out of the warm-up, the step that reaches proxsuite imports it.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

SCRIPT = r"""
import json, sys, tempfile
from numba.core.registry import CPUDispatcher
from harvest_qp.config.settings import load_settings
from harvest_qp.real.episode import run_real, warm_up
from harvest_qp.sim.paper_episode import build_robot
from tests.real.conftest import CAMERA_HOST, GRASP_HOST
from tests.real.standin import LabCamera, LabCell
from tests.real.test_episode import OVERRIDES, PAPER

def loaded():
    counts = {}
    for name, module in list(sys.modules.items()):
        if name.startswith("harvest_qp"):
            for obj in list(vars(module).values()):
                if isinstance(obj, CPUDispatcher):
                    counts[f"{obj.py_func.__module__}.{obj.py_func.__qualname__}"] = len(obj.signatures)
    return counts

settings = load_settings(PAPER, OVERRIDES)
if WARM:
    warm_up(settings)
lab = build_robot(settings, 0)
cell = LabCell(lab, (CAMERA_HOST, GRASP_HOST))
before = loaded()
with tempfile.TemporaryDirectory() as out:
    metrics = run_real(PAPER, camera_arm=CAMERA_HOST, grasp_arm=GRASP_HOST, overrides=OVERRIDES, out=out,
                       figures=False, rtde=cell, camera_source=LabCamera(lab), clock=cell.clock, warmup=False)
after = loaded()

# A step whose daqp and quadprog both fail: the solver's last fallback (proxsuite) answers.
import numpy as np
from harvest_qp import Configuration
from harvest_qp.backends import make_backend
from harvest_qp.backends.base import SolverCyclingError
from harvest_qp.limits import JointVelocityLimit
from harvest_qp.solver import Solver
from harvest_qp.tasks import DampingTask, FrameTwistTask

class Failing:
    def __init__(self, name):
        self.name = name
    def solve(self, problem):
        raise SolverCyclingError("planted", problem=problem, backend=self.name)

configuration = Configuration.dual_ur5e()
task = FrameTwistTask("camera")
task.set_reference(np.array([0.05, 0.0, 0.0, 0.0, 0.0, 0.0]))
solver = Solver(backend_factory=lambda name, level: Failing(name) if name in ("daqp", "quadprog")
                else make_backend(name))
modules = set(sys.modules)
solution = solver.solve(configuration, [task, DampingTask(12)], [JointVelocityLimit(configuration)], 0.002)
print(json.dumps({"phase": metrics["phase_reached"],
                  "new": sorted(k for k, n in after.items() if n > before.get(k, 0)),
                  "fallback_retries": solution.retries,
                  "fallback_imports": sorted(m for m in set(sys.modules) - modules if "." not in m)}))
"""


def _run(warm: bool) -> dict:
    env = {**os.environ, "PYTHONPATH": str(REPO), "NUMBA_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", f"WARM = {warm}\n" + SCRIPT], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_after_the_warm_up_the_real_episode_loads_no_kernel_in_its_loop():
    result = _run(warm=True)
    assert result["phase"] == "precut"  # the episode went through the switch and the stretch
    assert result["new"] == [], f"kernels first called inside the real episode: {result['new']}"
    # the last fallback backend answered a step without importing anything (proxsuite: ~140 ms)
    assert result["fallback_retries"] == ["daqp: SolverCyclingError", "quadprog: SolverCyclingError"]
    assert result["fallback_imports"] == []


def test_run_real_warms_up_with_the_mapper_and_settings_the_episode_runs(monkeypatch, tmp_path, lab):
    """Bug caught (an independent review): the warm-up ran the settings' mapper.kind while the episode
    ran ``--mapper``; with mapper.kind pinv and --mapper qp, 18 kernels (the map's, the QP's) were
    first called inside the real loop."""
    from harvest_qp.real import episode
    from tests.real.conftest import CAMERA_HOST, GRASP_HOST
    from tests.real.standin import LabCell

    seen = {}

    def recording_warm_up(settings, *, mapper=None, **kwargs):
        seen.update(mapper=mapper, kind=settings.mapper.kind, environment=list(settings.qp.environment))
        return {"wall_time": 0.0, "phase_reached": "precut"}

    monkeypatch.setattr(episode, "warm_up", recording_warm_up)
    lab.reset()
    cell = LabCell(lab, (CAMERA_HOST, GRASP_HOST))
    from harvest_qp.robot.paths import tasks_dir

    episode.run_real(tasks_dir() / "paper.yaml", camera_arm=CAMERA_HOST, grasp_arm=GRASP_HOST, camera=None,
                     dry_run=False, out=tmp_path, duration=0.02, figures=False, mapper="qp",
                     overrides=["mapper.kind=pinv", "qp.environment=[]"], rtde=cell, clock=cell.clock,
                     camera_source=_NoFrames())
    assert seen == {"mapper": "qp", "kind": "pinv", "environment": []}


class _NoFrames:
    """A camera that delivers nothing (the 0.02 s episode needs none)."""

    def attach(self, robot):
        pass

    def latest(self):
        return None

    def close(self):
        pass
