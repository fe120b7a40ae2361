"""One paper episode end to end: scene, robot, :class:`HarvestController`, runner, metrics, figures.

This is what ``harvest-qp run CONFIG`` executes (:func:`run_paper_episode`). The ground truth
that the metrics need (true stem base and end, stem tension, contacts) is logged by the
runner as ``truth/<name>`` next to the controller's own log and is never shown to the
controller.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from harvest_qp.config import EpisodeConfig
from harvest_qp.exceptions import ConfigError, InvalidInputError
from harvest_qp.harvest.environment import environment_capsules_for
from harvest_qp.harvest.harvest_controller import HarvestController
from harvest_qp.harvest.metrics import compute_metrics
from harvest_qp.harvest.phases import Phase
from harvest_qp.runtime.interface import ROBOT
from harvest_qp.runtime.runner import EpisodeResult, run_episode

__all__ = ["build_robot", "run_paper_episode", "EpisodeReport", "episode_ground_truth", "environment_capsules_for"]


@dataclasses.dataclass
class EpisodeReport:
    """What :func:`run_paper_episode` produced."""

    metrics: dict[str, Any]
    out_dir: Path
    log_path: Path
    figures: list[Path]
    result: EpisodeResult
    controller: HarvestController


def scene_params(settings: EpisodeConfig, seed: int):
    """The vine scene of an episode: the default scene for seed 0, a sampled one otherwise."""
    from harvest_qp.sim import VineSceneParams

    overrides = dict(settings.scene.params)
    names = {f.name for f in dataclasses.fields(VineSceneParams)}
    unknown = sorted(set(overrides) - names)
    if unknown:
        raise ConfigError(f"scene.params: unknown key(s) {unknown}; expected VineSceneParams fields: {sorted(names)}")
    try:
        if seed > 0 and settings.scene.randomize:
            return VineSceneParams.sample(seed, **overrides)
        overrides.setdefault("seed", seed)
        return VineSceneParams(**overrides)
    except (InvalidInputError, TypeError) as err:
        raise ConfigError(f"scene.params: {err}") from None


def build_robot(settings: EpisodeConfig, seed: int):
    """A :class:`~harvest_qp.sim.SimRobot` for the settings' camera, force sensor and scene."""
    from harvest_qp.sim import CameraConfig, ForceSensorConfig, SimRobot
    from harvest_qp.sim.robot import SensorFaults

    camera = settings.camera.model_dump(exclude={"frame_loss"})
    force = settings.force_sensor.model_dump()
    try:
        return SimRobot(scene_params(settings, seed), seed=seed, camera=CameraConfig(**camera),
                        force=ForceSensorConfig(**force),
                        faults=SensorFaults(frame_loss=float(settings.camera.frame_loss)))
    except InvalidInputError as err:
        raise ConfigError(f"camera/force_sensor settings: {err}") from None


def episode_ground_truth(robot) -> callable:
    """Per-tick ground truth for the metrics: the robot's own plus stem end and robot contacts."""
    model, data = robot.model, robot.data
    stem_end = model.site("stem_end").id
    labels = robot.scene.geom_labels
    base = getattr(robot, "ground_truth", dict)

    # Whether the robot counts its contacts itself is fixed: look once, not every tick.
    counts_contacts = any(key.startswith("contacts_") for key in base())
    # SimRobot.ground_truth builds a new dict per call: it can be extended in place (a
    # robot's own method might return a dict it keeps, so any other one is copied).
    from harvest_qp.sim.robot import uses_own_ground_truth

    fresh = uses_own_ground_truth(robot)
    stem_end_position = data.site_xpos[stem_end]  # a live view of the site's position

    def truth() -> dict[str, Any]:
        out = base() if fresh else dict(base())
        out["stem_end"] = stem_end_position.copy()
        if not counts_contacts:
            count = 0
            for i in range(data.ncon):
                c = data.contact[i]
                if labels[c.geom1] == ROBOT or labels[c.geom2] == ROBOT:
                    count += 1
            out["robot_contacts"] = count
        return out

    return truth


def run_paper_episode(
    settings: EpisodeConfig,
    *,
    seed: int = 0,
    mapper: str | None = None,
    duration: float | None = None,
    out_dir: str | Path | None = None,
    config_name: str = "paper",
    figures: bool = True,
    wrap_controller: Callable[[Any, Any], Any] | None = None,
) -> EpisodeReport:
    """Run one episode of the paper's experiment and write metrics.json, the log and the figures.

    Args:
        settings: checked settings (:func:`harvest_qp.config.settings.load_settings`).
        seed: 0 = the default scene; N > 0 = ``VineSceneParams.sample(N)`` (and the sensor
            noise seed).
        mapper: ``"qp"`` or ``"pinv"`` (default: the settings' ``mapper.kind``).
        duration: episode length [s] (default: ``episode.duration``).
        out_dir: output folder (default ``runs/<config>-<seed>``, ``-pinv`` appended for pinv).
        figures: write the PNG figures.
        wrap_controller: ``(robot, controller) -> controller`` applied before the episode
            runs, e.g. a live viewer that observes each tick (``harvest_qp.viewer``); the
            wrapped object must keep the runner's reset/step protocol.
    """
    mapper = mapper or settings.mapper.kind
    duration = float(duration if duration is not None else settings.episode.duration)
    if out_dir is None:
        out_dir = Path("runs") / f"{config_name}-{seed}{'-pinv' if mapper == 'pinv' else ''}"
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    robot = build_robot(settings, seed)
    environment = environment_capsules_for(robot, settings.qp.environment)
    controller = HarvestController(settings, environment=environment, mapper=mapper)
    episode_controller = controller if wrap_controller is None else wrap_controller(robot, controller)
    wall0 = time.perf_counter()
    result = run_episode(
        robot, episode_controller, duration=duration, log_path=None, log_timing=True,
        # thinned clouds for the replay viewer and its HTML export (not used by any metric)
        log_clouds=settings.episode.log_cloud_every, cloud_max_points=settings.episode.log_cloud_points,
        metadata={"config": config_name, "mapper": mapper, "phase_names": ",".join(p.name.lower() for p in Phase),
                  # the replay viewer rebuilds the vine from the scene's seed (0 = the default scene)
                  **({"scene_sample_seed": seed} if seed > 0 else {})},
        ground_truth=episode_ground_truth(robot),
    )
    wall = time.perf_counter() - wall0
    metrics = compute_metrics(result.log, robot, controller, settings, mapper=mapper, seed=seed,
                              realtime_factor=result.sim_time / wall if wall > 0 else float("inf"))
    log = dict(result.log)
    from harvest_qp.runtime.runner import write_npz

    log_path = write_npz(out_dir / "episode.npz", log)
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2, sort_keys=True) + "\n")
    paths: list[Path] = []
    if figures:
        from harvest_qp.harvest.figures import write_figures

        paths = write_figures(log, controller, settings, out_dir, metrics)
    return EpisodeReport(metrics, out_dir, log_path, paths, result, controller)
