"""Compiled (numba) kernels for collision avoidance: kinematics, distances, damper rows.

Everything the collision constraint needs per control step runs in compiled code,
because per-pair work from Python costs ~1 us a pair and the constraint must stay
within a few tens of microseconds for ~200 candidate pairs. The kernels are written
with scalars and explicit loops: small temporary arrays (and BLAS calls on 3x3
matrices) cost more than the arithmetic itself.
"""

from __future__ import annotations

import numpy as np
from numba import njit

REVOLUTE = 0
PRISMATIC = 1


@njit(cache=True, fastmath=False)
def forward_kinematics(q, parent, idx_v, joint_type, axis, place_R, place_p, out_R, out_p):
    """World rotation ``out_R[j]`` and position ``out_p[j]`` of every joint frame (joint 0 = world).

    ``place_R/place_p`` is each joint's fixed placement in its parent joint frame;
    the joint then turns about (or slides along) ``axis[j]`` in its own frame.
    """
    for i in range(3):
        out_p[0, i] = 0.0
        for k in range(3):
            out_R[0, i, k] = 1.0 if i == k else 0.0
    R = np.empty((3, 3))
    M = np.empty((3, 3))
    for j in range(1, parent.shape[0]):
        pj = parent[j]
        for i in range(3):
            acc = out_p[pj, i]
            for k in range(3):
                acc += out_R[pj, i, k] * place_p[j, k]
            out_p[j, i] = acc
            for c in range(3):
                acc = 0.0
                for k in range(3):
                    acc += out_R[pj, i, k] * place_R[j, k, c]
                R[i, c] = acc
        x = q[idx_v[j]]
        ax, ay, az = axis[j, 0], axis[j, 1], axis[j, 2]
        if joint_type[j] == REVOLUTE:
            c, s = np.cos(x), np.sin(x)
            t = 1.0 - c
            M[0, 0] = c + ax * ax * t
            M[0, 1] = ax * ay * t - az * s
            M[0, 2] = ax * az * t + ay * s
            M[1, 0] = ay * ax * t + az * s
            M[1, 1] = c + ay * ay * t
            M[1, 2] = ay * az * t - ax * s
            M[2, 0] = az * ax * t - ay * s
            M[2, 1] = az * ay * t + ax * s
            M[2, 2] = c + az * az * t
            for i in range(3):
                for cc in range(3):
                    out_R[j, i, cc] = R[i, 0] * M[0, cc] + R[i, 1] * M[1, cc] + R[i, 2] * M[2, cc]
        else:
            for i in range(3):
                for cc in range(3):
                    out_R[j, i, cc] = R[i, cc]
                out_p[j, i] += (R[i, 0] * ax + R[i, 1] * ay + R[i, 2] * az) * x


@njit(cache=True)
def capsule_world(cap_joint, cap_p0, cap_p1, joint_R, joint_p, out0, out1):
    """World end points of every capsule from the joint placements."""
    for c in range(cap_joint.shape[0]):
        j = cap_joint[c]
        for i in range(3):
            a = joint_p[j, i]
            b = joint_p[j, i]
            for k in range(3):
                a += joint_R[j, i, k] * cap_p0[c, k]
                b += joint_R[j, i, k] * cap_p1[c, k]
            out0[c, i] = a
            out1[c, i] = b


@njit(cache=True)
def _clamp01(x):
    return 0.0 if x < 0.0 else (1.0 if x > 1.0 else x)


