"""A task defined in user code, used from YAML: ``type: user_tasks.gaze:GazeTask``.

``examples/user_tasks/gaze.py`` defines ``GazeTask`` (a :class:`harvest_qp.tasks.Task`
subclass with its own pydantic ``Params``); ``examples/04_custom_task.yaml`` names it next to
built-in tasks and limits. :func:`harvest_qp.config.load_controller_config` checks the file
against the schema (the task's ``params`` against ``GazeTask.Params``), imports the module
(found next to the YAML file; no ``sys.path`` set-up needed) and builds the task with its
``level`` and ``gain``. The loop then runs headless on the kinematic dual UR5e (ideal velocity
tracking at 500 Hz) and prints the gaze angle before and after. The same entry can go under
``qp.extra_tasks`` of an episode file (``examples/04_paper_with_gaze.yaml``).

    python examples/04_custom_task_from_yaml.py [--steps 500] [--json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from harvest_qp import Configuration, TaskController
from harvest_qp.config import load_controller_config

HERE = Path(__file__).resolve().parent
CONFIG = HERE / "04_custom_task.yaml"


def run(steps: int = 500, config_path: Path = CONFIG) -> dict:
    """Run the YAML-configured QP for ``steps`` ticks; returns the joint vectors and the gaze target."""
    configuration = Configuration.dual_ur5e()
    config = load_controller_config(config_path, configuration)
    gaze = next(t for t in config.tasks if type(t).__name__ == "GazeTask")
    controller = TaskController(configuration, config.tasks, config.limits, dt=config.dt, solver=config.solver)
    q0 = configuration.q.copy()
    angle_start = gaze.angle(configuration)
    q = q0.copy()
    statuses = set()
    for _ in range(steps):
        step = controller.step(q)
        statuses.add(step.status.split(":")[0])
        q = q + step.qdot * config.dt
    configuration.update(q)
    return {"q_start": q0.tolist(), "q_end": q.tolist(), "target": gaze.target.tolist(), "frame": gaze.frame,
            "angle_start_deg": float(np.degrees(angle_start)),
            "angle_end_deg": float(np.degrees(gaze.angle(configuration))), "statuses": sorted(statuses),
            "gaze_level": gaze.level, "gaze_gain": gaze.gain}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=500, help="control ticks at 500 Hz (default 500 = 1 s)")
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object")
    args = parser.parse_args()
    out = run(args.steps)
    if args.json:
        print(json.dumps(out))
        return
    print(f"GazeTask from {CONFIG.name}: level {out['gaze_level']}, gain {out['gaze_gain']} 1/s")
    print(f"camera axis to target: {out['angle_start_deg']:.1f} deg -> {out['angle_end_deg']:.2f} deg "
          f"after {args.steps} ticks (QP statuses: {', '.join(out['statuses'])})")


if __name__ == "__main__":
    main()
