"""Compiled (numba) per-tick kernel of :class:`~harvest_qp.loop.HarvestController`: the camera
arm's references in one call.

:func:`camera_references` computes, from this tick's camera pose and the laws' filter states,
what :meth:`HarvestController._camera_twist` (V_cr of ``eq:control_signal_rr_world`` with its
filtered p_r, the keep-out term, V_cu's low-pass) and the numpy-free part of
:meth:`HarvestController._roll_reference` compute on Python floats and 3-vector numpy dot
products: the same IEEE operations in the same order, in one call instead of ~20 small numpy
calls and ~100 Python float operations (measured: ~25 + 15 us per 2 ms tick inside the
episode, the rest of the tick evicting their caches). Nothing is mutated except the output
arrays: the caller commits the new filter states (and falls back to the Python path for the
rare degenerate minimum rotation, where the axis is chosen by numpy).

Bit-identical to the Python path, which stays the oracle (tests/loop/test_tick_kernels.py):

* element-wise steps: the same expressions in the same order (numba, without ``fastmath``,
  neither reassociates nor contracts them into fused multiply-adds);
* dot products: numpy's ``a.dot(b)`` of two float64 3-vectors, reproduced bit for bit by
  :func:`harvest_qp.references._kernels.dot3` (OpenBLAS ddot's fused chain; see there, and
  what it means on a machine whose BLAS sums without FMA).
* ``math.atan2`` / ``math.sqrt``: numba calls the same libm ``atan2`` as Python's ``math``
  (tested) and ``sqrt`` is exact. numpy's own ``arctan2`` (the roll angle), which differs from
  libm's in the last bit on ~2 % of arguments, stays in the caller.
"""

from __future__ import annotations

import math

from numba import njit

from harvest_qp.references._kernels import dot3 as _dot3

# _NO_NRT: the per-tick kernels allocate nothing, so they are compiled without numba's reference-
# counted runtime (``_nrt=False``): an array argument is then unboxed without a MemInfo allocated
# and freed per call (measured: 8 array arguments 0.82 -> 0.55 us per call, hot).

# Slots of camera_references' ``out`` (float64, at least OUT_SIZE long).
V0 = 0  # V_cr + keep-out + V_cu, 6 floats [m/s; rad/s]
THETA = 6  # ReachingCentering.theta [rad]
DISTANCE = 7  # ReachingCentering.distance = |p_r - p_c| [m]
ROLL_Y = 8  # (y_c x d) . z_c: np.arctan2's first argument (when the roll is defined)
ROLL_X = 9  # y_c . d: np.arctan2's second argument
ROLL_ANGLE = 10  # left for the caller's np.arctan2(out[ROLL_Y], out[ROLL_X]) (written with out=)
OUT_SIZE = 11

# camera_references' return codes.
DONE = 0  # every output written, the roll defined (ROLL_Y, ROLL_X)
DONE_NO_ROLL = 2  # every output written; no roll (the direction is along z_c)
DEGENERATE = 1  # nothing valid: the minimum rotation is degenerate (use the Python path)

# eq:ktheta_world's axis is undefined below this sine (reaching._PARALLEL_SINE).
_PARALLEL_SINE = 1e-12


@njit(cache=True)
def dot3(a, b):  # pragma: no cover (compiled)
    """numpy's ``a.dot(b)`` of two float64 arrays of length 3, bit for bit (for the tests)."""
    return _dot3(a[0], a[1], a[2], b[0], b[1], b[2])