@njit(cache=True)
def segment_distance(p0x, p0y, p0z, p1x, p1y, p1z, q0x, q0y, q0z, q1x, q1y, q1z):
    """Closest points of segments p0-p1 and q0-q1 (either may be a point).

    Returns ``(distance, s, t)`` with the witness points ``p0 + s (p1 - p0)`` and
    ``q0 + t (q1 - q0)``, ``s, t`` in [0, 1] (Ericson, Real-Time Collision Detection 5.1.9).
    """
    d1x, d1y, d1z = p1x - p0x, p1y - p0y, p1z - p0z
    d2x, d2y, d2z = q1x - q0x, q1y - q0y, q1z - q0z
    rx, ry, rz = p0x - q0x, p0y - q0y, p0z - q0z
    a = d1x * d1x + d1y * d1y + d1z * d1z
    e = d2x * d2x + d2y * d2y + d2z * d2z
    f = d2x * rx + d2y * ry + d2z * rz
    eps = 1e-14
    if a <= eps and e <= eps:
        s = 0.0
        t = 0.0
    elif a <= eps:
        s = 0.0
        t = _clamp01(f / e)
    else:
        c = d1x * rx + d1y * ry + d1z * rz
        if e <= eps:
            t = 0.0
            s = _clamp01(-c / a)
        else:
            b = d1x * d2x + d1y * d2y + d1z * d2z
            denom = a * e - b * b
            # Parallel segments (denom ~ 0): any s works, start from s = 0.
            s = _clamp01((b * f - c * e) / denom) if denom > eps * a * e else 0.0
            t = (b * s + f) / e
            if t < 0.0:
                t = 0.0
                s = _clamp01(-c / a)
            elif t > 1.0:
                t = 1.0
                s = _clamp01((b - c) / a)
    wx = rx + s * d1x - t * d2x
    wy = ry + s * d1y - t * d2y
    wz = rz + s * d1z - t * d2z
    return np.sqrt(wx * wx + wy * wy + wz * wz), s, t


@njit(cache=True)
def pair_distances(pair_a, pair_b, cap_radius, w0, w1, influence, out_d, out_s, out_t):
    """Surface distance [m] of each candidate pair, skipping far pairs cheaply.

    Pairs whose bounding spheres are farther apart than ``influence`` get
    ``out_d = inf`` without the exact segment test (the broadphase).
    """
    # Bounding sphere (centre and radius) of each capsule, once per capsule instead of twice
    # per pair; the test on squared distances needs no square root per pair. It only decides
    # which pairs get the exact test: a pair it passes gets the same exact distance as before.
    m = cap_radius.shape[0]
    centre = np.empty((m, 3))
    bound = np.empty(m)
    for c in range(m):
        dx, dy, dz = w1[c, 0] - w0[c, 0], w1[c, 1] - w0[c, 1], w1[c, 2] - w0[c, 2]
        bound[c] = 0.5 * np.sqrt(dx * dx + dy * dy + dz * dz) + cap_radius[c]
        centre[c, 0] = 0.5 * (w0[c, 0] + w1[c, 0])
        centre[c, 1] = 0.5 * (w0[c, 1] + w1[c, 1])
        centre[c, 2] = 0.5 * (w0[c, 2] + w1[c, 2])
    for k in range(pair_a.shape[0]):
        a = pair_a[k]
        b = pair_b[k]
        cx = centre[a, 0] - centre[b, 0]
        cy = centre[a, 1] - centre[b, 1]
        cz = centre[a, 2] - centre[b, 2]
        reach = influence + bound[a] + bound[b]
        if cx * cx + cy * cy + cz * cz > reach * reach:
            out_d[k] = np.inf
            continue
        dist, s, t = segment_distance(
            w0[a, 0], w0[a, 1], w0[a, 2], w1[a, 0], w1[a, 1], w1[a, 2],
            w0[b, 0], w0[b, 1], w0[b, 2], w1[b, 0], w1[b, 1], w1[b, 2],
        )
        out_d[k] = dist - cap_radius[a] - cap_radius[b]
        out_s[k] = s
        out_t[k] = t


