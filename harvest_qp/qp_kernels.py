"""Compiled helpers for assembling the task QP (small dense loops beat numpy's per-call overhead)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def accumulate_task(H, f, J, w, v):
    """``H += J^T diag(w) J`` and ``f -= J^T diag(w) v`` for one task."""
    m, n = J.shape
    for r in range(m):
        wr = w[r]
        if wr == 0.0:
            continue
        wv = wr * v[r]
        for i in range(n):
            wji = wr * J[r, i]
            if wji == 0.0:
                continue
            f[i] -= J[r, i] * wv
            for k in range(n):
                H[i, k] += wji * J[r, k]


@njit(cache=True)
def accumulate_diagonal(H, f, w, v, floor):
    """``H += diag(w)``, ``f -= w * v`` and ``floor += w`` for a joint-space task (``J = I``);
    ``floor`` sums the diagonal weight joint-space tasks put on each joint."""
    for i in range(w.shape[0]):
        H[i, i] += w[i]
        f[i] -= w[i] * v[i]
        floor[i] += w[i]


@njit(cache=True)
def rotate_twist_rows(R, J, v, J_out, v_out):
    """Rows of a world-aligned twist task expressed in the frame's axes: ``blkdiag(R^T, R^T)``."""
    rotate_twist(R, v, v_out)
    n = J.shape[1]
    for b in range(2):
        o = 3 * b
        for i in range(3):
            for c in range(n):
                acc = 0.0
                for k in range(3):
                    acc += R[k, i] * J[o + k, c]
                J_out[o + i, c] = acc


@njit(cache=True)
def rotate_twist(R, v, v_out):
    """The ``v`` part of :func:`rotate_twist_rows` alone: ``blkdiag(R^T, R^T) v``."""
    for b in range(2):
        o = 3 * b
        for i in range(3):
            acc = 0.0
            for k in range(3):
                acc += R[k, i] * v[o + k]
            v_out[o + i] = acc


@njit(cache=True)
def clip_inplace(x, lower, upper):
    """Clip ``x`` to ``[lower, upper]`` in place; returns ``x``."""
    for i in range(x.shape[0]):
        if x[i] < lower[i]:
            x[i] = lower[i]
        elif x[i] > upper[i]:
            x[i] = upper[i]
    return x


@njit(cache=True)
def intersect_boxes(lowers, uppers, lower, upper, conflict):
    """Intersect boxes row by row (rows in priority order); a later row that does not
    overlap the running box is moved onto the running box's nearest point.

    ``conflict[j]`` is set to the index of the first yielding row for joint ``j`` (-1: none);
    returns the number of joints with a conflict.
    """
    k, n = lowers.shape
    n_conflicts = 0
    for j in range(n):
        lo = -1e30
        hi = 1e30
        conflict[j] = -1
        for r in range(k):
            new_lo = max(lo, lowers[r, j])
            new_hi = min(hi, uppers[r, j])
            if new_lo > new_hi:
                if conflict[j] < 0:
                    conflict[j] = r
                    n_conflicts += 1
                # The yielding box lies entirely above or below: keep the nearest point.
                target = hi if lowers[r, j] > hi else lo
                new_lo = target
                new_hi = target
            lo = new_lo
            hi = new_hi
        lower[j] = lo
        upper[j] = hi
    return n_conflicts


@njit(cache=True)
def acceleration_bounds(previous, max_acceleration, dt, lower, upper):
    """``previous -+ max_acceleration * dt``: the velocities reachable in one step [rad/s]."""
    for i in range(previous.shape[0]):
        step = max_acceleration[i] * dt
        lower[i] = previous[i] - step
        upper[i] = previous[i] + step


@njit(cache=True)
def all_finite(x):
    """True when no entry of the 1-D array ``x`` is NaN or infinite."""
    for i in range(x.shape[0]):
        if not np.isfinite(x[i]):
            return False
    return True


@njit(cache=True)
def add_to_diagonal(H, value):
    """``H += value * I`` in place."""
    for i in range(H.shape[0]):
        H[i, i] += value


@njit(cache=True)
def position_limit_bounds(q, q_min, q_max, gain, dt, max_acceleration, lower, upper):
    """Velocity bounds [rad/s] keeping ``q + qdot dt`` in ``[q_min, q_max]``.

    ``gain * (q_min - q) / dt <= qdot <= gain * (q_max - q) / dt``; with a non-empty
    ``max_acceleration`` the bounds are also capped at the braking speed
    ``sqrt(2 a margin)`` (only inside the range: outside, the plain bound returns the joint).
    """
    braking = max_acceleration.shape[0] > 0
    for i in range(q.shape[0]):
        below = q_min[i] - q[i]
        above = q_max[i] - q[i]
        lo = gain * below / dt
        hi = gain * above / dt
        if braking:
            hi = min(hi, np.sqrt(2.0 * max_acceleration[i] * max(above, 0.0)))
            lo = max(lo, -np.sqrt(2.0 * max_acceleration[i] * max(-below, 0.0)))
        lower[i] = lo
        upper[i] = hi


