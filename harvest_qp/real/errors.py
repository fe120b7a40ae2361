"""Errors of the field side (all rooted in :class:`~harvest_qp.exceptions.HarvestQPError`)."""

from __future__ import annotations

from harvest_qp.exceptions import HarvestQPError

__all__ = ["RobotConnectionError", "WatchdogError", "CameraError", "CalibrationError", "missing_package"]


class RobotConnectionError(HarvestQPError):
    """A UR5e cannot be reached or its connection was lost; the message names the address."""


class WatchdogError(HarvestQPError):
    """A watchdog check failed before a command: both arms were stopped; the message is the reason."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


class CameraError(HarvestQPError):
    """The RealSense camera cannot be opened or delivered unusable frames."""


class CalibrationError(HarvestQPError):
    """A calibration file is missing or malformed, or the views do not determine a transform."""


def missing_package(package: str, module: str) -> HarvestQPError:
    """The error for a hardware package that is not installed, with the exact fix."""
    return HarvestQPError(f"{module} needs the Python package {package!r}: pip install -e \".[robot]\" "
                          f"(or pip install {package})")
