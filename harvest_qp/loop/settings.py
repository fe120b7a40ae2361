"""The paper's experiment as a checked settings tree (``tasks/paper.yaml``).

Every value of Section ``sec:exper`` has a key, written as in the paper (gains ``k_*``);
every key has a default, so a file only needs what it changes, and every key can be
overridden from the command line (``--set grasping.f_d=2.5``).  Unknown keys, wrong types
and out-of-range values raise :class:`~harvest_qp.exceptions.ConfigError` with one line
naming the file, the key, the expected value and what was found.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from harvest_qp.exceptions import ConfigError

__all__ = ["DEFAULTS", "SPEC", "load_settings", "apply_override", "check_settings"]

# Value kinds: "pos" finite > 0, "nonneg" finite >= 0, "real" finite, "frac" in [0, 1),
# "int+" integer >= 1, "int0" integer >= 0, "bool", "pos|null", "pos|l" (> 0 or the string
# "l": the estimated stem length), ("choice", {...}), "weights6" (a number or 6 numbers >= 0),
# "weight" (a number >= 0), "level" (integer >= 1), "mapping", "list".
SPEC: dict[str, dict[str, Any]] = {
    "description": "text",
    "episode": {
        "duration": "pos",  # [s] episode length (the force loop needs ~20 s after the switch)
        "end_after_precut": "pos|null",  # [s] end this long after "pre-cut reached"; null: run the full duration
        "stop_after_abort": "nonneg",  # [s] the episode ends this long after an abort's safe stop
    },
    "scene": {
        "randomize": "bool",  # seed > 0: VineSceneParams.sample(seed); seed 0 is the default scene
        "params": "mapping",  # VineSceneParams fields set explicitly
    },
    "camera": {
        "width": "int+", "height": "int+", "downsample": "int+", "rate": "pos", "stem_range": "pos",
        "depth_noise": "nonneg", "dropout": "frac", "latency": "nonneg", "frame_loss": "frac",
    },
    "force_sensor": {"noise_std": "nonneg", "filter_time_constant": "nonneg"},
    "reaching": {"radius": "pos", "k_cp": "pos", "k_co": "pos", "roi_time_constant": "nonneg",
                 "target_radius_factor": "pos",  # V_cr's sphere is this x r (1 = the paper)
                 "min_distance_factor": "frac",  # beyond the paper: keep the camera >= this x r from p_r
                 "k_keep_out": "pos"},  # [1/s] gain of that outward term
    "unveiling": {
        "enabled": "bool", "k_c": "pos", "d_a": "pos", "d_o": "nonneg", "time_constant": "nonneg",
        "max_linear": "pos", "max_angular": "pos",  # [m/s], [rad/s] bounds on the raw V_cu (not in the paper)
        "min_pivot": "nonneg",  # [m] ray/obstacle pairs with a shorter pivot arm are dropped (not in the paper)
        "predicted_stem": "bool",  # beyond the paper: act on the predicted stem while n_S = 0
    },
    "switch": {"distance_factor": "pos", "max_linear_speed": "pos", "max_angular_speed": "pos",
               "window": "pos"},  # [s] the speeds are means over this window
    "grasping": {
        "k_pg": "pos", "k_og": "pos", "k_fp": "pos", "k_fi": "nonneg", "f_d": "pos",
        "max_speed": "pos",  # [m/s] saturation of the force term (anti-windup holds the integral there)
        "integration_threshold": "pos|null",  # [N] integrate once n_c^T f exceeds it (null: from the start)
        "r_o": "pos|l",  # radius of S(p_sb, r_o) bounding O for p_gd; "l" = the estimated stem length
        "n_samples": "int+",  # Fibonacci samples of S(p_sb, l)
        "exclude_held_crop": "bool",  # O for p_gd without the robot's points and the held crop
        "max_swing_deg": "pos|null",  # p_gd within this angle of the hanging stem (null: the paper's hemisphere)
        "swing_clearance": "pos|null",  # [m] map distance the gripper keeps along its swing to p_gd (null: not checked)
        "swing_stretch": "nonneg",  # [m] the swing check also moves the gripper this far out along n_c
        "k_hold": "pos",  # [1/s] the grasping arm holds the crop still during the approach
        "feed_forward": "bool",  # eq:final_vc's term on the camera in the bimanual phase
    },
    "perception": {
        "min_stem_points": "int+",
        "max_base_distance": "pos",  # [m] a p_sb further than this from the gripper is rejected
        "grasp_offset": "nonneg",  # [m] from the gripper point up (-y_g) to where the stem enters the crop
    },
    "roll": {"enabled": "bool", "k_roll": "pos"},  # beyond the paper: cutter across the stem
    "obstacles": {  # beyond the paper: the vine seen near the gripper as QP collision spheres
        "enabled": "bool", "max_distance": "pos", "voxel": "pos", "radius": "nonneg",
        "cluster_radius": "nonneg", "cluster_length": "nonneg",
    },
    "obstacle_map": {  # issue 11: the camera's frames as a persistent map fed to the collision rows
        "enabled": "bool", "resolution": "pos",  # [m] cell edge
        "arms": ("choice", {"camera", "both"}),  # whose capsules get the map's rows
        "clear_rays": "int+",  # clearing rays per frame (about)
        "per_capsule": "int+", "max_cells": "int+",  # cells kept per arm capsule / in all
        "min_separation": "nonneg", "margin": "nonneg",  # [m] see MapCollisionFeed
        "cluster_length": "nonneg", "cluster_radius": "nonneg",  # [m] held cluster (along y_g) never mapped
        "cluster_start": "real",  # [m] that capsule's axis starts this far below the gripper point (along y_g)
        "stem_radius": "nonneg",  # [m] capsule around the stem (top of the crop to p_sb) never mapped
        "stem_length": "pos",  # [m] the stem's length along -y_g before a stem base is found
    },
    "safety": {
        "force_limit": "pos|null",  # [N] abort above it; null = 2 f_d
        "stem_lost_timeout": "pos",  # [s] no stem point in the bimanual phase
        "no_stem_timeout": "pos",  # [s] no valid stem base ever found
        "max_qp_failures": "int+",  # QP failures in a row
    },
    "precut": {
        "force_tolerance": "frac",  # fraction of f_d
        "position_tolerance": "pos",  # [m] projected position error
        "alignment_tolerance_deg": "pos",
        "hold_time": "nonneg",  # [s]
        "force_time_constant": "nonneg",  # [s] low-pass on the force for this test
    },
    "qp": {
        "solver": "text",
        "backup_solver": "text|null",  # re-solves a tick the main backend failed (null: none)
        "camera_task": {"level": "level", "weight": "weights6"},
        "gripper_task": {"level": "level", "weight": "weights6"},
        "roll_task": {"level": "level", "weight": "weight"},
        "posture": {"level": "level", "weight": "weight"},
        "damping": {"level": "level", "weight": "weight"},
        "limits": "list",  # entries as in tasks/*.yaml (see harvest_qp.config)
        "environment": "list",  # static capsule geoms of the scene known to the controller
    },
    "mapper": {"kind": ("choice", {"qp", "pinv"}), "pinv_damping": "nonneg"},
}

DEFAULTS: dict[str, Any] = {
    "description": "",
    "episode": {"duration": 50.0, "end_after_precut": None, "stop_after_abort": 0.5},
    "scene": {"randomize": True, "params": {}},
    "camera": {"width": 848, "height": 480, "downsample": 3, "rate": 30.0, "stem_range": 0.7,
               "depth_noise": 0.0, "dropout": 0.0, "latency": 0.0, "frame_loss": 0.0},
    "force_sensor": {"noise_std": 0.0, "filter_time_constant": 0.0},
    "reaching": {"radius": 0.35, "k_cp": 1.0, "k_co": 1.0, "roi_time_constant": 0.5,
                 "target_radius_factor": 0.95, "min_distance_factor": 0.9, "k_keep_out": 2.0},
    "unveiling": {"enabled": True, "k_c": 0.00025, "d_a": 0.01, "d_o": 0.001, "time_constant": 0.5,
                  "max_linear": 0.05, "max_angular": 0.1, "min_pivot": 0.03,
                  "predicted_stem": True},
    "switch": {"distance_factor": 1.05, "max_linear_speed": 0.01, "max_angular_speed": 0.025, "window": 0.5},
    "grasping": {"k_pg": 0.15, "k_og": 0.3, "k_fp": 0.001, "k_fi": 0.0002, "f_d": 3.0, "r_o": "l",
                 "max_speed": 0.05, "integration_threshold": 2.0,
                 "n_samples": 500, "exclude_held_crop": False, "max_swing_deg": 30.0, "swing_clearance": 0.02,
                 "swing_stretch": 0.03, "k_hold": 1.0,
                 "feed_forward": True},
    "perception": {"min_stem_points": 10, "max_base_distance": 0.2, "grasp_offset": 0.015},
    "roll": {"enabled": True, "k_roll": 1.0},
    "obstacles": {"enabled": False, "max_distance": 0.25, "voxel": 0.02, "radius": 0.01, "cluster_radius": 0.075,
                  "cluster_length": 0.22},
    "obstacle_map": {"enabled": True, "arms": "camera", "resolution": 0.01, "clear_rays": 12000, "per_capsule": 4,
                     "max_cells": 24,
                     "min_separation": 0.03, "margin": 0.01, "cluster_length": 0.22, "cluster_radius": 0.08,
                     "cluster_start": 0.04, "stem_radius": 0.02, "stem_length": 0.08},
    "safety": {"force_limit": None, "stem_lost_timeout": 5.0, "no_stem_timeout": 30.0, "max_qp_failures": 25},
    "precut": {"force_tolerance": 0.1, "position_tolerance": 0.005, "alignment_tolerance_deg": 5.0,
               "hold_time": 1.0, "force_time_constant": 0.2},
    "qp": {
        "solver": "daqp",
        "backup_solver": "proxsuite",
        "camera_task": {"level": 1, "weight": [1.0, 1.0, 1.0, 1.0, 1.0, 0.0]},
        "gripper_task": {"level": 1, "weight": 1.0},
        "roll_task": {"level": 2, "weight": 1.0},
        "posture": {"level": 2, "weight": 1.0e-4},
        "damping": {"level": 2, "weight": 1.0e-3},
        "limits": [
            {"type": "joint_position"},
            {"type": "joint_velocity", "max_velocity": 1.0},
            {"type": "joint_acceleration", "max_acceleration": 5.0},
            {"type": "collision", "safety_distance": 0.01, "influence_distance": 0.1, "gain": 0.3},
        ],
        "environment": [],
    },
    "mapper": {"kind": "qp", "pinv_damping": 0.0},
}


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _expected(kind: Any) -> str:
    if isinstance(kind, tuple):
        return "one of " + ", ".join(sorted(kind[1]))
    return {
        "pos": "a number > 0", "nonneg": "a number >= 0", "real": "a finite number",
        "frac": "a number in [0, 1)", "int+": "an integer >= 1", "int0": "an integer >= 0",
        "bool": "true or false", "pos|null": "a number > 0 or null", "pos|l": "a number > 0 or 'l'",
        "weights6": "a number >= 0 or a list of 6 numbers >= 0", "weight": "a number >= 0",
        "level": "an integer >= 1", "mapping": "a mapping", "list": "a list", "text": "a string",
        "text|null": "a string or null",
    }[kind]


def _valid(kind: Any, value: Any) -> bool:
    if isinstance(kind, tuple):
        return value in kind[1]
    if kind == "pos":
        return _is_number(value) and value > 0
    if kind in ("nonneg", "weight"):
        return _is_number(value) and value >= 0
    if kind == "real":
        return _is_number(value)
    if kind == "frac":
        return _is_number(value) and 0 <= value < 1
    if kind in ("int+", "level"):
        return isinstance(value, int) and not isinstance(value, bool) and value >= 1
    if kind == "int0":
        return isinstance(value, int) and not isinstance(value, bool) and value >= 0
    if kind == "bool":
        return isinstance(value, bool)
    if kind == "pos|null":
        return value is None or (_is_number(value) and value > 0)
    if kind == "pos|l":
        return value == "l" or (_is_number(value) and value > 0)
    if kind == "weights6":
        if _is_number(value):
            return value >= 0
        return isinstance(value, list) and len(value) == 6 and all(_is_number(v) and v >= 0 for v in value)
    if kind == "mapping":
        return isinstance(value, dict)
    if kind == "list":
        return isinstance(value, list)
    if kind == "text":
        return isinstance(value, str)
    if kind == "text|null":
        return value is None or isinstance(value, str)
    raise AssertionError(kind)


def _check(spec: Mapping[str, Any], data: Mapping[str, Any], where: str, source: str) -> None:
    for key, value in data.items():
        path = f"{where}.{key}" if where else str(key)
        if key not in spec:
            raise ConfigError(f"{source}: unknown key '{path}'; expected one of: {', '.join(sorted(spec))}")
        kind = spec[key]
        if isinstance(kind, dict):
            if not isinstance(value, dict):
                raise ConfigError(f"{source}: '{path}' must be a mapping of {', '.join(sorted(kind))}; got {value!r}")
            _check(kind, value, path, source)
        elif not _valid(kind, value):
            raise ConfigError(f"{source}: '{path}' must be {_expected(kind)}; got {value!r}")


def _merge(base: dict[str, Any], update: Mapping[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(base)
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict) and key != "params":
            out[key] = _merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def check_settings(data: Mapping[str, Any], source: str = "settings") -> dict[str, Any]:
    """Check ``data`` against :data:`SPEC` and return it merged over :data:`DEFAULTS`."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: the file must hold a mapping of sections; got {type(data).__name__}")
    _check(SPEC, data, "", source)
    return _merge(DEFAULTS, data)


