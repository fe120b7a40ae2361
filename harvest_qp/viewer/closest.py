"""Witness points of a collision row, for the viewer's "closest pair" line.

The QP reports its active collision rows by name and distance (``Command.collision_pairs``:
``("cam_cutter", "grasp_gripper", d)`` or ``("cam_forearm", "cell[45,18,118]", d)`` for a
cell of the obstacle map). The viewer needs the two points to draw; this recomputes them
from the joint positions with pinocchio and the robot description's capsules (the closest
points of two segments by the collision kernels' ``segment_distance``). It runs on the
control thread of ``harvest-qp run --viewer``, so it places only the two frames it needs
(no Jacobians).
"""

from __future__ import annotations

import re

import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike, NDArray

from harvest_qp.collision.kernels import segment_distance
from harvest_qp.exceptions import InvalidInputError

__all__ = ["ClosestPairLocator"]

_CELL = re.compile(r"cell\[(-?\d+),(-?\d+),(-?\d+)\]")


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
        configuration = Configuration.dual_ur5e()
        self._model, self._data = configuration.model, configuration.data
        self._frame_ids = {body.name: configuration.frame_id(body.link) for body in desc.collision_bodies()}
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
        pose = pin.updateFramePlacement(self._model, self._data, self._frame_ids[name])
        R, p = pose.rotation, pose.translation
        cap = body.capsule
        return R @ np.asarray(cap.p0) + p, R @ np.asarray(cap.p1) + p, float(cap.radius)

    def points(self, q: ArrayLike, name_a: str, name_b: str) -> NDArray[np.float64]:
        """``(2, 3)``: the point on ``name_a``'s surface closest to ``name_b``'s, and that one [m]."""
        pin.forwardKinematics(self._model, self._data, np.asarray(q, dtype=float))
        a0, a1, ra = self._segment(name_a)
        b0, b1, rb = self._segment(name_b)
        _, s, t = segment_distance(*a0, *a1, *b0, *b1)
        pa, pb = a0 + s * (a1 - a0), b0 + t * (b1 - b0)
        gap = pb - pa
        norm = float(np.linalg.norm(gap))
        n = gap / norm if norm > 1e-12 else np.zeros(3)
        return np.stack([pa + ra * n, pb - rb * n])