@njit(cache=True)
def max_violation(x, lower, upper, A, b, G, h):
    """Largest violation of ``lower <= x <= upper``, ``A x = b`` and ``G x <= h`` (0 if feasible).

    A non-finite ``x`` counts as an infinite violation.
    """
    worst = 0.0
    for i in range(x.shape[0]):
        if not np.isfinite(x[i]):
            return np.inf
        worst = max(worst, lower[i] - x[i], x[i] - upper[i])
    for r in range(A.shape[0]):
        acc = -b[r]
        for i in range(x.shape[0]):
            acc += A[r, i] * x[i]
        worst = max(worst, abs(acc))
    for r in range(G.shape[0]):
        if h[r] >= 1e29:
            continue
        acc = -h[r]
        for i in range(x.shape[0]):
            acc += G[r, i] * x[i]
        worst = max(worst, acc)
    return worst


@njit(cache=True)
def max_scaled_violation(x, lower, upper, A, b, G, h):
    """Largest violation of the constraints, each row relative to its own scale.

    A row ``g x <= h`` counts ``(g x - h) / (1 + |h| + sum_i |g_i x_i|)``, a bound
    ``x_i <= u_i`` counts ``(x_i - u_i) / (1 + |u_i|)``: a rounding error on terms of
    size ~1 is ~1e-16 whatever the row's units. A non-finite ``x`` is infinite.
    """
    worst = 0.0
    for i in range(x.shape[0]):
        if not np.isfinite(x[i]):
            return np.inf
        if lower[i] > -1e29:
            worst = max(worst, (lower[i] - x[i]) / (1.0 + abs(lower[i])))
        if upper[i] < 1e29:
            worst = max(worst, (x[i] - upper[i]) / (1.0 + abs(upper[i])))
    for r in range(A.shape[0]):
        acc = -b[r]
        size = 1.0 + abs(b[r])
        for i in range(x.shape[0]):
            term = A[r, i] * x[i]
            acc += term
            size += abs(term)
        worst = max(worst, abs(acc) / size)
    for r in range(G.shape[0]):
        if h[r] >= 1e29:
            continue
        acc = -h[r]
        size = 1.0 + abs(h[r])
        for i in range(x.shape[0]):
            term = G[r, i] * x[i]
            acc += term
            size += abs(term)
        worst = max(worst, acc / size)
    return worst


@njit(cache=True)
def top_up_diagonal(H, floor, value):
    """``H[i, i] += max(value - floor[i], 0)``: a diagonal of at least ``value`` where tasks left less."""
    for i in range(H.shape[0]):
        if floor[i] < value:
            H[i, i] += value - floor[i]


@njit(cache=True)
def weighted_rows(J, w, out, start):
    """Rows ``sqrt(w_r) J_r`` of the rows with ``w_r > 0``, written from row ``start`` of ``out``.

    The same products as ``(np.sqrt(w)[:, None] * J)[w > 0]`` (bit for bit); returns the
    row after the last one written.
    """
    r_out = start
    for r in range(J.shape[0]):
        if w[r] > 0.0:
            scale = np.sqrt(w[r])
            for c in range(J.shape[1]):
                out[r_out, c] = scale * J[r, c]
            r_out += 1
    return r_out


@njit(cache=True)
def weighted_identity_rows(w, out, start):
    """:func:`weighted_rows` for ``J = I`` (a joint-space task)."""
    r_out = start
    n = w.shape[0]
    for r in range(n):
        if w[r] > 0.0:
            scale = np.sqrt(w[r])
            for c in range(out.shape[1]):
                out[r_out, c] = scale * (1.0 if c == r else 0.0)
            r_out += 1
    return r_out


