"""QP tasks and limits as configuration entries, and QP-only task configurations.

A task entry is a mapping with a ``type``: one of the built-in tasks (``frame_twist``,
``frame_pose``, ``relative_frame``, ``posture``, ``damping``) or a user's own
:class:`~harvest_qp.tasks.Task` subclass named ``module.path:ClassName`` (imported from
``sys.path``, else from next to the config file) or ``file.py:ClassName`` (relative to the
config file). A user task's ``params`` are validated against the class's ``Params`` pydantic
model when it has one, else against its constructor's signature; ``level``, ``weight`` and
``gain`` are set on the built task through :class:`~harvest_qp.tasks.Task`'s checked setters.

Defaults of the built-in entries are read from the classes' own signatures (one place).
Note: a config naming ``module:Class`` imports that module (its top-level code runs), as a
Python ``import`` would; YAML itself is always read with ``yaml.safe_load``.
"""

# ruff: noqa: UP007 (unions built from tuples at run time, and Union[Annotated[...], ...] reads better here)
from __future__ import annotations

import hashlib
import importlib
import importlib.util
import inspect
import sys
import typing
from pathlib import Path
from typing import Annotated, Any, Literal, Union

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
    TypeAdapter,
    ValidationError,
    ValidationInfo,
    create_model,
    field_validator,
)
from pydantic_core import PydanticCustomError

from harvest_qp.config._types import (
    HardLevel,
    NonNegative,
    Positive,
    PositiveInt,
    Real,
    Section,
    Text,
    Vector3,
    Weights,
    Weights6,
    expect,
    suggest,
)
from harvest_qp.limits import CollisionAvoidance, JointAccelerationLimit, JointPositionLimit, JointVelocityLimit
from harvest_qp.tasks import DampingTask, FramePoseTask, FrameTwistTask, PostureTask, RelativeFrameTask, Task

__all__ = [
    "TaskEntry", "LimitEntry", "TaskConfig", "BUILT_IN_TASKS", "BUILT_IN_LIMITS", "resolve_task_class",
    "validate_user_params",
]


def _default(cls: type, name: str, method: str = "__init__") -> Any:
    """The default of ``cls.<method>``'s parameter ``name`` (so the class stays the one place)."""
    return inspect.signature(getattr(cls, method)).parameters[name].default


Name = expect(str, "a frame name (a string)", min_length=1)
Scalars = expect(Union[float, Annotated[list[float], Field(min_length=1)]], "a number or a list of numbers")
NonNegScalars = expect(
    Union[Annotated[float, Field(ge=0)], Annotated[list[Annotated[float, Field(ge=0)]], Field(min_length=1)]],
    "a number >= 0 or a list of 12 numbers >= 0 (one per joint)",
)


class _Entry(Section):
    """A list entry chosen by its ``type``."""


class FrameTwistEntry(_Entry):
    """Track a twist of a frame: ``J qdot = gain * V`` (the reference is set by code or ``reference``)."""

    type: Literal["frame_twist"]
    frame: Name = Field(description="frame name in the robot model (e.g. camera, gripper)")
    weight: Weights6 = Field(_default(FrameTwistTask, "weight"),
                             description="[1/(m/s)^2, 1/(rad/s)^2] a weight or 6 per-axis weights")
    weight_frame: expect(Literal["world", "local"], "one of: local, world") = Field(
        _default(FrameTwistTask, "weight_frame"), description="axes of the weights: world or local")
    level: HardLevel = Field(_default(FrameTwistTask, "level"), description="priority level (0: hard)")
    gain: NonNegative = Field(_default(FrameTwistTask, "gain"), description="scale on the reference (1: as given)")
    reference: expect(Union[Annotated[list[float], Field(min_length=6, max_length=6)], None],
                      "a list of 6 numbers [m/s, rad/s] or null") = Field(
        None, description="[m/s, rad/s] constant twist (vx, vy, vz, wx, wy, wz); null: zero until code sets it")


class RPY(Section):
    """A rotation as roll, pitch, yaw."""

    rpy: Vector3 = Field(description="[rad] roll, pitch, yaw")


Matrix3 = expect(
    Annotated[list[Annotated[list[float], Field(min_length=3, max_length=3)]], Field(min_length=3, max_length=3)],
    "a 3x3 matrix (3 lists of 3 numbers)",
)


