"""YAML task configurations: tasks and limits of a controller, loaded safely.

A configuration file looks like ``tasks/reach_targets.yaml``::

    dt: 0.002            # control period [s]
    solver: daqp         # daqp | proxsuite | qpsolvers:<name>
    tasks:
      - {type: frame_pose, frame: gripper, offset: [0.05, 0.0, -0.03], gain: 2.0}
      - {type: posture, weight: 1.0e-3}
      - {type: damping, weight: 1.0e-4}
    limits:
      - {type: joint_velocity, max_velocity: 1.5}
      - {type: collision, safety_distance: 0.01, influence_distance: 0.10}

Every key is checked: an unknown task type, option or a bad value raises
:class:`~harvest_qp.exceptions.ConfigError` naming the entry and what was expected.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import yaml

from harvest_qp.configuration import Configuration
from harvest_qp.exceptions import ConfigError, HarvestQPError
from harvest_qp.limits import (
    CapsuleGeometry,
    CollisionAvoidance,
    JointAccelerationLimit,
    JointPositionLimit,
    JointVelocityLimit,
    Limit,
)
from harvest_qp.tasks import DampingTask, FramePoseTask, FrameTwistTask, PostureTask, RelativeFrameTask, Task


@dataclass
class ControllerConfig:
    """Parsed configuration: the tasks and limits for one :class:`~harvest_qp.TaskController`."""

    tasks: list[Task]
    limits: list[Limit]
    dt: float = 0.002
    solver: str = "daqp"
    duration: float = 4.0
    extra: dict[str, Any] = field(default_factory=dict)


def _options(entry: dict, allowed: set[str], where: str) -> dict:
    unknown = set(entry) - allowed - {"type"}
    if unknown:
        raise ConfigError(f"{where}: unknown option(s) {sorted(unknown)}; allowed: {sorted(allowed)}")
    return {k: v for k, v in entry.items() if k != "type"}


def _rotation(spec: Any, where: str) -> np.ndarray:
    """A rotation from ``rpy: [r, p, y]`` [rad] or a 3x3 matrix."""
    if isinstance(spec, dict) and set(spec) == {"rpy"}:
        return pin.rpy.rpyToMatrix(np.asarray(spec["rpy"], dtype=float))
    arr = np.asarray(spec, dtype=float)
    if arr.shape != (3, 3):
        raise ConfigError(f"{where}: rotation must be {{rpy: [r, p, y]}} or a 3x3 matrix, got {spec!r}")
    return arr


def _build_task(entry: dict, configuration: Configuration, where: str) -> Task:
    kind = entry.get("type")
    common = {"weight", "level", "gain"}
    if kind == "frame_twist":
        opts = _options(entry, common | {"frame", "weight_frame", "reference"}, where)
        reference = opts.pop("reference", None)
        task = FrameTwistTask(opts.pop("frame"), **opts)
        if reference is not None:
            task.set_reference(reference)
        return task
    if kind == "frame_pose":
        opts = _options(entry, common | {"frame", "position", "rotation", "offset"}, where)
        frame = opts.pop("frame")
        pose = configuration.frame_pose(frame)
        position = np.asarray(opts.pop("position", pose.translation), dtype=float)
        position = position + np.asarray(opts.pop("offset", np.zeros(3)), dtype=float)
        rotation = _rotation(opts.pop("rotation"), where) if "rotation" in opts else pose.rotation
        task = FramePoseTask(frame, **opts)
        task.set_target(position, rotation)
        return task
    if kind == "relative_frame":
        opts = _options(entry, common | {"frame", "root"}, where)
        task = RelativeFrameTask(opts.pop("frame"), opts.pop("root"), **opts)
        p, R = task.relative_pose(configuration)
        task.set_target(p, R)  # hold the current relative pose
        return task
    if kind == "posture":
        opts = _options(entry, common | {"target"}, where)
        return PostureTask(np.asarray(opts.pop("target", configuration.q), dtype=float), **opts)
    if kind == "damping":
        opts = _options(entry, {"weight", "level"}, where)
        return DampingTask(configuration.nv, **opts)
    raise ConfigError(
        f"{where}: unknown task type {kind!r}; expected one of "
        "frame_twist, frame_pose, relative_frame, posture, damping"
    )


def _build_limit(entry: dict, configuration: Configuration, where: str, environment=()) -> Limit:
    kind = entry.get("type")
    if kind == "joint_position":
        return JointPositionLimit(configuration, **_options(entry, {"gain", "max_acceleration"}, where))
    if kind == "joint_velocity":
        return JointVelocityLimit(configuration, **_options(entry, {"max_velocity"}, where))
    if kind == "joint_acceleration":
        return JointAccelerationLimit(configuration, **_options(entry, {"max_acceleration"}, where))
    if kind == "collision":
        opts = _options(
            entry, {"safety_distance", "influence_distance", "gain", "max_pairs", "obstacle_spheres"}, where
        )
        spheres = opts.pop("obstacle_spheres", [])
        limit = CollisionAvoidance.dual_ur5e(configuration, environment=environment, **opts)
        if spheres:
            try:
                centers = np.array([s["center"] for s in spheres], dtype=float)
                radii = np.array([s["radius"] for s in spheres], dtype=float)
            except (KeyError, TypeError):
                raise ConfigError(f"{where}: obstacle_spheres entries need center: [x, y, z] and radius") from None
            limit.set_obstacle_spheres(centers, radii)
        return limit
    raise ConfigError(
        f"{where}: unknown limit type {kind!r}; expected one of "
        "joint_position, joint_velocity, joint_acceleration, collision"
    )


def build_controller_config(
    data: dict, configuration: Configuration, *, environment: Sequence[CapsuleGeometry] = ()
) -> ControllerConfig:
    """Tasks and limits from an already-parsed configuration mapping.

    ``environment``: world-fixed capsules (e.g. the scene's branch) for the collision limit.
    """
    if not isinstance(data, dict):
        raise ConfigError(f"a task configuration must be a mapping, got {type(data).__name__}")
    known = {"dt", "solver", "duration", "tasks", "limits", "description"}  # the rest goes to ``extra``
    tasks_spec = data.get("tasks")
    if not isinstance(tasks_spec, list) or not tasks_spec:
        raise ConfigError("'tasks' must be a non-empty list of task entries")
    tasks, limits = [], []
    def build_limit(entry, config, where):
        return _build_limit(entry, config, where, environment)

    for key, spec, build, out in (("tasks", tasks_spec, _build_task, tasks),
                                  ("limits", data.get("limits", []) or [], build_limit, limits)):
        if not isinstance(spec, list):
            raise ConfigError(f"'{key}' must be a list, got {type(spec).__name__}")
        for i, entry in enumerate(spec):
            where = f"{key}[{i}]"
            if not isinstance(entry, dict) or "type" not in entry:
                raise ConfigError(f"{where}: each entry must be a mapping with a 'type' key, got {entry!r}")
            try:
                item = build(entry, configuration, where)
                for attr in ("frame", "root"):  # fail now, with the valid names, not at the first step
                    if isinstance(getattr(item, attr, None), str):
                        configuration.frame_id(getattr(item, attr))
                out.append(item)
            except ConfigError:
                raise
            except (HarvestQPError, TypeError, ValueError, KeyError) as err:
                raise ConfigError(f"{where} ({entry.get('type')}): {err}") from err
    try:
        dt = float(data.get("dt", 0.002))
        duration = float(data.get("duration", 4.0))
    except (TypeError, ValueError):
        raise ConfigError("'dt' and 'duration' must be numbers [s]") from None
    if not (dt > 0 and np.isfinite(dt)) or not (duration > 0 and np.isfinite(duration)):
        raise ConfigError(f"'dt' and 'duration' must be > 0 [s], got dt={dt}, duration={duration}")
    extra = {k: v for k, v in data.items() if k not in known}
    return ControllerConfig(tasks, limits, dt=dt, solver=str(data.get("solver", "daqp")), duration=duration,
                            extra=extra)


def read_config_file(path: str | Path) -> dict:
    """Parse a YAML task configuration file safely (``yaml.safe_load``: no arbitrary objects)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"task configuration not found: {path}")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: invalid YAML: {err}") from err
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a task configuration must be a mapping, got {type(data).__name__}")
    return data


def load_controller_config(
    path: str | Path, configuration: Configuration, *, environment: Sequence[CapsuleGeometry] = ()
) -> ControllerConfig:
    """Read a YAML task configuration (``yaml.safe_load``: no arbitrary objects)."""
    data = read_config_file(path)
    try:
        return build_controller_config(data, configuration, environment=environment)
    except ConfigError as err:
        raise ConfigError(f"{path}: {err}") from err