@njit(cache=True, _nrt=False)  # see _NO_NRT
def camera_references(  # pragma: no cover (compiled)
    pose, roi_centre, roi_target, roi_fraction, radius_squared, k_cp, k_co, keep_out_minimum, k_keep_out,
    unveil, value, raw, unveil_fraction, u0, u1, u2, out, p_r, new_value,
):
    """The camera arm's references of one tick; returns :data:`DONE`, :data:`DONE_NO_ROLL`
    (|direction projected normal to z_c| < 1e-6) or :data:`DEGENERATE` (``|p_r - p_c| = 0`` or
    z_c parallel to it: nothing is valid, use the Python path).

    Args:
        pose: the camera pose, float64 ``(4, 4)``.
        roi_centre, roi_target: the p_r filter's state and target, float64 ``(3,)`` [m].
        roi_fraction: ``-expm1(-dt / tau)`` of the p_r filter (tau > 0).
        radius_squared: ``ReachingCentering.radius ** 2`` [m^2] (Python's, passed in).
        k_cp, k_co: V_cr's gains.
        keep_out_minimum, k_keep_out: the keep-out term's distance [m] (off when <= 0) and gain.
        unveil: add V_cu (unveiling enabled); then ``value``, ``raw`` (float64 ``(6,)``) are
            its low-pass state and input and ``unveil_fraction`` its step fraction.
        u0, u1, u2: the roll reference's direction (the stem's) [unit].
        out: float64 ``(OUT_SIZE,)``, the slots named in this module (V, theta, distance, the roll's).
        p_r: float64 ``(3,)``, receives the new filtered p_r [m].
        new_value: float64 ``(6,)``, receives V_cu's new filter value (when ``unveil``).
    """
    # ReachingCentering._update_floats: the p_r filter, e_pc, the minimum rotation, V_cr.
    r0, r1, r2 = roi_centre[0], roi_centre[1], roi_centre[2]
    g0, g1, g2 = roi_target[0], roi_target[1], roi_target[2]
    p0 = r0 + roi_fraction * (g0 - r0)
    p1 = r1 + roi_fraction * (g1 - r1)
    p2 = r2 + roi_fraction * (g2 - r2)
    y0, y1, y2 = pose[0, 1], pose[1, 1], pose[2, 1]
    z0, z1, z2 = pose[0, 2], pose[1, 2], pose[2, 2]
    c0, c1, c2 = pose[0, 3], pose[1, 3], pose[2, 3]
    e0, e1, e2 = p0 - c0, p1 - c1, p2 - c2
    squared = _dot3(e0, e1, e2, e0, e1, e2)
    norm_e = math.sqrt(squared)
    x0, x1, x2 = z1 * e2 - z2 * e1, z2 * e0 - z0 * e2, z0 * e1 - z1 * e0
    sine = math.sqrt(_dot3(x0, x1, x2, x0, x1, x2))
    cosine = _dot3(z0, z1, z2, e0, e1, e2)
    if norm_e == 0.0 or not sine > _PARALLEL_SINE * norm_e:
        return DEGENERATE
    theta = math.atan2(sine, cosine)
    a0, a1, a2 = x0 / sine, x1 / sine, x2 / sine
    excess = squared - radius_squared
    gain = k_cp * (excess if excess > 0.0 else 0.0)  # Python's max(0.0, excess), NaN included
    turn = k_co * theta
    v0, v1, v2 = gain * e0, gain * e1, gain * e2
    v3, v4, v5 = turn * a0, turn * a1, turn * a2
    # _camera_twist: the keep-out term, then + V_cu (or + zeros: -0.0 becomes 0.0 as numpy's sum).
    distance = norm_e
    if keep_out_minimum > 0 and 1e-9 < distance and distance < keep_out_minimum:
        push = k_keep_out * (keep_out_minimum - distance)
        v0 = v0 + push * (c0 - p0) / distance
        v1 = v1 + push * (c1 - p1) / distance
        v2 = v2 + push * (c2 - p2) / distance
        v3 = v3 + 0.0
        v4 = v4 + 0.0
        v5 = v5 + 0.0
    else:
        v0, v1, v2, v3, v4, v5 = v0 + 0.0, v1 + 0.0, v2 + 0.0, v3 + 0.0, v4 + 0.0, v5 + 0.0
    if unveil:
        for i in range(6):
            new_value[i] = value[i] + unveil_fraction * (raw[i] - value[i])
        v0, v1, v2 = v0 + new_value[0], v1 + new_value[1], v2 + new_value[2]
        v3, v4, v5 = v3 + new_value[3], v4 + new_value[4], v5 + new_value[5]
    else:
        v0, v1, v2, v3, v4, v5 = v0 + 0.0, v1 + 0.0, v2 + 0.0, v3 + 0.0, v4 + 0.0, v5 + 0.0
    out[0], out[1], out[2], out[3], out[4], out[5] = v0, v1, v2, v3, v4, v5
    out[THETA] = theta
    out[DISTANCE] = distance
    p_r[0], p_r[1], p_r[2] = p0, p1, p2
    # HarvestController._roll_reference without np.arctan2: d = u - (u . z) z, y x d.
    along = _dot3(u0, u1, u2, z0, z1, z2)
    d0, d1, d2 = u0 - along * z0, u1 - along * z1, u2 - along * z2
    if math.sqrt(_dot3(d0, d1, d2, d0, d1, d2)) < 1e-6:
        return DONE_NO_ROLL
    w0, w1, w2 = y1 * d2 - y2 * d1, y2 * d0 - y0 * d2, y0 * d1 - y1 * d0
    out[ROLL_Y] = _dot3(w0, w1, w2, z0, z1, z2)
    out[ROLL_X] = _dot3(y0, y1, y2, d0, d1, d2)
    return DONE