class FramePoseEntry(_Entry):
    """Drive a frame to a target pose: ``J qdot = gain * e`` with ``e = [p* - p; log3(R* R^T)]`` (world)."""

    type: Literal["frame_pose"]
    frame: Name = Field(description="frame name in the robot model (e.g. camera, gripper)")
    position: expect(Union[Annotated[list[float], Field(min_length=3, max_length=3)], None],
                     "a list of 3 numbers [m] or null") = Field(
        None, description="[m] target position in the world; null: the frame's start position")
    offset: expect(Union[Annotated[list[float], Field(min_length=3, max_length=3)], None],
                   "a list of 3 numbers [m] or null") = Field(None, description="[m] added to the target position")
    rotation: expect(Union[RPY, Matrix3, None], "{rpy: [r, p, y]} or a 3x3 matrix or null") = Field(
        None, description="target rotation {rpy: [r, p, y]} [rad] or a 3x3 matrix; null: the start rotation")
    weight: Weights6 = Field(_default(FramePoseTask, "weight"),
                             description="[1/m^2, 1/rad^2] a weight or 6 per-axis weights (world axes)")
    level: HardLevel = Field(_default(FramePoseTask, "level"), description="priority level (0: hard)")
    gain: NonNegative = Field(_default(FramePoseTask, "gain"), description="[1/s] error feedback gain")


class RelativeFrameEntry(_Entry):
    """Hold the pose of ``frame`` relative to ``root`` (its start pose)."""

    type: Literal["relative_frame"]
    frame: Name = Field(description="frame name in the robot model")
    root: Name = Field(description="frame the pose is expressed in")
    weight: Weights6 = Field(_default(RelativeFrameTask, "weight"),
                             description="[1/m^2, 1/rad^2] a weight or 6 per-axis weights")
    level: HardLevel = Field(_default(RelativeFrameTask, "level"), description="priority level (0: hard)")
    gain: NonNegative = Field(_default(RelativeFrameTask, "gain"), description="[1/s] error feedback gain")


class PostureEntry(_Entry):
    """Pull the joints toward a posture."""

    type: Literal["posture"]
    target: expect(Union[Annotated[list[float], Field(min_length=1)], None], "a list of joint positions [rad] or null"
                   ) = Field(None, description="[rad] joint positions (one per joint); null: the start posture")
    weight: Weights = Field(_default(PostureTask, "weight"), description="[1/rad^2] a weight or one per joint")
    level: HardLevel = Field(_default(PostureTask, "level"), description="priority level (0: hard)")
    gain: NonNegative = Field(_default(PostureTask, "gain"), description="[1/s] error feedback gain")


class DampingEntry(_Entry):
    """Penalise joint velocities (regularisation)."""

    type: Literal["damping"]
    weight: Weights = Field(_default(DampingTask, "weight"), description="[1/(rad/s)^2] a weight or one per joint")
    level: HardLevel = Field(_default(DampingTask, "level"), description="priority level (0: hard)")


UserTaskType = Annotated[str, Field(pattern=r"^[^:\s]+:[A-Za-z_]\w*$")]


class UserTaskEntry(_Entry):
    """A user's own :class:`harvest_qp.tasks.Task` subclass, ``type: my_package.tasks:GazeTask``."""

    type: UserTaskType = Field(description="'module.path:ClassName' (importable, or a module next to the config "
                                           "file) or 'file.py:ClassName' (relative to the config file)")
    params: dict[str, Any] = Field({}, description="constructor arguments, validated against the "
                                   "class's `Params` pydantic model or its __init__ signature")
    level: HardLevel | None = Field(None, description="priority level set on the built task (null: the class's)")
    weight: Weights | None = Field(None, description="weight(s) set on the built task (null: the class's)")
    gain: NonNegative | None = Field(None, description="[1/s] gain set on the built task (null: the class's)")

    @field_validator("type", mode="after")
    @classmethod
    def _resolve(cls, value: str, info: ValidationInfo) -> str:
        base_dir = (info.context or {}).get("base_dir")
        return _resolve(value, base_dir)[0]

    @field_validator("params", mode="after")
    @classmethod
    def _check_params(cls, value: dict[str, Any], info: ValidationInfo) -> dict[str, Any]:
        if "type" not in info.data:
            return value  # the type already failed; that is the error to report
        task_class = resolve_task_class(info.data["type"])
        validate_user_params(task_class, value)
        return value


BUILT_IN_TASK_ENTRIES = {
    "frame_twist": FrameTwistEntry, "frame_pose": FramePoseEntry, "relative_frame": RelativeFrameEntry,
    "posture": PostureEntry, "damping": DampingEntry,
}
BUILT_IN_TASKS = tuple(BUILT_IN_TASK_ENTRIES)