@njit(cache=True)
def load_daqp_rows(A_buf, upper, lower, sense, A, b, G, h, box_lower, box_upper, n_eq_before, inf):
    """Write one QP into DAQP's fixed layout: ``n`` bounds, ``n`` equality slots, the inequality rows.

    Equality slots past ``A``'s rows are cleared (free rows) when this QP or the one before
    had equalities; returns the number of equality rows now loaded.
    """
    n = A_buf.shape[1]
    n_eq = A.shape[0]
    if n_eq > 0 or n_eq_before > 0:
        for r in range(n):
            if r < n_eq:
                for c in range(n):
                    A_buf[r, c] = A[r, c]
                upper[n + r] = b[r]
                lower[n + r] = b[r]
                sense[n + r] = 5
            else:
                for c in range(n):
                    A_buf[r, c] = 0.0
                upper[n + r] = inf
                lower[n + r] = -inf
                sense[n + r] = 0
    for r in range(G.shape[0]):
        for c in range(n):
            A_buf[n + r, c] = G[r, c]
        upper[2 * n + r] = h[r]
    for i in range(n):
        upper[i] = box_upper[i]
        lower[i] = box_lower[i]
    return n_eq


@njit(cache=True)
def orthonormal_rows_qr(A, c, tol, rows_out, rhs_out):
    """Orthonormal rows spanning the rows of ``A`` (m x n) and the right-hand side that keeps
    ``A x = c``: Householder QR of ``A^T`` with column pivoting (``A^T P = Q R``).

    Writes the ``rank`` rows of ``Q^T`` into ``rows_out[:rank]`` and ``y`` with
    ``R11^T y = (P^T c)[:rank]`` into ``rhs_out[:rank]``; returns ``rank``, the number of
    pivots with ``|R_kk| > tol * max(1, |R_00|)`` (``|R_00|``: the largest row norm of ``A``).
    For consistent ``c`` (``c = A x0``), ``{x : rows x = y}`` is ``{x : A x = c}``.
    """
    m, n = A.shape
    M = np.empty((n, m))  # A^T, overwritten by R above the diagonal and the reflectors below
    for i in range(m):
        for j in range(n):
            M[j, i] = A[i, j]
    piv = np.arange(m)
    beta = np.zeros(n)
    diag = np.zeros(min(m, n))
    steps = min(m, n)
    rank = 0
    threshold = 0.0
    for k in range(steps):
        # Pivot: the remaining column (row of A) with the largest norm below row k (recomputed,
        # not downdated: exact on these small sizes).
        best = -1.0
        p = k
        for col in range(k, m):
            acc = 0.0
            for r in range(k, n):
                acc += M[r, col] * M[r, col]
            if acc > best:
                best = acc
                p = col
        if p != k:
            for r in range(n):
                tmp = M[r, k]
                M[r, k] = M[r, p]
                M[r, p] = tmp
            tmp_i = piv[k]
            piv[k] = piv[p]
            piv[p] = tmp_i
        norm = np.sqrt(best)
        if k == 0:
            threshold = tol * max(1.0, norm)
        if not norm > threshold:
            break
        # Householder reflector H = I - beta v v^T with v[k] = 1 mapping M[k:, k] to alpha e_k.
        x0 = M[k, k]
        alpha = -norm if x0 >= 0.0 else norm
        v0 = x0 - alpha
        for r in range(k + 1, n):
            M[r, k] /= v0
        beta[k] = -v0 / alpha
        M[k, k] = alpha
        diag[k] = alpha
        for col in range(k + 1, m):
            acc = M[k, col]
            for r in range(k + 1, n):
                acc += M[r, k] * M[r, col]
            acc *= beta[k]
            M[k, col] -= acc
            for r in range(k + 1, n):
                M[r, col] -= acc * M[r, k]
        rank += 1
    # Q[:, :rank] = H_0 H_1 ... H_{rank-1} [e_0 .. e_{rank-1}], built backwards; rows_out = Q^T.
    Q = np.zeros((n, rank))
    for j in range(rank):
        Q[j, j] = 1.0
    for k in range(rank - 1, -1, -1):
        for j in range(rank):
            acc = Q[k, j]
            for r in range(k + 1, n):
                acc += M[r, k] * Q[r, j]
            acc *= beta[k]
            Q[k, j] -= acc
            for r in range(k + 1, n):
                Q[r, j] -= acc * M[r, k]
    for j in range(rank):
        for r in range(n):
            rows_out[j, r] = Q[r, j]
    # R11^T y = c[piv[:rank]] (R11 upper triangular: forward substitution).
    for i in range(rank):
        acc = c[piv[i]]
        for j in range(i):
            acc -= M[j, i] * rhs_out[j]
        rhs_out[i] = acc / M[i, i]
    return rank