@njit(cache=True)
def _add_point_row(px, py, pz, joint, support, joint_type, joint_R, joint_p, axis, idx_v, scale, nx, ny, nz, G, r):
    """Add ``scale * n^T dv(p)/dqdot`` to row ``G[r]`` for a point fixed to ``joint``'s body."""
    for k in range(1, support.shape[1]):
        if not support[joint, k]:
            continue
        ax = joint_R[k, 0, 0] * axis[k, 0] + joint_R[k, 0, 1] * axis[k, 1] + joint_R[k, 0, 2] * axis[k, 2]
        ay = joint_R[k, 1, 0] * axis[k, 0] + joint_R[k, 1, 1] * axis[k, 1] + joint_R[k, 1, 2] * axis[k, 2]
        az = joint_R[k, 2, 0] * axis[k, 0] + joint_R[k, 2, 1] * axis[k, 1] + joint_R[k, 2, 2] * axis[k, 2]
        if joint_type[k] == REVOLUTE:
            rx, ry, rz = px - joint_p[k, 0], py - joint_p[k, 1], pz - joint_p[k, 2]
            vx = ay * rz - az * ry
            vy = az * rx - ax * rz
            vz = ax * ry - ay * rx
            G[r, idx_v[k]] += scale * (nx * vx + ny * vy + nz * vz)
        else:
            G[r, idx_v[k]] += scale * (nx * ax + ny * ay + nz * az)


@njit(cache=True)
def damper_rows(
    n_rows, row_pair, row_s, row_t, row_d, pair_a, pair_b, cap_joint, w0, w1,
    support, joint_type, joint_R, joint_p, axis, idx_v,
    safety, influence, gain, recovery_time, G, h, normals,
):
    """Velocity-damper rows ``-n^T (J_a - J_b) qdot <= h(d)``, one per witness pair.

    Row ``r`` constrains the distance between the point ``s = row_s[r]`` of capsule
    ``a`` and ``t = row_t[r]`` of ``b`` of pair ``row_pair[r]`` (surface distance
    ``row_d[r]``). ``n`` is the unit vector from the witness point on ``b`` to the one on
    ``a``, so ``n^T (J_a - J_b) qdot`` is the rate of change of the distance. Outside the
    safety distance ``h = gain (d - d_s) / (d_i - d_s)`` (the damper); inside it the row
    asks for the separation speed ``(d_s - d) / recovery_time`` if that is larger (the
    solver lowers it to what the acceleration limit allows). Rows past ``n_rows``
    are left inactive (zero, bound 1e30).
    """
    G[:] = 0.0
    h[:] = 1e30
    for r in range(n_rows):
        k = row_pair[r]
        a = pair_a[k]
        b = pair_b[k]
        s = row_s[r]
        t = row_t[r]
        pax = w0[a, 0] + s * (w1[a, 0] - w0[a, 0])
        pay = w0[a, 1] + s * (w1[a, 1] - w0[a, 1])
        paz = w0[a, 2] + s * (w1[a, 2] - w0[a, 2])
        pbx = w0[b, 0] + t * (w1[b, 0] - w0[b, 0])
        pby = w0[b, 1] + t * (w1[b, 1] - w0[b, 1])
        pbz = w0[b, 2] + t * (w1[b, 2] - w0[b, 2])
        nx, ny, nz = pax - pbx, pay - pby, paz - pbz
        norm = np.sqrt(nx * nx + ny * ny + nz * nz)
        if norm < 1e-9:
            # Segments intersect: separate along the line between the capsule centres.
            nx = 0.5 * (w0[a, 0] + w1[a, 0] - w0[b, 0] - w1[b, 0])
            ny = 0.5 * (w0[a, 1] + w1[a, 1] - w0[b, 1] - w1[b, 1])
            nz = 0.5 * (w0[a, 2] + w1[a, 2] - w0[b, 2] - w1[b, 2])
            norm = np.sqrt(nx * nx + ny * ny + nz * nz)
            if norm < 1e-12:
                nx, ny, nz, norm = 0.0, 0.0, 1.0, 1.0
        nx /= norm
        ny /= norm
        nz /= norm
        normals[r, 0] = nx
        normals[r, 1] = ny
        normals[r, 2] = nz
        _add_point_row(pax, pay, paz, cap_joint[a], support, joint_type, joint_R, joint_p, axis, idx_v,
                       -1.0, nx, ny, nz, G, r)
        _add_point_row(pbx, pby, pbz, cap_joint[b], support, joint_type, joint_R, joint_p, axis, idx_v,
                       1.0, nx, ny, nz, G, r)
        d = row_d[r]
        bound = gain * (d - safety) / (influence - safety)
        if d < safety:
            bound = min(bound, (d - safety) / recovery_time)
        h[r] = bound


