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

Every key is checked against the schema :class:`harvest_qp.config.TaskConfig` (pydantic):
an unknown task type, option or a bad value raises :class:`~harvest_qp.exceptions.ConfigError`
with one line naming the file, the key path, the bad value and what was expected. A task may
also be a user's own :class:`~harvest_qp.tasks.Task` subclass, ``type: my_package.tasks:GazeTask``
with ``params:`` checked against its signature (see :mod:`harvest_qp.config.task_schema`).
"""

from __future__ import annotations

import inspect
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
from pydantic_core import PydanticCustomError

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
    return {k: v for k, v in entry.items() if k != "type" and v is not None}


def _rotation(spec: Any, where: str) -> np.ndarray:
    """A rotation from ``rpy: [r, p, y]`` [rad] or a 3x3 matrix."""
    if isinstance(spec, dict) and set(spec) == {"rpy"}:
        return pin.rpy.rpyToMatrix(np.asarray(spec["rpy"], dtype=float))
    arr = np.asarray(spec, dtype=float)
    if arr.shape != (3, 3):
        raise ConfigError(f"{where}: rotation must be {{rpy: [r, p, y]}} or a 3x3 matrix, got {spec!r}")
    return arr


def build_user_task(entry: dict, configuration: Configuration, where: str) -> Task:
    """A user's Task subclass from a validated entry ``{type: 'module:Class', params, level, weight, gain}``.

    The constructor gets the checked ``params`` (and ``configuration=`` when it takes one);
    ``level``, ``weight`` and ``gain``, when given, go through the Task's checked setters.
    """
    from harvest_qp.config.task_schema import resolve_task_class, validate_user_params

    task_class = resolve_task_class(entry["type"])
    try:
        params = validate_user_params(task_class, dict(entry.get("params") or {}))
    except PydanticCustomError as err:  # already one line
        raise ConfigError(f"{where}: {err.message()}") from None
    if "configuration" in inspect.signature(task_class.__init__).parameters:
        params["configuration"] = configuration
    try:
        task = task_class(**params)
        for attr in ("level", "weight", "gain"):
            if entry.get(attr) is not None:
                setattr(task, attr, entry[attr])
    except HarvestQPError as err:
        raise ConfigError(f"{where} ({entry['type']}): {err}") from None
    except Exception as err:  # user code: name it, keep one line
        raise ConfigError(f"{where} ({entry['type']}): the constructor raised {type(err).__name__}: {err}") from None
    if not isinstance(task, Task):
        raise ConfigError(f"{where}: {entry['type']} built a {type(task).__name__}, not a harvest_qp Task")
    return task


def _build_task(entry: dict, configuration: Configuration, where: str) -> Task:
    kind = entry.get("type")
    common = {"weight", "level", "gain"}
    if isinstance(kind, str) and ":" in kind:
        return build_user_task(entry, configuration, where)
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
        "frame_twist, frame_pose, relative_frame, posture, damping, or 'module.path:ClassName'"
    )


def _built(build, entry: dict, configuration: Configuration, where: str):
    """``build(entry, configuration, where)`` with frame names checked now and errors as ConfigError."""
    try:
        item = build(entry, configuration, where)
        for attr in ("frame", "root"):  # fail now, with the valid names, not at the first step
            if isinstance(getattr(item, attr, None), str):
                configuration.frame_id(getattr(item, attr))
        return item
    except ConfigError:
        raise
    except (HarvestQPError, TypeError, ValueError, KeyError) as err:
        raise ConfigError(f"{where} ({entry.get('type')}): {' '.join(str(err).split())}") from None


def build_tasks(entries: Sequence[dict], configuration: Configuration, *, where: str = "tasks") -> list[Task]:
    """Tasks from validated task entries (built-in or ``module:Class``), e.g. the episode's ``qp.extra_tasks``."""
    return [_built(_build_task, dict(e), configuration, f"{where}[{i}]") for i, e in enumerate(entries)]


def build_limit(entry: dict, configuration: Configuration, where: str, environment=()) -> Limit:
    """One limit from a validated limit entry (``{type: joint_velocity, ...}``); ``where`` names it in errors."""
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
    data: dict, configuration: Configuration, *, environment: Sequence[CapsuleGeometry] = (),
    source: str = "task configuration", base_dir: str | Path | None = None,
) -> ControllerConfig:
    """Tasks and limits from a configuration mapping (checked against :class:`harvest_qp.config.TaskConfig`).

    ``environment``: world-fixed capsules (e.g. the scene's branch) for the collision limit.
    """
    from harvest_qp.config.loading import validate_data

    checked = validate_data(data, kind="tasks", source=source, base_dir=base_dir).model_dump()
    return controller_config_from_checked(checked, configuration, environment)


def build_limits(
    entries: Sequence[dict], configuration: Configuration, *, environment: Sequence[CapsuleGeometry] = (),
    where: str = "limits",
) -> list[Limit]:
    """Limits from validated limit entries (``limits`` of a task config, ``qp.limits`` of an episode)."""
    def build(entry, config, at):
        return build_limit(entry, config, at, environment)

    return [_built(build, dict(e), configuration, f"{where}[{i}]") for i, e in enumerate(entries)]


def controller_config_from_checked(
    checked: dict, configuration: Configuration, environment: Sequence[CapsuleGeometry] = ()
) -> ControllerConfig:
    """A :class:`ControllerConfig` from an already validated task configuration (``TaskConfig.model_dump()``)."""
    tasks = build_tasks(checked["tasks"], configuration)
    limits = build_limits(checked["limits"], configuration, environment=environment)
    extra = {k: checked[k] for k in ("viewpoint", "environment", "description")}
    return ControllerConfig(tasks, limits, dt=checked["dt"], solver=checked["solver"], duration=checked["duration"],
                            extra=extra)


def read_config_file(path: str | Path) -> dict:
    """A QP task configuration file: read safely (``yaml.safe_load``), ``extends`` followed, checked, defaulted."""
    from harvest_qp.config.loading import load_config

    return load_config(path, kind="tasks").model_dump()


def load_controller_config(
    path: str | Path, configuration: Configuration, *, environment: Sequence[CapsuleGeometry] = ()
) -> ControllerConfig:
    """Read a YAML task configuration and build its tasks and limits on ``configuration``.

    Raises:
        ConfigError: one line naming the file, the key path, the bad value and what was expected.
    """
    checked = read_config_file(path)
    try:
        return controller_config_from_checked(checked, configuration, environment)
    except ConfigError as err:
        raise ConfigError(f"{path}: {err}") from None
