"""Reading configuration files: safe YAML, ``extends`` with deep merge, ``--set`` overrides, one-line errors.

Every failure is a :class:`~harvest_qp.exceptions.ConfigError` whose message is one line
naming the file (the one in the ``extends`` chain that set the key, or ``--set``), the key
path (``grasping.k_fp``, ``tasks[1].weight``), the bad value and what was expected.
"""

from __future__ import annotations

import copy
import json
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ValidationError

from harvest_qp.config.episode_schema import EpisodeConfig
from harvest_qp.config.task_schema import BUILT_IN_LIMITS, BUILT_IN_TASKS, TaskConfig
from harvest_qp.exceptions import ConfigError

__all__ = [
    "Kind", "ResolvedConfig", "read_yaml", "resolve_file", "apply_override", "config_kind", "validate_data",
    "load_config", "deep_merge",
]

Kind = Literal["episode", "tasks"]
_MODELS: dict[str, type[BaseModel]] = {"episode": EpisodeConfig, "tasks": TaskConfig}
_COMMON = {"extends", "description"}
_TASK_KEYS = set(TaskConfig.model_fields) - _COMMON
_EPISODE_KEYS = set(EpisodeConfig.model_fields) - _COMMON
_TAGS = {*BUILT_IN_TASKS, *BUILT_IN_LIMITS, "user"}
_WHAT = {
    "episode": "an episode configuration (settings tree such as tasks/paper.yaml, for `harvest-qp run`)",
    "tasks": "a QP task configuration (dt, tasks, limits such as tasks/reach_targets.yaml, for "
             "`harvest-qp demo --config`)",
}