@njit(cache=True)
def _point(w0, w1, c, u):
    return (w0[c, 0] + u * (w1[c, 0] - w0[c, 0]), w0[c, 1] + u * (w1[c, 1] - w0[c, 1]),
            w0[c, 2] + u * (w1[c, 2] - w0[c, 2]))


@njit(cache=True)
def end_point_rows(
    n, close, pair_a, pair_b, cap_radius, w0, w1, s_arr, t_arr, influence, min_offset, max_extra,
    row_pair, row_s, row_t, row_d,
):
    """Extra witness rows at the segments' end points; returns how many were added after row ``n``.

    The capsule distance is the minimum of smooth pieces (interior-interior and the
    four end-point-to-segment distances). One row on the closest piece does not stop
    another piece from shrinking: two near-parallel links can turn about the witness
    point while their other ends close in, and the witness jumps there one tick too
    late. Every end-point piece within ``d_i`` whose witness points lie more than
    ``min_offset`` [m] from the main witness gets its own damper row (the closest
    ``max_extra`` of them), so each piece, hence the minimum, is held above ``d_s``.
    """
    cand_pair = np.empty(4 * n, dtype=np.int64)
    cand_s = np.empty(4 * n)
    cand_t = np.empty(4 * n)
    cand_d = np.empty(4 * n)
    m = 0
    taken = np.empty((5, 6))  # witness points already given a row for this pair
    for r in range(n):
        k = close[r]
        a = pair_a[k]
        b = pair_b[k]
        taken[0, 0], taken[0, 1], taken[0, 2] = _point(w0, w1, a, s_arr[k])
        taken[0, 3], taken[0, 4], taken[0, 5] = _point(w0, w1, b, t_arr[k])
        n_taken = 1
        for e in range(4):
            if e < 2:
                px, py, pz = _point(w0, w1, a, float(e))
                dist, _, t = segment_distance(px, py, pz, px, py, pz,
                                              w0[b, 0], w0[b, 1], w0[b, 2], w1[b, 0], w1[b, 1], w1[b, 2])
                s = float(e)
            else:
                px, py, pz = _point(w0, w1, b, float(e - 2))
                dist, _, s = segment_distance(px, py, pz, px, py, pz,
                                              w0[a, 0], w0[a, 1], w0[a, 2], w1[a, 0], w1[a, 1], w1[a, 2])
                t = float(e - 2)
            d = dist - cap_radius[a] - cap_radius[b]
            if d >= influence:
                continue
            ax, ay, az = _point(w0, w1, a, s)
            bx, by, bz = _point(w0, w1, b, t)
            duplicate = False
            for j in range(n_taken):
                offset = max(
                    np.sqrt((ax - taken[j, 0]) ** 2 + (ay - taken[j, 1]) ** 2 + (az - taken[j, 2]) ** 2),
                    np.sqrt((bx - taken[j, 3]) ** 2 + (by - taken[j, 4]) ** 2 + (bz - taken[j, 5]) ** 2),
                )
                if offset < min_offset:
                    duplicate = True
                    break
            if duplicate:
                continue
            taken[n_taken, 0], taken[n_taken, 1], taken[n_taken, 2] = ax, ay, az
            taken[n_taken, 3], taken[n_taken, 4], taken[n_taken, 5] = bx, by, bz
            n_taken += 1
            cand_pair[m] = k
            cand_s[m] = s
            cand_t[m] = t
            cand_d[m] = d
            m += 1
    order = np.argsort(cand_d[:m], kind="mergesort")
    extra = min(m, max_extra)
    for i in range(extra):
        c = order[i]
        row_pair[n + i] = cand_pair[c]
        row_s[n + i] = cand_s[c]
        row_t[n + i] = cand_t[c]
        row_d[n + i] = cand_d[c]
    return extra


