"""``harvest-qp run CONFIG --robot ur ...``: the paper episode on the real cell, and its dry run.

The same :class:`~harvest_qp.harvest.HarvestController` and the same runner
(:func:`harvest_qp.runtime.runner.run_episode`) as in the lab drive :class:`DualUR5eRobot`; the log
(``episode.npz``), the metrics that need no ground truth (``metrics.json``) and the figures are
written as in the lab. The robot is closed (``speedStop`` + ``stopScript`` on both arms) on every
exit path, and SIGTERM is handled as Ctrl-C.
"""

from __future__ import annotations

import json
import math
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from harvest_qp.config import EpisodeConfig
from harvest_qp.exceptions import ConfigError, HarvestQPError
from harvest_qp.real.calibration import Calibration, load_calibration
from harvest_qp.real.cell import CellConfig, load_cell
from harvest_qp.real.errors import CalibrationError
from harvest_qp.runtime.interface import ROBOT, STEM

__all__ = ["run_real_episode", "real_metrics", "dry_run_report", "open_real_robot", "run_real", "warm_up"]


def _check_settings(settings: EpisodeConfig) -> None:
    if settings.qp.environment:
        raise ConfigError(f"qp.environment names lab geoms {settings.qp.environment}; the real cell has no "
                          "scene model: set qp.environment to []")


def real_metrics(log: dict, controller, settings: EpisodeConfig, *, mapper: str,
                 realtime_factor: float) -> dict[str, Any]:
    """The episode's metrics that need no ground truth (:func:`~harvest_qp.harvest.metrics.controller_metrics`,
    the lab's names) and the real cell's own: why the robot stopped, the frames received, the closest
    robot-robot / robot-stand capsule distance."""
    from harvest_qp.harvest.metrics import controller_metrics, finite_or_none, min_capsule_distance

    own, own_checks = controller_metrics(log, controller, settings, mapper=mapper, realtime_factor=realtime_factor)
    metrics: dict[str, Any] = {
        "robot": "ur",
        **own,
        "stop_reason": own["episode_error"],
        "min_collision_distance": finite_or_none(min_capsule_distance(log["q"], [])),  # robot-robot and stand only
        "camera_frames": int(len(log["frame_time"])),
    }
    # pre-cut reached and the episode completed (no robot stop) are among the controller's own checks
    metrics["criteria"] = {k: bool(v) for k, v in own_checks.items()}
    metrics["success"] = bool(all(own_checks.values()))
    return metrics



def warm_up(settings: EpisodeConfig, *, mapper: str | None = None, seed: int = 0,
            duration: float = 30.0) -> dict[str, Any]:
    """Run the lab's paper episode on ``settings`` with ``mapper`` (headless, no figures, discarded) so
    that every compiled kernel the controller calls is loaded in this process before the arms move.

    Returns ``{"wall_time": [s], "phase_reached": ...}``: a lab episode that did not reach pre-cut
    (within ``duration`` [s] of simulated time, whatever the settings' own ``episode.duration``)
    has left the later phases' first calls to the real episode.

    numba loads a kernel from its on-disk cache at the kernel's first call in each process
    (measured: 50-170 ms for the stem fit's or the grasp target's kernels on a warm cache, 8 s on a
    cold one), and the first calls come mid-episode: the first stem fit, the switch. Inside the
    control loop, with the arms moving, a cycle that long stops them (``watchdog.max_cycle_periods``,
    20 ms). The lab episode (approach, switch, stretch, pre-cut) makes those first calls here instead.
    The QP backends a failed step falls back on are imported and solve once too (proxsuite's import
    alone takes ~140 ms, at whichever tick daqp and quadprog first fail).
    """
    import tempfile

    from harvest_qp.backends import make_backend
    from harvest_qp.exceptions import SolverNotAvailableError
    from harvest_qp.sim.paper_episode import run_paper_episode
    from harvest_qp.solver import DEFAULT_FALLBACK_BACKENDS, QPProblem

    wall0 = time.perf_counter()
    # ends 1 s after pre-cut (the stretch's kernels have run by then), whatever the settings say
    lab = settings.model_copy(update={"episode": settings.episode.model_copy(update={"end_after_precut": 1.0})})
    with tempfile.TemporaryDirectory(prefix="harvest_qp_warm_up_") as out:
        report = run_paper_episode(lab, seed=seed, mapper=mapper, duration=duration, out_dir=out, figures=False)
    n = 12
    problem = QPProblem(H=np.eye(n), f=-np.ones(n), lower=-np.ones(n), upper=np.ones(n), A=np.zeros((0, n)),
                        b=np.zeros(0), G=np.eye(1, n), h=np.full(1, 0.5))
    for name in dict.fromkeys([settings.qp.solver, settings.qp.backup_solver, *DEFAULT_FALLBACK_BACKENDS]):
        if name is None:
            continue
        try:
            make_backend(name).solve(problem)
        except SolverNotAvailableError:  # not installed: the solver skips it at run time too
            continue
    return {"wall_time": time.perf_counter() - wall0, "phase_reached": report.metrics["phase_reached"]}


