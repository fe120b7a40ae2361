"""Per-step cost of the dual-UR5e velocity QP: harvest_qp side by side with placo, mink, pink.

The problem (see ``benchmarks/peers.py``, ``BenchProblem``): camera 5-D twist task,
gripper 6-D twist task, posture, damping, joint position / velocity / acceleration
limits and, in the collision variants, velocity-damper collision avoidance over the
same-arm, arm-to-arm, arm-to-stand and 8 obstacle-sphere candidate pairs. Every
contender is timed in the same process, in closed loop (q += qdot dt), from the
kinematics update to the solved joint velocities.

Usage: ``python benchmarks/bench_qp.py [-n 2000] [--peers placo,mink,pink] [--episode 20]``.
The last line printed is one JSON object with the medians [us].

``--episode S`` (0: off) adds ``harvest_qp_episode_us``: the paper episode's own QP
(``tasks/paper.yaml``: two priority levels, the camera/gripper/roll twist tasks, posture and
damping, the joint limits and the collision limit with the obstacle map's cells), recorded
from the first ``S`` simulated seconds of the default episode (every ``--episode-every``-th
tick: joint positions, previous command, the three task references and the map cells fed
to the collision limit) and replayed problem by problem on the episode's own
:class:`~harvest_qp.TaskController` the way the loop calls it (the tick's kinematics updated
first, untimed, then ``TaskController.step(q, kinematics_updated=True)`` timed), next to
``harvest_qp_collision_us`` timed the same way (thread CPU time, interleaved rounds): the
like-for-like figure for the in-episode QP step of ``bench_episode.py`` (issue 7 section 7).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
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


@dataclass
class EpisodeTick:
    """What the paper episode's QP step saw at one tick (enough to rebuild its problem exactly)."""

    q: np.ndarray
    previous_qdot: np.ndarray
    references: tuple[np.ndarray, np.ndarray, np.ndarray]
    """Camera, gripper and roll task references [m/s, rad/s]."""
    obstacle_p0: np.ndarray
    obstacle_p1: np.ndarray
    obstacle_radius: np.ndarray
    qdot: np.ndarray | None = None
    """The command the episode's step returned (the replay is checked against it)."""


class EpisodeProblems:
    """The paper episode's own QP problems, recorded from a run and replayed on its controller.

    Args:
        duration: simulated seconds of the default paper episode (seed 0) to record [s].
        every: record every ``every``-th tick.
        settings: settings file (default ``tasks/paper.yaml``).
    """

    def __init__(self, duration: float = 20.0, every: int = 10, settings: Path | None = None) -> None:
        from harvest_qp.config.settings import load_settings
        from harvest_qp.harvest.harvest_controller import HarvestController
        from harvest_qp.robot.paths import tasks_dir
        from harvest_qp.runtime.runner import run_episode
        from harvest_qp.sim.paper_episode import build_robot, environment_capsules_for

        settings = load_settings(settings or tasks_dir() / "paper.yaml")
        robot = build_robot(settings, 0)
        controller = HarvestController(
            settings, environment=environment_capsules_for(robot, settings.qp.environment)
        )
        qp = controller.qp
        self.controller = controller
        self.tasks = (controller.camera_task, controller.gripper_task, controller.roll_task)
        self.collision = controller.collision
        # The obstacle map's cells are the limit's last capsules (none without the map).
        slots = controller.map_feed.slots if controller.map_feed is not None else 0
        self.first = self.collision.cap_p0.shape[0] - slots
        self.ticks: list[EpisodeTick] = []
        step = qp.step  # the loop's own call (HarvestController: ``qp.step(q, kinematics_updated=True)``)
        count = [0]

        def recording_step(q, *, kinematics_updated=False):
            record = count[0] % every == 0
            count[0] += 1
            if record:
                lim, first = self.collision, self.first
                tick = EpisodeTick(
                    q=np.array(q, dtype=float), previous_qdot=qp.previous_qdot.copy(),
                    references=tuple(task.reference.copy() for task in self.tasks),
                    obstacle_p0=lim.cap_p0[first:].copy(), obstacle_p1=lim.cap_p1[first:].copy(),
                    obstacle_radius=lim.cap_radius[first:].copy(),
                )
            result = step(q, kinematics_updated=kinematics_updated)
            if record:
                tick.qdot = result.qdot.copy()
                self.ticks.append(tick)
            return result

        qp.step = recording_step
        try:
            run_episode(robot, controller, duration=duration)
        finally:
            del qp.step  # the instance attribute: back to the class's method
        if not self.ticks:
            raise RuntimeError("no QP step was recorded: the loop no longer calls TaskController.step")
        self.qp = qp
        self.levels = sorted({task.level for task in qp.tasks})

    def load(self, tick: EpisodeTick) -> None:
        """Put the controller in the state of ``tick`` (outside any timed region)."""
        for task, reference in zip(self.tasks, tick.references):
            task.reference = reference
        lim, first = self.collision, self.first
        lim.cap_p0[first:] = tick.obstacle_p0
        lim.cap_p1[first:] = tick.obstacle_p1
        lim.cap_radius[first:] = tick.obstacle_radius
        self.qp.previous_qdot = tick.previous_qdot.copy()

    def replay(self, clock=time.thread_time) -> tuple[np.ndarray, float]:
        """Step every recorded problem once; per-step times [s] on ``clock`` and the largest
        difference [rad/s] between the replayed and the episode's commands."""
        times = np.empty(len(self.ticks))
        worst = 0.0
        step = self.qp.step
        update = self.qp.configuration.update
        for j, tick in enumerate(self.ticks):
            self.load(tick)
            # As in the loop: the tick's kinematics are computed before the QP step (for the
            # reference laws) and reused by it, so they are not part of the step's time.
            update(tick.q)
            t0 = clock()
            result = step(tick.q, kinematics_updated=True)
            times[j] = clock() - t0
            worst = max(worst, float(np.max(np.abs(result.qdot - tick.qdot))))
        return times, worst


