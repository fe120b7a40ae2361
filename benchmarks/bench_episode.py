"""Real-time factor of the paper episode (``harvest-qp run tasks/paper.yaml``) on one core.

Runs the paper's closed loop (:class:`harvest_qp.harvest.HarvestController` on the simulated
dual UR5e in the default vine scene, built exactly as :func:`harvest_qp.sim.paper_episode.run_paper_episode`
builds it, without figures) at the paper's 283x160 (848x480 downsampled by 3) and at the
full 848x480, after an untimed warm-up episode past the switch that loads the numba kernels. The process is
pinned to one CPU core and BLAS/numba to one thread.

Per-tick breakdown: timers are wrapped around the episode's parts (on the objects of this
run only; the library code is unchanged):

* ``camera``: the simulated RGB-D frame (ray casting + cloud), per frame;
* ``physics``: MuJoCo substeps, servos, wrist sensor, tear check, per tick;
* ``perception``: the controller's per-frame perception (stem split and fit, unveiling
  pairs, V_cu target), per frame, without the obstacle map;
* ``map_update``: the obstacle map's frame integration (ray clearing), per frame;
* ``references``: the reference laws per tick (V_cr, V_cu filter, V_g, feed-forward,
  switch and safety logic);
* ``map_feed``: the obstacle map's cells fed to the collision limit, per tick;
* ``qp``: the QP step (``TaskController.step`` as the loop calls it: tasks, limits, daqp; the
  kinematics are the loop's own update, in ``runner``), per tick;
* ``ground_truth``: the lab's ground truth logged per tick (stem tension, contacts, true
  robot-vine distance);
* ``logged_values``: the controller's per-tick values for the log (phase, p_r, V_c, ...,
  active collision pairs);
* ``runner``: the rest: the runner's observation, command checks and log arrays, and the
  controller's own glue (kinematics update, phase logic outside the reference laws).

The timers read the thread's CPU time (``--clock cpu``, the default: the breakdown stays
meaningful on a loaded machine) or the wall clock (``--clock wall``); the shares are of the
episode's total on that clock. The real-time factor is given both on the wall clock
(``rtf``) and on the process's CPU time (``rtf_cpu``: what the episode would reach alone on
the core; on a loaded machine the wall-clock figure is lower).

The QP step is reported three ways: its median inside the episode, the same step replayed
alone after the episode on the episode's own problems (the gap is the rest of the loop
evicting its data from the caches), and ``bench_qp.py``'s harvest_qp collision problem (a
one-level QP without map cells; the gap is the episode's two-level hierarchy and map rows).

Usage::

    python benchmarks/bench_episode.py [--duration 20] [--settings tasks/paper.yaml] [--set k=v ...]
                                       [--resolutions 283x160,848x480] [--clock cpu|wall] [--repeats 3]

The headline real-time factor comes from a separate run without any timer: the episode exactly
as ``harvest-qp run`` runs it (:func:`harvest_qp.sim.paper_episode.run_paper_episode`, figures off),
whose ``realtime_factor`` it reports: the median of ``--repeats`` such runs (default 3; the
machine's speed can swing within minutes, so one run says little); the timed run that gives the
breakdown is slower by its own timers (a wrapper and two clock reads around each timed call) and reports its own factor.

The last line printed is one JSON object with ``episode_rtf_283x160``, ``episode_rtf_848x480``
(wall clock, uninstrumented, median of the repeats; ``episode_rtf_min_*`` / ``episode_rtf_max_*``
their range), ``episode_rtf_cpu_*`` (CPU time), ``episode_tick_us_*``,
``episode_rtf_instrumented_*`` (the timed run), ``qp_tick_us_in_episode`` (median QP step at
283x160), ``qp_tick_us_replayed``, ``qp_tick_us_bench_qp``, ``perception_ms_283x160`` (median
per frame, perception plus map update, as the controller's own timer counts it) and the other
medians.
Timings on a shared machine are noisy: run it alone (check ``uptime``).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import functools  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

_REPO = Path(__file__).resolve().parents[1]
if str(_REPO) not in sys.path:
    sys.path.insert(0, str(_REPO))

from harvest_qp.config.settings import load_settings  # noqa: E402
from harvest_qp.harvest.harvest_controller import HarvestController  # noqa: E402
from harvest_qp.robot.paths import tasks_dir  # noqa: E402
from harvest_qp.runtime.runner import run_episode  # noqa: E402
from harvest_qp.sim.paper_episode import (  # noqa: E402
    build_robot,
    environment_capsules_for,
    episode_ground_truth,
    run_paper_episode,
)

SECTIONS = (
    "camera", "physics", "perception", "map_update", "references", "map_feed", "qp", "ground_truth", "logged_values",
)
_RESOLUTIONS = {"283x160": 3, "848x480": 1, "424x240": 2, "142x80": 6}


def _pin() -> str:
    if hasattr(os, "sched_setaffinity"):
        cpu = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpu})
        return f"pinned to CPU {cpu}"
    return "not pinned"


class _Timers:
    """Named lists of durations [s] on ``clock``; ``wrap`` times every call of a bound method."""

    def __init__(self, clock) -> None:
        self.clock = clock
        self.samples: dict[str, list[float]] = {name: [] for name in SECTIONS}
        self._open: list[tuple[str, float]] = []

    def wrap(self, obj, attribute: str, name: str, *, exclusive: bool = False) -> None:
        """Replace ``obj.attribute`` by a timed call; ``exclusive``: nested timed calls are subtracted."""
        inner = getattr(obj, attribute)
        store = self.samples[name]
        stack = self._open
        clock = self.clock

        @functools.wraps(inner)
        def timed(*args, **kwargs):
            stack.append((name, 0.0))
            t0 = clock()
            try:
                return inner(*args, **kwargs)
            finally:
                elapsed = clock() - t0
                _, nested = stack.pop()
                store.append(elapsed - nested if exclusive else elapsed)
                if stack:  # charge the enclosing timer's nested time
                    outer, n = stack[-1]
                    stack[-1] = (outer, n + elapsed)

        setattr(obj, attribute, timed)


def _controller_clock(controller, clock) -> None:
    """Make the controller's own timers (perception per frame, references per tick) use ``clock``."""
    import harvest_qp.harvest.harvest_controller as module

    class _Time:
        perf_counter = staticmethod(clock)

        def __getattr__(self, name):
            return getattr(time, name)

    module.time = _Time()