def run_real_episode(settings: EpisodeConfig, robot, *, mapper: str | None = None, duration: float | None = None,
                     out_dir: str | Path = "runs/real", config_name: str = "paper", figures: bool = True,
                     metadata: dict | None = None) -> dict[str, Any]:
    """Run the paper episode on ``robot`` (any RobotInterface without ground truth); write the
    log, ``metrics.json`` and the figures to ``out_dir``; return the metrics.

    A robot with a ``hand_eye`` (:class:`~harvest_qp.real.ur_rtde_robot.DualUR5eRobot`: the calibrated
    camera in the flange, the frame its clouds are expressed with) hands it to the controller, whose
    camera task and reference laws then use the same camera frame."""
    from harvest_qp.harvest.harvest_controller import HarvestController, Phase
    from harvest_qp.runtime.runner import run_episode, write_npz

    _check_settings(settings)
    mapper = mapper or settings.mapper.kind
    duration = float(duration if duration is not None else settings.episode.duration)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    controller = HarvestController(settings, environment=(), mapper=mapper,
                                   camera_in_flange=getattr(robot, "hand_eye", None))
    wall0 = time.perf_counter()
    result = run_episode(
        robot, controller, duration=duration, log_timing=True,
        log_clouds=settings.episode.log_cloud_every, cloud_max_points=settings.episode.log_cloud_points,
        metadata={"config": config_name, "mapper": mapper, "robot": "ur",
                  "phase_names": ",".join(p.name.lower() for p in Phase), **(metadata or {})},
    )
    wall = time.perf_counter() - wall0
    log = dict(result.log)
    write_npz(out_dir / "episode.npz", log)
    metrics = real_metrics(log, controller, settings, mapper=mapper,
                           realtime_factor=result.sim_time / wall if wall > 0 else math.inf)
    metrics["out_dir"] = str(out_dir)
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2, sort_keys=True) + "\n")
    if figures:
        from harvest_qp.harvest.figures import write_figures

        write_figures(log, controller, settings, out_dir, metrics)
    return metrics


def dry_run_report(robot, calibration: Calibration | None, calibration_path: Path | None,
                   cloud_timeout: float = 3.0) -> dict[str, Any]:
    """Read both arms and one camera frame; move nothing. Returns what ``--dry-run`` prints."""
    q, force = robot.joint_positions(), robot.wrist_force()
    report: dict[str, Any] = {
        "camera arm joints [rad]": np.round(q[:6], 4).tolist(),
        "grasping arm joints [rad]": np.round(q[6:], 4).tolist(),
        "joint speeds max [rad/s]": float(np.abs(robot.joint_velocities()).max()),
        "wrist force, world, untared [N]": np.round(force, 3).tolist(),
        "calibration": str(calibration_path) if calibration_path else "none (the robot description's camera mount)",
    }
    if calibration is not None:
        he = calibration.hand_eye
        report["hand-eye translation [m]"] = np.round(he[:3, 3], 4).tolist()
        discrepancy = calibration.base_discrepancy()
        report["bases vs description [mm, deg]"] = (
            "not calibrated" if discrepancy is None else [round(1e3 * discrepancy[0], 2), round(discrepancy[1], 3)])
    cloud = None
    if getattr(robot, "camera", None) is not None:
        deadline = time.monotonic() + cloud_timeout
        while cloud is None and time.monotonic() < deadline:
            cloud = robot.camera_cloud()
            if cloud is None:
                time.sleep(0.01)
    if cloud is None:
        report["cloud"] = "no frame"
    else:
        depth = cloud.depth
        report["cloud"] = (f"{len(cloud)} points of {cloud.image_size[0]}x{cloud.image_size[1]}, "
                           f"{cloud.count(STEM)} stem, {cloud.count(ROBOT)} robot, depth "
                           f"{depth.min():.3f}..{depth.max():.3f} m (median {np.median(depth):.3f}), "
                           f"age {robot.time - cloud.timestamp:.3f} s")
        report["camera position, world [m]"] = np.round(cloud.camera_position, 4).tolist()
    return report