@njit(cache=True)
def builtin_boxes(q, q_min, q_max, gain, dt, braking, max_velocity, previous, max_acceleration, lowers, uppers,
                  lower, upper, conflict):
    """The boxes of the built-in joint limits and their intersection, in one call.

    Rows of ``lowers`` / ``uppers``: 0 ``JointVelocityLimit`` (``-+max_velocity``), 1
    ``JointPositionLimit`` (:func:`position_limit_bounds`), 2 ``JointAccelerationLimit``
    (:func:`acceleration_bounds`); then :func:`intersect_boxes` into ``lower`` / ``upper``.
    The same arithmetic as the limits' own ``fill_box`` and the solver's intersection.
    Returns the number of conflicting joints, or -1 (nothing written) when a size does
    not fit ``q`` (the caller then takes the checked path).
    """
    n = q.shape[0]
    if (q_min.shape[0] != n or q_max.shape[0] != n or max_velocity.shape[0] != n or previous.shape[0] != n
            or max_acceleration.shape[0] != n or (braking.shape[0] != 0 and braking.shape[0] != n)
            or lowers.shape[0] < 3 or lowers.shape[1] != n or uppers.shape[0] < 3 or uppers.shape[1] != n
            or lower.shape[0] != n or upper.shape[0] != n or conflict.shape[0] != n):
        return -1
    for i in range(n):
        lowers[0, i] = -max_velocity[i]
        uppers[0, i] = max_velocity[i]
    position_limit_bounds(q, q_min, q_max, gain, dt, braking, lowers[1], uppers[1])
    acceleration_bounds(previous, max_acceleration, dt, lowers[2], uppers[2])
    return intersect_boxes(lowers[:3], uppers[:3], lower, upper, conflict)


#: Stands for ``J = I`` (a joint-space task) in the fused level kernels (a task has >= 1 row).
IDENTITY_ROWS = np.zeros((0, 0))


@njit(cache=True)
def _add_task(H, f, floor, J, w, v):
    if J.shape[0] == 0:
        accumulate_diagonal(H, f, w, v, floor)
    else:
        accumulate_task(H, f, J, w, v)


# One call per level for 1..4 tasks: the per-task kernels in task order, then the diagonal
# top-up (the same operations as calling them one by one, in one dispatch).
@njit(cache=True)
def assemble_level_1(H, f, floor, reg, J0, w0, v0):
    """``H``, ``f`` of one level from 1 task (``J`` = :data:`IDENTITY_ROWS` for ``I``), then the top-up."""
    _add_task(H, f, floor, J0, w0, v0)
    top_up_diagonal(H, floor, reg)


@njit(cache=True)
def assemble_level_2(H, f, floor, reg, J0, w0, v0, J1, w1, v1):
    """:func:`assemble_level_1` for 2 tasks."""
    _add_task(H, f, floor, J0, w0, v0)
    _add_task(H, f, floor, J1, w1, v1)
    top_up_diagonal(H, floor, reg)


@njit(cache=True)
def assemble_level_3(H, f, floor, reg, J0, w0, v0, J1, w1, v1, J2, w2, v2):
    """:func:`assemble_level_1` for 3 tasks."""
    _add_task(H, f, floor, J0, w0, v0)
    _add_task(H, f, floor, J1, w1, v1)
    _add_task(H, f, floor, J2, w2, v2)
    top_up_diagonal(H, floor, reg)


@njit(cache=True)
def assemble_level_4(H, f, floor, reg, J0, w0, v0, J1, w1, v1, J2, w2, v2, J3, w3, v3):
    """:func:`assemble_level_1` for 4 tasks."""
    _add_task(H, f, floor, J0, w0, v0)
    _add_task(H, f, floor, J1, w1, v1)
    _add_task(H, f, floor, J2, w2, v2)
    _add_task(H, f, floor, J3, w3, v3)
    top_up_diagonal(H, floor, reg)


@njit(cache=True)
def _weighted_into(J, w, out, start):
    if J.shape[0] == 0:  # IDENTITY_ROWS: a joint-space task
        return weighted_identity_rows(w, out, start)
    return weighted_rows(J, w, out, start)


@njit(cache=True)
def _equalities_from_stack(stack, m, x, tol):
    """Orthonormal rows and right-hand side of ``stack[:m] x' = stack[:m] x`` (:func:`orthonormal_rows_qr`)."""
    n = stack.shape[1]
    c = np.empty(m)
    for i in range(m):
        acc = 0.0
        for j in range(n):
            acc += stack[i, j] * x[j]
        c[i] = acc
    k = min(m, n)
    rows = np.empty((k, n))
    rhs = np.empty(k)
    rank = orthonormal_rows_qr(stack[:m], c, tol, rows, rhs)
    return rows[:rank], rhs[:rank]