def time_episode(settings: dict, duration: float, *, clock=time.thread_time) -> dict:
    """One episode with timers (on ``clock``) around its parts; returns the breakdown."""
    robot = build_robot(settings, 0)
    controller = HarvestController(settings, environment=environment_capsules_for(robot, settings.qp.environment))
    _controller_clock(controller, clock)
    timers = _Timers(clock)
    # Simulation: robot.step = physics + (every 1/30 s) the camera frame.
    timers.wrap(robot, "step", "physics", exclusive=True)
    if robot._camera is not None:
        timers.wrap(robot._camera, "capture", "camera")
    timers.wrap(controller, "_perceive", "perception")
    if controller.obstacle_map is not None:
        timers.wrap(controller.obstacle_map, "update", "map_update")
    if controller.map_feed is not None:
        timers.wrap(controller.map_feed, "update", "map_feed")
    # The loop calls TaskController.step(q, kinematics_updated=True) (its own kinematics
    # update for the reference laws comes first and is counted in "runner").
    controller.qp.step_unwrapped = controller.qp.step
    timers.wrap(controller.qp, "step", "qp")
    for name in ("_log_values", "_active_pairs", "_log_row", "_active_pair_columns"):
        if hasattr(controller, name):
            timers.wrap(controller, name, "logged_values")
    controller.timing = {}
    truth = episode_ground_truth(robot)

    def timed_truth():
        t0 = clock()
        out = truth()
        timers.samples["ground_truth"].append(clock() - t0)
        return out

    cpu0, wall0, clock0 = time.process_time(), time.perf_counter(), clock()
    result = run_episode(robot, controller, duration=duration, log_timing=True, ground_truth=timed_truth)
    wall, cpu, elapsed = time.perf_counter() - wall0, time.process_time() - cpu0, clock() - clock0
    ticks = result.n_ticks
    s = {name: np.asarray(v, float) for name, v in timers.samples.items()}
    s["references"] = np.asarray(controller.timing.get("references", []), float)
    # The controller's own per-frame timer: perception + map update.
    frame_total = np.asarray(controller.timing.get("perception", []), float)
    total = {name: float(v.sum()) for name, v in s.items()}
    total["runner"] = elapsed - sum(total.values())
    per_tick_us = {name: 1e6 * t / ticks for name, t in total.items()}

    def med(name, scale):
        return scale * float(np.median(s[name])) if s[name].size else float("nan")

    qp_isolated = _qp_isolated(controller, result.log, clock)
    return {
        "qp_isolated_us_median": qp_isolated,
        "rtf": result.sim_time / wall,
        "rtf_cpu": result.sim_time / cpu,
        "sim_time": result.sim_time,
        "wall": wall,
        "cpu": cpu,
        "ticks": ticks,
        "frames": int(s["camera"].size),
        "phase": controller.phase.name.lower(),
        "camera_ms_median": med("camera", 1e3),
        "perception_ms_median": med("perception", 1e3),
        "map_update_ms_median": med("map_update", 1e3),
        "frame_ms_median": 1e3 * float(np.median(frame_total)) if frame_total.size else float("nan"),
        "frame_ms_p90": 1e3 * float(np.percentile(frame_total, 90)) if frame_total.size else float("nan"),
        "references_us_median": med("references", 1e6),
        "map_feed_us_median": med("map_feed", 1e6),
        "qp_us_median": med("qp", 1e6),
        "physics_us_median": med("physics", 1e6),
        "ground_truth_us_median": med("ground_truth", 1e6),
        "per_tick_us": per_tick_us,
        "share": {name: t / elapsed for name, t in total.items()},
        "elapsed": elapsed,
        "stem_points_last": int(result.log["stem_points"][-1]),
    }


