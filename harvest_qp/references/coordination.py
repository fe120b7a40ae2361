"""Bimanual coordination (``subsec:biman_coord``): the feed-forward of ``eq:final_vc`` and the
approach -> bimanual switch thresholds.

``eq:final_vc`` as printed::

    V_c' = V_c + [ v_gt ;  S(p_c - p_sb) v_gt ]

The angular term has units m^2/s as printed (S(.) is in m, v_gt in m/s), not rad/s.  Its
intent is to keep the stem centred while the camera translates with v_gt: with
e = p_sb - p_c and de/dt = -v_gt (p_sb is static), the bearing e/|e| stays on z_c exactly
when omega = (p_c - p_sb) x v_gt / |p_c - p_sb|^2, the paper's term divided by
|p_c - p_sb|^2.  :class:`GraspFeedForward` uses that exact bearing rate by default
(``normalise=True``); ``normalise=False`` gives the printed term.  At the paper's
|p_c - p_sb| ~ r = 0.35 m the printed term is 1/0.35^2 ~ 8x smaller; the lab measurements showed no
difference in end theta (0.41-0.46 deg either way, |omega| <= 0.002 rad/s), so the choice is
about units, not about a measured effect.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.references._checks import as_position, as_positive_scalar
from harvest_qp.references._vec3 import cross, dot, scale, sub

__all__ = ["GraspFeedForward", "switch_ready"]


class GraspFeedForward:
    """The term added to V_c in ``eq:final_vc``: [v_gt; omega] with omega the bearing rate.

    Args:
        normalise: divide the paper's S(p_c - p_sb) v_gt by |p_c - p_sb|^2 (rad/s, the exact
            rate that keeps p_sb's bearing fixed; default) or not (the printed term, m^2/s).
    """

    def __init__(self, *, normalise: bool = True) -> None:
        self.normalise = bool(normalise)

    def __call__(self, v_gt: ArrayLike, camera_position: ArrayLike, stem_base: ArrayLike) -> NDArray[np.float64]:
        """``(6,)`` [m/s; rad/s] from v_gt [m/s], p_c [m] and p_sb [m].

        With ``normalise`` and p_c = p_sb (no bearing defined) the angular part is zero.
        """
        v = as_position(v_gt, "v_gt").tolist()
        lever = sub(as_position(camera_position, "camera_position").tolist(),
                    as_position(stem_base, "stem_base").tolist())
        angular = cross(lever, v)  # S(p_c - p_sb) v_gt
        if self.normalise:
            squared = dot(lever, lever)
            angular = scale(1.0 / squared, angular) if squared > 0.0 else (0.0, 0.0, 0.0)
        return np.array((*v, *angular))


def switch_ready(
    distance: float,
    radius: float,
    linear_speed: float,
    angular_speed: float,
    *,
    distance_factor: float = 1.05,
    max_linear: float = 0.01,
    max_angular: float = 0.025,
) -> bool:
    """Whether the approach may switch to the bimanual phase (``subsec:biman_coord``).

    True when the camera is within ``distance_factor`` x ``radius`` of the ROI centre
    (``distance`` [m]) and its tip moves slower than ``max_linear`` [m/s] and ``max_angular``
    [rad/s] (Section ``sec:exper``: 1.05 r, 0.01 m/s, 0.025 rad/s).  Which speed is passed is
    the caller's choice (lab measurements: the camera's free roll alone moves at ~0.045 rad/s, so pass
    the angular speed without the roll about z_c if that roll is left free).
    """
    distance = as_positive_scalar(distance, "distance", allow_zero=True)
    radius = as_positive_scalar(radius, "radius")
    linear_speed = as_positive_scalar(linear_speed, "linear_speed", allow_zero=True)
    angular_speed = as_positive_scalar(angular_speed, "angular_speed", allow_zero=True)
    distance_factor = as_positive_scalar(distance_factor, "distance_factor")
    max_linear = as_positive_scalar(max_linear, "max_linear")
    max_angular = as_positive_scalar(max_angular, "max_angular")
    return distance <= distance_factor * radius and linear_speed < max_linear and angular_speed < max_angular