def _task_kind(value: Any) -> str:
    if isinstance(value, dict):
        kind = value.get("type")
        return kind if kind in BUILT_IN_TASK_ENTRIES else "user"
    return getattr(value, "type", "user") if not isinstance(value, UserTaskEntry) else "user"


def _check_task_type(value: Any) -> Any:
    if not isinstance(value, dict):
        if isinstance(value, BaseModel):
            return value
        raise PydanticCustomError("expected", "expected {expected}",
                                  {"expected": "a mapping with a 'type' key (a task entry)"})
    kind = value.get("type")
    if kind is None:
        raise PydanticCustomError("missing_type", "a task entry needs a 'type': one of {valid}, or 'module:Class'",
                                  {"valid": ", ".join(BUILT_IN_TASKS)})
    if kind not in BUILT_IN_TASK_ENTRIES and not (isinstance(kind, str) and ":" in kind):
        raise PydanticCustomError(
            "unknown_type", "unknown task type {kind}{hint}; expected one of: {valid}, or 'module.path:ClassName'",
            {"kind": repr(kind), "hint": suggest(str(kind), list(BUILT_IN_TASKS)), "valid": ", ".join(BUILT_IN_TASKS)},
        )
    return value


TaskEntry = Annotated[
    Union[tuple(Annotated[model, Tag(name)] for name, model in BUILT_IN_TASK_ENTRIES.items())
          + (Annotated[UserTaskEntry, Tag("user")],)],
    Discriminator(_task_kind),
    BeforeValidator(_check_task_type),
]


# ------------------------------------------------------------------ limits


class JointPositionEntry(_Entry):
    """Keep the joints inside their position limits (a velocity damper)."""

    type: Literal["joint_position"]
    gain: expect(float, "a number in (0, 1]", gt=0, le=1) = Field(
        _default(JointPositionLimit, "gain"), description="fraction of the remaining range allowed per step")
    max_acceleration: NonNegScalars | None = Field(
        _default(JointPositionLimit, "max_acceleration"),
        description="[rad/s^2] braking deceleration capping the bound near a limit, one or 12 values (null: none)")


class JointVelocityEntry(_Entry):
    """Bound the joint velocities."""

    type: Literal["joint_velocity"]
    max_velocity: NonNegScalars | None = Field(
        _default(JointVelocityLimit, "max_velocity"), description="[rad/s] one or 12 values (null: the model's)")


class JointAccelerationEntry(_Entry):
    """Bound the change of joint velocity per step."""

    type: Literal["joint_acceleration"]
    max_acceleration: NonNegScalars = Field(
        _default(JointAccelerationLimit, "max_acceleration"), description="[rad/s^2] one or 12 values")


class ObstacleSphere(Section):
    """A world-fixed obstacle sphere."""

    center: Vector3 = Field(description="[m] centre in the world")
    radius: NonNegative = Field(description="[m] radius")


class CollisionEntry(_Entry):
    """Keep robot capsule pairs (and obstacles) at least ``safety_distance`` apart (velocity dampers)."""

    type: Literal["collision"]
    safety_distance: Positive = Field(_default(CollisionAvoidance, "safety_distance"), description="[m] d_s")
    influence_distance: Positive = Field(_default(CollisionAvoidance, "influence_distance"),
                                         description="[m] d_i: pairs closer than this get a damper row")
    gain: Positive = Field(_default(CollisionAvoidance, "gain"), description="[m/s] damper gain")
    max_pairs: PositiveInt = Field(_default(CollisionAvoidance, "max_pairs"),
                                   description="closest pairs kept as rows per step")
    obstacle_spheres: list[ObstacleSphere] = Field([], description="world-fixed spheres")


BUILT_IN_LIMIT_ENTRIES = {
    "joint_position": JointPositionEntry, "joint_velocity": JointVelocityEntry,
    "joint_acceleration": JointAccelerationEntry, "collision": CollisionEntry,
}
BUILT_IN_LIMITS = tuple(BUILT_IN_LIMIT_ENTRIES)


