"""Ground truth of the robot's contacts and of its clearance to the vine.

:class:`ContactMonitor` sorts MuJoCo's active contacts by kind and measures the smallest
true distance between the robot and the vine. It reads the simulation state only (a real
robot cannot measure either); :meth:`harvest_qp.sim.SimRobot.ground_truth` reports both.

Kinds of robot contact:

* ``arm_arm`` -- two arm or tool geoms (the other arm, or the same arm's own links);
* ``arm_vine`` -- an arm or tool geom and a vine geom (branch, cane, leaf, petiole, a
  cluster other than the held one);
* ``arm_stand`` -- an arm or tool geom and the pedestal the arms stand on;
* ``arm_floor`` -- an arm or tool geom and the floor.

The held stem and cluster never collide with the robot (the weld holds the cluster in
the gripper), so they are neither contacts nor part of ``min_vine_distance``.
"""

from __future__ import annotations

import mujoco
import numpy as np
from numba import njit
from numpy.typing import NDArray

__all__ = ["CONTACT_KINDS", "ContactMonitor"]

#: Contact kinds counted by :meth:`ContactMonitor.contact_counts`, in this order.
CONTACT_KINDS = ("arm_arm", "arm_vine", "arm_stand", "arm_floor")

_ARM, _STAND, _VINE, _FLOOR, _OTHER = 1, 2, 3, 4, 0


class ContactMonitor:
    """Contact counts by kind and the robot's true distance to the vine.

    Args:
        model: the compiled scene model.
        arm_geoms: geom ids of both arms and their tools.
        stand_geoms: geom ids of the pedestal.
        vine_geoms: geom ids of the vine the robot must not touch (not the held stem
            and cluster).
        floor_geoms: geom ids of the floor.
        max_distance: distances beyond this are reported as this [m] (MuJoCo's
            ``mj_geomDistance`` cut-off).
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        *,
        arm_geoms: NDArray[np.integer],
        stand_geoms: NDArray[np.integer],
        vine_geoms: NDArray[np.integer],
        floor_geoms: NDArray[np.integer],
        max_distance: float = 1.0,
    ) -> None:
        self.model = model
        self.kind = np.full(model.ngeom, _OTHER, dtype=np.int8)
        self.kind[np.asarray(arm_geoms, int)] = _ARM
        self.kind[np.asarray(stand_geoms, int)] = _STAND
        self.kind[np.asarray(vine_geoms, int)] = _VINE
        self.kind[np.asarray(floor_geoms, int)] = _FLOOR
        self.arm_geoms = np.asarray(arm_geoms, dtype=np.int64)
        self.vine_geoms = np.asarray(vine_geoms, dtype=np.int64)
        self.max_distance = float(max_distance)
        # Every geom as an enclosing capsule (local z half-length, radius): exact for spheres
        # and capsules, whose distances then need no further call; an ellipsoid with
        # semi-axes a >= b >= c lies inside the capsule along its a axis with radius b and
        # half-length a - b.
        self._arm_caps = _enclosing_capsules(model, self.arm_geoms)
        self._vine_caps = _enclosing_capsules(model, self.vine_geoms)
        self._fromto = np.zeros(6)
        exact = self._arm_caps[3][:, None] & self._vine_caps[3][None, :]
        self._exact_pairs = np.flatnonzero(exact.ravel())
        self._bounded_pairs = np.flatnonzero(~exact.ravel())
        self._radius_sum = self._arm_caps[2][:, None] + self._vine_caps[2][None, :]

    def contact_counts(self, data: mujoco.MjData) -> dict[str, int]:
        """Number of active contacts of each kind of :data:`CONTACT_KINDS` (penetrating or within margin)."""
        counts = dict.fromkeys(CONTACT_KINDS, 0)
        if data.ncon == 0:
            return counts
        g1 = self.kind[data.contact.geom1[: data.ncon]]
        g2 = self.kind[data.contact.geom2[: data.ncon]]
        lo, hi = np.minimum(g1, g2), np.maximum(g1, g2)
        arm = lo == _ARM
        counts["arm_arm"] = int(np.sum(arm & (hi == _ARM)))
        counts["arm_stand"] = int(np.sum(arm & (hi == _STAND)))
        counts["arm_vine"] = int(np.sum(arm & (hi == _VINE)))
        counts["arm_floor"] = int(np.sum(arm & (hi == _FLOOR)))
        return counts

    def min_vine_distance(self, data: mujoco.MjData) -> tuple[float, int, int]:
        """Smallest signed distance [m] between an arm geom and a vine geom, and that pair.

        Negative when they penetrate. A bounding-sphere lower bound orders the pairs and
        only pairs whose bound beats the best distance so far are measured exactly
        (``mujoco.mj_geomDistance``), a handful per call.

        Returns:
            (distance [m], arm geom id, vine geom id); (max_distance, -1, -1) when there is
            no vine or nothing is closer than ``max_distance``.
        """
        if self.vine_geoms.size == 0 or self.arm_geoms.size == 0:
            return self.max_distance, -1, -1
        pa, qa = _world_segments(data, self.arm_geoms, self._arm_caps)
        pv, qv = _world_segments(data, self.vine_geoms, self._vine_caps)
        bound = (_segment_distances(pa, qa, pv, qv) - self._radius_sum).ravel()
        nv = self.vine_geoms.size
        best, pair = self.max_distance, (-1, -1)
        if self._exact_pairs.size:
            # Capsule and sphere pairs: the enclosing capsules are the geoms, the bound is exact.
            exact = bound[self._exact_pairs]
            i = int(np.argmin(exact))
            if exact[i] < best:
                k = int(self._exact_pairs[i])
                best, pair = float(exact[i]), (int(self.arm_geoms[k // nv]), int(self.vine_geoms[k % nv]))
        if self._bounded_pairs.size:
            lower = bound[self._bounded_pairs]
            for i in np.flatnonzero(lower < best)[np.argsort(lower[lower < best])]:
                if lower[i] >= best:
                    break  # every remaining pair is at least this far apart
                k = int(self._bounded_pairs[i])
                ga, gv = int(self.arm_geoms[k // nv]), int(self.vine_geoms[k % nv])
                dist = mujoco.mj_geomDistance(self.model, data, ga, gv, best, self._fromto)
                if dist < best:
                    best, pair = float(dist), (ga, gv)
        return best, pair[0], pair[1]


def _enclosing_capsules(model: mujoco.MjModel, geoms: NDArray[np.int64]) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Per geom: local axis index, half-length [m], radius [m], and whether the capsule is the geom."""
    axis = np.full(geoms.size, 2, dtype=np.int64)
    half = np.zeros(geoms.size)
    radius = np.zeros(geoms.size)
    exact = np.zeros(geoms.size, dtype=bool)
    for i, g in enumerate(geoms):
        size, kind = model.geom_size[g], int(model.geom_type[g])
        if kind == mujoco.mjtGeom.mjGEOM_SPHERE:
            radius[i], exact[i] = size[0], True
        elif kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
            radius[i], half[i], exact[i] = size[0], size[1], True
        elif kind == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
            order = np.argsort(size)[::-1]
            axis[i] = order[0]
            radius[i] = size[order[1]]
            half[i] = size[order[0]] - size[order[1]]
        else:  # anything else: its bounding sphere
            radius[i] = model.geom_rbound[g]
    return axis, half, radius, exact


