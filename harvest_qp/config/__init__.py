"""The one configuration system: the schema of every harvest_qp file (pydantic v2), how files are read,
and how checked entries become tasks, limits and the episode's settings.

* :mod:`.episode_schema`, :mod:`.task_schema`: the schema (every key, its unit, default and check);
* :mod:`.loading`: YAML read safely, ``extends`` followed, ``--set`` overrides, one-line errors;
* :mod:`.build`: tasks and limits built from checked entries (:func:`load_controller_config`);
* :mod:`.settings`: the paper episode's settings (:func:`load_settings`);
* :mod:`.reference`: the JSON Schema and the generated key reference (``docs/config.md``).

Two kinds of file share it (``harvest-qp schema`` writes both into one JSON Schema):

* :class:`EpisodeConfig`, the paper episode's settings tree (``tasks/paper.yaml``,
  ``harvest-qp run``): scene, camera, perception, reference laws, QP tasks with levels and
  weights, limits, collision, solver, faults, episode;
* :class:`TaskConfig`, a QP task configuration (``tasks/reach_targets.yaml``,
  ``harvest-qp demo``): ``dt``, ``tasks`` and ``limits`` of one controller.

A file's kind follows from its keys (``tasks``/``dt``/``limits``... make a task config).
Both may ``extends:`` other files and may name a user's own Task class (``type: pkg.mod:Class``).
"""

from harvest_qp.config.build import (  # noqa: E402  (after the schema it checks against)
    ControllerConfig,
    build_controller_config,
    build_limit,
    build_limits,
    build_tasks,
    controller_config_from_checked,
    load_controller_config,
    read_config_file,
)
from harvest_qp.config.episode_schema import EpisodeConfig
from harvest_qp.config.loading import (
    ResolvedConfig,
    apply_override,
    config_kind,
    deep_merge,
    load_config,
    read_yaml,
    resolve_file,
    validate_data,
)
from harvest_qp.config.reference import config_reference_markdown, json_schema
from harvest_qp.config.settings import DEFAULTS, check_settings, load_settings  # noqa: E402
from harvest_qp.config.task_schema import TaskConfig, params_model, resolve_task_class

__all__ = [
    "EpisodeConfig", "TaskConfig", "ResolvedConfig", "apply_override", "config_kind", "deep_merge", "load_config",
    "read_yaml", "resolve_file", "validate_data", "json_schema", "config_reference_markdown", "params_model",
    "resolve_task_class", "ControllerConfig", "build_controller_config", "build_limit", "build_limits", "build_tasks",
    "controller_config_from_checked", "load_controller_config", "read_config_file", "DEFAULTS", "check_settings",
    "load_settings",
]
