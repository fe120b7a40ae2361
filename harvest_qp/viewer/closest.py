"""Witness points of a collision row, for the viewer's "closest pair" line.

The QP reports its active collision rows by name and distance (``Command.collision_pairs``:
``("cam_cutter", "grasp_gripper", d)`` or ``("cam_forearm", "cell[45,18,118]", d)`` for a
cell of the obstacle map). The viewer needs the two points to draw; this recomputes them
from the joint positions with pinocchio and the robot description's capsules, independently
of the compiled collision kernels (the viewer only observes).
"""

from __future__ import annotations

import re

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import InvalidInputError

__all__ = ["ClosestPairLocator", "segment_closest_points"]

_CELL = re.compile(r"cell\[(-?\d+),(-?\d+),(-?\d+)\]")


def segment_closest_points(
    p0: NDArray[np.float64], p1: NDArray[np.float64], q0: NDArray[np.float64], q1: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Closest points of segments p0-p1 and q0-q1 (either may be a point) [m].

    Ericson, *Real-Time Collision Detection*, 5.1.9, written with numpy.
    """
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a, e, f = d1 @ d1, d2 @ d2, d2 @ r
    eps = 1e-18
    if a <= eps and e <= eps:
        return p0.copy(), q0.copy()
    if a <= eps:
        s, t = 0.0, float(np.clip(f / e, 0.0, 1.0))
    else:
        c = d1 @ r
        if e <= eps:
            s, t = float(np.clip(-c / a, 0.0, 1.0)), 0.0
        else:
            b = d1 @ d2
            denom = a * e - b * b
            s = float(np.clip((b * f - c * e) / denom, 0.0, 1.0)) if denom > eps else 0.0
            t = (b * s + f) / e
            if t < 0.0:
                s, t = float(np.clip(-c / a, 0.0, 1.0)), 0.0
            elif t > 1.0:
                s, t = float(np.clip((b - c) / a, 0.0, 1.0)), 1.0
    return p0 + s * d1, q0 + t * d2


class ClosestPairLocator:
    """World witness points [m] of a named collision pair at joint positions ``q``.

    Args:
        cell_resolution: edge of the obstacle map's cells [m] (``obstacle_map.resolution``);
            a cell's point is its centre.
    """

    def __init__(self, *, cell_resolution: float = 0.01) -> None:
        from harvest_qp.configuration import Configuration
        from harvest_qp.robot import description as desc

        if not (isinstance(cell_resolution, (int, float)) and np.isfinite(cell_resolution) and cell_resolution > 0):
            raise InvalidInputError(f"cell_resolution must be a number of metres > 0, got {cell_resolution!r}")
        self.cell_resolution = float(cell_resolution)
        self._configuration = Configuration.dual_ur5e()
        self._bodies = {body.name: body for body in desc.collision_bodies()}

    def _segment(self, name: str) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
        match = _CELL.fullmatch(name)
        if match:
            centre = (np.array([int(k) for k in match.groups()], dtype=float) + 0.5) * self.cell_resolution
            return centre, centre, 0.0
        body = self._bodies.get(name)
        if body is None:
            raise InvalidInputError(f"unknown collision body {name!r}; expected a capsule of the robot "
                                    f"description ({sorted(self._bodies)}) or 'cell[i,j,k]'")
        pose = self._configuration.frame_pose(body.link)
        R, p = pose.rotation, pose.translation
        cap = body.capsule
        return R @ np.asarray(cap.p0) + p, R @ np.asarray(cap.p1) + p, float(cap.radius)

    def points(self, q: ArrayLike, name_a: str, name_b: str) -> NDArray[np.float64]:
        """``(2, 3)``: the point on ``name_a``'s surface closest to ``name_b``'s, and that one [m]."""
        self._configuration.update(np.asarray(q, dtype=float))
        a0, a1, ra = self._segment(name_a)
        b0, b1, rb = self._segment(name_b)
        pa, pb = segment_closest_points(a0, a1, b0, b1)
        gap = pb - pa
        norm = float(np.linalg.norm(gap))
        n = gap / norm if norm > 1e-12 else np.zeros(3)
        return np.stack([pa + ra * n, pb - rb * n])
