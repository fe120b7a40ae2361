"""Keep-out term of the camera arm (beyond the paper): an outward speed near the ROI centre.

::

    V_ko = [ k_ko (d_min - d) (p_c - p_r) / d ; 0 ]   for 0 < d < d_min,   d = |p_c - p_r|
    V_ko = 0                                          otherwise

Inside the ROI sphere V_cr's translation (``eq:control_signal_rr_world``) is zero, so nothing in
the paper's laws stops the camera drifting inwards while V_cu (``eq:v_c2``) acts (measured: from
0.43 m to 0.05 m from p_sb on the default scene without occluder, colliding with the vine and
blind below the camera's 0.1 m minimum depth). The controller adds V_ko to V_cr + V_cu.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.references._checks import as_position, as_positive_scalar
from harvest_qp.references._vec3 import norm, scale, sub

__all__ = ["keep_out_velocity"]


def keep_out_velocity(
    camera_position: ArrayLike, roi_centre: ArrayLike, *, min_distance: float, gain: float
) -> NDArray[np.float64]:
    """V_ko ``(6,)`` [m/s; rad/s], world frame, from p_c and p_r [m].

    Args:
        camera_position: p_c [m].
        roi_centre: p_r [m] (the reaching law's filtered ROI centre).
        min_distance: d_min [m]; 0 turns the term off.
        gain: k_ko [1/s].

    Zero when d >= d_min, and at d <= 1e-9 m (no outward direction defined).
    """
    p_c = as_position(camera_position, "camera_position").tolist()
    offset = sub(p_c, as_position(roi_centre, "roi_centre").tolist())
    min_distance = as_positive_scalar(min_distance, "min_distance", allow_zero=True)
    gain = as_positive_scalar(gain, "gain", allow_zero=True)
    distance = norm(offset)
    if not 1e-9 < distance < min_distance:
        return np.zeros(6)
    return np.array((*scale(gain * (min_distance - distance) / distance, offset), 0.0, 0.0, 0.0))
