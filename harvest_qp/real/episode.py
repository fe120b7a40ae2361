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
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from harvest_qp.config import EpisodeConfig
from harvest_qp.exceptions import ConfigError, EpisodeError
from harvest_qp.real.calibration import Calibration, load_calibration
from harvest_qp.real.cell import CellConfig, load_cell
from harvest_qp.real.errors import CalibrationError
from harvest_qp.runtime.interface import ROBOT, STEM

__all__ = ["run_real_episode", "real_metrics", "dry_run_report", "open_real_robot", "run_real"]


def _check_settings(settings: EpisodeConfig) -> None:
    if settings.qp.environment:
        raise ConfigError(f"qp.environment names lab geoms {settings.qp.environment}; the real cell has no "
                          "scene model: set qp.environment to []")


def real_metrics(log: dict, controller, settings: EpisodeConfig, *, mapper: str,
                 realtime_factor: float) -> dict[str, Any]:
    """The episode's metrics that need no ground truth (the lab's names where they exist)."""
    from harvest_qp.harvest.harvest_controller import Phase
    from harvest_qp.harvest.metrics import min_capsule_distance

    t = log["t"]
    n = len(t)
    if n == 0 or "value/phase" not in log:
        lines = str(log.get("error", "")).strip().splitlines()
        raise EpisodeError(f"the episode ended with status {str(log.get('episode_status'))!r} before the controller "
                           f"logged its values: {lines[0] if lines else 'no error message'}")
    st, phases = controller.state, controller.phases
    f_d = float(settings.grasping.f_d)

    def finite(x: float) -> float | None:
        return float(x) if x is not None and math.isfinite(float(x)) else None

    frame_time, frame_stem = log["frame_time"], log["frame_stem_points"]
    start = int(frame_stem[0]) if len(frame_stem) else 0
    end = int(np.median(frame_stem[frame_time >= frame_time[-1] - 0.5])) if len(frame_stem) else 0
    at_switch = None
    if phases.t_switch is not None and len(frame_time):
        before = np.flatnonzero(frame_time <= phases.t_switch + 1e-9)
        at_switch = int(frame_stem[before[-1]]) if len(before) else None
    force_nc = log["value/force_nc"]
    last = t >= t[-1] - 1.0 + 1e-9
    force_mean = float(np.nanmean(force_nc[last])) if np.any(np.isfinite(force_nc[last])) else math.nan
    force_max = float(np.nanmax(force_nc)) if np.any(np.isfinite(force_nc)) else math.nan
    def last(key: str) -> float:
        """The last finite value of a per-tick series (the failing tick of an episode logs NaN)."""
        values = np.asarray(log[key], dtype=float)
        finite_values = values[np.isfinite(values)]
        return float(finite_values[-1]) if len(finite_values) else math.nan

    position_error = last("value/position_error")
    alignment = math.degrees(last("value/alignment"))
    reached = Phase(int(last("value/phase")))
    error = str(log.get("error", ""))

    metrics: dict[str, Any] = {
        "robot": "ur",
        "mapper": mapper,
        "episode_status": str(log["episode_status"]),
        "stop_reason": error.strip().splitlines()[0] if error.strip() else None,
        "duration": float(n * float(log["control_period"])),
        "phase_reached": "abort" if reached == Phase.ABORT else reached.name.lower(),
        "t_bimanual_start": finite(phases.t_switch) if phases.t_switch is not None else None,
        "t_precut": finite(phases.t_precut) if phases.t_precut is not None else None,
        "final_distance_to_estimated_roi_center": finite(last("value/roi_distance")),
        "final_theta_estimated_roi_deg": finite(math.degrees(last("value/theta"))),
        "visible_stem_points_start": start,
        "visible_stem_points_switch": at_switch,
        "visible_stem_points_end": end,
        "final_position_error": finite(position_error),
        "final_alignment_deg": finite(alignment),
        "force_mean_last_1s": finite(force_mean),
        "force_max": finite(force_max),
        "f_d": f_d,
        "min_collision_distance": finite(min_capsule_distance(log["q"], [])),  # robot-robot and stand only
        "peak_joint_speed": float(np.abs(log["qdot"]).max()),
        "qp_failures": int(phases.qp_failures),
        "qp_backup_solves": int(phases.backup_solves),
        "abort_reason": phases.abort_reason,
        "estimated_stem_length": finite(st.stem_length),
        "camera_frames": int(len(frame_time)),
        "realtime_factor": float(realtime_factor),
    }
    checks = {
        "precut_reached": phases.t_precut is not None,
        "unveiled": end >= 3 * max(start, 1),
        "force_settled": math.isfinite(force_mean) and abs(force_mean - f_d) <= 0.1 * f_d,
        "force_below_2fd": math.isfinite(force_max) and force_max <= 2.0 * f_d,
        "aligned": math.isfinite(alignment) and alignment < 5.0,
        "position_error_small": math.isfinite(position_error) and position_error < 0.005,
        "no_abort": phases.abort_reason is None,
        "no_robot_stop": metrics["episode_status"] == "completed",
    }
    metrics["criteria"] = {k: bool(v) for k, v in checks.items()}
    metrics["success"] = bool(all(checks.values()))
    return metrics


def run_real_episode(settings: EpisodeConfig, robot, *, mapper: str | None = None, duration: float | None = None,
                     out_dir: str | Path = "runs/real", config_name: str = "paper", figures: bool = True,
                     metadata: dict | None = None) -> dict[str, Any]:
    """Run the paper episode on ``robot`` (any RobotInterface without ground truth); write the
    log, ``metrics.json`` and the figures to ``out_dir``; return the metrics."""
    from harvest_qp.harvest.harvest_controller import HarvestController, Phase
    from harvest_qp.runtime.runner import run_episode, write_npz

    _check_settings(settings)
    mapper = mapper or settings.mapper.kind
    duration = float(duration if duration is not None else settings.episode.duration)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    controller = HarvestController(settings, environment=(), mapper=mapper)
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
        "calibration": str(calibration_path) if calibration_path else "none (identity hand-eye)",
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
                    rtde: Any = None, camera_source: Any = None, clock: Callable[[], float] | None = None):
    """Connect both arms (and start the camera); the caller must ``close()`` the robot."""
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
                             rtde=rtde, **kwargs)
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
             clock: Callable[[], float] | None = None) -> dict[str, Any]:
    """What the command line runs for ``--robot ur``: the dry run's report or the episode's metrics."""
    from harvest_qp.config.settings import load_settings

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
                                camera=camera, serial=serial, rtde=rtde, camera_source=camera_source, clock=clock)
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