def _world_segments(
    data: mujoco.MjData, geoms: NDArray[np.int64], caps: tuple[NDArray, NDArray, NDArray, NDArray]
) -> tuple[NDArray, NDArray]:
    """World end points of the enclosing capsules of ``geoms``."""
    axis, half, _, _ = caps
    # Column `axis` of each geom's rotation matrix (row-major 9-vector).
    direction = data.geom_xmat[geoms[:, None], (3 * np.arange(3))[None, :] + axis[:, None]]
    centre = data.geom_xpos[geoms]
    offset = half[:, None] * direction
    return centre - offset, centre + offset


@njit(cache=True, inline="always")
def _dot(x0: float, x1: float, x2: float, y0: float, y1: float, y2: float) -> float:
    return x0 * y0 + x1 * y1 + x2 * y2


@njit(cache=True)
def _segment_distances(p1: NDArray, q1: NDArray, p2: NDArray, q2: NDArray) -> NDArray[np.float64]:
    """(n, m) distances between segments p1[i]-q1[i] and p2[j]-q2[j] (Ericson's clamped solution).

    Scalar arithmetic only: small-array temporaries made it 30x slower.
    """
    n, m = p1.shape[0], p2.shape[0]
    out = np.empty((n, m))
    eps = 1e-12
    for i in range(n):
        ux, uy, uz = q1[i, 0] - p1[i, 0], q1[i, 1] - p1[i, 1], q1[i, 2] - p1[i, 2]
        a = _dot(ux, uy, uz, ux, uy, uz)
        for j in range(m):
            vx, vy, vz = q2[j, 0] - p2[j, 0], q2[j, 1] - p2[j, 1], q2[j, 2] - p2[j, 2]
            rx, ry, rz = p1[i, 0] - p2[j, 0], p1[i, 1] - p2[j, 1], p1[i, 2] - p2[j, 2]
            e = _dot(vx, vy, vz, vx, vy, vz)
            f = _dot(vx, vy, vz, rx, ry, rz)
            if a <= eps and e <= eps:
                s, t = 0.0, 0.0
            elif a <= eps:
                s, t = 0.0, min(max(f / e, 0.0), 1.0)
            else:
                c = _dot(ux, uy, uz, rx, ry, rz)
                if e <= eps:
                    t, s = 0.0, min(max(-c / a, 0.0), 1.0)
                else:
                    b = _dot(ux, uy, uz, vx, vy, vz)
                    denom = a * e - b * b
                    s = min(max((b * f - c * e) / denom, 0.0), 1.0) if denom > eps else 0.0
                    t = (b * s + f) / e
                    if t < 0.0:
                        t, s = 0.0, min(max(-c / a, 0.0), 1.0)
                    elif t > 1.0:
                        t, s = 1.0, min(max((b - c) / a, 0.0), 1.0)
            gx, gy, gz = rx + s * ux - t * vx, ry + s * uy - t * vy, rz + s * uz - t * vz
            out[i, j] = np.sqrt(gx * gx + gy * gy + gz * gz)
    return out