def _check_limit_type(value: Any) -> Any:
    if isinstance(value, BaseModel):
        return value
    if not isinstance(value, dict):
        raise PydanticCustomError("expected", "expected {expected}",
                                  {"expected": "a mapping with a 'type' key (a limit entry)"})
    kind = value.get("type")
    if kind not in BUILT_IN_LIMIT_ENTRIES:
        raise PydanticCustomError(
            "unknown_type", "unknown limit type {kind}{hint}; expected one of: {valid}",
            {"kind": repr(kind), "hint": suggest(str(kind), list(BUILT_IN_LIMITS)),
             "valid": ", ".join(BUILT_IN_LIMITS)},
        )
    return value


LimitEntry = Annotated[
    Union[tuple(BUILT_IN_LIMIT_ENTRIES.values())],
    Field(discriminator="type"),
    BeforeValidator(_check_limit_type),
]


# ------------------------------------------------------------------ QP-only task configs


class Viewpoint(Section):
    """Camera viewpoint of ``harvest-qp demo`` relative to the stem's mid-point (``stem_viewpoint``)."""

    distance: Positive = Field(0.3, description="[m] from the stem's mid-point")
    azimuth: Real = Field(0.6, description="[rad] from -x (toward the robot) toward +y")
    elevation: Real = Field(0.05, description="[rad] above the horizontal")


class TaskConfig(Section):
    """A QP task configuration: tasks and limits of one controller (``harvest-qp demo``, ``check-config``)."""

    extends: expect(str | list[str] | None, "a file name or a list of file names") = Field(
        None, description="file(s) this one extends (relative to this file); its keys override theirs (deep merge)")
    description: Text = Field("", description="what this configuration is for")
    dt: Positive = Field(0.002, description="[s] control period (UR5e: 2 ms)")
    duration: Positive = Field(4.0, description="[s] length of the demo")
    solver: Text = Field("daqp", description="QP backend: daqp | proxsuite | qpsolvers:<name>")
    viewpoint: Viewpoint = Field(Viewpoint(), description=Viewpoint.__doc__)
    environment: list[str] = Field([], description="static capsule geoms of the scene used as "
                                   "obstacles (e.g. [branch, cane]; MuJoCo demo only)")
    tasks: Annotated[list[TaskEntry], Field(min_length=1)] = Field(
        description="the QP's tasks (at least one), each a built-in `type` or a user's 'module:Class'")
    limits: list[LimitEntry] = Field([], description="the QP's limits")

    @field_validator("solver", mode="after")
    @classmethod
    def _known_backend(cls, value: str) -> str:
        from harvest_qp.backends import backend_name_problem

        problem = backend_name_problem(value)
        if problem is not None:
            raise PydanticCustomError("qp_backend", "{problem}", {"problem": problem})
        return value


# ------------------------------------------------------------------ user task classes

_MODULE_CACHE: dict[str, Any] = {}


def _fail(text: str, **ctx: Any) -> PydanticCustomError:
    """A one-line error about a user task; ``{name}`` fields of ``text`` are filled with ``repr``-free strings."""
    return PydanticCustomError("user_task", text, {k: str(v) for k, v in ctx.items()})


def _import(module_name: str, base_dir: Path | None):
    """Import ``module_name`` from sys.path, else from ``base_dir`` (the config file's folder)."""
    try:
        return importlib.import_module(module_name)
    except ModuleNotFoundError as err:
        top = module_name.split(".")[0]
        if err.name not in (top, module_name) or base_dir is None:
            raise
    sys.path.insert(0, str(base_dir))
    try:
        return importlib.import_module(module_name)
    finally:
        sys.path.remove(str(base_dir))


def _import_file(path: Path):
    key = str(path.resolve())
    if key in _MODULE_CACHE:
        return _MODULE_CACHE[key]
    name = "harvest_qp_user_" + hashlib.sha1(key.encode()).hexdigest()[:12]
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    _MODULE_CACHE[key] = module
    return module


