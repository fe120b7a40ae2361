"""ROI reaching with centering, V_cr (``subsec:rr_control_signal``).

``eq:control_signal_rr_world``::

    V_cr = [ k_cp max(0, f(e_pc)) e_pc ;  k_co theta k ],   f(x) = x^T x - r^2,  e_pc = p_r - p_c

with theta and k of ``eq:ktheta_world``, the angle and axis of the minimum rotation taking the
camera's optical axis z_c onto e_pc.  The ROI centre p_r goes through a first-order filter
(the paper's "smoothed by a filter"), so a new ROI target (for example the stem base replacing
the grape) never makes V_cr jump.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.references._checks import as_pose, as_position, as_positive_scalar, as_time_step
from harvest_qp.references._vec3 import add, dot, rotation_between, scale, sub

__all__ = ["ReachingCentering", "minimum_rotation"]

def minimum_rotation(z_axis: ArrayLike, direction: ArrayLike) -> tuple[float, NDArray[np.float64]]:
    """theta [rad] and unit axis k of ``eq:ktheta_world``: the minimum rotation taking ``z_axis``
    onto ``direction``.

    theta = atan2(|z x e|, z . e) equals the paper's acos(z^T e / |e|) but keeps its accuracy
    near 0 (acos loses half the digits there).  theta lies in [0, pi]: the paper states
    [0, pi/2], which holds only while the ROI is in front of the camera.  Where k is undefined
    (theta = 0, or e = 0) k is returned as zeros so that theta k = 0 without NaN; at theta = pi
    any axis normal to z turns it, and the camera's own x-like axis z x (1, 0, 0) (or
    z x (0, 1, 0)) is used.
    """
    z = as_position(z_axis, "z_axis").tolist()
    e = as_position(direction, "direction").tolist()
    theta, axis = rotation_between(z, e)
    return theta, np.array(axis)


class ReachingCentering:
    """Reaching-with-centering reference V_cr of the camera arm (``eq:control_signal_rr_world``).

    Args:
        radius: r, radius of the ROI sphere [m] (0.35 in Section ``sec:exper``).
        k_cp: translational gain k_cp [1/(m^2 s)] (1 in ``sec:exper``).
        k_co: rotational gain k_co [1/s] (1 in ``sec:exper``).
        roi_time_constant: time constant of the first-order filter on p_r [s].  Not a paper
            value: the paper only says p_r is "smoothed by a filter".

    Attributes:
        roi_centre: filtered p_r used by the law [m] (``None`` until the first target).
        theta: theta of the last :meth:`update` [rad].
        distance: |p_r - p_c| of the last :meth:`update` [m].
    """

    def __init__(
        self, *, radius: float = 0.35, k_cp: float = 1.0, k_co: float = 1.0, roi_time_constant: float = 0.5
    ) -> None:
        self.radius = as_positive_scalar(radius, "radius")
        self.k_cp = as_positive_scalar(k_cp, "k_cp")
        self.k_co = as_positive_scalar(k_co, "k_co")
        self.roi_time_constant = as_positive_scalar(roi_time_constant, "roi_time_constant", allow_zero=True)
        self.roi_centre: NDArray[np.float64] | None = None
        self._roi_target: NDArray[np.float64] | None = None
        self.theta = 0.0
        self.distance = math.nan

    def reset(self, roi_centre: ArrayLike | None = None) -> None:
        """Forget the filter state; with ``roi_centre`` [m] the filter starts (jumps) there."""
        centre = None if roi_centre is None else as_position(roi_centre, "roi_centre")
        self.roi_centre = centre
        self._roi_target = None if centre is None else centre.copy()
        self.theta = 0.0
        self.distance = math.nan

    def set_roi_centre(self, target: ArrayLike) -> None:
        """New target for p_r [m]; the filtered :attr:`roi_centre` moves to it over the next
        updates.  The very first target (after construction or ``reset()``) is taken at once:
        there is nothing to be continuous with."""
        target = as_position(target, "target")
        self._roi_target = target
        if self.roi_centre is None:
            self.roi_centre = target.copy()

    @property
    def roi_target(self) -> NDArray[np.float64] | None:
        """The unfiltered p_r target [m] (``None`` until set)."""
        return None if self._roi_target is None else self._roi_target.copy()

    def update(self, camera_pose: ArrayLike, dt: float) -> NDArray[np.float64]:
        """Advance the p_r filter by ``dt`` [s] and return V_cr ``(6,)`` [m/s; rad/s], world frame.

        The filter is the exact discretisation of tau dp_r/dt = p_target - p_r:
        p_r += (1 - exp(-dt / tau)) (p_target - p_r), so p_r moves continuously (by at most
        that fraction of the remaining gap per update) whatever the target does.

        Raises:
            InvalidInputError: no ROI centre set yet, a bad pose, or dt <= 0.
        """
        pose = as_pose(camera_pose, "camera_pose")
        dt = as_time_step(dt)
        if self.roi_centre is None or self._roi_target is None:
            raise InvalidInputError("ReachingCentering.update needs an ROI centre: call set_roi_centre(p_r) first")
        if self.roi_time_constant == 0.0:
            self.roi_centre = self._roi_target.copy()
        else:
            fraction = -math.expm1(-dt / self.roi_time_constant)
            p_r = self.roi_centre.tolist()
            self.roi_centre = np.array(add(p_r, scale(fraction, sub(self._roi_target.tolist(), p_r))))
        return self._velocity(pose, self.roi_centre)

    def velocity(self, camera_pose: ArrayLike, roi_centre: ArrayLike) -> NDArray[np.float64]:
        """V_cr of ``eq:control_signal_rr_world`` for a given p_r [m], without touching the filter."""
        return self._velocity(as_pose(camera_pose, "camera_pose"), as_position(roi_centre, "roi_centre"))

    def _velocity(self, pose: NDArray[np.float64], p_r: NDArray[np.float64]) -> NDArray[np.float64]:
        (_, _, z0, c0), (_, _, z1, c1), (_, _, z2, c2) = pose[:3].tolist()
        e_pc = sub(p_r.tolist(), (c0, c1, c2))
        squared = dot(e_pc, e_pc)
        self.distance = math.sqrt(squared)
        self.theta, axis = rotation_between((z0, z1, z2), e_pc)
        linear = scale(self.k_cp * max(0.0, squared - self.radius**2), e_pc)
        return np.array((*linear, *scale(self.k_co * self.theta, axis)))
