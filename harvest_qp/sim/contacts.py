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

import ctypes
import math

import mujoco
import numpy as np
from numba import njit
from numpy.typing import NDArray

__all__ = ["CONTACT_KINDS", "ContactCertificate", "ContactMonitor"]

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
        self._radius_sum = np.ascontiguousarray(self._arm_caps[2][:, None] + self._vine_caps[2][None, :])
        self._sizes = (self.arm_geoms.size, self.vine_geoms.size)
        self._pack_near()
        # The pair found by the last call: its distance now bounds this call's result.
        self._hint = -1
        # Plain-int copies for the per-call Python loop (numpy scalar indexing costs more).
        self._arm_list = self.arm_geoms.tolist()
        self._vine_list = self.vine_geoms.tolist()
        self._bounded_list = self._bounded_pairs.tolist()
        self._bound_data: mujoco.MjData | None = None

    def _pack_near(self) -> None:
        """Operands and state of :func:`_vine_near_search` in one int and one float buffer.

        ``_near_ints = [valid, n_near, geoms (ng), axes (ng), bounded index per pair (npairs;
        -1: an exact pair), near list (npairs), bounded pairs (nb), candidates (nb)]``; ``_near_floats =
        [threshold, halves (ng), radius sums (npairs), reaches (npairs), lower (nb),
        baseline ends (6 ng), ends (6 ng), displacements (ng), near bounds (npairs)]``.
        ``_lower`` and ``_candidates`` (what :meth:`min_vine_distance` reads) are views.
        """
        na, nv = self.arm_geoms.size, self.vine_geoms.size
        ng, npairs, nb = na + nv, na * nv, self._bounded_pairs.size
        bounded_index = np.full(npairs, -1, dtype=np.int64)
        bounded_index[self._bounded_pairs] = np.arange(nb)
        reach = (self._arm_caps[1][:, None] + self._vine_caps[1][None, :]) + self._radius_sum
        self._near_ints = np.concatenate([
            [0, 0], self.arm_geoms, self.vine_geoms, self._arm_caps[0], self._vine_caps[0], bounded_index,
            np.zeros(npairs, np.int64), self._bounded_pairs, np.zeros(nb, np.int64),
        ]).astype(np.int64)  # fmt: skip
        self._near_floats = np.concatenate([
            [0.0], self._arm_caps[1], self._vine_caps[1], self._radius_sum.ravel(), reach.ravel(),
            np.zeros(nb + 13 * ng + npairs),
        ])  # fmt: skip
        self._candidates = self._near_ints[2 + 2 * ng + 2 * npairs + nb :]
        self._lower = self._near_floats[1 + ng + 2 * npairs :][:nb]

    @staticmethod
    def ncon_view(data: mujoco.MjData) -> NDArray[np.int32] | None:
        """A one-element live view of ``data.ncon`` (the int in MuJoCo's struct), or None where unknown.

        Reading it costs a numpy item access instead of a bindings property (see
        :func:`_probe_ncon_offset`); the view is checked against ``data.ncon`` here.
        """
        if _NCON_OFFSET is None:
            return None
        view = np.ctypeslib.as_array((ctypes.c_int32 * 1).from_address(data._address + _NCON_OFFSET))
        return view if view[0] == data.ncon else None

    def contact_counts(self, data: mujoco.MjData) -> dict[str, int]:
        """Number of active contacts of each kind of :data:`CONTACT_KINDS` (penetrating or within margin)."""
        ncon = data.ncon
        if ncon == 0:
            return dict.fromkeys(CONTACT_KINDS, 0)
        contact = data.contact
        arm_arm, arm_vine, arm_stand, arm_floor = _count_kinds(self.kind, contact.geom1, contact.geom2, ncon)
        return {"arm_arm": arm_arm, "arm_vine": arm_vine, "arm_stand": arm_stand, "arm_floor": arm_floor}

    def min_vine_distance(self, data: mujoco.MjData) -> tuple[float, int, int]:
        """Smallest signed distance [m] between an arm geom and a vine geom, and that pair.

        Negative when they penetrate. Enclosing capsules give every pair a lower bound
        (exact for spheres and capsules); only the pairs whose bound beats the best distance
        so far are measured exactly (``mujoco.mj_geomDistance``), a handful per call, and
        only the pairs that can still be near since a baseline are bounded at all
        (:func:`_vine_near_search`).

        Returns:
            (distance [m], arm geom id, vine geom id); (max_distance, -1, -1) when there is
            no vine or nothing is closer than ``max_distance``.
        """
        if self.vine_geoms.size == 0 or self.arm_geoms.size == 0:
            return self.max_distance, -1, -1
        # One numba call for the capsule bounds (numpy's fancy indexing on ~17 x 80 pairs
        # cost ~100 us per tick); the exact distance of the few non-capsule pairs whose
        # bound beats the best stays with MuJoCo.
        bound = self._bound_data
        if bound is None or bound[0] is not data:
            bound = self._bound_data = (data, data.geom_xpos, data.geom_xmat)  # live views, made once
            self._near_ints[0] = 0  # a new data: no baseline yet
        na, nv = self._sizes
        # Only the few pairs that can still be nearest since a baseline are measured (see
        # _vine_near_search): the same result as testing every pair's capsule. It also
        # returns the geoms of the best pair and of the nearest candidate (usually the only one).
        best, self._hint, n_candidates, arm, vine, candidate_arm, candidate_vine = _vine_near_search(
            bound[1], bound[2], self._near_ints, self._near_floats, na, nv, self.max_distance, self._hint,
        )  # fmt: skip
        if n_candidates:
            # The first candidate's bound is below the best by construction.
            dist = mujoco.mj_geomDistance(self.model, data, candidate_arm, candidate_vine, best, self._fromto)
            if dist < best:
                best, arm, vine = float(dist), candidate_arm, candidate_vine
            if n_candidates > 1:
                lower, bounded, arms, vines = self._lower, self._bounded_list, self._arm_list, self._vine_list
                for i in self._candidates[1:n_candidates].tolist():
                    if lower[i] >= best:
                        break  # every remaining pair is at least this far apart
                    k = bounded[i]
                    ga, gv = arms[k // nv], vines[k % nv]
                    dist = mujoco.mj_geomDistance(self.model, data, ga, gv, best, self._fromto)
                    if dist < best:
                        best, arm, vine = float(dist), ga, gv
        return float(best), arm, vine


#: Safety margin [m] of the pruning in :func:`_vine_near_search`: far above the round-off of
#: the distances (~1e-15 m), so a pair it skips is certainly farther than the best.
_PRUNE_MARGIN = 1e-9


#: Reach [m] of the near list of :func:`_vine_near_search`: pairs whose distance bound at a baseline
#: is this much above the answer then stay out of it until a geom has moved ~half of it.
_NEAR_HORIZON = 0.1


@njit(cache=True, error_model="numpy")
def _vine_near_search(xpos, xmat, ints, floats, na, nv, max_distance, hint):
    """Enclosing-capsule distances of the arm-vine pairs that can be nearest (pair k = arm k // nv, vine k % nv).

    Returns the smallest distance over the exact pairs (the capsules are the geoms) if it
    is below ``max_distance`` (else ``max_distance``), its pair index (-1: none; the
    first such pair in pair order on a tie), the number of bounded pairs (an ellipsoid
    or other geom in its capsule) whose lower bound (written to ``lower``, by bounded
    index) is below it, their bounded indices written to ``candidates`` nearest first
    (ties in index order): the same as measuring every pair (a test holds it to that);
    then the geom ids of the best pair and of the first candidate (-1 for none).
    ``hint`` (an exact pair, e.g. the last call's answer) bounds the answer from above.
    Operands and state packed by ``ContactMonitor._pack_near``.

    Every pair's capsule
    distance is 1-Lipschitz in the motion of its two segments: if every point of a
    geom's segment moved by at most ``disp`` since the baseline (``disp`` = the larger
    move of its two ends, a segment's points being their convex combinations), the
    pair's distance now is at least its baseline bound minus both geoms' ``disp``. So a
    pair whose bound minus those moves is at least the current cut (the best distance so
    far, or the hinted pair's distance, plus ``_PRUNE_MARGIN``) cannot be nearer and is
    skipped: the same pairs win, ties included (exact pairs are compared as (distance,
    pair index), the first minimum in pair order; candidates are sorted by (lower bound,
    index), a stable sort's order). Before sim7 every call measured the bounding-sphere
    gap of all ~540 pairs (~12 us of the episode's tick); now one call reads each geom's
    pose once and measures a handful of pairs.

    The baseline (taken when ``valid`` is 0 or when the largest moves reach the near
    list's threshold) measures every pair: its bound is its capsule distance, or the
    bounding spheres' gap where the segment distance takes a degenerate branch (a
    segment shorter than ~1e-6 m but not a point, or near-parallel segments: only those
    are not exact to round-off); the near list holds the pairs whose bound is below the
    answer then plus :data:`_NEAR_HORIZON`, sorted by bound; every other pair's bound is
    at least that ``threshold``.
    """
    ng, npairs = na + nv, na * nv
    geoms, axes = ints[2 : 2 + ng], ints[2 + ng : 2 + 2 * ng]
    bounded_index = ints[2 + 2 * ng : 2 + 2 * ng + npairs]
    near = ints[2 + 2 * ng + npairs : 2 + 2 * ng + 2 * npairs]
    nb = (ints.shape[0] - (2 + 2 * ng + 2 * npairs)) // 2
    bounded_pairs = ints[2 + 2 * ng + 2 * npairs : 2 + 2 * ng + 2 * npairs + nb]
    candidates = ints[2 + 2 * ng + 2 * npairs + nb :]
    halves = floats[1 : 1 + ng]
    radius_sum = floats[1 + ng : 1 + ng + npairs]
    lower = floats[1 + ng + 2 * npairs : 1 + ng + 2 * npairs + nb]
    w = 1 + ng + 2 * npairs + nb
    base_ends = floats[w : w + 6 * ng].reshape(ng, 6)
    ends = floats[w + 6 * ng : w + 12 * ng].reshape(ng, 6)
    disp = floats[w + 12 * ng : w + 13 * ng]
    near_bound = floats[w + 13 * ng : w + 13 * ng + npairs]
    for i in range(ng):
        g, ax, h = geoms[i], axes[i], halves[i]
        for c in range(3):
            off = h * xmat[g, 3 * c + ax]
            ends[i, c] = xpos[g, c] - off
            ends[i, 3 + c] = xpos[g, c] + off
    # An upper bound of the answer: the distance of the hinted pair (an exact one) now.
    upper = max_distance
    if hint >= 0:
        upper = min(upper, _ends_distance(ends, hint // nv, na + hint % nv) - radius_sum[hint])
    move = 0.0
    if ints[0]:
        arm_move = vine_move = 0.0
        for i in range(ng):
            s0 = s1 = 0.0
            for c in range(3):
                e0 = ends[i, c] - base_ends[i, c]
                e1 = ends[i, 3 + c] - base_ends[i, 3 + c]
                s0 += e0 * e0
                s1 += e1 * e1
            disp[i] = math.sqrt(max(s0, s1))
            if i < na:
                arm_move = max(arm_move, disp[i])
            else:
                vine_move = max(vine_move, disp[i])
        move = arm_move + vine_move
        # Every pair outside the near list must stay beyond the first cut (the loosest).
        if not floats[0] - move >= min(max_distance, upper) + 2.0 * _PRUNE_MARGIN:
            ints[0] = 0
    if not ints[0]:
        _vine_near_rebase(ends, ints, floats, na, nv, max_distance)
        move = 0.0
        for i in range(ng):
            disp[i] = 0.0
    n_near = ints[1]
    best = max_distance
    best_k = -1
    cut = min(best, upper) + _PRUNE_MARGIN
    for p in range(n_near):
        k = near[p]
        bound = near_bound[p]
        if bound - move >= cut:
            break  # every later pair is at least as far
        if bounded_index[k] >= 0:
            continue
        i, m = k // nv, k % nv
        if bound - disp[i] - disp[na + m] >= cut:
            continue
        d = _ends_distance(ends, i, na + m) - radius_sum[k]
        if d < best or (d == best and k < best_k):
            best, best_k = d, k
            cut = min(best, upper) + _PRUNE_MARGIN
    n = 0
    cut = best + _PRUNE_MARGIN
    for p in range(n_near):
        k = near[p]
        bound = near_bound[p]
        if bound - move >= cut:
            break
        j = bounded_index[k]
        if j < 0:
            continue
        i, m = k // nv, k % nv
        if bound - disp[i] - disp[na + m] >= cut:
            continue
        lower[j] = _ends_distance(ends, i, na + m) - radius_sum[k]
        if lower[j] < best:
            candidates[n] = j
            n += 1
    # Nearest first, ties in index order (a stable sort's order over the bounded pairs).
    for a in range(1, n):
        j = candidates[a]
        key = lower[j]
        b = a - 1
        while b >= 0 and (lower[candidates[b]] > key or (lower[candidates[b]] == key and candidates[b] > j)):
            candidates[b + 1] = candidates[b]
            b -= 1
        candidates[b + 1] = j
    arm = vine = candidate_arm = candidate_vine = -1
    if best_k >= 0:
        arm, vine = geoms[best_k // nv], geoms[na + best_k % nv]
    if n:
        k = bounded_pairs[candidates[0]]
        candidate_arm, candidate_vine = geoms[k // nv], geoms[na + k % nv]
    return best, best_k, n, arm, vine, candidate_arm, candidate_vine


@njit(cache=True, error_model="numpy")
def _vine_near_rebase(ends, ints, floats, na, nv, max_distance):
    """The baseline of :func:`_vine_near_search` at ``ends`` (layout there): bounds, near list, threshold."""
    ng, npairs = na + nv, na * nv
    bounded_index = ints[2 + 2 * ng : 2 + 2 * ng + npairs]
    near = ints[2 + 2 * ng + npairs : 2 + 2 * ng + 2 * npairs]
    nb = (ints.shape[0] - (2 + 2 * ng + 2 * npairs)) // 2
    radius_sum = floats[1 + ng : 1 + ng + npairs]
    reach = floats[1 + ng + npairs : 1 + ng + 2 * npairs]
    w = 1 + ng + 2 * npairs + nb
    base_ends = floats[w : w + 6 * ng].reshape(ng, 6)
    near_bound = floats[w + 13 * ng : w + 13 * ng + npairs]
    eps = 1e-12
    answer = max_distance
    for k in range(npairs):
        i, j = k // nv, na + k % nv
        ux, uy, uz = ends[i, 3] - ends[i, 0], ends[i, 4] - ends[i, 1], ends[i, 5] - ends[i, 2]
        vx, vy, vz = ends[j, 3] - ends[j, 0], ends[j, 4] - ends[j, 1], ends[j, 5] - ends[j, 2]
        a = _dot(ux, uy, uz, ux, uy, uz)
        e = _dot(vx, vy, vz, vx, vy, vz)
        b = _dot(ux, uy, uz, vx, vy, vz)
        d = _ends_distance(ends, i, j) - radius_sum[k]
        if bounded_index[k] < 0 and d < answer:
            answer = d
        degenerate = (a > 0.0 and a <= eps) or (e > 0.0 and e <= eps) or (a > eps and e > eps and a * e - b * b <= eps)
        if degenerate:
            # Centre distance minus both half-lengths and radii: below any distance of the two capsules.
            cx = 0.5 * (ends[i, 0] + ends[i, 3]) - 0.5 * (ends[j, 0] + ends[j, 3])
            cy = 0.5 * (ends[i, 1] + ends[i, 4]) - 0.5 * (ends[j, 1] + ends[j, 4])
            cz = 0.5 * (ends[i, 2] + ends[i, 5]) - 0.5 * (ends[j, 2] + ends[j, 5])
            d = math.sqrt(cx * cx + cy * cy + cz * cz) - reach[k] - 1e-9
        near_bound[k] = d  # scratch: bound per pair index, compacted below
    threshold = answer + _NEAR_HORIZON
    n = 0
    for k in range(npairs):
        if near_bound[k] < threshold:
            near[n] = k
            n += 1
    # near_bound[p] must follow near[p]: move the selected bounds to the front (p <= k), then sort.
    for p in range(n):
        near_bound[p] = near_bound[near[p]]
    for a in range(1, n):
        k = near[a]
        key = near_bound[a]
        c = a - 1
        while c >= 0 and near_bound[c] > key:
            near[c + 1] = near[c]
            near_bound[c + 1] = near_bound[c]
            c -= 1
        near[c + 1] = k
        near_bound[c + 1] = key
    for i in range(ng):
        for c in range(6):
            base_ends[i, c] = ends[i, c]
    floats[0] = threshold
    ints[1] = n
    ints[0] = 1


@njit(cache=True, inline="always")
def _ends_distance(ends, i, j):
    """:func:`_pair_distance` of the segments ``ends[i]`` and ``ends[j]`` (rows: one end, the other end)."""
    eps = 1e-12
    ux, uy, uz = ends[i, 3] - ends[i, 0], ends[i, 4] - ends[i, 1], ends[i, 5] - ends[i, 2]
    a = _dot(ux, uy, uz, ux, uy, uz)
    vx, vy, vz = ends[j, 3] - ends[j, 0], ends[j, 4] - ends[j, 1], ends[j, 5] - ends[j, 2]
    rx, ry, rz = ends[i, 0] - ends[j, 0], ends[i, 1] - ends[j, 1], ends[i, 2] - ends[j, 2]
    return _clamped_distance(ux, uy, uz, vx, vy, vz, rx, ry, rz, a, eps)


@njit(cache=True)
def _count_kinds(kind, geom1, geom2, ncon):
    """Contacts among the first ``ncon`` of each kind: (arm-arm, arm-vine, arm-stand, arm-floor)."""
    arm_arm = arm_vine = arm_stand = arm_floor = 0
    for c in range(ncon):
        k1, k2 = kind[geom1[c]], kind[geom2[c]]
        lo, hi = min(k1, k2), max(k1, k2)
        if lo == _ARM:
            if hi == _ARM:
                arm_arm += 1
            elif hi == _STAND:
                arm_stand += 1
            elif hi == _VINE:
                arm_vine += 1
            elif hi == _FLOOR:
                arm_floor += 1
    return arm_arm, arm_vine, arm_stand, arm_floor


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


@njit(cache=True, inline="always")
def _dot(x0: float, x1: float, x2: float, y0: float, y1: float, y2: float) -> float:
    return x0 * y0 + x1 * y1 + x2 * y2


@njit(cache=True)
def _pair_distance(p1, q1, i, p2, q2, j):
    """Distance between segments p1[i]-q1[i] and p2[j]-q2[j] (Ericson's clamped solution)."""
    eps = 1e-12
    ux, uy, uz = q1[i, 0] - p1[i, 0], q1[i, 1] - p1[i, 1], q1[i, 2] - p1[i, 2]
    a = _dot(ux, uy, uz, ux, uy, uz)
    vx, vy, vz = q2[j, 0] - p2[j, 0], q2[j, 1] - p2[j, 1], q2[j, 2] - p2[j, 2]
    rx, ry, rz = p1[i, 0] - p2[j, 0], p1[i, 1] - p2[j, 1], p1[i, 2] - p2[j, 2]
    return _clamped_distance(ux, uy, uz, vx, vy, vz, rx, ry, rz, a, eps)


@njit(cache=True, inline="always")
def _clamped_distance(ux, uy, uz, vx, vy, vz, rx, ry, rz, a, eps):
    """Distance of segments p1 + s u and p2 + t v, s, t in [0, 1], with r = p1 - p2, a = u.u."""
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
    return np.sqrt(gx * gx + gy * gy + gz * gz)


@njit(cache=True)
def _segment_distances(p1: NDArray, q1: NDArray, p2: NDArray, q2: NDArray) -> NDArray[np.float64]:
    """(n, m) distances between segments p1[i]-q1[i] and p2[j]-q2[j] (Ericson's clamped solution).

    Scalar arithmetic only: small-array temporaries made it 30x slower.
    """
    n, m = p1.shape[0], p2.shape[0]
    out = np.empty((n, m))
    for i in range(n):
        for j in range(m):
            out[i, j] = _pair_distance(p1, q1, i, p2, q2, j)
    return out


#: MuJoCo's flags (mjtDisableBit / mjtEnableBit) the contact certificate reads.
_DSBL_CONSTRAINT = int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
_DSBL_CONTACT = int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
_DSBL_FILTERPARENT = int(mujoco.mjtDisableBit.mjDSBL_FILTERPARENT)
_ENBL_OVERRIDE = int(mujoco.mjtEnableBit.mjENBL_OVERRIDE)
_ENBL_SLEEP = int(mujoco.mjtEnableBit.mjENBL_SLEEP)

#: Clearance [m] the certificate keeps above every pair's contact margin: far above the
#: round-off of the bounds (~1e-15 m) and of MuJoCo's convex narrow phase (``ccd_tolerance``,
#: 1e-6 by default), so a certified pair is certainly farther apart than its margin.
_CERTIFICATE_CLEARANCE = 1e-3

_SHAPE_SEGMENT, _SHAPE_PLANE = 0, 1

#: After a baseline that certified nothing, this many rebase calls are skipped (a robot
#: resting in contact or within the clearance would otherwise pay for one every step).
_REBASE_BACKOFF = 10

#: Total joint travel [rad] (sum over the joints of |q - q0|) after which a new baseline is
#: taken whatever the slacks: pairs that stay clear over this travel need no per-step test.
_CERTIFICATE_HORIZON = 0.1

#: At most this many loose pairs per baseline get MuJoCo's exact distance (~1.5 us each).
_MAX_REFINED = 8

#: Every model array ``ContactCertificate._build`` (and so the proof) reads; compared with a
#: copy on every certified step. Geom pose and bounding shape (``geom_rbound`` is MuJoCo's
#: broad phase), bitmask filters, margins and gaps; the kinematic tree down to the hinges
#: (positions: the reaches); the explicit pairs.
_SNAPSHOT_ARRAYS = (
    "geom_type", "geom_contype", "geom_conaffinity", "geom_bodyid", "geom_size", "geom_rbound", "geom_pos",
    "geom_quat", "geom_margin", "geom_gap",
    "body_parentid", "body_weldid", "body_jntnum", "body_jntadr", "body_mocapid", "body_pos", "body_quat",
    "jnt_type", "jnt_qposadr", "jnt_pos",
    "pair_geom1", "pair_geom2", "pair_margin", "pair_gap",
)  # fmt: skip


def _probe_option_window() -> tuple[int, int, int] | None:
    """Where the options the certificate depends on lie in MuJoCo's ``mjModel`` struct.

    Returns ``(byte offset, words, int32 index of disableflags)``: the 8-byte words from
    ``opt.o_margin`` to ``opt.enableflags`` (``disableflags`` in between), found by writing
    a sentinel through the bindings into each field of a throwaway model and seeing which
    bytes change; None when the struct does not look as expected (the certificate is then
    unsupported: full detection every step). The layout is the library's, fixed at its
    compile time, so the offsets hold for every model.
    """
    m = mujoco.MjModel.from_xml_string("<mujoco/>")
    opt = m.opt
    # opt lies in the first ~1.1 KB of the struct, which is several KB long (~590 fields).
    raw = np.ctypeslib.as_array((ctypes.c_uint8 * 2048).from_address(m._address))
    found = {}
    for name, sentinel, dtype in (
        ("o_margin", 1.2345678e-7, np.float64), ("disableflags", 0x5A5A, np.int32), ("enableflags", 0x2A5A, np.int32),
    ):  # fmt: skip
        size = np.dtype(dtype).itemsize
        before = raw.copy()
        old = getattr(opt, name)
        setattr(opt, name, sentinel)
        changed = np.flatnonzero(before != raw)
        at = int(changed[0]) - int(changed[0]) % size if changed.size else -1
        # Only this field's bytes changed, and they read back as the sentinel.
        ok = changed.size > 0 and changed[-1] < at + size and raw[at : at + size].view(dtype)[0] == sentinel
        setattr(opt, name, old)
        if not ok:
            return None
        found[name] = at
    start, stop = found["o_margin"], found["enableflags"] + 4
    if not start < found["disableflags"] < found["enableflags"] or start % 8:
        return None
    words = (stop - start + 7) // 8
    return start, words, (found["disableflags"] - start) // 4


_OPTION_WINDOW = _probe_option_window()


def _option_view(model: mujoco.MjModel) -> NDArray[np.int64] | None:
    """An int64 view of ``model``'s option words of :data:`_OPTION_WINDOW` (None if unknown or inconsistent)."""
    if _OPTION_WINDOW is None:
        return None
    start, words, disable = _OPTION_WINDOW
    view = np.ctypeslib.as_array((ctypes.c_int64 * words).from_address(model._address + start))
    flags = view.view(np.int32)
    # The same values as the bindings give (else the layout is not what the probe found).
    if (
        view[:1].view(np.float64)[0] != model.opt.o_margin
        or flags[disable] != model.opt.disableflags
        or flags[disable + 1] != model.opt.enableflags
    ):
        return None
    return view


def _probe_ncon_offset() -> int | None:
    """Byte offset of ``ncon`` in MuJoCo's ``mjData`` struct (None if it cannot be told apart).

    ``data.ncon`` through the bindings costs ~1-3 us per read inside an episode (cold);
    :meth:`ContactMonitor.ncon_view` reads the int itself. Found on a throwaway model
    whose contact count takes several values, with islands and constraint rows that do
    not follow it (a box on the floor makes 4 contacts in one island): the one int between
    the solver statistics and ``energy`` (both inside the struct) that equals ``ncon`` in
    every state. The layout is fixed when the library is compiled.
    """
    bodies = "".join(
        f'<body pos="{i} 0 1"><joint type="slide" axis="0 0 1"/><geom type="{kind}" size=".1 .1 .1"/></body>'
        for i, kind in enumerate(("sphere", "sphere", "box"))
    )
    m = mujoco.MjModel.from_xml_string(
        f'<mujoco><worldbody><geom type="plane" size="5 5 .1"/>{bodies}</worldbody></mujoco>'
    )
    d = mujoco.MjData(m)
    lo = d.solver_fwdinv.ctypes.data + d.solver_fwdinv.nbytes - d._address
    hi = d.energy.ctypes.data - d._address
    if not 0 < lo < hi:
        return None
    window = np.ctypeslib.as_array((ctypes.c_int32 * ((hi - lo) // 4)).from_address(d._address + lo))
    found = None
    for down in ((), (0,), (0, 1), (2,), (0, 2), (0, 1, 2)):
        d.qpos[:] = [-0.95 if i in down else 0.0 for i in range(3)]
        mujoco.mj_forward(m, d)
        hits = set(np.flatnonzero(window == d.ncon).tolist())
        found = hits if found is None else found & hits
    if found is None or len(found) != 1:
        return None
    return lo + 4 * found.pop()


_NCON_OFFSET = _probe_ncon_offset()


class ContactCertificate:
    """Proves, before ``mj_step1``, that its collision detection would find no contact.

    ``mj_step1`` runs MuJoCo's collision detection (broad and narrow phase, ~40 % of it here)
    even when the robot is far from everything, which in the paper episode is every step
    (no contact in any golden run). When no contact can be found, running ``mj_step1`` with
    ``mjDSBL_CONTACT`` set gives the same result bit for bit (MuJoCo then only clears the
    contact list, which the full detection leaves empty too; a test holds the two to each
    other over whole trajectories).

    The proof: at a *baseline* state (right after a full ``mj_step1`` that found no
    contact) every geom pair MuJoCo may test (the model's explicit ``<pair>``s and every
    pair its bitmask and body filters let through) gets a lower bound of its distance
    (spheres, capsules exact; an ellipsoid inside its enclosing capsule; anything else
    inside its bounding sphere; a plane as a half-space). The robot's collidable geoms hang
    on chains of hinge joints; a point at most R away from a hinge's anchor (R: the sum of
    the rigid link lengths below it, a model constant) moves by at most R |dq| when that
    hinge turns by dq, for any path between the two configurations, so a pair's distance
    changes by at most sum_j R_j |q_j - q0_j| over the joints that move one geom relative
    to the other (their common ancestors move both rigidly). While that sum stays below every pair's
    baseline bound minus its margin minus :data:`_CERTIFICATE_CLEARANCE`, no contact is
    possible and :meth:`certified` says so; else the caller runs the full detection and
    calls :meth:`rebase`.

    Models the proof does not cover (a collidable geom moved by a non-hinge joint, a mocap
    body or a body with several joints, flexes, height fields, SDFs, a dynamic plane) get
    a certificate that is never valid (always the full detection).

    The model may be edited between steps (``robot.model`` is public: a body moved, a
    margin raised, a contype changed, an option set): the proof reads the geoms' and
    bodies' types, sizes, poses, margins, gaps, bitmasks and tree, the joints' positions,
    the explicit pairs and the options. Every one of those model arrays is compared with
    a copy taken at the last :meth:`_build` on every certified step (one compiled pass
    over ~16 KB, :func:`_model_unchanged`); the same call compares the option words from
    ``o_margin`` to ``enableflags`` (``disableflags`` among them; read in the model struct,
    see :func:`_option_view`) with those at the baseline, and the caller checks that no
    contact-filter callback is installed (:meth:`certified`). Any
    difference: no certificate for that step (the full detection runs), and the next
    :meth:`rebase` rebuilds the certificate from the edited model. ``data.qpos`` edited
    directly is covered by the motion bound itself (joint travel since the baseline's
    ``q0``, read from the live ``qpos``).
    """

    def __init__(self, model: mujoco.MjModel) -> None:
        self.model = model
        self.supported = False
        self._valid = False
        self._wait = 0
        self._full = True  # the next baseline measures every pair (no slack to carry over)
        self._override: float | None = None  # the o_margin the margins were set for (None: the model's)
        self._bound_data: tuple | None = None
        self._pair_slack = np.zeros(0)
        self._disableflags = self._enableflags = -1  # the options at the baseline (see certified)
        self._live = self._snapshot = np.zeros(1, dtype=np.int64)
        self._opt_live: NDArray[np.int64] | None = None
        self._opt_flags: NDArray[np.int32] | None = None
        self._disable_index = -1
        self._rebuild()

    def __getstate__(self) -> dict:
        # _live aliases this model's memory: a copy (pickle, deepcopy) binds its own model's.
        state = self.__dict__.copy()
        state["_live"] = state["_snapshot"] = state["_opt_live"] = state["_opt_flags"] = None
        state["_bound_data"] = None
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._rebuild()

    def _rebuild(self) -> None:
        """(Re)read everything the proof uses from the model; forget the baseline."""
        self.supported = False
        self.invalidate()
        self._override = None
        try:
            self._build(self.model)
            self._take_snapshot(self.model)
        except _Unsupported:
            return
        self.supported = True

    def _take_snapshot(self, m: mujoco.MjModel) -> None:
        """Bind one int64 view of the model's buffer over every array :meth:`_build` reads and copy them.

        ``self._snapshot = [n_ranges, (start, n_words) per range, the words of each range,
        the option words]`` (starts in 8-byte words from the view's first word);
        :func:`_model_unchanged` compares the live words with the copy. MuJoCo keeps all
        model arrays in one buffer (``nbuffer`` bytes), each 8-byte aligned; anything else is
        refused (full detection). The option words (``o_margin`` to ``enableflags`` of
        ``model.opt``, :func:`_option_view`; they live in the model struct, not its buffer)
        are copied at each baseline (:meth:`rebase`) and compared by :func:`_certified_now`.
        """
        opt_live = _option_view(m)
        if opt_live is None:
            raise _Unsupported
        arrays = [getattr(m, name) for name in _SNAPSHOT_ARRAYS]
        spans = [(int(a.ctypes.data), int(a.nbytes)) for a in arrays if a.nbytes]
        base = min(addr for addr, _ in spans)
        end = max(addr + ((size + 7) // 8) * 8 for addr, size in spans)
        if base % 8 or any(addr % 8 for addr, _ in spans) or end - base > m.nbuffer:
            raise _Unsupported
        ranges: list[list[int]] = []
        for addr, size in sorted(spans):
            start, stop = (addr - base) // 8, (addr - base + size + 7) // 8
            if ranges and start <= ranges[-1][1]:
                ranges[-1][1] = max(ranges[-1][1], stop)
            else:
                ranges.append([start, stop])
        # The view aliases the model's buffer: self.model keeps it alive.
        live = np.ctypeslib.as_array((ctypes.c_int64 * ((end - base) // 8)).from_address(base))
        header = [len(ranges)] + [v for start, stop in ranges for v in (start, stop - start)]
        words = [live[start:stop] for start, stop in ranges]
        self._live = live
        self._snapshot = np.concatenate(
            [np.array(header, dtype=np.int64)] + words + [np.zeros(opt_live.size, dtype=np.int64)]
        ).astype(np.int64)
        self._opt_live = opt_live
        self._opt_flags = opt_live.view(np.int32)  # disableflags at _disable_index (the step's restore)
        self._disable_index = _OPTION_WINDOW[2]

    def _build(self, m: mujoco.MjModel) -> None:
        if m.nflex:
            raise _Unsupported
        collidable = [
            g for g in range(m.ngeom) if m.geom_contype[g] or m.geom_conaffinity[g]
        ] + m.pair_geom1.tolist() + m.pair_geom2.tolist()  # fmt: skip
        collidable = sorted(set(collidable))
        data = mujoco.MjData(m)
        mujoco.mj_kinematics(m, data)
        hinge = int(mujoco.mjtJoint.mjJNT_HINGE)
        # Per collidable geom: its chain of hinge joints (qpos address, reach R [m]), root first.
        chains: dict[int, list[tuple[int, float]]] = {}
        joint_of: dict[int, int] = {}
        for g in collidable:
            kind = int(m.geom_type[g])
            if kind in (int(mujoco.mjtGeom.mjGEOM_HFIELD), int(mujoco.mjtGeom.mjGEOM_SDF)):
                raise _Unsupported
            body = int(m.geom_bodyid[g])
            joints = []  # leaf first
            b = body
            while b != 0:
                if m.body_mocapid[b] >= 0 or m.body_jntnum[b] > 1:
                    raise _Unsupported
                if m.body_jntnum[b] == 1:
                    j = int(m.body_jntadr[b])
                    if int(m.jnt_type[j]) != hinge:
                        raise _Unsupported
                    joints.append(j)
                b = int(m.body_parentid[b])
            if joints and kind == int(mujoco.mjtGeom.mjGEOM_PLANE):
                raise _Unsupported  # a moving half-space: no finite reach
            # Reach of each hinge: anchor to anchor down the chain, then to the geom's centre,
            # plus the geom's bounding radius (all rigid distances, the same in any pose).
            reach = []
            far = 0.0
            if joints:
                far = float(np.linalg.norm(data.geom_xpos[g] - data.xanchor[joints[0]])) + float(m.geom_rbound[g])
            for i, j in enumerate(joints):
                if i:
                    far += float(np.linalg.norm(data.xanchor[joints[i - 1]] - data.xanchor[j]))
                reach.append((j, far * (1.0 + 1e-9)))
            chains[g] = reach[::-1]
            for j, _ in reach:
                joint_of.setdefault(j, len(joint_of))
        self._joint_qpos = np.array([m.jnt_qposadr[j] for j in joint_of], dtype=np.int64)
        # The pairs MuJoCo may test: explicit pairs, then the filtered dynamic ones (a superset is safe).
        pairs: list[tuple[int, int, float]] = []
        for k in range(m.npair):
            pairs.append((int(m.pair_geom1[k]), int(m.pair_geom2[k]), float(m.pair_margin[k]), float(m.pair_gap[k])))
        filter_parent = not (m.opt.disableflags & _DSBL_FILTERPARENT)
        self._filter_parent = filter_parent
        weld = m.body_weldid
        for a_i, a in enumerate(collidable):
            for b in collidable[a_i + 1 :]:
                ba, bb = int(m.geom_bodyid[a]), int(m.geom_bodyid[b])
                wa, wb = int(weld[ba]), int(weld[bb])
                if wa == wb:
                    continue  # same weld body (static-static included): never tested
                pa, pb = int(weld[m.body_parentid[wa]]), int(weld[m.body_parentid[wb]])
                if filter_parent and wa != 0 and wb != 0 and (wa == pb or wb == pa):
                    continue
                if not (m.geom_contype[a] & m.geom_conaffinity[b]) and not (m.geom_contype[b] & m.geom_conaffinity[a]):
                    continue
                plane = int(mujoco.mjtGeom.mjGEOM_PLANE)
                if int(m.geom_type[a]) == plane and int(m.geom_type[b]) == plane:
                    continue  # no collision function
                pairs.append((a, b, float(m.geom_margin[a] + m.geom_margin[b]), float(m.geom_gap[a] + m.geom_gap[b])))
        # MuJoCo's narrow phase reports a contact within margin + gap (the gap only makes it
        # inactive): the certificate keeps every pair clear of both.
        self._pair_margins = np.array([p[2] for p in pairs], dtype=np.float64)
        self._pair_gaps = np.array([p[3] for p in pairs], dtype=np.float64)
        # Per pair, the joints moving one geom relative to the other and their reaches.
        terms = []
        for a, b, _, _ in pairs:
            ra, rb = dict(chains[a]), dict(chains[b])
            common = set(ra) & set(rb)
            terms.append([(joint_of[j], r) for j, r in chains[a] if j not in common]
                         + [(joint_of[j], r) for j, r in chains[b] if j not in common])  # fmt: skip
        width = max([len(t) for t in terms] + [1])
        self._term_joint = np.zeros((len(pairs), width), dtype=np.int64)
        self._term_reach = np.zeros((len(pairs), width))
        for p, t in enumerate(terms):
            for c, (j, r) in enumerate(t):
                self._term_joint[p, c], self._term_reach[p, c] = j, r
        self._pair_geoms = np.array([(a, b) for a, b, _, _ in pairs], dtype=np.int64).reshape(-1, 2)
        # Per geom: bounding shape (segment along a local axis with a radius, or a plane).
        n = m.ngeom
        self._shape = np.full(n, _SHAPE_SEGMENT, dtype=np.int64)
        self._axis = np.full(n, 2, dtype=np.int64)
        self._half = np.zeros(n)
        self._radius = np.zeros(n)
        for g in collidable:
            kind, size = int(m.geom_type[g]), m.geom_size[g]
            if kind == int(mujoco.mjtGeom.mjGEOM_PLANE):
                self._shape[g] = _SHAPE_PLANE
            elif kind == int(mujoco.mjtGeom.mjGEOM_SPHERE):
                self._radius[g] = size[0]
            elif kind == int(mujoco.mjtGeom.mjGEOM_CAPSULE):
                self._radius[g], self._half[g] = size[0], size[1]
            elif kind == int(mujoco.mjtGeom.mjGEOM_ELLIPSOID):
                order = np.argsort(size)[::-1]
                self._axis[g], self._radius[g] = order[0], size[order[1]]
                self._half[g] = size[order[0]] - size[order[1]]
            else:
                self._radius[g] = m.geom_rbound[g]
        exact = np.zeros(n, dtype=bool)
        for g in collidable:
            exact[g] = int(m.geom_type[g]) in (
                int(mujoco.mjtGeom.mjGEOM_PLANE), int(mujoco.mjtGeom.mjGEOM_SPHERE), int(mujoco.mjtGeom.mjGEOM_CAPSULE),
            )  # fmt: skip
        # Pairs whose bound is loose (a geom inside an enclosing shape): refined with MuJoCo's distance.
        self._loose = ~(exact[self._pair_geoms[:, 0]] & exact[self._pair_geoms[:, 1]])
        self._fromto = np.zeros(6)
        # The per-step test's operands in one int and one float buffer (a numba call costs
        # ~0.06 us per array argument), sizes in their headers (see _certificate_holds).
        nj, npairs = self._joint_qpos.size, len(pairs)
        self._ints = np.concatenate([
            [nj, npairs, width, 0], self._joint_qpos, np.zeros(npairs, np.int64), self._term_joint.ravel(),
        ]).astype(np.int64)  # fmt: skip
        max_reach = self._term_reach.max(axis=1)
        self._floats = np.concatenate([
            [_CERTIFICATE_HORIZON, 0.0], np.zeros(2 * nj + 2 * npairs), self._term_reach.ravel(), max_reach,
            self._pair_margins + self._pair_gaps,
        ])  # fmt: skip
        self._q0 = self._floats[2 : 2 + nj]
        self._pair_slack = self._floats[2 + 2 * nj + npairs : 2 + 2 * nj + 2 * npairs]
        self._margin_view = self._floats[self._floats.size - npairs :]
        self._rbound = np.ascontiguousarray(m.geom_rbound, dtype=np.float64)

    def rebase(self, data: mujoco.MjData) -> None:
        """Take ``data``'s state (after ``mj_step1``) as the baseline, if it certifies anything.

        Valid only when the model's options and callbacks allow the proof (no sleeping, no
        contact-filter callback) and every pair is clear of its margin by
        :data:`_CERTIFICATE_CLEARANCE` now.
        """
        self._valid = False
        if not self.supported:
            return
        m = self.model
        if not _model_unchanged(self._live, self._snapshot) or (
            bool(m.opt.disableflags & _DSBL_FILTERPARENT) != (not self._filter_parent)
        ):
            self._rebuild()  # the model was edited since the certificate read it
            if not self.supported:
                return
        if data.ncon:
            return
        if self._wait > 0:
            self._wait -= 1  # the last baseline failed: a robot resting within the clearance would pay every step
            return
        m = self.model
        opt = m.opt
        if opt.enableflags & _ENBL_SLEEP or opt.disableflags & (_DSBL_CONTACT | _DSBL_CONSTRAINT):
            return
        if mujoco.get_mjcb_contactfilter() is not None:
            return
        margins = self._margin_view
        override = float(opt.o_margin) if opt.enableflags & _ENBL_OVERRIDE else None
        if override != self._override:
            # The margins changed: the carried slacks (see _certificate_rebase) no longer hold.
            margins[:] = (self._pair_margins if override is None else override) + self._pair_gaps
            self._override = override
            self._full = True
        self._floats[1] = _CERTIFICATE_CLEARANCE
        slack = self._pair_slack
        bound = self._bound_data
        if bound is None or bound[0] is not data:
            bound = self._bound_data = (data, data.geom_xpos, data.geom_xmat, data.qpos)  # live views, made once
            self._full = True
        n_failing = _certificate_rebase(
            bound[1], bound[2], bound[3], self._ints, self._floats, self._pair_geoms, self._shape, self._axis,
            self._half, self._radius, self._rbound, self._full,
        )  # fmt: skip
        self._full = False
        if n_failing:
            # A pair with an ellipsoid (or a geom bounded by its sphere) may fail only because
            # its enclosing shape is loose (a flat leaf in a fat capsule): ask MuJoCo for the
            # distance of those few (its convex distance is accurate to ccd_tolerance, far
            # below the clearance).
            failing = np.flatnonzero(~(slack > 0.0))
            if failing.size > _MAX_REFINED or not self._loose[failing].all():
                self._wait = _REBASE_BACKOFF
                return
            for p in failing.tolist():
                a, b = self._pair_geoms[p].tolist()
                distance = mujoco.mj_geomDistance(m, data, a, b, 1.0, self._fromto)
                slack[p] = distance - margins[p] - _CERTIFICATE_CLEARANCE
        self._valid = _certificate_order(self._ints, self._floats)
        if not self._valid:
            self._wait = _REBASE_BACKOFF
        # The options this baseline holds for (certified compares them every step).
        self._disableflags, self._enableflags = int(opt.disableflags), int(opt.enableflags)
        self._snapshot[self._snapshot.size - self._opt_live.size :] = self._opt_live

    def invalidate(self) -> None:
        """Forget the baseline (the next step runs the full detection and takes a new one,
        measuring every pair again)."""
        self._valid = False
        self._wait = 0
        self._full = True

    def certified(self, qpos: NDArray[np.float64]) -> bool:
        """True when no contact is possible at the configuration ``qpos`` (see the class).

        False as well when the model, its options (``o_margin`` to ``enableflags``: any of
        these words) or the contact-filter callback changed since the baseline
        (``SimRobot._physics_step`` runs these same tests through :func:`_certify_step`).
        """
        return (
            self._valid
            and mujoco.get_mjcb_contactfilter() is None
            and _certified_now(qpos, self._ints, self._floats, self._live, self._snapshot, self._opt_live)
        )


class _Unsupported(Exception):
    """The model is outside what :class:`ContactCertificate` can prove."""


@njit(cache=True)
def _certificate_rebase(xpos, xmat, qpos, ints, floats, pair_geoms, shape, axis, half, radius, rbound, full):
    """Baseline of :class:`ContactCertificate`: per pair, its distance's lower bound minus margin and clearance.

    Writes ``q0`` (the joints now) and every pair's ``slack`` (layout: :func:`_certificate_holds`);
    returns the number of pairs whose slack is not positive. Unless ``full``, a pair's
    slack at the last baseline is carried over: minus its largest reach times the joints'
    total travel since then, it is still a lower bound now (the motion bound of the class),
    and it is kept while it leaves the pair beyond the horizon (``slack >= horizon *
    largest reach``: then its exact value cannot change the per-step test); only the
    others are measured again. Likewise a measured pair whose bounding spheres' gap
    already puts it beyond the horizon keeps that bound.
    """
    nj, npairs, width = ints[0], ints[1], ints[2]
    joint_qpos = ints[4 : 4 + nj]
    horizon, clearance = floats[0], floats[1]
    q0 = floats[2 : 2 + nj]
    slack = floats[2 + 2 * nj + npairs : 2 + 2 * nj + 2 * npairs]
    base = 2 + 2 * nj + 2 * npairs + npairs * width
    max_reach = floats[base : base + npairs]
    margins = floats[base + npairs : base + 2 * npairs]
    travel = 0.0
    for i in range(nj):
        q = qpos[joint_qpos[i]]
        travel += abs(q - q0[i])
        q0[i] = q
    failing = 0
    for p in range(npairs):
        if not full and max_reach[p] > 0.0:
            carried = slack[p] - max_reach[p] * travel
            if carried >= horizon * max_reach[p]:
                slack[p] = carried
                continue
        elif not full and slack[p] > 0.0:
            continue  # two geoms that never move relative to each other: the same bound
        a, b = pair_geoms[p, 0], pair_geoms[p, 1]
        if max_reach[p] > 0.0 and shape[a] != _SHAPE_PLANE and shape[b] != _SHAPE_PLANE:
            dx, dy, dz = xpos[a, 0] - xpos[b, 0], xpos[a, 1] - xpos[b, 1], xpos[a, 2] - xpos[b, 2]
            gap = math.sqrt(dx * dx + dy * dy + dz * dz) - rbound[a] - rbound[b] - margins[p] - clearance
            if gap >= horizon * max_reach[p]:
                slack[p] = gap
                continue
        slack[p] = _pair_lower_bound(xpos, xmat, a, b, shape, axis, half, radius) - margins[p] - clearance
        if not slack[p] > 0.0:
            failing += 1
    return failing


@njit(cache=True)
def _certificate_order(ints, floats):
    """After :func:`_certificate_rebase` (and any refinement): the per-step test's pair list.

    The pairs that can come within their margin before the joints' total travel reaches
    the horizon (``tau = slack / largest reach < horizon``), in increasing ``tau``
    (insertion sort: a handful). Returns True when every slack is positive (a valid baseline).
    """
    nj, npairs, width = ints[0], ints[1], ints[2]
    near = ints[4 + nj : 4 + nj + npairs]
    horizon = floats[0]
    tau = floats[2 + 2 * nj : 2 + 2 * nj + npairs]
    slack = floats[2 + 2 * nj + npairs : 2 + 2 * nj + 2 * npairs]
    base = 2 + 2 * nj + 2 * npairs + npairs * width
    max_reach = floats[base : base + npairs]
    n = 0
    for p in range(npairs):
        if not slack[p] > 0.0:
            ints[3] = 0
            return False
        if max_reach[p] > 0.0:
            # Rounded down so that travel < tau implies max_reach * travel < slack.
            t = slack[p] / max_reach[p] * (1.0 - 1e-12)
            if t < horizon:
                j = n
                while j > 0 and tau[j - 1] > t:
                    tau[j] = tau[j - 1]
                    near[j] = near[j - 1]
                    j -= 1
                tau[j] = t
                near[j] = p
                n += 1
    ints[3] = n
    return True


@njit(cache=True)
def _pair_lower_bound(xpos, xmat, a, b, shape, axis, half, radius):
    """Lower bound of the distance between geoms ``a`` and ``b`` from their bounding shapes.

    Segments with radii (spheres, capsules exact; ellipsoids in their enclosing capsule;
    other geoms in their bounding sphere): the segments' distance minus both radii. A
    plane is a half-space: the lowest end of the other geom's segment above it minus its
    radius. Two planes never collide (no collision function): infinity.
    """
    if shape[a] == _SHAPE_PLANE and shape[b] == _SHAPE_PLANE:
        return np.inf
    if shape[a] == _SHAPE_PLANE or shape[b] == _SHAPE_PLANE:
        pl, g = (a, b) if shape[a] == _SHAPE_PLANE else (b, a)
        # Signed height of the segment's ends above the plane (its normal: local z).
        nx, ny, nz = xmat[pl, 2], xmat[pl, 5], xmat[pl, 8]
        ax = axis[g]
        lower = np.inf
        for s in (-1.0, 1.0):
            h = 0.0
            for c in range(3):
                end = xpos[g, c] + s * half[g] * xmat[g, 3 * c + ax]
                h += (end - xpos[pl, c]) * (nx if c == 0 else (ny if c == 1 else nz))
            lower = min(lower, h - radius[g])
        return lower
    aa, ab = axis[a], axis[b]
    ux = 2.0 * half[a] * xmat[a, _ax_index(0, aa)]
    uy = 2.0 * half[a] * xmat[a, _ax_index(1, aa)]
    uz = 2.0 * half[a] * xmat[a, _ax_index(2, aa)]
    vx = 2.0 * half[b] * xmat[b, _ax_index(0, ab)]
    vy = 2.0 * half[b] * xmat[b, _ax_index(1, ab)]
    vz = 2.0 * half[b] * xmat[b, _ax_index(2, ab)]
    # Segment starts: centre minus half the axis.
    rx = (xpos[a, 0] - 0.5 * ux) - (xpos[b, 0] - 0.5 * vx)
    ry = (xpos[a, 1] - 0.5 * uy) - (xpos[b, 1] - 0.5 * vy)
    rz = (xpos[a, 2] - 0.5 * uz) - (xpos[b, 2] - 0.5 * vz)
    distance = _clamped_distance(ux, uy, uz, vx, vy, vz, rx, ry, rz, _dot(ux, uy, uz, ux, uy, uz), 1e-12)
    return distance - radius[a] - radius[b]


@njit(cache=True, inline="always")
def _ax_index(row, axis):
    """Index in a row-major 3x3 ``xmat`` of the world ``row`` component of local axis ``axis``."""
    return 3 * row + axis


@njit(cache=True, _nrt=False)
def _model_unchanged(live, snapshot):
    """True when the model words listed in ``snapshot`` (see ``ContactCertificate._take_snapshot``) are unchanged.

    No early exit inside a range and slices indexed from 0: the XOR-OR then vectorizes
    (~2,000 words here: 0.27 us, against 1.7 us indexing ``live[start + i]``).
    """
    n = snapshot[0]
    k = 1 + 2 * n
    diff = 0
    for r in range(n):
        start, length = snapshot[1 + 2 * r], snapshot[2 + 2 * r]
        now = live[start : start + length]
        then = snapshot[k : k + length]
        for i in range(length):
            diff |= now[i] ^ then[i]
        k += length
    return diff == 0


@njit(cache=True, _nrt=False)
def _certified_now(qpos, ints, floats, live, snapshot, opt_live):
    """:func:`_certificate_holds`, only when the model is still the one the certificate was built
    from (:func:`_model_unchanged`) and the option words ``opt_live`` (see
    ``ContactCertificate._take_snapshot``) are those of the baseline (the last words of ``snapshot``)."""
    n = opt_live.shape[0]
    then = snapshot[snapshot.shape[0] - n :]
    diff = 0
    for i in range(n):
        diff |= opt_live[i] ^ then[i]
    return diff == 0 and _model_unchanged(live, snapshot) and _certificate_holds(qpos, ints, floats)


@njit(cache=True, _nrt=False)
def _certify_step(qpos, ints, floats, live, snapshot, opt_live, disable_index, contact_bit):
    """:func:`_certified_now`, and if so ``contact_bit`` set in the live ``disableflags``.

    Returns the flags as they were (the caller restores them right after ``mj_step1``), or
    -1 when the step is not certified (nothing written) or the flags' sign bit is set.
    """
    if not _certified_now(qpos, ints, floats, live, snapshot, opt_live):
        return -1
    flags = opt_live.view(np.int32)
    old = flags[disable_index]
    if old < 0:
        return -1
    flags[disable_index] = old | contact_bit
    return old


@njit(cache=True)
def _certificate_holds(qpos, ints, floats):
    """True when every pair's possible approach since the baseline, sum R |q - q0|, is below its slack.

    ``ints = [nj, npairs, width, n_near, joint qpos addresses (nj), near pairs (npairs),
    term joints (npairs x width)]``; ``floats = [horizon, clearance, q0 (nj), work (nj),
    tau of the near pairs (npairs), slack (npairs), term reaches (npairs x width), largest
    reach (npairs), margins (npairs)]``. Beyond the horizon of total joint travel ``S``
    the answer is False (the caller takes a new baseline). Else only the near pairs (see
    :func:`_certificate_order`) can be at risk, in increasing ``tau``: once ``S`` is below
    a pair's ``tau``, it and all later ones are safe (``sum R |dq| <= max R * S < slack``);
    the pairs before are tested term by term.
    """
    nj, npairs, width, n_near = ints[0], ints[1], ints[2], ints[3]
    joint_qpos, near = ints[4 : 4 + nj], ints[4 + nj : 4 + nj + npairs]
    term_joint = ints[4 + nj + npairs :].reshape(npairs, width)
    horizon = floats[0]
    q0, dq = floats[2 : 2 + nj], floats[2 + nj : 2 + 2 * nj]
    tau = floats[2 + 2 * nj : 2 + 2 * nj + npairs]
    slack = floats[2 + 2 * nj + npairs : 2 + 2 * nj + 2 * npairs]
    base = 2 + 2 * nj + 2 * npairs
    term_reach = floats[base : base + npairs * width].reshape(npairs, width)
    travel = 0.0
    for i in range(nj):
        dq[i] = abs(qpos[joint_qpos[i]] - q0[i])
        travel += dq[i]
    if not travel < horizon:
        return False
    for i in range(n_near):
        if travel < tau[i]:
            return True
        p = near[i]
        moved = 0.0
        for c in range(width):
            moved += term_reach[p, c] * dq[term_joint[p, c]]
        if not moved < slack[p]:
            return False
    return True
