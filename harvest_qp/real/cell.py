"""The cell file (``tasks/real/ur5e.yaml``): what the real cell needs beyond the episode's settings.

The episode's settings file (``tasks/paper.yaml``) stays the same for the lab and the real cell;
the cell file names the calibration file and holds the wrist F/T interpretation, the speedJ
acceleration, the watchdog thresholds and the camera options. Unknown keys and bad values are a
:class:`~harvest_qp.exceptions.ConfigError` naming the file and the key.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from harvest_qp.exceptions import ConfigError, HarvestQPError
from harvest_qp.real.watchdog import WatchdogConfig

__all__ = ["ForceConfig", "CameraCellConfig", "CellConfig", "load_cell", "default_cell_path"]


@dataclass(frozen=True)
class ForceConfig:
    """How to read the grasping arm's ``getActualTCPForce``.

    Attributes:
        frame: ``"base"`` (the UR e-series reports the TCP wrench in the arm's base frame) or
            ``"tool"`` (the flange frame); either way it is rotated to the world frame with the
            measured pose.
        tool_mass: mass below the sensor that the robot does not compensate [kg] (the gripper's
            mass when the pendant's payload is 0; 0 when the payload is set on the pendant).
        tool_com: that mass's centre of mass in the flange frame [m].
        zero_on_tare: ``tare_force`` also calls ``zeroFtSensor`` (the sensor's own offset is then
            removed in the sensor frame; the adapter keeps the world reading continuous).
    """

    frame: str = "base"
    tool_mass: float = 0.6
    tool_com: tuple[float, float, float] = (0.0, 0.0, 0.06)
    zero_on_tare: bool = True

    def __post_init__(self) -> None:
        if self.frame not in ("base", "tool"):
            raise ConfigError(f"force.frame must be 'base' or 'tool', got {self.frame!r}")
        if not isinstance(self.tool_mass, (int, float)) or not np.isfinite(self.tool_mass) or self.tool_mass < 0:
            raise ConfigError(f"force.tool_mass must be a number >= 0 [kg], got {self.tool_mass!r}")
        com = np.asarray(self.tool_com, dtype=float) if isinstance(self.tool_com, (list, tuple)) else None
        if com is None or com.shape != (3,) or not np.all(np.isfinite(com)):
            raise ConfigError(f"force.tool_com must be 3 numbers [m] in the flange frame, got {self.tool_com!r}")
        object.__setattr__(self, "tool_com", tuple(float(x) for x in com))


@dataclass(frozen=True)
class CameraCellConfig:
    """The D415 stream and the cloud's labels.

    Attributes:
        width, height, fps: the depth and colour streams (the paper's 848x480 at 30 FPS).
        min_depth, max_depth: valid depth interval [m].
        stem_detector: ``"red"`` (default threshold), ``{red: {hue_width, min_saturation, min_value}}``
            or ``"module:name"`` (:mod:`harvest_qp.real.stem_detector`).
        robot_margin: points within this distance of the robot's own capsules (at the measured
            joints) are labelled ROBOT [m].
    """

    width: int = 848
    height: int = 480
    fps: int = 30
    min_depth: float = 0.1
    max_depth: float = 2.0
    stem_detector: Any = "red"
    robot_margin: float = 0.005


@dataclass(frozen=True)
class CellConfig:
    """The cell file (see the module docstring)."""

    calibration: Path | None = None
    control_period: float = 0.002
    speedj_acceleration: float = 10.0
    robot_watchdog_hz: float = 10.0
    max_base_discrepancy: tuple[float, float] = (0.01, 1.0)
    force: ForceConfig = field(default_factory=ForceConfig)
    watchdog: WatchdogConfig = field(default_factory=WatchdogConfig)
    camera: CameraCellConfig = field(default_factory=CameraCellConfig)

    def __post_init__(self) -> None:
        for name in ("control_period", "speedj_acceleration", "robot_watchdog_hz"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value <= 0:
                raise ConfigError(f"{name} must be a number > 0, got {value!r}")


def default_cell_path() -> Path:
    """``tasks/real/ur5e.yaml`` of this checkout (or of the installed package)."""
    from harvest_qp.robot.paths import tasks_dir

    return tasks_dir() / "real" / "ur5e.yaml"


def _build(kind, data: Any, where: str):
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping, got {data!r}")
    names = {f.name for f in dataclasses.fields(kind)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; expected some of {sorted(names)}")
    try:
        return kind(**data)
    except TypeError as err:
        raise ConfigError(f"{where}: {err}") from None


def load_cell(path: str | Path | None = None) -> CellConfig:
    """Read a cell file (``yaml.safe_load``); ``calibration`` is resolved relative to the file.

    Raises:
        ConfigError: unreadable file, unknown key or bad value, naming the file and the key.
    """
    path = Path(path) if path is not None else default_cell_path()
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except OSError as err:
        raise ConfigError(f"cannot read the cell file {path}: {err.strerror}") from None
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML: {' '.join(str(err).split())}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: the cell file must hold a mapping, got {type(data).__name__}")
    data = dict(data)
    try:
        sections = {"force": ForceConfig, "watchdog": WatchdogConfig, "camera": CameraCellConfig}
        for key, kind in sections.items():
            if key in data:
                data[key] = _build(kind, data[key], f"{path}: {key}")
        if data.get("calibration") is not None:
            calibration = Path(str(data["calibration"]))
            data["calibration"] = calibration if calibration.is_absolute() else (path.parent / calibration)
        if "max_base_discrepancy" in data:
            d = data["max_base_discrepancy"]
            if not isinstance(d, dict) or set(d) != {"position", "angle_deg"}:
                raise ConfigError(f"{path}: max_base_discrepancy must be {{position: [m], angle_deg: [deg]}}, "
                                  f"got {d!r}")
            data["max_base_discrepancy"] = (float(d["position"]), float(d["angle_deg"]))
        return _build(CellConfig, data, str(path))
    except HarvestQPError as err:
        message = str(err)
        raise ConfigError(message if message.startswith(str(path)) else f"{path}: {message}") from None
