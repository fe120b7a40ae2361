"""One schema for every harvest_qp configuration file (pydantic v2), and how files are read.

Two kinds of file share it (``harvest-qp schema`` writes both into one JSON Schema):

* :class:`EpisodeConfig`, the paper episode's settings tree (``tasks/paper.yaml``,
  ``harvest-qp run``): scene, camera, perception, reference laws, QP tasks with levels and
  weights, limits, collision, solver, faults, episode;
* :class:`TaskConfig`, a QP task configuration (``tasks/reach_targets.yaml``,
  ``harvest-qp demo``): ``dt``, ``tasks`` and ``limits`` of one controller.

A file's kind follows from its keys (``tasks``/``dt``/``limits``... make a task config).
Both may ``extends:`` other files and may name a user's own Task class (``type: pkg.mod:Class``).
"""

from harvest_qp.schema.episode import EpisodeConfig
from harvest_qp.schema.loading import (
    ResolvedConfig,
    apply_override,
    config_kind,
    deep_merge,
    load_config,
    read_yaml,
    resolve_file,
    validate_data,
)
from harvest_qp.schema.reference import config_reference_markdown, json_schema
from harvest_qp.schema.tasks import TaskConfig, params_model, resolve_task_class

__all__ = [
    "EpisodeConfig", "TaskConfig", "ResolvedConfig", "apply_override", "config_kind", "deep_merge", "load_config",
    "read_yaml", "resolve_file", "validate_data", "json_schema", "config_reference_markdown", "params_model",
    "resolve_task_class",
]
