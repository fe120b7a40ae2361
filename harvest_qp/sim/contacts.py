"""Ground truth of the robot's contacts and of its clearance to the vine.

:class:`ContactMonitor` sorts MuJoCo's active contacts (``data.ncon``, ``data.contact``,
found by the physics step's own collision detection) by kind and measures the smallest
true distance between the robot and the vine. It reads the simulation state only (a real
robot cannot measure either); :meth:`harvest_qp.sim.SimRobot.ground_truth` reports both.

Kinds of robot contact:

* ``arm_arm`` -- two arm or tool geoms (the other arm, or the same arm's own links);
* ``arm_vine`` -- an arm or tool geom and a vine geom (branch, cane, leaf, petiole, a
  cluster other than the held one);
* ``arm_stand`` -- an arm or tool geom and the pedestal the arms stand on;
* ``arm_floor`` -- an arm or tool geom and the floor.

Kinds of contact of the held crop (the cluster in the gripper):

* ``crop_wood`` -- the held crop and the branch or cane;
* ``crop_leaf`` -- the held crop and a leaf, petiole or another cluster (soft: they yield).

The held stem and cluster never collide with the robot (the weld holds the cluster in
the gripper), so they are not part of ``min_vine_distance``.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
from numba import njit
from numpy.typing import NDArray

__all__ = ["CONTACT_KINDS", "ContactMonitor", "segment_distances"]

#: Contact kinds counted by :meth:`ContactMonitor.contact_counts`, in this order.
CONTACT_KINDS = ("arm_arm", "arm_vine", "arm_stand", "arm_floor", "crop_wood", "crop_leaf")

_ARM, _STAND, _VINE, _FLOOR, _CROP, _WOOD, _OTHER = 1, 2, 3, 4, 5, 6, 0


class ContactMonitor:
    """Contact counts by kind and the robot's true distance to the vine.

    Args:
        model: the compiled scene model.
        arm_geoms: geom ids of both arms and their tools.
        stand_geoms: geom ids of the pedestal.
        vine_geoms: geom ids of the vine the robot must not touch (not the held stem
            and cluster).
        floor_geoms: geom ids of the floor.
        wood_geoms: which of ``vine_geoms`` are wood (branch, cane).
        crop_geoms: geom ids of the held crop (berries, rachis).
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
        wood_geoms: NDArray[np.integer] = (),
        crop_geoms: NDArray[np.integer] = (),
        max_distance: float = 1.0,
    ) -> None:
        self.model = model
        self.kind = np.full(model.ngeom, _OTHER, dtype=np.int8)
        self.kind[np.asarray(arm_geoms, int)] = _ARM
        self.kind[np.asarray(stand_geoms, int)] = _STAND
        self.kind[np.asarray(vine_geoms, int)] = _VINE
        self.kind[np.asarray(floor_geoms, int)] = _FLOOR
        self.kind[np.asarray(wood_geoms, int)] = _WOOD
        self.kind[np.asarray(crop_geoms, int)] = _CROP
        self.arm_geoms = np.asarray(arm_geoms, dtype=np.int64)
        self.vine_geoms = np.asarray(vine_geoms, dtype=np.int64)
        self.max_distance = float(max_distance)
        # Every geom as an enclosing capsule (local axis, half-length, radius): exact for
        # spheres and capsules; an ellipsoid with semi-axes a >= b >= c lies inside the
        # capsule along its a axis with radius b and half-length a - b; any other geom
        # inside its bounding sphere.
        geoms = np.concatenate([self.arm_geoms, self.vine_geoms])
        self._geoms = geoms
        self._axis, self._half, self._radius, self._exact = _enclosing_capsules(model, geoms)
        self._candidates = np.zeros(self.arm_geoms.size * self.vine_geoms.size, dtype=np.int64)
        self._bounds = np.zeros(self.arm_geoms.size * self.vine_geoms.size)
        self._views: tuple[mujoco.MjData, NDArray[np.float64], NDArray[np.float64]] | None = None

    def contact_counts(self, data: mujoco.MjData) -> dict[str, int]:
        """Number of active contacts of each kind of :data:`CONTACT_KINDS` (penetrating or within margin)."""
        ncon = data.ncon
        if ncon == 0:
            return dict.fromkeys(CONTACT_KINDS, 0)
        contact = data.contact
        counts = _count_kinds(self.kind, contact.geom1, contact.geom2, ncon)
        return dict(zip(CONTACT_KINDS, counts))

    def min_vine_distance(self, data: mujoco.MjData) -> tuple[float, int, int]:
        """Smallest signed distance [m] between an arm geom and a vine geom, and that pair.

        Negative when they penetrate. The enclosing capsules give every pair a lower bound
        of its distance, exact for two spheres or capsules (:func:`_capsule_search`); the
        other pairs whose bound beats the best exact distance are measured by MuJoCo
        (``mujoco.mj_geomDistance``), nearest bound first, until the bound of the next one
        cannot beat the best any more.

        Returns:
            (distance [m], arm geom id, vine geom id); (max_distance, -1, -1) when there is
            no vine or nothing is closer than ``max_distance``.
        """
        na, nv = self.arm_geoms.size, self.vine_geoms.size
        if na == 0 or nv == 0:
            return self.max_distance, -1, -1
        views = self._views
        if views is None or views[0] is not data:
            views = self._views = (data, data.geom_xpos, data.geom_xmat)  # live views, made once
        best, best_k, n = _capsule_search(
            views[1], views[2], self._geoms, self._axis, self._half, self._radius, self._exact, na,
            self.max_distance, self._bounds, self._candidates,
        )  # fmt: skip
        arm = vine = -1
        if best_k >= 0:
            arm, vine = int(self.arm_geoms[best_k // nv]), int(self.vine_geoms[best_k % nv])
        for k in self._candidates[:n].tolist():
            if self._bounds[k] >= best:
                break  # every remaining pair is at least this far apart
            ga, gv = int(self.arm_geoms[k // nv]), int(self.vine_geoms[k % nv])
            dist = mujoco.mj_geomDistance(self.model, data, ga, gv, best, None)
            if dist < best:
                best, arm, vine = float(dist), ga, gv
        return float(best), arm, vine


@njit(cache=True)
def _capsule_search(xpos, xmat, geoms, axis, half, radius, exact, na, max_distance, bounds, candidates):
    """Enclosing-capsule distances of every arm-vine pair (pair k = arm k // nv, vine k % nv).

    ``geoms`` holds the ``na`` arm geoms, then the vine geoms; ``axis``, ``half``,
    ``radius``, ``exact`` describe their capsules (see :func:`_enclosing_capsules`).
    Writes a lower bound of every pair's true distance to ``bounds``: its capsule distance
    where that can matter, else its bounding spheres' gap. Returns the smallest distance
    over the exact pairs (both geoms their own capsules) if below ``max_distance`` (else
    ``max_distance``), its pair index (-1: none), and the number of inexact pairs whose
    bound is below it, their indices written to ``candidates`` nearest bound first.
    """
    ng = geoms.shape[0]
    nv = ng - na
    ends = np.empty((ng, 6))
    for i in range(ng):
        g, ax, h = geoms[i], axis[i], half[i]
        for c in range(3):
            off = h * xmat[g, 3 * c + ax]
            ends[i, c] = xpos[g, c] - off
            ends[i, 3 + c] = xpos[g, c] + off
    # First the bounding spheres: a lower bound of every pair's capsule distance (centre
    # distance minus both half-lengths and radii) and, for the exact pairs, an upper bound
    # (the centres lie on the segments: centre distance minus both radii).
    upper = max_distance
    for i in range(na):
        for m in range(nv):
            j = na + m
            cx = xpos[geoms[i], 0] - xpos[geoms[j], 0]
            cy = xpos[geoms[i], 1] - xpos[geoms[j], 1]
            cz = xpos[geoms[i], 2] - xpos[geoms[j], 2]
            centres = math.sqrt(cx * cx + cy * cy + cz * cz)
            bounds[i * nv + m] = centres - half[i] - radius[i] - half[j] - radius[j]
            if exact[i] and exact[j]:
                upper = min(upper, centres - radius[i] - radius[j])
    # Then the capsule distance of the pairs whose lower bound can beat that (a few dozen):
    # a pair left out can be neither the best nor a candidate.
    best = max_distance
    best_k = -1
    for i in range(na):
        for m in range(nv):
            k = i * nv + m
            if bounds[k] >= upper:
                continue
            j = na + m
            d = _clamped_distance(
                ends[i, 3] - ends[i, 0], ends[i, 4] - ends[i, 1], ends[i, 5] - ends[i, 2],
                ends[j, 3] - ends[j, 0], ends[j, 4] - ends[j, 1], ends[j, 5] - ends[j, 2],
                ends[i, 0] - ends[j, 0], ends[i, 1] - ends[j, 1], ends[i, 2] - ends[j, 2],
            ) - radius[i] - radius[j]  # fmt: skip
            bounds[k] = d
            if exact[i] and exact[j] and d < best:
                best, best_k = d, k
    n = 0
    for k in range(na * nv):
        if not (exact[k // nv] and exact[na + k % nv]) and bounds[k] < best:
            candidates[n] = k
            n += 1
    # Nearest bound first (insertion sort: a handful).
    for a in range(1, n):
        k = candidates[a]
        b = a - 1
        while b >= 0 and bounds[candidates[b]] > bounds[k]:
            candidates[b + 1] = candidates[b]
            b -= 1
        candidates[b + 1] = k
    return best, best_k, n


@njit(cache=True)
def _count_kinds(kind, geom1, geom2, ncon):
    """Contacts among the first ``ncon`` of each kind of :data:`CONTACT_KINDS`."""
    arm_arm = arm_vine = arm_stand = arm_floor = crop_wood = crop_leaf = 0
    for c in range(ncon):
        k1, k2 = kind[geom1[c]], kind[geom2[c]]
        lo, hi = min(k1, k2), max(k1, k2)
        if lo == _ARM:
            if hi == _ARM:
                arm_arm += 1
            elif hi == _STAND:
                arm_stand += 1
            elif hi == _VINE or hi == _WOOD:
                arm_vine += 1
            elif hi == _FLOOR:
                arm_floor += 1
        elif lo == _CROP and hi == _WOOD:
            crop_wood += 1
        elif lo == _VINE and hi == _CROP:
            crop_leaf += 1
    return arm_arm, arm_vine, arm_stand, arm_floor, crop_wood, crop_leaf


def _enclosing_capsules(model: mujoco.MjModel, geoms: NDArray[np.int64]) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Per geom: local axis index, half-length [m], radius [m], and whether the capsule is the geom."""
    axis = np.full(geoms.size, 2, dtype=np.int64)
    half = np.zeros(geoms.size)
    radius = np.zeros(geoms.size)
    exact = np.zeros(geoms.size, dtype=np.bool_)
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


@njit(cache=True, inline="always")
def _dot(x0: float, x1: float, x2: float, y0: float, y1: float, y2: float) -> float:
    return x0 * y0 + x1 * y1 + x2 * y2


@njit(cache=True)
def _clamped_distance(ux, uy, uz, vx, vy, vz, rx, ry, rz):
    """Distance [m] of the segments p1 + s u and p2 + t v, s, t in [0, 1], with r = p1 - p2
    (Ericson's clamped solution; a segment shorter than ~1e-6 m is a point)."""
    eps = 1e-12
    a = _dot(ux, uy, uz, ux, uy, uz)
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
    return math.sqrt(gx * gx + gy * gy + gz * gz)


@njit(cache=True)
def segment_distances(p1: NDArray, q1: NDArray, p2: NDArray, q2: NDArray) -> NDArray[np.float64]:
    """(n, m) distances [m] between the segments p1[i]-q1[i] and p2[j]-q2[j]."""
    n, m = p1.shape[0], p2.shape[0]
    out = np.empty((n, m))
    for i in range(n):
        for j in range(m):
            out[i, j] = _clamped_distance(
                q1[i, 0] - p1[i, 0], q1[i, 1] - p1[i, 1], q1[i, 2] - p1[i, 2],
                q2[j, 0] - p2[j, 0], q2[j, 1] - p2[j, 1], q2[j, 2] - p2[j, 2],
                p1[i, 0] - p2[j, 0], p1[i, 1] - p2[j, 1], p1[i, 2] - p2[j, 2],
            )  # fmt: skip
    return out