def _resolve(spec: str, base_dir: str | Path | None) -> tuple[str, type]:
    """``(normalised spec, class)`` for ``module:Class`` or ``file.py:Class``; PydanticCustomError if not."""
    where, _, class_name = spec.rpartition(":")
    base = Path(base_dir) if base_dir is not None else None
    try:
        if where.endswith(".py"):
            path = Path(where) if Path(where).is_absolute() or base is None else base / where
            if not path.is_file():
                raise _fail("no file '{path}' for task type '{spec}'; expected 'file.py:ClassName' relative to the "
                            "config file", path=str(path), spec=spec)
            module = _import_file(path)
            spec = f"{path.resolve()}:{class_name}"
        else:
            module = _import(where, base)
    except PydanticCustomError:
        raise
    except ModuleNotFoundError as err:
        raise _fail("cannot import module '{module}' of task type '{spec}' ({err}); expected 'module.path:ClassName' "
                    "importable from sys.path or next to the config file", module=where, spec=spec, err=str(err)
                    ) from None
    except Exception as err:  # the user's module raised while importing
        raise _fail("importing '{module}' for task type '{spec}' raised {kind}: {err}", module=where, spec=spec,
                    kind=type(err).__name__, err=str(err)) from None
    task_class = getattr(module, class_name, None)
    if task_class is None:
        tasks_there = [n for n, v in vars(module).items() if isinstance(v, type) and issubclass(v, Task)]
        raise _fail("module '{module}' has no class '{name}'{hint}; its Task classes: {there}", module=where,
                    name=class_name, hint=suggest(class_name, tasks_there), there=", ".join(tasks_there) or "none")
    if not (isinstance(task_class, type) and issubclass(task_class, Task)) or inspect.isabstract(task_class):
        raise _fail("'{spec}' is not a harvest_qp Task; expected a concrete subclass of harvest_qp.tasks.Task",
                    spec=spec)
    # Remembered so that building the task finds a module that was found next to the config file.
    _CLASS_CACHE[spec] = task_class
    return spec, task_class


_CLASS_CACHE: dict[str, type] = {}


def resolve_task_class(spec: str, base_dir: str | Path | None = None) -> type[Task]:
    """The :class:`~harvest_qp.tasks.Task` subclass named by ``spec`` (``module:Class`` or ``file.py:Class``).

    Raises:
        ConfigError: the module or class is missing, or the class is not a Task.
    """
    if spec in _CLASS_CACHE:
        return _CLASS_CACHE[spec]
    try:
        return _resolve(spec, base_dir)[1]
    except PydanticCustomError as err:
        from harvest_qp.exceptions import ConfigError

        raise ConfigError(f"type: {err.message()}") from None


_RESERVED = {"self", "configuration", "level", "weight", "gain"}


def params_model(task_class: type) -> type[BaseModel]:
    """The pydantic model a user task's ``params`` are checked against.

    The class's own ``Params`` (a pydantic model) when it has one; else one built from its
    ``__init__`` signature (annotations pydantic cannot check are accepted as they are;
    ``configuration``, ``level``, ``weight`` and ``gain`` are not params).
    """
    own = getattr(task_class, "Params", None)
    if isinstance(own, type) and issubclass(own, BaseModel):
        return own
    signature = inspect.signature(task_class.__init__)
    try:
        hints = typing.get_type_hints(task_class.__init__)
    except Exception:
        hints = {}
    fields: dict[str, Any] = {}
    extra = "forbid"
    for name, parameter in signature.parameters.items():
        if name in _RESERVED or parameter.kind is inspect.Parameter.VAR_POSITIONAL:
            continue
        if parameter.kind is inspect.Parameter.VAR_KEYWORD:
            extra = "allow"
            continue
        hint = hints.get(name, Any)
        try:
            TypeAdapter(hint)
        except Exception:
            hint = Any
        default = ... if parameter.default is inspect.Parameter.empty else parameter.default
        fields[name] = (hint, default)
    return create_model(f"{task_class.__name__}Params", __config__=ConfigDict(extra=extra), **fields)


def validate_user_params(task_class: type, params: dict[str, Any]) -> dict[str, Any]:
    """``params`` checked against :func:`params_model`; a PydanticCustomError naming the bad one if not."""
    model = params_model(task_class)
    try:
        checked = model.model_validate(params)
    except ValidationError as err:
        first = err.errors()[0]
        sub = ".".join(str(p) for p in first["loc"])
        names = ", ".join(model.model_fields)
        if first["type"] == "extra_forbidden":
            raise PydanticCustomError("unknown_key", "unknown key '{key}'{hint}; expected one of: {valid}", {
                "key": sub, "hint": suggest(sub, list(model.model_fields)), "valid": names}) from None
        if first["type"] == "missing":
            raise _fail("is required by {cls} (its params: {names})", subpath=sub, cls=task_class.__name__,
                        names=names) from None
        raise _fail("{msg} ({cls}'s params); got {value}", subpath=sub, cls=task_class.__name__,
                    msg=first["msg"][0].lower() + first["msg"][1:], value=repr(first.get("input"))) from None
    return {name: getattr(checked, name) for name in model.model_fields} | dict(checked.model_extra or {})