def plain_episode(settings: dict, duration: float) -> dict:
    """The episode exactly as ``harvest-qp run`` runs it (no timers), without figures.

    Returns ``rtf``: the ``realtime_factor`` the run writes to ``metrics.json`` (simulated
    time over the wall-clock time of the episode loop), ``rtf_cpu``: the same over this
    thread's CPU time of the episode loop (read around the runner's call, nothing per tick),
    and the phase reached.
    """
    import tempfile

    import harvest_qp.sim.paper_episode as episode_module

    cpu: list[float] = []
    inner = episode_module.run_episode

    def counted(*args, **kwargs):
        t0 = time.thread_time()
        try:
            return inner(*args, **kwargs)
        finally:
            cpu.append(time.thread_time() - t0)

    episode_module.run_episode = counted
    try:
        with tempfile.TemporaryDirectory(prefix="bench_episode_") as out:
            report = run_paper_episode(settings, duration=duration, out_dir=out, figures=False)
    finally:
        episode_module.run_episode = inner
    ticks = report.result.n_ticks
    rtf = float(report.metrics["realtime_factor"])
    return {
        "rtf": rtf,
        "rtf_cpu": report.result.sim_time / cpu[0],
        "tick_us": 1e6 * report.result.sim_time / rtf / ticks,
        "tick_us_cpu": 1e6 * cpu[0] / ticks,
        "phase": report.controller.phase.name.lower(),
    }


def _median_run(runs: list[dict]) -> dict:
    """Each figure of :func:`plain_episode` as its median over ``runs`` (figure by figure),
    with the ``rtf``'s and ``rtf_cpu``'s smallest and largest as ``*_min`` / ``*_max``."""
    out = {key: float(np.median([r[key] for r in runs])) for key in ("rtf", "rtf_cpu", "tick_us", "tick_us_cpu")}
    for key in ("rtf", "rtf_cpu"):
        out[f"{key}_min"] = min(r[key] for r in runs)
        out[f"{key}_max"] = max(r[key] for r in runs)
    out["phase"] = runs[-1]["phase"]
    return out