@njit(cache=True, _nrt=False)  # see _NO_NRT
def hold_terms(pose, hold_translation, hold_rotation_T, k, linear, rotation):  # pragma: no cover (compiled)
    """The approach's hold twist before pinocchio's log3: ``linear`` = k (p_g - p_hold) [m/s] and
    ``rotation`` = R_g R_hold^T, numpy's ``pose[:3, :3] @ hold_rotation_T`` bit for bit (OpenBLAS's
    3x3 dgemm sums each entry as the same fused chain as its ddot, tests/loop/test_tick_kernels.py).

    ``pose``: the gripper pose, float64 ``(4, 4)``; ``hold_translation`` float64 ``(3,)``;
    ``hold_rotation_T`` float64 ``(3, 3)``; ``k`` = -k_hold; ``linear`` float64 ``(3,)`` or longer
    (slots 0-2 written: the loop hands its new ``(6,)`` twist) and ``rotation`` float64 ``(3, 3)``
    receive the results.
    """
    for i in range(3):
        linear[i] = k * (pose[i, 3] - hold_translation[i])
        for j in range(3):
            rotation[i, j] = _dot3(pose[i, 0], pose[i, 1], pose[i, 2],
                                   hold_rotation_T[0, j], hold_rotation_T[1, j], hold_rotation_T[2, j])


@njit(cache=True, _nrt=False)  # see _NO_NRT
def log_row(  # pragma: no cover (compiled)
    row, with_map, roll_error, map_cells, phase, p_r, pose, p_sb, p_gd, n_c, V_c, V_g, force_nc, theta,
    roi_distance, position_error, alignment, unveiling_pairs,
):
    """:meth:`HarvestController._log_row`'s float64 row, written into ``row`` (copies only):
    ``roll_error``, ``map_cells`` (when ``with_map``), ``phase``, p_r, p_c, z_c, x_c (from
    ``pose``), p_sb, p_gd, n_c (float64 ``(3,)``), V_c, V_g (float64 ``(6,)``) and the six scalars,
    in the layout's order (``controller._LOGGED_VALUES``)."""
    row[0] = roll_error
    i = 1
    if with_map:
        row[1] = map_cells
        i = 2
    row[i] = phase
    for j in range(3):
        row[i + 1 + j] = p_r[j]
        row[i + 4 + j] = pose[j, 3]
        row[i + 7 + j] = pose[j, 2]
        row[i + 10 + j] = pose[j, 0]
        row[i + 13 + j] = p_sb[j]
        row[i + 16 + j] = p_gd[j]
        row[i + 19 + j] = n_c[j]
    for j in range(6):
        row[i + 22 + j] = V_c[j]
        row[i + 28 + j] = V_g[j]
    i += 34
    row[i] = force_nc
    row[i + 1] = theta
    row[i + 2] = roi_distance
    row[i + 3] = position_error
    row[i + 4] = alignment
    row[i + 5] = unveiling_pairs