# The equalities that hold a level's optimum for the levels below, in one call for a level of
# 1..4 tasks: ``A`` stacked over each task's rows ``sqrt(w_r) J_r`` (w_r > 0), the stack times
# the level's solution ``x`` as right-hand side, then the orthonormal rows of that system.
@njit(cache=True)
def level_equalities_1(A, x, tol, stack, J0, w0):
    """``(rows, rhs)`` for a level of 1 task (``J`` = :data:`IDENTITY_ROWS` for ``I``); ``stack`` is scratch."""
    r = A.shape[0]
    stack[:r] = A
    r = _weighted_into(J0, w0, stack, r)
    return _equalities_from_stack(stack, r, x, tol)


@njit(cache=True)
def level_equalities_2(A, x, tol, stack, J0, w0, J1, w1):
    """:func:`level_equalities_1` for 2 tasks."""
    r = A.shape[0]
    stack[:r] = A
    r = _weighted_into(J0, w0, stack, r)
    r = _weighted_into(J1, w1, stack, r)
    return _equalities_from_stack(stack, r, x, tol)


@njit(cache=True)
def level_equalities_3(A, x, tol, stack, J0, w0, J1, w1, J2, w2):
    """:func:`level_equalities_1` for 3 tasks."""
    r = A.shape[0]
    stack[:r] = A
    r = _weighted_into(J0, w0, stack, r)
    r = _weighted_into(J1, w1, stack, r)
    r = _weighted_into(J2, w2, stack, r)
    return _equalities_from_stack(stack, r, x, tol)


# DAQP levels of the solver's cascade in two compiled calls each (see ``Solver._cascade``):
# before the solve, the level's H and f (``assemble_level_*``) and DAQP's fixed layout
# (``load_daqp_rows``); after it, the feasibility check, the clip to the box and, below a
# level with others after it, its equalities (``level_equalities_*``). The same operations
# in the same order as the separate calls.
@njit(cache=True)
def assemble_load_1(block, reg, J0, w0, v0, A_buf, upper, lower, sense, A, b, G, h, box_lower, box_upper,
                    n_eq_before, inf):
    """:func:`assemble_level_1` into ``block`` (rows: H, f, floor), then :func:`load_daqp_rows`; returns its count."""
    n = block.shape[1]
    assemble_level_1(block[:n], block[n], block[n + 1], reg, J0, w0, v0)
    return load_daqp_rows(A_buf, upper, lower, sense, A, b, G, h, box_lower, box_upper, n_eq_before, inf)


@njit(cache=True)
def assemble_load_2(block, reg, J0, w0, v0, J1, w1, v1, A_buf, upper, lower, sense, A, b, G, h, box_lower,
                    box_upper, n_eq_before, inf):
    """:func:`assemble_load_1` for 2 tasks."""
    n = block.shape[1]
    assemble_level_2(block[:n], block[n], block[n + 1], reg, J0, w0, v0, J1, w1, v1)
    return load_daqp_rows(A_buf, upper, lower, sense, A, b, G, h, box_lower, box_upper, n_eq_before, inf)


@njit(cache=True)
def assemble_load_3(block, reg, J0, w0, v0, J1, w1, v1, J2, w2, v2, A_buf, upper, lower, sense, A, b, G, h,
                    box_lower, box_upper, n_eq_before, inf):
    """:func:`assemble_load_1` for 3 tasks."""
    n = block.shape[1]
    assemble_level_3(block[:n], block[n], block[n + 1], reg, J0, w0, v0, J1, w1, v1, J2, w2, v2)
    return load_daqp_rows(A_buf, upper, lower, sense, A, b, G, h, box_lower, box_upper, n_eq_before, inf)


@njit(cache=True)
def assemble_load_4(block, reg, J0, w0, v0, J1, w1, v1, J2, w2, v2, J3, w3, v3, A_buf, upper, lower, sense, A, b,
                    G, h, box_lower, box_upper, n_eq_before, inf):
    """:func:`assemble_load_1` for 4 tasks."""
    n = block.shape[1]
    assemble_level_4(block[:n], block[n], block[n + 1], reg, J0, w0, v0, J1, w1, v1, J2, w2, v2, J3, w3, v3)
    return load_daqp_rows(A_buf, upper, lower, sense, A, b, G, h, box_lower, box_upper, n_eq_before, inf)


@njit(cache=True)
def check_clip(x, lower, upper, A, b, G, h, tol):
    """``max_scaled_violation(x, ...) <= tol``; only then ``x`` is clipped to ``[lower, upper]`` in place
    (a rejected ``x`` is left as the backend returned it)."""
    if max_scaled_violation(x, lower, upper, A, b, G, h) <= tol:
        clip_inplace(x, lower, upper)
        return True
    return False


