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


class HarvestQPBindingStep(HarvestQPStep):
    """The collision variant with the tools driven towards each other: collision rows bind.

    The camera's and gripper's linear references point at the other tool (1 m/s each), so after
    a few hundred ticks the dampers between the arms are active and binding. Peers are not run
    on this variant (their set-ups in ``peers.py`` follow the shared reference trajectory).
    """

    def __init__(self, problem: peers.BenchProblem, solver: str = "daqp") -> None:
        super().__init__(problem, True, solver)
        self.binding_rows: list[int] = []
        self.rows: list[int] = []

    def step(self, q: np.ndarray, t: float) -> np.ndarray:
        config = self.controller.configuration
        config.update(q)
        gap = config.frame_position(peers.GRIPPER_FRAME) - config.frame_position(peers.CAMERA_FRAME)
        direction = gap / max(np.linalg.norm(gap), 1e-9)
        self.camera.set_reference(np.concatenate([1.0 * direction, np.zeros(3)]))
        self.gripper.set_reference(np.concatenate([-1.0 * direction, np.zeros(3)]))
        result = self.controller.step(q)
        if not result.ok:
            raise RuntimeError(result.status)
        problem = self.controller.solver_solution.problems[-1]
        active = problem.h < 1e29
        self.rows.append(int(active.sum()))
        self.binding_rows.append(int(np.sum(np.abs(problem.G[active] @ result.qdot - problem.h[active]) < 1e-9)))
        return result.qdot


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-n", type=int, default=2000, help="timed steps per contender (split over the rounds)")
    parser.add_argument("--rounds", type=int, default=5, help="round-robin rounds (robust to host speed drift)")
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

    # Every contender: key -> factory of a fresh stepper.
    factories: dict[str, object] = {}
    for solver in ("daqp", "proxsuite"):
        for collision in (False, True):
            key = "harvest_qp" + ("_proxsuite" if solver == "proxsuite" else "") + ("_collision" if collision else "")
            factories[key + "_us"] = lambda c=collision, s=solver: HarvestQPStep(problem, c, s)
    factories["harvest_qp_collision_binding_us"] = lambda: HarvestQPBindingStep(problem)
    for name in (p for p in args.peers.split(",") if p):
        for collision in (False, True):
            key = f"{name}_collision_us" if collision else f"{name}_us"
            factories[key] = lambda c=collision, f=peers.PEERS[name]: f(problem, c)

    infos: dict[str, dict] = {}
    steppers: dict[str, object] = {}
    for key, make in factories.items():
        info: dict = {}
        infos[key] = info
        try:
            stepper = make()
            info["pairs"] = getattr(stepper, "n_pairs", 0)
            if args.check:
                info["check"] = peers.check_closed_loop(stepper.step, problem, args.check, evaluator)
            steppers[key] = make()  # fresh state for timing
        except Exception as exc:  # noqa: BLE001 - report and skip a contender that cannot run
            info["error"] = f"{type(exc).__name__}: {exc}"

    # Round-robin: the host's speed drifts by up to ~1.7x over minutes, so every contender
    # is timed in every round and the median of its round medians is reported.
    per_round = max(args.n // max(args.rounds, 1), 50)
    rounds: dict[str, list[float]] = {key: [] for key in steppers}
    for _ in range(max(args.rounds, 1)):
        for key, stepper in steppers.items():
            rounds[key].append(peers.time_closed_loop(stepper.step, problem, 50, per_round))
    results: dict[str, float | None] = {
        key: (float(np.median(rounds[key])) if key in rounds else None) for key in factories
    }
    binding = steppers.get("harvest_qp_collision_binding_us")
    if binding is not None and binding.rows:
        late = slice(len(binding.rows) // 2, None)
        print(
            f"binding variant: {np.median(binding.rows[late]):.0f} collision rows in the QP (median, second half), "
            f"{np.median(binding.binding_rows[late]):.0f} binding; pairs evaluated exactly per step: those passing "
            f"the bounding-sphere broadphase (d_i), of {binding.n_pairs} candidates; rows kept: max_pairs "
            f"{binding.collision.max_pairs} closest + up to {binding.collision.max_extra_rows} end-point rows"
        )
    print(f"medians per step (kinematics to joint velocities), closed loop, {args.rounds} interleaved rounds:")
    for key in factories:
        print(peers.format_result(key, results[key], infos[key]))
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