class _UniqueKeyLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` (no Python objects) that rejects a key given twice in one mapping."""


def _construct_mapping(loader: _UniqueKeyLoader, node: yaml.MappingNode, deep: bool = False) -> dict:
    seen = set()
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if isinstance(key, (str, int, float, bool)) and key in seen:
            raise yaml.constructor.ConstructorError(
                None, None, f"key {key!r} given twice in one mapping", key_node.start_mark)
        seen.add(key) if isinstance(key, (str, int, float, bool)) else None
    return yaml.SafeLoader.construct_mapping(loader, node, deep=deep)


_UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def read_yaml(path: str | Path) -> dict[str, Any]:
    """The mapping in the YAML file ``path`` (safe loader: no Python objects).

    An empty file (blank or only comments) is refused rather than read as "every default":
    a config that silently ran the defaults after a bad copy or a wrong path would reproduce
    nothing the user meant; ``{}`` asks for the defaults explicitly.

    Raises:
        ConfigError: missing or unreadable file, empty, not YAML, a repeated key, or not a mapping.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: file not found; expected a YAML configuration file such as tasks/paper.yaml")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"{path}: cannot read it as text ({type(err).__name__}); expected a YAML file") from None
    try:
        data = yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 (a SafeLoader subclass)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        problem = getattr(err, "problem", None) or ""
        raise ConfigError(f"{path}: not valid YAML{where} ({problem}); expected a mapping of keys") from None
    if data is None:
        raise ConfigError(f"{path}: the file is empty (blank or only comments); expected a mapping of keys "
                          "(write {} to take every default)")
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: the file must hold a mapping of keys (a mapping of sections); "
                          f"got {type(data).__name__}")
    return data


def deep_merge(base: Mapping[str, Any], update: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with ``update`` merged in: mappings recursively, everything else (lists too) replaced."""
    out = copy.deepcopy(dict(base))
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


@dataclass
class ResolvedConfig:
    """A configuration file after ``extends`` and overrides, before validation.

    Attributes:
        path: the file named by the user.
        data: the merged mapping (no ``extends`` key left).
        chain: ``(file, its own mapping)`` from the farthest ancestor to ``path`` (for error provenance).
        overrides: the ``section.key=value`` strings applied last.
    """

    path: Path
    data: dict[str, Any]
    chain: list[tuple[Path, dict[str, Any]]] = field(default_factory=list)
    overrides: list[str] = field(default_factory=list)

    def origin(self, keys: Sequence[Any]) -> str:
        """The file (or the ``--set`` override) that gave the value at ``keys``; the user's file if none did."""
        for item in reversed(self.overrides):
            head = item.split("=", 1)[0].strip().split(".")
            if [str(k) for k in keys[: len(head)]] == head:
                return f"{self.path} (--set {item})"
        for path, raw in reversed(self.chain):
            node: Any = raw
            found = True
            for key in keys:
                if isinstance(node, dict) and key in node:
                    node = node[key]
                elif isinstance(node, list) and isinstance(key, int) and key < len(node):
                    node = node[key]
                else:
                    found = False
                    break
            if found and keys:
                return str(path)
        return str(self.path)

    def fingerprint_text(self) -> str:
        """The merged mapping as canonical JSON (sorted keys): equal for configs that mean the same."""
        return json.dumps(self.data, sort_keys=True, default=str, separators=(",", ":"))


def resolve_file(path: str | Path, overrides: Iterable[str] = ()) -> ResolvedConfig:
    """Read ``path``, follow its ``extends`` (relative to each file, cycles rejected), apply ``overrides``."""
    path = Path(path)
    chain: list[tuple[Path, dict[str, Any]]] = []
    data = _resolve_extends(path, chain, stack=[])
    overrides = list(overrides)
    for item in overrides:
        data = apply_override(data, item, str(path))
    return ResolvedConfig(path, data, chain, overrides)


def _resolve_extends(path: Path, chain: list, stack: list[Path]) -> dict[str, Any]:
    key = path.resolve()
    if key in stack:
        cycle = " -> ".join(str(p) for p in [*stack[stack.index(key):], key])
        raise ConfigError(f"{stack[-1]}: 'extends' makes a cycle ({cycle}); expected a chain that ends")
    raw = read_yaml(path)
    parents = raw.get("extends")
    merged: dict[str, Any] = {}
    if parents is not None:
        names = [parents] if isinstance(parents, str) else parents
        if not isinstance(names, list) or not names or not all(isinstance(n, str) and n for n in names):
            raise ConfigError(f"{path}: 'extends' must be a file name or a list of file names; got {parents!r}")
        for name in names:
            parent = Path(name) if Path(name).is_absolute() else path.parent / name
            if not parent.is_file():
                raise ConfigError(f"{path}: 'extends' names {name!r}, but {parent} is not a file; expected a path "
                                  "relative to this file")
            merged = deep_merge(merged, _resolve_extends(parent, chain, [*stack, key]))
    own = {k: v for k, v in raw.items() if k != "extends"}
    chain.append((path, own))
    return deep_merge(merged, own)


def apply_override(data: dict[str, Any], item: str, source: str = "--set") -> dict[str, Any]:
    """``data`` with ``section.key=value`` set (the value parsed as YAML)."""
    if not isinstance(item, str) or "=" not in item:
        raise ConfigError(f"{source}: override {item!r} must be section.key=value")
    key, text = item.split("=", 1)
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        raise ConfigError(f"{source}: override {item!r}: the value is not valid YAML") from None
    parts = key.strip().split(".")
    if not all(parts):
        raise ConfigError(f"{source}: override {item!r} must be section.key=value")
    out = copy.deepcopy(data)
    node = out
    for part in parts[:-1]:
        if not isinstance(node.get(part, {}), dict):
            raise ConfigError(f"{source}: override {item!r}: '{part}' is not a section")
        node = node.setdefault(part, {})
    node[parts[-1]] = value
    return out


def config_kind(data: Mapping[str, Any]) -> Kind:
    """``"tasks"`` for a QP task configuration (``tasks``, ``dt``, ...), ``"episode"`` for the paper's tree."""
    task_keys = len(_TASK_KEYS & set(data))
    episode_keys = len(_EPISODE_KEYS & set(data))
    if task_keys > episode_keys or (task_keys == episode_keys and "tasks" in data):
        return "tasks"
    return "episode"


def _path(loc: Sequence[Any]) -> tuple[str, list[Any]]:
    """``("qp.limits[1].gain", keys)`` from a pydantic location (union tags dropped)."""
    text, keys = "", []
    for i, part in enumerate(loc):
        if isinstance(part, int):
            text += f"[{part}]"
            keys.append(part)
        elif part in _TAGS and i > 0 and isinstance(loc[i - 1], int):
            continue  # the union member pydantic tried, not a key
        else:
            text += f".{part}" if text else str(part)
            keys.append(part)
    return text, keys


def _describe(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def format_error(err: ValidationError, resolved: ResolvedConfig | None, source: str) -> str:
    """One line for the first error of ``err`` (and how many more there are)."""
    errors = err.errors(include_url=False)
    first = errors[0]
    path, keys = _path(first["loc"])
    ctx = first.get("ctx") or {}
    kind = first["type"]
    value = first.get("input")
    if kind == "unknown_key":
        keys = [*keys, ctx["key"]]
        path = f"{path}.{ctx['key']}" if path else ctx["key"]
    elif kind == "unknown_type":
        keys = [*keys, "type"]
        path = f"{path}.type"
    elif kind == "user_task" and "subpath" in ctx:
        keys = [*keys, *ctx["subpath"].split(".")]
        path = f"{path}.{ctx['subpath']}"
    where = resolved.origin(keys) if resolved is not None else source
    if kind == "user_task" and "subpath" in ctx:
        text = f"'{path}' {first['msg']}"
    elif kind == "expected":
        text = f"'{path}' must be {ctx['expected']}; got {_describe(value)}"
        if isinstance(value, str) and _looks_numeric(value):
            text += " (YAML 1.1 reads 1e-3 as text: write 1.0e-3)"
    elif kind == "unknown_key":
        text = f"unknown key '{path}'{ctx['hint']}; expected one of: {ctx['valid']}"
    elif kind == "missing":
        text = f"'{path}' is required"
    elif kind == "literal_error":
        text = f"'{path}' must be {ctx.get('expected')}; got {_describe(value)}"
    elif kind in ("bool_type", "bool_parsing"):
        text = f"'{path}' must be true or false; got {_describe(value)}"
    elif kind == "scene_params":  # VineSceneParams' own one-line message names the field and the value
        text = f"'{path}': {first['msg']}"
    elif kind in ("string_type",):
        text = f"'{path}' must be a string; got {_describe(value)}"
    elif kind in ("list_type", "too_short", "too_long"):
        text = f"'{path}': {first['msg'][0].lower()}{first['msg'][1:]}; got {_describe(value)}"
    else:
        text = f"'{path}': {first['msg'][0].lower()}{first['msg'][1:]}"
        if kind not in ("user_task", "unknown_type", "missing_type"):
            text += f"; got {_describe(value)}"
    more = len(errors) - 1
    suffix = f" (and {more} more error{'s' if more > 1 else ''})" if more else ""
    return f"{where}: {text}{suffix}"


def _looks_numeric(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def validate_data(
    data: Mapping[str, Any], *, kind: Kind | None = None, source: str = "config",
    resolved: ResolvedConfig | None = None, base_dir: str | Path | None = None,
) -> BaseModel:
    """The validated model (:class:`EpisodeConfig` or :class:`TaskConfig`) of a mapping; ConfigError if not."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"{source}: the configuration must be a mapping of keys (a mapping of sections); "
                          f"got {type(data).__name__}")
    detected = config_kind(data)
    own_keys = _TASK_KEYS if kind == "tasks" else _EPISODE_KEYS
    other_keys = _EPISODE_KEYS if kind == "tasks" else _TASK_KEYS
    if kind is not None and detected != kind and other_keys & set(data) and not own_keys & set(data):
        raise ConfigError(f"{source}: this is {_WHAT[detected]}; expected {_WHAT[kind]}")
    kind = kind or detected
    model = _MODELS[kind]
    try:
        return model.model_validate(dict(data), context={"base_dir": str(base_dir) if base_dir else None})
    except ValidationError as err:
        raise ConfigError(format_error(err, resolved, source)) from None


def load_config(path: str | Path, overrides: Iterable[str] = (), *, kind: Kind | None = None) -> BaseModel:
    """Read, resolve and validate a configuration file (either kind unless ``kind`` says)."""
    resolved = resolve_file(path, overrides)
    return validate_data(resolved.data, kind=kind, source=str(path), resolved=resolved,
                         base_dir=Path(path).resolve().parent)