def _qp_isolated(controller, log: dict, clock, n: int = 1000) -> float:
    """Median [us] of the episode's own QP step replayed in a tight loop, after the episode.

    The controller's :class:`~harvest_qp.TaskController` as the episode left it (same tasks,
    levels, limits and map cells) steps at ``n`` logged joint positions, each from the
    command logged the tick before: the same problems as in the episode, without the
    rest of the loop in between (caches stay warm).
    """
    qp = getattr(controller, "qp", None)
    if qp is None or getattr(qp, "step_unwrapped", None) is None:  # the pinv mapper
        return float("nan")
    step = qp.step_unwrapped
    q, qdot = log["q"], log["qdot_cmd"]
    ticks = np.unique(np.linspace(1, len(q) - 1, min(n, len(q) - 1)).astype(int))
    # As in the episode: the kinematics are updated first (untimed, as the loop's own
    # update is not in its "qp" section), then the step reuses them.
    for k in ticks[:20]:  # warm-up
        qp.previous_qdot = qdot[k - 1].copy()
        qp.configuration.update(q[k])
        step(q[k], kinematics_updated=True)
    times = np.empty(ticks.size)
    for j, k in enumerate(ticks):
        qp.previous_qdot = qdot[k - 1].copy()
        qp.configuration.update(q[k])
        t0 = clock()
        step(q[k], kinematics_updated=True)
        times[j] = clock() - t0
    return 1e6 * float(np.median(times))


def _bench_qp_figure(clock, n: int = 1000) -> float:
    """Median [us] of ``bench_qp.py``'s harvest_qp step with collision rows (its problem: one level)."""
    from benchmarks import peers
    from benchmarks.bench_qp import HarvestQPStep

    problem = peers.BenchProblem()
    stepper = HarvestQPStep(problem, True)
    q, t = problem.q0.copy(), 0.0
    times = np.empty(n)
    for k in range(n + 50):
        t0 = clock()
        qdot = stepper.step(q, t)
        if k >= 50:
            times[k - 50] = clock() - t0
        q, t = q + qdot * problem.dt, t + problem.dt
    return 1e6 * float(np.median(times))


