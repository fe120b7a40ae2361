"""Wrist force/torque sensor of the grasping arm, and the stem-tension ground truth.

MuJoCo's ``force`` sensor at the ``ft_sensor`` site (the grasping arm's flange) gives the
force the wrist applies to the tool body, in the site frame. :class:`WristForceSensor`
turns that into what a calibrated F/T sensor reports after gravity compensation:

* rotated to the world frame;
* the tool's own weight removed (so it reads the force the tool applies to what it holds);
* minus the tare offset, set by :meth:`WristForceSensor.tare` at the current reading;
* plus optional white noise (seeded) and an optional first-order low-pass.

The tool's inertial force (mass times acceleration) is not removed, as on a real sensor.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
from numpy.typing import NDArray

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.validation import check_field_types

__all__ = ["ForceSensorConfig", "WristForceSensor", "site_force_world"]


@dataclass(frozen=True)
class ForceSensorConfig:
    """Wrist F/T sensor options.

    Attributes:
        noise_std: standard deviation of white noise on each force component [N].
        filter_time_constant: first-order low-pass time constant [s] (0: unfiltered).
        tare_samples: number of latest samples averaged by a tare (at 500 Hz, 25 = 50 ms).
    """

    noise_std: float = 0.0
    filter_time_constant: float = 0.0
    tare_samples: int = 25

    def __post_init__(self) -> None:
        check_field_types(self)  # text, None or a list never reaches the range checks
        for name in ("noise_std", "filter_time_constant"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise InvalidInputError(f"ForceSensorConfig.{name} must be finite and >= 0, got {value!r}")
        if isinstance(self.tare_samples, bool) or not isinstance(self.tare_samples, int) or self.tare_samples < 1:
            raise InvalidInputError(
                f"ForceSensorConfig.tare_samples must be an integer >= 1, got {self.tare_samples!r}"
            )


def site_force_world(model: mujoco.MjModel, data: mujoco.MjData, sensor_id: int, site_id: int) -> NDArray[np.float64]:
    """A MuJoCo ``force`` sensor's reading rotated from its site frame to the world [N].

    It is the force the parent body applies to the child body carrying the site.
    """
    adr = model.sensor_adr[sensor_id]
    return data.site_xmat[site_id].reshape(3, 3) @ data.sensordata[adr : adr + 3]


class WristForceSensor:
    """Gravity-compensated, tared, world-frame force at the grasping arm's wrist.

    Args:
        model: compiled scene model.
        sensor_id: id of the ``force`` sensor at the wrist site.
        site_id: id of that site.
        tool_mass: mass below the sensor whose weight is removed [kg].
        config: noise and filter options.
        seed: seed of the noise.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        sensor_id: int,
        site_id: int,
        tool_mass: float,
        config: ForceSensorConfig,
        *,
        seed: int = 0,
    ) -> None:
        self.model = model
        self.sensor_id = int(sensor_id)
        self.site_id = int(site_id)
        self.config = config
        # Weight of the tool as a world vector (gravity points down): removing it leaves the
        # force that the tool applies to the held object.
        self._tool_weight = tool_mass * np.asarray(model.opt.gravity, dtype=float)
        self._rng = np.random.default_rng([int(seed), 0xF0CE])
        self._offset = np.zeros(3)
        self._filtered: NDArray[np.float64] | None = None
        self._last = np.zeros(3)
        self._history = np.zeros((config.tare_samples, 3))
        self._count = 0
        self._views: tuple[mujoco.MjData, NDArray[np.float64], NDArray[np.float64]] | None = None

    def reset(self, *, seed: int | None = None) -> None:
        """Clear the tare offset and the filter; optionally reseed the noise."""
        if seed is not None:
            self._rng = np.random.default_rng([int(seed), 0xF0CE])
        self._offset = np.zeros(3)
        self._filtered = None
        self._last = np.zeros(3)
        self._history[:] = 0.0
        self._count = 0

    def raw(self, data: mujoco.MjData) -> NDArray[np.float64]:
        """Noise-free force the tool applies to what it holds [N, world], not tared."""
        views = self._views
        if views is None or views[0] is not data:
            # site_force_world's operands as live views of this data's arrays, made once (each
            # ``data.x`` builds a new view: ~1-3 us per tick with the caches the loop leaves).
            adr = int(self.model.sensor_adr[self.sensor_id])
            views = self._views = (data, data.site_xmat[self.site_id].reshape(3, 3), data.sensordata[adr : adr + 3])
        return views[1] @ views[2] + self._tool_weight

    def update(self, data: mujoco.MjData, dt: float) -> NDArray[np.float64]:
        """Take one sample (after a physics step of ``dt`` [s]) and return the reading [N, world]."""
        self.sample(data, dt)
        return self.reading()

    def sample(self, data: mujoco.MjData, dt: float) -> None:
        """Take one sample (after a physics step of ``dt`` [s]): :meth:`update` without the reading."""
        f = self.raw(data)
        if self.config.noise_std > 0:
            f = f + self._rng.normal(0.0, self.config.noise_std, 3)
        tau = self.config.filter_time_constant
        if tau > 0:
            if self._filtered is None:
                self._filtered = f
            else:
                alpha = dt / (tau + dt)
                self._filtered = self._filtered + alpha * (f - self._filtered)
            f = self._filtered
        self._last = f
        self._history[self._count % len(self._history)] = f
        self._count += 1

    def reading(self) -> NDArray[np.float64]:
        """Latest sample minus the tare offset [N, world]."""
        return self._last - self._offset

    def tare(self) -> None:
        """Zero the reading at the mean of the latest ``tare_samples`` samples (fewer right after a reset)."""
        n = min(self._count, len(self._history))
        self._offset = self._history[:n].mean(axis=0) if n else self._last.copy()