@njit(cache=True)
def collision_step(
    q, parent, idx_v, joint_type, axis, place_R, place_p, joint_R, joint_p,
    cap_joint, cap_p0, cap_p1, cap_radius, w0, w1, pair_a, pair_b, dist, s_arr, t_arr,
    support, safety, influence, gain, recovery_time, max_rows, max_extra, min_offset,
    G, h, normals, selected, row_pair, row_s, row_t, row_d,
):
    """Kinematics, broadphase, distances, N-closest selection and damper rows in one call.

    Returns ``(n_pairs, n_rows)``: ``selected[:n_pairs]`` holds the pair indices of the
    first ``n_pairs`` rows (their closest points), rows ``n_pairs..n_rows`` are end-point rows.
    """
    forward_kinematics(q, parent, idx_v, joint_type, axis, place_R, place_p, joint_R, joint_p)
    capsule_world(cap_joint, cap_p0, cap_p1, joint_R, joint_p, w0, w1)
    pair_distances(pair_a, pair_b, cap_radius, w0, w1, influence, dist, s_arr, t_arr)
    n = 0
    for k in range(dist.shape[0]):
        if dist[k] < influence:
            n += 1
    close = np.empty(n, dtype=np.int64)
    n = 0
    for k in range(dist.shape[0]):
        if dist[k] < influence:
            close[n] = k
            n += 1
    if n > max_rows:
        order = np.argsort(dist[close], kind="mergesort")  # stable: ties keep pair order
        close = close[order[:max_rows]]
        n = max_rows
    for r in range(n):
        k = close[r]
        selected[r] = k
        row_pair[r] = k
        row_s[r] = s_arr[k]
        row_t[r] = t_arr[k]
        row_d[r] = dist[k]
    extra = 0
    if max_extra > 0:
        extra = end_point_rows(n, close, pair_a, pair_b, cap_radius, w0, w1, s_arr, t_arr, influence,
                               min_offset, max_extra, row_pair, row_s, row_t, row_d)
    damper_rows(
        n + extra, row_pair, row_s, row_t, row_d, pair_a, pair_b, cap_joint, w0, w1,
        support, joint_type, joint_R, joint_p, axis, idx_v, safety, influence, gain, recovery_time, G, h, normals,
    )
    return n, n + extra


@njit(cache=True)
def clamp_approach_rows(h, approach_pair, row_pair, n_rows):
    """``h[r] = 0`` where row ``r``'s pair is approach-only and ``h[r] < 0`` ("no further approach")."""
    for r in range(n_rows):
        if approach_pair[row_pair[r]] and h[r] < 0.0:
            h[r] = 0.0


@njit(cache=True)
def collision_step_clamped(
    q, parent, idx_v, joint_type, axis, place_R, place_p, joint_R, joint_p,
    cap_joint, cap_p0, cap_p1, cap_radius, w0, w1, pair_a, pair_b, dist, s_arr, t_arr,
    support, safety, influence, gain, recovery_time, max_rows, max_extra, min_offset,
    G, h, normals, selected, row_pair, row_s, row_t, row_d, approach_pair, clamp,
):
    """:func:`collision_step`, then (with ``clamp``) :func:`clamp_approach_rows` on its rows: the
    collision limit's two compiled calls in one."""
    n, n_rows = collision_step(
        q, parent, idx_v, joint_type, axis, place_R, place_p, joint_R, joint_p,
        cap_joint, cap_p0, cap_p1, cap_radius, w0, w1, pair_a, pair_b, dist, s_arr, t_arr,
        support, safety, influence, gain, recovery_time, max_rows, max_extra, min_offset,
        G, h, normals, selected, row_pair, row_s, row_t, row_d,
    )
    if clamp and n_rows:
        clamp_approach_rows(h, approach_pair, row_pair, n_rows)
    return n, n_rows
