"""Command-line interface: ``harvest-qp run``, ``demo``, ``replay``, ``sweep``, ``check-config``, ``schema``.

``harvest-qp run tasks/paper.yaml`` runs the paper's experiment (Section ``sec:exper``) in
the MuJoCo lab and writes ``metrics.json``, the ``.npz`` log and the figures.

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
from harvest_qp.exceptions import ConfigError, HarvestQPError
from harvest_qp.limits import CollisionAvoidance
from harvest_qp.real.cli import add_calibrate_parser, add_run_options, calibrate_main, check_sim_run, run_ur
from harvest_qp.robot.paths import tasks_dir
from harvest_qp.sweep.cli import add_sweep_parser, sweep_main
from harvest_qp.task_controller import TaskController
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


def run_sim_demo(
    config_path: Path,
    *,
    duration: float | None = None,
    solver: str | None = None,
    seed: int = 0,
    camera: bool = True,
    log_path: Path | None = None,
) -> dict:
    """The main demo: the QP controller on the MuJoCo vine scene, headless; return a summary.

    The grasping arm holds the cluster (the paper's initial state); the camera arm
    reaches the viewpoint of the config's ``viewpoint`` entry around the stem.
    """
    from harvest_qp.config import build_controller_config, read_config_file
    from harvest_qp.runtime.runner import run_episode
    from harvest_qp.runtime.task_episode import QPEpisodeController, environment_capsules, stem_viewpoint
    from harvest_qp.sim import CameraConfig, SimRobot, VineSceneParams

    data = read_config_file(config_path)  # checked, defaults filled, extends followed
    robot = SimRobot(VineSceneParams(), seed=seed, camera=CameraConfig() if camera else None)
    environment = environment_capsules(robot.model, robot.data, data["environment"])
    configuration = Configuration.dual_ur5e(robot.joint_positions())
    config = build_controller_config(data, configuration, environment=environment, source=str(config_path))
    controller = TaskController(configuration, config.tasks, config.limits, dt=config.dt,
                                solver=solver or config.solver)
    stem = 0.5 * (robot.scene.stem_base + robot.scene.stem_end)
    view = data["viewpoint"]
    camera_task = next((t for t in config.tasks if isinstance(t, FramePoseTask) and t.frame == "camera"), None)
    if camera_task is not None:
        camera_task.set_target(*stem_viewpoint(stem, **view))
    collision = next((lim for lim in config.limits if isinstance(lim, CollisionAvoidance)), None)
    episode = QPEpisodeController(controller)
    duration = duration or config.duration
    result = run_episode(robot, episode, duration=duration, log_path=log_path, log_timing=True,
                         metadata={"config": str(config_path)})
    log = result.log
    statuses = Counter(str(s).split(":")[0] for s in log["status"])
    q = log["q"]
    min_distance = None
    if collision is not None:  # every 10th tick of the log, over every candidate pair
        distances = []
        for q_tick in q[::10]:
            configuration.update(q_tick)
            distances.append(collision.distances(configuration).min())
        min_distance = float(min(distances))
    configuration.update(q[-1])
    camera_position = configuration.frame_position("camera")
    z_axis = configuration.frame_rotation("camera")[:, 2]
    to_stem = stem - camera_position
    centring = float(np.degrees(np.arccos(np.clip(z_axis @ to_stem / np.linalg.norm(to_stem), -1, 1))))
    stem_points = log["stem_points"]
    return {
        "episode": result.status,
        "simulated [s]": float(result.sim_time),
        "real-time factor": float(result.realtime_factor),
        "solver": controller.solver.backend_name,
        "statuses": dict(statuses),
        "camera to viewpoint [m]": float(log["task_error/camera_position"][-1]),
        "camera to stem [m]": float(np.linalg.norm(to_stem)),
        "stem off optical axis [deg]": centring,
        "stem points seen first/last": f"{int(max(stem_points[0], 0))} / {int(max(stem_points[-1], 0))}",
        "gripper hold error [mm]": 1e3 * float(np.nanmax(log["task_error/gripper_position"])),
        "wrist force, untared [N]": float(np.linalg.norm(log["force"][-1])),
        "min collision distance [m]": min_distance,
        "max joint speed [rad/s]": float(np.abs(log["qdot_cmd"]).max()),
        "joints within limits": bool(
            np.all(q >= configuration.lower_limits) and np.all(q <= configuration.upper_limits)
        ),
        "median QP step [us]": 1e6 * float(np.median(log["controller_time"])),
        "log": str(result.log_path) if result.log_path else None,
    }


def run_paper(config: Path, *, seed: int = 0, out: Path | None = None, mapper: str | None = None,
              duration: float | None = None, overrides: list[str] | None = None, figures: bool = True,
              viewer: str = "none", realtime: bool = True, host: str = "127.0.0.1", port: int = 7000,
              progress: bool | None = None) -> dict:
    """``harvest-qp run``: one paper episode; returns its metrics (also written to ``out``).

    ``progress``: draw a line with the simulated time, the phase and the real-time factor on standard
    error (default: when standard error is a terminal).
    """
    from harvest_qp.config.settings import load_settings
    from harvest_qp.runtime.progress import ProgressController, wants_progress
    from harvest_qp.sim.paper_episode import run_paper_episode

    settings = load_settings(config, overrides or [])
    if duration is not None and not (np.isfinite(duration) and duration > 0):
        raise HarvestQPError(f"--duration must be a number of seconds > 0; got {duration}")
    if seed < 0:
        raise HarvestQPError(f"--seed must be an integer >= 0; got {seed}")
    live = None
    shown = None

    def wrap(robot, controller):
        # The progress line and the viewer only observe: they wrap the controller.
        nonlocal shown
        if progress if progress is not None else wants_progress():
            length = duration if duration is not None else settings.episode.duration
            controller = shown = ProgressController(controller, duration=length)
        return with_viewer(robot, controller) if viewer == "meshcat" else controller

    def with_viewer(robot, controller):
        # The viewer only observes: it wraps the controller, nothing in the loop imports it.
        nonlocal live
        from harvest_qp.viewer import LiveViewer, RealTimePacer, ViewedController, paper_episode_extras

        live = LiveViewer(vine=robot.model, host=host, port=port)  # prints the URL
        extras = paper_episode_extras(settings.reaching.radius,
                                      cell_resolution=settings.obstacle_map.resolution, controller=controller)
        return ViewedController(controller, live, extras=extras, pacer=RealTimePacer() if realtime else None)

    try:
        report = run_paper_episode(settings, seed=seed, mapper=mapper, duration=duration, out_dir=out,
                                   config_name=Path(config).stem, figures=figures,
                                   wrap_controller=wrap)
    finally:
        if shown is not None:
            shown.finish()
        if live is not None:
            live.close()  # draws the last tick, stops the worker and the server
    if live is not None and live.error is not None:
        # The viewer never raises into the control loop; it keeps its error for the user instead.
        print(f"harvest-qp: the live viewer stopped drawing: {live.error!r}", file=sys.stderr)
    report.metrics["out_dir"] = str(report.out_dir)
    return report.metrics


def replay_run(run_dir: Path, *, html: Path | None = None, fps: float = 30.0, host: str = "127.0.0.1",
               port: int = 7000) -> int:
    """``harvest-qp replay``: serve a saved episode with a time slider, or write one offline HTML file."""
    from harvest_qp.viewer import export_episode_html, replay, wait_for_interrupt

    if html is not None:
        path = export_episode_html(run_dir, html, fps=fps)
        print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB): open it in any browser, offline")
        return 0
    viewer = replay(run_dir, fps=fps, host=host, port=port)
    try:
        wait_for_interrupt(f"replaying {run_dir} at {viewer.url} (Open Controls > Animations); Ctrl-C to quit")
    finally:
        viewer.close()
    return 0


def check_config(path: Path, overrides: list[str] | None = None) -> str:
    """``harvest-qp check-config``: validate a file of either kind and build what it names; a one-line verdict.

    An episode file is checked against the schema and its ``qp.extra_tasks`` and ``qp.limits`` are
    built on the dual UR5e model; a QP task config's tasks and limits are built too (frame names,
    sizes and user task classes are checked by building them).

    Raises:
        ConfigError: one line naming the file, the key path, the bad value and what was expected.
    """
    from harvest_qp.config import EpisodeConfig, build_limits, build_tasks, controller_config_from_checked, load_config

    model = load_config(path, overrides or [])
    configuration = Configuration.dual_ur5e()
    data = model.model_dump()
    try:
        if isinstance(model, EpisodeConfig):
            extra = build_tasks(data["qp"]["extra_tasks"], configuration, where="qp.extra_tasks")
            build_limits(data["qp"]["limits"], configuration, where="qp.limits")
            return (f"{path}: episode configuration ({len(extra)} extra task(s), {len(data['qp']['limits'])} "
                    f"limits, mapper {data['mapper']['kind']}): OK")
        config = controller_config_from_checked(data, configuration)
    except ConfigError as err:
        raise ConfigError(f"{path}: {err}") from None
    return (f"{path}: QP task configuration, {len(config.tasks)} tasks, {len(config.limits)} limits, "
            f"dt={config.dt} s: OK")


def write_schema(out: Path | None, markdown: Path | None = None) -> int:
    """``harvest-qp schema``: the JSON Schema to ``out`` (or stdout), the config reference to ``markdown``."""
    import json

    from harvest_qp.config import config_reference_markdown, json_schema

    text = json.dumps(json_schema(), indent=2) + "\n"
    if out is None:
        sys.stdout.write(text)
    else:
        out.write_text(text, encoding="utf-8")
        print(f"wrote {out}", file=sys.stderr)
    if markdown is not None:
        markdown.write_text(config_reference_markdown(), encoding="utf-8")
        print(f"wrote {markdown}", file=sys.stderr)
    return 0


_RUN_SUMMARY = (
    "success", "phase_reached", "abort_reason", "t_bimanual_start", "final_distance_to_roi_center",
    "final_theta_deg", "visible_stem_points_start", "visible_stem_points_switch", "visible_stem_points_end",
    "final_position_error", "final_alignment_deg", "final_cutter_stem_angle_deg", "force_mean_last_1s",
    "force_max", "min_collision_distance", "contacts", "stem_torn", "qp_failures", "realtime_factor", "out_dir",
)


def _print_summary(title: str, summary: dict) -> None:
    print(title)
    for key, value in summary.items():
        text = f"{value:.4g}" if isinstance(value, float) else str(value)
        print(f"  {key:<32} {text}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="harvest-qp", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run the paper's experiment headless (tasks/paper.yaml) and write "
                         "metrics.json, the log and the figures")
    run.add_argument("config", type=Path, help="settings file, e.g. tasks/paper.yaml")
    run.add_argument("--seed", type=int, default=0, help="0: the default scene; N > 0: a randomised scene")
    run.add_argument("--out", type=Path, default=None, help="output folder (default runs/<config>-<seed>/)")
    run.add_argument("--mapper", choices=("qp", "pinv"), default=None,
                     help="QP (default) or the paper's pseudo-inverse on the same references")
    run.add_argument("--duration", type=float, default=None, help="episode length [s]")
    run.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                     help="override a setting, e.g. --set grasping.f_d=2.5 (repeatable)")
    run.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    run.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                     help="a progress line (simulated time, phase, real-time factor) on standard error "
                     "(default: when it is a terminal)")
    run.add_argument("--viewer", choices=("none", "meshcat"), default="none",
                     help="show the episode live in a browser (meshcat)")
    speed = run.add_mutually_exclusive_group()
    speed.add_argument("--realtime", dest="realtime", action="store_true", default=True,
                       help="with --viewer: pace the loop to wall-clock time (default)")
    speed.add_argument("--fast", dest="realtime", action="store_false",
                       help="with --viewer: run as fast as the loop goes")
    run.add_argument("--host", default="127.0.0.1",
                     help="viewer address (default 127.0.0.1: this machine only; 0.0.0.0 serves every interface)")
    run.add_argument("--port", type=int, default=7000, help="viewer web port (an error if it is taken)")
    add_run_options(run)
    replay = sub.add_parser("replay", help="replay a saved episode in the browser (meshcat, time slider)")
    replay.add_argument("run_dir", type=Path, help="run directory holding episode.npz, or a .npz file")
    replay.add_argument("--html", type=Path, default=None,
                        help="write one self-contained HTML file that plays offline instead of serving")
    replay.add_argument("--fps", type=float, default=30.0, help="animation frames per second of episode time")
    replay.add_argument("--host", default="127.0.0.1", help="viewer address (default 127.0.0.1)")
    replay.add_argument("--port", type=int, default=7000, help="viewer web port (an error if it is taken)")
    add_sweep_parser(sub)
    add_calibrate_parser(sub)
    demo = sub.add_parser("demo", help="run the QP demo headless on the MuJoCo vine scene and print a summary")
    demo.add_argument("--config", type=Path, default=None,
                      help="YAML task config (default: tasks/sim_reach_stem.yaml; "
                      "tasks/reach_targets.yaml with --kinematic)")
    demo.add_argument("--duration", type=float, default=None, help="seconds to simulate")
    demo.add_argument("--solver", default=None, help="daqp | proxsuite | qpsolvers:<name>")
    demo.add_argument("--seed", type=int, default=0, help="sensor-noise seed of the simulation")
    demo.add_argument("--no-camera", action="store_true", help="simulate without the RGB-D camera (faster)")
    demo.add_argument("--log", type=Path, default=None, help="write the episode log (.npz) here")
    demo.add_argument("--kinematic", action="store_true",
                      help="ideal velocity tracking instead of MuJoCo (arms swap sides; no vine)")
    check = sub.add_parser("check-config", help="validate a YAML config (an episode's settings tree or a QP task "
                           "config): schema, extends, user task classes, frame names")
    check.add_argument("config", type=Path)
    check.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                       help="override a setting first, as `run` would (repeatable)")
    schema = sub.add_parser("schema", help="write the JSON Schema of the config files (editors complete and check "
                            "tasks/*.yaml with it)")
    schema.add_argument("--out", type=Path, default=None, help="file to write (default: print it)")
    schema.add_argument("--markdown", type=Path, default=None, help="also write the config reference (markdown)")
    args = parser.parse_args(argv)
    try:
        if args.command == "run" and args.robot == "ur":
            return run_ur(args)
        if args.command == "run":
            check_sim_run(args)
        if args.command == "calibrate":
            return calibrate_main(args)
        if args.command == "run":
            metrics = run_paper(args.config, seed=args.seed, out=args.out, mapper=args.mapper,
                                duration=args.duration, overrides=args.overrides, figures=not args.no_figures,
                                viewer=args.viewer, realtime=args.realtime, host=args.host, port=args.port,
                                progress=args.progress)
            _print_summary(f"harvest_qp paper episode ({args.config.name}, seed {args.seed}, "
                           f"{metrics['mapper']})", {k: metrics.get(k) for k in _RUN_SUMMARY})
            if metrics.get("episode_error"):
                print(f"  the episode stopped early ({metrics['episode_status']}): {metrics['episode_error']}")
            if not metrics["success"]:
                failed = [k for k, ok in metrics["criteria"].items() if not ok]
                print(f"  failed criteria: {', '.join(failed)}")
            return 0 if metrics["success"] else 1
        if args.command == "replay":
            return replay_run(args.run_dir, html=args.html, fps=args.fps, host=args.host, port=args.port)
        if args.command == "sweep":
            return sweep_main(args)
        if args.command == "demo" and args.kinematic:
            path = args.config or tasks_dir() / "reach_targets.yaml"
            summary = run_reach_demo(path, duration=args.duration, solver=args.solver)
            _print_summary(f"harvest_qp reach demo ({path.name}), dual UR5e, kinematic, headless", summary)
            ok = summary["joints within limits"] and summary["statuses"].get("fallback", 0) == 0
            return 0 if ok else 1
        if args.command == "demo":
            path = args.config or tasks_dir() / "sim_reach_stem.yaml"
            summary = run_sim_demo(path, duration=args.duration, solver=args.solver, seed=args.seed,
                                   camera=not args.no_camera, log_path=args.log)
            _print_summary(f"harvest_qp demo ({path.name}), dual UR5e in the MuJoCo vine scene, headless", summary)
            ok = (summary["episode"] == "completed" and summary["joints within limits"]
                  and summary["statuses"].get("fallback", 0) == 0)
            return 0 if ok else 1
        if args.command == "check-config":
            print(check_config(args.config, args.overrides))
            return 0
        if args.command == "schema":
            return write_schema(args.out, args.markdown)
    except HarvestQPError as err:
        print(f"harvest-qp: error: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        # Ctrl-C: the viewer and the workers have already been closed by their own finally
        # blocks; a traceback here would only hide that the stop was clean.
        print(f"harvest-qp: {args.command} interrupted (Ctrl-C)", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
