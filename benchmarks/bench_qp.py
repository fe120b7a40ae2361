"""Per-step cost of the dual-UR5e velocity QP: harvest_qp side by side with placo, mink, pink.

The problem (see ``benchmarks/peers.py``, ``BenchProblem``): camera 5-D twist task,
gripper 6-D twist task, posture, damping, joint position / velocity / acceleration
limits and, in the collision variants, velocity-damper collision avoidance over the
same-arm, arm-to-arm, arm-to-stand and 8 obstacle-sphere candidate pairs. Every
contender is timed in the same process, in closed loop (q += qdot dt), from the
kinematics update to the solved joint velocities.

Usage: ``python benchmarks/bench_qp.py [-n 2000] [--peers placo,mink,pink]``.
The last line printed is one JSON object with the medians [us].
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks import peers  # noqa: E402
from harvest_qp import Configuration, TaskController  # noqa: E402
from harvest_qp.limits import (  # noqa: E402
    CollisionAvoidance,
    JointAccelerationLimit,
    JointPositionLimit,
    JointVelocityLimit,
)
from harvest_qp.tasks import DampingTask, FrameTwistTask, PostureTask  # noqa: E402


class HarvestQPStep:
    """harvest_qp's controller set up on the benchmark problem."""

    def __init__(self, problem: peers.BenchProblem, collision: bool, solver: str = "daqp") -> None:
        config = Configuration.dual_ur5e(problem.q0)
        self.camera = FrameTwistTask(
            peers.CAMERA_FRAME, weight=problem.w_camera * np.array([1, 1, 1, 1, 1, 0.0]), weight_frame="local"
        )
        self.gripper = FrameTwistTask(peers.GRIPPER_FRAME, weight=problem.w_gripper)
        tasks = [
            self.camera,
            self.gripper,
            PostureTask(problem.q_home, weight=problem.w_posture, gain=problem.k_posture),
            DampingTask(config.nv, weight=problem.w_damping),
        ]
        limits = [
            JointPositionLimit(config, gain=1.0),
            JointVelocityLimit(config, max_velocity=problem.v_max),
            JointAccelerationLimit(config, max_acceleration=problem.a_max),
        ]
        self.collision = None
        if collision:
            self.collision = CollisionAvoidance.dual_ur5e(
                config, safety_distance=problem.d_safe, influence_distance=problem.d_influence, gain=problem.xi
            )
            centres, radii = problem.obstacle_arrays()
            self.collision.set_obstacle_spheres(centres, radii)
            limits.append(self.collision)
        self.n_pairs = self.collision.num_candidate_pairs if self.collision else 0
        self.controller = TaskController(config, tasks, limits, dt=problem.dt, solver=solver,
                                         max_acceleration=problem.a_max)
        self.problem = problem

    def step(self, q: np.ndarray, t: float) -> np.ndarray:
        v_c, v_g = self.problem.twists(t)
        self.camera.set_reference(v_c)
        self.gripper.set_reference(v_g)
        result = self.controller.step(q)
        if not result.ok:
            raise RuntimeError(result.status)
        return result.qdot


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-n", type=int, default=2000, help="timed steps per contender")
    parser.add_argument("--check", type=int, default=200, help="closed-loop check steps (0: none)")
    parser.add_argument("--peers", default="placo,mink,pink", help="comma-separated subset of peers")
    parser.add_argument("--differences", action="store_true", help="print how the peers' set-ups differ")
    args = parser.parse_args(argv)

    problem = peers.BenchProblem()
    print(peers.describe_problem(problem))
    if args.differences:
        for who, lines in peers.DIFFERENCES.items():
            print(f"differences ({who}):")
            for line in lines:
                print(f"  - {line}")
    evaluator = peers.Evaluator(problem) if args.check else None
    results: dict[str, float | None] = {}
    print("medians per step (kinematics to joint velocities), closed loop:")
    for solver in ("daqp", "proxsuite"):
        for collision in (False, True):
            key = "harvest_qp" + ("_proxsuite" if solver == "proxsuite" else "") + ("_collision" if collision else "")
            key += "_us"
            info = {"pairs": HarvestQPStep(problem, collision, solver).n_pairs}
            if args.check:
                info["check"] = peers.check_closed_loop(
                    HarvestQPStep(problem, collision, solver).step, problem, args.check, evaluator
                )
            results[key] = peers.time_closed_loop(HarvestQPStep(problem, collision, solver).step, problem, 200, args.n)
            print(peers.format_result(key, results[key], info))
    results.update(
        peers.run_peers(problem, n=args.n, n_check=args.check, peers=tuple(p for p in args.peers.split(",") if p))
    )
    print("ratios (peer / harvest_qp daqp, same variant; > 1: harvest_qp faster):")
    for peer in ("placo", "mink", "pink"):
        for suffix in ("", "_collision"):
            ours, theirs = results.get(f"harvest_qp{suffix}_us"), results.get(f"{peer}{suffix}_us")
            if ours and theirs:
                print(f"  {peer + suffix:20s} {theirs / ours:6.2f}x")
    print(json.dumps({k: (None if v is None else round(v, 2)) for k, v in results.items()}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
