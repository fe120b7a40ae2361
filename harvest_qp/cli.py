"""Command-line interface: ``harvest-qp demo``, ``harvest-qp check-config``.

Headless by default; nothing is downloaded and no server is started unless asked.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

from harvest_qp.config import load_controller_config
from harvest_qp.configuration import Configuration
from harvest_qp.controller import TaskController
from harvest_qp.exceptions import HarvestQPError
from harvest_qp.limits import CollisionAvoidance
from harvest_qp.robot.paths import tasks_dir
from harvest_qp.tasks import FramePoseTask


def run_reach_demo(config_path: Path, *, duration: float | None = None, solver: str | None = None) -> dict:
    """Drive both arms to the targets of a YAML config on a kinematic robot; return a summary."""
    configuration = Configuration.dual_ur5e()
    config = load_controller_config(config_path, configuration)
    controller = TaskController(
        configuration, config.tasks, config.limits, dt=config.dt, solver=solver or config.solver
    )
    collision = next((lim for lim in config.limits if isinstance(lim, CollisionAvoidance)), None)
    duration = duration or config.duration
    q = configuration.q.copy()
    statuses: Counter[str] = Counter()
    step_us, min_distance, max_speed = [], np.inf, 0.0
    for _ in range(int(round(duration / config.dt))):
        t0 = time.perf_counter_ns()
        step = controller.step(q)
        step_us.append((time.perf_counter_ns() - t0) / 1e3)
        statuses[step.status.split(":")[0]] += 1
        max_speed = max(max_speed, float(np.abs(step.qdot).max()))
        q = q + step.qdot * config.dt  # ideal velocity tracking (the MuJoCo robot comes with the sim)
        if collision is not None:
            configuration.update(q)
            min_distance = min(min_distance, float(collision.distances(configuration).min()))
    configuration.update(q)
    errors = {
        f"{task.frame} position error [m]": float(np.linalg.norm(task.error(configuration)[:3]))
        for task in config.tasks
        if isinstance(task, FramePoseTask)
    }
    in_limits = bool(np.all(q >= configuration.lower_limits) and np.all(q <= configuration.upper_limits))
    return {
        "duration [s]": duration,
        "solver": controller.solver.backend_name,
        "steps": sum(statuses.values()),
        "statuses": dict(statuses),
        **errors,
        "min collision distance [m]": min_distance if collision is not None else None,
        "safety distance [m]": collision.safety_distance if collision is not None else None,
        "max joint speed [rad/s]": max_speed,
        "joints within limits": in_limits,
        "median step [us]": float(np.median(step_us)),
    }


def _print_summary(title: str, summary: dict) -> None:
    print(title)
    for key, value in summary.items():
        text = f"{value:.4g}" if isinstance(value, float) else str(value)
        print(f"  {key:<32} {text}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="harvest-qp", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="run the QP demo headless and print a summary")
    demo.add_argument("--config", type=Path, default=None, help="YAML task config (default: tasks/reach_targets.yaml)")
    demo.add_argument("--duration", type=float, default=None, help="seconds to simulate")
    demo.add_argument("--solver", default=None, help="daqp | proxsuite | qpsolvers:<name>")
    check = sub.add_parser("check-config", help="validate a YAML task config")
    check.add_argument("config", type=Path)
    args = parser.parse_args(argv)
    try:
        if args.command == "demo":
            path = args.config or tasks_dir() / "reach_targets.yaml"
            summary = run_reach_demo(path, duration=args.duration, solver=args.solver)
            _print_summary(f"harvest_qp reach demo ({path.name}), dual UR5e, headless", summary)
            ok = summary["joints within limits"] and summary["statuses"].get("fallback", 0) == 0
            return 0 if ok else 1
        if args.command == "check-config":
            config = load_controller_config(args.config, Configuration.dual_ur5e())
            print(f"{args.config}: {len(config.tasks)} tasks, {len(config.limits)} limits, dt={config.dt} s: OK")
            return 0
    except HarvestQPError as err:
        print(f"harvest-qp: error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