def load_settings(path: str | Path, overrides: list[str] | tuple[str, ...] = ()) -> dict[str, Any]:
    """Read a paper-episode settings file (YAML), apply ``section.key=value`` overrides, check it.

    Raises:
        ConfigError: missing or unreadable file, invalid YAML, unknown key, bad value.
    """
    path = Path(path)
    source = str(path)
    if not path.is_file():
        raise ConfigError(f"{source}: file not found; expected a YAML settings file such as tasks/paper.yaml")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"{source}: cannot read it as text ({type(err).__name__}); expected a YAML file") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise ConfigError(f"{source}: not valid YAML{where}; expected a mapping of sections") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: the file must hold a mapping of sections; got {type(data).__name__}")
    for item in overrides:
        data = apply_override(data, item, source)
    return check_settings(data, source)


def apply_override(data: dict[str, Any], item: str, source: str = "--set") -> dict[str, Any]:
    """``data`` with ``section.key=value`` set (the value parsed as YAML)."""
    if "=" not in item:
        raise ConfigError(f"{source}: override {item!r} must be section.key=value")
    key, text = item.split("=", 1)
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        raise ConfigError(f"{source}: override {item!r}: the value is not valid YAML") from None
    parts = key.strip().split(".")
    out = copy.deepcopy(data)
    node = out
    for part in parts[:-1]:
        if not isinstance(node.get(part, {}), dict):
            raise ConfigError(f"{source}: override {item!r}: '{part}' is not a section")
        node = node.setdefault(part, {})
    node[parts[-1]] = value
    return out
