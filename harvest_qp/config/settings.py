"""The paper's experiment as typed, checked settings (``tasks/paper.yaml``).

Every value of Section ``sec:exper`` has a key, written as in the paper (gains ``k_*``);
every key has a default, so a file only needs what it changes, and every key can be
overridden from the command line (``--set grasping.f_d=2.5``). The keys, their units and
defaults live in ONE place, the schema :class:`harvest_qp.config.EpisodeConfig` (pydantic);
the controller reads its attributes (``settings.grasping.f_d``). Unknown keys, wrong types and
out-of-range values raise :class:`~harvest_qp.exceptions.ConfigError` with one line naming the
file, the key, the expected value and what was found.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from harvest_qp.config.episode_schema import EpisodeConfig
from harvest_qp.config.loading import apply_override, load_config, validate_data
from harvest_qp.exceptions import ConfigError

__all__ = ["DEFAULTS", "load_settings", "apply_override", "check_settings"]

#: Every key's default (the schema's; do not edit here).
DEFAULTS: EpisodeConfig = EpisodeConfig()


def check_settings(data: EpisodeConfig | Mapping[str, Any], source: str = "settings") -> EpisodeConfig:
    """``data`` as checked settings: an :class:`EpisodeConfig` as it is, a mapping checked against the
    schema with every default filled in.

    Raises:
        ConfigError: not a mapping, an unknown key, a bad value (one line naming the key).
    """
    if isinstance(data, EpisodeConfig):
        return data
    if not isinstance(data, Mapping):
        raise ConfigError(f"{source}: the settings must be an EpisodeConfig or a mapping of sections; "
                          f"got {type(data).__name__}")
    return validate_data(data, kind="episode", source=source)


def load_settings(path: str | Path, overrides: list[str] | tuple[str, ...] = ()) -> EpisodeConfig:
    """Read a paper-episode settings file (YAML, ``extends`` followed), apply ``section.key=value`` overrides, check it.

    Raises:
        ConfigError: missing or unreadable file, invalid YAML, unknown key, bad value, ``extends`` cycle.
    """
    return load_config(path, overrides, kind="episode")