def time_episode_problems(
    episode: EpisodeProblems, problem: peers.BenchProblem, rounds: int, clock=time.thread_time
) -> dict[str, float]:
    """Median CPU time [us] per step of the episode's problems and of ``harvest_qp_collision``, interleaved."""
    bench = HarvestQPStep(problem, True)
    n = len(episode.ticks)
    state = {"q": problem.q0.copy(), "t": 0.0}
    ep_rounds, bench_rounds, worst = [], [], 0.0
    for _ in range(rounds):
        times, diff = episode.replay(clock)
        worst = max(worst, diff)
        ep_rounds.append(float(np.median(times)))
        samples = np.empty(n)
        for j in range(n):
            t0 = clock()
            qdot = bench.step(state["q"], state["t"])
            samples[j] = clock() - t0
            state["q"] = state["q"] + qdot * problem.dt
            state["t"] += problem.dt
        bench_rounds.append(float(np.median(samples)))
    return {
        "harvest_qp_episode_us": 1e6 * float(np.median(ep_rounds)),
        "harvest_qp_collision_cpu_us": 1e6 * float(np.median(bench_rounds)),
        "episode_replay_max_diff": worst,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-n", type=int, default=2000, help="timed steps per contender (split over the rounds)")
    parser.add_argument("--rounds", type=int, default=5, help="round-robin rounds (robust to host speed drift)")
    parser.add_argument("--check", type=int, default=200, help="closed-loop check steps (0: none)")
    parser.add_argument("--peers", default="placo,mink,pink", help="comma-separated subset of peers")
    parser.add_argument("--differences", action="store_true", help="print how the peers' set-ups differ")
    parser.add_argument("--episode", type=float, default=20.0,
                        help="simulated seconds of the paper episode whose QP problems are replayed (0: skip)")
    parser.add_argument("--episode-every", type=int, default=10, help="record every N-th tick of that episode")
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
    if args.episode > 0:
        episode = EpisodeProblems(args.episode, args.episode_every)
        figures = time_episode_problems(episode, problem, max(args.rounds, 1))
        print(
            f"paper episode's own QP (levels {episode.levels}, {len(episode.ticks)} problems from "
            f"{args.episode:g} s, every {args.episode_every}th tick), thread CPU time, {args.rounds} interleaved "
            f"rounds: {figures['harvest_qp_episode_us']:.1f} us per step; harvest_qp_collision the same way: "
            f"{figures['harvest_qp_collision_cpu_us']:.1f} us; replayed commands equal the episode's to "
            f"{figures['episode_replay_max_diff']:.1e} rad/s"
        )
        results.update(figures)
    print(json.dumps({k: (None if v is None else round(v, 2)) for k, v in results.items()}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