@njit(cache=True)
def check_clip_equalities_1(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0):
    """:func:`check_clip`, then (if accepted) :func:`level_equalities_1` at the clipped ``x``:
    ``(accepted, rows, rhs)`` (empty rows when rejected)."""
    if not check_clip(x, lower, upper, A, b, G, h, tol):
        return False, np.empty((0, stack.shape[1])), np.empty(0)
    rows, rhs = level_equalities_1(A, x, eq_tol, stack, J0, w0)
    return True, rows, rhs


@njit(cache=True)
def check_clip_equalities_2(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, J1, w1):
    """:func:`check_clip_equalities_1` for 2 tasks."""
    if not check_clip(x, lower, upper, A, b, G, h, tol):
        return False, np.empty((0, stack.shape[1])), np.empty(0)
    rows, rhs = level_equalities_2(A, x, eq_tol, stack, J0, w0, J1, w1)
    return True, rows, rhs


@njit(cache=True)
def check_clip_equalities_3(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, J1, w1, J2, w2):
    """:func:`check_clip_equalities_1` for 3 tasks."""
    if not check_clip(x, lower, upper, A, b, G, h, tol):
        return False, np.empty((0, stack.shape[1])), np.empty(0)
    rows, rhs = level_equalities_3(A, x, eq_tol, stack, J0, w0, J1, w1, J2, w2)
    return True, rows, rhs


@njit(cache=True)
def scaled_difference(gain, target, q):
    """A new array ``gain * (target - q)`` (the posture task's velocity), the same products as numpy's."""
    out = np.empty(target.shape[0])
    for i in range(target.shape[0]):
        out[i] = gain * (target[i] - q[i])
    return out


@njit(cache=True, _nrt=False)
def episode_task_rows(R, J, v, J_local, v_local, roll_v, roll_local, gain, target, q, posture_v):
    """The paper episode's task rows in one call (``Solver._episode_rows``), the same operations
    as the tasks' own ``compute_rows``: the camera task's local-axes rows
    (:func:`rotate_twist_rows` of ``J``, ``v`` into ``J_local``, ``v_local``), the roll task's
    twist in the same axes (:func:`rotate_twist` of ``roll_v`` into ``roll_local``) and the
    posture task's velocity ``gain * (target - q)`` (:func:`scaled_difference`) into ``posture_v``.
    """
    rotate_twist_rows(R, J, v, J_local, v_local)
    rotate_twist(R, roll_v, roll_local)
    for i in range(target.shape[0]):
        posture_v[i] = gain * (target[i] - q[i])


# The cascade's step between two DAQP levels in one compiled call (``Solver._solve_step``): the
# upper level's ``check_clip_equalities_*`` and, only when its answer is accepted, the lower
# level's ``assemble_load_*`` on the equalities just computed; the same operations in the same
# order as the two separate calls. Returns ``(accepted, rows, rhs, n_eq)``; a rejected answer is
# left as the backend returned it and the lower level untouched (``n_eq`` -1).

@njit(cache=True)
def handover_1_1(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, block, reg, K0, u0, v0,
                A_buf, buf_upper, buf_lower, sense, n_eq_before, inf):
    """``check_clip_equalities_1`` of the upper level, then ``assemble_load_1`` of the lower one."""
    if not check_clip(x, lower, upper, A, b, G, h, tol):
        return False, np.empty((0, stack.shape[1])), np.empty(0), -1
    rows, rhs = level_equalities_1(A, x, eq_tol, stack, J0, w0)
    n_eq = assemble_load_1(block, reg, K0, u0, v0, A_buf, buf_upper, buf_lower, sense, rows, rhs, G, h, lower,
        upper, n_eq_before, inf)
    return True, rows, rhs, n_eq


@njit(cache=True)
def handover_1_2(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, block, reg, K0, u0, v0,
                K1, u1, v1, A_buf, buf_upper, buf_lower, sense, n_eq_before, inf):
    """``check_clip_equalities_1`` of the upper level, then ``assemble_load_2`` of the lower one."""
    if not check_clip(x, lower, upper, A, b, G, h, tol):
        return False, np.empty((0, stack.shape[1])), np.empty(0), -1
    rows, rhs = level_equalities_1(A, x, eq_tol, stack, J0, w0)
    n_eq = assemble_load_2(block, reg, K0, u0, v0, K1, u1, v1, A_buf, buf_upper, buf_lower, sense, rows, rhs, G,
        h, lower, upper, n_eq_before, inf)
    return True, rows, rhs, n_eq