def open_real_robot(settings: EpisodeConfig, cell: CellConfig, calibration: Calibration | None, *, camera_arm: str,
                    grasp_arm: str, camera: str | None = "realsense", serial: str | None = None,
                    rtde: Any = None, camera_source: Any = None, clock: Callable[[], float] | None = None,
                    read_only: bool = False):
    """Connect both arms (and start the camera); the caller must ``close()`` the robot.

    ``read_only`` (the dry run): only the arms' receive interfaces, no control script started."""
    from harvest_qp.real.ur_rtde_robot import DualUR5eRobot

    source = camera_source
    if source is None and camera == "realsense":
        from harvest_qp.real.realsense import RealSenseSource, open_pipeline

        pipeline, scale = open_pipeline(cell.camera, serial)
        source = RealSenseSource(pipeline, depth_scale=scale, downsample=int(settings.camera.downsample),
                                 stem_range=float(settings.camera.stem_range), cell=cell.camera)
    kwargs = {"clock": clock} if clock is not None else {}
    try:
        return DualUR5eRobot(camera_arm, grasp_arm, cell=cell,
                             hand_eye=None if calibration is None else calibration.hand_eye, camera=source,
                             rtde=rtde, read_only=read_only, **kwargs)
    except BaseException:
        if source is not None:
            source.close()
        raise


def _load_calibration(cell: CellConfig) -> Calibration | None:
    if cell.calibration is None:
        return None
    return load_calibration(cell.calibration)


def run_real(config: Path, *, camera_arm: str, grasp_arm: str, camera: str | None = "realsense",
             serial: str | None = None, cell_path: Path | None = None, dry_run: bool = False,
             out: Path | None = None, duration: float | None = None, overrides: list[str] | None = None,
             mapper: str | None = None, figures: bool = True, rtde: Any = None, camera_source: Any = None,
             clock: Callable[[], float] | None = None, warmup: bool = True) -> dict[str, Any]:
    """What the command line runs for ``--robot ur``: the dry run's report or the episode's metrics.

    Before an episode (not a dry run) and before connecting, :func:`warm_up` runs the lab episode on
    the same settings (``warmup=False``: skipped, e.g. when this process already ran it)."""
    from harvest_qp.config.settings import load_settings

    if camera is None and camera_source is None and not dry_run:
        raise HarvestQPError("an episode needs the camera (camera 'none' only for a dry run): the arms would move "
                             "without perception")
    settings = load_settings(config, overrides or [])
    _check_settings(settings)
    cell = load_cell(cell_path)
    calibration = _load_calibration(cell)
    if calibration is None and camera is not None and not dry_run:
        raise CalibrationError("the cell file names no calibration file: run `harvest-qp calibrate solve` and set "
                               "`calibration:` in the cell file (the camera's hand-eye transform is needed)")
    discrepancy = None if calibration is None else calibration.base_discrepancy()
    if discrepancy is not None and not dry_run and (discrepancy[0] > cell.max_base_discrepancy[0]
                                                    or discrepancy[1] > cell.max_base_discrepancy[1]):
        raise CalibrationError(
            f"the calibrated grasping-arm base is {1e3 * discrepancy[0]:.1f} mm / {discrepancy[1]:.2f} deg from the "
            f"robot description's (limit {1e3 * cell.max_base_discrepancy[0]:.0f} mm / "
            f"{cell.max_base_discrepancy[1]:g} deg): update MOUNTS in harvest_qp/robot/description.py or re-calibrate")
    if warmup and not dry_run:
        print("harvest-qp: loading the controller's compiled kernels on the lab episode before the arms move "
              "(--no-warmup skips it)", file=sys.stderr)
        warm = warm_up(settings, mapper=mapper)
        print(f"harvest-qp: warm-up done in {warm['wall_time']:.1f} s (the lab episode reached "
              f"{warm['phase_reached']})", file=sys.stderr)
        if warm["phase_reached"] != "precut":
            print("harvest-qp: warning: the warm-up's lab episode did not reach pre-cut: the later phases' kernels "
                  "load on their first call in the real episode, where a long cycle stops the arms", file=sys.stderr)
    previous = signal.getsignal(signal.SIGTERM)

    def on_term(signum, frame):
        raise KeyboardInterrupt

    in_main = True
    try:
        signal.signal(signal.SIGTERM, on_term)
    except ValueError:  # not the main thread
        in_main = False
    robot = None
    try:
        robot = open_real_robot(settings, cell, calibration, camera_arm=camera_arm, grasp_arm=grasp_arm,
                                camera=camera, serial=serial, rtde=rtde, camera_source=camera_source, clock=clock,
                                read_only=dry_run)
        if dry_run:
            return dry_run_report(robot, calibration, cell.calibration)
        out = out if out is not None else Path("runs") / f"real-{Path(config).stem}-{time.strftime('%Y%m%d-%H%M%S')}"
        return run_real_episode(settings, robot, mapper=mapper, duration=duration, out_dir=out,
                                config_name=Path(config).stem, figures=figures,
                                metadata={"camera_arm": camera_arm, "grasp_arm": grasp_arm,
                                          "calibration": str(cell.calibration or "")})
    finally:
        if robot is not None:
            robot.close()  # speedStop + stopScript on both arms, whatever happened
        if in_main:
            signal.signal(signal.SIGTERM, previous)

