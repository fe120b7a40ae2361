"""Roll of the camera about its optical axis that turns the cutter across the stem (beyond the paper).

The paper leaves the camera's roll about z_c free (its camera task is 5-D). The cutter's blade
closes along the camera's x axis, so a lower-priority task uses that freedom::

    d     = u - (u^T z_c) z_c                     (the stem direction u seen in the image plane)
    phi   = wrap(atan2((y_c x d)^T z_c, y_c^T d))  (turn of y_c onto d about z_c, in [-pi/2, pi/2))
    V_rol = [ 0 ; k_roll phi z_c ]

which drives y_c along the stem, hence x_c (the blade) across it. The stem is an undirected line,
so phi is wrapped to a half turn.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.references._checks import as_pose, as_position, as_positive_scalar
from harvest_qp.references._vec3 import cross, dot, norm, scale, sub

__all__ = ["roll_reference", "wrap_half_turn"]

#: Below this |d| (the stem along the optical axis) the roll is undefined and not commanded.
_MIN_PROJECTION = 1e-6


def wrap_half_turn(angle: float) -> float:
    """An angle between two undirected lines [rad], wrapped into [-pi/2, pi/2)."""
    return (float(angle) + math.pi / 2) % math.pi - math.pi / 2


def roll_reference(
    camera_pose: ArrayLike, direction: ArrayLike, *, k_roll: float, blade_y: ArrayLike | None = None
) -> tuple[NDArray[np.float64], float]:
    """(V_rol ``(6,)`` [m/s; rad/s] world frame, phi [rad]) for the stem ``direction`` u (world).

    ``blade_y``: the blade's own y axis (world) when the camera is not mounted square to it (a
    calibrated camera): it replaces y_c, projected onto the image plane (the roll is still about
    z_c). None: y_c, as in the robot description's mount.

    phi is NaN and V_rol zero where u is along the optical axis (|d| < 1e-6).
    """
    pose = as_pose(camera_pose, "camera_pose")
    u = as_position(direction, "direction").tolist()
    k_roll = as_positive_scalar(k_roll, "k_roll", allow_zero=True)
    (_, y0, z0, _), (_, y1, z1, _), (_, y2, z2, _) = pose[:3].tolist()
    y, z = (y0, y1, y2), (z0, z1, z2)
    if blade_y is not None:
        b = as_position(blade_y, "blade_y").tolist()
        y = sub(b, scale(dot(b, z), z))
        length = norm(y)
        if length < _MIN_PROJECTION:
            raise InvalidInputError(f"blade_y must not lie along the optical axis, got {b}")
        y = scale(1.0 / length, y)
    d = sub(u, scale(dot(u, z), z))
    if norm(d) < _MIN_PROJECTION:
        return np.zeros(6), math.nan
    angle = wrap_half_turn(math.atan2(dot(cross(y, d), z), dot(y, d)))
    return np.array((0.0, 0.0, 0.0, *scale(k_roll * angle, z))), angle