@njit(cache=True)
def handover_1_3(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, block, reg, K0, u0, v0,
                K1, u1, v1, K2, u2, v2, A_buf, buf_upper, buf_lower, sense, n_eq_before, inf):
    """``check_clip_equalities_1`` of the upper level, then ``assemble_load_3`` of the lower one."""
    if not check_clip(x, lower, upper, A, b, G, h, tol):
        return False, np.empty((0, stack.shape[1])), np.empty(0), -1
    rows, rhs = level_equalities_1(A, x, eq_tol, stack, J0, w0)
    n_eq = assemble_load_3(block, reg, K0, u0, v0, K1, u1, v1, K2, u2, v2, A_buf, buf_upper, buf_lower, sense,
                           rows, rhs, G, h, lower, upper, n_eq_before, inf)
    return True, rows, rhs, n_eq


@njit(cache=True)
def handover_1_4(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, block, reg, K0, u0, v0,
                K1, u1, v1, K2, u2, v2, K3, u3, v3, A_buf, buf_upper, buf_lower, sense, n_eq_before, inf):
    """``check_clip_equalities_1`` of the upper level, then ``assemble_load_4`` of the lower one."""
    if not check_clip(x, lower, upper, A, b, G, h, tol):
        return False, np.empty((0, stack.shape[1])), np.empty(0), -1
    rows, rhs = level_equalities_1(A, x, eq_tol, stack, J0, w0)
    n_eq = assemble_load_4(block, reg, K0, u0, v0, K1, u1, v1, K2, u2, v2, K3, u3, v3, A_buf, buf_upper,
        buf_lower, sense, rows, rhs, G, h, lower, upper, n_eq_before, inf)
    return True, rows, rhs, n_eq


@njit(cache=True)
def handover_2_1(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, J1, w1, block, reg, K0,
                u0, v0, A_buf, buf_upper, buf_lower, sense, n_eq_before, inf):
    """``check_clip_equalities_2`` of the upper level, then ``assemble_load_1`` of the lower one."""
    if not check_clip(x, lower, upper, A, b, G, h, tol):
        return False, np.empty((0, stack.shape[1])), np.empty(0), -1
    rows, rhs = level_equalities_2(A, x, eq_tol, stack, J0, w0, J1, w1)
    n_eq = assemble_load_1(block, reg, K0, u0, v0, A_buf, buf_upper, buf_lower, sense, rows, rhs, G, h, lower,
        upper, n_eq_before, inf)
    return True, rows, rhs, n_eq


@njit(cache=True)
def handover_2_2(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, J1, w1, block, reg, K0,
                u0, v0, K1, u1, v1, A_buf, buf_upper, buf_lower, sense, n_eq_before, inf):
    """``check_clip_equalities_2`` of the upper level, then ``assemble_load_2`` of the lower one."""
    if not check_clip(x, lower, upper, A, b, G, h, tol):
        return False, np.empty((0, stack.shape[1])), np.empty(0), -1
    rows, rhs = level_equalities_2(A, x, eq_tol, stack, J0, w0, J1, w1)
    n_eq = assemble_load_2(block, reg, K0, u0, v0, K1, u1, v1, A_buf, buf_upper, buf_lower, sense, rows, rhs, G,
        h, lower, upper, n_eq_before, inf)
    return True, rows, rhs, n_eq


@njit(cache=True)
def handover_2_3(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, J1, w1, block, reg, K0,
                u0, v0, K1, u1, v1, K2, u2, v2, A_buf, buf_upper, buf_lower, sense, n_eq_before, inf):
    """``check_clip_equalities_2`` of the upper level, then ``assemble_load_3`` of the lower one."""
    if not check_clip(x, lower, upper, A, b, G, h, tol):
        return False, np.empty((0, stack.shape[1])), np.empty(0), -1
    rows, rhs = level_equalities_2(A, x, eq_tol, stack, J0, w0, J1, w1)
    n_eq = assemble_load_3(block, reg, K0, u0, v0, K1, u1, v1, K2, u2, v2, A_buf, buf_upper, buf_lower, sense,
                           rows, rhs, G, h, lower, upper, n_eq_before, inf)
    return True, rows, rhs, n_eq