def _report(name: str, r: dict) -> str:
    lines = [
        f"{name} with the breakdown's timers: real-time factor {r['rtf']:.2f} wall-clock, "
        f"{r['rtf_cpu']:.2f} on CPU time "
        f"({r['sim_time']:.1f} s simulated in {r['wall']:.1f} s wall, {r['cpu']:.1f} s CPU; {r['ticks']} ticks, "
        f"{r['frames']} frames; ended in {r['phase']})",
        f"  medians: camera {r['camera_ms_median']:.2f} ms/frame, perception {r['perception_ms_median']:.2f} ms/frame, "
        f"map update {r['map_update_ms_median']:.2f} ms/frame (perception+map {r['frame_ms_median']:.2f}, "
        f"p90 {r['frame_ms_p90']:.2f}); per tick: physics {r['physics_us_median']:.0f} us, references "
        f"{r['references_us_median']:.0f} us, map feed {r['map_feed_us_median']:.0f} us, "
        f"QP {r['qp_us_median']:.0f} us, "
        f"ground truth {r['ground_truth_us_median']:.0f} us",
        f"  {r['clock']} per tick (mean over the episode, frames spread over ticks) and share:",
    ]
    for key in (*SECTIONS, "runner"):
        lines.append(f"    {key:<20s} {r['per_tick_us'][key]:8.1f} us  {r['share'][key]:6.1%}")
    lines.append(f"    {'total':<20s} {1e6 * r['elapsed'] / r['ticks']:8.1f} us")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--duration", type=float, default=20.0, help="simulated seconds per resolution")
    parser.add_argument("--settings", type=Path, default=tasks_dir() / "paper.yaml")
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    parser.add_argument("--clock", choices=("cpu", "wall"), default="cpu",
                        help="clock of the breakdown: this thread's CPU time (robust on a loaded machine) or wall time")
    parser.add_argument("--resolutions", default="283x160,848x480", help=f"comma-separated, of {sorted(_RESOLUTIONS)}")
    parser.add_argument("--warmup", type=float, default=12.0,
                        help="simulated seconds of the untimed warm-up episode at the first resolution [s]: past the "
                             "switch (~8 s on the default scene), so every numba kernel of the episode is loaded or "
                             "compiled before the timing (a fresh clone compiles them once, ~35 s)")
    parser.add_argument("--repeats", type=int, default=3,
                        help="untimed episodes per resolution; the headline figures are their medians (>= 1)")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats: expected an integer >= 1, got {args.repeats}")
    print(_pin())
    print(f"load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    names = [n.strip() for n in args.resolutions.split(",") if n.strip()]
    for name in names:
        if name not in _RESOLUTIONS:
            parser.error(f"--resolutions: unknown {name!r}; expected some of {sorted(_RESOLUTIONS)}")
    clock = time.thread_time if args.clock == "cpu" else time.perf_counter
    # Warm-up: loads (or compiles) the numba kernels. Some run only from the switch on (the
    # stem fit at the switch, p_gd, the stretching phase's paths): a 0.1 s warm-up left their
    # compilation inside the timed episode (measured on a fresh worktree: perception 1,248 us
    # per tick instead of 76). The other resolutions only need their frame-size paths.
    for i, name in enumerate(names):
        settings = load_settings(args.settings, [*args.overrides, f"camera.downsample={_RESOLUTIONS[name]}"])
        time_episode(settings, args.warmup if i == 0 else 0.1)
    out = {}
    plain = {}
    for name in names:
        settings = load_settings(args.settings, [*args.overrides, f"camera.downsample={_RESOLUTIONS[name]}"])
        # The headline figure: the episode as the CLI runs it. The breakdown's timers (a
        # Python wrapper and two clock reads around each timed call, ~8 per tick) slow the
        # instrumented run down; its shares are what it is for.
        # Repeated, and the median run reported: this kind of machine's speed was measured
        # to swing by up to 2x within minutes with nothing else running (the same code at
        # 573 and 1,122 us per tick ten minutes apart), so one run says little.
        runs = []
        for i in range(args.repeats):
            runs.append(p := plain_episode(settings, args.duration))
            print(f"{name} run {i + 1}/{args.repeats}: real-time factor {p['rtf']:.2f} wall-clock as "
                  f"`harvest-qp run` measures it ({p['tick_us']:.0f} us per tick), {p['rtf_cpu']:.2f} on this "
                  f"thread's CPU time ({p['tick_us_cpu']:.0f} us per tick); ended in {p['phase']}", flush=True)
        plain[name] = p = _median_run(runs)
        if args.repeats > 1:
            print(f"{name}: median of {args.repeats} runs: real-time factor {p['rtf']:.2f} wall-clock "
                  f"(range {p['rtf_min']:.2f}-{p['rtf_max']:.2f}), {p['rtf_cpu']:.2f} CPU time "
                  f"(range {p['rtf_cpu_min']:.2f}-{p['rtf_cpu_max']:.2f})", flush=True)
        r = time_episode(settings, args.duration, clock=clock)
        r["clock"] = "thread CPU time" if args.clock == "cpu" else "wall-clock time"
        print(_report(name, r), flush=True)
        out[name] = r
    bench_qp_us = _bench_qp_figure(clock)
    first = out[names[0]]
    print(
        f"QP step at {names[0]}: {first['qp_us_median']:.0f} us in the episode, "
        f"{first['qp_isolated_us_median']:.0f} us "
        f"replayed alone on the episode's own problems, {bench_qp_us:.0f} us for bench_qp.py's problem "
        f"(harvest_qp_collision: one level, no map cells)"
    )
    print(f"load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    summary: dict[str, float | str] = {}
    for name, r in out.items():
        summary[f"episode_rtf_{name}"] = plain[name]["rtf"]
        summary[f"episode_rtf_cpu_{name}"] = plain[name]["rtf_cpu"]
        summary[f"episode_tick_us_{name}"] = plain[name]["tick_us"]
        summary[f"episode_tick_us_cpu_{name}"] = plain[name]["tick_us_cpu"]
        summary[f"episode_rtf_min_{name}"] = plain[name]["rtf_min"]
        summary[f"episode_rtf_max_{name}"] = plain[name]["rtf_max"]
        summary[f"episode_rtf_instrumented_{name}"] = r["rtf"]
        summary[f"perception_ms_{name}"] = r["frame_ms_median"]
        summary[f"camera_ms_{name}"] = r["camera_ms_median"]
        summary[f"map_update_ms_{name}"] = r["map_update_ms_median"]
    summary["qp_tick_us_in_episode"] = first["qp_us_median"]
    summary["qp_tick_us_replayed"] = first["qp_isolated_us_median"]
    summary["qp_tick_us_bench_qp"] = bench_qp_us
    summary["references_us"] = first["references_us_median"]
    summary["physics_us"] = first["physics_us_median"]
    summary["ground_truth_us"] = first["ground_truth_us_median"]
    summary["duration_s"] = args.duration
    summary["repeats"] = args.repeats
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
