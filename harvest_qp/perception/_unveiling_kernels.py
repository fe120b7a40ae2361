"""Compiled (numba) kernel of :func:`harvest_qp.perception.unveiling.ray_obstacle_pairs`: the obstacle cull.

The cull is the same test as the vectorised ``_candidate_obstacles_numpy`` (kept as its
oracle), in one pass over the cloud without its numpy temporaries (measured on the paper
episode at 848x480: 38,000 obstacle points, 1.8 ms -> ~0.2 ms per frame). Its dot products
are summed in a fixed order, so their last bits may differ from numpy's BLAS; the cull is
conservative by a relative slack of 1e-9 (``ray_obstacle_pairs``), so a point whose
decision such a difference could flip lies farther than the reach from every ray and is
never a pair either way.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def candidate_obstacles(
    obstacles, camera, axis, camera_along_axis, max_depth, cos_half_angle, sin_half_angle, reach, max_squared_range,
    out_index, out_offsets,
):
    """Obstacles that may lie within ``reach`` [m] of a ray of the cone (apex ``camera``, unit
    ``axis``, half-angle by its cos / sin) whose depth along the axis is within
    ``(-reach, max_depth)`` and whose squared range from the camera is below
    ``max_squared_range``; their indices (ascending) and offsets ``p_o - p_c`` [m] are
    written to ``out_index`` / ``out_offsets``; returns how many.
    """
    n = 0
    reach2 = reach * reach
    sin_reach = sin_half_angle * reach
    for i in range(obstacles.shape[0]):
        x, y, z = obstacles[i, 0], obstacles[i, 1], obstacles[i, 2]
        depth = x * axis[0] + y * axis[1] + z * axis[2] - camera_along_axis
        if not (depth > -reach and depth < max_depth):
            continue
        ox, oy, oz = x - camera[0], y - camera[1], z - camera[2]
        squared = ox * ox + oy * oy + oz * oz
        if not squared < max_squared_range:
            continue
        # Within reach of the camera end of every ray, or inside the widened cone.
        if not squared < reach2:
            slant = np.sqrt(max(squared - reach2, 0.0))
            if not depth > cos_half_angle * slant - sin_reach:
                continue
        out_index[n] = i
        out_offsets[n, 0] = ox
        out_offsets[n, 1] = oy
        out_offsets[n, 2] = oz
        n += 1
    return n