@njit(cache=True)
def handover_2_4(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, J1, w1, block, reg, K0,
                u0, v0, K1, u1, v1, K2, u2, v2, K3, u3, v3, A_buf, buf_upper, buf_lower, sense, n_eq_before, inf):
    """``check_clip_equalities_2`` of the upper level, then ``assemble_load_4`` of the lower one."""
    if not check_clip(x, lower, upper, A, b, G, h, tol):
        return False, np.empty((0, stack.shape[1])), np.empty(0), -1
    rows, rhs = level_equalities_2(A, x, eq_tol, stack, J0, w0, J1, w1)
    n_eq = assemble_load_4(block, reg, K0, u0, v0, K1, u1, v1, K2, u2, v2, K3, u3, v3, A_buf, buf_upper,
        buf_lower, sense, rows, rhs, G, h, lower, upper, n_eq_before, inf)
    return True, rows, rhs, n_eq


@njit(cache=True)
def handover_3_1(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, J1, w1, J2, w2, block,
                reg, K0, u0, v0, A_buf, buf_upper, buf_lower, sense, n_eq_before, inf):
    """``check_clip_equalities_3`` of the upper level, then ``assemble_load_1`` of the lower one."""
    if not check_clip(x, lower, upper, A, b, G, h, tol):
        return False, np.empty((0, stack.shape[1])), np.empty(0), -1
    rows, rhs = level_equalities_3(A, x, eq_tol, stack, J0, w0, J1, w1, J2, w2)
    n_eq = assemble_load_1(block, reg, K0, u0, v0, A_buf, buf_upper, buf_lower, sense, rows, rhs, G, h, lower,
        upper, n_eq_before, inf)
    return True, rows, rhs, n_eq


@njit(cache=True)
def handover_3_2(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, J1, w1, J2, w2, block,
                reg, K0, u0, v0, K1, u1, v1, A_buf, buf_upper, buf_lower, sense, n_eq_before, inf):
    """``check_clip_equalities_3`` of the upper level, then ``assemble_load_2`` of the lower one."""
    if not check_clip(x, lower, upper, A, b, G, h, tol):
        return False, np.empty((0, stack.shape[1])), np.empty(0), -1
    rows, rhs = level_equalities_3(A, x, eq_tol, stack, J0, w0, J1, w1, J2, w2)
    n_eq = assemble_load_2(block, reg, K0, u0, v0, K1, u1, v1, A_buf, buf_upper, buf_lower, sense, rows, rhs, G,
        h, lower, upper, n_eq_before, inf)
    return True, rows, rhs, n_eq


@njit(cache=True)
def handover_3_3(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, J1, w1, J2, w2, block,
                reg, K0, u0, v0, K1, u1, v1, K2, u2, v2, A_buf, buf_upper, buf_lower, sense, n_eq_before, inf):
    """``check_clip_equalities_3`` of the upper level, then ``assemble_load_3`` of the lower one."""
    if not check_clip(x, lower, upper, A, b, G, h, tol):
        return False, np.empty((0, stack.shape[1])), np.empty(0), -1
    rows, rhs = level_equalities_3(A, x, eq_tol, stack, J0, w0, J1, w1, J2, w2)
    n_eq = assemble_load_3(block, reg, K0, u0, v0, K1, u1, v1, K2, u2, v2, A_buf, buf_upper, buf_lower, sense,
                           rows, rhs, G, h, lower, upper, n_eq_before, inf)
    return True, rows, rhs, n_eq


@njit(cache=True)
def handover_3_4(x, lower, upper, A, b, G, h, tol, eq_tol, stack, J0, w0, J1, w1, J2, w2, block,
                reg, K0, u0, v0, K1, u1, v1, K2, u2, v2, K3, u3, v3, A_buf, buf_upper, buf_lower, sense,
                n_eq_before, inf):
    """``check_clip_equalities_3`` of the upper level, then ``assemble_load_4`` of the lower one."""
    if not check_clip(x, lower, upper, A, b, G, h, tol):
        return False, np.empty((0, stack.shape[1])), np.empty(0), -1
    rows, rhs = level_equalities_3(A, x, eq_tol, stack, J0, w0, J1, w1, J2, w2)
    n_eq = assemble_load_4(block, reg, K0, u0, v0, K1, u1, v1, K2, u2, v2, K3, u3, v3, A_buf, buf_upper,
        buf_lower, sense, rows, rhs, G, h, lower, upper, n_eq_before, inf)
    return True, rows, rhs, n_eq


@njit(cache=True)
def check_clip_rate(x, lower, upper, A, b, G, h, tol, previous, dt):
    """:func:`check_clip`, then (if accepted) a new array ``(x - previous) / dt`` (the controller's
    acceleration [rad/s^2], the same operations as numpy's); an empty array when rejected."""
    if not check_clip(x, lower, upper, A, b, G, h, tol):
        return np.empty(0)
    rate = np.empty(x.shape[0])
    for i in range(x.shape[0]):
        rate[i] = (x[i] - previous[i]) / dt
    return rate
