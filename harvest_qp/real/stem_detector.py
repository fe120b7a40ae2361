"""Stem detectors: which pixels of a colour image are the crop's stem (the paper's set S).

A detector is any callable ``detector(rgb, depth) -> mask``: ``rgb`` the (H, W, 3) uint8 colour
image aligned with ``depth``, the (H, W) float64 depth [m] (0 where invalid), and ``mask`` an
(H, W) bool array, True on stem pixels. :class:`RedThreshold` is the default: the paper's stem
is painted red, so a hue/saturation/value window finds it. A learned detector plugs in the same
way: name it in the cell file as ``module:attribute`` (:func:`load_detector`).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from harvest_qp.exceptions import ConfigError, InvalidInputError

__all__ = ["StemDetector", "RedThreshold", "hsv", "load_detector"]

#: ``detector(rgb (H, W, 3) uint8, depth (H, W) [m]) -> (H, W) bool``.
StemDetector = Callable[[NDArray[np.uint8], NDArray[np.float64]], NDArray[np.bool_]]


def hsv(rgb: NDArray[np.uint8]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Hue [deg, 0..360), saturation [0..1] and value [0..1] of an (..., 3) uint8 RGB image."""
    x = np.asarray(rgb, dtype=np.float64) / 255.0
    r, g, b = x[..., 0], x[..., 1], x[..., 2]
    v = x.max(axis=-1)
    c = v - x.min(axis=-1)
    s = np.divide(c, v, out=np.zeros_like(v), where=v > 0)
    safe = np.where(c > 0, c, 1.0)
    h = np.where(v == r, ((g - b) / safe) % 6.0, np.where(v == g, (b - r) / safe + 2.0, (r - g) / safe + 4.0))
    return np.where(c > 0, 60.0 * h, 0.0) % 360.0, s, v


@dataclass(frozen=True)
class RedThreshold:
    """Stem = red pixels: hue within ``hue_width`` [deg] of red, saturation and value high enough.

    The defaults take the paper's red stem (and the lab's, RGB 217/20/20) and leave out green
    leaves, brown wood (hue ~30 deg) and purple berries (hue ~280 deg). Tune them on a recorded
    frame of the real vine under its light (docs/real_robots.md).
    """

    hue_width: float = 20.0
    min_saturation: float = 0.5
    min_value: float = 0.25

    def __post_init__(self) -> None:
        for name, low, high in (("hue_width", 0.0, 180.0), ("min_saturation", 0.0, 1.0), ("min_value", 0.0, 1.0)):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not low <= value <= high:
                raise InvalidInputError(f"RedThreshold.{name} must be a number in [{low}, {high}], got {value!r}")

    def __call__(self, rgb: NDArray[np.uint8], depth: NDArray[np.float64]) -> NDArray[np.bool_]:
        h, s, v = hsv(rgb)
        near_red = np.minimum(h, 360.0 - h) <= self.hue_width
        return near_red & (s >= self.min_saturation) & (v >= self.min_value)


def load_detector(spec: str | dict | None) -> StemDetector:
    """The detector a cell file names: None or ``"red"`` (default :class:`RedThreshold`), a mapping
    ``{"red": {hue_width: ...}}``, or ``"package.module:name"`` (a callable, or a class built with no
    arguments)."""
    if spec is None or spec == "red":
        return RedThreshold()
    if isinstance(spec, dict) and set(spec) == {"red"}:
        try:
            return RedThreshold(**(spec["red"] or {}))
        except TypeError as err:
            raise ConfigError(f"camera.stem_detector.red: {err}") from None
    if isinstance(spec, str) and ":" in spec:
        module_name, _, attribute = spec.partition(":")
        try:
            target = getattr(importlib.import_module(module_name), attribute)
        except (ImportError, AttributeError) as err:
            raise ConfigError(f"camera.stem_detector: cannot load {spec!r}: {err}") from None
        detector = target() if isinstance(target, type) else target
        if not callable(detector):
            raise ConfigError(f"camera.stem_detector: {spec!r} is not callable")
        return detector
    raise ConfigError(f"camera.stem_detector must be 'red', {{red: {{...}}}} or 'module:name'; got {spec!r}")
